"""Stixels in 3D: reference points, boxes, camera poses chained over a clip, frame times.

What the 3D viewer (:mod:`monostixels.output.viewer`) draws and the batch dataset
(:mod:`monostixels.batch`) stores, computed once here so both agree.

Convention (docs/conventions.md, section 2): camera x right, y down, z forward, metres. The world
frame of a clip is its first camera (the previous image of the first frame pair), so the world's y
axis points down too. A pose is the (4, 4) camera-to-world matrix ``X_w = R_wc X_c + t_wc``. A
pair's camera motion ``X_prev = R X_cur + t`` is the current camera's pose in the previous camera,
so poses chain as ``T_w_cur = T_w_prev @ [R t; 0 1]``.
"""
from __future__ import annotations

import logging
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Hashable

import numpy as np
import torch

from monostixels.core.classes import DYNAMIC_OBJECT, GROUND, SKY, STATIC_OBJECT
from monostixels.core.geometry import object_normals, pixel_rays
from monostixels.core.stixels import StixelWorld
from monostixels.data.base import FramePair

__all__ = ["StixelBoxes", "PoseChain", "frame_time", "optional_field", "reference_points", "stixel_boxes",
           "to_world"]

logger = logging.getLogger(__name__)

#: Fields that the sequence layer adds to a StixelWorld (docs/conventions.md, section 4.4), absent
#: on single pairs.
TEMPORAL_FIELDS = ("track_id", "velocity", "ttc_s")


def optional_field(world: StixelWorld, name: str) -> np.ndarray | None:
    """A temporal per-stixel field (``track_id`` (N,), ``velocity`` (N, 3) m/s, ``ttc_s`` (N,) s) as
    numpy, or None where the stixel world does not carry it (single frame pairs)."""
    value = getattr(world, name, None)
    if value is None:
        return None
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    arr = np.asarray(value)
    return arr if arr.shape[:1] == (len(world),) else None


def _column_centres(world: StixelWorld) -> torch.Tensor:
    """Centre pixel u (N,) of each stixel's column (as :attr:`StixelWorld.depth` uses)."""
    W = world.image_size[1]
    u0 = world.column.double() * world.column_width
    return (u0 + torch.clamp(u0 + world.column_width, max=W) - 1) / 2


def reference_points(world: StixelWorld) -> np.ndarray:
    """Camera-frame point (N, 3) of each stixel, metres; NaN for sky and for an invalid plane hit.

    The point is the one whose depth :attr:`StixelWorld.depth` reports: the column-centre pixel at
    the bottom row for ground stixels, at the middle row for objects, on the stixel's plane; so its
    z equals ``depth``. A ground stixel above the horizon (its ray never meets the plane) is NaN.
    """
    if len(world) == 0:
        return np.zeros((0, 3))
    K = world.K.double()
    v = torch.where(world.type == GROUND, world.v_bottom, (world.v_top + world.v_bottom) // 2).double()
    ray = pixel_rays(K, _column_centres(world), v)  # N x 3, z = 1
    z = 1.0 / (world.inverse_depth.double() * (ray * world.normals()).sum(-1))
    X = ray * z[:, None]
    bad = (world.type == SKY) | ~torch.isfinite(z) | (z <= 0)
    X[bad] = float("nan")
    return X.numpy()


@dataclass
class StixelBoxes:
    """Object stixels as oriented boxes in the camera frame.

    Attributes:
        index: (M,) index of each box's stixel in the StixelWorld.
        centers: (M, 3) metres. half_sizes: (M, 3) metres along the box's own axes (lateral, down,
            depth). rotations: (M, 3, 3) box-to-camera rotations, columns = those axes.
    """

    index: np.ndarray
    centers: np.ndarray
    half_sizes: np.ndarray
    rotations: np.ndarray

    def __len__(self) -> int:
        return int(self.index.shape[0])


def stixel_boxes(world: StixelWorld) -> StixelBoxes:
    """The static and dynamic object stixels of a frame as boxes (camera frame, metres).

    Convention: an object stixel lies on the upright plane ``n^T X = 1/p`` facing the camera
    (``n`` = the column's horizontal viewing direction, orthogonal to the ground normal ``n_g``).
    Its front face is the part of the plane that the column's pixel edges (``u0 - 0.5 .. u1 - 0.5``,
    ``v_top - 0.5 .. v_bottom + 0.5``, pixel centres at integers) cut out; the box extends behind
    it by its width, so from above each stixel is a square. Box axes: lateral ``n_g x n`` (right),
    ``n_g`` (down), ``n`` (away from the camera). Stixels with an invalid plane are left out.
    """
    keep = torch.nonzero((world.type == STATIC_OBJECT) | (world.type == DYNAMIC_OBJECT)).flatten()
    K = world.K.double()
    ng = world.ground_normal.double()
    ng = ng / ng.norm()
    W = world.image_size[1]
    c = world.column[keep].double()
    u0 = c * world.column_width - 0.5
    u1 = torch.clamp((c + 1) * world.column_width, max=W) - 0.5
    vt = world.v_top[keep].double() - 0.5
    vb = world.v_bottom[keep].double() + 0.5
    n = object_normals(K, ng, _column_centres(world)[keep])  # M x 3
    d = 1.0 / world.inverse_depth[keep].double()  # horizontal distance of the plane, metres
    corners = []
    for u, v in ((u0, vt), (u1, vt), (u0, vb), (u1, vb)):
        r = pixel_rays(K, u, v)
        corners.append(r * (d / (r * n).sum(-1))[:, None])
    P = torch.stack(corners, 1)  # M x 4 x 3
    lateral = torch.linalg.cross(ng.expand_as(n), n)
    axes = torch.stack([lateral, ng.expand_as(n), n], -1)  # M x 3 x 3, columns = box axes
    local = torch.einsum("mkj,mji->mki", P, axes)  # corner coordinates along the axes
    lo, hi = local.amin(1), local.amax(1)
    width = hi[:, 0] - lo[:, 0]
    centre_local = torch.stack([(lo[:, 0] + hi[:, 0]) / 2, (lo[:, 1] + hi[:, 1]) / 2, d + width / 2], -1)
    half = torch.stack([width / 2, (hi[:, 1] - lo[:, 1]) / 2, width / 2], -1)
    centres = torch.einsum("mij,mj->mi", axes, centre_local)
    ok = torch.isfinite(centres).all(-1) & torch.isfinite(half).all(-1) & (d > 0) & ((P[..., 2] > 0).all(-1))
    return StixelBoxes(keep[ok].numpy(), centres[ok].numpy(), half[ok].numpy(), axes[ok].numpy())


def to_world(pose: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Camera-frame points (..., 3) to the world frame with a (4, 4) camera-to-world pose."""
    return X @ pose[:3, :3].T + pose[:3, 3]


def frame_time(pair: FramePair, fps: float | None) -> float | None:
    """Time (seconds) of a pair's current frame in its recording where known, else None.

    ``pair.info.time_s`` if a source provides it; else the video frame number over the frame rate.
    """
    info = pair.info
    if info.time_s is not None:
        return float(info.time_s)
    if fps and info.frame is not None and info.source == "video":
        return float(info.frame) / float(fps)
    return None


def _motion_matrix(res: Any) -> np.ndarray:
    """``[R t; 0 1]`` (4, 4) of the pair's camera motion ``X_prev = R X_cur + t``: the current
    camera's pose in the previous camera's frame. Identity where no motion was used."""
    T = np.eye(4)
    motion = getattr(getattr(res, "motion", None), "motion", None)
    if motion is not None:
        T[:3, :3] = motion.R.double().cpu().numpy()
        T[:3, 3] = motion.t.double().cpu().numpy()
    return T


#: Frames whose pose a :class:`PoseChain` keeps: a pair's previous frame is one of the last few current
#: frames (``keyframes.window`` back at most, 10 by default); older ones are forgotten, so a recording of
#: a camera left running does not grow with every frame.
_KEPT_POSES = 64


class PoseChain:
    """Camera-to-world poses (4, 4) of the frames of a clip, world = the first camera.

    Takes ``result.pose`` where the pipeline provides it (the sequence layer); otherwise chains
    the pairs' camera motions: a pair's previous frame is found by its ``meta`` keys (video frame
    number, image path), or, where a source names none, taken to be the previous pair's current
    frame. The poses of the last :data:`_KEPT_POSES` frames are kept.
    """

    def __init__(self) -> None:
        self._poses: OrderedDict[Hashable, np.ndarray] = OrderedDict()
        self._last: np.ndarray | None = None
        self._warned = False

    @staticmethod
    def _keys(pair: FramePair) -> tuple[Hashable, Hashable]:
        """Keys of the pair's current and previous frame, by what its source names them with: video and
        KITTI raw (frame numbers), image folders (paths), DDAD (timestamps); (None, None) where it names none."""
        info = pair.info
        for kind, cur, prev in (("frame", info.frame, info.frame_prev), ("path", info.path, info.path_prev),
                                ("timestamp", info.timestamp, info.timestamp_prev)):
            if cur is not None and prev is not None:
                return (kind, cur), (kind, prev)
        return None, None

    def update(self, pair: FramePair, res: Any) -> np.ndarray:
        """Pose (4, 4) float64 of ``pair``'s current frame; remembers it for the later pairs."""
        cur, prev = self._keys(pair)
        pose = getattr(res, "pose", None)
        if pose is not None:
            T = np.asarray(pose.detach().cpu().numpy() if isinstance(pose, torch.Tensor) else pose,
                           dtype=np.float64).reshape(4, 4)
        else:
            T_prev = self._poses.get(prev) if prev is not None else self._last
            if T_prev is None:
                if self._last is not None and not self._warned:
                    # E.g. image folders with data.step > 1: pairs (2, 0), (3, 1): frame 1 was never
                    # a pair's current frame, so its pose is unknown.
                    logger.warning("%s: the previous frame's pose is unknown; chaining from the last frame "
                                   "(camera path approximate)", getattr(pair, "name", "frame"))
                    self._warned = True
                T_prev = self._last if self._last is not None else np.eye(4)
                if self._last is None and prev is not None:
                    self._poses[prev] = T_prev  # the first pair's previous frame is the world
            T = T_prev @ _motion_matrix(res)
        self._poses[cur] = T
        self._poses.move_to_end(cur)
        while len(self._poses) > _KEPT_POSES:
            self._poses.popitem(last=False)
        self._last = T
        return T
