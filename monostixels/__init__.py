"""Mono-Stixels: the multi-layer stixel world from a single moving camera (Brickwedde et al., ICRA 2018)."""
from __future__ import annotations

import os

__version__ = "0.1.0"

# Idle OpenMP threads sleep instead of spinning (unless the user chose otherwise). On a machine
# shared with other jobs, spinning threads made 2-thread solves 2-4x slower than 1-thread ones
# (README "Solver speed"). Effective only if torch was not imported before monostixels.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
