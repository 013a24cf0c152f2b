"""The lazy data source: frame pairs loaded on access, unreadable frames skipped (paired across, or the
sequence started again), and the frame limit of a source."""
from __future__ import annotations

import logging
import math
from typing import Any, Iterator, Sequence

from monostixels._checks import InputError
from monostixels.data.base import FramePair, PreviousFrame, SourceAttributes
from monostixels.core.geometry import Motion

__all__ = [
    "MAX_SKIPPED_FRAMES",
    "UnreadableFrame",
    "PairSkipped",
    "LazySource",
    "limit_frames",
]


logger = logging.getLogger(__name__)


#: Consecutive unreadable frames a pair may reach across: the pair after them takes the last readable
#: frame before them (at 10 Hz 0.3 s, a baseline the flow still matches). A longer gap, or unreadable
#: frames at the very start, starts the sequence again: the first readable frame after them is the
#: previous frame of the next pair (it has no pair of its own; tracks and the stream start afresh).
MAX_SKIPPED_FRAMES = 3


class UnreadableFrame(InputError):
    """A frame of a sequence that cannot be read or decoded (raised by a source's ``_load``).

    Attributes:
        name: the frame's name as the source's ``_prev_name`` gives it (file stem, ``clip_000017``).
        label: how reports name it (the file name, ``video frame 17``).
        current: whether it is the pair's current frame (else its previous frame).
    """

    def __init__(self, message: str, *, name: str, label: str, current: bool) -> None:
        super().__init__(message)
        self.name, self.label, self.current = name, label, current


class PairSkipped(InputError):
    """A pair that cannot be made because frames could not be read: its current frame is unreadable, or
    no readable frame lies within :data:`MAX_SKIPPED_FRAMES` before it (the sequence starts again there).
    It has been warned about; callers skip it (:class:`monostixels.sequence.SequenceRunner`)."""


class LazySource(SourceAttributes, Sequence[FramePair]):
    """A sequence of frame pairs that indexes its files up front and reads images on access.

    Subclasses fill ``self._items`` (one record per pair) in ``__init__`` (so that a missing folder
    or calibration file fails at construction) and implement ``_load(item) -> FramePair`` (so that
    an unreadable image fails when that pair is used, naming the file).

    Sequences (keyframes, tracks: :mod:`monostixels.sequence`): a source whose pairs are frames of
    videos or drives also implements ``_sequence_key(item)`` (the clip a pair belongs to; pairs of
    one clip come in time order), ``_back(item, back)`` (the same current frame paired with the
    frame ``back`` of its frames earlier, or None where there is none) and, where it knows them
    without reading images, ``_pair_dt(item)`` (seconds) and ``_pair_motion(item)`` (ground-truth
    camera motion). Independent pairs keep the defaults (no sequence).

    Unreadable frames (a sequence source's ``_load`` raises :class:`UnreadableFrame`) are skipped with a
    warning naming them: a pair whose previous frame is unreadable takes the readable frame before it
    (up to :data:`MAX_SKIPPED_FRAMES` back, else the sequence starts again), a pair whose current frame
    is unreadable raises :class:`PairSkipped`. :attr:`skipped_frames` lists them, :attr:`restarts` the
    frames where a sequence started again.
    """

    _items: list[Any]

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, index: int) -> FramePair:  # type: ignore[override]
        return self._load_readable(index, 1)

    def __iter__(self) -> Iterator[FramePair]:
        """The pairs in order, those that cannot be made (:class:`PairSkipped`) left out (each warned about)."""
        for index in range(len(self._items)):
            try:
                yield self[index]
            except PairSkipped:
                continue

    # --- unreadable frames ----------------------------------------------------------------------
    @property
    def skipped_frames(self) -> list[str]:
        """Labels (file name, ``video frame N``) of the frames found unreadable so far, in the order found."""
        return list(self.__dict__.get("_unreadable", {}).values())

    @property
    def restarts(self) -> list[str]:
        """Names of the frames where a sequence started again after unreadable frames."""
        return list(self.__dict__.get("_restarts", {}).values())

    def _note_unreadable(self, err: UnreadableFrame) -> None:
        # State kept in the instance's __dict__, created on first use: subclasses fill their own in
        # __init__ and call no LazySource.__init__.
        unreadable = self.__dict__.setdefault("_unreadable", {})
        if err.name not in unreadable:
            unreadable[err.name] = err.label
            logger.warning("skipping %s: %s", err.label, err)

    def _load_readable(self, index: int, back: int) -> FramePair:
        """Pair ``index``'s current frame with the frame ``back`` frames earlier, or with the readable one
        before it where that is unreadable (``pair.meta["back"]`` says which; ``skipped_before`` the frames
        paired across)."""
        item = self._item(index)
        crossed: list[str] = []
        unreadable = self.__dict__.setdefault("_unreadable", {})
        name = self._cur_name(item)
        if name in unreadable:  # found before (a pair read ahead): not decoded again
            raise PairSkipped(f"{unreadable[name]} is unreadable: the pair of that frame is skipped")
        b = int(back)
        while True:
            it = self._back(item, b) if b != 1 else item
            if it is None or len(crossed) > MAX_SKIPPED_FRAMES:
                # Nothing readable close enough before it: its frame begins the next stretch of the sequence.
                why = (f"the {len(crossed)} frame(s) before it are unreadable ({', '.join(crossed)}), more than "
                       f"the {MAX_SKIPPED_FRAMES} a pair may reach across" if it is not None
                       else "no readable frame before it" + (f" ({', '.join(crossed)} unreadable)" if crossed else ""))
                restarts = self.__dict__.setdefault("_restarts", {})
                if index not in restarts:
                    restarts[index] = name
                    logger.warning("%s: %s; the sequence starts again at this frame (it has no pair of its own)",
                                   name, why)
                raise PairSkipped(f"{name}: {why}")
            if self._prev_name(it) in unreadable:  # known: not decoded again (a video would seek back)
                crossed.insert(0, unreadable[self._prev_name(it)])  # kept in time order
                b += 1
                continue
            try:
                pair = self._load(it)
            except UnreadableFrame as err:
                self._note_unreadable(err)
                if err.current:
                    raise PairSkipped(f"{err.label} is unreadable: the pair of that frame is skipped") from None
                crossed.insert(0, err.label)
                b += 1
                continue
            pair.meta["back"] = b
            if crossed:
                pair.meta["skipped_before"] = list(crossed)
                logger.warning("%s: paired with %s across %d unreadable frame(s) (%s)", pair.name,
                               pair.meta.get("name_prev", "the readable frame before"), len(crossed), ", ".join(crossed))
            return pair

    def _item(self, index: int) -> Any:
        if isinstance(index, slice):
            raise TypeError(f"{type(self).__name__} does not support slicing; use range(len(source))")
        n = len(self._items)
        if not -n <= index < n:
            raise IndexError(f"{type(self).__name__}: pair index {index} out of range ({n} pairs)")
        return self._items[index]

    def _load(self, item: Any) -> FramePair:
        raise NotImplementedError

    # --- sequences (keyframes) ------------------------------------------------------------------
    def _sequence_key(self, item: Any) -> str | None:
        return None

    def _back(self, item: Any, back: int) -> Any | None:
        return item if back == 1 else None

    def _pair_dt(self, item: Any) -> float | None:
        return None

    def _pair_motion(self, item: Any) -> Motion | None:
        return None

    def _prev_name(self, item: Any) -> str:
        return ""

    def _cur_name(self, item: Any) -> str:
        """The name of ``item``'s current frame (its pair's name): the key of unreadable current frames."""
        return ""

    def sequence_key(self, index: int) -> str | None:
        """The clip (drive, video, scene) pair ``index`` belongs to; None for an independent pair. After a
        restart (unreadable frames) the pairs that follow are a new stretch: ``KEY#1``, ``KEY#2``..."""
        key = self._sequence_key(self._item(index))
        n = sum(r < index for r in self.__dict__.get("_restarts", {}))
        return key if key is None or n == 0 else f"{key}#{n}"

    def previous_frames(self, index: int, window: int) -> list[PreviousFrame]:
        """Earlier frames pair ``index``'s current frame can be paired with, 1 to ``window`` frames back
        (nearest first), without reading images."""
        item = self._item(index)
        out: list[PreviousFrame] = []
        unreadable = self.__dict__.get("_unreadable", {})
        run = 0  # consecutive unreadable frames: a pair does not reach across more than MAX_SKIPPED_FRAMES
        for back in range(1, int(window) + 1):
            it = self._back(item, back)
            if it is None:
                break
            if self._prev_name(it) in unreadable:
                run += 1
                if run > MAX_SKIPPED_FRAMES:
                    break
                continue
            run = 0
            dt = self._pair_dt(it)
            out.append(PreviousFrame(back=back, dt=float(dt) if dt is not None else math.nan,
                                     motion=self._pair_motion(it), name=self._prev_name(it)))
        return out

    def pair_back(self, index: int, back: int) -> FramePair:
        """Pair ``index``'s current frame with the frame ``back`` frames earlier (``back = 1``: pair ``index``).

        Raises:
            InputError: there is no such earlier frame.
        """
        if self._back(self._item(index), int(back)) is None:
            raise InputError(f"{type(self).__name__}: pair {index} has no frame {back} frames back")
        return self._load_readable(index, int(back))


def limit_frames(items: list[Any], frames: int | None, what: str) -> list[Any]:
    """The first ``frames`` items (all when ``frames`` is None); ``InputError`` when none remain."""
    if frames is not None:
        if int(frames) < 1:
            raise InputError(f"data.frames: must be a positive number of frame pairs or null, got {frames}")
        items = items[: int(frames)]
    if not items:
        raise InputError(f"{what}: no frame pairs found")
    return items
