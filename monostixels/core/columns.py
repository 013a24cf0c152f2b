"""The solver's data per column: cells, the stixel hypotheses and their prefix-summed costs.

Steps 1 and 2 of :mod:`monostixels.core.solver`'s method: each column of width ``w_s`` is cut into cells
of ``r`` pixel rows counted from the image bottom, with the flow, covariance and semantic scores
averaged per cell (:func:`prepare_columns`, a :class:`ColumnProblem`); every ``hypothesis_stride``-th
cell gives a ground / static-object inverse depth or a dynamic object's motion, and the flow cost
of each hypothesis on each cell is prefix-summed over the cells (:func:`flow_prefix`), as are the
semantic costs (:func:`semantic_prefix`). The DP (:func:`monostixels.core.solver.solve_columns`) reads
segment costs as differences of these sums. Where the C++ kernel is loaded the same expressions
run there (``csrc/column_dp.cpp``).
"""
from __future__ import annotations

import inspect
import math
from dataclasses import dataclass
from typing import Any, Sequence

import torch

from monostixels.core import _dp_cpp
from monostixels.core.classes import GROUND, NUM_CLASSES, SKY, TYPE_CLASSES
from monostixels.core.energy import PriorParams, flow_cost
from monostixels.core.geometry import (
    Camera,
    Motion,
    ground_basis,
    object_normals,
    pixel_rays,
    solve_dynamic_dof,
    solve_static_dof,
)
from monostixels.core.solver_config import SolverConfig

__all__ = ["ColumnProblem", "prepare_columns", "beyond_horizon", "Z_MIN", "column_geometry", "cpp_prep", "flow_geometry",
           "flow_prefix", "hypotheses", "semantic_prefix"]

#: Default class of each type when there is no semantic input (road, building, vehicle, sky).
_DEFAULT_CLASS = (0, 3, 6, 9)
# Bits of the per-cell mask of semantic_prefix: the sky is not seen there, the ground is not.
_UNSEEN_SKY, _UNSEEN_GROUND = 1, 2
# Which bit of the unseen mask each class pays for (semantic_prefix): the sky class the sky's, the ground classes the ground's.
_UNSEEN_RULE = torch.tensor([_UNSEEN_SKY if k in TYPE_CLASSES[SKY] else _UNSEEN_GROUND if k in TYPE_CLASSES[GROUND] else 0
                             for k in range(NUM_CLASSES)], dtype=torch.uint8)
#: Hypothesis-cell pairs evaluated at once when computing flow costs (bounds peak memory).
_CHUNK_ELEMENTS = 4_000_000
#: A predicted point with ``z`` at or below this (homogeneous, px) is behind the camera: flow cap.
Z_MIN = 1e-9
#: Singular-system threshold of the per-cell fits (geometry.solve_static_dof / solve_dynamic_dof).
_FIT_EPS = inspect.signature(solve_static_dof).parameters["eps"].default


@dataclass
class ColumnProblem:
    """Per-column, per-cell inputs of the DP for C columns (of one or several frames), n cells each.

    Cell 0 is at the image bottom. Attributes (``C`` columns, ``n`` cells):
        K, R: (C, 3, 3); t, n_g, n_obj: (C, 3); h_cam: (C,) metres; u: (C,) column-centre u (px).
        v: (n,) cell-centre rows; v_edge: (n,) row of each cell's bottom boundary; rows: (n,)
        pixel rows per cell. flow: (C, n, 2) px; cov_inv: (C, n, 2, 2); logdet: (C, n).
        nll: (C, n, 10) ``-log`` of the cell-mean class scores, or None without semantics.
        degenerate: (C,) bool, frames whose camera translation carries no depth.
        frame: (C,) int64 frame index; column: (C,) int64 column index within its frame.
        image_size: (H, W).
        checked: whether the kernel's cell sums found every input value valid in the same pass
        (finite flow, covariances and scores; positive definite covariances; scores >= 0: the
        inputs are read once). False on the eager path, which has no such pass, and where a value
        may be bad: :func:`solve_batch` then runs :func:`_check_values`, which names the problem.
    """

    K: torch.Tensor
    R: torch.Tensor
    t: torch.Tensor
    n_g: torch.Tensor
    n_obj: torch.Tensor
    h_cam: torch.Tensor
    u: torch.Tensor
    v: torch.Tensor
    v_edge: torch.Tensor
    rows: torch.Tensor
    flow: torch.Tensor
    cov_inv: torch.Tensor
    logdet: torch.Tensor
    nll: torch.Tensor | None
    degenerate: torch.Tensor
    frame: torch.Tensor
    column: torch.Tensor
    image_size: tuple[int, int]
    checked: bool = False

    @property
    def num_columns(self) -> int:
        return int(self.u.shape[0])

    @property
    def num_cells(self) -> int:
        return int(self.v.shape[0])


# ---------------------------------------------------------------------------------------------
# Column preparation
# ---------------------------------------------------------------------------------------------
def _block_sum(x: torch.Tensor, r: int, w: int, use_cpp: bool = False) -> torch.Tensor:
    """Sum (B, ch, n, C) of x (B, ch, H, W) over cells of r rows counted from the bottom and columns of w.

    Each row's ``w`` pixels are added left to right, then the cell's rows bottom-up, as strided
    adds (torch's reductions over short axes after flipping and padding the full image took
    twice as long). A partial last column / top cell sums the pixels it has. Where the C++ kernel
    is loaded (and with ``use_cpp``), it adds the same numbers in the same order in one pass.
    """
    B, ch, H, W = x.shape
    n, C = -(-H // r), -(-W // w)
    if use_cpp and x.dtype in (torch.float32, torch.float64) and not x.requires_grad:
        return _dp_cpp.cell_sums(x, r, w)  # the same sums in the same order, one pass (csrc/column_dp.cpp)

    def add_up(parts: torch.Tensor, dim: int) -> torch.Tensor:
        out = parts.select(dim, 0)
        for k in range(1, parts.shape[dim]):
            out = out + parts.select(dim, k)
        return out

    full = W // w
    rows = add_up(x[..., :full * w].reshape(B, ch, H, full, w), -1)  # B x ch x H x full
    if full < C:
        rows = torch.cat([rows, add_up(x[..., full * w:, None], -2)], -1)
    rows = rows.flip(-2)  # row 0 = image bottom
    if n * r != H:
        rows = torch.nn.functional.pad(rows, (0, 0, 0, n * r - H))
    return add_up(rows.reshape(B, ch, n, r, C), 3)


def prepare_columns(
    flow: torch.Tensor,
    cov: torch.Tensor,
    scores: torch.Tensor | None,
    cameras: Sequence[Camera],
    motions: Sequence[Motion],
    cfg: SolverConfig,
) -> ColumnProblem:
    """Cut frames into columns and cells and average the inputs per cell.

    Args:
        flow: (B, 2, H, W) current -> previous, pixels.
        cov: (B, H, W, 2, 2) flow covariance, pixels^2.
        scores: (B, 10, H, W) class scores or None.
        cameras, motions: one per frame.
        cfg: solver settings (column width, cell rows, dtype, min_translation).

    The kernel's cell sums check the input values in the same pass (``ColumnProblem.checked``).
    """
    dt = cfg.torch_dtype
    B, _, H, W = flow.shape
    r, w = cfg.cell_rows, cfg.column_width
    n, C = -(-H // r), -(-W // w)
    rows = torch.clamp(torch.tensor(H, dtype=dt) - torch.arange(n, dtype=dt) * r, max=r)
    widths = torch.clamp(torch.tensor(W, dtype=dt) - torch.arange(C, dtype=dt) * w, max=w)
    count = rows[:, None] * widths[None, :]  # n x C pixels per cell
    cpp = cfg.backend != "eager" and _dp_cpp.available()
    checked = cpp

    def cell_means(x: torch.Tensor, check: int) -> torch.Tensor:
        """(B, C, n, ch) means of x (B, ch, H, W) over the cells."""
        nonlocal checked
        if not (cpp and not x.requires_grad):
            checked = False
            return (_block_sum(x, r, w) / count).permute(0, 3, 2, 1)
        means, ok = _dp_cpp.cell_means_checked(x, r, w, count, check)  # the same bits, and the check
        checked &= ok
        return means

    fl = cell_means(flow.to(dt), _dp_cpp.CHECK_FINITE)  # B x C x n x 2
    # (B, 4, H, W) view of the (B, H, W, 2, 2) memory: the kernel reads the 4 entries per pixel in place.
    cv = cov.to(dt).contiguous().permute(0, 3, 4, 1, 2).reshape(B, 4, H, W)
    cv = cell_means(cv, _dp_cpp.CHECK_POSITIVE_DEFINITE).reshape(B, C, n, 2, 2)
    nll = None
    if scores is not None:
        sc = cell_means(scores.to(dt), _dp_cpp.CHECK_NONNEGATIVE)  # B x C x n x 10
        # In place on the fresh means: each MB-sized temporary costs page faults when it is mmap'ed.
        nll = sc.clamp_(min=1e-12).log_().neg_().reshape(B * C, n, NUM_CLASSES)

    j0 = torch.arange(n, dtype=dt) * r  # bottom-based index of each cell's lowest row
    v = (H - 1) - (j0 + (rows - 1) / 2)
    v_edge = H - j0 - 0.5
    u = torch.arange(C, dtype=dt) * w + (widths - 1) / 2

    K = torch.stack([c.K.to(dt) for c in cameras])
    n_g = torch.stack([c.ground_normal.to(dt) for c in cameras])
    h = torch.tensor([c.height for c in cameras], dtype=dt)
    R = torch.stack([m.R.to(dt) for m in motions])
    t = torch.stack([m.t.to(dt) for m in motions])
    degenerate = torch.tensor([m.translation_norm < cfg.min_translation for m in motions])

    rep = lambda x: x.repeat_interleave(C, dim=0)  # noqa: E731  (per frame -> per column)
    K_c, n_g_c = rep(K), rep(n_g)
    u_c = u.repeat(B)
    cov_c = cv.reshape(B * C, n, 2, 2)
    det = cov_c[..., 0, 0] * cov_c[..., 1, 1] - cov_c[..., 0, 1] * cov_c[..., 1, 0]
    inv = torch.stack([torch.stack([cov_c[..., 1, 1], -cov_c[..., 0, 1]], -1),
                       torch.stack([-cov_c[..., 1, 0], cov_c[..., 0, 0]], -1)], -2) / det[..., None, None]
    return ColumnProblem(
        K=K_c, R=rep(R), t=rep(t), n_g=n_g_c, n_obj=object_normals(K_c, n_g_c, u_c), h_cam=rep(h),
        u=u_c, v=v, v_edge=v_edge, rows=rows,
        flow=fl.reshape(B * C, n, 2), cov_inv=inv, logdet=torch.log(det),
        nll=nll, degenerate=rep(degenerate), frame=torch.arange(B).repeat_interleave(C),
        column=torch.arange(C).repeat(B), image_size=(H, W), checked=checked,
    )


# ---------------------------------------------------------------------------------------------
# Hypotheses and their prefix-summed flow costs
# ---------------------------------------------------------------------------------------------
@dataclass
class _Hypotheses:
    p_ground: torch.Tensor   # C x Kg
    p_object: torch.Tensor   # C x Ko
    tau: torch.Tensor        # C x Kd x 2
    B: torch.Tensor          # C x 3 x 2 ground-plane basis
    g: torch.Tensor | None = None  # C x Kd x 3 K B tau, if already computed (see flow_geometry)


def _window_median(x: torch.Tensor, stride: int) -> torch.Tensor:
    """Median over windows of ``stride`` cells along dim 1 of x (C, n, ...) -> (C, ceil(n / stride), ...).

    NaNs (cells without a solution) are ignored; a window without any value gives NaN.
    """
    C, n = x.shape[:2]
    m = -(-n // stride)
    pad = m * stride - n
    if pad:
        x = torch.cat([x, x.new_full((C, pad) + tuple(x.shape[2:]), float("nan"))], dim=1)
    return x.reshape((C, m, stride) + tuple(x.shape[2:])).nanmedian(dim=2).values


def _bottom_ray_ratio(prob: ColumnProblem) -> torch.Tensor:
    """(C, n) ratio ``n_g.r / n_obj.r`` of the ray ``r`` through each cell's lower edge.

    An object with inverse depth ``p`` whose bottom is that edge stands ``1/p_g - q/p`` metres above
    a ground of inverse height ``p_g``: it stands on it at ``p = q p_g`` (gravity, standing depth).
    """
    ray_b = pixel_rays(prob.K[:, None], prob.u[:, None], prob.v_edge[None, :])
    return (ray_b * prob.n_g[:, None]).sum(-1) / (ray_b * prob.n_obj[:, None]).sum(-1)


@dataclass
class _Geometry:
    """Per-cell terms shared by the hypotheses, the flow costs and the priors (computed once per solve).

    ray (C, n, 3): ``K^-1 x`` of each cell centre (unit z); a (C, n, 3): ``K R K^-1 x``; cK (C, 3):
    ``K t``; s_g, s_o (C, n): ``n^T K^-1 x`` of the ground and object normals; q (C, n): the
    bottom-ray ratio (:func:`_bottom_ray_ratio`). A static hypothesis ``p`` predicts
    ``a + p s cK``, a dynamic one ``a + s_o K B tau``, the sky ``a``.
    """

    ray: torch.Tensor
    a: torch.Tensor
    cK: torch.Tensor
    s_g: torch.Tensor
    s_o: torch.Tensor
    q: torch.Tensor


def column_geometry(prob: ColumnProblem, cpp: bool = False) -> _Geometry:
    """The terms of :class:`_Geometry`, with the expressions of geometry.static_dof_system (same bits).

    ``cpp``: the same expressions cell by cell in one pass (csrc/column_dp.cpp; tests/test_solver_fast.py).
    """
    if cpp:
        ray, a, s_g, s_o, q = _dp_cpp.geometry(prob.K, prob.K @ prob.R, prob.n_g, prob.n_obj, prob.u, prob.v,
                                               prob.v_edge)
        return _Geometry(ray=ray, a=a, cK=(prob.K @ prob.t[..., None])[..., 0], s_g=s_g, s_o=s_o, q=q)
    ray = pixel_rays(prob.K[:, None], prob.u[:, None], prob.v[None, :])  # C x n x 3
    return _Geometry(
        ray=ray,
        a=((prob.K @ prob.R)[:, None] @ ray[..., None])[..., 0],
        cK=(prob.K @ prob.t[..., None])[..., 0],
        s_g=(ray * prob.n_g[:, None]).sum(-1),
        s_o=(ray * prob.n_obj[:, None]).sum(-1),
        q=_bottom_ray_ratio(prob),
    )


def _fits(prob: ColumnProblem, geo: _Geometry) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every cell's own hypotheses: ground and object inverse depth (C, n), dynamic tau (C, n, 2), B (C, 3, 2).

    The systems of geometry.static_dof_system / dynamic_dof_system built from the shared terms
    (the same expressions, so the same bits; tests/test_solver_fast.py compares them), solved by
    geometry.solve_static_dof / solve_dynamic_dof. NaN where a system is singular.
    """
    a, c = geo.a, geo.cK[:, None]  # C x n x 3, C x 1 x 3
    up, vp = prob.u[:, None] + prob.flow[..., 0], prob.v[None] + prob.flow[..., 1]
    b = torch.stack([a[..., 0] - up * a[..., 2], a[..., 1] - vp * a[..., 2]], -1)
    cu, cv = up * c[..., 2] - c[..., 0], vp * c[..., 2] - c[..., 1]
    p_g, p_o = (solve_static_dof(torch.stack([s * cu, s * cv], -1), b) for s in (geo.s_g, geo.s_o))
    Bm = ground_basis(prob.n_g)
    M = (prob.K @ Bm)[:, None]  # C x 1 x 3 x 2: K B
    s = geo.s_o[..., None]
    A = torch.stack([s * (up[..., None] * M[..., 2, :] - M[..., 0, :]),
                     s * (vp[..., None] * M[..., 2, :] - M[..., 1, :])], -2)
    return p_g, p_o, solve_dynamic_dof(A, b), Bm


def hypotheses(prob: ColumnProblem, cfg: SolverConfig, geo: _Geometry | None = None) -> _Hypotheses:
    """Per-column hypothesis sets of the three flow-fitted types (see module docstring).

    Every cell gives one hypothesis per type from its own flow vector. With
    ``hypothesis_stride = s > 1`` the cells are grouped in windows of ``s`` and each window gives
    the median of its cells' hypotheses: exact for a plane that covers most of a window, robust
    to flow noise, and ``s`` times fewer hypotheses (the DP cost is linear in their number).
    ``geo``: the problem's :func:`column_geometry`, if already computed.
    """
    geo = column_geometry(prob) if geo is None else geo
    s = cfg.hypothesis_stride
    p_min, p_max = 1.0 / cfg.max_depth, 1.0 / cfg.min_depth
    p_ref = (1.0 / prob.h_cam)[:, None]
    if s == 1 and cpp_prep(prob, cfg):
        # The same expressions, cell by cell in one pass (csrc/column_dp.cpp; tests/test_solver_fast.py).
        Bm = ground_basis(prob.n_g)
        p_g, p_o, tau, g = _dp_cpp.hypotheses(
            geo.a, geo.cK, geo.s_g, geo.s_o, geo.q, prob.u, prob.v, prob.flow, prob.K @ Bm, p_ref[:, 0],
            prob.degenerate, p_min, p_max, _FIT_EPS, cfg.standing_hypotheses)
        return _Hypotheses(p_ground=p_g, p_object=p_o, tau=tau, B=Bm, g=g)

    def valid(p: torch.Tensor) -> torch.Tensor:
        ok = torch.isfinite(p) & (p >= p_min) & (p <= p_max)
        return torch.where(ok, p, torch.full_like(p, float("nan")))

    p_g, p_o, tau, Bm = _fits(prob, geo)
    p_g, p_o = valid(p_g), valid(p_o)
    if s > 1:
        p_g, p_o, tau = _window_median(p_g, s), _window_median(p_o, s), _window_median(tau, s)
    if cfg.standing_hypotheses:
        # The scene model's depth of an object whose bottom is at each cell's lower edge: it stands
        # on the reference ground there. Where the flow fails (every hypothesis at the cap, e.g. a
        # near wall moving 100+ px) the priors can then still place it.
        p_stand = valid(geo.q * p_ref)
        if s > 1:
            p_stand = p_stand[:, ::s]
        p_o = torch.cat([p_o, p_stand], dim=1)
    # Without translation the flow says nothing about depth: the ground is the reference ground.
    p_g = torch.where(prob.degenerate[:, None], torch.full_like(p_g, float("nan")), p_g)
    # Missing hypotheses are replaced by the reference ground (always in the ground set), by
    # the farthest object, and by tau = 0: duplicates never change a minimum.
    p_g = torch.cat([torch.where(torch.isnan(p_g), p_ref, p_g), p_ref], dim=1)
    p_o = torch.where(torch.isnan(p_o), torch.full_like(p_o, p_min), p_o)
    tau = torch.where(torch.isfinite(tau), tau, torch.zeros_like(tau))
    return _Hypotheses(p_ground=p_g, p_object=p_o, tau=tau, B=Bm)


def _row_costs(prob: ColumnProblem, Hx: torch.Tensor, prm: PriorParams) -> torch.Tensor:
    """Flow cost (C, K, n) per cell of predicted points ``H x`` (C, K, n, 3), weighted by rows."""
    z = Hx[..., 2]
    ok = z > Z_MIN
    zs = torch.where(ok, z, torch.ones_like(z))
    up = prob.u[:, None, None] + prob.flow[:, None, :, 0]
    vp = prob.v[None, None, :] + prob.flow[:, None, :, 1]
    res = torch.stack([up - Hx[..., 0] / zs, vp - Hx[..., 1] / zs], -1)
    c = flow_cost(res, prob.cov_inv[:, None], prob.logdet[:, None], prm.alpha_F)
    c = torch.where(ok, c, torch.as_tensor(prm.alpha_F, dtype=c.dtype).expand_as(c))
    return c * prob.rows * prm.delta_F


def beyond_horizon(cost: torch.Tensor, impossible: torch.Tensor, prob: ColumnProblem, prm: PriorParams) -> torch.Tensor:
    """Flow cost (..., n) with the cells where a type cannot be seen (``impossible``) at the cap.

    With a flat ground plane below the camera, ground is seen only below the horizon (above it
    the ray meets the plane behind the camera) and sky only above it (below it the ray meets the
    ground first). Such cells cost what a point behind the camera costs (``alpha_F`` per row).
    Without the rule, near the focus of expansion (flow ~ 0 at every depth) the road can run up
    through the sky and the sky down onto the road.
    """
    return torch.where(impossible, (prm.alpha_F * prm.delta_F * prob.rows).to(cost.dtype), cost)


def _prefix(x: torch.Tensor) -> torch.Tensor:
    """Prefix sums over the last dim with a leading zero: (..., n) -> (..., n + 1)."""
    return torch.nn.functional.pad(torch.cumsum(x, -1), (1, 0))


def flow_geometry(prob: ColumnProblem, hyp: _Hypotheses, geo: _Geometry | None = None) -> tuple[torch.Tensor, ...]:
    """Terms of the predicted points ``H x`` of every hypothesis (shared by both backends).

    Returns:
        a (C, n, 3), cK (C, 3), s_g, s_o (C, n) of :class:`_Geometry`, and g (C, Kd, 3) ``K B tau``
        of the dynamic hypotheses. A static hypothesis ``p`` predicts ``a + p s cK``, a dynamic
        one ``a + s_o g``, the sky ``a``.
    """
    geo = column_geometry(prob) if geo is None else geo
    g = hyp.g
    if g is None:
        M = prob.K @ hyp.B  # C x 3 x 2
        g = (M[:, None] @ hyp.tau[..., None])[..., 0]  # C x Kd x 3: K B tau
    return geo.a, geo.cK, geo.s_g, geo.s_o, g


def flow_prefix(prob: ColumnProblem, hyp: _Hypotheses, prm: PriorParams,
                geo: _Geometry | None = None) -> list[torch.Tensor]:
    """Prefix-summed flow cost (C, K_T, n + 1) of every hypothesis of every type."""
    a, cK, s_g, s_o, g = flow_geometry(prob, hyp, geo)

    def chunked(Hx_of: Any, K: int) -> torch.Tensor:
        # Hypotheses in chunks: the (C, K, n, 3) points of all at once are the peak memory at r = 1.
        step = max(1, _CHUNK_ELEMENTS // max(1, prob.num_columns * prob.num_cells))
        return torch.cat([_row_costs(prob, Hx_of(slice(k, k + step)), prm) for k in range(0, K, step)], 1)

    def static(p: torch.Tensor, s: torch.Tensor, behind: torch.Tensor | None = None) -> torch.Tensor:
        c = chunked(lambda sl: a[:, None] + (p[:, sl, None] * s[:, None, :])[..., None] * cK[:, None, None, :], p.shape[1])
        if behind is not None:
            c = beyond_horizon(c, behind[:, None, :], prob, prm)
        return _prefix(c)

    dyn = _prefix(chunked(lambda sl: a[:, None] + s_o[:, None, :, None] * g[:, sl, None, :], g.shape[1])
                  + prm.alpha_dyn * prob.rows)
    sky = _prefix(beyond_horizon(_row_costs(prob, a[:, None], prm), (s_g > 0)[:, None, :], prob, prm))
    return [static(hyp.p_ground, s_g, behind=s_g <= 0), static(hyp.p_object, s_o), dyn, sky]




def _past_horizon(geo: _Geometry, margin_deg: float, side: float) -> torch.Tensor:
    """(C, n) cells whose ray points more than ``margin_deg`` below (``side`` +1) or above (-1) the horizon of
    the road plane."""
    sin_below = geo.s_g / geo.ray.norm(dim=-1)
    return side * sin_below > math.sin(math.radians(margin_deg))


def semantic_prefix(prob: ColumnProblem, prm: PriorParams, dt: torch.dtype, sky_margin_deg: float = math.inf,
                    geo: _Geometry | None = None, cpp: bool = False,
                    ground_margin_deg: float = math.inf) -> tuple[torch.Tensor, list[list[int]]]:
    """Prefix-summed semantic cost (C, 10, n + 1) and the classes of each type.

    With semantics, the sky class also pays the flow and semantic caps (``alpha_F delta_F + alpha_L
    delta_L`` per row) in cells more than ``sky_margin_deg`` below the horizon, and the ground classes
    in cells more than ``ground_margin_deg`` above it. The flow term alone only caps them there
    (:func:`beyond_horizon`), the cost of any type whose flow fails, so where the flow fails the net's
    score decided: at the image's lower corners, which leave the previous frame, a bright patch of road
    read as sky became a sky stixel a few metres ahead; on a vehicle that drives along with the camera
    (its flow is the sky's), a surface read as road became ground above the horizon, whose depth is
    negative. A road's grade changes by a few degrees, so sky is seen at most slightly below the road
    plane's horizon and ground at most slightly above it. Without semantics: zeros (C, 1, n + 1) and
    the default class of each type. ``cpp``: in the kernel (values only, no gradients).
    """
    C, n = prob.num_columns, prob.num_cells
    if prob.nll is not None:
        unseen = extra = None
        if math.isfinite(sky_margin_deg) or math.isfinite(ground_margin_deg):
            geo = column_geometry(prob) if geo is None else geo
            unseen = torch.zeros(C, n, dtype=torch.uint8)
            if math.isfinite(sky_margin_deg):
                unseen |= _past_horizon(geo, sky_margin_deg, 1.0).to(torch.uint8) * _UNSEEN_SKY
            if math.isfinite(ground_margin_deg):
                unseen |= _past_horizon(geo, ground_margin_deg, -1.0).to(torch.uint8) * _UNSEEN_GROUND
            extra = (prm.alpha_F * prm.delta_F + prm.alpha_L * prm.delta_L) * prob.rows[None, :]
        if cpp:  # the same expressions and sums, one pass (csrc/column_dp.cpp; tests/test_solver_fast.py)
            Lp = _dp_cpp.semantic_prefix(prob.nll, prob.rows, prm.alpha_L, prm.delta_L, unseen,
                                         None if extra is None else extra[0], _UNSEEN_RULE)
            return Lp, [list(cs) for cs in TYPE_CLASSES]
        sem = torch.minimum(prob.nll, prm.alpha_L) * prob.rows[None, :, None] * prm.delta_L
        if unseen is not None:
            rule = (unseen[..., None] & _UNSEEN_RULE) != 0  # C x n x 10
            sem = torch.where(rule, sem + extra[..., None], sem)
        return _prefix(sem.transpose(1, 2)), [list(cs) for cs in TYPE_CLASSES]  # C x 10 x (n + 1)
    return torch.zeros(C, 1, n + 1, dtype=dt), [[c] for c in _DEFAULT_CLASS]


def cpp_prep(prob: ColumnProblem, cfg: SolverConfig) -> bool:
    """Whether the C++ kernel may prepare ``prob`` (values only: no gradients through it)."""
    if cfg.backend == "eager" or prob.flow.dtype not in (torch.float32, torch.float64):
        return False
    if torch.is_grad_enabled() and any(x.requires_grad for x in (prob.flow, prob.K, prob.R, prob.t, prob.n_g)):
        return False
    return _dp_cpp.available()
