"""Data and prior terms of the mono-stixel energy (paper eq. 2-9), as torch ops.

All terms are in units of one pixel row of a column: data terms are summed over the rows of a
stixel. Every parameter comes from the Hydra config group ``prior`` (:class:`PriorParams`); the
fields may be tensors with ``requires_grad`` so that the soft DP differentiates through them.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Mapping

import torch

from monostixels._checks import InputError, check_keys, check_number

__all__ = [
    "GRAVITY_TOLERANCE_M",
    "load_config_group",
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
class PriorParams:
    """Prior parameters and data-term weights (config group ``prior``; units in conf/prior/default.yaml).

    There are no defaults in code: :meth:`from_yaml` reads ``conf/prior/<name>.yaml``. Fields may
    be floats or 0-d tensors (for learning them through the soft DP).
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
        """Parameters of ``conf/prior/<name>.yaml`` (as packaged), with keyword overrides."""
        return cls.from_config({**load_config_group("prior", name), **overrides})

    @staticmethod
    def names() -> list[str]:
        """Names of all parameters, in declaration order."""
        return [f.name for f in fields(PriorParams)]

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> "PriorParams":
        """Build from the ``prior`` config node; unknown or missing keys are errors."""
        check_keys(cfg.keys(), cls.names(), "prior config")
        values = {k: float(check_number(cfg[k], f"prior.{k}")) for k in cls.names()}
        for k, v in values.items():
            if not torch.isfinite(torch.tensor(v)):
                raise InputError(f"prior.{k}: must be finite, got {v}")
            if v < 0 and k != "alpha_flat":
                raise InputError(f"prior.{k}: must be >= 0, got {v}")
        return cls(**values)

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
    """The packaged config file ``conf/<group>/<name>.yaml`` as a plain dict."""
    from importlib.resources import files

    from omegaconf import OmegaConf

    res = files("monostixels.conf").joinpath(group, f"{name}.yaml")
    if not res.is_file():
        raise InputError(f"config {group}={name}: no file conf/{group}/{name}.yaml")
    return OmegaConf.to_container(OmegaConf.create(res.read_text()), resolve=True)  # type: ignore[return-value]


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
