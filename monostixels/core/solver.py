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

Steps 1 and 2 (the cells, the hypotheses and their prefix-summed costs) live in
:mod:`monostixels.core.columns`; this module holds the DP, its back-tracking and the frame-level API.

The Python loop runs over DP stages (cells, ``n`` iterations); every iteration works on all
columns, hypotheses and classes at once. This eager code is the readable definition and the soft
DP. The hard DP (``tau = 0``, no gradients) runs by default (``solver.backend: auto``) in a fused
C++ kernel (``csrc/column_dp.cpp``, built at first use by :mod:`monostixels.core._dp_cpp`): flow
costs, prefix sums and all stages of one column in cache-sized buffers, columns in parallel over
torch's threads, every float operation in the eager order, so its results are bit-identical
(tests/test_solver_fast.py). Where it is loaded, the preparation runs there too, with the same
expressions: the cell means (which also check the input values, so that the inputs are read
once), the per-cell geometry and hypotheses (stride 1), the semantic prefix sums and the
back-tracking. Without a compiler it falls back to this code with one warning.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Sequence

import torch

from monostixels.core import _dp_cpp
from monostixels._checks import InputError, check_finite, check_same_size, check_shape
from monostixels.core.classes import DYNAMIC_OBJECT, GROUND, NUM_CLASSES, NUM_TYPES, STATIC_OBJECT
from monostixels.core.columns import (Z_MIN, ColumnProblem, column_geometry, cpp_prep, flow_geometry, flow_prefix, hypotheses,
                                      prepare_columns, semantic_prefix)
from monostixels.core.energy import GRAVITY_TOLERANCE_M, PriorParams, gravity, ordering_from_depths
from monostixels.core.geometry import Camera, Motion, stixel_motion
from monostixels.core.solver_config import SolverConfig
from monostixels.core.stixels import StixelWorld
from monostixels.core.status import FrameStatus, MotionStatus

__all__ = ["SolverConfig", "ColumnSolution", "solve_columns", "solve", "solve_batch"]

logger = logging.getLogger(__name__)

#: Which predecessor types are objects (the ordering prior applies above them).
_IS_OBJECT = torch.tensor([False, True, True, False])
@dataclass
class ColumnSolution:
    """Stixels of all columns as a flat table (see :class:`monostixels.core.stixels.StixelWorld`).

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
    geo = column_geometry(prob, cpp=cpp_prep(prob, cfg))
    hyp = hypotheses(prob, cfg, geo)
    a, cK, s_g, s_o, g = flow_geometry(prob, hyp, geo)
    Lp, classes = semantic_prefix(prob, prm, dt, cfg.sky_horizon_margin_deg, geo, cpp=cpp_prep(prob, cfg),
                                   ground_margin_deg=cfg.ground_horizon_margin_deg)
    cls_table = torch.tensor([cs + [-1] * (3 - len(cs)) for cs in classes], dtype=torch.long)  # 4 x 3
    ncs = torch.tensor([len(cs) for cs in classes], dtype=torch.long)
    params = torch.stack([getattr(prm, k) for k in _dp_cpp.PARAM_ORDER]
                         + [torch.tensor(x, dtype=dt) for x in (1.0 / cfg.max_depth, 1.0 / cfg.min_depth,
                                                                GRAVITY_TOLERANCE_M, Z_MIN)])
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
    geo = column_geometry(prob, cpp=cpp_prep(prob, cfg))
    hyp = hypotheses(prob, cfg, geo)
    P = flow_prefix(prob, hyp, prm, geo)  # per type: C x K_T x (n + 1)
    p_min, p_max = 1.0 / cfg.max_depth, 1.0 / cfg.min_depth

    Lp, classes = semantic_prefix(prob, prm, dt, cfg.sky_horizon_margin_deg, geo,
                                 ground_margin_deg=cfg.ground_horizon_margin_deg)
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
            motion[dyn] = stixel_motion(tau[dyn], p[dyn], cameras[f].ground_normal, motions[f].R, motions[f].t)
        status = FrameStatus(motion=MotionStatus(degenerate=bool(prob.degenerate[f * C])))
        if status.motion.degenerate:
            status.motion.reason = (f"camera translation {motions[f].translation_norm:.3f} m < solver.min_translation "
                               f"{cfg.min_translation} m: flow carries no depth; depths come from the scene model "
                               "(ground at the camera height, objects standing on the ground or on the object below)")
        worlds.append(StixelWorld(
            column_width=cfg.column_width, image_size=(H, W), K=cameras[f].K.double(),
            ground_normal=cameras[f].ground_normal.double(), column=col,
            v_top=torch.clamp(H - (t + 1) * r, min=0), v_bottom=H - 1 - b * r,
            type=typ, cls=sol.cls[m], inverse_depth=p.double(), motion=motion,
            cost=sol.cost[m].double(), tau=tau.double(),
            energy=sol.energy[f * C:(f + 1) * C].detach().double(), status=status,
        ))
    return worlds
