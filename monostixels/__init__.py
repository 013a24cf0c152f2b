"""Mono-Stixels: the multi-layer stixel world from a single moving camera (Brickwedde et al., ICRA 2018)."""
from __future__ import annotations

from monostixels._threads import quiet_spinning

__version__ = "0.1.0"

# Idle OpenMP and OpenCV threads sleep instead of spinning (unless the user chose otherwise). On a
# machine shared with other jobs, spinning threads make 2-thread solves slower than 1-thread ones
# (docs/benchmarks.md). Effective only if torch and cv2 were not imported before monostixels.
quiet_spinning()
