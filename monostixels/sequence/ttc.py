"""Time to collision and its warnings (paper: ``t̃`` "represent the time to contact in the longitudinal and lateral
direction"): with the stixel at ``X`` and the relative velocity ``v_rel = v - v_cam`` in the current
camera's axes, ``ttc = Z / -v_rel,z`` where ``v_rel,z < 0`` (closing), else ``inf``; each track
filters the closing rate ``-v_rel,z / Z`` (a scalar filter with a chi-square gate on each pair's rate).
A stixel is *critical* when ``ttc < warn_s`` and its lateral position at contact, ``X + v_rel,x ttc``,
lies within ``corridor_m`` of the camera's path.

The track that filters the closing rate: :mod:`monostixels.sequence.tracking`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from monostixels._checks import InputError
from monostixels.core.stixels import StixelWorld, neighbours

__all__ = ["TtcParams", "time_to_collision", "critical", "confirmed", "object_wide"]


@dataclass
class TtcParams:
    """Time-to-collision warnings: the schema of the config group ``ttc`` (monostixels.config_schema).

    Attributes:
        warn_s: a stixel closing in less than this (seconds) within the corridor is critical.
        corridor_m: half width of the camera's path (metres) a critical stixel's contact lies in.
        confirm_frames: on a tracked sequence, a critical stixel is warned about only once its track has
            continued this many frames: its closing rate is then filtered over them, not one pair's (a
            sliver of road taken for an object for one frame raises nothing). 0 = every critical stixel.
        max_closing_mps: the fastest closing speed (m/s) a warning is raised at: two cars meeting head-on at
            110 km/h each close at 61 m/s; a faster one is the estimate's error, not a road's traffic.

    Warnings are raised only on the classes that can move (vehicle, two-wheeler, person), on objects wider than
    one column (:func:`object_wide`), and never where the camera motion's length is uncertain
    (:mod:`monostixels.sequence.runner`).
    """

    warn_s: float = 2.0
    corridor_m: float = 1.5
    confirm_frames: int = 2
    max_closing_mps: float = 61.0

    def __post_init__(self) -> None:
        for k in ("warn_s", "corridor_m", "max_closing_mps"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0):
                raise InputError(f"ttc.{k}: a number > 0, got {v!r}")
        v = self.confirm_frames
        if not (isinstance(v, int) and not isinstance(v, bool) and v >= 0):
            raise InputError(f"ttc.confirm_frames: a whole number >= 0, got {v!r}")


def time_to_collision(X: torch.Tensor, v_rel: torch.Tensor) -> torch.Tensor:
    """Longitudinal time to collision (N,) seconds: ``Z / -v_rel,z`` where closing, else inf.

    Args:
        X: (N, 3) positions in the current camera (metres). v_rel: (N, 3) velocities relative to the
            camera, same axes (m/s).
    """
    closing = -v_rel[:, 2]
    ok = (closing > 1e-6) & (X[:, 2] > 0)
    return torch.where(ok, X[:, 2] / closing.clamp_min(1e-6), torch.full_like(closing, math.inf))


def critical(X: torch.Tensor, v_rel: torch.Tensor, ttc: torch.Tensor, params: TtcParams) -> torch.Tensor:
    """(N,) bool: in the camera's path now (``|X| < corridor_m``), closing within ``warn_s`` at a plausible
    speed (``-v_rel,z <= max_closing_mps``), with the contact inside the corridor ``|X + v_rel,x ttc| < corridor_m``.

    ``ttc`` (N,) seconds: the caller's time to collision; where it comes from a track's filtered closing rate,
    the caller passes the larger of it and the one of the track's filtered velocity, so that a warning needs a
    closing that holds in both (a single stixel's rate that grows while its track's velocity does not is noise).
    """
    lateral = X[:, 0] + v_rel[:, 0] * torch.where(torch.isfinite(ttc), ttc, torch.zeros_like(ttc))
    return ((ttc < params.warn_s) & (lateral.abs() < params.corridor_m) & (X[:, 0].abs() < params.corridor_m)
            & (-v_rel[:, 2] <= params.max_closing_mps))


def object_wide(warn: torch.Tensor, world: StixelWorld) -> torch.Tensor:
    """(N,) bool: the warned stixels ``warn`` (N,) with a warned stixel beside them (an adjacent column, a
    shared row): a vehicle, a two-wheeler or a person is wider than one column; a lone column is a sliver
    the net called a vehicle (a shadow, a road mark), not an object closing."""
    idx = torch.nonzero(warn).flatten()
    if idx.numel() == 0:
        return warn
    beside = neighbours(world.column[idx], world.v_top[idx], world.v_bottom[idx]).any(1)
    out = torch.zeros_like(warn)
    out[idx[beside]] = True
    return out


def confirmed(warn: torch.Tensor, age: torch.Tensor | None, params: TtcParams) -> torch.Tensor:
    """(N,) bool: the critical stixels ``warn`` (N,) whose track has continued ``params.confirm_frames`` frames
    (``age`` (N,), from :meth:`monostixels.sequence.tracking.Tracks.update`); all of ``warn`` without tracks (``age`` None) or a count of 0."""
    if age is None or params.confirm_frames <= 0:
        return warn
    return warn & (age >= params.confirm_frames)
