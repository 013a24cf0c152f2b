"""The frame-pair type every data source yields and every command consumes, what a source must and may
provide (:class:`SequenceSource`, :class:`SequentialSource`, :class:`LiveSource`), and the keyframe settings.

The keyframe settings (:class:`KeyframeParams`, used by :mod:`monostixels.sequence.runner`) live here
because a live source sizes its buffer of frames by how far back a pair may reach.
"""
from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field, fields
from typing import Any, Protocol, runtime_checkable

import torch

from monostixels._checks import InputError, check_finite_fast, check_same_size, check_shape
from monostixels.core.geometry import Camera, Motion

__all__ = ["GroundTruth", "FrameInfo", "FramePair", "PreviousFrame", "KeyframeParams", "FOLDER_FPS", "SequenceSource",
           "SequentialSource", "LiveSource", "Source", "SourceInfo", "SourceAttributes", "source_info"]

#: Frame rate (Hz) of a folder of images that states none (``data=frames``' ``data.fps``): KITTI's 10 Hz.
FOLDER_FPS = 10.0


@dataclass
class GroundTruth:
    """Ground truth of a frame pair; every field is optional (absent = the source lacks it).

    Attributes:
        depth: (H, W) float32 metres (z in the current camera); 0 where there is no ground truth
            (sky, LiDAR gaps).
        flow: (2, H, W) float32 current -> previous, pixels.
        flow_valid: (H, W) bool, pixels where ``flow`` is defined (visible in both frames).
        labels: (H, W) int64 class ids 0..9, ``IGNORE_LABEL`` (255) where unknown.
        instances: (H, W) int64 instance ids (0 = background / stuff).
        moving: (H, W) bool, pixels of objects that move in the world.
        bottoms: (N, 2) float32 ``(u, v)`` stixel-bottom labels (first obstacle meets ground).
        velocity: (3, H, W) float32 world velocity of the surface seen at each pixel (m/s, relative
            to the ground, in the *current* camera's axes); 0 on static surfaces, NaN where unknown.
        ttc: (H, W) float32 time to contact (s): depth over the closing speed along the optical axis
            of the point relative to the camera; inf where it does not close, NaN where unknown.
    """

    depth: torch.Tensor | None = None
    flow: torch.Tensor | None = None
    flow_valid: torch.Tensor | None = None
    labels: torch.Tensor | None = None
    instances: torch.Tensor | None = None
    moving: torch.Tensor | None = None
    bottoms: torch.Tensor | None = None
    velocity: torch.Tensor | None = None
    ttc: torch.Tensor | None = None


@dataclass
class PreviousFrame:
    """An earlier frame of a sequence that the current frame can be paired with (keyframes).

    Attributes:
        back: how many of the source's frames (``data.step`` apart) it lies before the current one (>= 1).
        dt: seconds between it and the current frame.
        motion: the ground-truth camera motion from the current frame to it (``X_prev = R X_cur + t``)
            where the source knows it without reading images, else None.
        name: a stable identifier of that frame.
    """

    back: int
    dt: float
    motion: Motion | None
    name: str


@dataclass
class KeyframeParams:
    """Keyframe choice: the schema of the config group ``keyframes`` (monostixels.config_schema).

    Attributes:
        min_distance_m: the least driven distance between the two frames of a pair (metres; 0 = always
            the previous frame). The paper's: 0.5 m.
        window: earlier frames considered (>= 1).
        chain_flow: a pair reaching back past the previous frame takes its flow chained through the
            frames between (each frame's flow to the one before, kept by the stream, composed and then
            refined on the pair: :func:`monostixels.inputs.flow_chain.chained_flow`); False: the flow is computed
            on the pair directly.
        standing_max_s: a standing camera pairs with the oldest frame of the window at most this long
            ago (seconds; the movers' velocity is averaged over the pair, and should not lag behind the
            TTC warnings it feeds, ``ttc.warn_s`` 2 s by default).
    """

    min_distance_m: float = 0.5
    window: int = 10
    chain_flow: bool = True
    standing_max_s: float = 2.0

    def __post_init__(self) -> None:
        v = self.min_distance_m
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v >= 0):
            raise InputError(f"keyframes.min_distance_m: a distance >= 0 metres, got {v!r}")
        if isinstance(self.window, bool) or not isinstance(self.window, int) or self.window < 1:
            raise InputError(f"keyframes.window: an integer >= 1 (earlier frames considered), got {self.window!r}")
        if not isinstance(self.chain_flow, bool):
            raise InputError(f"keyframes.chain_flow: true or false, got {self.chain_flow!r}")
        v = self.standing_max_s
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
            raise InputError(f"keyframes.standing_max_s: a time > 0 seconds, got {v!r}")


@dataclass(frozen=True)
class FrameInfo:
    """The keys of :attr:`FramePair.meta` that the pipeline and the sequence layer read, typed: a view of
    ``meta`` (:attr:`FramePair.info`), which stays where sources write them. None = the source does not say.

    Attributes:
        sequence: the clip the pair belongs to (:meth:`SequentialSource.sequence_key`); pairs of one clip
            come in time order.
        frame: the source's number of the current frame (raw frame, video frame, clip frame).
        frame_prev: the source's number of the earlier frame (``frame - back`` frames of ``data.step``).
        name_prev: a stable identifier of the earlier frame.
        back: how many of the source's frames the earlier frame lies back (1: the previous one; more: a
            keyframe pair, or a pair across unreadable frames).
        dt: seconds between the two frames.
        time_s: the current frame's time in its recording (seconds).
        timestamp, timestamp_prev: the two frames' timestamps as the source writes them (DDAD: microseconds).
        ignore_mask: (H, W) bool, True = pixels to ignore (``data.mask``, pixels undistortion leaves empty).
        ignore_pixels: (H, W) bool, the part of ``ignore_mask`` left once a bonnet's rows are cut off
            (:func:`monostixels.data.static_regions.crop_ignored`), or None.
        source: the kind of source that made the pair (``"video"``, ``"frames"``, ``"kitti_raw"``...):
            messages, and a video's frame times.
        dataset: the dataset's name, where a source writes it instead of ``source`` (messages).
        path, path_prev: the files of the two frames (an image, or the video of a video frame).
        frame_index, frame_index_prev: the two frames' numbers in a poses file (``motion=file``; a source
            that writes none is looked up by ``frame`` / ``frame_prev``).
        nominal_camera: True where the camera is a nominal one, not calibrated (single labelled images
            such as CamVid): ``semantic.focal_px`` is not applied.
        motion_source: where the ground-truth camera motion comes from (a poses file, the OXTS
            velocities): ``eval``'s report.
        full_pair: the pair before a bonnet's rows were cut off
            (:func:`monostixels.data.static_regions.crop_ignored`), from which the outputs take back the
            frame's size.
        capture_time_s, capture_time_prev_s: a live source's capture times of the two frames (seconds: the
            position in a file, or since the first frame of a camera or URL).
        dropped_before: a live source's frames dropped since the frame taken before the current one.
        realtime: a live source's ``data.realtime``.
    """

    sequence: str | None = None
    frame: int | None = None
    frame_prev: int | None = None
    name_prev: str | None = None
    back: int | None = None
    dt: float | None = None
    time_s: float | None = None
    timestamp: Any = None
    timestamp_prev: Any = None
    ignore_mask: torch.Tensor | None = None
    ignore_pixels: torch.Tensor | None = None
    source: str | None = None
    dataset: str | None = None
    path: str | None = None
    path_prev: str | None = None
    frame_index: int | None = None
    frame_index_prev: int | None = None
    nominal_camera: bool | None = None
    motion_source: str | None = None
    full_pair: FramePair | None = None
    capture_time_s: float | None = None
    capture_time_prev_s: float | None = None
    dropped_before: int | None = None
    realtime: bool | None = None

    @classmethod
    def of(cls, meta: dict[str, Any]) -> FrameInfo:
        """The view of ``meta`` (values as the source wrote them)."""
        return cls(**{k: meta.get(k) for k in _INFO_KEYS})


_INFO_KEYS = tuple(f.name for f in fields(FrameInfo))


@dataclass
class FramePair:
    """A current image, the previous image, the camera and (when known) the camera motion.

    Attributes:
        image: current image (3, H, W) float32 RGB in [0, 1].
        image_prev: previous image (3, H, W) float32 RGB in [0, 1].
        camera: intrinsics, height and ground normal.
        motion: camera motion ``X_prev = R X_cur + t`` (ground truth or from a poses file), or None.
        gt: ground truth, fields absent where the source lacks them.
        name: a stable identifier (file stem, ``synthetic_000003``...).
        meta: anything else a source wants to pass on (seed, timestamps). The keys with a fixed meaning
            are the fields of :class:`FrameInfo`, read through :attr:`info`; ``"ignore_mask"``: (H, W) torch
            bool, True = pixels to ignore (the user's ``data.mask``, and pixels that undistortion leaves
            without a source; ``data=video`` / ``data=frames``), at the image's size; absent = use every pixel.
    """

    image: torch.Tensor
    image_prev: torch.Tensor
    camera: Camera
    motion: Motion | None = None
    gt: GroundTruth = field(default_factory=GroundTruth)
    name: str = ""
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_shape(self.image, [3, "H", "W"], f"{self.name or 'frame'}: image")
        check_shape(self.image_prev, [3, "H", "W"], f"{self.name or 'frame'}: image_prev")
        check_same_size(self.image, self.image_prev, "image (current)", "image_prev (previous)")
        check_finite_fast(self.image, "image")
        if self.gt.depth is not None:
            check_same_size(self.gt.depth, self.image, "gt.depth", "image")
        ignore = self.info.ignore_mask
        if ignore is not None:
            check_shape(ignore, list(self.image.shape[-2:]), f"{self.name or 'frame'}: meta['ignore_mask']")
            if ignore.dtype != torch.bool:
                raise InputError(f"{self.name or 'frame'}: meta['ignore_mask'] must be a bool tensor, got {ignore.dtype}")

    @property
    def info(self) -> FrameInfo:
        """The keys of :attr:`meta` with a fixed meaning, typed (a view: write to ``meta``)."""
        return FrameInfo.of(self.meta)

    @property
    def size(self) -> tuple[int, int]:
        """(H, W) in pixels."""
        return int(self.image.shape[-2]), int(self.image.shape[-1])


# ---------------------------------------------------------------------------------------------- sources
# What the sequence layer (monostixels.sequence), the writers (monostixels.output.writers) and eval ask
# of a data source. The capabilities are protocols checked with isinstance, so that a source of one's
# own reads here, in one place, what it must and may provide.


@runtime_checkable
class SequenceSource(Protocol):
    """A recorded source: every source must provide these (``Sequence[FramePair]`` does).

    Pairs are read on access, in any order; a pair that cannot be made raises
    :class:`monostixels.data._lazy_source.PairSkipped` (warned about and skipped by the sequence layer).

    The attributes of :class:`SourceInfo` (``fps``, ``step``, ``skipped_frames``, ``restarts``) are part of
    a source too: every source of :mod:`monostixels.data` has them (:class:`SourceAttributes`), and a
    source of one's own that leaves them out has their defaults. They are read through
    :func:`source_info`, never probed one by one.
    """

    def __len__(self) -> int:
        """Number of frame pairs."""
        ...

    def __getitem__(self, index: int) -> FramePair:
        """Pair ``index``: its current frame with the frame before it."""
        ...


@runtime_checkable
class SequentialSource(Protocol):
    """A source whose pairs are frames of clips (videos, drives): keyframes, tracks, TTC and
    ``stream.overlap`` run on them. Without these methods every pair is solved on its own."""

    def __getitem__(self, index: int) -> FramePair:
        ...

    def sequence_key(self, index: int) -> str | None:
        """The clip pair ``index`` belongs to (pairs of one clip come in time order); None for an
        independent pair."""
        ...

    def previous_frames(self, index: int, window: int) -> list[PreviousFrame]:
        """Earlier frames pair ``index``'s current frame can be paired with, 1 to ``window`` frames back
        (nearest first), without reading images."""
        ...

    def pair_back(self, index: int, back: int) -> FramePair:
        """Pair ``index``'s current frame with the frame ``back`` frames earlier (1: pair ``index``)."""
        ...


@runtime_checkable
class LiveSource(SequentialSource, Protocol):
    """A source of frames as they come (a camera, a URL, ``data.realtime``): no length; the sequence
    layer takes the pairs' indices from :meth:`indices`, and reads only pairs of frames still kept."""

    def indices(self) -> Iterator[int]:
        """Pair indices as frames arrive (blocking until each does); stops the reading when done."""
        ...

    def summary(self) -> dict[str, Any]:
        """Which frames were processed and dropped (``run``'s ``stream.json``, docs/conventions.md)."""
        ...

    def close(self) -> None:
        """Stop reading (a source never iterated)."""
        ...


#: Any data source: recorded (with a length) or live (frames as they come).
Source = SequenceSource | LiveSource


@dataclass(frozen=True)
class SourceInfo:
    """What a source says of its frames besides its pairs (:func:`source_info`); the defaults are those
    of a source that does not say.

    Attributes:
        fps: frames per second of the recording (a video's frame rate: ``run``'s videos, the frames'
            times), or None (unknown: image folders give ``data.fps``, others none).
        step: recorded frames per frame offered (``data.step``; >= 1).
        skipped_frames: labels (file name, ``video frame N``) of the frames found unreadable so far, in the
            order found (``run``'s and ``eval``'s summaries).
        restarts: names of the frames where a sequence started again after unreadable frames.
    """

    fps: float | None = None
    step: int = 1
    skipped_frames: list[str] = field(default_factory=list)
    restarts: list[str] = field(default_factory=list)


class SourceAttributes:
    """The :class:`SourceInfo` attributes with their defaults: a base of every source of
    :mod:`monostixels.data`, which sets (or computes) those it knows."""

    #: Frames per second of the recording, or None (unknown).
    fps: float | None = None
    #: Recorded frames per frame offered.
    step: int = 1

    @property
    def skipped_frames(self) -> list[str]:
        """Labels of the frames found unreadable so far (none)."""
        return []

    @property
    def restarts(self) -> list[str]:
        """Names of the frames where a sequence started again (none)."""
        return []


def source_info(src: object) -> SourceInfo:
    """``src``'s :class:`SourceInfo` now (``skipped_frames`` and ``restarts`` grow as pairs are read).

    The one place where a source's attributes are read: a source of one's own may have none of them
    (``__len__`` and ``__getitem__`` are all a source must provide), and gets the defaults.
    """
    return SourceInfo(fps=getattr(src, "fps", None), step=getattr(src, "step", 1),
                      skipped_frames=list(getattr(src, "skipped_frames", [])),
                      restarts=list(getattr(src, "restarts", [])))
