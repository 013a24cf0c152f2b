"""Synthetic chessboard views through a known lens, for the calibration tests.

Each pixel is ray-cast: its sub-pixel samples are undistorted with OpenCV's model
(``cv2.undistortPoints``, iterated to convergence), the rays meet the board plane, and the board
coordinates there give the colour. So the squares' edges are curved exactly as the lens curves
them, which straight polygons between projected corners would not be.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

#: Grey levels: dark squares, light squares and the board's margin, the background.
_DARK, _LIGHT, _BACKGROUND = 30, 225, 110
#: Sub-pixel samples per pixel side (anti-aliasing: cornerSubPix needs grey edges).
_SAMPLES = 2


def _rotation(ax: float, ay: float, az: float) -> np.ndarray:
    """R = Rz Ry Rx, angles in radians."""
    return cv2.Rodrigues(np.array([0.0, 0.0, az]))[0] @ cv2.Rodrigues(np.array([0.0, ay, 0.0]))[0] @ \
        cv2.Rodrigues(np.array([ax, 0.0, 0.0]))[0]


def board_poses(n: int, board: tuple[int, int], K: np.ndarray, size: tuple[int, int], seed: int = 0,
                fill: float = 0.45) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` board poses (R, t: board -> camera, board units = squares) spread over the image, tilted
    up to 35 degrees, the board spanning about ``fill`` of the image width."""
    rng = np.random.default_rng(seed)
    H, W = size
    cols, rows = board
    z = K[0, 0] * (cols + 1) / (fill * W)
    centre = np.array([(cols - 1) / 2, (rows - 1) / 2, 0.0])
    out = []
    for k in range(n):
        # Board centres on a ring and the middle, where the distortion shows (corners) and where it does not.
        a = 2 * np.pi * k / max(n - 1, 1)
        r = 0.0 if k == n - 1 else 0.28
        u, v = W / 2 + r * W * np.cos(a), H / 2 + r * H * np.sin(a)
        C = np.array([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
        R = _rotation(*rng.uniform(-0.6, 0.6, 2), rng.uniform(-0.3, 0.3))
        out.append((R, C - R @ centre))
    return out


def pixel_rays(K: np.ndarray, dist: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H * S * W * S, 3) viewing rays ``(x, y, 1)`` of every pixel's S x S sub-pixel samples through the
    lens ``K, dist`` (OpenCV's model), rows of samples in image order. The same for every board pose."""
    H, W = size
    off = (np.arange(_SAMPLES) + 0.5) / _SAMPLES - 0.5
    uu, vv = np.meshgrid((np.arange(W)[:, None] + off[None, :]).ravel(), (np.arange(H)[:, None] + off[None, :]).ravel())
    pts = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(np.float64).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 30, 1e-9)
    xy = cv2.undistortPoints(pts, K, dist, R=None, P=None, criteria=crit).reshape(-1, 2)
    return np.concatenate([xy, np.ones((len(xy), 1))], axis=1)


def render_board(rays: np.ndarray, size: tuple[int, int], R: np.ndarray, t: np.ndarray,
                 board: tuple[int, int]) -> np.ndarray:
    """(H, W) uint8 view of a chessboard of ``board`` inner corners (squares of side 1, a light margin
    of one square) at pose ``X_cam = R X_board + t``, seen along :func:`pixel_rays`."""
    H, W = size
    cols, rows = board
    n = R[:, 2]
    s = (n @ t) / (rays @ n)
    Xb = (s[:, None] * rays - t) @ R  # board coordinates: R^T (X - t)
    a, b = Xb[:, 0], Xb[:, 1]
    on_board = (a >= -1) & (a < cols) & (b >= -1) & (b < rows)
    margin = (a >= -2) & (a < cols + 1) & (b >= -2) & (b < rows + 1)
    dark = on_board & ((np.floor(a) + np.floor(b)) % 2 == 0)
    val = np.where(dark, _DARK, np.where(margin, _LIGHT, _BACKGROUND)).astype(np.float64)
    val[s <= 0] = _BACKGROUND
    # The samples are laid out as (pixel row, sample row) x (pixel column, sample column): average each S x S.
    img = val.reshape(H, _SAMPLES, W, _SAMPLES).mean(axis=(1, 3))
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def write_board_views(folder: Path, K: np.ndarray, dist: np.ndarray, size: tuple[int, int], n: int,
                      board: tuple[int, int] = (9, 6), seed: int = 0) -> list[Path]:
    """``n`` views as PNGs ``view_NN.png`` in ``folder``; returns their paths."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    rays = pixel_rays(K, dist, size)
    for k, (R, t) in enumerate(board_poses(n, board, K, size, seed)):
        p = folder / f"view_{k:02d}.png"
        cv2.imwrite(str(p), render_board(rays, size, R, t, board))
        paths.append(p)
    return paths
