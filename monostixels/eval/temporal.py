"""The ``temporal`` section of the eval report on sequences (docs/conventions.md, section 4.5):
velocities, TTC, depth jitter.

Per frame, every pixel takes the values of the stixel covering it (``velocity`` rotated from the world
into the current camera's axes, ``ttc_s``, the depth of the ray-plane intersection):

- ``velocity_err_mps``: median ``|v_est - v_gt|`` over ground-truth moving pixels with a known velocity.
- ``static_speed_mps``: median ``|v_est|`` over ground-truth static pixels in object stixels (the ground
  and the sky are static by construction, so they would only dilute it).
- ``ttc_rel_err``: median ``|ttc_est - ttc_gt| / ttc_gt`` over ground-truth *moving* object pixels
  closing with ``ttc_gt < 10 s`` (the other traffic: their relative motion is what the temporal layer
  estimates); an estimate that does not close counts as error 1. ``ttc_rel_err_static``: the same over
  static object pixels (classes building .. person), whose TTC is their depth over the ego speed, a
  ratio in which the monocular scale cancels.
- ``depth_jitter``: the previous frame's stixel depth map carried into the current frame by the camera
  motion between them (ground truth where the data has it, else the estimate), against the current
  one: median ``|d_t - d_carried| / d_t`` over ground-truth static pixels with depth ground truth
  (LiDAR pixels on KITTI), within the evaluation depth range.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from monostixels.core.classes import CLASS_TYPE, DYNAMIC_OBJECT, STATIC_OBJECT
from monostixels.core.geometry import Motion, pixel_rays
from monostixels.core.stixels import StixelWorld
from monostixels.data.base import FrameInfo

__all__ = ["TemporalAccumulator", "carry_depth"]

#: Ground-truth TTC up to which closing objects are scored (seconds).
TTC_MAX_S = 10.0
#: Pixels sampled per frame for the medians (keeps memory flat on long sequences).
_MAX_SAMPLES = 20000

_OBJECT_CLASS = torch.tensor([CLASS_TYPE[c] in (STATIC_OBJECT, DYNAMIC_OBJECT) for c in range(len(CLASS_TYPE))])


def carry_depth(depth_prev: torch.Tensor, K: torch.Tensor, motion: Motion) -> torch.Tensor:
    """The previous frame's depth map (H, W) seen from the current camera (H, W; NaN where nothing lands).

    Args:
        depth_prev: (H, W) metres (non-finite or <= 0: none).
        K: (3, 3) intrinsics of both frames.
        motion: current -> previous camera motion, ``X_prev = R X_cur + t``.

    Every previous pixel is back-projected, moved into the current camera (``X_cur = R^T (X_prev - t)``)
    and splatted to its nearest pixel, the nearest point winning (z-buffer).
    """
    H, W = depth_prev.shape
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    d = depth_prev.double()
    ok = torch.isfinite(d) & (d > 0)
    X = pixel_rays(K.double(), u[ok], v[ok]) * d[ok][:, None]
    R, t = motion.R.double(), motion.t.double()
    Xc = (X - t) @ R  # R^T (X - t) as rows
    z = Xc[:, 2]
    front = z > 1e-3
    Kd = K.double()
    uc = (Kd[0, 0] * Xc[front, 0] / z[front] + Kd[0, 2]).round().long()
    vc = (Kd[1, 1] * Xc[front, 1] / z[front] + Kd[1, 2]).round().long()
    zf = z[front]
    inside = (uc >= 0) & (uc < W) & (vc >= 0) & (vc < H)
    out = torch.full((H * W,), math.inf, dtype=torch.float64)
    out.scatter_reduce_(0, vc[inside] * W + uc[inside], zf[inside], reduce="amin")
    out = torch.where(torch.isfinite(out), out, torch.full_like(out, math.nan))
    return out.view(H, W)


class TemporalAccumulator:
    """Collects the per-pixel errors of the ``temporal`` section over a sequence source.

    Args:
        min_depth, max_depth: evaluation depth range (metres) of the depth jitter.
        seed: sampling of the per-frame pixels for the medians.
    """

    def __init__(self, min_depth: float, max_depth: float, seed: int = 0) -> None:
        self.lo, self.hi = float(min_depth), float(max_depth)
        self.gen = torch.Generator().manual_seed(seed)
        self.vel_err: list[torch.Tensor] = []
        self.static_speed: list[torch.Tensor] = []
        self.ttc_err: list[torch.Tensor] = []
        self.ttc_err_static: list[torch.Tensor] = []
        self.jitter: list[torch.Tensor] = []
        self.frames = 0
        self._prev: tuple[str, int, torch.Tensor] | None = None  # sequence, frame, depth map

    def _sample(self, x: torch.Tensor) -> torch.Tensor:
        if x.numel() > _MAX_SAMPLES:
            x = x[torch.randperm(x.numel(), generator=self.gen)[:_MAX_SAMPLES]]
        return x.float()

    def add(self, world: StixelWorld, pose: torch.Tensor | None, gt: Any, info: FrameInfo,
            motion_to_prev_frame: Motion | None, estimated_prev_pose: torch.Tensor | None) -> None:
        """Score one frame.

        Args:
            world: the frame's stixels with ``velocity`` and ``ttc_s``.
            pose: (4, 4) camera-to-world of the frame.
            gt: its ground truth (``moving``, ``velocity``, ``ttc``, ``depth``, ``labels``: any may be None).
            info: the pair's :class:`~monostixels.data.base.FrameInfo` (``sequence``, ``frame``).
            motion_to_prev_frame: ground-truth camera motion from this frame to the frame just before it
                (``X_prev = R X_cur + t``), or None.
            estimated_prev_pose: the stream's pose of the frame just before it, or None.
        """
        if world.velocity is None or world.ttc_s is None:
            return
        self.frames += 1
        idx = world.index_map()
        has = idx >= 0
        safe = idx.clamp(min=0)
        R_wc = (pose if pose is not None else torch.eye(4, dtype=torch.float64))[:3, :3]
        v_cam = world.velocity.double() @ R_wc  # world -> current camera axes, per stixel
        v_px = v_cam[safe].permute(2, 0, 1)  # 3 x H x W
        obj_stixel = (world.type == STATIC_OBJECT) | (world.type == DYNAMIC_OBJECT)
        in_obj = has & obj_stixel[safe]
        moving = gt.moving
        if gt.velocity is not None:
            known = torch.isfinite(gt.velocity).all(0) & has
            if moving is not None and bool((known & moving).any()):
                m = known & moving
                self.vel_err.append(self._sample((v_px[:, m] - gt.velocity[:, m].double()).norm(dim=0)))
        static = None
        if moving is not None:
            static = ~moving
            if gt.depth is not None:
                static = static & (gt.depth > 0)
        elif gt.depth is not None:
            static = gt.depth > 0  # no moving mask (KITTI raw, a static street): every measured pixel
        if static is not None and bool((static & in_obj).any()):
            m = static & in_obj
            self.static_speed.append(self._sample(v_px[:, m].norm(dim=0)))
        if gt.ttc is not None:
            ttc_gt = gt.ttc.double()
            sel = torch.isfinite(ttc_gt) & (ttc_gt > 0) & (ttc_gt < TTC_MAX_S) & has
            if gt.labels is not None:
                lab = gt.labels.clamp(0, len(CLASS_TYPE) - 1)
                sel &= _OBJECT_CLASS[lab] & (gt.labels < len(CLASS_TYPE))
            for part, out in ((moving, self.ttc_err), (None if moving is None else ~moving, self.ttc_err_static)):
                m = sel & part if part is not None else None
                if m is None or not bool(m.any()):
                    continue
                est = world.ttc_s.double()[safe][m]
                err = (est - ttc_gt[m]).abs() / ttc_gt[m]
                out.append(self._sample(torch.where(torch.isfinite(est), err, torch.ones_like(err))))
        # Depth jitter against the previous frame of the same sequence.
        depth = world.depth_map().double()
        seq, frame = info.sequence, info.frame
        if (self._prev is not None and seq is not None and frame is not None and self._prev[0] == seq
                and gt.depth is not None and static is not None):
            motion = motion_to_prev_frame
            if motion is None and estimated_prev_pose is not None and pose is not None:
                T = torch.linalg.solve(estimated_prev_pose.double(), pose.double())
                motion = Motion(T[:3, :3], T[:3, 3])
            if motion is not None:
                carried = carry_depth(self._prev[2], world.K, motion)
                sel = (static & torch.isfinite(carried) & torch.isfinite(depth) & (depth > self.lo) & (depth < self.hi)
                       & (carried > self.lo) & (carried < self.hi))
                if bool(sel.any()):
                    self.jitter.append(self._sample((depth[sel] - carried[sel]).abs() / depth[sel]))
        self._prev = (seq, frame, depth) if seq is not None and frame is not None else None

    def result(self) -> dict[str, Any]:
        """The ``temporal`` section (medians; NaN where nothing was scored)."""
        def med(xs: list[torch.Tensor]) -> float:
            return float(torch.cat(xs).median()) if xs else float("nan")

        return {"velocity_err_mps": med(self.vel_err), "static_speed_mps": med(self.static_speed),
                "ttc_rel_err": med(self.ttc_err), "ttc_rel_err_static": med(self.ttc_err_static),
                "depth_jitter": med(self.jitter), "frames": self.frames}
