"""Camera motion (config group ``motion``): ground truth, a poses file, or monocular estimation.

Convention (docs/conventions.md, section 2): the motion ``(R, t)`` of a frame pair maps
current-camera coordinates of a static point to previous-camera coordinates,
``X_prev = R X_cur + t``, metres; flow maps current to previous pixels, ``x_prev = x + f``.

Backends (``cfg.name``):

- ``gt``: ``pair.motion`` from the data source.
- ``file``: a KITTI-style poses file (``cfg.path``, read by
  :func:`monostixels.data._camera_files.read_poses_file`): per line either 12 numbers (the 3x4 row-major
  ``T_w_cam``, camera to world, metres; line ``i`` = frame ``i``), a frame number followed by the
  12 numbers, or the 16 numbers of the 4x4 matrix. Frames are ``pair.info.frame_index`` (current) and
  ``pair.info.frame_index_prev`` (or ``frame`` / ``frame_prev``, as kitti_raw writes them). ``cfg.offset`` (3,) is the position of the image camera
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
     The sign of ``t`` then comes from the road where its flow says it clearly: the road's plane lies
     below the camera (normal pointing down) under the true direction and above it under the reversed
     one (:func:`~monostixels.inputs.ground.road_sign_votes`). The cheirality test counts every
     likely-static vector, and a truck beside the camera that the semantic net calls a building and
     that pulls ahead outvotes the scene; the road does not move.
  4. Metric scale from the ground: ground pixels (semantic road where given, else the road
     region in front of the car predicted by the camera height and ground normal) move with the
     plane homography ``K (R + t̂ m^T) K^-1`` with ``m = (s / h) n``: ``s`` the metric length of
     ``t``, ``h`` the camera height, ``n`` the ground normal.

     a. Photometric (when the images are given, ``photometric_scale``): the previous image is
        warped onto the current one by the ground homography; a 1-D search over ``s`` then a
        pattern search over ``(s, n)`` minimise the median grey-value difference over the
        ground pixels. The near road moves by up to ~130 px between KITTI-like frames, where
        flow fails; the images themselves do not. Taken when its minimum is sharp
        (``photometric_sharp``); on weakly textured real asphalt it often is not, and steps b and
        c take over.
     b. Road marks (``road_marks``, without a sharp photometric minimum): the same warp over the
        road pixels whose gradient runs along their epipolar line (lane dashes' ends, joints), with
        the road normal at right angles to the travel direction, minimised over the length ``s`` and
        the direction ``t̂`` (:mod:`monostixels.inputs.road_marks`). At highway speed the near road
        moves tens of pixels over textureless asphalt: the flow there is near zero and the whole-road
        search prefers no warp; the marks still fix the scale, and the far scene's essential matrix
        can be degrees off in direction, more than the marks' width at 2 m a pair.
     c. From the flow: ``m`` is linear in the flow equations (RANSAC with the tilt bounded by
        ``ground_max_tilt``, then least squares); ``s = camera.height * |m|``. It is taken unless
        the road marks gave a length and it is shorter than :data:`FLOW_SHORT_RATIO` of theirs:
        the flow of textureless asphalt errs short, pulled towards zero, not long. On a stream (a
        constant-velocity prediction of the length), a flow within :data:`FLOW_NEAR_PREDICTION` of
        the predicted length is not short, and the marks are not read. When the flow finds no plane,
        the road marks are used, else a weak photometric minimum; with neither, no estimate.

     d. The scene model (``scene_scale``, with semantic scores; :mod:`monostixels.inputs.motion_scene`):
        static objects standing on the ground give the length from their flow and their ground
        contacts. It checks the road's length (where the two disagree, the pair's ``scale_std`` is
        their difference) and stands in where the road gives none.

  5. Over a sequence (:class:`monostixels.inputs.motion_track.MotionTrack`, kept by the sequence layer,
     :mod:`monostixels.sequence`, for the consecutive pairs of one sequence): the speed ``|t| / dt`` follows a constant-velocity model, filtered in log space
     (a 1-D Kalman filter, each pair's measurement error its own ``scale_std``); a pair's scale that
     disagrees with a confirmed speed by more than ``scale_gate`` standard deviations is replaced by the
     prediction and marked uncertain by the difference; one that disagrees with a speed never confirmed
     restarts it. A single pair, or the first pair of a sequence, is unchanged.
"""
from __future__ import annotations

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
from monostixels._checks import InputError, check_finite, check_shape, config_params
from monostixels.core.classes import CLASS_TYPE, DYNAMIC_OBJECT, NUM_CLASSES, SKY
from monostixels.data._camera_files import read_poses_file, relative_motion
from monostixels.data.base import FramePair
from monostixels.core.geometry import Motion, angle_deg
from monostixels.inputs.ground import (PATTERN_MAX_GAIN, ROAD_CLASS, fit_ground, ground_candidates, ground_system,
                                       photometric_ground, photometric_inputs, rays, road_sign_votes, tilt_deg,
                                       ROAD_SIGN_SHARE)
from monostixels.inputs.epipolar import (car_offsets_deg, cheirality_sign, fit_rotation, max_eigenvalue_at_most,
                                         refine_car_pose, refine_pose, sampson, skew)
from monostixels.inputs.motion_base import (MIN_TRANSLATION_M, MOTION_BACKENDS, MOTION_KINDS, NO_METRIC_MOTION,
                                            ROAD_SCALES, FileMotionConfig, GtMotionConfig, MonoParams, MotionEstimate,
                                            MotionKind, ScaleFrom)
from monostixels.inputs.motion_scene import scene_scale, with_scene_scale
from monostixels.inputs.motion_track import MonoMotionConfig, motion_params
from monostixels.inputs.road_marks import RoadMarksFit, road_marks_scale

__all__ = [
    "MOTION_BACKENDS",
    "MotionKind",
    "ScaleFrom",
    "MOTION_KINDS",
    "NO_METRIC_MOTION",
    "MIN_TRANSLATION_M",
    "MonoParams",
    "travel_normal",
    "GtMotionConfig",
    "FileMotionConfig",
    "MotionEstimate",
    "estimate_motion",
    "estimate_mono",
    "load_poses",
    "relative_motion",
    "implied_height",
]

logger = logging.getLogger(__name__)


def _mono_params(cfg: Any) -> MonoParams:
    """The estimator's settings of the ``motion`` config node (``motion=mono``; its schema
    :class:`~monostixels.inputs.motion_track.MonoMotionConfig` holds them)."""
    return config_params(MonoMotionConfig, cfg, "motion")


# ----------------------------------------------------------------------------------------------
# gt / file


def _gt_motion(pair: FramePair) -> MotionEstimate:
    if pair.motion is None:
        source = pair.info.source if pair.info.source is not None else pair.name or "this data source"
        raise InputError(f"motion=gt: {source} has no ground-truth camera motion (pair.motion is None); use motion=file or motion=mono")
    return _known(pair.motion, "ground truth")


def _known(motion: Motion, what: str) -> MotionEstimate:
    """A known motion, flagged degenerate when it has no translation to speak of."""
    tn = motion.translation_norm
    if tn < MIN_TRANSLATION_M:
        return MotionEstimate(motion, True, f"no translation ({what}): |t| = {tn:.2e} m < {MIN_TRANSLATION_M} m", 1.0,
                              kind=MotionKind.STANDING)
    return MotionEstimate(motion, False, f"ok ({what})", 1.0, scale_from=ScaleFrom.GIVEN, scale_std=0.0)


@lru_cache(maxsize=8)
def _load_poses_cached(path: str, mtime: float) -> dict[int, np.ndarray]:
    try:
        ids, mats = read_poses_file(path)
    except InputError as exc:
        raise InputError(f"motion.path: {exc}") from None
    if ids is None:
        return {i: T for i, T in enumerate(mats)}
    poses: dict[int, np.ndarray] = {}
    for frame, T in zip(ids, mats):
        try:
            number = float(frame)
        except ValueError:
            number = math.nan
        if not number.is_integer():
            raise InputError(f"motion.path: {path!r}: frame id {frame!r} is not a frame number")
        poses[int(number)] = T
    return poses


def load_poses(path: str | Path) -> dict[int, np.ndarray]:
    """Poses ``T_w_cam`` (4, 4) float64 (camera to world, metres) by frame number from a poses file.

    The formats of :func:`monostixels.data._camera_files.read_poses_file` (12 numbers a line, line ``i`` =
    frame ``i``; a frame number and 12 numbers; 16 numbers), the frame ids being whole numbers.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"motion.path: poses file not found: {str(p)!r}")
    return _load_poses_cached(str(p.resolve()), p.stat().st_mtime)


def _file_motion(pair: FramePair, cfg: FileMotionConfig) -> MotionEstimate:
    path = cfg.path
    poses = load_poses(path)
    # Raw frame numbers: FrameInfo.frame_index / frame_index_prev, else (kitti_raw, videos) frame / frame_prev.
    info = pair.info
    frames = next(((c, p) for c, p in ((info.frame_index, info.frame_index_prev), (info.frame, info.frame_prev))
                   if c is not None and p is not None), None)
    if frames is None:
        raise InputError(
            f"motion=file: frame pair {pair.name!r} has no meta['frame_index'] / ['frame_index_prev'] (or 'frame' / "
            f"'frame_prev') to look up in {str(path)!r}"
        )
    cur, prev = int(frames[0]), int(frames[1])
    for f in (cur, prev):
        if f not in poses:
            raise InputError(f"motion.path: {str(path)!r} has no pose for frame {f} (frames {min(poses)}..{max(poses)})")
    offset = cfg.offset
    off = None if offset is None else np.asarray(offset, dtype=np.float64)
    if off is not None and off.shape != (3,):
        raise InputError(f"motion.offset: expected 3 numbers (metres), got {list(offset)}")
    motion = relative_motion(poses[cur], poses[prev], off)
    return _known(motion, f"poses file, frames {cur} <- {prev}")


# ----------------------------------------------------------------------------------------------
# mono


#: The flow of the ground is taken over the road marks' scale unless it is shorter than this share of it.
FLOW_SHORT_RATIO = 0.7
#: With a stream's constant-velocity prediction, a flow of the ground at least this share of the predicted
#: length is taken without reading the road marks (they would need to say ``FLOW_NEAR_PREDICTION /
#: FLOW_SHORT_RATIO`` = 1.14x the prediction to override it).
FLOW_NEAR_PREDICTION = 0.8

def _photometric_estimate(found: tuple[float, np.ndarray, float], R: np.ndarray, t: np.ndarray, n_g: np.ndarray,
                          head: str, pixels: str, inlier_ratio: float, note: str = "") -> MotionEstimate:
    """The estimate from a :func:`photometric_ground` result; ``head``, ``pixels``, ``note`` word its reason."""
    scale, normal, contrast = found
    motion = Motion(torch.from_numpy(np.ascontiguousarray(R)), torch.from_numpy(scale * t))
    reason = (f"{head}, scale photometric from {pixels}, contrast {contrast:.2f}, "
              f"normal tilt {tilt_deg(normal, n_g):.1f} deg)")
    if note:
        reason += f" ({note})"
    return MotionEstimate(motion, False, reason, inlier_ratio, ground_normal=torch.from_numpy(normal),
                          scale_from=ScaleFrom.PHOTOMETRIC)


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
                          scale_from=ScaleFrom.ROAD_MARKS)


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
        prior: a stream's last estimate (:mod:`monostixels.sequence.stream`, ``stream.motion_warm_start``), the
            start of this one at constant velocity: its motion (rotation angle and translation scaled
            by ``interval_ratio``, this pair's interval over its) replaces the essential matrix's
            RANSAC when its Sampson inliers make at least 90 % of its own inlier ratio (then refined
            as RANSAC's would be), and the photometric search starts from its scale and road normal
            (see :func:`photometric_ground`). Where either test fails, that step runs from scratch.
            None: from scratch.
        interval_ratio: see ``prior``.
        ignore: (H, W) bool pixels to leave out (a bonnet, :mod:`monostixels.data.static_regions`), or None.

    Returns:
        A :class:`MotionEstimate` (metres).
    """
    check_shape(flow, [2, "H", "W"], "flow")
    flow_np = flow.detach().cpu().numpy()
    if not np.isfinite(flow_np).all():  # numpy's test is faster; check_finite words the error
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
    grid = us.shape
    us, vs = us.ravel(), vs.ravel()
    f = flow_np[:, vs, us].astype(np.float64).T  # N x 2; gathered before the (exact) conversion
    ok = np.ones(len(us), dtype=bool) if ignore_np is None else ~ignore_np[vs, us]
    if cov is not None:
        ok &= max_eigenvalue_at_most(cov.detach().cpu().numpy()[vs, us], params.max_flow_sigma**2)
    labels = None
    if semantic is not None:
        # Class argmax where it is read: on the vector grid and on every second pixel (the
        # photometric ground pixels). numpy's argmax over the leading axis is faster than
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
                              kind=MotionKind.UNKNOWN)
    idx = np.nonzero(ok)[0]
    if len(idx) > params.max_points:
        idx = np.sort(rng.choice(idx, size=params.max_points, replace=False))
    road = labels is not None and (labels[idx] == ROAD_CLASS).sum() >= params.min_points
    photometric = images is not None and params.photometric_scale
    # The photometric search's inputs need no flow: made in a second thread during steps 2-3
    # (single-threaded). ``rng`` is that thread's alone until it is joined: steps 2-3 draw nothing.
    prep = (helper_pool("photometric-inputs").submit(photometric_inputs, images, sem_np if road else None, Kn, n_g,
                                                     height, params, rng, ignore_np)
            if photometric else None)
    try:
        est = _mono_from_vectors(Kn, n_g, height, params, rng, H, W, ok, labels, idx, p_cur, p_prev, road, prep,
                                 _prediction(prior, interval_ratio))
    finally:
        if prep is not None:
            wait([prep])  # its thread draws from ``rng``: done before this estimate returns
    moving = est.motion if est.kind == MotionKind.METRIC and not est.degenerate else est.unit_motion
    if labels is None or moving is None or float(moving.t.norm()) <= 0 or not params.scene_scale:
        return with_scene_scale(est, None, np.zeros(3), params)
    # The scene model's length of t (static objects stand on the ground): a second source beside the road's.
    # It meets the ground through the plane of travel (a car moves along its road): it fits no normal of its
    # own, and a phone looking 10 deg down, configured level, put its length 10x off (docs/experiments.md,
    # "The road's normal from the direction of travel"). The road's own searches fit their normal.
    t_unit = moving.t.double().numpy() / float(moving.t.norm())
    n_travel = travel_normal(n_g, t_unit)
    scene = scene_scale(Kn, moving.R.double().numpy(), t_unit, n_travel, height, labels.reshape(grid), us, vs, f, ok,
                        params.step, params.kerb_height)
    return with_scene_scale(est, scene, t_unit, params)


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


#: Warm start of the essential matrix: the prediction replaces RANSAC when, within this many times the
#: RANSAC threshold (Sampson distance), it explains at least the given share of the vectors the last pair's
#: estimate explained (a sudden turn or a mover taking the view fails it). A prediction is not exact (yaw
#: changes by hundredths of a degree from pair to pair), so the share is counted within a wider bound than
#: RANSAC's; its inliers within 2 px start the refinement RANSAC's would.
_WARM_SEED_FACTOR = 4.0
_WARM_MIN_INLIER_SHARE = 0.9


def travel_normal(n_g: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The unit ground normal (3,) nearest to ``n_g`` (3,) that is perpendicular to the translation ``t`` (3,):
    the configured normal turned, by the least rotation, into the plane the camera moves in. ``n_g`` as it
    is where ``t`` is zero."""
    q = float(np.linalg.norm(t))
    if q <= 0:
        return n_g
    d = t / q
    n = n_g - float(n_g @ d) * d
    q = float(np.linalg.norm(n))
    return n / q if q > 1e-9 else n_g  # t along the normal: no plane to turn into


def _off_a_car(R: np.ndarray, t: np.ndarray, n_g: np.ndarray, params: MonoParams) -> str:
    """Why the travel direction ``t`` is not a car's (""; within ``car_max_azimuth_deg`` of its chord on the
    road plane and within ``car_max_elevation_deg`` of that plane, :func:`car_offsets_deg`)."""
    az, el = car_offsets_deg(R, t, n_g)
    if az > params.car_max_azimuth_deg:
        return f"{az:.0f} deg off a car's direction on the road"
    if el > params.car_max_elevation_deg:
        return f"{el:.0f} deg off the road plane"
    return ""


def _as_car_motion(R: np.ndarray, t: np.ndarray, inl: np.ndarray, n_g: np.ndarray, a: np.ndarray, b: np.ndarray,
                   f_scale: float, params: MonoParams) -> tuple[np.ndarray, np.ndarray, np.ndarray, str, Motion | None]:
    """The essential matrix's ``(R, t̂)`` and inliers ``inl`` (N,) held against a car's motion (``params.car_motion``).

    Returns ``(R, t̂, inliers, note, unit)``: the pose unchanged and ``note`` empty where ``t̂`` is a car's
    (:func:`_off_a_car`); the car's pose (:func:`refine_car_pose`) and its inliers where it explains at
    least ``car_min_inlier_share`` of the free one's; else ``unit``, the car's pose as a unit motion
    whose length is unknown (the flow fits no car: movers fill it, or the camera is not looking ahead).
    """
    off = _off_a_car(R, t, n_g, params)
    if not off:
        return R, t, inl, "", None
    Rc, tc = refine_car_pose(R, n_g, a[inl], b[inl], f_scale, params.car_max_elevation_deg)
    inl_c = np.abs(sampson(skew(tc) @ Rc, a, b)) < f_scale
    share = float(inl_c.sum()) / max(int(inl.sum()), 1)
    # The sign the points in front of both cameras give (the road's vote, step 3b, may still reverse it).
    tc = tc * cheirality_sign(Rc, tc, a[inl_c], b[inl_c])
    if share >= params.car_min_inlier_share and inl_c.sum() >= params.min_points:
        return Rc, tc, inl_c, (f"travel direction {off}: a car's motion "
                               f"({int(inl_c.sum())} inliers, {share:.2f} of the free estimate's)"), None
    note = (f"the flow fits no car's motion: the free estimate travels {off}, and a car's motion explains "
            f"{share:.2f} of its inliers (< {params.car_min_inlier_share})")
    unit = Motion(torch.from_numpy(np.ascontiguousarray(Rc)), torch.from_numpy(np.ascontiguousarray(tc)))
    return Rc, tc, inl_c, note, unit


def _mono_from_vectors(Kn: np.ndarray, n_g: np.ndarray, height: float, params: MonoParams, rng: np.random.Generator,
                       H: int, W: int, ok: np.ndarray, labels: np.ndarray | None, idx: np.ndarray, p_cur: np.ndarray,
                       p_prev: np.ndarray, road: bool, prep: Any, pred: _Prediction | None = None) -> MotionEstimate:
    """Steps 2-4 of :func:`estimate_mono` on the grid of usable vectors (``ok``, the subset ``idx``);
    ``prep``: the future of :func:`photometric_inputs`, or None without the photometric search;
    ``pred``: a stream's prediction (:func:`_prediction`) to start from, or None."""
    pc, pp = p_cur[idx], p_prev[idx]

    # 2. Degeneracy: does a rotation alone explain the flow?
    R0, res0 = fit_rotation(Kn, pc, pp)
    parallax = float(np.median(res0))
    if parallax < params.min_parallax:
        still = float(np.median(np.linalg.norm(pp - pc, axis=1))) < params.min_parallax
        kind = "standing still" if still else "pure rotation"
        inl = float((res0 < params.ransac_threshold * 2).mean())
        reason = f"no translation ({kind}): median parallax {parallax:.2f} px < {params.min_parallax} px"
        return MotionEstimate(Motion(torch.from_numpy(R0), torch.zeros(3, dtype=torch.float64)), True, reason, inl,
                              kind=MotionKind.STANDING)

    # 3. Essential matrix (points1 = current, points2 = previous: X_prev = R X_cur + t).
    a_all, b_all = rays(Kn, pc), rays(Kn, pp)
    f_scale = params.ransac_threshold / Kn[0, 0]  # pixels -> normalised image units
    warm = False
    if pred is not None:
        # A stream's prediction in place of RANSAC where it explains as many vectors as the last pair did.
        inl = np.abs(sampson(skew(pred.t_unit) @ pred.R, a_all, b_all)) < _WARM_SEED_FACTOR * f_scale
        warm = inl.sum() >= params.min_points and inl.mean() >= _WARM_MIN_INLIER_SHARE * pred.inlier_ratio
        # The epipolar constraint holds for -t as well: the sign is the one that puts the points in front
        # of both cameras (recoverPose's cheirality test), the prediction's where it does (a camera that
        # reverses does not).
        R, t = pred.R, pred.t_unit * cheirality_sign(pred.R, pred.t_unit, a_all[inl], b_all[inl])
    if not warm:
        try:
            E, mask = cv2.findEssentialMat(pc, pp, Kn, method=cv2.RANSAC, prob=params.ransac_confidence,
                                           threshold=params.ransac_threshold)
            if E is None or E.shape != (3, 3):
                return MotionEstimate(None, False, "essential matrix: RANSAC found no model", 0.0,
                                      kind=MotionKind.UNKNOWN)
            _, R, t, mask = cv2.recoverPose(E, pc, pp, Kn, mask=mask.copy())
        except cv2.error as err:
            # The 5-point solver asserts on some near-degenerate samples (a zero leading coefficient in
            # solvePoly): a failed estimate of this pair, not a crash.
            first = str(err).strip().splitlines()[-1] if str(err).strip() else type(err).__name__
            return MotionEstimate(None, False, f"essential matrix: OpenCV failed on these vectors ({first})", 0.0,
                                  kind=MotionKind.UNKNOWN)
        inl = mask.ravel() > 0
        if inl.sum() < params.min_points:
            return MotionEstimate(None, False, f"essential matrix: only {int(inl.sum())} inliers", float(inl.mean()),
                                  kind=MotionKind.UNKNOWN)
        t = t.ravel()
    # Refine, then re-select inliers with the refined model (the RANSAC set is from a 5-point
    # hypothesis and misses good vectors), and refine once more on them.
    for _ in range(2):
        R, t = refine_pose(R, t, a_all[inl], b_all[inl], f_scale=f_scale)
        inl = np.abs(sampson(skew(t) @ R, a_all, b_all)) < f_scale
        if inl.sum() < params.min_points:
            return MotionEstimate(None, False, f"essential matrix: only {int(inl.sum())} inliers after refinement",
                                  float(inl.mean()), kind=MotionKind.UNKNOWN)
    car_note = ""
    if params.car_motion:
        # 3a. A car moves along its heading. Where the parallax is small the lateral direction trades against
        # the yaw, and the free estimate can travel sideways (docs/experiments.md, "A car's motion").
        R, t, inl, car_note, unit = _as_car_motion(R, t, inl, n_g, a_all, b_all, f_scale, params)
        if unit is not None:
            return MotionEstimate(None, False, f"no metric scale: {car_note}", float(inl.mean()),
                                  kind=MotionKind.SCALE_UNKNOWN, unit_motion=unit)
    inlier_ratio = float(inl.mean())

    # 3b. The sign of t from the road. The epipolar constraint holds for -t as well, and the cheirality
    # vote of step 3 counts every likely-static vector: in traffic, a truck beside the camera that the
    # semantic net calls a building and that pulls ahead outvotes the scene behind it, and t comes out
    # reversed (docs/experiments.md, "Camera motion on unseen footage"). The road cannot move and lies
    # below the camera: its plane under +t has the normal pointing down, under -t up.
    road_votes = road_sign_votes(Kn, n_g, height, params, R, t, p_cur, p_prev,
                                  ((labels == ROAD_CLASS) & ok) if road else ok, lateral=not road)
    flipped = (road_votes is not None and road_votes[1] > road_votes[0]
               and road_votes[1] >= ROAD_SIGN_SHARE * road_votes[2])
    if flipped:
        t = -t
    # 4. Metric scale (and road normal) from the ground.
    head = (f"ok: {int(inl.sum())}/{len(inl)} essential-matrix inliers{' (warm start)' if warm else ''}, "
            f"median parallax {parallax:.1f} px")
    if flipped:
        head += f", direction reversed by the road ({road_votes[1]} of its {road_votes[2]} vectors against {road_votes[0]})"
    if car_note:
        head += f", {car_note}"
    src = "road pixels" if road else "road region ahead"
    failures = []
    found = None
    marks = None
    marks_pending = False
    refine_weak = False
    if prep is not None:
        grey_cur, grey_prev, pts = prep.result()
        pixels = f"{len(pts)} ground pixels ({src}"
        if len(pts) >= params.min_points:
            # Warm: from the predicted length of this t (the sign of t is RANSAC's or the prediction's).
            start = None
            if warm and pred.normal is not None and float(t @ pred.t_unit) > 0:
                start = (pred.scale, pred.normal)
            # Warm, a grid minimum far from sharp is not refined: the pattern search lowers the contrast by
            # too little to bring it from above sharp / 0.7 to sharp.
            found = photometric_ground(grey_cur, grey_prev, Kn, R, t, n_g, height, pts, params.ground_max_tilt, start,
                                        unsharp=params.photometric_sharp / PATTERN_MAX_GAIN)
            refine_weak = start is not None
        if found is None:
            failures.append(f"photometric: no clear minimum over {pixels})")
        elif found[2] <= params.photometric_sharp:
            return _photometric_estimate(found, R, t, n_g, head, pixels, inlier_ratio)
        else:
            failures.append(f"photometric minimum not sharp: contrast {found[2]:.2f} > {params.photometric_sharp}")
        marks_pending = params.road_marks and len(pts) >= params.min_points
    marks_note_at = len(failures)

    def road_marks() -> RoadMarksFit | None:
        """The road marks' fit, read at the first call (where the flow of the ground needs it)."""
        nonlocal marks, marks_pending
        if marks_pending:
            marks_pending = False
            # Its own generator: the ground-flow RANSAC draws the same numbers with or without it.
            marks = road_marks_scale(grey_cur, grey_prev, Kn, R, t, n_g, height, pts, np.random.default_rng(params.seed),
                                     start=pred.scale if warm else None)
            off = _off_a_car(R, marks.t, n_g, params) if marks is not None and params.car_motion else ""
            if marks is None:
                failures.insert(marks_note_at, f"road marks: no clear alignment over {pixels})")
            elif off:
                # The marks turn the travel direction; not into one no car takes.
                failures.insert(marks_note_at, f"road marks: their travel direction {off}")
                marks = None
        return marks

    # The flow of the ground: the corridor ahead first; with road labels, the whole road if a
    # vehicle blocks the corridor.
    base = ((labels == ROAD_CLASS) & ok) if road else ok
    for lateral in ((True, False) if road else (True,)):
        gidx = np.nonzero(base & ground_candidates(Kn, n_g, height, p_cur, params, lateral=lateral))[0]
        if len(gidx) < params.min_points:
            failures.append(f"{len(gidx)} ground vectors ({src}) < {params.min_points}")
            continue
        A, bb = ground_system(Kn, R, t, p_cur[gidx], p_prev[gidx])
        m, ginl = fit_ground(A, bb, params.ground_threshold, rng, n_g=n_g, max_tilt=params.ground_max_tilt)
        q = float(np.linalg.norm(m))
        tilt = tilt_deg(m, n_g)
        if q > 0 and tilt <= params.ground_max_tilt and ginl.sum() >= params.min_points:
            break
        if ginl.sum() < params.min_points:
            failures.append(f"{int(ginl.sum())} ground vectors ({src}) fit a plane (< {params.min_points})")
        else:
            failures.append(f"ground fit normal {tilt:.1f} deg from camera.ground_normal (> {params.ground_max_tilt})")
    else:
        if road_marks() is not None:
            return _road_marks_estimate(marks, R, t, head, pixels, inlier_ratio, "; ".join(failures))
        if found is not None:  # a weak photometric minimum is still better than none
            if refine_weak:  # warm, it may not have been refined: the search from scratch
                found = photometric_ground(grey_cur, grey_prev, Kn, R, t, n_g, height, pts, params.ground_max_tilt) or found
            return _photometric_estimate(found, R, t, n_g, head, pixels, inlier_ratio, note="; ".join(failures))
        # The camera moves and its direction is known; only the length of t is not (a sequence may supply it).
        unit = Motion(torch.from_numpy(np.ascontiguousarray(R)), torch.from_numpy(np.ascontiguousarray(t)))
        return MotionEstimate(None, False, "no metric scale: " + "; ".join(failures), inlier_ratio,
                              kind=MotionKind.SCALE_UNKNOWN, unit_motion=unit)
    scale = height * q
    # Near a stream's prediction the flow is not short: marks could only override it by saying the speed
    # rose by a seventh or more in one interval where the flow says it fell; they are not read then.
    near_prediction = pred is not None and scale >= FLOW_NEAR_PREDICTION * pred.scale
    if not near_prediction and road_marks() is not None and scale < FLOW_SHORT_RATIO * marks.scale:
        # The flow of textureless asphalt errs short (pulled towards zero), not long: well short of the
        # marks' length, it is the flow that failed.
        failures.append(f"{int(ginl.sum())} ground vectors give {scale:.3f} m, short of the marks' {marks.scale:.3f} m")
        return _road_marks_estimate(marks, R, t, head, pixels, inlier_ratio, "; ".join(failures))
    motion = Motion(torch.from_numpy(np.ascontiguousarray(R)), torch.from_numpy(scale * t))
    reason = f"{head}, scale from {int(ginl.sum())} ground vectors ({src}, normal tilt {tilt:.1f} deg)"
    if failures:
        reason += f" ({'; '.join(failures)})"
    normal = torch.from_numpy(np.ascontiguousarray(m / q))
    return MotionEstimate(motion, False, reason, inlier_ratio, ground_normal=normal, scale_from=ScaleFrom.GROUND_FLOW)


def estimate_motion(pair: FramePair, flow: Any, cfg: Any, semantic: torch.Tensor | None = None, *,
                    prior: MotionEstimate | None = None, interval_ratio: float = 1.0) -> MotionEstimate:
    """Camera motion of a frame pair with the backend ``cfg.name`` (gt | file | mono).

    Args:
        pair: the frame pair (camera intrinsics, height and ground normal; ``motion`` for gt;
            ``info.frame_index`` / ``frame_index_prev`` (else ``frame`` / ``frame_prev``) for file).
        flow: the :class:`~monostixels.inputs.flow.FlowResult` of the pair (used by mono).
        cfg: the ``motion`` config group node, a dict or its settings dataclass
            (:data:`monostixels.inputs.motion_track.MOTION_SCHEMAS`).
        semantic: (10, H, W) class scores or None.
        prior: the last pair's estimate of a stream, the start of ``mono`` (see :func:`estimate_mono`);
            None = from scratch. ``gt`` and ``file`` do not read it.
        interval_ratio: this pair's time interval over the last pair's (the prior's translation scales with it).

    Returns:
        A :class:`MotionEstimate`.
    """
    name = getattr(cfg, "name", "") if not hasattr(cfg, "keys") else str(cfg.get("name", ""))
    if name not in MOTION_BACKENDS:
        raise InputError(f"motion.name: unknown motion backend {name!r}, expected one of {MOTION_BACKENDS}")
    params = motion_params(cfg)
    if name == "gt":
        return _gt_motion(pair)
    if name == "file":
        return _file_motion(pair, params)
    if flow is None:
        raise InputError("motion=mono: needs the flow of the pair (flow is None)")
    check_shape(flow.flow, [2, *pair.size], "flow")
    return estimate_mono(
        pair.camera.K, pair.camera.height, pair.camera.ground_normal, flow.flow, flow.cov, params, semantic,
        images=(pair.image, pair.image_prev), prior=prior, interval_ratio=interval_ratio,
        ignore=pair.info.ignore_pixels,
    )


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
                        ignore=pair.info.ignore_pixels)
    if est.motion is None or est.degenerate or est.scale_from not in ROAD_SCALES:
        return None
    if angle_deg(est.motion.t.double(), given.t.double()) > 10.0:
        return None
    return float(pair.camera.height * given.translation_norm / float(est.motion.t.norm()))
