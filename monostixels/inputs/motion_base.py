"""The camera motion's settings and result, below the estimator and the sequence's track that both use them.

The backends (:mod:`monostixels.inputs.motion`), the road fit (:mod:`monostixels.inputs.ground`), the
scene model (:mod:`monostixels.inputs.motion_scene`) and the sequence prior
(:mod:`monostixels.inputs.motion_track`) import these from here, so that none of them imports the
estimator back; :mod:`monostixels.inputs.motion` exports them too.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional

import torch
from omegaconf import MISSING

from monostixels._checks import InputError
from monostixels.core.geometry import Motion
from monostixels.core.status import MotionKind, ScaleFrom

__all__ = ["MOTION_BACKENDS", "MotionKind", "ScaleFrom", "MOTION_KINDS", "NO_METRIC_MOTION", "ROAD_SCALES",
           "MIN_TRANSLATION_M", "MotionEstimate", "MonoParams", "GtMotionConfig", "FileMotionConfig"]

MOTION_BACKENDS = ("gt", "file", "mono")

#: The kinds, in the order reports list them.
MOTION_KINDS = tuple(MotionKind)
#: The kinds without a metric camera motion (no movers, no TTC, no pose).
NO_METRIC_MOTION = (MotionKind.SCALE_UNKNOWN, MotionKind.UNKNOWN)
#: The scales measured on the road of the pair itself.
ROAD_SCALES = (ScaleFrom.PHOTOMETRIC, ScaleFrom.ROAD_MARKS, ScaleFrom.GROUND_FLOW)
#: Below this camera translation (metres) a known motion (gt / file) counts as standing still:
#: 1 mm moves a point 5 m away by ~0.15 px at KITTI focal length — no usable parallax.
MIN_TRANSLATION_M = 1e-3


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
        kind: which :class:`MotionKind` the estimate is: ``metric`` (rotation and metric
            translation), ``standing`` (no translation: standing still or turning on the spot;
            ``degenerate``), ``scale_unknown`` (rotation and translation direction known, its metric
            length not: ``unit_motion``) or ``unknown`` (nothing known about the camera).
        unit_motion: ``scale_unknown``: the rotation and the unit translation direction; else None.
        scale_from: where a metric translation's length came from (:class:`ScaleFrom`): ``given`` (gt / file),
            ``photometric`` (the road's image alignment), ``road_marks`` (the alignment of the road's marks
            and the travel direction, :mod:`~monostixels.inputs.road_marks`), ``ground_flow`` (the road's flow vectors),
            ``sequence`` (the recent pairs' speed, :class:`~monostixels.inputs.motion_track.MotionTrack`), ``scene``
            (static objects standing on the ground, :mod:`~monostixels.inputs.motion_scene`); None otherwise.
        scale_std: the relative uncertainty (std of ``log |t|``) of a metric translation's length: 0 for a
            given motion, the sequence filter's (:class:`~monostixels.inputs.motion_track.MotionTrack`) over a
            sequence, the settings' ``scale_meas_std`` for a single pair; None without a metric translation.
        scene_reach: where the length came from the scene model (``scale_from`` ``scene``), its contacts'
            distance in camera heights (:class:`~monostixels.inputs.motion_scene.SceneScale`): a tilt of the
            plane of travel by δ moves that length by about ``δ * scene_reach`` in log; else None.
    """

    motion: Motion | None
    degenerate: bool
    reason: str
    inlier_ratio: float
    ground_normal: torch.Tensor | None = None
    kind: MotionKind = MotionKind.METRIC
    unit_motion: Motion | None = None
    scale_from: ScaleFrom | None = None
    scale_std: float | None = None
    scene_reach: float | None = None

    def __post_init__(self) -> None:
        # Given as strings (tests, callers of old), still typed; an unknown one is a ValueError here.
        self.kind = MotionKind(self.kind)
        if self.scale_from is not None:
            self.scale_from = ScaleFrom(self.scale_from)


@dataclass
class MonoParams:
    """Parameters of the ``mono`` estimator (keys of the ``motion`` config group's option ``mono``;
    its schema is :class:`~monostixels.inputs.motion_track.MonoMotionConfig`).

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
        scene_scale: the scene model's length of ``t`` (static objects' ground contacts,
            :mod:`monostixels.inputs.motion_scene`), with semantic scores: checked against the road's (where the
            two disagree the pair's scale is uncertain) and taken where the road gives none.
        kerb_height: how far sidewalks and verges lie above the road (m), for the scene model's contacts on them.
        road_marks: without a sharp photometric minimum, the scale and travel direction from the road's
            marks (:mod:`monostixels.inputs.road_marks`) where the flow of the ground gives none or
            one well short of theirs (:data:`FLOW_SHORT_RATIO`).
        car_motion: the camera rides a car, which moves along its heading on the road: an essential matrix
            whose travel direction lies more than ``car_max_azimuth_deg`` off a car's on the road plane (its
            heading turned by half the yaw) or more than ``car_max_elevation_deg`` off that plane
            (:func:`~monostixels.inputs.epipolar.car_offsets_deg`) is refitted as a car's motion
            (:func:`~monostixels.inputs.epipolar.refine_car_pose`), and the car's replaces it where it
            explains at least ``car_min_inlier_share`` of the vectors the free one explains; otherwise the
            flow fits no car's motion (crossing traffic or wipers before a standing camera, a camera looking
            sideways) and only the car's direction is kept, its length unknown (``scale_unknown``). The road
            marks' direction (``road_marks``) is held to the same bounds.
        car_max_azimuth_deg: the most degrees between the travel direction and a car's on the road plane
            (the camera's yaw on the car, and the yaw's error).
        car_max_elevation_deg: the most degrees between the travel direction and the configured road plane
            (the camera's pitch on the car: a phone on a windscreen may look down by 10-15 degrees).
        car_min_inlier_share: the share of the free estimate's inliers a car's motion must explain to replace it.
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
    scene_scale: bool = True
    kerb_height: float = 0.15
    car_motion: bool = True
    car_max_azimuth_deg: float = 10.0
    car_max_elevation_deg: float = 20.0
    car_min_inlier_share: float = 0.8
    seed: int = 0

    def __post_init__(self) -> None:
        for k in ("car_max_azimuth_deg", "car_max_elevation_deg"):
            v = getattr(self, k)
            if not 0.0 <= v <= 90.0:
                raise InputError(f"motion.{k}: degrees in [0, 90], got {v!r}")
        if not 0.0 < self.car_min_inlier_share <= 1.0:
            raise InputError(f"motion.car_min_inlier_share: a share in (0, 1], got {self.car_min_inlier_share!r}")


@dataclass
class GtMotionConfig:
    """``motion=gt``: the data source's ground-truth camera motion (``pair.motion``); no settings."""

    name: str = "gt"


@dataclass
class FileMotionConfig:
    """``motion=file``: the camera motion from a KITTI-style poses file.

    Attributes:
        path: the poses file (mandatory): per line 12 numbers (3x4 row-major ``T_w_cam``) or a frame number
            and 12 numbers; the frames are those of the data source (meta ``frame_index`` / ``frame_index_prev``).
        offset: position (metres) of the image camera in the posed camera's frame (same orientation); KITTI's
            camera 2 against camera-0 poses: ``[P_rect_02[0,3] / fx, 0, 0]`` ~ ``[0.06, 0, 0]``. None = none.
    """

    name: str = "file"
    path: str = MISSING
    offset: Optional[List[float]] = None
