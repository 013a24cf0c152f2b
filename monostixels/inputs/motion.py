"""Camera motion (config group ``motion``): ground truth, a poses file, or monocular estimation.

Convention (docs/conventions.md, section 2): the motion ``(R, t)`` of a frame pair maps
current-camera coordinates of a static point to previous-camera coordinates,
``X_prev = R X_cur + t``, metres; flow maps current to previous pixels, ``x_prev = x + f``.

Backends (``cfg.name``):

- ``gt``: ``pair.motion`` from the data source.
- ``file``: a KITTI-style poses file (``cfg.path``): per line either 12 numbers (the 3x4
  row-major ``T_w_cam``, camera to world, metres; line ``i`` = frame ``i``) or a frame number
  followed by the 12 numbers. Frames are ``pair.meta["frame_index"]`` (current) and
  ``pair.meta["frame_index_prev"]`` (or ``"frame"`` / ``"frame_prev"``, as kitti_raw writes them). ``cfg.offset`` (3,) is the position of the image camera
  in the posed camera's frame when the two differ by a translation only (KITTI camera 2 vs the
  camera-0 poses: ``(P_rect_02[0,3] / fx, 0, 0)``, about 6 cm).
- ``mono``: from the flow alone.

  1. Likely-static pixels: a grid of flow vectors with a small flow covariance, minus pixels whose
     semantic argmax is a dynamic class or sky (when scores are given).
  2. Degeneracy: the best rotation-only motion ``x_prev ~ K R K^-1 x`` is fitted (trimmed
     Procrustes on viewing rays). If it explains the flow to within ``min_parallax_px``
     (median residual), the pair has no usable translation (standing still or pure rotation):
     reported with ``degenerate=True``, ``R`` from that fit and ``t = 0`` — not guessed.
  3. Rotation and translation direction: essential matrix with RANSAC (OpenCV, five-point) and
     the cheirality test, then a robust nonlinear refinement of ``(R, t̂)`` on the inliers
     (Sampson distance, soft-L1 loss).
  4. Metric scale from the ground: ground pixels (semantic road where given, else the road
     region in front of the car predicted by the camera height and ground normal) move with the
     plane homography ``K (R + t̂ m^T) K^-1`` with ``m = (s / h) n``: ``s`` the metric length of
     ``t``, ``h`` the camera height, ``n`` the ground normal.

     a. Photometric (when the images are given, ``photometric_scale``): the previous image is
        warped onto the current one by the ground homography; a 1-D search over ``s`` then a
        pattern search over ``(s, n)`` minimise the median grey-value difference over the
        ground pixels. The near road moves by up to ~130 px between KITTI-like frames, where
        flow fails; the images themselves do not (synthetic seed 2 at half size: median scale
        error 0.2 % against 16 % from the flow on the 13 worst frames). Taken when its minimum
        is sharp (``photometric_sharp``); on weakly textured real asphalt it often is not
        (KITTI raw: flow 4 %, photometric 8 %).
     b. Road marks (``road_marks``, without a sharp photometric minimum): the same warp over the
        road pixels whose gradient runs along their epipolar line (lane dashes' ends, joints), with
        the road normal at right angles to the travel direction, minimised over the length ``s`` and
        the direction ``t̂`` (:mod:`monostixels.inputs.road_marks`). At highway speed the near road
        moves 30-80 px over textureless asphalt: the flow there is near zero and the whole-road
        search prefers no warp; the marks still fix the scale, and the far scene's essential matrix
        is up to ~3 deg off in direction, more than the marks' width at 2 m a pair.
     c. From the flow: ``m`` is linear in the flow equations (RANSAC with the tilt bounded by
        ``ground_max_tilt``, then least squares); ``s = camera.height * |m|``. It is taken unless
        the road marks gave a length and it is shorter than :data:`FLOW_SHORT_RATIO` of theirs:
        the flow of textureless asphalt errs short, pulled towards zero, not long. When the flow
        finds no plane, the road marks are used, else a weak photometric minimum; with neither,
        no estimate.

  5. Over a sequence (:class:`MotionTrack`, used by the pipeline for consecutive pairs of one
     sequence): the speed ``|t| / dt`` follows a constant-velocity model, filtered in log space
     (a 1-D Kalman filter); a per-pair scale that disagrees with the prediction by more than
     ``scale_gate`` standard deviations is replaced by the prediction (flagged in ``reason``).
     A single pair, or the first pair of a sequence, is unchanged.
"""
from __future__ import annotations

import dataclasses
import logging
import math
from concurrent.futures import wait
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from monostixels._pools import helper_pool
from monostixels._checks import InputError, check_finite, check_shape
from monostixels.classes import CLASS_TYPE, DYNAMIC_OBJECT, NUM_CLASSES, SKY
from monostixels.data._io import relative_motion
from monostixels.data.base import FramePair
from monostixels.geometry import Motion
from monostixels.inputs.confidence import to_gray
from monostixels.inputs.road_marks import RoadMarksFit, road_marks_scale

__all__ = [
    "MOTION_BACKENDS",
    "MOTION_KINDS",
    "NO_METRIC_MOTION",
    "MIN_TRANSLATION_M",
    "MonoParams",
    "MotionEstimate",
    "estimate_motion",
    "estimate_mono",
    "load_poses",
    "relative_motion",
    "motion_errors",
    "implied_height",
    "MotionTrack",
    "TrackParams",
]

logger = logging.getLogger(__name__)

MOTION_BACKENDS = ("gt", "file", "mono")
#: What a camera-motion estimate knows (:attr:`MotionEstimate.kind`). Only ``standing`` lets the movers
#: treat every flow vector as object motion; ``scale_unknown`` and ``unknown`` call nothing moving.
MOTION_KINDS = ("metric", "standing", "scale_unknown", "unknown")
#: The kinds without a metric camera motion (no movers, no TTC, no pose).
NO_METRIC_MOTION = ("scale_unknown", "unknown")
#: Below this camera translation (metres) a known motion (gt / file) counts as standing still:
#: 1 mm moves a point 5 m away by ~0.15 px at KITTI focal length — no usable parallax.
MIN_TRANSLATION_M = 1e-3
#: Semantic class id of road (classes.CLASS_NAMES): the plane the mounting height refers to.
_ROAD_CLASS = 0


@dataclass
class MotionEstimate:
    """Result of a camera-motion backend.

    Attributes:
        motion: ``X_prev = R X_cur + t`` (metres); for a degenerate pair ``R`` is estimated and
            ``t = 0``; None when it cannot be determined at all.
        degenerate: standing still / pure rotation: translation direction and scale unknown.
        reason: human-readable ("ok", "no translation: median parallax 0.2 px", ...).
        inlier_ratio: fraction of the used flow vectors consistent with the estimate (1 for gt/file).
        ground_normal: (3,) float64 unit normal of the road plane fitted for the metric scale
            (current camera, pointing down), or None (gt/file, or no fit).
        kind: which of :data:`MOTION_KINDS` the estimate is: ``metric`` (rotation and metric
            translation), ``standing`` (no translation: standing still or turning on the spot;
            ``degenerate``), ``scale_unknown`` (rotation and translation direction known, its metric
            length not: ``unit_motion``) or ``unknown`` (nothing known about the camera).
        unit_motion: ``scale_unknown``: the rotation and the unit translation direction; else None.
        scale_from: where a metric translation's length came from: ``given`` (gt / file),
            ``photometric`` (the road's image alignment), ``road_marks`` (the alignment of the road's marks
            and the travel direction, :mod:`~monostixels.inputs.road_marks`), ``ground_flow`` (the road's flow vectors),
            ``sequence`` (the recent pairs' speed, :class:`MotionTrack`); None otherwise.
    """

    motion: Motion | None
    degenerate: bool
    reason: str
    inlier_ratio: float
    ground_normal: torch.Tensor | None = None
    kind: str = "metric"
    unit_motion: Motion | None = None
    scale_from: str | None = None


@dataclass
class MonoParams:
    """Parameters of the ``mono`` estimator (keys of the ``motion`` config group).

    Attributes:
        step: stride (pixels) of the grid of flow vectors used.
        max_points: at most this many vectors (random subset, seeded) for the essential matrix.
        max_flow_sigma: vectors whose flow standard deviation (sqrt of the largest covariance
            eigenvalue, pixels) exceeds this are not used.
        ransac_threshold: RANSAC inlier threshold of the essential matrix (pixels).
        ransac_confidence: RANSAC confidence.
        min_parallax: median residual (pixels) of the rotation-only fit below which the pair
            counts as degenerate (no translation).
        min_points: fewest usable flow vectors (and ground vectors) for an estimate.
        ground_max_distance: ground region ahead of the car (no semantics), metres along z.
        ground_half_width: half width of that region, metres.
        ground_threshold: inlier threshold of the ground-plane fit (pixels).
        ground_max_tilt: largest angle (degrees) between the fitted and the configured ground normal.
        photometric_scale: scale and road normal from the images (step 4a) when they are given;
            the flow of the ground (step 4b) is then the fallback.
        photometric_pixels: at most this many ground pixels (seeded subset) in that search.
        photometric_sharp: the photometric estimate is taken first when its minimum is this sharp
            (best / median cost over the scale grid); a weaker one only when the flow gives no plane.
        road_marks: without a sharp photometric minimum, the scale and travel direction from the road's
            marks (:mod:`monostixels.inputs.road_marks`) where the flow of the ground gives none or
            one well short of theirs (:data:`FLOW_SHORT_RATIO`).
        seed: RNG seed of the subsampling and RANSAC.
    """

    step: int = 4
    max_points: int = 4000
    max_flow_sigma: float = 2.0
    ransac_threshold: float = 0.5
    ransac_confidence: float = 0.999
    min_parallax: float = 1.0
    min_points: int = 50
    ground_max_distance: float = 25.0
    ground_half_width: float = 2.5
    ground_threshold: float = 0.5
    ground_max_tilt: float = 10.0
    photometric_scale: bool = True
    photometric_pixels: int = 40000
    photometric_sharp: float = 0.3
    road_marks: bool = True
    seed: int = 0


def _get(cfg: Any, key: str, default: Any) -> Any:
    if cfg is None:
        return default
    val = cfg.get(key, default) if hasattr(cfg, "get") else getattr(cfg, key, default)
    return default if val is None else val


def _mono_params(cfg: Any) -> MonoParams:
    d = MonoParams()
    kw = {k: type(getattr(d, k))(_get(cfg, k, getattr(d, k))) for k in d.__dataclass_fields__}
    return MonoParams(**kw)


# ----------------------------------------------------------------------------------------------
# gt / file


def _gt_motion(pair: FramePair) -> MotionEstimate:
    if pair.motion is None:
        source = pair.meta.get("source", pair.name or "this data source")
        raise InputError(f"motion=gt: {source} has no ground-truth camera motion (pair.motion is None); use motion=file or motion=mono")
    return _known(pair.motion, "ground truth")


def _known(motion: Motion, what: str) -> MotionEstimate:
    """A known motion, flagged degenerate when it has no translation to speak of."""
    tn = motion.translation_norm
    if tn < MIN_TRANSLATION_M:
        return MotionEstimate(motion, True, f"no translation ({what}): |t| = {tn:.2e} m < {MIN_TRANSLATION_M} m", 1.0,
                              kind="standing")
    return MotionEstimate(motion, False, f"ok ({what})", 1.0, scale_from="given")


@lru_cache(maxsize=8)
def _load_poses_cached(path: str, mtime: float) -> dict[int, np.ndarray]:
    poses: dict[int, np.ndarray] = {}
    with open(path, encoding="utf-8") as fh:
        for lineno, line in enumerate(fh):
            parts = line.split()
            if not parts:
                continue
            try:
                vals = [float(x) for x in parts]
            except ValueError as exc:
                raise InputError(f"motion.path: {path!r} line {lineno + 1}: not numbers ({exc})") from exc
            if len(vals) == 12:
                frame = len(poses)
            elif len(vals) == 13 and float(vals[0]).is_integer():
                frame, vals = int(vals[0]), vals[1:]
            else:
                raise InputError(
                    f"motion.path: {path!r} line {lineno + 1}: expected 12 numbers (3x4 T_w_cam) or a frame number "
                    f"and 12 numbers, got {len(vals)}"
                )
            T = np.eye(4)
            T[:3, :] = np.asarray(vals).reshape(3, 4)
            if not np.isfinite(T).all():
                raise InputError(f"motion.path: {path!r} line {lineno + 1}: non-finite pose")
            poses[frame] = T
    if not poses:
        raise InputError(f"motion.path: {path!r} holds no poses")
    return poses


def load_poses(path: str | Path) -> dict[int, np.ndarray]:
    """Poses ``T_w_cam`` (4, 4) float64 (camera to world, metres) by frame number from a KITTI poses file."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"motion.path: poses file not found: {str(p)!r}")
    return _load_poses_cached(str(p.resolve()), p.stat().st_mtime)


def _file_motion(pair: FramePair, cfg: Any) -> MotionEstimate:
    path = _get(cfg, "path", None)
    if path is None:
        raise InputError("motion.path: motion=file needs a poses file (motion.path=PATH)")
    poses = load_poses(path)
    # Our sources put raw frame numbers in meta: "frame_index"/"frame_index_prev", or (kitti_raw)
    # "frame"/"frame_prev".
    keys = next((k for k in (("frame_index", "frame_index_prev"), ("frame", "frame_prev")) if all(x in pair.meta for x in k)), None)
    if keys is None:
        raise InputError(
            f"motion=file: frame pair {pair.name!r} has no meta['frame_index'] / ['frame_index_prev'] (or 'frame' / "
            f"'frame_prev') to look up in {str(path)!r}"
        )
    cur, prev = int(pair.meta[keys[0]]), int(pair.meta[keys[1]])
    for f in (cur, prev):
        if f not in poses:
            raise InputError(f"motion.path: {str(path)!r} has no pose for frame {f} (frames {min(poses)}..{max(poses)})")
    offset = _get(cfg, "offset", None)
    off = None if offset is None else np.asarray(list(offset), dtype=np.float64)
    if off is not None and off.shape != (3,):
        raise InputError(f"motion.offset: expected 3 numbers (metres), got {list(offset)}")
    motion = relative_motion(poses[cur], poses[prev], off)
    return _known(motion, f"poses file, frames {cur} <- {prev}")


# ----------------------------------------------------------------------------------------------
# mono


def _rays(K: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Viewing rays (N, 3) with z = 1 of pixels (N, 2)."""
    return np.c_[pts, np.ones(len(pts))] @ np.linalg.inv(K).T


def _project(K: np.ndarray, X: np.ndarray) -> np.ndarray:
    x = X @ K.T
    return x[:, :2] / x[:, 2:3]


def _fit_rotation(K: np.ndarray, p_cur: np.ndarray, p_prev: np.ndarray, iters: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Best rotation-only motion (trimmed Procrustes on unit rays); returns R and pixel residuals (N,)."""
    a = _rays(K, p_cur)
    b = _rays(K, p_prev)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    use = np.ones(len(a), dtype=bool)
    R = np.eye(3)
    for _ in range(iters):
        U, _, Vt = np.linalg.svd(b[use].T @ a[use])  # maximise sum b^T R a
        R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        res = np.linalg.norm(_project(K, a @ R.T) - p_prev, axis=1)
        use = res <= max(np.median(res) * 2.0, 1e-6)
    return R, res


def _max_eigenvalue_at_most(cov: np.ndarray, bound: float) -> np.ndarray:
    """Mask (N,): the largest eigenvalue of each symmetric (N, 2, 2) matrix is <= ``bound``.

    ``bound I - C`` positive semi-definite: both diagonal entries and the determinant >= 0
    (the lower triangle is read, as ``eigvalsh`` reads it). For float32 covariances this is exact
    in float64 (the products need at most ~50 bits), where an eigen-solver rounds; 20x faster
    than ``torch.linalg.eigvalsh`` on the ~30000 grid vectors of a KITTI frame.
    """
    c = cov.astype(np.float64)
    pa, pd = bound - c[:, 0, 0], bound - c[:, 1, 1]
    b = c[:, 1, 0]
    return (pa >= 0) & (pd >= 0) & (pa * pd >= b * b)


def _sampson(E: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Sampson distance (N,) of ray pairs (z = 1) under ``b^T E a = 0``, in normalised units."""
    Ea = a @ E.T
    Etb = b @ E
    num = np.sum(b * Ea, axis=1)
    den = Ea[:, 0] ** 2 + Ea[:, 1] ** 2 + Etb[:, 0] ** 2 + Etb[:, 1] ** 2
    return num / np.sqrt(np.maximum(den, 1e-30))


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def _refine_pose(R: np.ndarray, t: np.ndarray, a: np.ndarray, b: np.ndarray, f_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Nonlinear refinement of ``(R, t̂)`` minimising the Sampson distance (soft-L1) over ray pairs."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    # t on the unit sphere: t = normalize(t0 + B beta), B a basis of the tangent plane at t0.
    t0 = t / np.linalg.norm(t)
    B = np.linalg.svd(t0[None])[2][1:].T  # (3, 2)

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Rx = Rotation.from_rotvec(x[:3]).as_matrix() @ R
        tx = t0 + B @ x[3:]
        return Rx, tx / np.linalg.norm(tx)

    def fun(x: np.ndarray) -> np.ndarray:
        Rx, tx = unpack(x)
        return _sampson(_skew(tx) @ Rx, a, b)

    sol = least_squares(fun, np.zeros(5), loss="soft_l1", f_scale=f_scale, method="trf", x_scale="jac")
    return unpack(sol.x)


def _ground_candidates(K: np.ndarray, n: np.ndarray, height: float, pts: np.ndarray, prm: MonoParams,
                       lateral: bool = True) -> np.ndarray:
    """Mask (N,) of pixels whose ray meets the reference ground ahead within the road region.

    ``lateral=False`` drops the corridor of ``ground_half_width``: with semantic road labels the
    road pixels are known wherever they are, and a vehicle ahead can block the corridor.
    """
    r = _rays(K, pts)
    rn = r @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.where(rn > 1e-6, height / rn, np.inf)  # X = lam r on the ground n^T X = h
    X = r * np.where(np.isfinite(lam), lam, 0.0)[:, None]
    near = np.isfinite(lam) & (X[:, 2] < prm.ground_max_distance)
    return near & (np.abs(X[:, 0]) < prm.ground_half_width) if lateral else near


def _ground_system(K: np.ndarray, R: np.ndarray, t: np.ndarray, p_cur: np.ndarray, p_prev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear equations ``A m = b`` (2N, 3), (2N,) of ground pixels for ``H = K (R + t m^T) K^-1``.

    With ``y = K^-1 x``, ``a = K R y``, ``c = K t``: ``H x = a + c (m^T y)`` and ``x_prev × H x = 0``
    give ``(u' c_3 - c_1) y^T m = a_1 - u' a_3`` and the same in ``v'``; dividing by ``a_3``
    (≈ the third coordinate of ``H x``) makes the residuals close to pixels.
    """
    y = _rays(K, p_cur)
    a = y @ (K @ R).T
    c = K @ t
    up, vp = p_prev[:, 0], p_prev[:, 1]
    w = 1.0 / a[:, 2:3]
    A = np.concatenate([y * ((up * c[2] - c[0])[:, None]) * w, y * ((vp * c[2] - c[1])[:, None]) * w])
    b = np.concatenate([(a[:, 0] - up * a[:, 2]) * w[:, 0], (a[:, 1] - vp * a[:, 2]) * w[:, 0]])
    return A, b


def _tilt_deg(m: np.ndarray, n_g: np.ndarray) -> float:
    """Angle (degrees) between the plane vector ``m`` and the unit normal ``n_g``."""
    q = float(np.linalg.norm(m))
    return math.degrees(math.acos(np.clip(float(m @ n_g) / max(q, 1e-30), -1.0, 1.0)))


def _fit_ground(A: np.ndarray, b: np.ndarray, thr: float, rng: np.random.Generator, hypotheses: int = 300,
                n_g: np.ndarray | None = None, max_tilt: float = 180.0) -> tuple[np.ndarray, np.ndarray]:
    """RANSAC (2 pixels = 4 equations per hypothesis) + least squares of ``A m = b``; returns m and inliers (N,).

    Hypotheses tilted more than ``max_tilt`` degrees from ``n_g`` are not scored: the road is
    near the configured plane, and a wall or a car side that happens to hold more of the
    candidate pixels must not win.
    """
    N = len(A) // 2
    best, best_count = None, -1
    for _ in range(hypotheses):
        idx = rng.choice(N, size=2, replace=False)
        rows = np.r_[idx, idx + N]
        m, *_ = np.linalg.lstsq(A[rows], b[rows], rcond=None)
        if n_g is not None and _tilt_deg(m, n_g) > max_tilt:
            continue
        res = np.hypot(A[:N] @ m - b[:N], A[N:] @ m - b[N:])
        count = int((res < thr).sum())
        if count > best_count:
            best, best_count = m, count
    if best is None:  # no hypothesis within the tilt: the unconstrained fit, rejected by the caller
        best, *_ = np.linalg.lstsq(A, b, rcond=None)
    m = best
    for _ in range(3):
        res = np.hypot(A[:N] @ m - b[:N], A[N:] @ m - b[N:])
        inl = res < thr
        if inl.sum() < 3:
            break
        rows = np.r_[np.nonzero(inl)[0], np.nonzero(inl)[0] + N]
        m, *_ = np.linalg.lstsq(A[rows], b[rows], rcond=None)
    res = np.hypot(A[:N] @ m - b[:N], A[N:] @ m - b[N:])
    return m, res < thr


#: The flow of the ground is taken over the road marks' scale unless it is shorter than this share of it.
FLOW_SHORT_RATIO = 0.7

#: Candidate metric translations (metres per frame) of the photometric scale search.
_SCALE_GRID_M = np.geomspace(0.02, 5.0, 96)


#: Step halvings of the photometric pattern search (from one grid step: a final step of 1/256 of it).
_PATTERN_ROUNDS = 8
#: Warm start of the photometric search (a prediction from the stream): every this-many-th scale of
#: the grid is read (the contrast's median, a minimum far away), and the scales within this many grid
#: steps (6 % each) of the prediction.
_WARM_GRID_STRIDE = 4
_WARM_GRID_HALF_WIDTH = 3
#: Least ratio of the refined to the grid contrast that the pattern search may reach (0.82 the least
#: seen on the KITTI raw drives): a warm grid contrast above ``photometric_sharp / 0.7`` is not refined.
_PATTERN_MAX_GAIN = 0.7


#: Most threads of the photometric search: its grid is 96 costs of ~0.5 ms, its pattern search
#: asks for two at a time.
_MAX_PHOTOMETRIC_WORKERS = 4


def _photometric_workers() -> int:
    """Threads of the photometric search: torch's thread count, which stands for the cores this
    process may use (``--threads`` of the benchmarks, ``torch.set_num_threads``), at most 4."""
    return max(1, min(_MAX_PHOTOMETRIC_WORKERS, torch.get_num_threads()))


def _grey(image: torch.Tensor) -> np.ndarray:
    """(3, H, W) RGB in [0, 1] -> (H, W) float32 grey, lightly smoothed (a wider basin for the search)."""
    # Clipped in numpy, then the covariance's grey conversion (numpy, the same float32 values as
    # torch's weighted channel sum), without torch's thread hand-offs.
    x = np.clip(image.detach().cpu().numpy().astype(np.float32, copy=False), 0.0, 1.0)
    g = to_gray(torch.from_numpy(x)).numpy()
    return cv2.GaussianBlur(g, (0, 0), 1.0)


def _median(x: np.ndarray) -> float:
    """``float(np.median(x))`` of a non-empty 1-D array, from one partition.

    The same value as numpy (the middle order statistic, or the mean of the two middle ones
    taken in ``x``'s dtype as ``np.mean`` takes it), 5-6x faster on the ~40000 costs of one
    photometric candidate: ``np.median`` partitions at three positions (two middles and the end,
    for its NaN check).
    """
    n = len(x)
    if np.isnan(x).any():
        return math.nan
    k = n // 2
    part = np.partition(x, k)
    if n % 2:
        return float(part[k])
    return float(np.mean(np.array([part[:k].max(), part[k]], dtype=x.dtype)))


def _sample(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples (N,) of ``img`` at (u, v) (maps are reshaped: OpenCV caps their sides at 32767)."""
    n = len(u)
    cols = 1024
    rows = -(-n // cols)
    mu = np.zeros(rows * cols, dtype=np.float32)
    mv = np.zeros(rows * cols, dtype=np.float32)
    mu[:n] = u
    mv[:n] = v
    return cv2.remap(img, mu.reshape(rows, cols), mv.reshape(rows, cols), cv2.INTER_LINEAR).reshape(-1)[:n]


def _photometric_ground(cur: np.ndarray, prev: np.ndarray, K: np.ndarray, R: np.ndarray, t_unit: np.ndarray,
                        n_g: np.ndarray, height: float, pts: np.ndarray, max_tilt: float,
                        start: tuple[float, np.ndarray] | None = None,
                        unsharp: float = math.inf) -> tuple[float, np.ndarray, float] | None:
    """Metric length (m) of ``t_unit`` and road normal that best warp ``prev`` onto ``cur`` over ``pts``.

    The ground homography of a length ``s`` and normal ``n`` is ``K (R + s t̂ n^T / h) K^-1``; the
    cost is the median absolute grey difference over the ground pixels ``pts`` (N, 2) (robust to
    an object on them). A 1-D search over ``s`` with ``n = n_g`` finds the basin, then a pattern
    search refines ``(log s, n)`` with ``n`` within ``max_tilt`` degrees of ``n_g``.

    ``start = (s, n)``: a prediction (a stream's last pair at constant velocity). The 1-D search then
    reads only every :data:`_WARM_GRID_STRIDE`-th scale of its grid (enough for the median the
    contrast is measured against, and to see a minimum far from the prediction) and the scales within
    :data:`_WARM_GRID_HALF_WIDTH` grid steps of ``s``: where the best of those lies inside that window
    it is the grid's minimum, and the pattern search runs from it as from scratch (the same result,
    a third of the 1-D search's cost); else the whole grid is read. The pattern search is not started
    at the prediction itself: on our renders that kept each pair's scale near the last pair's (a bias
    of 1-2 % where the search from the grid finds 0.3-0.9 %). ``unsharp``: with a start, a grid contrast
    above this is returned as it is, without the pattern search (the caller then takes another scale;
    it asks again without a start where it needs the refined minimum after all).

    Returns:
        ``(s, n (3,), contrast)``, contrast = best cost / median cost over the 1-D grid (lower is
        clearer), or None without a clear minimum.
    """
    y = _rays(K, pts)
    a = y @ (K @ R).T
    c = K @ t_unit
    H, W = cur.shape
    ref = cur[pts[:, 1].astype(np.int64), pts[:, 0].astype(np.int64)]
    e1 = np.cross(n_g, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n_g, e1)  # n_g, e1 (sideways), e2 (forward): roll and pitch of the road plane

    def normal(x: np.ndarray) -> np.ndarray:
        n = n_g + x[1] * e1 + x[2] * e2
        return n / np.linalg.norm(n)

    # Per-component arrays and a cache of ``y @ n``/costs: the same float operations as on
    # (N, 3) arrays, fewer passes over memory (the search evaluates ~180 candidates per pair).
    a0, a1, a2 = (np.ascontiguousarray(a[:, i]) for i in range(3))
    c0, c1, c2 = (float(ci) for ci in c)
    yn_cache: dict[bytes, np.ndarray] = {}
    cost_cache: dict[bytes, float] = {}

    def cost(x: np.ndarray) -> float:
        key = x.tobytes()
        if key in cost_cache:
            return cost_cache[key]
        n = normal(x)
        if _tilt_deg(n, n_g) > max_tilt:
            cost_cache[key] = math.inf
            return math.inf
        nkey = n.tobytes()
        yn = yn_cache.get(nkey)
        if yn is None:
            yn = y @ n
            if len(yn_cache) >= 8:  # the normals of one pattern-search step; bounded memory
                yn_cache.clear()
            yn_cache[nkey] = yn
        k = math.exp(x[0]) * yn / height
        q2 = a2 + k * c2
        u, v = (a0 + k * c0) / q2, (a1 + k * c1) / q2
        inside = (q2 > 0) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
        n_in = int(np.count_nonzero(inside))
        if 2 * n_in < len(inside):  # fewer than half of the pixels land in the previous image
            out = math.inf
        elif n_in == len(inside):  # the usual case: no selection needed
            out = _median(np.abs(_sample(prev, u, v) - ref))
        else:
            out = _median(np.abs(_sample(prev, u[inside], v[inside]) - ref[inside]))
        cost_cache[key] = out
        return out

    # ``cost`` is a pure function of x: candidates the search will (or may) ask for next are
    # evaluated side by side into the cache (numpy and OpenCV release the GIL), and the search
    # below then runs as written, one candidate after the other, on cached values: the same
    # result as the sequential search, in less wall time.
    workers = _photometric_workers()
    pool = helper_pool("photometric", workers - 1) if workers > 1 else None

    def prefetch(xs: list[np.ndarray]) -> None:
        todo = [x for x in xs if x.tobytes() not in cost_cache]
        if pool is None or len(todo) < 2:
            return
        chunks = [todo[i::workers] for i in range(workers)]  # interleaved: the far scales are cheap
        futures = [pool.submit(lambda xs_: [cost(x_) for x_ in xs_], ch) for ch in chunks[1:] if ch]
        for x_ in chunks[0]:
            cost(x_)
        for fut in futures:
            fut.result()

    grid_step = math.log(_SCALE_GRID_M[1] / _SCALE_GRID_M[0])
    step = np.array([grid_step, 0.01, 0.01])  # 1 grid step, ~0.6 deg
    x = None
    if start is not None:
        # A sparse cover of the grid (for the contrast's median, and to see a minimum far from the
        # prediction) and the grid's scales within a window around the predicted one.
        k0 = int(round(math.log(start[0] / _SCALE_GRID_M[0]) / grid_step))
        window = range(max(k0 - _WARM_GRID_HALF_WIDTH, 0), min(k0 + _WARM_GRID_HALF_WIDTH + 1, len(_SCALE_GRID_M)))
        read = sorted(set(range(0, len(_SCALE_GRID_M), _WARM_GRID_STRIDE)) | set(window))
        grid = [np.array([math.log(_SCALE_GRID_M[k]), 0.0, 0.0]) for k in read]
        prefetch(grid)
        c_read = np.array([cost(g) for g in grid])
        fin = np.isfinite(c_read)
        if fin.sum() >= 8:
            kb = read[int(np.argmin(np.where(fin, c_read, np.inf)))]
            # The best scale read lies inside the window (not at its ends: the speed changed more than
            # the window allows) and is clear against the cover: the grid's minimum, as a full grid
            # would have found it; the pattern search then runs as from scratch.
            if window.start < kb < window.stop - 1 and 0 < kb < len(_SCALE_GRID_M) - 1:
                cover = np.array([c for k, c in zip(read, c_read) if k % _WARM_GRID_STRIDE == 0])
                costs, finite = cover, np.isfinite(cover)
                best = float(c_read[read.index(kb)])
                if best >= 0.6 * np.median(costs[finite]):
                    return None
                x = np.array([math.log(_SCALE_GRID_M[kb]), 0.0, 0.0])
                contrast = best / float(np.median(costs[finite]))
                if contrast > unsharp:
                    return math.exp(x[0]), n_g.copy(), contrast
    if x is None:
        grid = [np.array([math.log(s), 0.0, 0.0]) for s in _SCALE_GRID_M]
        prefetch(grid)
        costs = np.array([cost(g) for g in grid])
        finite = np.isfinite(costs)
        if finite.sum() < 8:
            return None
        k = int(np.argmin(np.where(finite, costs, np.inf)))
        # A clear minimum: well below the typical cost, and not at the end of the grid.
        if k in (0, len(_SCALE_GRID_M) - 1) or costs[k] >= 0.6 * np.median(costs[finite]):
            return None
        x = np.array([math.log(_SCALE_GRID_M[k]), 0.0, 0.0])
        best = costs[k]

    def trial(x: np.ndarray, d: int, sign: float) -> np.ndarray:
        out = x.copy()
        out[d] += sign * step[d]
        return out

    for _ in range(_PATTERN_ROUNDS):
        improved = True
        while improved:
            improved = False
            for d in range(3):
                # Both signs at once; when +1 improves, the -1 one was spare work of the other thread.
                prefetch([trial(x, d, 1.0), trial(x, d, -1.0)])
                for sign in (1.0, -1.0):
                    cand = trial(x, d, sign)
                    ct = cost(cand)
                    if ct < best:
                        x, best, improved = cand, ct, True
        step /= 2
    return math.exp(x[0]), normal(x), float(best / np.median(costs[finite]))


def _photometric_inputs(images: tuple[torch.Tensor, torch.Tensor], road_scores: np.ndarray | None, K: np.ndarray,
                        n_g: np.ndarray, height: float, params: MonoParams,
                        rng: np.random.Generator,
                        ignore: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The grey images (current, previous) and ground pixels (N, 2) of :func:`_photometric_ground`.

    The pixels are every second pixel that is road (``road_scores``: (10, H, W) class scores)
    or, without them, every second pixel of the road region ahead, less the ``ignore`` (H, W) pixels;
    at most ``photometric_pixels`` of them (a seeded subset drawn from ``rng``). They depend on the
    images, the semantics and the camera only, not on the flow.
    """
    H, W = images[0].shape[-2:]
    if road_scores is not None:
        dense_2 = np.argmax(road_scores[:, ::2, ::2], axis=0) == _ROAD_CLASS
    else:
        dense_2 = np.ones(((H + 1) // 2, (W + 1) // 2), dtype=bool)
    vv, uu = np.nonzero(dense_2)  # every second pixel
    pts = np.c_[uu * 2, vv * 2].astype(np.float64)
    pts = pts[_ground_candidates(K, n_g, height, pts, params, lateral=road_scores is None)]
    if ignore is not None:
        pts = pts[~ignore[pts[:, 1].astype(np.int64), pts[:, 0].astype(np.int64)]]
    if len(pts) > params.photometric_pixels:
        pts = pts[np.sort(rng.choice(len(pts), size=params.photometric_pixels, replace=False))]
    return _grey(images[0]), _grey(images[1]), pts


def _photometric_estimate(found: tuple[float, np.ndarray, float], R: np.ndarray, t: np.ndarray, n_g: np.ndarray,
                          head: str, pixels: str, inlier_ratio: float, note: str = "") -> MotionEstimate:
    """The estimate from a :func:`_photometric_ground` result; ``head``, ``pixels``, ``note`` word its reason."""
    scale, normal, contrast = found
    motion = Motion(torch.from_numpy(np.ascontiguousarray(R)), torch.from_numpy(scale * t))
    reason = (f"{head}, scale photometric from {pixels}, contrast {contrast:.2f}, "
              f"normal tilt {_tilt_deg(normal, n_g):.1f} deg)")
    if note:
        reason += f" ({note})"
    return MotionEstimate(motion, False, reason, inlier_ratio, ground_normal=torch.from_numpy(normal),
                          scale_from="photometric")


def _road_marks_estimate(fit: RoadMarksFit, R: np.ndarray, t_essential: np.ndarray, head: str, pixels: str,
                         inlier_ratio: float, note: str) -> MotionEstimate:
    """The estimate from a :func:`~monostixels.inputs.road_marks.road_marks_scale` fit: its length and
    travel direction (the essential matrix's rotation); ``head``, ``pixels``, ``note`` word its reason."""
    turn = math.degrees(math.acos(float(np.clip(fit.t @ t_essential, -1.0, 1.0))))
    motion = Motion(torch.from_numpy(np.ascontiguousarray(R)), torch.from_numpy(fit.scale * fit.t))
    reason = (f"{head}, scale from the road marks ({fit.pixels} mark pixels of {pixels}), cost {fit.ratio:.2f} of "
              f"no translation, direction turned {turn:.1f} deg)")
    if note:
        reason += f" ({note})"
    return MotionEstimate(motion, False, reason, inlier_ratio, ground_normal=torch.from_numpy(fit.normal),
                          scale_from="road_marks")


def estimate_mono(
    K: torch.Tensor,
    height: float,
    ground_normal: torch.Tensor,
    flow: torch.Tensor,
    cov: torch.Tensor | None,
    params: MonoParams,
    semantic: torch.Tensor | None = None,
    images: tuple[torch.Tensor, torch.Tensor] | None = None,
    prior: MotionEstimate | None = None,
    interval_ratio: float = 1.0,
    ignore: torch.Tensor | None = None,
) -> MotionEstimate:
    """Monocular camera motion from dense flow (see the module docstring for the method).

    Args:
        K: (3, 3) intrinsics, pixels.
        height: camera height above the road (metres) — fixes the metric scale.
        ground_normal: (3,) unit ground normal in the current camera (points down).
        flow: (2, H, W) current -> previous, pixels.
        cov: (H, W, 2, 2) flow covariance, pixels^2, or None (all vectors used).
        params: estimator parameters.
        semantic: (10, H, W) class scores or None.
        images: (current, previous) (3, H, W) RGB in [0, 1], for the photometric scale (step 4a);
            None: the scale from the flow of the ground only.
        prior: a stream's last estimate (:mod:`monostixels.stream`, ``stream.motion_warm_start``), the
            start of this one at constant velocity: its motion (rotation angle and translation scaled
            by ``interval_ratio``, this pair's interval over its) replaces the essential matrix's
            RANSAC when its Sampson inliers make at least 90 % of its own inlier ratio (then refined
            as RANSAC's would be), and the photometric search starts from its scale and road normal
            (see :func:`_photometric_ground`). Where either test fails, that step runs from scratch.
            None: from scratch.
        interval_ratio: see ``prior``.
        ignore: (H, W) bool pixels to leave out (a bonnet, :mod:`monostixels.static_regions`), or None.

    Returns:
        A :class:`MotionEstimate` (metres).
    """
    check_shape(flow, [2, "H", "W"], "flow")
    flow_np = flow.detach().cpu().numpy()
    if not np.isfinite(flow_np).all():  # numpy's test is ~15x faster; check_finite words the error
        check_finite(flow, "flow")
    _, H, W = flow.shape
    if cov is not None:
        check_shape(cov, [H, W, 2, 2], "flow covariance")
    if semantic is not None:
        check_shape(semantic, [NUM_CLASSES, H, W], "semantic scores")
    ignore_np = None
    if ignore is not None:
        check_shape(ignore, [H, W], "ignore mask")
        ignore_np = ignore.bool().numpy()
    Kn = K.double().numpy()
    n_g = ground_normal.double().numpy()
    rng = np.random.default_rng(params.seed)

    # 1. Grid of usable vectors.
    off = params.step // 2
    vs, us = np.meshgrid(np.arange(off, H, params.step), np.arange(off, W, params.step), indexing="ij")
    us, vs = us.ravel(), vs.ravel()
    f = flow_np[:, vs, us].astype(np.float64).T  # N x 2; gathered before the (exact) conversion
    ok = np.ones(len(us), dtype=bool) if ignore_np is None else ~ignore_np[vs, us]
    if cov is not None:
        ok &= _max_eigenvalue_at_most(cov.detach().cpu().numpy()[vs, us], params.max_flow_sigma**2)
    labels = None
    if semantic is not None:
        # Class argmax where it is read: on the vector grid and on every second pixel (the
        # photometric ground pixels). numpy's argmax over the leading axis is ~3x faster than
        # torch's; both take the first maximum.
        sem_np = semantic.detach().numpy()
        labels = np.argmax(sem_np[:, off::params.step, off::params.step], axis=0).ravel()
        ctype = np.asarray(CLASS_TYPE)[labels]
        ok &= (ctype != DYNAMIC_OBJECT) & (ctype != SKY)
    p_cur = np.c_[us, vs].astype(np.float64)
    p_prev = p_cur + f
    # The flow must land inside the previous image.
    ok &= (p_prev[:, 0] >= 0) & (p_prev[:, 0] <= W - 1) & (p_prev[:, 1] >= 0) & (p_prev[:, 1] <= H - 1)
    if ok.sum() < params.min_points:
        return MotionEstimate(None, False, f"too few usable flow vectors: {int(ok.sum())} < {params.min_points}", 0.0,
                              kind="unknown")
    idx = np.nonzero(ok)[0]
    if len(idx) > params.max_points:
        idx = np.sort(rng.choice(idx, size=params.max_points, replace=False))
    pc, pp = p_cur[idx], p_prev[idx]
    road = labels is not None and (labels[idx] == _ROAD_CLASS).sum() >= params.min_points
    photometric = images is not None and params.photometric_scale
    # The photometric search's inputs need no flow: made in a second thread during steps 2-3
    # (single-threaded). ``rng`` is that thread's alone until it is joined: steps 2-3 draw nothing.
    prep = (helper_pool("photometric-inputs").submit(_photometric_inputs, images, sem_np if road else None, Kn, n_g,
                                                     height, params, rng, ignore_np)
            if photometric else None)
    try:
        return _mono_from_vectors(Kn, n_g, height, params, rng, H, W, ok, labels, idx, p_cur, p_prev, road, prep,
                                  _prediction(prior, interval_ratio))
    finally:
        if prep is not None:
            wait([prep])  # its thread draws from ``rng``: done before this estimate returns


@dataclass
class _Prediction:
    """A stream's constant-velocity prediction of a pair's motion: rotation, unit translation, its
    length (m), the road normal in the current camera (or None) and the last pair's inlier ratio."""

    R: np.ndarray
    t_unit: np.ndarray
    scale: float
    normal: np.ndarray | None
    inlier_ratio: float


def _prediction(prior: MotionEstimate | None, ratio: float) -> _Prediction | None:
    """The last pair's motion carried over ``ratio`` times its interval (rotation angle and translation
    scaled; the road normal turned into the current camera, ``n_cur = R^T n_prev``), or None."""
    if prior is None or prior.motion is None or prior.degenerate or not (ratio > 0 and math.isfinite(ratio)):
        return None
    from scipy.spatial.transform import Rotation

    R = prior.motion.R.double().numpy()
    t = prior.motion.t.double().numpy() * ratio
    s = float(np.linalg.norm(t))
    if s <= 0:
        return None
    if ratio != 1.0:
        R = Rotation.from_rotvec(Rotation.from_matrix(R).as_rotvec() * ratio).as_matrix()
    n = None
    if prior.ground_normal is not None:
        n = R.T @ prior.ground_normal.double().numpy()
        n = n / np.linalg.norm(n)
    return _Prediction(R, t / s, s, n, float(prior.inlier_ratio))


def _cheirality_sign(R: np.ndarray, t: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """+1 if ``(R, t)`` puts more of the ray pairs (current ``a``, previous ``b``, (N, 3)) in front of both
    cameras than ``(R, -t)``, else -1. Depths from ``λ_a R a + t = λ_b b``: ``λ_a = -(b × t)·(b × Ra) /
    |b × Ra|²``, ``λ_b = (Ra × t)·(Ra × b) / |Ra × b|²`` (both change sign with ``t``)."""
    Ra = a @ R.T
    bra = np.cross(b, Ra)
    den = np.maximum(np.einsum("ij,ij->i", bra, bra), 1e-30)
    lam_a = -np.einsum("ij,ij->i", np.cross(b, t[None]), bra) / den
    lam_b = -np.einsum("ij,ij->i", np.cross(Ra, t[None]), bra) / den
    front = int(np.count_nonzero((lam_a > 0) & (lam_b > 0)))
    behind = int(np.count_nonzero((lam_a < 0) & (lam_b < 0)))
    return 1.0 if front >= behind else -1.0


#: Warm start of the essential matrix: the prediction replaces RANSAC when, within this many times the
#: RANSAC threshold (Sampson distance), it explains at least the given share of the vectors the last pair's
#: estimate explained (a sudden turn or a mover taking the view fails it). A prediction is not exact (yaw
#: changes by hundredths of a degree from pair to pair: on KITTI raw ~45-75 % of the vectors lie within
#: 0.5 px of it, ~97 % within 2 px); its inliers within 2 px start the refinement RANSAC's would.
_WARM_SEED_FACTOR = 4.0
_WARM_MIN_INLIER_SHARE = 0.9


def _mono_from_vectors(Kn: np.ndarray, n_g: np.ndarray, height: float, params: MonoParams, rng: np.random.Generator,
                       H: int, W: int, ok: np.ndarray, labels: np.ndarray | None, idx: np.ndarray, p_cur: np.ndarray,
                       p_prev: np.ndarray, road: bool, prep: Any, pred: _Prediction | None = None) -> MotionEstimate:
    """Steps 2-4 of :func:`estimate_mono` on the grid of usable vectors (``ok``, the subset ``idx``);
    ``prep``: the future of :func:`_photometric_inputs`, or None without the photometric search;
    ``pred``: a stream's prediction (:func:`_prediction`) to start from, or None."""
    pc, pp = p_cur[idx], p_prev[idx]

    # 2. Degeneracy: does a rotation alone explain the flow?
    R0, res0 = _fit_rotation(Kn, pc, pp)
    parallax = float(np.median(res0))
    if parallax < params.min_parallax:
        still = float(np.median(np.linalg.norm(pp - pc, axis=1))) < params.min_parallax
        kind = "standing still" if still else "pure rotation"
        inl = float((res0 < params.ransac_threshold * 2).mean())
        reason = f"no translation ({kind}): median parallax {parallax:.2f} px < {params.min_parallax} px"
        return MotionEstimate(Motion(torch.from_numpy(R0), torch.zeros(3, dtype=torch.float64)), True, reason, inl,
                              kind="standing")

    # 3. Essential matrix (points1 = current, points2 = previous: X_prev = R X_cur + t).
    a_all, b_all = _rays(Kn, pc), _rays(Kn, pp)
    f_scale = params.ransac_threshold / Kn[0, 0]  # pixels -> normalised image units
    warm = False
    if pred is not None:
        # A stream's prediction in place of RANSAC where it explains as many vectors as the last pair did.
        inl = np.abs(_sampson(_skew(pred.t_unit) @ pred.R, a_all, b_all)) < _WARM_SEED_FACTOR * f_scale
        warm = inl.sum() >= params.min_points and inl.mean() >= _WARM_MIN_INLIER_SHARE * pred.inlier_ratio
        # The epipolar constraint holds for -t as well: the sign is the one that puts the points in front
        # of both cameras (recoverPose's cheirality test), the prediction's where it does (a camera that
        # reverses does not).
        R, t = pred.R, pred.t_unit * _cheirality_sign(pred.R, pred.t_unit, a_all[inl], b_all[inl])
    if not warm:
        try:
            E, mask = cv2.findEssentialMat(pc, pp, Kn, method=cv2.RANSAC, prob=params.ransac_confidence,
                                           threshold=params.ransac_threshold)
            if E is None or E.shape != (3, 3):
                return MotionEstimate(None, False, "essential matrix: RANSAC found no model", 0.0,
                                      kind="unknown")
            _, R, t, mask = cv2.recoverPose(E, pc, pp, Kn, mask=mask.copy())
        except cv2.error as err:
            # The 5-point solver asserts on some near-degenerate samples (a zero leading coefficient in
            # solvePoly: seen after ~200 frames of a soak): a failed estimate of this pair, not a crash.
            first = str(err).strip().splitlines()[-1] if str(err).strip() else type(err).__name__
            return MotionEstimate(None, False, f"essential matrix: OpenCV failed on these vectors ({first})", 0.0,
                                  kind="unknown")
        inl = mask.ravel() > 0
        if inl.sum() < params.min_points:
            return MotionEstimate(None, False, f"essential matrix: only {int(inl.sum())} inliers", float(inl.mean()),
                                  kind="unknown")
        t = t.ravel()
    # Refine, then re-select inliers with the refined model (the RANSAC set is from a 5-point
    # hypothesis and misses good vectors), and refine once more on them.
    for _ in range(2):
        R, t = _refine_pose(R, t, a_all[inl], b_all[inl], f_scale=f_scale)
        inl = np.abs(_sampson(_skew(t) @ R, a_all, b_all)) < f_scale
        if inl.sum() < params.min_points:
            return MotionEstimate(None, False, f"essential matrix: only {int(inl.sum())} inliers after refinement",
                                  float(inl.mean()), kind="unknown")
    inlier_ratio = float(inl.mean())

    # 4. Metric scale (and road normal) from the ground.
    head = (f"ok: {int(inl.sum())}/{len(inl)} essential-matrix inliers{' (warm start)' if warm else ''}, "
            f"median parallax {parallax:.1f} px")
    src = "road pixels" if road else "road region ahead"
    failures = []
    found = None
    marks = None
    refine_weak = False
    if prep is not None:
        grey_cur, grey_prev, pts = prep.result()
        pixels = f"{len(pts)} ground pixels ({src}"
        if len(pts) >= params.min_points:
            # Warm: from the predicted length of this t (the sign of t is RANSAC's or the prediction's).
            start = None
            if warm and pred.normal is not None and float(t @ pred.t_unit) > 0:
                start = (pred.scale, pred.normal)
            # Warm, a grid minimum far from sharp is not refined: the pattern search lowered the contrast by
            # at most 18 % on the KITTI raw drives (0.30 -> 0.25), never from above sharp / 0.7.
            found = _photometric_ground(grey_cur, grey_prev, Kn, R, t, n_g, height, pts, params.ground_max_tilt, start,
                                        unsharp=params.photometric_sharp / _PATTERN_MAX_GAIN)
            refine_weak = start is not None
        if found is None:
            failures.append(f"photometric: no clear minimum over {pixels})")
        elif found[2] <= params.photometric_sharp:
            return _photometric_estimate(found, R, t, n_g, head, pixels, inlier_ratio)
        else:
            failures.append(f"photometric minimum not sharp: contrast {found[2]:.2f} > {params.photometric_sharp}")
        if params.road_marks and len(pts) >= params.min_points:
            # Its own generator: the ground-flow RANSAC below draws the same numbers with or without it.
            marks = road_marks_scale(grey_cur, grey_prev, Kn, R, t, n_g, height, pts, np.random.default_rng(params.seed),
                                     start=pred.scale if warm else None)
            if marks is None:
                failures.append(f"road marks: no clear alignment over {pixels})")
    # The flow of the ground: the corridor ahead first; with road labels, the whole road if a
    # vehicle blocks the corridor.
    base = ((labels == _ROAD_CLASS) & ok) if road else ok
    for lateral in ((True, False) if road else (True,)):
        gidx = np.nonzero(base & _ground_candidates(Kn, n_g, height, p_cur, params, lateral=lateral))[0]
        if len(gidx) < params.min_points:
            failures.append(f"{len(gidx)} ground vectors ({src}) < {params.min_points}")
            continue
        A, bb = _ground_system(Kn, R, t, p_cur[gidx], p_prev[gidx])
        m, ginl = _fit_ground(A, bb, params.ground_threshold, rng, n_g=n_g, max_tilt=params.ground_max_tilt)
        q = float(np.linalg.norm(m))
        tilt = _tilt_deg(m, n_g)
        if q > 0 and tilt <= params.ground_max_tilt and ginl.sum() >= params.min_points:
            break
        if ginl.sum() < params.min_points:
            failures.append(f"{int(ginl.sum())} ground vectors ({src}) fit a plane (< {params.min_points})")
        else:
            failures.append(f"ground fit normal {tilt:.1f} deg from camera.ground_normal (> {params.ground_max_tilt})")
    else:
        if marks is not None:
            return _road_marks_estimate(marks, R, t, head, pixels, inlier_ratio, "; ".join(failures))
        if found is not None:  # a weak photometric minimum is still better than none
            if refine_weak:  # warm, it may not have been refined: the search from scratch
                found = _photometric_ground(grey_cur, grey_prev, Kn, R, t, n_g, height, pts, params.ground_max_tilt) or found
            return _photometric_estimate(found, R, t, n_g, head, pixels, inlier_ratio, note="; ".join(failures))
        # The camera moves and its direction is known; only the length of t is not (a sequence may supply it).
        unit = Motion(torch.from_numpy(np.ascontiguousarray(R)), torch.from_numpy(np.ascontiguousarray(t)))
        return MotionEstimate(None, False, "no metric scale: " + "; ".join(failures), inlier_ratio,
                              kind="scale_unknown", unit_motion=unit)
    scale = height * q
    if marks is not None and scale < FLOW_SHORT_RATIO * marks.scale:
        # The flow of textureless asphalt errs short (pulled towards zero), not long: well short of the
        # marks' length, it is the flow that failed.
        failures.append(f"{int(ginl.sum())} ground vectors give {scale:.3f} m, short of the marks' {marks.scale:.3f} m")
        return _road_marks_estimate(marks, R, t, head, pixels, inlier_ratio, "; ".join(failures))
    motion = Motion(torch.from_numpy(np.ascontiguousarray(R)), torch.from_numpy(scale * t))
    reason = f"{head}, scale from {int(ginl.sum())} ground vectors ({src}, normal tilt {tilt:.1f} deg)"
    if failures:
        reason += f" ({'; '.join(failures)})"
    normal = torch.from_numpy(np.ascontiguousarray(m / q))
    return MotionEstimate(motion, False, reason, inlier_ratio, ground_normal=normal, scale_from="ground_flow")


def estimate_motion(pair: FramePair, flow: Any, cfg: Any, semantic: torch.Tensor | None = None, *,
                    prior: MotionEstimate | None = None, interval_ratio: float = 1.0) -> MotionEstimate:
    """Camera motion of a frame pair with the backend ``cfg.name`` (gt | file | mono).

    Args:
        pair: the frame pair (camera intrinsics, height and ground normal; ``motion`` for gt;
            ``meta["frame_index"]`` / ``["frame_index_prev"]`` for file).
        flow: the :class:`~monostixels.inputs.flow.FlowResult` of the pair (used by mono).
        cfg: the ``motion`` config group node.
        semantic: (10, H, W) class scores or None.
        prior: the last pair's estimate of a stream, the start of ``mono`` (see :func:`estimate_mono`);
            None = from scratch. ``gt`` and ``file`` do not read it.
        interval_ratio: this pair's time interval over the last pair's (the prior's translation scales with it).

    Returns:
        A :class:`MotionEstimate`.
    """
    name = str(_get(cfg, "name", ""))
    if name == "gt":
        return _gt_motion(pair)
    if name == "file":
        return _file_motion(pair, cfg)
    if name == "mono":
        if flow is None:
            raise InputError("motion=mono: needs the flow of the pair (flow is None)")
        check_shape(flow.flow, [2, *pair.size], "flow")
        return estimate_mono(
            pair.camera.K, pair.camera.height, pair.camera.ground_normal, flow.flow, flow.cov, _mono_params(cfg), semantic,
            images=(pair.image, pair.image_prev), prior=prior, interval_ratio=interval_ratio,
            ignore=pair.meta.get("ignore_pixels"),
        )
    raise InputError(f"motion.name: unknown motion backend {name!r}, expected one of {MOTION_BACKENDS}")


def implied_height(pair: FramePair, flow: Any, mono_cfg: Any, semantic: torch.Tensor | None,
                   given: Motion) -> float | None:
    """The camera height (metres) that the road implies, given a metric camera motion from elsewhere.

    The monocular scale is ``camera.height`` times what the road's motion says (:func:`estimate_mono`):
    run with the pair's ``camera.height`` against a translation of known length (``motion=gt`` / ``file``),
    the height that would have made the two agree is ``height * |t_given| / |t_mono|``. None where the
    road gives no scale, the pair has no translation, or the two directions disagree (more than 10 deg).
    ``mono_cfg``: the settings of the estimate (the ``motion=mono`` config group).
    """
    if given.translation_norm < MIN_TRANSLATION_M or flow is None:
        return None
    est = estimate_mono(pair.camera.K, pair.camera.height, pair.camera.ground_normal, flow.flow, flow.cov,
                        _mono_params(mono_cfg), semantic, images=(pair.image, pair.image_prev),
                        ignore=pair.meta.get("ignore_pixels"))
    if est.motion is None or est.degenerate or est.scale_from not in ("photometric", "road_marks", "ground_flow"):
        return None
    if _angle_deg(est.motion.t.double(), given.t.double()) > 10.0:
        return None
    return float(pair.camera.height * given.translation_norm / float(est.motion.t.norm()))


# ----------------------------------------------------------------------------------------------
# sequence prior


@dataclass
class TrackParams:
    """Constant-velocity prior of :class:`MotionTrack` (keys of the ``motion`` config group).

    Attributes:
        sequence_prior: filter the metric scale over consecutive pairs (``mono`` only).
        speed_process_std: relative change of speed per second allowed by the model (1/s, std):
            0.3 = 30 %/s, i.e. 2.7 m/s^2 at 9 m/s (braking or accelerating firmly), 3 % per KITTI frame.
        scale_meas_std: relative error (std) of one pair's monocular scale (KITTI raw: 2-5 %).
        scale_gate: a pair's scale farther than this many innovation standard deviations from the
            prediction is an outlier and replaced by the prediction. The next pair's scale, again an
            outlier but within this many standard deviations of the first one, restarts the track at it
            (the track, not the pairs, was wrong: a first pair far off held every later pair out).
        normal_process_std_deg: how fast the road normal may turn in the camera (degrees per
            square-root second: a random walk; pitching on bumps, a change of slope).
        normal_meas_std_deg: error (std, degrees) of one pair's fitted road normal (KITTI raw drive
            0023: consecutive fits differ by 0.3-2 degrees).
        normal_gate_deg: a fit farther than this from the prediction (degrees, beyond its innovation
            std) is an outlier and the prediction stands. 0 = no normal filter.
        scale_hold_s: a pair whose translation direction is known but not its length
            (``scale_unknown``) takes the filtered speed of the pairs before it, for at most this many
            seconds after the last pair with a measured scale (a car's speed changes slowly); later, or
            without such pairs, it stays ``scale_unknown``. 0 = never.
    """

    sequence_prior: bool = True
    speed_process_std: float = 0.3
    scale_meas_std: float = 0.04
    scale_gate: float = 2.0
    normal_process_std_deg: float = 0.3
    normal_meas_std_deg: float = 0.5
    normal_gate_deg: float = 3.0
    scale_hold_s: float = 2.0


class MotionTrack:
    """Steadies the metric scale and the road normal of monocular ego-motion over a sequence.

    Scale: the state is the log speed ``log(|t| / dt)`` (dt seconds between the frames,
    ``meta["dt"]``; 1 per pair when unknown) with its variance. Per pair: predict (constant velocity,
    variance grows by ``(speed_process_std dt)^2``), gate the new measurement, update. Only the
    length of ``t`` changes (direction and rotation are the pair's own: with ~20 px parallax they are
    already steady, 0.3-0.6 deg on KITTI raw).

    Road normal (the plane the ground stixels lie on, ``ground_normal``): the filtered normal of the
    pair's earlier frame, turned into the current camera (``n_cur = R^T n_prev``), is the prediction
    (variance grows by ``normal_process_std_deg^2 dt``); the pair's fit updates it (isotropic, in
    radians on the unit sphere). One fit's error moves far ground by ``z / h`` times the angle (0.3
    degrees: 6 % at 20 m), so the filter steadies the ground's depth from frame to frame.

    Pairs continue the track when they come from the same ``meta["sequence"]`` in time order: this
    pair's current frame after the last one, its earlier frame not after it (a keyframe pair may reach
    back several frames); anything else (another sequence, a jump, a degenerate or failed pair)
    restarts the track.

    Args:
        params: the prior's parameters.
    """

    def __init__(self, params: TrackParams | None = None) -> None:
        self.params = params or TrackParams()
        self._key: tuple | None = None
        self._x = 0.0  # log speed
        self._var = math.inf
        self._rejected: float | None = None  # log speed of the last pair, where it was an outlier
        self._normals: dict[Any, tuple[torch.Tensor, float]] = {}  # frame -> (filtered normal, variance rad^2)
        self._held_s = 0.0  # seconds since the last pair with a measured scale

    @staticmethod
    def from_config(cfg: Any) -> "MotionTrack":
        d = TrackParams()
        kw = {k: type(getattr(d, k))(_get(cfg, k, getattr(d, k))) for k in d.__dataclass_fields__}
        return MotionTrack(TrackParams(**kw))

    def reset(self) -> None:
        self._key, self._x, self._var = None, 0.0, math.inf
        self._rejected = None
        self._normals = {}
        self._held_s = 0.0

    def update(self, pair: FramePair, est: MotionEstimate) -> MotionEstimate:
        """The estimate of ``pair`` with its scale and road normal filtered by the sequence so far (and the state advanced)."""
        prm = self.params
        seq, cur, prev = pair.meta.get("sequence"), pair.meta.get("frame"), pair.meta.get("frame_prev")
        consecutive = (seq is not None and cur is not None and prev is not None and self._key is not None
                       and self._key[0] == seq and prev <= self._key[1] < cur and math.isfinite(self._var))
        dt = float(pair.meta.get("dt") or 1.0)
        if est.kind == "scale_unknown" and est.unit_motion is not None and consecutive:
            if self._held_s + dt <= prm.scale_hold_s:
                return self._hold(est, cur, prev, dt)
        if est.motion is None or est.degenerate or seq is None or cur is None:
            self.reset()
            return est
        norm = float(est.motion.t.norm())
        if norm <= 0:
            self.reset()
            return est
        est = self._filter_normal(est, cur, prev if consecutive else None, dt)
        self._held_s = 0.0
        z = math.log(norm / dt)
        r = prm.scale_meas_std**2
        self._key = (seq, cur)
        if not consecutive:
            self._x, self._var, self._rejected = z, r, None
            return est
        x_pred = self._x
        p_pred = self._var + (prm.speed_process_std * dt) ** 2
        innov = z - x_pred
        s = p_pred + r
        last, self._rejected = self._rejected, None
        if abs(innov) > prm.scale_gate * math.sqrt(s):
            # Two outliers in a row that agree with each other (two pairs' errors and the speed change
            # between them): the track was off, not the pairs; it restarts at this one. (Without this,
            # a first pair 8 % long held a slowing car's pairs out for the whole drive: their
            # innovations grew faster than the prediction's variance.)
            if last is not None and abs(z - last) <= prm.scale_gate * math.sqrt(2 * r + (prm.speed_process_std * dt) ** 2):
                self._x, self._var = z, r
                note = (f"sequence prior: scale {norm:.3f} m is {innov * 100:+.0f} % from the constant-velocity "
                        f"prediction, the second such pair in a row and consistent with the first: the speed restarts at it")
            else:
                # An outlier: keep the prediction (its variance grows).
                self._x, self._var, self._rejected = x_pred, p_pred, z
                note = (f"sequence prior: scale {norm:.3f} m is {innov * 100:+.0f} % from the constant-velocity "
                        f"prediction, replaced by {math.exp(x_pred) * dt:.3f} m")
                # The length is the sequence's now, not the pair's own measurement.
                est = dataclasses.replace(est, scale_from="sequence")
        else:
            k = p_pred / s
            self._x, self._var = x_pred + k * innov, (1 - k) * p_pred
            note = f"sequence prior: scale {norm:.3f} -> {math.exp(self._x) * dt:.3f} m"
        t_new = est.motion.t * (math.exp(self._x) * dt / norm)
        logger.debug("%s: %s", pair.name, note)
        return dataclasses.replace(est, motion=Motion(est.motion.R, t_new), reason=f"{est.reason}; {note}")


    def _hold(self, est: MotionEstimate, cur: Any, prev: Any, dt: float) -> MotionEstimate:
        """A ``scale_unknown`` pair made metric by the filtered speed (predicted, not updated: its variance
        grows) and, where the earlier frame has one, the filtered road normal turned into this camera."""
        prm = self.params
        self._var += (prm.speed_process_std * dt) ** 2
        self._held_s += dt
        self._key = (self._key[0], cur)
        self._rejected = None
        R, t_unit = est.unit_motion.R, est.unit_motion.t
        length = math.exp(self._x) * dt
        normal = None
        old = self._normals.get(prev)
        if old is not None:
            n = R.double().T @ old[0]
            normal = n / n.norm()
            var = old[1] + math.radians(prm.normal_process_std_deg) ** 2 * dt
            self._normals = {f: v for f, v in self._normals.items() if f >= prev} | {cur: (normal, var)}
        note = (f"scale from the sequence: {length:.3f} m ({math.exp(self._x):.1f} m/s, "
                f"{self._held_s:.2f} s since the last measured scale)")
        logger.debug("%s", note)
        return dataclasses.replace(est, motion=Motion(R, t_unit / t_unit.norm() * length), kind="metric",
                                   scale_from="sequence", ground_normal=normal, reason=f"{est.reason}; {note}")

    def _filter_normal(self, est: MotionEstimate, cur: Any, prev: Any, dt: float) -> MotionEstimate:
        """``est`` with its road normal fused with the one of frame ``prev`` (None: restart)."""
        prm = self.params
        n_m = est.ground_normal
        if n_m is None or prm.normal_gate_deg <= 0:
            return est
        n_m = n_m.double() / n_m.double().norm()
        r = math.radians(prm.normal_meas_std_deg) ** 2
        old = self._normals.get(prev) if prev is not None else None
        if old is None:
            self._normals = {cur: (n_m, r)}
            return est
        n_prev, var = old
        n_pred = est.motion.R.double().T @ n_prev  # a direction in the earlier camera, seen from the current one
        var_pred = var + math.radians(prm.normal_process_std_deg) ** 2 * dt
        innov = math.acos(max(-1.0, min(1.0, float(n_pred @ n_m))))
        if innov > math.radians(prm.normal_gate_deg) + 3.0 * math.sqrt(var_pred + r):
            n_new, var_new = n_pred, var_pred
        else:
            k = var_pred / (var_pred + r)
            n_new = n_pred + k * (n_m - n_pred)
            n_new, var_new = n_new / n_new.norm(), (1.0 - k) * var_pred
        # Kept: the frames from this pair's earlier frame on. A keyframe pair reaching back past them (pairs
        # (3, 1), (4, 2), ...) starts the normal again at its own fit, which matches its own scale (the two
        # trade off in the photometric search); continuing the filter over such pairs raised the depth
        # jitter on every synthetic clip set (docs/experiments.md, "Ego-motion").
        self._normals = {f: v for f, v in self._normals.items() if f >= prev} | {cur: (n_new, var_new)}
        return dataclasses.replace(est, ground_normal=n_new.to(est.ground_normal.dtype))


def _angle_deg(a: torch.Tensor, b: torch.Tensor) -> float:
    """Angle (degrees) between two vectors; NaN if either is zero."""
    na, nb = float(a.norm()), float(b.norm())
    if na <= 0 or nb <= 0:
        return math.nan
    return math.degrees(math.acos(max(-1.0, min(1.0, float((a @ b) / (na * nb))))))


def motion_errors(est: Motion, gt: Motion) -> dict[str, float]:
    """Errors of an estimated camera motion against ground truth.

    Returns:
        ``rot_err_deg``: angle of ``R_est R_gt^T`` (degrees); ``trans_dir_err_deg``: angle between
        the translations (degrees; NaN if either is zero); ``trans_dir_err_xz_deg``: the same for
        their horizontal parts ``(t_x, t_z)`` (camera x right, z forward; for ground truth whose
        vertical component drifts, e.g. the poses of KITTI odometry sequence 08); ``scale_rel_err``:
        ``|‖t‖/‖t_gt‖ - 1|`` (NaN if ``t_gt = 0``).
    """
    Rd = est.R.double() @ gt.R.double().T
    # ||R - I||_F = 2 sqrt(2) sin(theta / 2): accurate for small angles, unlike acos of the trace.
    s = float(torch.linalg.norm(Rd - torch.eye(3, dtype=Rd.dtype))) / (2.0 * math.sqrt(2.0))
    rot = math.degrees(2.0 * math.asin(min(1.0, s)))
    te, tg = est.t.double(), gt.t.double()
    ne, ng = float(te.norm()), float(tg.norm())
    tdir = _angle_deg(te, tg)
    tdir_xz = _angle_deg(te[[0, 2]], tg[[0, 2]])
    scale = abs(ne / ng - 1.0) if ng > 0 else math.nan
    return {"rot_err_deg": rot, "trans_dir_err_deg": tdir, "trans_dir_err_xz_deg": tdir_xz, "scale_rel_err": scale}
