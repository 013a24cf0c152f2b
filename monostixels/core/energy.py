"""Data and prior terms of the mono-stixel energy (paper eq. 2-9), as torch ops.

All terms are in units of one pixel row of a column: data terms are summed over the rows of a
stixel. Every parameter comes from the Hydra config group ``prior`` (:class:`PriorConfig`); the
fields may be tensors with ``requires_grad`` so that the soft DP differentiates through them.
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass, fields
from functools import lru_cache
from typing import Any

import torch

from monostixels._checks import InputError, check_number, config_params
from monostixels._config import load_group

__all__ = [
    "GRAVITY_TOLERANCE_M",
    "load_config_group",
    "PriorConfig",
    "PriorParams",
    "flow_cost",
    "semantic_nll",
    "semantic_cost",
    "gravity",
    "ordering",
    "flatness",
    "ordering_from_depths",
    "height_over_ground",
]


#: Heights within this of the ground count as standing on it (metres). Objects placed on the
#: ground by the structural rule have Δh = 0 up to rounding, which must not pick the "sunk" branch.
GRAVITY_TOLERANCE_M = 1e-4


@dataclass
class PriorConfig:
    """The stixel priors and data-term weights as settings: the schema of the config group ``prior``
    (monostixels.config_schema); the defaults are the paper's priors (conf/prior/default.yaml chooses them).

    Energies are in units of one pixel row of a column: every data term is summed over the rows of a
    stixel. :meth:`params` gives the :class:`PriorParams` the solver takes.

    Attributes:
        beta_mc: model complexity, the cost of every new stixel. It must exceed the capped flow cost of a
            cell that straddles a boundary (``cell_rows x (alpha_F - log det C)``), else such cells split off.
        alpha_grav_below, beta_grav_below, alpha_grav_above, beta_grav_above: gravity (an object stixel
            above ground/sky, or the min with ordering above an object). ``dh`` = height of the object's
            bottom over the reference ground (metres); ``dh < 0`` (sunk into the ground):
            ``alpha_grav_below + beta_grav_below * |dh|``; ``dh >= 0`` (floating):
            ``alpha_grav_above + beta_grav_above * dh``.
        alpha_ord, beta_ord: ordering (an object above an object that is farther away):
            ``alpha_ord + beta_ord * (1/p_prev - 1/p)``, metres.
        alpha_flat, beta_flat: flat ground, ``alpha_flat + beta_flat * dh^2``, ``dh`` = height change to
            the reference ground (metres).
        alpha_F, alpha_L: robust caps of the flow and semantic data terms (outlier levels, per row).
        delta_F, delta_L: weights of the flow and semantic data terms.
        alpha_dyn: extra cost per row of a dynamic-object stixel (0 in the paper). With semantics off, the
            2-DOF dynamic type fits any flow at least as well as the 1-DOF static types; this keeps it honest.

    Every value must be finite and >= 0 (``alpha_flat`` may be negative).
    """

    beta_mc: float = 25.0
    alpha_grav_below: float = 2.0
    beta_grav_below: float = 20.0
    alpha_grav_above: float = 1.0
    beta_grav_above: float = 10.0
    alpha_ord: float = 4.0
    beta_ord: float = 1.0
    alpha_flat: float = 0.0
    beta_flat: float = 200.0
    alpha_F: float = 4.0
    alpha_L: float = 4.0
    delta_F: float = 1.0
    delta_L: float = 1.0
    alpha_dyn: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = float(check_number(getattr(self, f.name), f"prior.{f.name}"))
            if not math.isfinite(v):
                raise InputError(f"prior.{f.name}: must be finite, got {v}")
            if v < 0 and f.name != "alpha_flat":
                raise InputError(f"prior.{f.name}: must be >= 0, got {v}")
            setattr(self, f.name, v)

    def params(self) -> "PriorParams":
        """The solver's :class:`PriorParams` (floats)."""
        return PriorParams(**{k: getattr(self, k) for k in PriorParams.names()})


@dataclass
class PriorParams:
    """Prior parameters and data-term weights as the solver takes them (config group ``prior``: its
    settings are :class:`PriorConfig`, which documents each).

    Fields may be floats or 0-d tensors (for learning them through the soft DP); there are no defaults
    here: :meth:`from_yaml` gives those of a packaged option, :meth:`PriorConfig.params` those of a config.
    """

    beta_mc: Any
    alpha_grav_below: Any
    beta_grav_below: Any
    alpha_grav_above: Any
    beta_grav_above: Any
    alpha_ord: Any
    beta_ord: Any
    alpha_flat: Any
    beta_flat: Any
    alpha_F: Any
    alpha_L: Any
    delta_F: Any
    delta_L: Any
    alpha_dyn: Any

    @classmethod
    def from_yaml(cls, name: str = "default", **overrides: float) -> "PriorParams":
        """Parameters of the packaged option ``prior=<name>`` as composed, with keyword overrides."""
        return config_params(PriorConfig, {**load_config_group("prior", name), **overrides}, "prior").params()

    @staticmethod
    def names() -> list[str]:
        """Names of all parameters, in declaration order."""
        return [f.name for f in fields(PriorParams)]

    def as_tensors(self, dtype: torch.dtype = torch.float32) -> "PriorParams":
        """A copy whose float fields are 0-d tensors of ``dtype`` (tensors are kept, cast)."""
        out = {}
        for k in self.names():
            v = getattr(self, k)
            out[k] = v.to(dtype) if isinstance(v, torch.Tensor) else torch.tensor(float(v), dtype=dtype)
        return PriorParams(**out)

    def to_dict(self) -> dict[str, float]:
        """Plain floats, e.g. for writing a yaml file."""
        return {k: float(getattr(self, k)) for k in self.names()}


def load_config_group(group: str, name: str) -> dict[str, Any]:
    """The packaged option ``<group>=<name>`` as Hydra composes it (its schema's defaults, the YAML's
    choices and overrides), as a plain dict."""
    return copy.deepcopy(_composed_group(group, name))


@lru_cache(maxsize=None)
def _composed_group(group: str, name: str) -> dict[str, Any]:
    return load_group(group, name)


def flow_cost(residual: torch.Tensor, cov_inv: torch.Tensor, logdet: torch.Tensor, alpha_F: Any) -> torch.Tensor:
    """Robust flow term ``Φ_F = min(α_F, log det C + r^T C^-1 r / 2)`` per pixel row.

    Args:
        residual: ``r = f - f̂`` (..., 2) pixels.
        cov_inv: ``C^-1`` (..., 2, 2) 1/pixels^2 (broadcastable to ``residual``).
        logdet: ``log det C`` (...) (broadcastable).
        alpha_F: the outlier level (scalar or tensor).

    Returns:
        (...) cost.
    """
    rx, ry = residual[..., 0], residual[..., 1]
    q = cov_inv[..., 0, 0] * rx * rx + 2 * cov_inv[..., 0, 1] * rx * ry + cov_inv[..., 1, 1] * ry * ry
    return torch.minimum(logdet + 0.5 * q, torch.as_tensor(alpha_F, dtype=residual.dtype))


def semantic_nll(scores: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """``-log l_v(c)`` (10, H, W) of class scores (10, H, W) (pseudo-probabilities)."""
    return -torch.log(scores.clamp(min=eps))


def semantic_cost(nll: torch.Tensor, alpha_L: Any) -> torch.Tensor:
    """``Φ_L = min(α_L, -log l_v(c))`` elementwise."""
    return torch.minimum(nll, torch.as_tensor(alpha_L, dtype=nll.dtype))


def height_over_ground(p: torch.Tensor, q_bottom: torch.Tensor, p_ground: torch.Tensor) -> torch.Tensor:
    """Height ``Δh`` (metres) of an upright stixel's bottom over the reference ground.

    The bottom pixel's ray ``r`` meets the object plane at ``X = r / (p n_obj^T r)``; its height over
    the ground ``n_g^T X = 1/p_ground`` is ``1/p_ground - n_g^T X = 1/p_ground - q / p`` with
    ``q = n_g^T r / n_obj^T r`` (``q_bottom``). Positive = floating, negative = sunk.
    """
    return 1.0 / p_ground - q_bottom / p


def gravity(dh: torch.Tensor, prm: PriorParams) -> torch.Tensor:
    """Gravity prior ``Ψ_grav`` (paper eq. grav) of an object stixel with bottom height ``dh`` (metres).

    As printed, ``α⁻ + β⁻ Δh`` for ``Δh < 0`` would reward sinking deeper; like the ordering term
    (docs/conventions.md, section 2) we implement the penalty growing with the violation:
    ``α⁻ + β⁻ |Δh|``. ``|Δh| <= GRAVITY_TOLERANCE_M`` (an object standing on the ground) falls in
    the ``α⁺`` branch.
    """
    below = prm.alpha_grav_below + prm.beta_grav_below * (-dh)
    above = prm.alpha_grav_above + prm.beta_grav_above * dh
    return torch.where(dh < -GRAVITY_TOLERANCE_M, below, above)


def ordering(p: torch.Tensor, p_prev: torch.Tensor, prm: PriorParams) -> torch.Tensor:
    """Ordering prior ``Ψ_ord`` of an object stixel above an object stixel.

    Paper sign slip (docs/conventions.md, section 2): printed as
    ``α_ord + β_ord (1/p_i - 1/p_{i-1})`` for ``p_i > p_{i-1}``, where the bracket is negative. We
    use ``α_ord + β_ord (1/p_{i-1} - 1/p_i)``, a penalty that grows with the violation (the upper
    stixel being closer than the lower one).
    """
    viol = p > p_prev
    safe_prev = torch.where(viol, p_prev, torch.ones_like(p_prev))
    safe_p = torch.where(viol, p, torch.ones_like(p))
    pen = prm.alpha_ord + prm.beta_ord * (1.0 / safe_prev - 1.0 / safe_p)
    return torch.where(viol, pen, torch.zeros_like(pen))


def ordering_from_depths(d: torch.Tensor, prm: PriorParams) -> torch.Tensor:
    """:func:`ordering` written with ``d = 1/p_{i-1} - 1/p_i`` (metres): ``α_ord + β_ord d`` where ``d > 0``."""
    return torch.where(d > 0, prm.alpha_ord + prm.beta_ord * d, torch.zeros_like(d))


def flatness(p: torch.Tensor, p_ref: torch.Tensor, prm: PriorParams) -> torch.Tensor:
    """Flat-ground prior ``Ψ_flat = α_flat + β_flat Δh²`` with ``Δh = 1/p_ref - 1/p`` (metres)."""
    dh = 1.0 / p_ref - 1.0 / p
    return prm.alpha_flat + prm.beta_flat * dh * dh
