"""Batched column solver: the mono-stixel DP over (segment top, type), vectorised over columns.

Structure (paper section C; Cordts et al. 2017 simplification):

1. Each column of width ``w_s`` is cut into cells of ``r`` pixel rows, counted from the image
   bottom (cell 0). Flow, covariance and semantic scores are averaged per cell; every data term
   of a cell is weighted by its number of rows, so energies are per pixel row as in the paper.
2. Hypotheses. The paper's MLESAC step draws one homography from every flow vector of a segment
   and keeps the best. We use the per-column superset (docs/conventions.md, section 3): one
   hypothesis from every ``hypothesis_stride``-th cell of the column (``A p = b`` for ground and
   static objects, ``A (t̃x, t̃y) = b`` for dynamic objects), plus the reference ground for the
   ground type. The flow cost of every hypothesis on every cell is prefix-summed over the cells.
3. Labels of a segment. The paper picks the hypothesis with the lowest flow term, then adds the
   priors. We pick the hypothesis (and class) that minimise the segment's whole energy — flow,
   semantic and structural prior given the best predecessor. This never gives a higher energy
   than the paper's rule, and it makes the DP separable: for every hypothesis and class we keep
   a running minimum over segment bottoms, so a column costs O(cells x hypotheses) instead of
   O(cells^2 x hypotheses). Dynamic-object depth follows the paper: standing on the reference
   ground below, or the depth of the object stixel below.
4. The DP state at a cell boundary is (type of the last stixel); the last stixel's inverse depth
   and the reference ground (last ground stixel, else the camera height) are taken from the
   best predecessor through back-pointers. ``tau > 0`` replaces every min by a soft-min
   ``-tau log sum exp(-x / tau)`` (values only; back-pointers follow the hard minimum), so the
   optimal energy becomes differentiable in the prior parameters and tends to the hard DP as
   ``tau -> 0``.

The Python loop runs over DP stages (cells, ``n`` iterations); every iteration works on all
columns, hypotheses and classes at once. This eager code is the readable definition and the soft
DP. The hard DP (``tau = 0``, no gradients) runs by default (``solver.backend: auto``) in a fused
C++ kernel (``csrc/column_dp.cpp``, built at first use by :mod:`monostixels._dp_cpp`): flow
costs, prefix sums and all stages of one column in cache-sized buffers, columns in parallel over
torch's threads, every float operation in the eager order, so its results are bit-identical
(tests/test_solver_fast.py). Where it is loaded, the preparation runs there too, with the same
expressions: the cell means (which also check the input values, so that the inputs are read
once), the per-cell geometry and hypotheses (stride 1), the semantic prefix sums and the
back-tracking. Without a compiler it falls back to this code with one warning.
"""
from __future__ import annotations

import inspect
import logging
import math
from dataclasses import dataclass, fields
from typing import Any, Mapping, Sequence

import torch

from monostixels import _dp_cpp
from monostixels._checks import InputError, check_finite, check_keys, check_same_size, check_shape
from monostixels.boundaries import REFINE_OBJECTS
from monostixels.classes import DYNAMIC_OBJECT, GROUND, NUM_CLASSES, NUM_TYPES, SKY, STATIC_OBJECT, TYPE_CLASSES
from monostixels.energy import (
    GRAVITY_TOLERANCE_M,
    PriorParams,
    flow_cost,
    gravity,
    load_config_group,
    ordering_from_depths,
)
from monostixels.geometry import (
    Camera,
    Motion,
    dynamic_motion,
    ground_basis,
    object_normals,
    pixel_rays,
    solve_dynamic_dof,
    solve_static_dof,
)
from monostixels.stixels import StixelWorld

__all__ = ["SolverConfig", "ColumnProblem", "ColumnSolution", "prepare_columns", "solve_columns", "solve", "solve_batch"]

logger = logging.getLogger(__name__)

#: Default class of each type when there is no semantic input (road, building, vehicle, sky).
_DEFAULT_CLASS = (0, 3, 6, 9)
_SKY_CLASS = TYPE_CLASSES[SKY][0]
#: Hypothesis-cell pairs evaluated at once when computing flow costs (bounds peak memory).
_CHUNK_ELEMENTS = 4_000_000
#: Which predecessor types are objects (the ordering prior applies above them).
_IS_OBJECT = torch.tensor([False, True, True, False])
#: A predicted point with ``z`` at or below this (homogeneous, px) is behind the camera: flow cap.
_Z_MIN = 1e-9
#: Singular-system threshold of the per-cell fits (geometry.solve_static_dof / solve_dynamic_dof).
_FIT_EPS = inspect.signature(solve_static_dof).parameters["eps"].default
#: ``solver.backend`` values: ``auto`` = the C++ kernel for the hard DP where it builds, else eager.
BACKENDS = ("auto", "eager", "cpp")


@dataclass
class SolverConfig:
    """Solver settings (config group ``solver``; units in conf/solver/default.yaml).

    No defaults in code: :meth:`from_yaml` reads ``conf/solver/<name>.yaml``.
    """

    column_width: int
    cell_rows: int
    hypothesis_stride: int
    min_depth: float
    max_depth: float
    tau: float
    dtype: str
    min_translation: float
    standing_hypotheses: bool
    backend: str
    sky_horizon_margin_deg: float
    # Applied after the DP by the pipeline (monostixels.boundaries.refine_object_tops).
    top_refine_rows: int
    top_refine_depth_ratio: float
    top_refine_objects: str

    @classmethod
    def from_yaml(cls, name: str = "default", **overrides: Any) -> "SolverConfig":
        """Settings of ``conf/solver/<name>.yaml`` (as packaged), with keyword overrides."""
        return cls.from_config({**load_config_group("solver", name), **overrides})

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> "SolverConfig":
        """Build from the ``solver`` config node, checking every value."""
        check_keys(cfg.keys(), (f.name for f in fields(cls)), "solver config")
        out = cls(**{k: cfg[k] for k in cfg.keys()})
        out.validate()
        return out

    def validate(self) -> None:
        """Raise :class:`InputError` naming the first bad setting."""
        for k in ("column_width", "cell_rows", "hypothesis_stride"):
            v = getattr(self, k)
            if not isinstance(v, int) or v < 1:
                raise InputError(f"solver.{k}: must be an integer >= 1, got {v!r}")
        if not (0 < self.min_depth < self.max_depth and math.isfinite(self.max_depth)):
            raise InputError(f"solver.min_depth/max_depth: need 0 < min_depth < max_depth < inf, got {self.min_depth}, {self.max_depth}")
        if not (self.tau >= 0 and math.isfinite(self.tau)):
            raise InputError(f"solver.tau: must be >= 0, got {self.tau}")
        if self.dtype not in ("float32", "float64"):
            raise InputError(f"solver.dtype: float32 or float64, got {self.dtype!r}")
        if not self.min_translation >= 0:
            raise InputError(f"solver.min_translation: must be >= 0, got {self.min_translation}")
        try:  # a command line gives `inf` as a float, but `.inf` (YAML's spelling) as a string
            margin = float(self.sky_horizon_margin_deg)
        except (TypeError, ValueError):
            margin = math.nan
        if not margin >= 0:
            raise InputError(f"solver.sky_horizon_margin_deg: degrees >= 0 (inf = off), got {self.sky_horizon_margin_deg!r}")
        self.sky_horizon_margin_deg = margin
        if not (isinstance(self.top_refine_rows, int) and self.top_refine_rows >= 0):
            raise InputError(f"solver.top_refine_rows: an integer >= 0 (0 = off), got {self.top_refine_rows!r}")
        if not (isinstance(self.top_refine_depth_ratio, (int, float)) and 1.0 <= self.top_refine_depth_ratio < math.inf):
            raise InputError(f"solver.top_refine_depth_ratio: a number >= 1, got {self.top_refine_depth_ratio!r}")
        if self.top_refine_objects not in REFINE_OBJECTS:
            raise InputError(f"solver.top_refine_objects: one of {', '.join(REFINE_OBJECTS)}, got {self.top_refine_objects!r}")
        if self.backend not in BACKENDS:
            raise InputError(f"solver.backend: one of {', '.join(BACKENDS)}, got {self.backend!r}")

    @property
    def torch_dtype(self) -> torch.dtype:
        return torch.float64 if self.dtype == "float64" else torch.float32


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


@dataclass
class ColumnSolution:
    """Stixels of all columns as a flat table (see :class:`monostixels.stixels.StixelWorld`).

    Attributes:
        col: (N,) index into the problem's columns. b, t: (N,) bottom / top cell (inclusive).
        type, cls: (N,). p: (N,) inverse depth. p_ground: (N,) reference ground. tau: (N, 2).
        cost: (N,) energy of each stixel. energy: (C,) optimal (soft, if tau > 0) energy per column.
    """

    col: torch.Tensor
    b: torch.Tensor
    t: torch.Tensor
    type: torch.Tensor
    cls: torch.Tensor
    p: torch.Tensor
    p_ground: torch.Tensor
    tau: torch.Tensor
    cost: torch.Tensor
    energy: torch.Tensor


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
    g: torch.Tensor | None = None  # C x Kd x 3 K B tau, if already computed (see _flow_geometry)


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


def _geometry(prob: ColumnProblem, cpp: bool = False) -> _Geometry:
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


def _hypotheses(prob: ColumnProblem, cfg: SolverConfig, geo: _Geometry | None = None) -> _Hypotheses:
    """Per-column hypothesis sets of the three flow-fitted types (see module docstring).

    Every cell gives one hypothesis per type from its own flow vector. With
    ``hypothesis_stride = s > 1`` the cells are grouped in windows of ``s`` and each window gives
    the median of its cells' hypotheses: exact for a plane that covers most of a window, robust
    to flow noise, and ``s`` times fewer hypotheses (the DP cost is linear in their number).
    ``geo``: the problem's :func:`_geometry`, if already computed.
    """
    geo = _geometry(prob) if geo is None else geo
    s = cfg.hypothesis_stride
    p_min, p_max = 1.0 / cfg.max_depth, 1.0 / cfg.min_depth
    p_ref = (1.0 / prob.h_cam)[:, None]
    if s == 1 and _cpp_prep(prob, cfg):
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
    ok = z > _Z_MIN
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


def _flow_geometry(prob: ColumnProblem, hyp: _Hypotheses, geo: _Geometry | None = None) -> tuple[torch.Tensor, ...]:
    """Terms of the predicted points ``H x`` of every hypothesis (shared by both backends).

    Returns:
        a (C, n, 3), cK (C, 3), s_g, s_o (C, n) of :class:`_Geometry`, and g (C, Kd, 3) ``K B tau``
        of the dynamic hypotheses. A static hypothesis ``p`` predicts ``a + p s cK``, a dynamic
        one ``a + s_o g``, the sky ``a``.
    """
    geo = _geometry(prob) if geo is None else geo
    g = hyp.g
    if g is None:
        M = prob.K @ hyp.B  # C x 3 x 2
        g = (M[:, None] @ hyp.tau[..., None])[..., 0]  # C x Kd x 3: K B tau
    return geo.a, geo.cK, geo.s_g, geo.s_o, g


def _flow_prefix(prob: ColumnProblem, hyp: _Hypotheses, prm: PriorParams,
                 geo: _Geometry | None = None) -> list[torch.Tensor]:
    """Prefix-summed flow cost (C, K_T, n + 1) of every hypothesis of every type."""
    a, cK, s_g, s_o, g = _flow_geometry(prob, hyp, geo)

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


# ---------------------------------------------------------------------------------------------
# The DP
# ---------------------------------------------------------------------------------------------
def _softmin(x: torch.Tensor, dim: int | tuple[int, ...], tau: float) -> torch.Tensor:
    if tau == 0:
        return x.amin(dim)
    return -tau * torch.logsumexp(-x / tau, dim)


def _softmin2(a: torch.Tensor, b: torch.Tensor, tau: float) -> torch.Tensor:
    if tau == 0:
        return torch.minimum(a, b)
    return -tau * torch.logaddexp(-a / tau, -b / tau)


def _structural_object(inv_p: torch.Tensor, q: torch.Tensor, inv_pp: torch.Tensor, inv_gp: torch.Tensor,
                       prm: PriorParams) -> torch.Tensor:
    """Ψ_str (C, X, 4') of an object stixel with inverse depth ``1 / inv_p`` (C, X, 1) above each predecessor type.

    q: (C,) bottom-ray ratio (see :func:`height_over_ground`); inv_pp, inv_gp: (C, 4') the
    predecessor's depth ``1/p`` (1 for non-objects) and reference-ground height ``1/p_g``.
    Above ground/sky: gravity; above an object: min(gravity, ordering) (paper).
    """
    grav = gravity(inv_gp[:, None, :] - q[:, None, None] * inv_p, prm)
    ordv = ordering_from_depths(inv_pp[:, None, :] - inv_p, prm)
    return torch.where(_IS_OBJECT, torch.minimum(grav, ordv), grav)


def _sky_unseen(geo: _Geometry, margin_deg: float) -> torch.Tensor:
    """(C, n) cells whose ray points more than ``margin_deg`` below the horizon of the road plane."""
    sin_below = geo.s_g / geo.ray.norm(dim=-1)
    return sin_below > math.sin(math.radians(margin_deg))


def _semantic_prefix(prob: ColumnProblem, prm: PriorParams, dt: torch.dtype, sky_margin_deg: float = math.inf,
                     geo: _Geometry | None = None, cpp: bool = False) -> tuple[torch.Tensor, list[list[int]]]:
    """Prefix-summed semantic cost (C, 10, n + 1) and the classes of each type.

    With semantics, the sky class also pays the flow and semantic caps (``alpha_F delta_F + alpha_L
    delta_L`` per row) in cells more than ``sky_margin_deg`` below the horizon: the flow term alone
    only caps the sky there (:func:`beyond_horizon`), the cost of any type whose flow fails, so where
    the flow fails (the image's lower corners, which leave the previous frame) the net's score decided,
    and a bright patch of road read as sky became a sky stixel 6 m ahead (KITTI drive 0023). A road's
    grade changes by a few degrees, so sky is seen at most slightly below the road plane's horizon.
    Without semantics: zeros (C, 1, n + 1) and the default class of each type. ``cpp``: in the
    kernel (values only, no gradients).
    """
    C, n = prob.num_columns, prob.num_cells
    if prob.nll is not None:
        unseen = extra = None
        if math.isfinite(sky_margin_deg):
            unseen = _sky_unseen(_geometry(prob) if geo is None else geo, sky_margin_deg)
            extra = (prm.alpha_F * prm.delta_F + prm.alpha_L * prm.delta_L) * prob.rows[None, :]
        if cpp:  # the same expressions and sums, one pass (csrc/column_dp.cpp; tests/test_solver_fast.py)
            Lp = _dp_cpp.semantic_prefix(prob.nll, prob.rows, prm.alpha_L, prm.delta_L, unseen,
                                         None if extra is None else extra[0], _SKY_CLASS)
            return Lp, [list(cs) for cs in TYPE_CLASSES]
        sem = torch.minimum(prob.nll, prm.alpha_L) * prob.rows[None, :, None] * prm.delta_L
        if unseen is not None:
            sky = torch.where(unseen, sem[..., _SKY_CLASS] + extra, sem[..., _SKY_CLASS])
            sem = torch.cat([sem[..., :_SKY_CLASS], sky[..., None], sem[..., _SKY_CLASS + 1:]], -1)
        return _prefix(sem.transpose(1, 2)), [list(cs) for cs in TYPE_CLASSES]  # C x 10 x (n + 1)
    return torch.zeros(C, 1, n + 1, dtype=dt), [[c] for c in _DEFAULT_CLASS]


def _cpp_prep(prob: ColumnProblem, cfg: SolverConfig) -> bool:
    """Whether the C++ kernel may prepare ``prob`` (values only: no gradients through it)."""
    if cfg.backend == "eager" or prob.flow.dtype not in (torch.float32, torch.float64):
        return False
    if torch.is_grad_enabled() and any(x.requires_grad for x in (prob.flow, prob.K, prob.R, prob.t, prob.n_g)):
        return False
    return _dp_cpp.available()


def _use_cpp(prob: ColumnProblem, prm: PriorParams, cfg: SolverConfig) -> bool:
    """Whether this call runs the C++ kernel: the hard DP (tau = 0) without gradients, where it builds.

    The kernel computes values only; the soft DP and anything that needs gradients stay eager.
    ``backend=cpp`` makes a missing kernel an error instead of a fallback.
    """
    if cfg.backend == "eager" or cfg.tau > 0 or prob.flow.dtype != cfg.torch_dtype:
        return False  # (a problem prepared in another dtype than the solver's: eager promotes)
    if torch.is_grad_enabled() and (prob.flow.requires_grad or any(
            getattr(prm, k).requires_grad for k in PriorParams.names())):
        return False
    if _dp_cpp.available():
        return True
    if cfg.backend == "cpp":
        raise RuntimeError(f"solver.backend=cpp: the C++ column DP is not available ({_dp_cpp.build_error()}); "
                           "use solver.backend=auto or eager")
    return False


def _solve_columns_cpp(prob: ColumnProblem, prm: PriorParams, cfg: SolverConfig) -> ColumnSolution:
    """The hard DP of :func:`solve_columns` in the fused C++ kernel (``csrc/column_dp.cpp``).

    Hypotheses, their geometry and the semantic prefix sums are computed as on the eager path (by
    the kernel's twins of that code, same bits); the kernel does the flow costs, their prefix sums
    and the DP stages per column, and follows the back-pointers as :func:`_backtrack` does.
    Bit-identical to eager.
    """
    dt = cfg.torch_dtype
    geo = _geometry(prob, cpp=_cpp_prep(prob, cfg))
    hyp = _hypotheses(prob, cfg, geo)
    a, cK, s_g, s_o, g = _flow_geometry(prob, hyp, geo)
    Lp, classes = _semantic_prefix(prob, prm, dt, cfg.sky_horizon_margin_deg, geo, cpp=_cpp_prep(prob, cfg))
    cls_table = torch.tensor([cs + [-1] * (3 - len(cs)) for cs in classes], dtype=torch.long)  # 4 x 3
    ncs = torch.tensor([len(cs) for cs in classes], dtype=torch.long)
    params = torch.stack([getattr(prm, k) for k in _dp_cpp.PARAM_ORDER]
                         + [torch.tensor(x, dtype=dt) for x in (1.0 / cfg.max_depth, 1.0 / cfg.min_depth,
                                                                GRAVITY_TOLERANCE_M, _Z_MIN)])
    col, b, t, typ, cls, p, g, tau, cost, energy = _dp_cpp.column_dp(
        a, cK, s_g, s_o, prob.u, prob.v, prob.rows, prob.flow, prob.cov_inv, prob.logdet,
        hyp.p_ground, hyp.p_object, g, hyp.tau, Lp, geo.q, 1.0 / prob.h_cam,
        prob.degenerate, params, cls_table, ncs, prob.nll is not None)
    return ColumnSolution(col=col, b=b, t=t, type=typ, cls=cls, p=p, p_ground=g, tau=tau, cost=cost, energy=energy)


def solve_columns(prob: ColumnProblem, prm: PriorParams, cfg: SolverConfig) -> ColumnSolution:
    """Run the DP on every column of ``prob`` at once (see the module docstring).

    The hard DP (``tau = 0``) without gradients runs in a fused C++ kernel where it builds
    (``solver.backend``); this eager code is its readable definition and the soft DP.

    Returns:
        the optimal stixels of every column and the optimal energy (C,) — soft when ``cfg.tau > 0``.
    """
    dt = cfg.torch_dtype
    prm = prm.as_tensors(dt)
    if _use_cpp(prob, prm, cfg):
        return _solve_columns_cpp(prob, prm, cfg)
    tau_T = float(cfg.tau)
    C, n = prob.num_columns, prob.num_cells
    geo = _geometry(prob, cpp=_cpp_prep(prob, cfg))
    hyp = _hypotheses(prob, cfg, geo)
    P = _flow_prefix(prob, hyp, prm, geo)  # per type: C x K_T x (n + 1)
    p_min, p_max = 1.0 / cfg.max_depth, 1.0 / cfg.min_depth

    Lp, classes = _semantic_prefix(prob, prm, dt, cfg.sky_horizon_margin_deg, geo)
    cls_idx = [torch.tensor(cs) if prob.nll is not None else torch.tensor([0]) for cs in classes]
    L = [Lp[:, ci] for ci in cls_idx]  # per type: C x nc x (n + 1)

    # Bottom-edge ray ratio q_b = n_g.r / n_obj.r of every cell (for gravity / standing on ground).
    q = geo.q  # C x n

    p_ref = 1.0 / prob.h_cam
    # State index i = number of cells consumed. Index 0 is a virtual ground stixel at the camera height.
    E = torch.full((C, n + 1, NUM_TYPES), float("inf"), dtype=dt)
    E[:, 0, GROUND] = 0.0
    EH = E.clone() if tau_T > 0 else E
    pS = p_ref[:, None, None].expand(C, n + 1, NUM_TYPES).clone()
    gS = pS.clone()
    bpB = torch.zeros(C, n + 1, NUM_TYPES, dtype=torch.long)
    bpK = torch.zeros_like(bpB)
    bpC = torch.zeros_like(bpB)
    tauS = torch.zeros(C, n + 1, NUM_TYPES, 2, dtype=dt)

    Ks = [x.shape[1] for x in P]
    ncs = [len(c) for c in classes]
    MS = [torch.full((C, Ks[T], ncs[T]), float("inf"), dtype=dt) for T in range(NUM_TYPES)]
    MH = [m.clone() for m in MS]
    MB = [torch.zeros(C, Ks[T], ncs[T], dtype=torch.long) for T in range(NUM_TYPES)]
    # Best predecessor type per (segment bottom, hypothesis): values 0..3, kept as int8 because
    # this table is (columns x cells x hypotheses) — the largest one at r = 1.
    kbest = [torch.zeros(C, n, Ks[T] if T in (GROUND, STATIC_OBJECT) else 1, dtype=torch.int8) for T in range(NUM_TYPES)]
    p_rule = torch.zeros(C, n, NUM_TYPES, dtype=dt)
    deg = prob.degenerate[:, None, None]
    cols = torch.arange(C)
    inv_pg = (1.0 / hyp.p_ground)[:, :, None]  # C x Kg x 1: ground heights of the hypotheses
    inv_po = (1.0 / hyp.p_object)[:, :, None]  # C x Ko x 1: object distances
    one = torch.ones((), dtype=dt)
    # Writes go to row i + 1 of the state arrays; every read of iteration i is of rows <= i.
    for i in range(n):
        Ep, EpH, pp, gp = E[:, i], EH[:, i], pS[:, i], gS[:, i]
        qi = q[:, i]
        inv_gp = 1.0 / gp
        inv_pp = torch.where(_IS_OBJECT, 1.0 / pp.clamp(min=p_min), one)
        # Inverse depth of an object standing on the reference ground (or on the object below).
        pr = torch.where(_IS_OBJECT, pp, qi[:, None] * gp).clamp(p_min, p_max)  # C x 4'
        p_rule[:, i] = pr
        st_rule = _structural_object((1.0 / pr)[:, None, :], qi, inv_pp, inv_gp, prm)  # C x 1 x 4'
        dh_g = inv_gp[:, None, :] - inv_pg
        st = [
            prm.alpha_flat + prm.beta_flat * dh_g * dh_g,  # flat ground (paper Ψ_flat)
            torch.where(deg, st_rule, _structural_object(inv_po, qi, inv_pp, inv_gp, prm)),
            st_rule,
            None,
        ]
        for T in range(NUM_TYPES):
            candH = EpH[:, None, :] if st[T] is None else EpH[:, None, :] + st[T]
            GH, kb = candH.min(-1)
            kbest[T][:, i] = kb
            cH = (GH - P[T][:, :, i])[..., None] - L[T][:, None, :, i]
            upd = cH < MH[T]
            MH[T] = torch.minimum(MH[T], cH)
            MB[T].masked_fill_(upd, i)
            if tau_T > 0:
                candS = Ep[:, None, :] if st[T] is None else Ep[:, None, :] + st[T]
                GS = _softmin(candS, -1, tau_T) - P[T][:, :, i]
                MS[T] = _softmin2(MS[T], GS[..., None] - L[T][:, None, :, i], tau_T)
            # Segments ending at cell i: close them with the prefix sums at i + 1.
            end = P[T][:, :, i + 1, None] + L[T][:, None, :, i + 1]
            val, arg = (MH[T] + end).flatten(1).min(1)
            EH[:, i + 1, T] = val + prm.beta_mc
            if tau_T > 0:
                E[:, i + 1, T] = _softmin((MS[T] + end).flatten(1), 1, tau_T) + prm.beta_mc
            h_star, c_star = arg // ncs[T], arg % ncs[T]
            b_star = MB[T].flatten(1).gather(1, arg[:, None])[:, 0]
            kb_all = kbest[T][cols, b_star]  # C x K'
            k_star = (kb_all[cols, h_star] if kb_all.shape[1] > 1 else kb_all[:, 0]).long()
            g_pred = gS[cols, b_star, k_star]
            if T == GROUND:
                p_new = hyp.p_ground[cols, h_star]
                g_new = p_new
            elif T == STATIC_OBJECT:
                p_new = torch.where(prob.degenerate, p_rule[cols, b_star, k_star], hyp.p_object[cols, h_star])
                g_new = g_pred
            elif T == DYNAMIC_OBJECT:
                p_new = p_rule[cols, b_star, k_star]
                g_new = g_pred
                tauS[:, i + 1, T] = hyp.tau[cols, h_star]
            else:
                p_new = torch.zeros_like(g_pred)
                g_new = g_pred
            pS[:, i + 1, T] = p_new
            gS[:, i + 1, T] = g_new
            bpB[:, i + 1, T] = b_star
            bpK[:, i + 1, T] = k_star
            bpC[:, i + 1, T] = cls_idx[T][c_star] if prob.nll is not None else classes[T][0]

    energy = _softmin(E[:, n], 1, tau_T)
    return _backtrack(prob, E if tau_T == 0 else EH, pS, gS, tauS, bpB, bpK, bpC, energy)


def _backtrack(prob: ColumnProblem, EH: torch.Tensor, pS, gS, tauS, bpB, bpK, bpC, energy) -> ColumnSolution:
    """Follow the back-pointers of every column from the top cell down to the virtual start."""
    C, n = prob.num_columns, prob.num_cells
    cols = torch.arange(C)
    cur_i = torch.full((C,), n, dtype=torch.long)
    cur_T = EH[:, n].argmin(1)
    out: dict[str, list[torch.Tensor]] = {k: [] for k in ("col", "b", "t", "type", "cls", "p", "g", "tau", "cost")}
    while bool((cur_i > 0).any()):
        act = cur_i > 0
        c, i, T = cols[act], cur_i[act], cur_T[act]
        b, k = bpB[c, i, T], bpK[c, i, T]
        out["col"].append(c)
        out["b"].append(b)
        out["t"].append(i - 1)
        out["type"].append(T)
        out["cls"].append(bpC[c, i, T])
        out["p"].append(pS[c, i, T])
        out["g"].append(gS[c, i, T])
        out["tau"].append(tauS[c, i, T])
        out["cost"].append(EH[c, i, T] - EH[c, b, k])
        cur_i = cur_i.clone()
        cur_T = cur_T.clone()
        cur_i[act] = b
        cur_T[act] = k
    cat = {k: torch.cat(v) for k, v in out.items()}
    order = torch.argsort(cat["col"] * (n + 1) + cat["b"])
    cat = {k: v[order] for k, v in cat.items()}
    return ColumnSolution(col=cat["col"], b=cat["b"], t=cat["t"], type=cat["type"], cls=cat["cls"],
                          p=cat["p"], p_ground=cat["g"], tau=cat["tau"], cost=cat["cost"], energy=energy)


# ---------------------------------------------------------------------------------------------
# Frame-level API
# ---------------------------------------------------------------------------------------------
def _all_finite(x: torch.Tensor) -> bool:
    """Whether ``x`` has no NaN/inf: one min/max pass (NaN propagates into both), no bool copy."""
    if x.numel() == 0:
        return True
    lo, hi = torch.aminmax(x)
    return bool(torch.isfinite(lo) & torch.isfinite(hi))


def _check_shapes(flow: torch.Tensor, cov: torch.Tensor, scores: torch.Tensor | None, name: str) -> None:
    check_shape(flow, [2, "H", "W"], f"{name}flow")
    check_shape(cov, ["H", "W", 2, 2], f"{name}flow covariance")
    check_same_size(flow, cov.permute(2, 3, 0, 1), f"{name}flow", f"{name}flow covariance")
    if scores is not None:
        if scores.dim() != 3 or scores.shape[0] != NUM_CLASSES:
            raise InputError(f"{name}semantic scores: expected ({NUM_CLASSES}, H, W) class scores, got shape {tuple(scores.shape)}")
        check_same_size(scores, flow, f"{name}semantic scores", f"{name}flow")


def _check_values(flow: torch.Tensor, cov: torch.Tensor, scores: torch.Tensor | None, name: str) -> None:
    # check_finite only where the cheap test fails: it counts and locates the bad values.
    if not _all_finite(flow):
        check_finite(flow, f"{name}flow")
    if not _all_finite(cov):
        check_finite(cov, f"{name}flow covariance")
    det = cov[..., 0, 0] * cov[..., 1, 1] - cov[..., 0, 1] * cov[..., 1, 0]
    if bool((cov[..., 0, 0] <= 0).any() or (det <= 0).any()):
        raise InputError(f"{name}flow covariance: must be positive definite at every pixel")
    if scores is not None:
        lo, hi = torch.aminmax(scores)
        if not bool(torch.isfinite(lo) & torch.isfinite(hi)):
            check_finite(scores, f"{name}semantic scores")
        if bool(lo < 0):
            raise InputError(f"{name}semantic scores: must be non-negative pseudo-probabilities")


def _batch(xs: Sequence[torch.Tensor]) -> torch.Tensor:
    """(B, ...) of B tensors: a view for one frame (stacking would copy tens of MB)."""
    return xs[0][None] if len(xs) == 1 else torch.stack(list(xs))


def solve_batch(
    flows: Sequence[torch.Tensor],
    covs: Sequence[torch.Tensor],
    scores: Sequence[torch.Tensor | None],
    cameras: Sequence[Camera],
    motions: Sequence[Motion],
    prior: PriorParams,
    cfg: SolverConfig,
) -> list[StixelWorld]:
    """Stixels of several frames of equal size, solved in one batch.

    Args:
        flows: per frame (2, H, W) flow current -> previous (pixels).
        covs: per frame (H, W, 2, 2) flow covariance (pixels^2).
        scores: per frame (10, H, W) class scores, or None (semantic mode ``none``: δ_L = 0).
        cameras, motions: per frame; motion ``X_prev = R X_cur + t`` (metres).
        prior, cfg: prior parameters and solver settings.

    Returns:
        one :class:`StixelWorld` per frame. A frame whose camera translation is below
        ``cfg.min_translation`` is flagged ``degenerate_motion``: its depths come from the scene model.
    """
    cfg.validate()
    if not flows:
        raise InputError("solve_batch: no frames given")
    if not (len(flows) == len(covs) == len(scores) == len(cameras) == len(motions)):
        raise InputError("solve_batch: flows, covs, scores, cameras and motions must have one entry per frame")
    names = [f"frame {k}: " if len(flows) > 1 else "" for k in range(len(flows))]
    for k, (f, c, s) in enumerate(zip(flows, covs, scores)):
        _check_shapes(f, c, s, names[k])
        check_same_size(f, flows[0], f"frame {k}: flow", "frame 0: flow")
    if any(s is None for s in scores) and not all(s is None for s in scores):
        raise InputError("solve_batch: semantic scores must be given for all frames or for none")
    has_sem = scores[0] is not None
    prob = prepare_columns(_batch(flows), _batch(covs), _batch(scores) if has_sem else None, cameras, motions, cfg)
    if not prob.checked:  # the cell sums did not check the values, or found one that may be bad
        for k, (f, c, s) in enumerate(zip(flows, covs, scores)):
            _check_values(f, c, s, names[k])
    sol = solve_columns(prob, prior, cfg)
    return _to_worlds(prob, sol, cameras, motions, cfg)


def solve(
    flow: torch.Tensor,
    cov: torch.Tensor,
    scores: torch.Tensor | None,
    camera: Camera,
    motion: Motion,
    prior: PriorParams,
    cfg: SolverConfig,
) -> StixelWorld:
    """Stixels of one frame; see :func:`solve_batch` for the arguments (without the frame lists)."""
    return solve_batch([flow], [cov], [scores], [camera], [motion], prior, cfg)[0]


def _to_worlds(prob: ColumnProblem, sol: ColumnSolution, cameras, motions, cfg: SolverConfig) -> list[StixelWorld]:
    H, W = prob.image_size
    r = cfg.cell_rows
    frame = prob.frame[sol.col]
    worlds = []
    B = len(cameras)
    C = prob.num_columns // B
    for f in range(B):
        m = frame == f
        col = prob.column[sol.col[m]]
        b, t = sol.b[m], sol.t[m]
        typ, p, tau = sol.type[m], sol.p[m], sol.tau[m]
        motion = torch.zeros(int(m.sum()), 3, dtype=torch.float64)
        dyn = typ == DYNAMIC_OBJECT
        if bool(dyn.any()):
            Bm = ground_basis(cameras[f].ground_normal.double())
            g = tau[dyn].double() @ Bm.T
            Rm, tm = motions[f].R.double(), motions[f].t.double()
            motion[dyn] = dynamic_motion(Rm.expand(g.shape[0], 3, 3), tm.expand_as(g), g, p[dyn].double())
        flags: dict[str, Any] = {"degenerate_motion": bool(prob.degenerate[f * C])}
        if flags["degenerate_motion"]:
            flags["reason"] = (f"camera translation {motions[f].translation_norm:.3f} m < solver.min_translation "
                               f"{cfg.min_translation} m: flow carries no depth; depths come from the scene model "
                               "(ground at the camera height, objects standing on the ground or on the object below)")
        worlds.append(StixelWorld(
            column_width=cfg.column_width, image_size=(H, W), K=cameras[f].K.double(),
            ground_normal=cameras[f].ground_normal.double(), column=col,
            v_top=torch.clamp(H - (t + 1) * r, min=0), v_bottom=H - 1 - b * r,
            type=typ, cls=sol.cls[m], inverse_depth=p.double(), motion=motion,
            cost=sol.cost[m].double(), tau=tau.double(),
            energy=sol.energy[f * C:(f + 1) * C].detach().double(), flags=flags,
        ))
    return worlds
