"""Mono-Stixels: the multi-layer stixel world from a single moving camera (Brickwedde et al., ICRA 2018)."""
from __future__ import annotations

__version__ = "0.1.0"
