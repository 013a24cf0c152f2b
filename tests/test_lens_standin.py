"""benchmarks.lens_standin: a distorted stand-in that the pipeline's undistortion turns back into the pinhole view."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from benchmarks.lens_standin import bonnet_mask, standin_maps, write_standin
from monostixels._checks import InputError
from monostixels.data._lens import FrameWarp

# The calibrated dashcam lens of docs/usage.md at half its 1280x720 size (barrel, k1 < 0).
_K = np.array([[579.4, 0.0, 334.8], [0.0, 577.0, 194.1], [0.0, 0.0, 1.0]])
_D = np.array([-0.256, 0.038, -0.0007, 0.0001, -0.103])
_SIZE = (360, 640)
_CLIP = (270, 480)
_HFOV = 58.0


def _texture(H: int, W: int) -> np.ndarray:
    """(H, W, 3) uint8: smooth random texture (bilinear sampling of it is accurate to a grey level or two)."""
    g = np.random.default_rng(1)
    small = g.random((H // 8, W // 8, 3)).astype(np.float32)
    return (255 * cv2.resize(small, (W, H), interpolation=cv2.INTER_CUBIC).clip(0, 1)).astype(np.uint8)


def _pinhole_view(clip: np.ndarray) -> np.ndarray:
    """The clip as the calibrated camera's pinhole (undistorted) image: the reference."""
    H, W = _SIZE
    Hc, Wc = clip.shape[:2]
    f = (Wc / 2) / math.tan(math.radians(_HFOV) / 2)  # written out: the reference does not share the code under test
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    x = (u - _K[0, 2]) / _K[0, 0]
    y = (v - _K[1, 2]) / _K[1, 1]
    mx = (f * x + (Wc - 1) / 2).astype(np.float32)
    my = (f * y + (Hc - 1) / 2).astype(np.float32)
    return cv2.remap(clip, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def test_the_pipelines_undistortion_of_the_standin_is_the_pinhole_view():
    clip = _texture(*_CLIP)
    mx, my = standin_maps(_K, _D, _SIZE, _CLIP, _HFOV)
    distorted = cv2.remap(clip, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    warp = FrameWarp((_K[0, 0], _K[1, 1], _K[0, 2], _K[1, 2]), _D, _SIZE, _SIZE)
    back = warp.image(distorted).astype(np.float32)
    ref = _pinhole_view(clip).astype(np.float32)
    # Where the clip covers the ray (a margin for the black border's interpolation).
    inner = cv2.erode((ref.min(-1) > 0).astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    assert inner.mean() > 0.75
    err = np.abs(back - ref)[inner].mean()
    assert err < 1.5, err  # a distortion 10 % off gives 7
    # Not trivially so: the distorted frame itself is far from the pinhole view.
    assert np.abs(distorted.astype(np.float32) - ref)[inner].mean() > 5 * err


def test_the_bonnet_rises_towards_the_middle():
    m = bonnet_mask(720, 1280, 70, 115)
    rows = m.sum(0)
    assert rows[0] == pytest.approx(70, abs=1) and rows[640] == pytest.approx(115, abs=1)
    assert m[-1].all() and not m[:600].any()


def test_an_intrinsics_file_without_distortion_or_size_is_refused(tmp_path):
    f = tmp_path / "intrinsics.yaml"
    f.write_text("fx: 500\nfy: 500\ncx: 320\ncy: 180\nwidth: 640\nheight: 360\n")
    with pytest.raises(InputError, match="intrinsics.yaml: no 'distortion'"):
        write_standin(tmp_path / "clip.mp4", f, tmp_path / "out.mp4")
    f.write_text("fx: 500\nfy: 500\ncx: 320\ncy: 180\ndistortion: [-0.2, 0.03, 0, 0, 0]\n")
    with pytest.raises(InputError, match="intrinsics.yaml: no 'width' and 'height'"):
        write_standin(tmp_path / "clip.mp4", f, tmp_path / "out.mp4")
