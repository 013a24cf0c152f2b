"""Frames as they come: a camera, a URL, or a video file read at its frame rate (``data=video`` with
``data.realtime``, a camera index or a URL as ``data.path``). A video file read on access:
:mod:`monostixels.data.video`.
"""
from __future__ import annotations

import array
import logging
import math
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Sequence

import cv2
import numpy as np
import torch

from monostixels._checks import InputError
from monostixels.data._lens import lens_camera, working_size
from monostixels.data._readers import MAX_U8, require_file
from monostixels.data.base import FramePair, GroundTruth, PreviousFrame, SourceAttributes
from monostixels.core.geometry import KITTI_CAMERA_HEIGHT_M
from monostixels.data.static_regions import AUTO_MASK

__all__ = ["LiveVideoSource", "is_live_path"]


logger = logging.getLogger(__name__)


def is_live_path(path: Any) -> bool:
    """Whether ``data.path`` names a live source: a camera index (an integer, or digits) or a URL
    (``scheme://...``, e.g. ``rtsp://``, ``http://``)."""
    if isinstance(path, bool):
        return False
    if isinstance(path, int):
        return True
    s = str(path)
    return s.isdigit() or "://" in s


@dataclass
class _Taken:
    """A frame the consumer took: its capture index (frames read from the start), capture time (s) and
    the frames dropped since the frame taken before it."""

    index: int
    time: float
    dropped: int
    image: torch.Tensor   # (3, H, W) uint8 RGB


class LiveVideoSource(SourceAttributes):
    """Frame pairs of a camera, a URL or a video file, read as the frames come (``data=video``).

    A reader thread decodes frames as they arrive: a camera or a URL at its own pace, a video file at
    its frame rate in wall time (as a camera would deliver it: frame ``k`` arrives ``k / fps`` seconds
    after the start). The consumer (:class:`~monostixels.sequence.SequenceRunner`) takes frames with
    :meth:`indices`; a frame is the current frame of pair ``i`` and the previous frame of pair
    ``i + 1`` (keyframe pairs reach further back among the taken frames).

    - ``realtime=True``: the reader keeps only the newest frame. A frame that arrives while the
      consumer is busy replaces the one waiting, which is dropped (not queued): each pair is made of
      the newest frame when the consumer asks and the frames it took before. The pairs' ``meta`` say
      which frames were taken (``frame``, ``frame_prev``: capture indices; ``capture_time_s``;
      ``dropped_before``: frames dropped since the previous taken frame), and :meth:`summary` lists them.
    - ``realtime=False``: every ``step``-th frame is taken, none dropped (a bounded queue holds the
      reader back; a camera's driver then drops on its own).

    Times: ``capture_time_s`` is the frame's position in a file (``k / fps``) or, for a camera or URL,
    the wall time since the first frame; ``meta["dt"]`` the difference of the two frames'.

    Args:
        path: a camera index (int or digits), a URL, or a video file.
        realtime: drop the frames that arrive while one is being solved (see above).
        intrinsics, hfov_deg, resize, camera_height, pitch, mask: as for :class:`VideoSource` (a mask then
            has the stream's frame size).
        step: frames read per frame offered (1 = every frame).
        start: frames skipped at the start; end: stop before this capture index (None = the end).
        frames: at most this many pairs (None = until the stream ends).
        window: taken frames kept for keyframe pairs (the sequence layer's ``keyframes.window``).

    Raises:
        InputError: a camera or URL that cannot be opened, a file that cannot be decoded, a stream that
            ends before two frames, no intrinsics, a bad ``step`` / ``start`` / ``end`` / ``resize``, a
            malformed distortion entry, a mask of another size.
    """

    #: Frames the reader may queue ahead of the consumer without ``realtime``.
    _QUEUE = 4
    #: Seconds the consumer waits for a frame of a live source before it counts the stream as ended.
    timeout_s = 10.0

    def __init__(self, path: Any, *, realtime: bool = False, intrinsics: str | Path | None = None,
                 hfov_deg: float | None = None, step: int = 1, start: int = 0, end: int | None = None,
                 resize: float | Sequence[int] | None = None, frames: int | None = None,
                 camera_height: float = KITTI_CAMERA_HEIGHT_M, pitch: float = 0.0, window: int = 10,
                 mask: str | Path | None = None) -> None:
        if path is None or str(path) == "":
            raise InputError("video data.path: no camera, URL or video file given (data.path=0, data.path=rtsp://..., "
                             "data.path=clip.mp4)")
        if int(step) < 1:
            raise InputError(f"data.step: must be a positive number of frames, got {step}")
        if int(start) < 0 or (end is not None and int(end) <= int(start)):
            raise InputError(f"data.start / data.end: need 0 <= start < end, got start={start}, end={end}")
        if frames is not None and int(frames) < 1:
            raise InputError(f"data.frames: must be a positive number of frame pairs or null, got {frames}")
        self.realtime = bool(realtime)
        self.step, self.start, self.end = int(step), int(start), None if end is None else int(end)
        self.max_pairs = None if frames is None else int(frames)
        self.window = max(1, int(window))
        self.camera_index: int | None = None
        if isinstance(path, int) or str(path).isdigit():
            self.camera_index = int(path)
            self.path = f"camera {self.camera_index}"
            self.kind = "camera"
            cap = cv2.VideoCapture(self.camera_index)
        elif "://" in str(path):
            self.path, self.kind = str(path), "url"
            cap = cv2.VideoCapture(self.path)
        else:
            self.path, self.kind = str(require_file(path, "video data.path")), "file"
            cap = cv2.VideoCapture(self.path)
        what = {"camera": f"data.path: camera {self.camera_index} cannot be opened (no such device, or it is busy)",
                "url": f"data.path: cannot open the stream {self.path}",
                "file": f"video data.path: cannot decode {self.path} (not a video OpenCV can read, or corrupt)"}[self.kind]
        ok, first = cap.read() if cap.isOpened() else (False, None)
        if not ok or first is None:
            cap.release()
            raise InputError(what)
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self.fps = fps if fps > 0 and math.isfinite(fps) else None
        if self.kind == "file" and self.realtime and self.fps is None:
            cap.release()
            raise InputError(f"data.realtime: {self.path} stores no frame rate, so its frames cannot arrive in time")
        H0, W0 = first.shape[:2]
        self.size_in = (H0, W0)
        try:
            self.size = working_size(resize, W0, H0)
            if mask == AUTO_MASK:
                # Frames as they come: none to look ahead at before the first pair.
                logger.info("video: data.mask=auto looks for a bonnet in a file's first frames; a live source "
                            "takes data.mask=FILE")
                mask = None
            self.camera, self.intrinsics_source, self._warp = lens_camera(intrinsics, hfov_deg, (H0, W0), self.size,
                                                                          camera_height, pitch, mask)
        except InputError:
            cap.release()
            raise
        self._key = f"stream/{self.path}"
        self._taken: list[_Taken] = []        # the last `window + 1` taken frames, oldest first
        self._count = 0                       # frames taken so far
        # Which frames were processed, as three compact columns (capture index, time, dropped before it):
        # a camera may run for days, and a dict per frame (~250 bytes) would grow the process by 200 MB
        # a day at 10 Hz; these take 20 bytes a frame. summary() turns them into the listed entries.
        self._processed = (array.array("q"), array.array("d"), array.array("q"))
        self._first: dict[str, Any] | None = None
        self.frames_read = 0
        self.frames_dropped = 0
        self._slot: _Taken | None = None      # realtime: the newest frame waiting
        self._since_taken = 0                 # realtime: frames offered since the last take
        self._queue: "queue.Queue[_Taken | None]" = queue.Queue(maxsize=self._QUEUE)
        self._cond = threading.Condition()
        self._ended = False
        self._error: str | None = None
        self._stop = threading.Event()
        # The reader starts when the consumer asks for the first frame: a file's clock (frame k arrives
        # k / fps after the first) starts then, not while the pipeline is being built.
        self._thread = threading.Thread(target=self._read, args=(cap, first), name="monostixels-video-reader", daemon=True)
        logger.info("video: %s %s (%dx%d -> %dx%d, %s fps, intrinsics %s)%s", self.kind, self.path, W0, H0,
                    self.size[1], self.size[0], f"{self.fps:g}" if self.fps else "unknown", self.intrinsics_source,
                    "; realtime: frames that arrive while one is solved are dropped" if self.realtime else "")

    # ------------------------------------------------------------------ the reader thread
    def _convert(self, img: np.ndarray) -> torch.Tensor:
        if img.shape[:2] != self.size_in:
            raise InputError(f"video: a frame of {self.path} is {img.shape[1]}x{img.shape[0]}, the first "
                             f"{self.size_in[1]}x{self.size_in[0]}")
        img = self._warp.image(img)
        return torch.from_numpy(np.ascontiguousarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB).transpose(2, 0, 1)))

    def _read(self, cap: Any, first: np.ndarray) -> None:
        t0 = time.perf_counter()
        index, img = 0, first
        try:
            while not self._stop.is_set():
                if img is None:
                    ok, img = cap.read()
                    if not ok or img is None:
                        break
                if self.end is not None and index >= self.end:
                    break
                if index >= self.start and (index - self.start) % self.step == 0:
                    if self.kind == "file":
                        # A file delivers its frames at the recorded rate when it stands in for a camera.
                        when = index / self.fps if self.fps else 0.0
                        if self.realtime:
                            delay = t0 + when - time.perf_counter()
                            if delay > 0:
                                self._stop.wait(delay)
                    else:
                        when = time.perf_counter() - t0
                    self._offer(_Taken(index, when, 0, self._convert(img)))
                self.frames_read += 1
                index += 1
                img = None
        except InputError as err:
            self._error = str(err)
        finally:
            cap.release()
            with self._cond:
                self._ended = True
                self._cond.notify_all()
            if not self.realtime:
                self._queue.put(None)

    def _offer(self, frame: _Taken) -> None:
        if self.realtime:
            with self._cond:
                if self._slot is not None:
                    self.frames_dropped += 1  # replaced before anyone took it
                self._since_taken += 1
                frame.dropped = self._since_taken - 1
                self._slot = frame
                self._cond.notify_all()
            return
        while not self._stop.is_set():
            try:
                self._queue.put(frame, timeout=0.1)
                return
            except queue.Full:
                continue

    def _next(self) -> _Taken | None:
        """The next frame to take (blocking), None when the stream has ended."""
        if self.realtime:
            with self._cond:
                while self._slot is None and not self._ended:
                    if not self._cond.wait(self.timeout_s):
                        logger.warning("video: no frame from %s for %.0f s; stopping", self.path, self.timeout_s)
                        return None
                frame, self._slot = self._slot, None
                self._since_taken = 0
                return frame
        try:
            return self._queue.get(timeout=self.timeout_s if self.kind != "file" else None)
        except queue.Empty:
            logger.warning("video: no frame from %s for %.0f s; stopping", self.path, self.timeout_s)
            return None

    # ------------------------------------------------------------------ what the sequence layer reads
    def indices(self) -> Iterator[int]:
        """Pair indices as frames are taken (blocking until each arrives): pair ``i`` ends on the
        ``i + 2``-th taken frame. In realtime mode a frame is taken when the consumer asks for it."""
        if not self._thread.is_alive() and self._count == 0 and not self._ended:
            self._thread.start()
        try:
            while self.max_pairs is None or self._count - 1 < self.max_pairs:
                frame = self._next()
                if frame is None:
                    break
                self._taken = (self._taken + [frame])[-(self.window + 1):]
                self._count += 1
                if self._count == 1:
                    self._first = {"frame": frame.index, "capture_time_s": frame.time}
                    continue
                for column, value in zip(self._processed, (frame.index, frame.time, frame.dropped)):
                    column.append(value)
                yield self._count - 2
        finally:
            self.close()
        if self._error is not None:
            raise InputError(self._error)
        if self._count < 2:
            raise InputError(f"video data.path: {self.path} ended after {self._count} frame(s); a pair needs two")

    def close(self) -> None:
        """Stop the reader thread."""
        self._stop.set()

    def _frame(self, i: int) -> _Taken:
        """The taken frame of taken index ``i`` (0-based) from the kept ones."""
        first = self._count - len(self._taken)
        if not first <= i < self._count:
            raise InputError(f"video: frame {i} of the stream is no longer kept (frames {first}..{self._count - 1}; "
                             f"keyframes.window {self.window})")
        return self._taken[i - first]

    def sequence_key(self, index: int) -> str:
        return self._key

    def previous_frames(self, index: int, window: int) -> list[PreviousFrame]:
        cur = self._frame(index + 1)
        out = []
        for back in range(1, int(window) + 1):
            k = index + 1 - back
            if k < self._count - len(self._taken) or k < 0:
                break
            prev = self._frame(k)
            out.append(PreviousFrame(back=back, dt=cur.time - prev.time, motion=None, name=self._name(prev)))
        return out

    def _name(self, frame: _Taken) -> str:
        stem = Path(self.path).stem if self.kind == "file" else ("camera" if self.kind == "camera" else "stream")
        return f"{stem}_{frame.index:06d}"

    def pair_back(self, index: int, back: int) -> FramePair:
        cur, prev = self._frame(index + 1), self._frame(index + 1 - int(back))
        meta: dict[str, Any] = {"source": "video", "path": self.path, "frame": cur.index, "frame_prev": prev.index,
                                "sequence": self._key, "name_prev": self._name(prev), "intrinsics": self.intrinsics_source,
                                "capture_time_s": cur.time, "capture_time_prev_s": prev.time,
                                "dropped_before": cur.dropped, "realtime": self.realtime, "back": int(back)}
        if cur.time > prev.time:
            meta["dt"] = cur.time - prev.time
        ignore = self._warp.ignore_mask()
        if ignore is not None:
            meta["ignore_mask"] = ignore
        return FramePair(image=cur.image.float() / MAX_U8, image_prev=prev.image.float() / MAX_U8, camera=self.camera,
                         motion=None, gt=GroundTruth(), name=self._name(cur), meta=meta)

    def __getitem__(self, index: int) -> FramePair:
        return self.pair_back(index, 1)

    def summary(self) -> dict[str, Any]:
        """Which frames were processed: per taken frame after the first, its capture index and time and
        the frames dropped before it; totals of frames read, taken and dropped."""
        return {"source": self.path, "kind": self.kind, "realtime": self.realtime, "fps": self.fps,
                "frames_read": self.frames_read, "frames_taken": self._count,
                "frames_dropped": self.frames_dropped if self.realtime else 0,
                "first_frame": self._first,
                "processed": [{"frame": int(k), "capture_time_s": float(t), "dropped_before": int(d)}
                              for k, t, d in zip(*self._processed)]}

    def __del__(self) -> None:
        if getattr(self, "_stop", None) is not None:
            self._stop.set()
