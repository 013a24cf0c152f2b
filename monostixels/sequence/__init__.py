"""What is carried between frames: keyframes and the sequence runner, the stream's reused work, the tracks."""
from __future__ import annotations

from monostixels.sequence.runner import KeyframeParams, SequenceRunner, SequenceStep, choose_keyframe, motion_matrix
from monostixels.sequence.tracked import TrackedFrame

__all__ = ["KeyframeParams", "SequenceStep", "SequenceRunner", "TrackedFrame", "choose_keyframe", "motion_matrix"]
