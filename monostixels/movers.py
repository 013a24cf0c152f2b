"""Post-solve check of dynamic stixels: is the motion detectable, or does an object standing still explain the flow?

Why: on a real street where nothing moves but the ego vehicle (KITTI raw drive 0023), 10-14 % of
the image lay in dynamic stixels with a world motion above 1 m/s (trees, hedges, parked cars, the
near road). A dynamic stixel has 2 degrees of freedom against 1 of a static one, so it wins
wherever real flow errors are spatially correlated (DeepFlow over foliage and at large
displacements: 1.1-1.6 px off the epipolar lines there, 0.2-0.5 px elsewhere) — and its depth is
not in its flow (paper): it comes from the scene model (standing on the ground at its bottom row,
or the object below), so a depth error of 11 % on a static object already reads as 1 m/s at
10 Hz (``Δ ≈ t (1 - d_model / d_true)``).

The check, per dynamic stixel (model selection with a minimum detectable motion):

1. The best *static* explanation of its flow: the plane distance ``d_s`` (1 DOF) as the median of
   its pixels' triangulated points along the stixel's normal (the same robust fit as MLESAC over
   the segment's flow vectors), and the flow residual of that static plane, ``e_s`` (median over
   its pixels, pixels).
2. The stixel stays dynamic if the static plane does not explain the flow (``e_s >
   max_static_residual_px``: a crossing or turning mover, whose flow leaves the epipolar lines),
   or if the scene model's depth disagrees with the static depth by more than the scene model can
   resolve (``|d_model / d_s - 1| > min_depth_discrepancy``: an oncoming or preceding car, whose
   flow *is* epipolar but whose ground contact places it elsewhere — the case mono-stixels exist for).
3. Otherwise the object stands still: it becomes a static object stixel at the static depth
   ``d_s`` with zero motion, and keeps its class (a parked car is still a vehicle: the class says
   what it is, the type how it behaves in this frame pair; `run`'s overlays then stop showing
   parked cars and trees as moving objects).

Pixels without a valid triangulation (near the focus of expansion, where flow carries no depth)
do not vote; a stixel with too few valid pixels keeps the solver's labels.

Convention: camera motion ``X_prev = R X_cur + t``, flow ``x_prev = x + f`` (SPEC section 2); an
object stixel lies on ``p n^T X = 1``.
"""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Any

import torch

from monostixels.classes import DYNAMIC_OBJECT, STATIC_OBJECT
from monostixels.geometry import Motion, apply_homography, homography, pixel_rays
from monostixels.stixels import StixelWorld

__all__ = ["MoverCheckParams", "check_movers"]

logger = logging.getLogger(__name__)


@dataclass
class MoverCheckParams:
    """Parameters of :func:`check_movers` (config group ``movers``).

    Attributes:
        enabled: apply the check.
        max_static_residual_px: a static plane that explains the stixel's flow to within this
            median residual (pixels) is an explanation (DeepFlow off the epipolar lines on KITTI raw:
            0.2-0.5 px median, 1-2 px over foliage). Chosen on drive 0023 pairs 1-3 only.
        min_depth_discrepancy: relative difference between the scene model's depth and the static
            fit's depth above which the stixel is a mover along the epipolar lines.
        min_pixels: fewest pixels with a valid triangulation for a decision.
        min_depth, max_depth: triangulated depths outside this range (metres) do not vote.
    """

    enabled: bool = True
    max_static_residual_px: float = 2.0
    min_depth_discrepancy: float = 0.3
    min_pixels: int = 10
    min_depth: float = 1.0
    max_depth: float = 150.0

    @staticmethod
    def from_config(cfg: Any) -> "MoverCheckParams":
        d = MoverCheckParams()
        if cfg is None:
            return d
        kw = {}
        for k in d.__dataclass_fields__:
            v = cfg.get(k, None) if hasattr(cfg, "get") else getattr(cfg, k, None)
            kw[k] = type(getattr(d, k))(getattr(d, k) if v is None else v)
        return MoverCheckParams(**kw)


def check_movers(stixels: StixelWorld, flow: torch.Tensor, motion: Motion, point_depth: torch.Tensor | None = None,
                 params: MoverCheckParams | None = None) -> StixelWorld:
    """Dynamic stixels that a static object explains become static (see the module docstring).

    Args:
        stixels: the solver's result.
        flow: (2, H, W) current -> previous, pixels.
        motion: the camera motion used by the solver (metres).
        point_depth: (H, W) per-pixel depth triangulated from ``flow`` and ``motion`` (metres;
            invalid = negative, inf or NaN), e.g. the SfM baseline's; None = triangulated here.
        params: thresholds.

    Returns:
        A new :class:`StixelWorld`; ``flags["static_checked"]`` = number of dynamic stixels made static.
    """
    prm = params or MoverCheckParams()
    H, W = stixels.image_size
    dyn = torch.nonzero(stixels.type == DYNAMIC_OBJECT).flatten()
    if not prm.enabled or dyn.numel() == 0 or float(motion.t.norm()) == 0.0:
        return stixels  # without translation nothing triangulates (a flagged degenerate frame)
    if point_depth is None:
        from monostixels.eval.sfm import triangulate

        point_depth = triangulate(flow, stixels.K, motion).depth
    K = stixels.K.double()
    R, t = motion.R.double(), motion.t.double()
    n_all = stixels.normals().double()
    z = point_depth.double()
    f = flow.double()
    types, p_out = stixels.type.clone(), stixels.inverse_depth.clone()
    mot, tau = stixels.motion.clone(), stixels.tau.clone()
    changed = 0
    for k in dyn.tolist():
        c0 = int(stixels.column[k]) * stixels.column_width
        c1 = min(c0 + stixels.column_width, W)
        v0, v1 = int(stixels.v_top[k]), int(stixels.v_bottom[k]) + 1
        vv, uu = torch.meshgrid(torch.arange(v0, v1, dtype=torch.float64), torch.arange(c0, c1, dtype=torch.float64),
                                indexing="ij")
        zz = z[v0:v1, c0:c1]
        ok = torch.isfinite(zz) & (zz >= prm.min_depth) & (zz <= prm.max_depth)
        if int(ok.sum()) < prm.min_pixels:
            continue
        n = n_all[k]
        rays = pixel_rays(K, uu[ok], vv[ok])
        d_s = float((zz[ok] * (rays @ n)).median())
        if d_s <= 0:
            continue
        Hs = homography(K, R, t, n, torch.tensor(1.0 / d_s, dtype=torch.float64))
        up, vp = apply_homography(Hs, uu, vv)
        res = torch.hypot(up - uu - f[0, v0:v1, c0:c1], vp - vv - f[1, v0:v1, c0:c1])
        e_s = float(res.median())
        d_model = 1.0 / float(stixels.inverse_depth[k]) if float(stixels.inverse_depth[k]) > 0 else float("inf")
        if e_s > prm.max_static_residual_px or abs(d_model / d_s - 1.0) > prm.min_depth_discrepancy:
            continue
        types[k] = STATIC_OBJECT
        p_out[k] = torch.as_tensor(1.0 / d_s, dtype=p_out.dtype)
        mot[k] = 0.0
        tau[k] = 0.0  # (t̃x, t̃y) belong to dynamic stixels only
        changed += 1
    flags = dict(stixels.flags)
    flags["static_checked"] = changed
    logger.debug("mover check: %d of %d dynamic stixels explained by a static object", changed, dyn.numel())
    return dataclasses.replace(stixels, type=types, inverse_depth=p_out, motion=mot, tau=tau, flags=flags)
