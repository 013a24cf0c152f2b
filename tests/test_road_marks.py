"""The road-marks alignment (monostixels.inputs.road_marks) on a rendered highway: flat asphalt, a solid
line and dashes, 2 m of travel per pair (the near road moves ~60 px), a travel direction given 2 deg off."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from monostixels.inputs.road_marks import _turn, road_marks_scale

H, W, F, HEIGHT = 270, 480, 433.0, 1.4
K = np.array([[F, 0.0, W / 2 - 0.5], [0.0, F, H / 2 - 0.5], [0.0, 0.0, 1.0]])
N_G = np.array([0.0, 1.0, 0.0])


def _road(x: np.ndarray, z: np.ndarray, dashes: bool) -> np.ndarray:
    """Grey value of the road at lateral x, ahead z (metres): a solid line at x = 2 m and, with ``dashes``,
    3 m dashes every 12 m at x = -1.8 m on asphalt with a faint fine texture; without, flat asphalt."""
    # Asphalt: faint value noise on a 5 cm grid (not periodic: a periodic texture aligns at its period).
    i, j = np.floor(x / 0.05).astype(np.int64), np.floor(z / 0.05).astype(np.int64)
    g = 0.35 + (0.02 if dashes else 0.0) * (((i * 73856093) ^ (j * 19349663)) % 1000 / 1000.0 - 0.5)
    g = np.where(np.abs(x - 2.0) < 0.08, 0.9, g)
    if dashes:
        g = np.where((np.abs(x + 1.8) < 0.08) & (np.mod(z, 12.0) < 3.0), 0.9, g)
    return g


def _render(position: float, dashes: bool) -> np.ndarray:
    """(H, W) float32 grey view of the road from a camera at ``position`` metres along the road (2x supersampled)."""
    s = 2
    vv, uu = np.mgrid[0:H * s, 0:W * s].astype(np.float64) / s - (0.5 - 0.5 / s)
    y = np.stack([(uu - K[0, 2]) / F, (vv - K[1, 2]) / F, np.ones_like(uu)])
    below = y[1] > 1e-3
    lam = np.where(below, HEIGHT / np.where(below, y[1], 1.0), 0.0)
    img = np.where(below, _road(lam * y[0], lam * y[2] + position, dashes), 0.7)  # sky above the horizon
    return cv2.resize(img.astype(np.float32), (W, H), interpolation=cv2.INTER_AREA)


def _ground_pixels() -> np.ndarray:
    """Every second pixel on the road 4-25 m ahead, within 6 m sideways (u, v)."""
    vv, uu = np.mgrid[0:H:2, 0:W:2]
    pts = np.c_[uu.ravel(), vv.ravel()].astype(np.float64)
    y = (pts - K[:2, 2]) / F
    with np.errstate(divide="ignore"):
        z = np.where(y[:, 1] > 0, HEIGHT / y[:, 1], np.inf)
    keep = (z > 4.0) & (z < 25.0) & (np.abs(z * y[:, 0]) < 6.0)
    return pts[keep]


def _blur(img: np.ndarray) -> np.ndarray:
    return cv2.GaussianBlur(img, (0, 0), 1.0)  # as motion._grey smooths before its searches


@pytest.mark.parametrize("yaw_deg,pitch_deg", [(2.0, 0.0), (-1.0, 1.5)])
def test_road_marks_find_the_travel_length_and_direction_where_the_essential_matrix_is_off(yaw_deg, pitch_deg):
    cur, prev = _blur(_render(0.0, True)), _blur(_render(-2.0, True))  # the previous camera 2 m behind
    t_true = np.array([0.0, 0.0, 1.0])  # X_prev = X_cur + 2 t: the point is 2 m farther in the previous view
    t_off = _turn(t_true, math.radians(yaw_deg), math.radians(pitch_deg))
    fit = road_marks_scale(cur, prev, K, np.eye(3), t_off, N_G, HEIGHT, _ground_pixels(), np.random.default_rng(0))
    assert fit is not None
    assert fit.scale == pytest.approx(2.0, rel=0.03)
    assert math.degrees(math.acos(min(1.0, float(fit.t @ t_true)))) < 0.4
    assert abs(float(fit.normal @ fit.t)) < 1e-9  # the road normal at right angles to the travel
    assert fit.ratio < 0.85


def test_a_road_with_nothing_across_the_travel_gives_no_scale():
    # Flat asphalt and a solid line look the same at every length of travel: no clear minimum, no guess.
    cur, prev = _blur(_render(0.0, False)), _blur(_render(-2.0, False))
    fit = road_marks_scale(cur, prev, K, np.eye(3), np.array([0.0, 0.0, 1.0]), N_G, HEIGHT, _ground_pixels(),
                           np.random.default_rng(0))
    assert fit is None


@pytest.mark.parametrize("start,window", [(1.8, True), (2.3, True), (8.0, False), (0.4, False)])
def test_a_predicted_length_near_or_far_from_the_truth_ends_at_the_same_fit(start, window, monkeypatch):
    # Near the truth the window around the prediction holds the minimum (far fewer warps); far off, its
    # minimum lies on the window's edge and the whole grid runs. Either way the travel is found.
    import monostixels.inputs.road_marks as rm

    cur, prev = _blur(_render(0.0, True)), _blur(_render(-2.0, True))
    t_off = _turn(np.array([0.0, 0.0, 1.0]), math.radians(0.5), 0.0)
    calls = {"n": 0}  # grey values warped

    class CountingCv2:
        def __getattr__(self, name):
            return getattr(cv2, name)

        def remap(self, src, map_u, map_v, interpolation):
            calls["n"] += map_u.size
            return cv2.remap(src, map_u, map_v, interpolation)

    monkeypatch.setattr(rm, "cv2", CountingCv2())
    cold = rm.road_marks_scale(cur, prev, K, np.eye(3), t_off, N_G, HEIGHT, _ground_pixels(), np.random.default_rng(0))
    n_cold, calls["n"] = calls["n"], 0
    fit = rm.road_marks_scale(cur, prev, K, np.eye(3), t_off, N_G, HEIGHT, _ground_pixels(), np.random.default_rng(0),
                              start=start)
    assert fit is not None and cold is not None
    assert fit.scale == pytest.approx(2.0, rel=0.03)
    assert fit.scale == pytest.approx(cold.scale, rel=0.01)
    assert (calls["n"] < n_cold / 3) == window
