"""The INT8 copies of our FCN-8s (monostixels.inputs.quantize, semantic=fcn8s_int8, preset=fast)."""
from __future__ import annotations

import functools
import logging
from pathlib import Path

import cv2
import onnx
import pytest
import torch
from onnx import numpy_helper

from monostixels import _cpu
from monostixels._checks import InputError
from monostixels.inputs import semantic
from monostixels.inputs.quantize import SAFE_WEIGHT_MAX, can_saturate, int8_weight_max
from monostixels.inputs.semantic import OnnxSegmenter, _fcn8s_segmenter, quantize_fcn8s_onnx
from monostixels.pipeline import load_config

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
FLOAT = REPO / "models" / "fcn8s_real.onnx"
INT8 = REPO / "models" / "fcn8s_real_int8.onnx"
KITTI2015 = SHARED / "kitti2015" / "training" / "image_2" / "000000_10.png"
CAMVID_TRAIN = SHARED / "camvid" / "train"
needs_frames = pytest.mark.skipif(not (KITTI2015.is_file() and CAMVID_TRAIN.is_dir()),
                                  reason="shared KITTI 2015 and CamVid samples (../shared/data) not present")


def _rgb(path: Path) -> torch.Tensor:
    return torch.from_numpy(cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)).permute(2, 0, 1).float() / 255.0


def _agreement(a: Path, b: Path, image: torch.Tensor, scale: float) -> float:
    pa = OnnxSegmenter(a, scale=scale, pad_to=32)(image)
    pb = OnnxSegmenter(b, scale=scale, pad_to=32)(image)
    return float((pa.argmax(0) == pb.argmax(0)).float().mean())


@needs_frames
def test_quantized_copy_has_int8_convolutions_and_labels_an_unseen_frame_as_the_float_net(tmp_path: Path) -> None:
    calib = [_rgb(p) for p in sorted(CAMVID_TRAIN.glob("*.jpg"))[:3]]
    out = quantize_fcn8s_onnx(FLOAT, tmp_path / "q.onnx", calib, scale=0.5)
    proto = onnx.load(str(out))
    inits = {i.name: i for i in proto.graph.initializer}
    producers = {o: n for n in proto.graph.node for o in n.output}
    convs = [n for n in proto.graph.node if n.op_type == "Conv"]
    assert len(convs) == 18  # every convolution of the FCN-8s
    quantized = [c for c in convs if c.input[1] in producers and producers[c.input[1]].op_type == "DequantizeLinear"]
    # All but the first (the image's 3 channels), which stays float.
    assert len(quantized) == 17
    first = numpy_helper.to_array(inits[convs[0].input[1]])
    assert convs[0] not in quantized and first.dtype.name == "float32" and first.shape[1] == 3
    for conv in quantized:
        # Its input and its weights each come through a DequantizeLinear; the weights are int8 per channel.
        x, w = (producers[name] for name in conv.input[:2])
        assert x.op_type == "DequantizeLinear" and w.op_type == "DequantizeLinear"
        assert numpy_helper.to_array(inits[w.input[0]]).dtype.name == "int8"
        assert numpy_helper.to_array(inits[w.input[1]]).size == numpy_helper.to_array(inits[w.input[0]]).shape[0]
    meta = {p.key: p.value for p in proto.metadata_props}
    assert meta["quantized"] == "int8" and meta["int8_from"] == "fcn8s_real.onnx" and "classes" in meta
    assert out.stat().st_size < 0.7 * FLOAT.stat().st_size
    # A frame of another camera, never calibrated on: the most likely class of nearly every pixel is kept.
    assert _agreement(FLOAT, out, _rgb(KITTI2015), 480 / 721.5377) >= 0.97


def test_quantize_refuses_what_it_cannot_calibrate(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no calibration input"):
        quantize_fcn8s_onnx(FLOAT, tmp_path / "q.onnx", [])
    with pytest.raises(InputError, match="no ONNX file"):
        quantize_fcn8s_onnx(tmp_path / "absent.onnx", tmp_path / "q.onnx", [torch.rand(3, 64, 64)])
    raft = REPO / "models" / "raft_small.onnx"
    with pytest.raises(InputError, match="not an FCN-8s export"):
        quantize_fcn8s_onnx(raft, tmp_path / "q.onnx", [torch.rand(3, 64, 64)])


@needs_frames
def test_fast_preset_runs_the_shipped_int8_copy_of_the_shipped_net() -> None:
    cfg = load_config(["preset=fast"]).semantic
    assert cfg.name == "fcn8s" and cfg.model == "models/fcn8s_real_int8.onnx"
    assert _fcn8s_segmenter(cfg).path.resolve() == INT8.resolve()
    meta = {p.key: p.value for p in onnx.load(str(INT8)).metadata_props}
    assert meta["quantized"] == "int8" and meta["int8_from"] == FLOAT.name
    # The float net's own metadata came along: the copy is of the shipped weights, not of older ones.
    float_meta = {p.key: p.value for p in onnx.load(str(FLOAT)).metadata_props}
    assert all(meta[k] == v for k, v in float_meta.items())
    assert _agreement(FLOAT, INT8, _rgb(KITTI2015), 480 / 721.5377) >= 0.98


def test_the_shipped_int8_file_cannot_saturate_on_any_cpu() -> None:
    # On an x86 CPU without VNNI, ONNX Runtime adds pairs of u8 x s8 products into saturating 16-bit sums
    # (VPMADDUBSW). Weights within [-64, 64] keep every pair within 2 x 255 x 64 = 32640 <= 32767, so the
    # integer sums, and the labels, are the VNNI path's on every CPU. The copy before (8-bit weights up to
    # 127) agreed with the float net on 0.971 of KITTI 000000_10 without VNNI, 0.992 with it.
    assert SAFE_WEIGHT_MAX == 64 and 2 * 255 * SAFE_WEIGHT_MAX <= 2**15 - 1
    assert int8_weight_max(INT8) == SAFE_WEIGHT_MAX and not can_saturate(INT8)
    assert int8_weight_max(FLOAT) == 0 and not can_saturate(FLOAT)  # no int8 weights at all


@needs_frames
def test_8_bit_weights_can_saturate_and_fast_falls_back_to_the_float_net_without_vnni(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    calib = [_rgb(p) for p in sorted(CAMVID_TRAIN.glob("*.jpg"))[:2]]
    wide = quantize_fcn8s_onnx(FLOAT, tmp_path / "wide_int8.onnx", calib, scale=0.5, reduce_range=False)
    assert int8_weight_max(wide) == 127 and can_saturate(wide)
    (tmp_path / FLOAT.name).write_bytes(FLOAT.read_bytes())
    cfg = load_config(["preset=fast", f"semantic.model={wide}"]).semantic
    monkeypatch.setattr(_cpu, "int8_path", lambda: "vnni")
    monkeypatch.setattr(semantic, "_int8_checked", functools.lru_cache(semantic._int8_checked.__wrapped__))
    assert _fcn8s_segmenter(cfg).path == wide  # a CPU with VNNI runs it
    monkeypatch.setattr(_cpu, "int8_path", lambda: "no_vnni")
    monkeypatch.setattr(semantic, "_int8_checked", functools.lru_cache(semantic._int8_checked.__wrapped__))
    with caplog.at_level(logging.WARNING, logger="monostixels.inputs.semantic"):
        assert _fcn8s_segmenter(cfg).path == tmp_path / FLOAT.name
    assert [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING] == [
        f"semantic: {wide} has 8-bit weights, which can saturate on this CPU (no VNNI): running the float net "
        f"{tmp_path / FLOAT.name} instead"]
    # The shipped 7-bit copy runs as it is there.
    assert _fcn8s_segmenter(load_config(["preset=fast"]).semantic).path.resolve() == INT8.resolve()


@needs_frames
def test_the_shipped_int8_file_is_what_its_command_makes_from_the_shipped_float_file(tmp_path: Path) -> None:
    # `python -m train.quantize_semantic` (conf/quantize_semantic.yaml) is deterministic: remade after the
    # float net changes, the copy cannot drift from it unnoticed.
    from hydra import compose, initialize_config_dir

    from train.quantize_semantic import run

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base=None):
        cfg = compose("quantize_semantic", overrides=[f"src={FLOAT}", f"dst={tmp_path / 'q.onnx'}",
                                                      f"calibration.root={SHARED / 'camvid'}"])
    out = run(cfg)
    assert out["calibration_images"] == 31
    assert (tmp_path / "q.onnx").read_bytes() == INT8.read_bytes()
