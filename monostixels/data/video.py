"""A video file of a user's own camera (a dashcam clip): consecutive frame pairs.

Frames used: ``start, start + step, start + 2 step, ...`` before ``end`` (video frame indices,
0-based); a pair is (used frame ``k``, used frame ``k - 1``), i.e. current = the later frame,
previous = ``step`` video frames earlier. Frames are decoded with OpenCV on access (sequential
access, as ``monostixels run`` and ``eval`` do, decodes every frame once).

Intrinsics, pixels of the video as stored (before ``resize``):

- a file (``intrinsics``), in the formats of :func:`monostixels.data._io.read_intrinsics_file`;
- else a horizontal field of view ``hfov_deg``: ``fx = fy = (W / 2) / tan(hfov / 2)``, principal
  point at the image centre ``((W - 1) / 2, (H - 1) / 2)``. **Approximate**: real lenses have
  their principal point off-centre, non-square pixels and distortion (dashcams: strong barrel
  distortion, not modelled). A wrong focal length scales depths and bends the road plane; use a
  calibration file where you can.
- neither: an error.

``resize`` scales the frames (and the intrinsics with them): a number (factor) or ``[W, H]``
(pixels). Frame interval ``meta["dt"] = step / fps`` (seconds; fps from the file).
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
from monostixels.data._io import LazySource, limit_frames, make_camera, read_intrinsics_file, require_file
from monostixels.data.base import FramePair, GroundTruth
from monostixels.geometry import KITTI_CAMERA_HEIGHT_M, Camera

__all__ = ["VideoSource", "intrinsics_from_hfov"]

logger = logging.getLogger(__name__)

#: Largest value of an 8-bit channel, to scale frames to [0, 1].
_MAX_U8 = 255.0


def intrinsics_from_hfov(width: int, height: int, hfov_deg: float) -> tuple[float, float, float, float]:
    """Approximate pinhole intrinsics ``(fx, fy, cx, cy)`` (pixels) from a horizontal field of view.

    Convention: pixel centres at integer coordinates, so the image centre is ``((W-1)/2, (H-1)/2)``;
    square pixels (``fy = fx``); no distortion.

    Raises:
        InputError: ``hfov_deg`` not in (0, 180).
    """
    if not (0.0 < float(hfov_deg) < 180.0) or not math.isfinite(float(hfov_deg)):
        raise InputError(f"data.hfov_deg: horizontal field of view must be in (0, 180) degrees, got {hfov_deg}")
    fx = (width / 2.0) / math.tan(math.radians(float(hfov_deg)) / 2.0)
    return fx, fx, (width - 1) / 2.0, (height - 1) / 2.0


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
        resize: None, a factor (e.g. 0.5), or ``(W, H)`` pixels.
        frames: at most this many pairs (None = all).
        camera_height: camera height above the road (metres).
        pitch: camera pitch (radians, positive = looking down).

    Raises:
        InputError: missing file, a file OpenCV cannot decode, fewer than two frames in the chosen
            range, neither intrinsics nor ``hfov_deg``, a bad ``step`` / ``start`` / ``end`` / ``resize``.
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
        self.size = self._out_size(resize, W0, H0)
        sx, sy = self.size[1] / W0, self.size[0] / H0
        if intrinsics is not None:
            self.intrinsics_source = str(intrinsics)
            fx, fy, cx, cy = read_intrinsics_file(intrinsics)
        elif hfov_deg is not None:
            self.intrinsics_source = f"hfov {float(hfov_deg):g} deg (approximate)"
            fx, fy, cx, cy = intrinsics_from_hfov(W0, H0, float(hfov_deg))
            logger.warning("video: intrinsics from a horizontal field of view of %g deg: approximate (principal "
                           "point at the centre, no distortion); depths scale with the focal length", float(hfov_deg))
        else:
            raise InputError("video: no intrinsics: set data.intrinsics=FILE (fx fy cx cy) or data.hfov_deg=DEGREES "
                             "(horizontal field of view, approximate)")
        # Pixel centres at integers: u' + 0.5 = s (u + 0.5).
        self.camera: Camera = make_camera(fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5,
                                          camera_height, pitch)
        items = [_Pair(used[k], used[k - 1]) for k in range(1, len(used))]
        self._items = limit_frames(items, frames, f"video {self.path}")
        self._cap: Any = None
        self._pos = 0  # index of the next frame the capture returns
        self._cache: dict[int, torch.Tensor] = {}
        self._keep = self.step  # decoded frames kept behind the newest (video frames)
        logger.info("video: %d frame pairs from %s (%dx%d -> %dx%d, %s fps, intrinsics %s)", len(self._items),
                    self.path, W0, H0, self.size[1], self.size[0], f"{self.fps:g}" if self.fps else "unknown",
                    self.intrinsics_source)

    @staticmethod
    def _out_size(resize: Any, W: int, H: int) -> tuple[int, int]:
        """(H, W) after ``resize``."""
        if resize is None:
            return H, W
        if isinstance(resize, (int, float)) and not isinstance(resize, bool):
            f = float(resize)
            if not (f > 0 and math.isfinite(f)):
                raise InputError(f"data.resize: factor must be positive, got {resize}")
            return max(1, round(H * f)), max(1, round(W * f))
        try:
            w, h = (int(x) for x in resize)
        except (TypeError, ValueError) as e:
            raise InputError(f"data.resize: expected a factor or [W, H] pixels, got {resize!r}") from e
        if w < 1 or h < 1:
            raise InputError(f"data.resize: [W, H] must be positive, got {resize!r}")
        return h, w

    def _frame(self, index: int) -> torch.Tensor:
        """Video frame ``index`` as (3, H, W) float32 RGB in [0, 1] (resized)."""
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
            if not self._cap.grab():
                raise InputError(f"video: {self.path} ends before frame {index} (decoded {self._pos} frames)")
            self._pos += 1
        ok, img = self._cap.read()
        if not ok or img is None:
            raise InputError(f"video: cannot decode frame {index} of {self.path}")
        self._pos += 1
        if img.shape[:2] != self.size_in:
            raise InputError(f"video: frame {index} of {self.path} is {img.shape[1]}x{img.shape[0]}, the first frame "
                             f"{self.size_in[1]}x{self.size_in[0]}")
        if img.shape[:2] != self.size:
            img = cv2.resize(img, (self.size[1], self.size[0]), interpolation=cv2.INTER_AREA)
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
        return f"{self.path.stem}_{item.frame_prev:06d}"

    def _load(self, item: _Pair) -> FramePair:
        # The oldest frame first: the capture decodes forward, and keyframes reach back several frames.
        self._keep = max(self._keep, item.frame - item.frame_prev)
        image_prev = self._frame(item.frame_prev)
        image = self._frame(item.frame)
        dt = self._pair_dt(item)
        meta: dict[str, Any] = {"source": "video", "path": str(self.path), "frame": item.frame,
                                "frame_prev": item.frame_prev, "sequence": self._sequence_key(item),
                                "name_prev": self._prev_name(item),
                                "intrinsics": self.intrinsics_source}
        if dt is not None:
            meta["dt"] = dt
        return FramePair(image=image, image_prev=image_prev, camera=self.camera, motion=None, gt=GroundTruth(),
                         name=f"{self.path.stem}_{item.frame:06d}", meta=meta)

    def __del__(self) -> None:
        if getattr(self, "_cap", None) is not None:
            self._cap.release()
