"""Unreadable frames of a folder or a video are skipped, warned about and reported (issue 41).

A pair whose previous frame is unreadable takes the readable frame before it (at most
``MAX_SKIPPED_FRAMES`` back); a pair whose current frame is unreadable is skipped; a longer gap starts
the sequence again. ``monostixels run`` lists the skipped frames in its summary line and in
``<outputs>/run/summary.json`` and writes every other frame's outputs.
"""
from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from monostixels._checks import InputError
from monostixels.data._lazy_source import MAX_SKIPPED_FRAMES, PairSkipped
from monostixels.data.frames import FramesSource
from monostixels.data.video import VideoSource


def _texture(H: int, W: int) -> np.ndarray:
    """A smooth random BGR texture (H, W, 3) uint8 that DIS can follow."""
    rng = np.random.default_rng(0)
    return cv2.resize((rng.random((H // 4, W // 4, 3)) * 255).astype(np.uint8), (W, H), interpolation=cv2.INTER_CUBIC)


def _folder(root: Path, n: int, bad: list[int], H: int = 48, W: int = 64) -> Path:
    """``n`` images 0000.png... (the texture shifted 1 px per frame), ``bad`` ones overwritten with random bytes."""
    root.mkdir()
    base = _texture(H, W)
    rng = np.random.default_rng(1)
    for k in range(n):
        path = root / f"{k:04d}.png"
        cv2.imwrite(str(path), np.roll(base, k, 1))
        if k in bad:
            path.write_bytes(rng.integers(0, 256, 400, dtype=np.uint8).tobytes())
    (root / "intrinsics.yaml").write_text(f"fx: {W}\nfy: {W}\ncx: {W / 2}\ncy: {H / 2}\n")
    return root


def _corrupt_mjpg(path: Path, n: int, bad: list[int], H: int = 48, W: int = 64) -> Path:
    """An MJPG .avi of ``n`` frames whose ``bad`` frames have their JPEG data overwritten with zeros (the
    AVI chunk headers kept, so the frames after them still decode)."""
    base = _texture(H, W)
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (W, H))
    if not vw.isOpened():
        pytest.skip("OpenCV cannot write MJPG .avi here")
    for k in range(n):
        vw.write(np.roll(base, k, 1))
    vw.release()
    data = bytearray(path.read_bytes())
    soi = [i for i in range(len(data) - 1) if data[i] == 0xFF and data[i + 1] == 0xD8]  # JPEG start markers
    assert len(soi) == n
    for k in bad:
        end = soi[k + 1] - 8 if k + 1 < n else soi[k] + 100  # up to the next chunk's 8-byte header
        data[soi[k]:end] = bytes(end - soi[k])
    path.write_bytes(bytes(data))
    # The stretch is really undecodable for OpenCV, and only it.
    cap = cv2.VideoCapture(str(path))
    decoded = [cap.read()[0] for _ in range(n)]
    cap.release()
    assert [k for k, ok in enumerate(decoded) if not ok] == sorted(bad)
    return path


def _pairs(src) -> list[tuple[str, str]]:
    return [(p.name, p.meta["name_prev"]) for p in src]


def test_frames_pair_across_a_corrupt_image(tmp_path, caplog):
    src = FramesSource(_folder(tmp_path / "f", 6, bad=[2, 3]))
    with caplog.at_level(logging.WARNING):
        pairs = list(src)
    assert [(p.name, p.meta["name_prev"], p.meta["back"]) for p in pairs] == [
        ("0001", "0000", 1), ("0004", "0001", 3), ("0005", "0004", 1)]
    assert pairs[1].meta["skipped_before"] == ["0002.png", "0003.png"]
    assert src.skipped_frames == ["0002.png", "0003.png"] and src.restarts == []
    assert "skipping 0002.png" in caplog.text and "skipping 0003.png" in caplog.text
    assert len({src.sequence_key(i) for i in range(len(src))}) == 1


def test_frames_gap_too_long_starts_the_sequence_again(tmp_path, caplog):
    bad = list(range(2, 3 + MAX_SKIPPED_FRAMES))  # one more than a pair may reach across
    n = len(bad) + 5
    src = FramesSource(_folder(tmp_path / "f", n, bad=bad))
    with caplog.at_level(logging.WARNING):
        pairs = _pairs(src)
    first_after = f"{bad[-1] + 1:04d}"
    # The frame after the gap has no pair of its own: it is the previous frame of the next one.
    assert pairs == [("0001", "0000")] + [(f"{k:04d}", f"{k - 1:04d}") for k in range(bad[-1] + 2, n)]
    assert src.restarts == [first_after] and "the sequence starts again" in caplog.text
    assert src.skipped_frames == [f"{k:04d}.png" for k in bad]
    # A new stretch: the sequence layer forgets its tracks and stream there.
    assert src.sequence_key(0) != src.sequence_key(len(src) - 1)
    # Keyframe candidates never reach across the gap.
    assert [c.name for c in src.previous_frames(len(src) - 1, 10)][-1] == first_after


def test_frames_corrupt_first_image(tmp_path):
    src = FramesSource(_folder(tmp_path / "f", 4, bad=[0]))
    assert _pairs(src) == [("0002", "0001"), ("0003", "0002")]
    assert src.skipped_frames == ["0000.png"] and src.restarts == ["0001"]
    with pytest.raises(PairSkipped):
        src[0]


def test_video_pairs_across_a_corrupt_stretch(tmp_path, caplog):
    src = VideoSource(_corrupt_mjpg(tmp_path / "c.avi", 7, bad=[3, 4]), hfov_deg=90.0)
    with caplog.at_level(logging.WARNING):
        pairs = list(src)
    assert [(p.meta["frame"], p.meta["frame_prev"]) for p in pairs] == [(1, 0), (2, 1), (5, 2), (6, 5)]
    assert pairs[2].meta["dt"] == pytest.approx(0.3)
    assert src.skipped_frames == ["video frame 3", "video frame 4"]
    assert "skipping video frame 3" in caplog.text
    # The frames after the stretch are the file's own (decoding went on past it).
    cap = cv2.VideoCapture(str(tmp_path / "c.avi"))
    for _ in range(7):  # frame 6 (the reads of frames 3 and 4 fail)
        ok, want = cap.read()
    got = (pairs[3].image.permute(1, 2, 0).numpy()[..., ::-1] * 255).round().astype(np.uint8)
    assert np.array_equal(got, want)


REPO = Path(__file__).resolve().parents[1]


def _cli(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "2")}
    return subprocess.run([sys.executable, "-m", "monostixels.cli", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=900)


def _check_run(p: subprocess.CompletedProcess, out: Path, outputs: list[str], skipped: list[str]) -> None:
    assert p.returncode == 0, p.stderr
    assert sorted(d.name for d in out.iterdir() if d.is_dir()) == outputs
    for d in outputs:
        assert (out / d / "stixels.json").is_file() and (out / d / "overlay.png").is_file()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["skipped_frames"] == skipped and summary["frame_pairs"] == len(outputs)
    line = [ln for ln in p.stdout.splitlines() if ln.startswith("run: ")][-1]
    assert f"{len(skipped)} unreadable frame(s) skipped: {', '.join(skipped)}" in line


def test_run_on_a_folder_with_a_corrupt_image(tmp_path):
    frames = _folder(tmp_path / "f", 4, bad=[2])
    # The nearest readable frame, not a keyframe further back (the folder's frame rate lets a standing
    # camera reach back for a longer interval).
    p = _cli(["run", "data=frames", f"data.root={frames}", "flow=dis", "semantic=none", "keyframes.min_distance_m=0"],
             tmp_path)
    _check_run(p, tmp_path / "outputs" / "run", ["0001", "0003"], ["0002.png"])
    st = json.loads((tmp_path / "outputs" / "run" / "0003" / "stixels.json").read_text())
    assert st["pair"]["previous"] == "0001" and st["pair"]["frames_back"] == 2


def test_run_on_a_video_with_a_corrupt_stretch(tmp_path):
    clip = _corrupt_mjpg(tmp_path / "c.avi", 5, bad=[2])
    p = _cli(["run", "data=video", f"data.path={clip}", "data.hfov_deg=90", "flow=dis", "semantic=none"], tmp_path)
    _check_run(p, tmp_path / "outputs" / "run", ["c_000001", "c_000003", "c_000004"], ["video frame 2"])


def test_run_fails_where_fewer_than_two_frames_can_be_read(tmp_path):
    frames = _folder(tmp_path / "f", 3, bad=[0, 2])
    p = _cli(["run", "data=frames", f"data.root={frames}", "flow=dis", "semantic=none"], tmp_path)
    lines = [ln for ln in p.stderr.splitlines() if "error:" in ln]
    assert p.returncode == 1 and len(lines) == 1 and "Traceback" not in p.stderr
    assert "0000.png, 0002.png" in lines[0] and "no frame pair could be made" in lines[0]


def test_eval_counts_skipped_frames(tmp_path):
    """`eval`'s report keeps its keys and adds the optional count of unreadable frames."""
    from monostixels.eval.evaluate import evaluate
    from monostixels.pipeline import load_config

    cfg = load_config(["data=frames", f"data.root={_folder(tmp_path / 'f', 4, bad=[1])}", "flow=dis",
                       "semantic=none", "motion=mono"])
    report = evaluate(cfg, FramesSource(cfg.data.root), dataset="frames", progress=False)
    assert report["skipped_frames"] == 1
    assert {"dataset", "frames", "methods"} <= set(report) and "monostixels" in report["methods"]
