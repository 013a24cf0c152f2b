"""What the sequence layer returns for a frame: the pair's stixels with what the tracks and the pose chain add.

The pipeline's :class:`~monostixels.core.stixels.StixelWorld` of a pair is left as the pipeline built it (the
tracks' filtered depths aside, which make a new one); the sequence layer's per-stixel results live in a
:class:`TrackedFrame` beside it. :meth:`TrackedFrame.world` is the stixel world as ``stixels.json`` writes it,
with the sequence fields (docs/conventions.md, section 4.4).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import torch

from monostixels.core.stixels import StixelWorld

__all__ = ["TrackedFrame"]


@dataclass
class TrackedFrame:
    """One frame as the sequence layer saw it.

    Attributes:
        stixels: the pair's stixels (tracked static depths filtered where the tracks had them).
        track_id: (N,) int64 track of each object stixel (-1: ground, sky, untracked).
        velocity: (N, 3) world velocity, m/s (world = the sequence's first camera; 0: ground, sky).
        ttc_s: (N,) time to collision, seconds (inf: not closing).
        ttc_warning: (N,) bool, closing within ``ttc.warn_s`` inside the camera's path.
        pose: (4, 4) camera-to-world of the frame, None where the camera motion is unknown.
        pair_info: the pair solved (``current``, ``previous`` frame names, ``frames_back``, ``dt_s``,
            ``driven_m``, ``keyframe_distance_m``).
    """

    stixels: StixelWorld
    track_id: torch.Tensor
    velocity: torch.Tensor
    ttc_s: torch.Tensor
    ttc_warning: torch.Tensor
    pose: torch.Tensor | None
    pair_info: dict[str, Any]

    @staticmethod
    def untracked(stixels: StixelWorld, pair_info: dict[str, Any]) -> "TrackedFrame":
        """A frame without tracks, velocities, time to collision or pose (an unknown camera motion)."""
        N = len(stixels)
        return TrackedFrame(stixels=stixels, track_id=torch.full((N,), -1, dtype=torch.long),
                            velocity=torch.zeros(N, 3, dtype=torch.float64),
                            ttc_s=torch.full((N,), math.inf, dtype=torch.float64),
                            ttc_warning=torch.zeros(N, dtype=torch.bool), pose=None, pair_info=pair_info)

    def world(self) -> StixelWorld:
        """A new stixel world: :attr:`stixels` with the sequence fields, as ``stixels.json`` writes it."""
        return dataclasses.replace(self.stixels, track_id=self.track_id, velocity=self.velocity, ttc_s=self.ttc_s,
                                   ttc_warning=self.ttc_warning, pose=self.pose, pair_info=self.pair_info)
