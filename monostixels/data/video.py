"""A video file of a user's own camera (a dashcam clip): consecutive frame pairs.

Frames used: ``start, start + step, start + 2 step, ...`` before ``end`` (video frame indices,
0-based); a pair is (used frame ``k``, used frame ``k - 1``), i.e. current = the later frame,
previous = ``step`` video frames earlier. Frames are decoded with OpenCV on access (sequential
access, as ``monostixels run`` and ``eval`` do, decodes every frame once).

Intrinsics, pixels of the video as stored (before ``resize``):

- a file (``intrinsics``), in the formats of :func:`monostixels.data._camera_files.read_intrinsics_file`
  (``monostixels calibrate`` writes one from chessboard views). With a ``distortion`` key every
  frame is undistorted, keeping the file's camera matrix (:mod:`monostixels.data._lens`);
- else a horizontal field of view ``hfov_deg``: ``fx = fy = (W / 2) / tan(hfov / 2)``, principal
  point at the image centre ``((W - 1) / 2, (H - 1) / 2)``. **Approximate**: real lenses have
  their principal point off-centre, non-square pixels and distortion (dashcams: strong barrel
  distortion, not modelled on this path). A wrong focal length scales depths and bends the road
  plane; use a calibration file where you can.
- neither: an error.

``resize`` scales the (undistorted) frames and the intrinsics with them: ``"auto"`` (about
:data:`AUTO_PIXELS`, never upscaled), a number (factor) or ``[W, H]`` (pixels). ``mask``: an image
of the stored size, non-zero = ignore, undistorted and resized with the frames (nearest neighbour);
each pair then carries it as ``meta["ignore_mask"]`` ((H, W) torch bool at the working size, True =
ignore; also True where undistortion leaves a pixel without a source). Frame interval
``meta["dt"] = step / fps`` (seconds; fps from the file).
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
from monostixels.data._lazy_source import LazySource, UnreadableFrame, limit_frames
from monostixels.data._lens import AUTO_PIXELS, intrinsics_from_hfov, lens_camera, working_size
from monostixels.data._readers import require_file
from monostixels.data.base import FramePair, GroundTruth, PreviousFrame
from monostixels.core.geometry import KITTI_CAMERA_HEIGHT_M
from monostixels.data.static_regions import AUTO_MASK, AUTO_SPACING_S, spread_samples, with_static_region

__all__ = ["VideoSource", "LiveVideoSource", "intrinsics_from_hfov", "is_live_path", "AUTO_PIXELS"]

logger = logging.getLogger(__name__)

#: Largest value of an 8-bit channel, to scale frames to [0, 1].
_MAX_U8 = 255.0
#: Frames further ahead than this are sought (CAP_PROP_POS_FRAMES), nearer ones grabbed one by one.
_SEEK_FRAMES = 60


@dataclass
class _Pair:
    frame: int
    frame_prev: int


class VideoSource(LazySource):
    """Frame pairs of a video file, with intrinsics from a file or a horizontal field of view.

    Args:
        path: the video file (any container/codec OpenCV's FFmpeg backend reads: mp4, avi, mkv...).
        intrinsics: intrinsics file (pixels of the stored video); None = use ``hfov_deg``.
        hfov_deg: horizontal field of view (degrees), used when ``intrinsics`` is None (approximate).
        step: video frames between the two frames of a pair (and between used frames).
        start: first video frame used (0-based).
        end: video frames from ``end`` on are not used (None = to the end).
        resize: None, ``"auto"`` (about :data:`AUTO_PIXELS`, never upscaled), a factor (e.g. 0.5), or
            ``(W, H)`` pixels.
        frames: at most this many pairs (None = all).
        camera_height: camera height above the road (metres).
        pitch: camera pitch (radians, positive = looking down).
        mask: an image of the stored frame size, non-zero = ignore (see the module docstring), ``auto``
            (a static region at the bottom found from frames spread over the used range: a bonnet,
            :mod:`monostixels.data.static_regions`), or None.

    Raises:
        InputError: missing file, a file OpenCV cannot decode, fewer than two frames in the chosen
            range, neither intrinsics nor ``hfov_deg``, a bad ``step`` / ``start`` / ``end`` / ``resize``,
            a malformed distortion entry, a mask of another size.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        intrinsics: str | Path | None = None,
        hfov_deg: float | None = None,
        step: int = 1,
        start: int = 0,
        end: int | None = None,
        resize: float | Sequence[int] | None = None,
        frames: int | None = None,
        camera_height: float = KITTI_CAMERA_HEIGHT_M,
        pitch: float = 0.0,
        mask: str | Path | None = None,
    ) -> None:
        if path is None or str(path) == "":
            raise InputError("video data.path: no video file given (data.path=clip.mp4)")
        self.path = require_file(path, "video data.path")
        if int(step) < 1:
            raise InputError(f"data.step: must be a positive number of video frames, got {step}")
        if int(start) < 0 or (end is not None and int(end) <= int(start)):
            raise InputError(f"data.start / data.end: need 0 <= start < end, got start={start}, end={end}")
        self.step, self.start = int(step), int(start)
        cap = cv2.VideoCapture(str(self.path))
        try:
            ok, first = cap.read() if cap.isOpened() else (False, None)
            if not ok or first is None:
                raise InputError(f"video data.path: cannot decode {self.path} (not a video OpenCV can read, or corrupt)")
            H0, W0 = first.shape[:2]
            fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
            count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
            if count <= 0:  # some containers do not store it: count by decoding
                count = 1
                while cap.grab():
                    count += 1
        finally:
            cap.release()
        self.fps = fps if fps > 0 and math.isfinite(fps) else None
        self.num_video_frames = count
        last = count if end is None else min(int(end), count)
        used = list(range(self.start, last, self.step))
        if len(used) < 2:
            raise InputError(
                f"video data.path: {self.path} gives {len(used)} frame(s) with start={start}, end={end}, step={step} "
                f"({count} frames in the file); a pair needs at least two"
            )
        self.size_in = (H0, W0)
        self.size = working_size(resize, W0, H0)
        auto = mask == AUTO_MASK
        self.camera, self.intrinsics_source, self._warp = lens_camera(intrinsics, hfov_deg, (H0, W0), self.size,
                                                                      camera_height, pitch, None if auto else mask)
        if auto:
            self._warp.ignore = with_static_region(self._warp.ignore, self._sample_frames(used), f"video {self.path}")
        items = [_Pair(used[k], used[k - 1]) for k in range(1, len(used))]
        self._items = limit_frames(items, frames, f"video {self.path}")
        self._cap: Any = None
        self._pos = 0  # index of the next frame the capture returns
        self._cache: dict[int, torch.Tensor] = {}
        self._keep = self.step  # decoded frames kept behind the newest (video frames)
        logger.info("video: %d frame pairs from %s (%dx%d -> %dx%d, %s fps, intrinsics %s)", len(self._items),
                    self.path, W0, H0, self.size[1], self.size[0], f"{self.fps:g}" if self.fps else "unknown",
                    self.intrinsics_source)

    def _sample_frames(self, used: list[int]) -> list[list[np.ndarray]]:
        """Runs of used frames, spread over the whole used range
        (:func:`~monostixels.data.static_regions.spread_samples`; BGR, undistorted and resized), for the static
        region search; undecodable ones are left out."""
        min_gap = max(1, round(AUTO_SPACING_S * self.fps / self.step)) if self.fps else 1
        runs: list[list[np.ndarray]] = []
        cap = cv2.VideoCapture(str(self.path))
        try:
            pos = 0  # index of the frame the capture returns next
            for run in spread_samples(len(used), min_gap):
                runs.append([])
                for k in (used[i] for i in run):
                    while pos < k and k - pos <= _SEEK_FRAMES and cap.grab():
                        pos += 1  # near frames are grabbed: cheaper than a seek, which decodes from a key frame
                    if pos != k:
                        cap.set(cv2.CAP_PROP_POS_FRAMES, k)
                    ok, img = cap.read()
                    pos = k + 1
                    if ok and img is not None and img.shape[:2] == self.size_in:
                        runs[-1].append(self._warp.image(img))
        finally:
            cap.release()
        return runs

    def _frame(self, index: int) -> torch.Tensor:
        """Video frame ``index`` as (3, H, W) float32 RGB in [0, 1] (undistorted, resized)."""
        if index in self._cache:
            return self._cache[index]
        if self._cap is None or index < self._pos:
            if self._cap is not None:
                self._cap.release()
            self._cap = cv2.VideoCapture(str(self.path))
            self._pos = 0
            if index > 0:
                self._cap.set(cv2.CAP_PROP_POS_FRAMES, index)
                self._pos = int(self._cap.get(cv2.CAP_PROP_POS_FRAMES))
                if self._pos > index:  # an inexact seek: start over and decode forward
                    self._cap.release()
                    self._cap = cv2.VideoCapture(str(self.path))
                    self._pos = 0
        while self._pos < index:
            # A frame that fails to decode fails its grab too, but the capture moves past it: only the end counts.
            if not self._cap.grab() and self._pos >= self.num_video_frames:
                raise InputError(f"video: {self.path} ends before frame {index} (decoded {self._pos} frames)")
            self._pos += 1
        ok, img = self._cap.read()
        self._pos += 1  # a frame that fails to decode is consumed all the same: the next read is the next frame
        if not ok or img is None:
            raise UnreadableFrame(f"video: cannot decode frame {index} of {self.path}", name=self._name(index),
                                  label=f"video frame {index}", current=index == getattr(self, "_reading", index))
        if img.shape[:2] != self.size_in:
            raise InputError(f"video: frame {index} of {self.path} is {img.shape[1]}x{img.shape[0]}, the first frame "
                             f"{self.size_in[1]}x{self.size_in[0]}")
        img = self._warp.image(img)
        rgb = np.ascontiguousarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB).transpose(2, 0, 1))
        t = torch.from_numpy(rgb).float() / _MAX_U8
        self._cache = {k: v for k, v in self._cache.items() if k >= index - self._keep} | {index: t}
        return t

    # --- sequences (keyframes) ------------------------------------------------------------------
    def _sequence_key(self, item: _Pair) -> str:
        return f"video/{self.path}"

    def _back(self, item: _Pair, back: int) -> _Pair | None:
        prev = item.frame - int(back) * self.step
        return _Pair(item.frame, prev) if prev >= self.start else None

    def _pair_dt(self, item: _Pair) -> float | None:
        return (item.frame - item.frame_prev) / self.fps if self.fps else None

    def _prev_name(self, item: _Pair) -> str:
        return self._name(item.frame_prev)

    def _cur_name(self, item: _Pair) -> str:
        return self._name(item.frame)

    def _name(self, frame: int) -> str:
        return f"{self.path.stem}_{frame:06d}"

    def _load(self, item: _Pair) -> FramePair:
        # The oldest frame first: the capture decodes forward, and keyframes reach back several frames.
        self._keep = max(self._keep, item.frame - item.frame_prev)
        self._reading = item.frame  # which of the two an unreadable frame is (UnreadableFrame.current)
        image_prev = self._frame(item.frame_prev)
        image = self._frame(item.frame)
        dt = self._pair_dt(item)
        meta: dict[str, Any] = {"source": "video", "path": str(self.path), "frame": item.frame,
                                "frame_prev": item.frame_prev, "sequence": self._sequence_key(item),
                                "name_prev": self._prev_name(item),
                                "intrinsics": self.intrinsics_source}
        if dt is not None:
            meta["dt"] = dt
        ignore = self._warp.ignore_mask()
        if ignore is not None:
            meta["ignore_mask"] = ignore
        return FramePair(image=image, image_prev=image_prev, camera=self.camera, motion=None, gt=GroundTruth(),
                         name=self._name(item.frame), meta=meta)

    def __del__(self) -> None:
        if getattr(self, "_cap", None) is not None:
            self._cap.release()


# ------------------------------------------------------------------------------------------------
# Frames as they come: a camera, a URL, or a video file read at its frame rate.


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


class LiveVideoSource:
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
        return FramePair(image=cur.image.float() / _MAX_U8, image_prev=prev.image.float() / _MAX_U8, camera=self.camera,
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
