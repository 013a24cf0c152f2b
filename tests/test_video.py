"""The `video` data source: frame selection, intrinsics from a file or a field of view, resize, bad input."""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from monostixels._checks import InputError
from monostixels.data.sources import make_source
from monostixels.data.video import VideoSource, intrinsics_from_hfov

H, W = 48, 80


def write_video(path: Path, n: int, size: tuple[int, int] = (H, W), fps: float = 10.0) -> Path:
    """An mp4 of ``n`` frames; frame ``k`` is uniformly grey at ``20 + 20 k`` (readable back despite the codec)."""
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (size[1], size[0]))
    assert vw.isOpened(), "OpenCV has no mp4v encoder"
    for k in range(n):
        vw.write(np.full((size[0], size[1], 3), 20 + 20 * k, np.uint8))
    vw.release()
    return path


def _grey(img) -> float:
    return float(img.mean()) * 255


def test_frame_selection_order_and_interval(tmp_path):
    v = write_video(tmp_path / "c.mp4", 9)
    src = VideoSource(v, hfov_deg=90.0, step=2, start=1, end=8)
    # Used frames 1, 3, 5, 7 -> pairs (3 <- 1), (5 <- 3), (7 <- 5).
    assert len(src) == 3
    for k, p in enumerate(src):
        cur, prev = 3 + 2 * k, 1 + 2 * k
        assert (p.meta["frame"], p.meta["frame_prev"]) == (cur, prev)
        assert _grey(p.image) == pytest.approx(20 + 20 * cur, abs=3)
        assert _grey(p.image_prev) == pytest.approx(20 + 20 * prev, abs=3)
        assert p.meta["dt"] == pytest.approx(0.2)  # step 2 at 10 fps
    # Random access (a backwards seek) gives the same frames.
    assert _grey(src[0].image) == pytest.approx(80, abs=3)
    assert len(VideoSource(v, hfov_deg=90.0, frames=2)) == 2


def test_intrinsics_from_hfov_file_and_resize(tmp_path):
    fx, fy, cx, cy = intrinsics_from_hfov(80, 48, 90.0)
    assert fx == pytest.approx(40.0) and fy == fx and (cx, cy) == (39.5, 23.5)
    v = write_video(tmp_path / "c.mp4", 3)
    K = VideoSource(v, hfov_deg=60.0).camera.K
    assert float(K[0, 0]) == pytest.approx(40.0 / math.tan(math.radians(30.0)))
    (tmp_path / "k.yaml").write_text("fx: 70\nfy: 66\ncx: 41\ncy: 22\n")
    src = VideoSource(v, intrinsics=tmp_path / "k.yaml", resize=0.5, hfov_deg=60.0)  # the file wins
    p = src[0]
    assert p.size == (24, 40)
    K = p.camera.K
    # Half size: focal lengths halve, pixel centres map as u' + 0.5 = (u + 0.5) / 2.
    assert [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])] == pytest.approx([35, 33, 20.25, 10.75])
    assert VideoSource(v, hfov_deg=60.0, resize=[40, 30])[0].size == (30, 40)


@pytest.mark.parametrize("case", ["missing", "unreadable", "one_frame", "no_intrinsics", "range", "bad_hfov"])
def test_bad_input_fails_clearly(tmp_path, case):
    v = write_video(tmp_path / "c.mp4", 1 if case == "one_frame" else 3)
    kw: dict = {"hfov_deg": 90.0}
    if case == "missing":
        v = tmp_path / "nope.mp4"
    if case == "unreadable":
        v = tmp_path / "junk.mp4"
        v.write_bytes(b"this is not a video" * 100)
    if case == "no_intrinsics":
        kw = {}
    if case == "range":
        kw["start"] = 2
    if case == "bad_hfov":
        kw["hfov_deg"] = 180.0
    want = {"missing": "nope.mp4 does not exist", "unreadable": "cannot decode", "one_frame": "at least two",
            "no_intrinsics": "data.hfov_deg", "range": "at least two", "bad_hfov": "field of view"}[case]
    with pytest.raises(InputError, match=want):
        VideoSource(v, **kw)


def test_make_source_video(tmp_path):
    v = write_video(tmp_path / "c.mp4", 4)
    src = make_source({"name": "video", "path": str(v), "hfov_deg": 90, "step": 1, "resize": [40, 24]})
    assert len(src) == 3 and src[0].size == (24, 40)
    with pytest.raises(InputError, match="no video file given"):
        make_source({"name": "video", "hfov_deg": 90})
