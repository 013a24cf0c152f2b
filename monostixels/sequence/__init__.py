"""What is carried between frames: keyframes and the sequence runner, the stream's reused work, the tracks.

The runner's public names (``from monostixels.sequence import SequenceRunner``) load at first use:
``runner.py`` builds on :mod:`monostixels.pipeline`, and the pipeline imports this package's
``stream.py``, so an import of ``runner.py`` here would make ``import monostixels.pipeline`` circular.
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from monostixels.sequence.runner import KeyframeParams, SequenceRunner, SequenceStep, choose_keyframe, motion_matrix

__all__ = ["KeyframeParams", "SequenceStep", "SequenceRunner", "choose_keyframe", "motion_matrix"]


def __getattr__(name: str) -> object:
    if name in __all__:
        return getattr(importlib.import_module("monostixels.sequence.runner"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
