"""The solver's settings: the schema of the config group ``solver`` and the choices it accepts.

Its own module so that the column preparation (:mod:`monostixels.core.columns`), the DP
(:mod:`monostixels.core.solver`) and the post-processing (:mod:`monostixels.post.boundaries`) read one
definition without importing each other; :mod:`monostixels.core.solver` exports it too.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from monostixels._checks import InputError, choice, config_params
from monostixels.core.classes import DYNAMIC_OBJECT, STATIC_OBJECT
from monostixels.core.energy import load_config_group

__all__ = ["BACKENDS", "REFINE_OBJECTS", "SolverDtype", "SolverBackend", "RefineObjects", "SolverConfig"]

# The choices among names of the solver's settings: OmegaConf refuses any other value (monostixels._checks.Choice).
SolverDtype = choice("SolverDtype", "float32 float64", __name__)  # the compute dtype
SolverBackend = choice("SolverBackend", "auto eager cpp", __name__)  # the DP's implementation
RefineObjects = choice("RefineObjects", "dynamic all", __name__)  # whose tops move

#: ``solver.top_refine_objects``: the stixel types whose tops move.
REFINE_OBJECTS = {RefineObjects.dynamic: (DYNAMIC_OBJECT,), RefineObjects.all: (STATIC_OBJECT, DYNAMIC_OBJECT)}
#: ``solver.backend`` values: ``auto`` = the C++ kernel for the hard DP where it builds, else eager.
BACKENDS = tuple(SolverBackend.__members__)


@dataclass
class SolverConfig:
    """Solver settings: the schema of the config group ``solver`` (monostixels.config_schema).

    Attributes:
        column_width: column width w_s (pixels).
        cell_rows: vertical cell size r (pixel rows per DP cell).
        hypothesis_stride: hypotheses per column from every ``hypothesis_stride``-th cell (1 = every
            cell, the per-column superset of the paper's per-segment MLESAC hypotheses).
        standing_hypotheses: add, per cell, the static-object hypothesis that stands on the reference
            ground at the cell's lower edge (the scene model's depth), beside the flow-fitted ones.
        min_depth, max_depth: depth range of object and ground hypotheses (metres); others are discarded.
        tau: soft-min temperature of the DP (0 = hard min; > 0 for learning the priors).
        dtype: compute dtype, ``float32`` (fast) or ``float64`` (tests, gradient checks).
        min_translation: camera translations below this (metres) carry no depth: the frame is flagged
            and depths come from the scene model only (docs/conventions.md, section 7).
        backend: DP implementation: ``auto`` = the fused C++ kernel (monostixels/core/csrc/column_dp.cpp,
            built at first use, cached in ~/.cache/torch_extensions) for the hard DP, the eager torch code
            where it cannot be built (one warning) and for the soft DP (tau > 0) and gradients;
            ``eager`` = always the torch code; ``cpp`` = the kernel or an error. Both give bit-identical results.
        sky_horizon_margin_deg: sky is not seen more than this many degrees below the horizon of the road
            plane: there the sky class pays the flow and semantic caps on top (with semantics; YAML ``.inf``,
            command line ``inf`` = off). Where the flow fails (the image's lower corners) the net's score
            alone would decide, and bright road read as sky would become a sky stixel a few metres ahead.
        ground_horizon_margin_deg: likewise, ground is not seen more than this many degrees above that horizon
            (the ground classes pay both caps there): a vehicle driving along with the camera has the sky's
            flow, and a surface of it read as road would become ground above the horizon (a negative depth).
        top_refine_rows, top_refine_depth_ratio, top_refine_objects: moving objects' tops at pixel rows
            (monostixels/post/boundaries.py; applied by the pipeline after the DP and the mover check, with
            semantics only): where an object stixel (of ``top_refine_objects``: dynamic | all) has sky or an
            object more than ``top_refine_depth_ratio`` times farther above it, their boundary moves to the
            row within ``top_refine_rows`` rows (0 = off) where the two stixels' semantic term, read row by
            row, is least (docs/experiments.md, "Tops of movers").
    """

    column_width: int = 5
    cell_rows: int = 3
    hypothesis_stride: int = 1
    min_depth: float = 0.5
    max_depth: float = 300.0
    tau: float = 0.0
    dtype: SolverDtype = SolverDtype.float32
    min_translation: float = 0.05
    standing_hypotheses: bool = True
    backend: SolverBackend = SolverBackend.auto
    sky_horizon_margin_deg: float = 5.0
    ground_horizon_margin_deg: float = 5.0
    # Applied after the DP by the pipeline (monostixels.post.boundaries.refine_object_tops).
    top_refine_rows: int = 3
    top_refine_depth_ratio: float = 1.5
    top_refine_objects: RefineObjects = RefineObjects.dynamic

    def __post_init__(self) -> None:
        self.validate()

    @classmethod
    def from_yaml(cls, name: str = "default", **overrides: Any) -> "SolverConfig":
        """Settings of the packaged option ``solver=<name>`` as composed, with keyword overrides."""
        return config_params(cls, {**load_config_group("solver", name), **overrides}, "solver")

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
        if not self.min_translation >= 0:
            raise InputError(f"solver.min_translation: must be >= 0, got {self.min_translation}")
        for k in ("sky_horizon_margin_deg", "ground_horizon_margin_deg"):
            try:  # a command line gives `inf` as a float, but `.inf` (YAML's spelling) as a string
                margin = float(getattr(self, k))
            except (TypeError, ValueError):
                margin = math.nan
            if not margin >= 0:
                raise InputError(f"solver.{k}: degrees >= 0 (inf = off), got {getattr(self, k)!r}")
            setattr(self, k, margin)
        if not (isinstance(self.top_refine_rows, int) and self.top_refine_rows >= 0):
            raise InputError(f"solver.top_refine_rows: an integer >= 0 (0 = off), got {self.top_refine_rows!r}")
        if not (isinstance(self.top_refine_depth_ratio, (int, float)) and 1.0 <= self.top_refine_depth_ratio < math.inf):
            raise InputError(f"solver.top_refine_depth_ratio: a number >= 1, got {self.top_refine_depth_ratio!r}")

    @property
    def torch_dtype(self) -> torch.dtype:
        return torch.float64 if self.dtype == "float64" else torch.float32
