"""Metric scale and travel direction from the road's marks: the road alignment of ``motion=mono`` (step 4b).

At highway speed the near road moves tens of pixels between frames and most of it is textureless asphalt:
the flow there collapses towards zero, and the photometric search over all road pixels
(:func:`monostixels.inputs.ground.photometric_ground`) finds asphalt matching itself best unwarped.
What fixes the length of a forward translation on a road is the image gradient *along* the epipolar
lines (the ends of lane dashes, joints, shadows' edges): a mark parallel to the direction of travel
(a solid lane line) looks the same at every scale and only tells the direction. So this search:

1. keeps the road pixels whose gradient points along the epipolar line through them (within
   ``acos(ALONG_MIN_COS)``) and is among the strongest ``1 - STRONG_QUANTILE`` of those along-line
   gradients (the marks, not the asphalt);
2. warps the previous image onto them by the ground homography ``K (R + s t n^T / h) K^-1``, with the
   road normal ``n`` at right angles to the travel direction ``t`` (a car drives on its road) and the
   rotation ``R`` of the essential matrix, and minimises the mean absolute grey difference over the
   length ``s`` **and** the direction ``t``: the essential matrix's direction comes from the far
   scene, and a degree of error in it misplaces the near road by several pixels at 2 m a pair, more
   than the marks' width; a coarse grid (:data:`DIRECTION_RANGE_DEG`, :data:`DIRECTION_STEP_DEG`)
   over the direction, each with the whole scale grid, then a pattern search over all three;
3. takes the result where the minimum is clear: at most :data:`CLEAR_RATIO` of the cost without
   translation (the warp by ``R`` alone), and not at an end of the scale grid.

On a stream (``stream.motion_warm_start``) the last pair's length starts the search: the grid first
covers only a window around it (:data:`WARM_SPAN`, :data:`WARM_DIRECTION_DEG`), about 30x fewer warps,
and the whole grid runs where that window's minimum lies on its edge or is not clear.

The settings are stated rather than tuned (docs/experiments.md, "A dashcam at highway speed").
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["RoadMarksFit", "road_marks_scale"]

#: Least cosine between a kept pixel's gradient and its epipolar direction (about 37 degrees).
ALONG_MIN_COS = 0.8
#: Kept pixels: the along-line gradient above this quantile of the road pixels' ones.
STRONG_QUANTILE = 0.9
#: Fewest kept pixels for a fit.
MIN_PIXELS = 200
#: At most this many kept pixels in the coarse grid (a seeded subset; the refinement uses all).
COARSE_PIXELS = 1200
#: The direction grid: this far (degrees) either side of the essential matrix's, in both angles, in these steps.
DIRECTION_RANGE_DEG = 3.0
DIRECTION_STEP_DEG = 1.0
#: Candidate translation lengths (metres per pair) of the coarse grid.
SCALE_GRID_M = np.geomspace(0.05, 6.0, 64)
#: A clear minimum costs at most this share of the warp without translation.
CLEAR_RATIO = 0.85
#: Step halvings of the pattern search.
PATTERN_ROUNDS = 6
#: With a predicted length: the first grid covers lengths within this factor of it (either way) and
#: directions within this many degrees (a pair's speed and heading change little at 10-25 Hz).
WARM_SPAN = 1.5
WARM_DIRECTION_DEG = 1.0


@dataclass
class RoadMarksFit:
    """A road alignment: ``scale`` (metres of ``t``), ``t`` (3,) unit travel direction, ``normal`` (3,)
    road normal (current camera, pointing down, at right angles to ``t``), ``ratio`` (best cost over the
    cost without translation) and ``pixels`` (how many mark pixels)."""

    scale: float
    t: np.ndarray
    normal: np.ndarray
    ratio: float
    pixels: int


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _normal_for(t: np.ndarray, n_g: np.ndarray) -> np.ndarray:
    """The road normal closest to ``n_g`` at right angles to ``t`` (both unit 3-vectors)."""
    return _unit(n_g - float(n_g @ t) * t)


def _turn(t: np.ndarray, yaw: float, pitch: float) -> np.ndarray:
    """``t`` turned by ``yaw`` about the camera's y axis and ``pitch`` about its x axis (radians)."""
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    Ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])
    return _unit(Rx @ Ry @ t)


def _mark_pixels(cur: np.ndarray, K: np.ndarray, t: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Indices into ``pts`` (N, 2) of the road pixels whose gradient runs along their epipolar line."""
    gx = cv2.Sobel(cur, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(cur, cv2.CV_32F, 0, 1, ksize=3)
    u, v = pts[:, 0].astype(np.int64), pts[:, 1].astype(np.int64)
    g = np.c_[gx[v, u], gy[v, u]].astype(np.float64)
    foe = K @ t
    if abs(foe[2]) < 1e-9:  # sideways travel: the epipolar lines are parallel, along t's image direction
        e = np.broadcast_to(_unit(foe[:2]), pts.shape)
    else:
        e = pts - foe[:2] / foe[2]
        e = e / np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-9)
    along = np.abs(np.einsum("ij,ij->i", g, e))
    mag = np.linalg.norm(g, axis=1)
    if len(along) == 0:
        return np.zeros(0, dtype=np.int64)
    keep = (along >= np.quantile(along, STRONG_QUANTILE)) & (along >= ALONG_MIN_COS * mag) & (mag > 0)
    return np.nonzero(keep)[0]


def road_marks_scale(cur: np.ndarray, prev: np.ndarray, K: np.ndarray, R: np.ndarray, t_unit: np.ndarray,
                     n_g: np.ndarray, height: float, pts: np.ndarray,
                     rng: np.random.Generator, start: float | None = None) -> RoadMarksFit | None:
    """Length and direction of the translation that align the road's marks (module docstring).

    Args:
        cur, prev: (H, W) float32 grey images (current, previous).
        K: (3, 3) intrinsics, pixels.
        R: (3, 3) rotation, ``X_prev = R X_cur + t``.
        t_unit: (3,) the essential matrix's unit translation (the search starts from it).
        n_g: (3,) the configured unit ground normal (current camera, pointing down).
        height: camera height above the road, metres.
        pts: (N, 2) road pixels of the current image (u, v).
        rng: draws the coarse grid's subset.
        start: a predicted length (metres; a stream's last pair, ``t_unit`` then its direction): the coarse
            grid first covers only lengths within :data:`WARM_SPAN` of it and directions within
            :data:`WARM_DIRECTION_DEG` of ``t_unit``; the whole grid where its minimum lies on the window's
            edge or is not clear.

    Returns:
        A :class:`RoadMarksFit`, or None: too few mark pixels, or no clear minimum.
    """
    H, W = cur.shape
    idx = _mark_pixels(cur, K, t_unit, pts)
    if len(idx) < MIN_PIXELS:
        return None
    p = pts[idx]
    y = np.c_[p, np.ones(len(p))] @ np.linalg.inv(K).T
    a = y @ (K @ R).T
    ref = cur[p[:, 1].astype(np.int64), p[:, 0].astype(np.int64)].astype(np.float64)

    def costs(t: np.ndarray, scales: np.ndarray, sub: np.ndarray | slice) -> np.ndarray:
        """Mean absolute difference (S,) per scale; inf where under half of the pixels land inside."""
        n = _normal_for(t, n_g)
        k = (y[sub] @ n) / height
        c = K @ t
        q = a[sub][None] + (scales[:, None] * k[None])[..., None] * c[None, None]  # (S, n, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = q[..., 0] / q[..., 2], q[..., 1] / q[..., 2]
        inside = (q[..., 2] > 0) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
        su = np.where(inside, u, 0.0).astype(np.float32)
        sv = np.where(inside, v, 0.0).astype(np.float32)
        d = np.abs(cv2.remap(prev, su, sv, cv2.INTER_LINEAR).astype(np.float64) - ref[sub][None])
        n_in = inside.sum(axis=1)
        out = np.where(inside, d, 0.0).sum(axis=1) / np.maximum(n_in, 1)
        return np.where(2 * n_in >= inside.shape[1], out, np.inf)

    sub = np.sort(rng.choice(len(p), size=COARSE_PIXELS, replace=False)) if len(p) > COARSE_PIXELS else slice(None)
    still = float(costs(t_unit, np.zeros(1), slice(None))[0])  # R alone: no translation

    def f(x: np.ndarray) -> float:
        return float(costs(_turn(t_unit, x[1], x[2]), np.array([math.exp(x[0])]), slice(None))[0])

    def search(scales: np.ndarray, range_deg: float) -> tuple[np.ndarray, float] | None:
        """The coarse grid over ``scales`` and directions within ``range_deg``, then a pattern search over
        (log s, yaw, pitch) on every mark pixel; None where the grid's minimum lies at an end of ``scales``."""
        span = np.radians(np.arange(-range_deg, range_deg + 1e-9, DIRECTION_STEP_DEG))
        best = (math.inf, 0.0, 0.0, 0)
        for yaw in span:
            for pitch in span:
                c = costs(_turn(t_unit, yaw, pitch), scales, sub)
                k = int(np.argmin(c))
                if c[k] < best[0]:
                    best = (float(c[k]), float(yaw), float(pitch), k)
        _, yaw, pitch, k = best
        if k in (0, len(scales) - 1):
            return None
        x = np.array([math.log(scales[k]), yaw, pitch])
        step = np.array([math.log(SCALE_GRID_M[1] / SCALE_GRID_M[0]), math.radians(DIRECTION_STEP_DEG) / 2,
                         math.radians(DIRECTION_STEP_DEG) / 2])
        fx = f(x)
        for _ in range(PATTERN_ROUNDS):
            improved = True
            while improved:
                improved = False
                for d in range(3):
                    for sign in (1.0, -1.0):
                        cand = x.copy()
                        cand[d] += sign * step[d]
                        fc = f(cand)
                        if fc < fx:
                            x, fx, improved = cand, fc, True
            step /= 2
        return x, fx

    found = None
    if start is not None and start > 0:
        # Speed changes little from one pair to the next: the minimum near the predicted length first.
        window = SCALE_GRID_M[(SCALE_GRID_M >= start / WARM_SPAN) & (SCALE_GRID_M <= start * WARM_SPAN)]
        if len(window) >= 3:
            found = search(window, WARM_DIRECTION_DEG)
            if found is not None and not found[1] / still <= CLEAR_RATIO:
                found = None
    if found is None:
        found = search(SCALE_GRID_M, DIRECTION_RANGE_DEG)
    if found is None:
        return None
    x, fx = found
    ratio = fx / still if still > 0 else math.inf
    if not ratio <= CLEAR_RATIO:
        return None
    t = _turn(t_unit, x[1], x[2])
    return RoadMarksFit(math.exp(x[0]), t, _normal_for(t, n_g), float(ratio), len(idx))
