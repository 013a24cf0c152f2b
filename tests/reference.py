"""A slow, obviously-correct reference solver for tiny problems (the tests compare against it).

It solves the same column problem as :mod:`monostixels.core.solver` with plain Python loops over
cells, segment bottoms, types, predecessor types, hypotheses and classes; every flow cost is
computed row by row through the full 3x3 homography (:func:`monostixels.core.geometry.homography`),
not through the solver's factorised form or its prefix sums. It also offers
:func:`column_energy`, the energy of a given labelled segmentation, and
:func:`exhaustive_column`, which enumerates every segmentation of a tiny column.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import torch

from monostixels.core.classes import DYNAMIC_OBJECT, GROUND, NUM_TYPES, SKY, STATIC_OBJECT, TYPE_CLASSES
from monostixels.core.energy import GRAVITY_TOLERANCE_M, PriorParams
from monostixels.core.geometry import (
    apply_homography,
    dynamic_homography,
    homography,
    pixel_rays,
)
from monostixels.core.columns import _DEFAULT_CLASS, ColumnProblem, hypotheses
from monostixels.core.solver import SolverConfig

__all__ = ["RefStixel", "reference_column", "column_energy", "exhaustive_column"]


@dataclass
class RefStixel:
    """One stixel of a reference solution (cells ``b..t`` inclusive, cell 0 at the bottom)."""

    b: int
    t: int
    type: int
    cls: int
    p: float
    p_ground: float
    h: int  # hypothesis index (flow labels); -1 for sky
    cost: float


def _f(x) -> float:
    return float(x)


class _Column:
    """Plain-float view of one column of a :class:`ColumnProblem`."""

    def __init__(self, prob: ColumnProblem, c: int, prm: PriorParams, cfg: SolverConfig):
        self.prob, self.c, self.prm, self.cfg = prob, c, prm, cfg
        self.n = prob.num_cells
        hyp = hypotheses(prob, cfg)  # the same hypothesis set (a shared definition, not the DP)
        self.p_ground = [float(x) for x in hyp.p_ground[c]]
        self.p_object = [float(x) for x in hyp.p_object[c]]
        self.tau = [hyp.tau[c, k].double() for k in range(hyp.tau.shape[1])]
        self.B = hyp.B[c].double()
        K, R, t = prob.K[c].double(), prob.R[c].double(), prob.t[c].double()
        self.K, self.R, self.t = K, R, t
        self.n_g, self.n_obj = prob.n_g[c].double(), prob.n_obj[c].double()
        self.h_cam = _f(prob.h_cam[c])
        self.degenerate = bool(prob.degenerate[c])
        self.classes = [list(cs) for cs in TYPE_CLASSES] if prob.nll is not None else [[k] for k in _DEFAULT_CLASS]
        self.p_min, self.p_max = 1.0 / cfg.max_depth, 1.0 / cfg.min_depth
        self._cache: dict = {}

    # -- data terms ----------------------------------------------------------------------------
    def _row_flow_cost(self, H: torch.Tensor, j: int) -> float:
        prob, c, prm = self.prob, self.c, self.prm
        u, v = prob.u[c].double(), prob.v[j].double()
        x = torch.stack([u, v, torch.ones((), dtype=torch.float64)])
        z = float((H @ x)[2])
        if z <= 1e-9:
            return _f(prm.alpha_F) * _f(prob.rows[j]) * _f(prm.delta_F)
        up, vp = apply_homography(H, u, v)
        r0 = float(u + prob.flow[c, j, 0] - up)
        r1 = float(v + prob.flow[c, j, 1] - vp)
        Ci = prob.cov_inv[c, j].double()
        q = float(Ci[0, 0]) * r0 * r0 + 2 * float(Ci[0, 1]) * r0 * r1 + float(Ci[1, 1]) * r1 * r1
        cost = min(_f(prm.alpha_F), _f(prob.logdet[c, j]) + 0.5 * q)
        return cost * _f(prob.rows[j]) * _f(prm.delta_F)

    def homography(self, T: int, h: int) -> torch.Tensor:
        if T == GROUND:
            return homography(self.K, self.R, self.t, self.n_g, torch.tensor(self.p_ground[h], dtype=torch.float64))
        if T == STATIC_OBJECT:
            return homography(self.K, self.R, self.t, self.n_obj, torch.tensor(self.p_object[h], dtype=torch.float64))
        if T == DYNAMIC_OBJECT:
            return dynamic_homography(self.K, self.R, self.n_obj, self.B @ self.tau[h])
        return homography(self.K, self.R, self.t, self.n_g, torch.tensor(0.0, dtype=torch.float64))

    def _above_horizon(self, j: int) -> bool:
        """The ray through cell ``j`` never meets the ground plane (it would meet it behind the camera)."""
        prob, c = self.prob, self.c
        ray = pixel_rays(prob.K[c].double(), prob.u[c].double(), prob.v[j].double())
        return float(ray @ self.n_g) <= 0.0

    def flow_cost(self, T: int, h: int, b: int, t: int) -> float:
        key = ("F", T, h)
        if key not in self._cache:
            H = self.homography(T, h)
            extra = _f(self.prm.alpha_dyn) if T == DYNAMIC_OBJECT else 0.0
            cap = _f(self.prm.alpha_F) * _f(self.prm.delta_F)
            # Ground only below the horizon, sky only above it (columns.beyond_horizon).
            self._cache[key] = [
                cap * _f(self.prob.rows[j]) if (T == GROUND and self._above_horizon(j))
                or (T == SKY and not self._above_horizon(j))
                else self._row_flow_cost(H, j) + extra * _f(self.prob.rows[j])
                for j in range(self.n)
            ]
        return sum(self._cache[key][b:t + 1])

    def sem_cost(self, cls: int, b: int, t: int) -> float:
        if self.prob.nll is None:
            return 0.0
        key = ("L", cls)
        if key not in self._cache:
            self._cache[key] = [min(_f(self.prm.alpha_L), _f(self.prob.nll[self.c, j, cls])) * _f(self.prob.rows[j])
                                * _f(self.prm.delta_L)
                                + (self._sky_extra(j) if cls in TYPE_CLASSES[SKY] else self._ground_extra(j) if cls in TYPE_CLASSES[GROUND]
                                   else 0.0) for j in range(self.n)]
        return sum(self._cache[key][b:t + 1])

    def _sky_extra(self, j: int) -> float:
        """Both caps per row where cell ``j``'s ray points more than ``sky_horizon_margin_deg`` below the
        horizon (columns.semantic_prefix): sky is not seen there."""
        return self._caps_beyond(j, 1.0, self.cfg.sky_horizon_margin_deg)

    def _ground_extra(self, j: int) -> float:
        """Both caps per row where cell ``j``'s ray points more than ``ground_horizon_margin_deg`` above the
        horizon (columns.semantic_prefix): ground is not seen there."""
        return self._caps_beyond(j, -1.0, self.cfg.ground_horizon_margin_deg)

    def _caps_beyond(self, j: int, sign: float, margin_deg: float) -> float:
        prob, c = self.prob, self.c
        ray = pixel_rays(prob.K[c].double(), prob.u[c].double(), prob.v[j].double())
        beyond = sign * float(ray @ self.n_g) / float(ray.norm())
        if not beyond > math.sin(math.radians(margin_deg)):
            return 0.0
        prm = self.prm
        return (_f(prm.alpha_F) * _f(prm.delta_F) + _f(prm.alpha_L) * _f(prm.delta_L)) * _f(prob.rows[j])

    def n_hyp(self, T: int) -> int:
        return [len(self.p_ground), len(self.p_object), len(self.tau), 1][T]

    # -- priors --------------------------------------------------------------------------------
    def q(self, b: int) -> float:
        if ("q", b) not in self._cache:
            ray = pixel_rays(self.K, self.prob.u[self.c].double(), self.prob.v_edge[b].double())
            self._cache[("q", b)] = float(ray @ self.n_g) / float(ray @ self.n_obj)
        return self._cache[("q", b)]

    def gravity(self, p: float, b: int, p_g: float) -> float:
        prm = self.prm
        dh = 1.0 / p_g - self.q(b) / p
        if dh < -GRAVITY_TOLERANCE_M:
            return _f(prm.alpha_grav_below) + _f(prm.beta_grav_below) * (-dh)
        return _f(prm.alpha_grav_above) + _f(prm.beta_grav_above) * dh

    def ordering(self, p: float, p_prev: float) -> float:
        if p > p_prev:
            return _f(self.prm.alpha_ord) + _f(self.prm.beta_ord) * (1.0 / p_prev - 1.0 / p)
        return 0.0

    def p_standing(self, b: int, k_prev: int, p_prev: float, g_prev: float) -> float:
        """Inverse depth of an object from the structural prior (dynamic; static when degenerate)."""
        p = p_prev if k_prev in (STATIC_OBJECT, DYNAMIC_OBJECT) else self.q(b) * g_prev
        return min(max(p, self.p_min), self.p_max)

    def structural(self, T: int, p: float, b: int, k_prev: int, p_prev: float, g_prev: float) -> float:
        prm = self.prm
        if T == GROUND:
            dh = 1.0 / g_prev - 1.0 / p
            return _f(prm.alpha_flat) + _f(prm.beta_flat) * dh * dh
        if T == SKY:
            return 0.0
        grav = self.gravity(p, b, g_prev)
        if k_prev in (STATIC_OBJECT, DYNAMIC_OBJECT):
            return min(grav, self.ordering(p, p_prev))
        return grav

    def segment_p(self, T: int, h: int, b: int, k_prev: int, p_prev: float, g_prev: float) -> float:
        if T == GROUND:
            return self.p_ground[h]
        if T == STATIC_OBJECT:
            return self.p_standing(b, k_prev, p_prev, g_prev) if self.degenerate else self.p_object[h]
        if T == DYNAMIC_OBJECT:
            return self.p_standing(b, k_prev, p_prev, g_prev)
        return 0.0


def _segment_options(col: _Column, b: int, t: int, T: int, k_prev: int, p_prev: float, g_prev: float):
    """Yield (energy, cls, h, p) of every (hypothesis, class) label of segment [b, t] of type T."""
    for h in range(col.n_hyp(T)):
        p = col.segment_p(T, h, b, k_prev, p_prev, g_prev)
        e_flow = col.flow_cost(T, h, b, t)
        e_str = col.structural(T, p, b, k_prev, p_prev, g_prev)
        for cls in col.classes[T]:
            e = e_flow + e_str + col.sem_cost(cls, b, t) + _f(col.prm.beta_mc)
            yield e, cls, h, p


def reference_column(prob: ColumnProblem, c: int, prm: PriorParams, cfg: SolverConfig) -> tuple[float, list[RefStixel]]:
    """Hard DP of column ``c`` with plain loops: returns (optimal energy, stixels bottom to top)."""
    col = _Column(prob, c, prm, cfg)
    n = col.n
    # best[i][k] = (energy, p, p_ground, back-pointer) of the best labelling of cells 0..i-1 ending in type k.
    best: list[list[tuple | None]] = [[None] * NUM_TYPES for _ in range(n + 1)]
    best[0][GROUND] = (0.0, 1.0 / col.h_cam, 1.0 / col.h_cam, None)
    for t in range(n):
        for T in range(NUM_TYPES):
            cand = None
            for b in range(t + 1):
                for k_prev in range(NUM_TYPES):
                    prev = best[b][k_prev]
                    if prev is None:
                        continue
                    e_prev, p_prev, g_prev, _ = prev
                    for e, cls, h, p in _segment_options(col, b, t, T, k_prev, p_prev, g_prev):
                        tot = e_prev + e
                        if cand is None or tot < cand[0]:
                            g_new = p if T == GROUND else g_prev
                            cand = (tot, p, g_new, (b, k_prev, cls, h, e))
            best[t + 1][T] = cand
    T_end = min(range(NUM_TYPES), key=lambda k: best[n][k][0])
    energy = best[n][T_end][0]
    stixels: list[RefStixel] = []
    i, T = n, T_end
    while i > 0:
        e_tot, p, g, (b, k_prev, cls, h, e) = best[i][T]
        stixels.append(RefStixel(b=b, t=i - 1, type=T, cls=cls, p=p, p_ground=g, h=h if T != SKY else -1, cost=e))
        i, T = b, k_prev
    return energy, stixels[::-1]


def column_energy(prob: ColumnProblem, c: int, prm: PriorParams, cfg: SolverConfig,
                  segments: list[tuple[int, int, int, int, int]]) -> float:
    """Energy of a labelled segmentation of column ``c``.

    Args:
        segments: bottom to top, ``(b, t, type, cls, h)`` with cells inclusive and ``h`` the
            hypothesis index (ignored for sky). Inverse depths follow from the labels and the
            structural rules exactly as in the solver.
    """
    return _segmentation_energy(_Column(prob, c, prm, cfg), segments)


def _segmentation_energy(col: _Column, segments: list[tuple[int, int, int, int, int]]) -> float:
    prm = col.prm
    k_prev, p_prev, g_prev = GROUND, 1.0 / col.h_cam, 1.0 / col.h_cam
    total = 0.0
    expect_b = 0
    for b, t, T, cls, h in segments:
        if b != expect_b or t < b:
            raise ValueError(f"segments must tile the column from cell 0 upward, got {segments}")
        h = max(h, 0) if T != SKY else 0
        p = col.segment_p(T, h, b, k_prev, p_prev, g_prev)
        total += (col.flow_cost(T, h, b, t) + col.structural(T, p, b, k_prev, p_prev, g_prev)
                  + col.sem_cost(cls, b, t) + _f(prm.beta_mc))
        g_prev = p if T == GROUND else g_prev
        k_prev, p_prev = T, p
        expect_b = t + 1
    if expect_b != col.n:
        raise ValueError(f"segments must end at the top cell {col.n - 1}")
    return total


def exhaustive_column(prob: ColumnProblem, c: int, prm: PriorParams, cfg: SolverConfig) -> float:
    """Minimum of :func:`column_energy` over every segmentation, type, class and hypothesis.

    Exponential: only for columns of a few cells and hypotheses. Unlike the DP, it does not take
    the predecessor's labels from the best path, so it is a lower bound of the DP optimum and equal
    to it whenever the structural priors do not depend on the predecessor.
    """
    col = _Column(prob, c, prm, cfg)
    n = col.n
    best = math.inf
    for cuts in range(1 << (n - 1)):
        bounds = [0] + [j + 1 for j in range(n - 1) if cuts >> j & 1] + [n]
        segs = [(bounds[k], bounds[k + 1] - 1) for k in range(len(bounds) - 1)]
        for types in itertools.product(range(NUM_TYPES), repeat=len(segs)):
            choices = [[(cls, h) for cls in col.classes[T] for h in range(col.n_hyp(T))] for T in types]
            for lab in itertools.product(*choices):
                segments = [(b, t, T, cls, h) for (b, t), T, (cls, h) in zip(segs, types, lab)]
                best = min(best, _segmentation_energy(col, segments))
    return best
