"""Post-solve check of dynamic stixels: does an object standing still explain the flow?

Why: a dynamic stixel has 2 degrees of freedom against 1 of a static one, so it wins wherever flow
errors are spatially correlated (foliage, large displacements), and its depth is not in its flow
but in the scene model (its ground contact, or the object below). A static object whose model
depth is 11 % off already reads as 1 m/s at 10 Hz (``Δ ≈ t (1 - d_model / d_true)``), so a
street where nothing moves fills with false movers. The check is model selection with a minimum
detectable motion, per dynamic stixel, decided bottom-up along each column:

1. Static fit: the plane distance ``d_s`` = median of its pixels' triangulated points along the
   stixel's normal (as MLESAC over the segment's flow vectors) and that plane's median flow
   residual ``e_s`` (pixels).
2. It stays dynamic if the static plane does not explain the flow (``e_s > max_static_residual_px``:
   crossing or turning movers) unless the solver's dynamic plane does not either (``e_d >
   max_dynamic_residual_ratio * e_s``: slanted walls, object edges); or if the scene model's depth
   disagrees with ``d_s`` (``|d_model / d_s - 1| > min_depth_discrepancy``: oncoming and preceding
   cars, whose flow is epipolar but whose ground contact is elsewhere); or, standing on the road, if
   a static object at ``d_s`` would meet the road more than ``max_contact_gap_px`` rows from the
   model's contact (a mover along its epipolar lines has ``d_s ≈ d t / (t - Δ)``, its contact is
   right). "On the road": on a ground stixel, on a sliver of at most ``contact_sliver_rows`` rows
   that is, or on a dynamic stack that is and stays dynamic. A stixel on one made static is compared
   with that one's static depth (``follow_below``; with ``allow_behind_still`` any depth behind it).
3. Classes in ``keep_classes`` (pedestrians, riders: too slow to tell from standing) stay dynamic.
4. With ``isolated_stand_still``, a stixel still dynamic without a dynamic neighbour in an adjacent
   column at overlapping rows stands still too: a moving object is wider than one column.
5. Otherwise it stands still: a static object stixel at depth ``d_s`` with zero motion, its class
   kept (a parked car is still a vehicle; the type says how it behaves in this frame pair).

Pixels without a valid triangulation (near the focus of expansion) do not vote; a stixel with too
few valid pixels keeps the solver's labels. How the thresholds were chosen: docs/experiments.md.

Convention: camera motion ``X_prev = R X_cur + t``, flow ``x_prev = x + f`` (docs/conventions.md,
section 2); an object stixel lies on ``p n^T X = 1``.
"""
from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import torch
from kornia.geometry.epipolar import cross_product_matrix, fundamental_from_essential, left_to_right_epipolar_distance

from monostixels._checks import InputError
from monostixels.core.classes import CLASS_NAMES, DYNAMIC_OBJECT, GROUND, STATIC_OBJECT
from monostixels.post.sfm import triangulate_points
from monostixels.core.geometry import Motion, apply_homography, dynamic_homography, homography, pixel_rays
from monostixels.core.stixels import StixelWorld, neighbours, segment_lower_median

__all__ = ["MoverCheckParams", "STATIC_EPIPOLAR_QUANTILE", "check_movers", "epipolar_distance", "settle_receding", "static_only"]

logger = logging.getLogger(__name__)


@dataclass
class MoverCheckParams:
    """Parameters of :func:`check_movers` (config group ``movers``).

    Attributes:
        enabled: apply the check.
        max_static_residual_px: median flow residual (pixels) up to which a static plane explains
            the stixel's flow (DeepFlow is a few tenths of a pixel off the epipolar lines on most
            pixels, 1-2 px over foliage).
        min_depth_discrepancy: relative difference between the scene model's depth and the static
            fit's depth above which the stixel is a mover along the epipolar lines.
        max_contact_gap_px: for a stixel standing on the road, the most rows between where its
            static plane and where the scene model's plane meet that road.
        follow_below: compare a stixel stacked on one the check makes static with that one's static
            depth instead of the solver's depth.
        allow_behind_still: such a stacked stixel passes the depth test at any static depth behind
            the object below (one-sided window).
        isolated_stand_still: a stixel still dynamic with no dynamic stixel in an adjacent column
            at overlapping rows stands still (one pass, kept classes excepted).
        max_dynamic_residual_ratio: a stixel the static plane leaves unexplained still stands still
            unless the solver's dynamic plane leaves at most this fraction of the static residual
            (``inf`` = off).
        keep_classes: class names (:data:`monostixels.core.classes.CLASS_NAMES`) whose dynamic stixels
            are never made static; empty = the purely geometric check.
        contact_sliver_rows: a stixel on an object at most this many rows tall that stands on a
            ground stixel stands on that ground for the contact test (0 = off).
        min_pixels: fewest pixels with a valid triangulation for a decision.
        min_depth, max_depth: triangulated depths outside this range (metres) do not vote (at an uncertain
            length nothing is triangulated: the epipolar distance decides).
        cut_off_contacts, cut_off_max_rms_m, cut_off_max_jump: dynamic stixels cut off by the image's lower
            edge stand on the line of their object's visible contacts (:func:`monostixels.post.cut_off.stand_cut_off`;
            applied by the pipeline after the check, also where ``enabled`` is false): at most this many
            contact columns on each side (0 = off), their most RMS distance from their line (m), the most
            relative depth change between neighbouring contacts of one object.

    The defaults are the shipped check (the schema of the config group ``movers``); the purely
    geometric check is ``keep_classes=()``, ``max_dynamic_residual_ratio=inf``,
    ``isolated_stand_still=False``, ``contact_sliver_rows=0``. Why each threshold: docs/experiments.md,
    "Mover check".
    """

    enabled: bool = True
    max_static_residual_px: float = 2.0
    min_depth_discrepancy: float = 0.3
    min_pixels: int = 10
    min_depth: float = 1.0
    max_depth: float = 150.0
    max_contact_gap_px: float = 12.0
    follow_below: bool = True
    allow_behind_still: bool = False
    isolated_stand_still: bool = True
    # inf (YAML .inf, command line inf) = off.
    max_dynamic_residual_ratio: float = 0.3
    # Pedestrians and riders move too slowly (0.1-0.2 m per frame) for the check to tell them from standing still.
    keep_classes: tuple[str, ...] = ("person", "two_wheeler")
    contact_sliver_rows: float = 12.0
    # Round values set before the traffic drive was scored with them (docs/experiments.md, "Movers cut off by the image's edge").
    cut_off_contacts: int = 8
    cut_off_max_rms_m: float = 0.25
    cut_off_max_jump: float = 0.15

    def __post_init__(self) -> None:
        if isinstance(self.keep_classes, str):
            raise InputError(f"movers.keep_classes: expected a list of class names, got the string {self.keep_classes!r}")
        self.keep_classes = tuple(str(c) for c in self.keep_classes)
        unknown = [c for c in self.keep_classes if c not in CLASS_NAMES]
        if unknown:
            raise InputError(f"movers.keep_classes: unknown class name(s) {unknown}; known: {list(CLASS_NAMES)}")
        if not (isinstance(self.cut_off_contacts, int) and self.cut_off_contacts >= 0):
            raise InputError(f"movers.cut_off_contacts: an integer >= 0 (0 = off), got {self.cut_off_contacts!r}")
        for k in ("cut_off_max_rms_m", "cut_off_max_jump"):
            if not getattr(self, k) > 0:
                raise InputError(f"movers.{k}: a number > 0, got {getattr(self, k)!r}")


def check_movers(stixels: StixelWorld, flow: torch.Tensor, motion: Motion, point_depth: torch.Tensor | None = None,
                 params: MoverCheckParams | None = None, scale_known: bool = True) -> StixelWorld:
    """Dynamic stixels that a static object explains become static (see the module docstring).

    All dynamic stixels are checked at once: their pixels are gathered into flat arrays with a
    stixel index, and the per-stixel medians are segment medians of the sorted values (the lower
    median, as ``torch.median``). Only those pixels are triangulated when ``point_depth`` is not
    given (the midpoint method of :func:`monostixels.post.sfm.triangulate`).

    Args:
        stixels: the solver's result.
        flow: (2, H, W) current -> previous, pixels.
        motion: the camera motion used by the solver (metres).
        point_depth: (H, W) per-pixel depth triangulated from ``flow`` and ``motion`` (metres;
            invalid = negative, inf or NaN), e.g. the SfM baseline's; None = triangulated here.
        params: thresholds.
        scale_known: False where the camera motion's length is uncertain (``motion.max_scale_std``): a
            stixel whose flow a static plane explains (it fits the epipolar geometry) stands still whatever
            its depth, since a wrong length moves every static depth, and keeps the scene model's depth (the
            flow's scales with that length); only a flow that breaks the epipolar constraint keeps a stixel
            dynamic, by more than ``max_static_residual_px`` and than the frame's static objects' flow breaks
            it (:data:`STATIC_EPIPOLAR_QUANTILE`): the median :func:`epipolar_distance` of its pixels (no
            triangulation, no kept classes, no depth or contact test).

    Returns:
        A new :class:`StixelWorld`; ``status.counts.static_checked`` = number of dynamic stixels made static.
    """
    prm = params or MoverCheckParams()
    H, W = stixels.image_size
    dyn = torch.nonzero(stixels.type == DYNAMIC_OBJECT).flatten()
    if not prm.enabled or dyn.numel() == 0 or float(motion.t.norm()) == 0.0:
        return stixels  # without translation nothing triangulates (a flagged degenerate frame)
    K = stixels.K.double()
    R, t = motion.R.double(), motion.t.double()
    S = dyn.numel()
    # Pixels of every dynamic stixel, row-major within a stixel; sid = index into dyn.
    c0 = stixels.column[dyn].long() * stixels.column_width
    c1 = torch.clamp(c0 + stixels.column_width, max=W)
    v0, v1 = stixels.v_top[dyn].long(), stixels.v_bottom[dyn].long() + 1
    widths = c1 - c0
    counts = (v1 - v0) * widths
    sid = torch.repeat_interleave(torch.arange(S), counts)
    local = torch.arange(int(counts.sum())) - torch.repeat_interleave(torch.cumsum(counts, 0) - counts, counts)
    vi = v0[sid] + local // widths[sid]
    ui = c0[sid] + local % widths[sid]
    vv, uu = vi.double(), ui.double()
    fu, fv = flow[0, vi, ui].double(), flow[1, vi, ui].double()
    if not scale_known:
        # Only a flow off the epipolar lines makes a mover, by more than the frame's static objects' own flow
        # is off them: where the camera's rotation or direction is as uncertain as its length (a phone behind
        # a windscreen), the static world breaks the epipolar geometry too, and that is no motion of its own.
        # The distance needs no depth (nothing is triangulated), so every stixel is judged. Their
        # depths stay the scene model's (the flow's static depth scales with the very length that is uncertain).
        e_epi = segment_lower_median(epipolar_distance(K, R, t, uu, vv, fu, fv), sid, counts)
        bound = max(prm.max_static_residual_px, _static_epipolar_quantile(stixels, flow, K, R, t))
        return _stand_still(stixels, dyn, e_epi <= bound, None, S)
    if point_depth is None:
        # In the flow's dtype, as triangulate() returns it (the decisions then match the full-frame path).
        z = triangulate_points(K, R, t, uu, vv, fu, fv)[0].to(flow.dtype if flow.is_floating_point() else torch.float32).double()
    else:
        z = point_depth[vi, ui].double()
    ok = torch.isfinite(z) & (z >= prm.min_depth) & (z <= prm.max_depth)
    n_ok = torch.bincount(sid[ok], minlength=S)
    n_all = stixels.normals().double()[dyn]  # S x 3
    rays = pixel_rays(K, uu[ok], vv[ok])
    proj = z[ok] * (rays * n_all[sid[ok]]).sum(-1)
    d_s = segment_lower_median(proj, sid[ok], n_ok)
    # The stixel's median static-plane residual (over all its pixels), where a static fit exists.
    fit = (n_ok >= prm.min_pixels) & (d_s > 0)
    d_fit = torch.where(fit, d_s, torch.ones_like(d_s))
    Hs = homography(K, R, t, n_all, 1.0 / d_fit)  # S x 3 x 3
    up, vp = apply_homography(Hs[sid], uu, vv)
    res = torch.hypot(up - uu - fu, vp - vv - fv)
    e_s = segment_lower_median(res, sid, counts)
    p_model = stixels.inverse_depth[dyn].double()
    d_model = torch.where(p_model > 0, 1.0 / p_model, torch.full_like(p_model, math.inf))
    explained = fit & ~(e_s > prm.max_static_residual_px)
    if math.isfinite(prm.max_dynamic_residual_ratio):
        # The solver's own dynamic plane of the stixel: g = p (t - R Δ) (geometry.dynamic_homography).
        g = p_model[:, None] * (t[None] - stixels.motion[dyn].double() @ R.T)
        Hd = dynamic_homography(K, R, n_all, g)
        upd, vpd = apply_homography(Hd[sid], uu, vv)
        e_d = segment_lower_median(torch.hypot(upd - uu - fu, vpd - vv - fv), sid, counts)
        explained |= fit & (e_d >= prm.max_dynamic_residual_ratio * e_s)
    if prm.keep_classes:
        kept = torch.tensor([CLASS_NAMES.index(c) for c in prm.keep_classes], dtype=torch.long)
        explained &= ~torch.isin(stixels.cls[dyn].long(), kept)
    # The stixel directly below each dynamic stixel (its column, starting at the next row), -1 = none.
    N = stixels.type.numel()
    start = _starts(stixels)
    below = start[stixels.column[dyn].long(), (v1).clamp(max=H)]
    has_below = below >= 0
    bi = below.clamp(min=0)
    p_all = stixels.inverse_depth.double()
    p_below = p_all[bi]
    dyn_below = has_below & (stixels.type[bi] == DYNAMIC_OBJECT)
    pos = torch.full((N,), -1, dtype=torch.long)
    pos[dyn] = torch.arange(S)
    below_pos = torch.where(dyn_below, pos[bi], torch.full_like(bi, -1))
    # Decided bottom-up along each column (a stixel's reference depends on the decision below it):
    # - on a ground stixel: it stands on that ground. A static object there meets the ground where its
    #   static plane does; that contact row must be (within the bottom's accuracy) the scene model's
    #   contact row, else the flow's depth is the motion's doing (a mover along its epipolar lines).
    # - on a dynamic stixel that stays dynamic: part of the same moving stack, which stands on the
    #   stack's ground (same test, the structural prior gave the stack the depth of its contact).
    # - on a dynamic stixel made static: it stood on that object's (wrong) depth; the reference
    #   depth becomes that object's static depth, and no ground contact is known.
    # - on a thin object (at most ``contact_sliver_rows`` tall) that stands on a ground stixel: it
    #   stands on that ground too. With a flow trusted to sub-pixel level (flow=deepflow) the rows
    #   where a car meets the road (shadow, bumper) become a stixel of their own, whose flow is the
    #   road's; made static, it would otherwise hand the car above it its static depth and no contact.
    below2 = start[stixels.column.long()[bi], (stixels.v_bottom.long()[bi] + 1).clamp(max=H)]
    b2 = below2.clamp(min=0)
    sliver = (has_below & ((stixels.type[bi] == STATIC_OBJECT) | (stixels.type[bi] == DYNAMIC_OBJECT))
              & ((stixels.v_bottom[bi] - stixels.v_top[bi] + 1).double() <= prm.contact_sliver_rows)
              & (below2 >= 0) & (stixels.type[b2] == GROUND) & (p_all[b2] > 0))
    p_gnd = torch.where(sliver, p_all[b2], p_below)
    on_gnd = ((has_below & (stixels.type[bi] == GROUND)) | sliver) & (p_gnd > 0) & d_model.isfinite()
    d_g0 = torch.where(on_gnd, 1.0 / p_gnd.clamp(min=1e-12), torch.full_like(p_gnd, math.nan))
    ng = stixels.ground_normal.double()
    bp = below_pos.clamp(min=0)
    still = torch.zeros(S, dtype=torch.bool)
    d_g = d_g0
    for _ in range(S + 1):
        b_still = (below_pos >= 0) & still[bp]
        d_g = torch.where(on_gnd, d_g0, torch.where((below_pos >= 0) & ~b_still & prm.follow_below, d_g[bp], math.nan))
        stands = d_g.isfinite()
        d_gs = torch.where(stands, d_g, torch.ones_like(d_g))
        gap = (_contact_row(K, n_all, ng, d_fit, d_gs) - _contact_row(K, n_all, ng, torch.where(stands, d_model, d_fit), d_gs)).abs()
        on_still = b_still & prm.follow_below
        d_ref = torch.where(on_still, d_s[bp], d_model)
        off = d_ref / d_s - 1.0
        # Behind an object that stands still, a static stixel is the background above it (any distance
        # farther): only one nearer than that object contradicts it (allow_behind_still).
        off = torch.where(on_still & prm.allow_behind_still, off.clamp(min=0.0), off.abs())
        new = explained & ~(stands & (gap > prm.max_contact_gap_px)) & ~(off > prm.min_depth_discrepancy)
        if torch.equal(new, still):
            break
        still = new
    if prm.isolated_stand_still:
        # A moving object is wider than one column: a stixel still dynamic with no dynamic stixel in an
        # adjacent column at overlapping rows is a flow artefact (object edges, single-column slivers).
        rem = ~still
        c_d, a_d, b_d = stixels.column[dyn].long(), v0, v1 - 1
        beside = neighbours(c_d, a_d, b_d) & rem[None, :]
        alone = rem & fit & ~beside.any(1)
        if prm.keep_classes:
            alone &= ~torch.isin(stixels.cls[dyn].long(), kept)
        still = still | alone
    return _stand_still(stixels, dyn, still, d_s, S)


#: The quantile of the static objects' distances from their epipolar lines that a mover's must exceed
#: where the camera motion's length is uncertain (:func:`check_movers`): their 9 in 10 nearest.
STATIC_EPIPOLAR_QUANTILE = 0.9


def epipolar_distance(K: torch.Tensor, R: torch.Tensor, t: torch.Tensor, u: torch.Tensor, v: torch.Tensor,
                      fu: torch.Tensor, fv: torch.Tensor) -> torch.Tensor:
    """Pixels (N,) from each flow's end ``(u + fu, v + fv)`` in the previous image to the epipolar line of
    ``(u, v)`` under ``X_prev = R X + t`` (``F = K^-T [t]x R K^-1``; kornia's one-sided distance, ``inf`` at
    the epipole); any length of ``t``; computed in float64."""
    K = K.double()
    E = cross_product_matrix(t.double()) @ R.double()
    F = fundamental_from_essential(E[None], K[None], K[None])
    cur = torch.stack([u, v], -1).double()
    prev = torch.stack([u + fu, v + fv], -1).double()
    return left_to_right_epipolar_distance(cur[None], prev[None], F)[0]


def _static_epipolar_quantile(stixels: StixelWorld, flow: torch.Tensor, K: torch.Tensor, R: torch.Tensor,
                              t: torch.Tensor) -> float:
    """:data:`STATIC_EPIPOLAR_QUANTILE` of the static object stixels' pixels' :func:`epipolar_distance`
    (pixels, on a grid of every 4th pixel), 0 without any."""
    typ = stixels.type_map()
    vs, us = torch.nonzero(typ[::4, ::4] == STATIC_OBJECT, as_tuple=True)
    if vs.numel() == 0:
        return 0.0
    vs, us = vs * 4, us * 4
    d = epipolar_distance(K, R, t, us.double(), vs.double(), flow[0, vs, us].double(), flow[1, vs, us].double())
    d = d[torch.isfinite(d)]  # the epipole's pixel has no line
    return float(torch.quantile(d, STATIC_EPIPOLAR_QUANTILE)) if d.numel() else 0.0


def _stand_still(stixels: StixelWorld, dyn: torch.Tensor, still: torch.Tensor, d_s: torch.Tensor | None,
                 S: int) -> StixelWorld:
    """``stixels`` with the dynamic stixels ``dyn[still]`` made static objects at their static depths ``d_s``
    (S,) metres (None: their depths kept), with zero motion and their classes kept; ``status.counts.static_checked``
    counts them."""
    k = dyn[still]
    types, p_out = stixels.type.clone(), stixels.inverse_depth.clone()
    mot, tau = stixels.motion.clone(), stixels.tau.clone()
    types[k] = STATIC_OBJECT
    if d_s is not None:
        p_out[k] = (1.0 / d_s[still]).to(p_out.dtype)
    mot[k] = 0.0
    tau[k] = 0.0  # (t̃x, t̃y) belong to dynamic stixels only
    changed = int(still.sum())
    status = stixels.status.copy()
    status.counts.static_checked = changed
    logger.debug("mover check: %d of %d dynamic stixels explained by a static object", changed, S)
    return dataclasses.replace(stixels, type=types, inverse_depth=p_out, motion=mot, tau=tau, status=status)


def static_only(stixels: StixelWorld) -> StixelWorld:
    """The stixels with every dynamic one made a static object (its motion and ``tau`` zeroed, its depth
    kept): for a frame whose camera motion is unknown, where no flow vector can be told to be an object's
    own motion. ``status.counts.movers_suppressed`` counts them."""
    dyn = stixels.type == DYNAMIC_OBJECT
    status = stixels.status.copy()
    status.counts.movers_suppressed = int(dyn.sum())
    if not bool(dyn.any()):
        return dataclasses.replace(stixels, status=status)
    types = torch.where(dyn, torch.full_like(stixels.type, STATIC_OBJECT), stixels.type)
    mot = stixels.motion.masked_fill(dyn[:, None], 0.0)
    tau = stixels.tau.masked_fill(dyn[:, None] if stixels.tau.dim() == 2 else dyn, 0.0)
    return dataclasses.replace(stixels, type=types, motion=mot, tau=tau, status=status)


def _starts(stixels: StixelWorld) -> torch.Tensor:
    """(columns, H + 1) int64: the index of the stixel whose top row is each row of each column, -1 where none
    (row H: none); the stixel directly below stixel ``i`` is ``[column_i, v_bottom_i + 1]``."""
    start = torch.full((stixels.num_columns, stixels.image_size[0] + 1), -1, dtype=torch.long)
    start[stixels.column.long(), stixels.v_top.long()] = torch.arange(stixels.type.numel())
    return start


def _contact_row(K: torch.Tensor, n_obj: torch.Tensor, n_g: torch.Tensor, d: torch.Tensor, d_g: torch.Tensor) -> torch.Tensor:
    """Row (S,) where an upright plane ``n_obj^T X = d`` meets the ground ``n_g^T X = d_g`` in the
    vertical plane of its column centre (``n_obj`` is that centre's horizontal viewing direction)."""
    X = d[:, None] * n_obj + d_g[:, None] * n_g
    x = X @ K.T
    return x[:, 1] / x[:, 2]


#: Rows between the pixels of a static stixel that vote on whether it recedes (:func:`settle_receding`).
_RECEDE_STRIDE = 4


def settle_receding(stixels: StixelWorld, flow: torch.Tensor, motion: Motion, height: float) -> StixelWorld:
    """Static object stixels whose flow puts them behind the camera take the scene model's depth.

    An object in front of the camera whose flow triangulates behind it on most of its pixels (those with
    parallax) is no static object: it pulls away faster than the camera drives, along its epipolar lines (a
    truck beside the camera that the semantic net calls a building; the KITTI traffic drive). Its flow gives
    it no depth; the scene model does: it stands where its bottom row meets the ground (the ground stixel
    directly below, else the reference ground ``height`` below the camera), or at the depth of the object
    below it. Its type and class stay (its motion is not measured); ``status.counts.receding_static`` counts them.

    Args:
        stixels: the solver's result (after the mover check). flow: (2, H, W) current -> previous, pixels.
        motion: the camera motion (metres). height: the camera height above the road (m).

    Returns:
        A new :class:`StixelWorld`, or ``stixels`` where nothing recedes.
    """
    stat = torch.nonzero(stixels.type == STATIC_OBJECT).flatten()
    if stat.numel() == 0 or float(motion.t.norm()) == 0.0:
        return stixels
    K = stixels.K.double()
    H, W = stixels.image_size
    c0 = stixels.column[stat].long() * stixels.column_width
    widths = torch.clamp(c0 + stixels.column_width, max=W) - c0
    v0, v1 = stixels.v_top[stat].long(), stixels.v_bottom[stat].long() + 1
    # The vote needs no pixel of every row: the column's middle pixel on every _RECEDE_STRIDE-th row (a
    # twentieth of the pixels at w_s = 5; the majority is the same, a frame's check 40 ms -> 3 ms).
    counts = (v1 - v0 + _RECEDE_STRIDE - 1) // _RECEDE_STRIDE
    sid = torch.repeat_interleave(torch.arange(stat.numel()), counts)
    local = torch.arange(int(counts.sum())) - torch.repeat_interleave(torch.cumsum(counts, 0) - counts, counts)
    vi = v0[sid] + local * _RECEDE_STRIDE
    ui = c0[sid] + (widths[sid] - 1) // 2
    # Parallax of at least a pixel: below it the flow's noise alone puts points behind.
    z, _, _ = triangulate_points(K, motion.R.double(), motion.t.double(), ui.double(), vi.double(),
                                 flow[0, vi, ui].double(), flow[1, vi, ui].double(), min_parallax_rad=1.0 / float(K[0, 0]))
    finite = torch.isfinite(z)
    n_fin = torch.bincount(sid[finite], minlength=stat.numel())
    n_behind = torch.bincount(sid[finite & (z < 0)], minlength=stat.numel())
    recede = (n_fin > 0) & (2 * n_behind > n_fin)
    if not bool(recede.any()):
        return stixels
    k = stat[recede]
    # Standing depth: the lower edge's ray meets the ground below (its plane distance 1 / p_g) at the object's
    # plane distance d = (n_obj . r) / (n_g . r) / p_g (core.columns: gravity, standing depth).
    below = _starts(stixels)[stixels.column[k].long(), (stixels.v_bottom[k].long() + 1).clamp(max=H)]
    bi = below.clamp(min=0)
    on_ground = (below >= 0) & (stixels.type[bi] == GROUND) & (stixels.inverse_depth[bi] > 0)
    p_g = torch.where(on_ground, stixels.inverse_depth[bi].double(), torch.full((k.numel(),), 1.0 / height, dtype=torch.float64))
    u_c = stixels.column[k].double() * stixels.column_width + (widths[recede].double() - 1) / 2
    ray = pixel_rays(K, u_c, stixels.v_bottom[k].double() + 0.5)
    n_obj = stixels.normals().double()[k]
    down = (ray * stixels.ground_normal.double()).sum(-1)
    p_stand = torch.where(down > 1e-9, p_g * down / (ray * n_obj).sum(-1), stixels.inverse_depth[k].double())
    # On an object below, the object's depth (the structural prior); stixels run bottom to top within a
    # column, so the one below is settled first.
    on_object = (below >= 0) & ((stixels.type[bi] == STATIC_OBJECT) | (stixels.type[bi] == DYNAMIC_OBJECT))
    p_out = stixels.inverse_depth.clone()
    for j in range(k.numel()):
        p_out[k[j]] = (p_out[bi[j]] if bool(on_object[j]) else p_stand[j]).to(p_out.dtype)
    status = stixels.status.copy()
    status.counts.receding_static = int(k.numel())
    logger.debug("%d static stixels recede (flow behind the camera): scene-model depths", k.numel())
    return dataclasses.replace(stixels, inverse_depth=p_out, status=status)
