"""A video file of a user's own camera (a dashcam clip): consecutive frame pairs (a camera, a URL or a
file read as its frames come: :mod:`monostixels.data.live_video`).

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

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np
import torch

from monostixels._checks import InputError
from monostixels.data._lazy_source import LazySource, UnreadableFrame, limit_frames
from monostixels.data._lens import AUTO_PIXELS, intrinsics_from_hfov, lens_camera, working_size
from monostixels.data._readers import MAX_U8, require_file
from monostixels.data.base import FramePair, GroundTruth
from monostixels.core.geometry import KITTI_CAMERA_HEIGHT_M
from monostixels.data.static_regions import AUTO_MASK, AUTO_SPACING_S, spread_samples, with_static_region

__all__ = ["VideoSource", "intrinsics_from_hfov", "AUTO_PIXELS"]


logger = logging.getLogger(__name__)


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
        t = torch.from_numpy(rgb).float() / MAX_U8
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
