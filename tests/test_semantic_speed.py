"""benchmarks/semantic_speed.py: every file timed as often as asked, the first the reference, bad input named."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from benchmarks.semantic_speed import measure
from monostixels._cpu import FLAGS, int8_path


def _tiny_onnx(path: Path, channels: int) -> Path:
    net = torch.nn.Sequential(torch.nn.Conv2d(3, channels, 3, padding=1), torch.nn.ReLU(),
                              torch.nn.Conv2d(channels, 10, 1)).eval()
    torch.onnx.export(net, torch.zeros(1, 3, 32, 64), str(path), input_names=["image"], output_names=["scores"],
                      dynamic_axes={"image": {2: "h", 3: "w"}}, dynamo=False)
    return path


def test_each_file_is_timed_runs_times_and_compared_with_the_first(tmp_path: Path) -> None:
    a, b = _tiny_onnx(tmp_path / "a.onnx", 4), _tiny_onnx(tmp_path / "b.onnx", 8)
    rep = measure([a, b], size=(32, 64), runs=3)
    assert rep["size"] == [32, 64] and rep["threads"] == 1
    assert [len(f["times_ms"]) for f in rep["files"]] == [3, 3]
    assert rep["files"][0]["ratio"] == 1.0
    # Where they ran: the CPU's flags and ONNX Runtime's INT8 path on it (VNNI or not).
    assert set(rep["cpu"]["flags"]) == set(FLAGS) and rep["int8_path"] == int8_path() and rep["onnxruntime"]
    for f in rep["files"]:
        assert 0 < f["min_ms"] <= f["median_ms"]
        assert f["ratio"] == pytest.approx(f["median_ms"] / rep["files"][0]["median_ms"])


def test_a_size_off_the_32_grid_and_a_missing_file_are_named(tmp_path: Path) -> None:
    a = _tiny_onnx(tmp_path / "a.onnx", 4)
    with pytest.raises(ValueError, match=r"--size \[30, 64\]"):
        measure([a], size=(30, 64))
    with pytest.raises(FileNotFoundError, match="nowhere.onnx"):
        measure([a, tmp_path / "nowhere.onnx"], size=(32, 64))
