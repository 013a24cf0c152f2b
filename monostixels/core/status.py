"""What is known about a frame beside its stixels, typed: the camera motion's status, the post-processing's
counts and a live source's frames (:attr:`StixelWorld.status <monostixels.core.stixels.StixelWorld.status>`).

``stixels.json`` writes them as its ``flags`` (docs/conventions.md, section 4.4): :meth:`FrameStatus.to_flags`
and :meth:`FrameStatus.from_flags` are the only places that know those keys. The camera motion's kinds
(:class:`MotionKind`, :class:`ScaleFrom`) live here, below the stixel world that holds them;
:mod:`monostixels.inputs.motion_base` exports them too.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

__all__ = ["MotionKind", "ScaleFrom", "MotionStatus", "FrameCounts", "StreamFrames", "FrameStatus"]


class _Named(str, Enum):
    """An enum whose members are their strings: equal to them, and written as them (``str``, f-strings,
    JSON), so that ``stixels.json`` keeps the strings of docs/conventions.md."""

    def __str__(self) -> str:
        # Python 3.12 formats mixed-in enums with __str__ ("MotionKind.METRIC" by default).
        return str(self.value)


class MotionKind(_Named):
    """What a camera-motion estimate knows (:attr:`MotionEstimate.kind`, ``flags.camera_motion``). Only
    ``standing`` lets the movers treat every flow vector as object motion; ``scale_unknown`` and ``unknown``
    call nothing moving."""

    METRIC = "metric"                # rotation and metric translation
    STANDING = "standing"            # no translation: standing still or turning on the spot
    SCALE_UNKNOWN = "scale_unknown"  # rotation and translation direction, not its length
    UNKNOWN = "unknown"              # nothing known about the camera


class ScaleFrom(_Named):
    """Where a metric translation's length came from (:attr:`MotionEstimate.scale_from`, ``flags.scale_from``)."""

    GIVEN = "given"              # gt / file
    PHOTOMETRIC = "photometric"  # the road's image alignment
    ROAD_MARKS = "road_marks"    # the road's marks and the travel direction (monostixels.inputs.road_marks)
    GROUND_FLOW = "ground_flow"  # the road's flow vectors
    SEQUENCE = "sequence"        # the recent pairs' speed (monostixels.inputs.motion_track.MotionTrack)
    SCENE = "scene"              # static objects standing on the ground (monostixels.inputs.motion_scene)


@dataclass
class MotionStatus:
    """The camera motion a frame was solved with, as the outputs report it. None: not set (a solver's
    result before the pipeline, a stixel world built by hand).

    Attributes:
        degenerate: no usable metric translation: depths from the scene model (``degenerate_motion``).
        reason: why (text), where degenerate or where static depths were carried from the tracks; "" = none.
        kind: what the ego-motion knew (``camera_motion``).
        scale_from: where a metric translation's length came from (``scale_from``).
        scale_std: a metric motion's scale uncertainty, std of ``log |t|`` (``scale_std``).
        scale_uncertain: ``scale_std`` above ``motion.max_scale_std`` (``scale_uncertain``; set with it).
        camera_height_fit_m: the camera height the road implies under a given motion (``camera_height_fit_m``).
    """

    degenerate: bool | None = None
    reason: str = ""
    kind: MotionKind | None = None
    scale_from: ScaleFrom | None = None
    scale_std: float | None = None
    scale_uncertain: bool | None = None
    camera_height_fit_m: float | None = None

    @property
    def is_degenerate(self) -> bool:
        """``degenerate`` as a bool (False where not set)."""
        return bool(self.degenerate)

    def add_reason(self, text: str, first: bool = False) -> None:
        """Join ``text`` to :attr:`reason` with ``"; "`` (before it where ``first``)."""
        parts = (text, self.reason) if first else (self.reason, text)
        self.reason = "; ".join(p for p in parts if p)


@dataclass
class FrameCounts:
    """Stixels the post-processing changed (None: the step did not run).

    Attributes:
        static_checked: dynamic stixels the mover check made static.
        receding_static: static object stixels pulling away whose depth became the scene model's.
        movers_suppressed: dynamic stixels made static for an unknown camera motion.
        ignored_pixels: pixels of the frame's ignore mask (a bonnet, ``data.mask``).
        carried_stixels: static stixels whose depth was kept from their tracks (sequence layer).
    """

    static_checked: int | None = None
    receding_static: int | None = None
    movers_suppressed: int | None = None
    ignored_pixels: int | None = None
    carried_stixels: int | None = None


@dataclass
class StreamFrames:
    """Which frames of a live source a pair is made of (``flags.stream``), as the source wrote them."""

    frame: Any = None
    capture_time_s: Any = None
    previous_frame: Any = None
    previous_capture_time_s: Any = None
    dropped_before: Any = None
    realtime: Any = None

    def to_dict(self) -> dict[str, Any]:
        """The ``flags.stream`` dict."""
        return {"frame": self.frame, "capture_time_s": self.capture_time_s, "previous_frame": self.previous_frame,
                "previous_capture_time_s": self.previous_capture_time_s, "dropped_before": self.dropped_before,
                "realtime": self.realtime}


_COUNT_KEYS = ("static_checked", "receding_static", "movers_suppressed", "ignored_pixels", "carried_stixels")


@dataclass
class FrameStatus:
    """Everything known about a frame beside its stixels: :class:`MotionStatus`, :class:`FrameCounts` and,
    for live sources, :class:`StreamFrames` (None otherwise)."""

    motion: MotionStatus = field(default_factory=MotionStatus)
    counts: FrameCounts = field(default_factory=FrameCounts)
    stream: StreamFrames | None = None

    def copy(self) -> "FrameStatus":
        """An independent copy (a new stixel world's status is changed without touching the old one's)."""
        return copy.deepcopy(self)

    def to_flags(self) -> dict[str, Any]:
        """The ``flags`` of ``stixels.json`` (docs/conventions.md, section 4.4): plain strings, numbers and
        bools, keys that are not set left out, in the order the pipeline's steps set them."""
        m, c = self.motion, self.counts
        out: dict[str, Any] = {}
        if m.degenerate is not None:
            out["degenerate_motion"] = bool(m.degenerate)
        if m.degenerate and m.reason:
            out["reason"] = m.reason
        for key in ("static_checked", "receding_static"):
            if getattr(c, key) is not None:
                out[key] = getattr(c, key)
        if m.camera_height_fit_m is not None:
            out["camera_height_fit_m"] = m.camera_height_fit_m
        if c.movers_suppressed is not None:
            out["movers_suppressed"] = c.movers_suppressed
        if m.kind is not None:
            out["camera_motion"] = MotionKind(m.kind).value
        if m.scale_from is not None:
            out["scale_from"] = ScaleFrom(m.scale_from).value
        if m.scale_std is not None:
            out["scale_std"] = m.scale_std
        if m.scale_uncertain is not None:
            out["scale_uncertain"] = m.scale_uncertain
        if self.stream is not None:
            out["stream"] = self.stream.to_dict()
        for key in ("ignored_pixels", "carried_stixels"):
            if getattr(c, key) is not None:
                out[key] = getattr(c, key)
        if not m.degenerate and m.reason:
            out["reason"] = m.reason
        return out

    @staticmethod
    def from_flags(flags: dict[str, Any]) -> "FrameStatus":
        """Inverse of :meth:`to_flags` (keys it does not know are left out)."""
        f = dict(flags)
        deg = f.get("degenerate_motion")
        motion = MotionStatus(
            degenerate=None if deg is None else bool(deg), reason=str(f.get("reason", "") or ""),
            kind=MotionKind(f["camera_motion"]) if f.get("camera_motion") is not None else None,
            scale_from=ScaleFrom(f["scale_from"]) if f.get("scale_from") is not None else None,
            scale_std=f.get("scale_std"), scale_uncertain=f.get("scale_uncertain"),
            camera_height_fit_m=f.get("camera_height_fit_m"))
        counts = FrameCounts(**{k: f.get(k) for k in _COUNT_KEYS})
        stream = StreamFrames(**dict(f["stream"])) if isinstance(f.get("stream"), dict) else None
        return FrameStatus(motion=motion, counts=counts, stream=stream)
