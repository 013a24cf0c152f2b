"""A folder of images from a user's own camera, with an intrinsics file or a field of view.

Layout::

    root/000.png, root/001.png, ...   images, sorted by file name = temporal order
    root/intrinsics.yaml              default intrinsics file (or data.intrinsics = any path)

Pairs: current = image ``i``, previous = image ``i - step`` in name order. Frame interval
``meta["dt"] = step / fps`` seconds (``fps``: the folder's frame rate, ``data.fps``, default
:data:`~monostixels.data.base.FOLDER_FPS`): velocities and TTC use it.

Intrinsics, pixels of the images as stored (before ``resize``), :func:`monostixels.data._lens.lens_camera`:

- a file, in the formats of :func:`monostixels.data._camera_files.read_intrinsics_file`:
  YAML / JSON ``fx: 718.9`` ``fy: 718.9`` ``cx: 607.2`` ``cy: 185.2`` (``fy`` optional = ``fx``),
  or ``K: [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``; text ``fx fy cx cy`` (4 numbers) or the 9 numbers
  of K (row-major), or ``key: value`` lines. A ``distortion: [k1, k2, p1, p2, k3]`` key (OpenCV's
  order; what ``monostixels calibrate`` writes) undistorts every image, keeping the file's camera
  matrix (:mod:`monostixels.data._lens`). With ``data.intrinsics`` unset,
  ``root/intrinsics.{yaml,yml,json,txt}`` is used (the first that exists);
- else a horizontal field of view ``hfov_deg`` (as for ``data=video``): ``fx = fy = (W / 2) /
  tan(hfov / 2)``, principal point at the image centre. **Approximate** (no distortion);
- a file and ``hfov_deg`` both: the file wins, and a warning says ``hfov_deg`` is not used;
- neither: an error naming both.

``resize`` scales the (undistorted) images and the intrinsics with them, as for ``data=video``:
``"auto"`` (about :data:`~monostixels.data._lens.AUTO_PIXELS`, never upscaled), None, a factor or
``[W, H]`` pixels. The first readable image's size sets up the tables; every image must have it.

Optional mask (``data.mask``): an image of the stored size, non-zero = ignore, undistorted and resized
with the images (nearest neighbour); each pair then carries it as ``meta["ignore_mask"]`` ((H, W) torch
bool at the working size, True = ignore; also True where undistortion leaves a pixel without a source).

Camera height from ``data.camera_height`` (metres), else the camera config.

Optional poses (``data.poses``): camera-to-world ``T_w_cam`` per image in the formats of
:func:`monostixels.data._camera_files.read_poses_file`: 13 values per line (image id = the file stem as a
number, then 3x4), or 12 / 16 values per line (3x4 / 4x4) for the images in name order (one
line per image). Then ``motion`` is the ground-truth camera motion ``X_prev = R X_cur + t``;
without poses ``motion`` is None. No ground truth otherwise.
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

from monostixels._checks import InputError, check_same_size
from monostixels.data._camera_files import read_poses_file, relative_motion
from monostixels.data._lazy_source import LazySource, UnreadableFrame, limit_frames
from monostixels.data._readers import list_images, read_rgb, require_dir
from monostixels.data._lens import lens_camera, working_size
from monostixels.data.static_regions import AUTO_MASK, AUTO_SPACING_S, spread_samples, with_static_region
from monostixels.data.base import FOLDER_FPS, FramePair, GroundTruth
from monostixels.core.geometry import KITTI_CAMERA_HEIGHT_M, Camera, Motion

__all__ = ["FramesSource", "INTRINSICS_NAMES"]

logger = logging.getLogger(__name__)

#: Default intrinsics file names looked up in the image folder, in this order.
INTRINSICS_NAMES: tuple[str, ...] = ("intrinsics.yaml", "intrinsics.yml", "intrinsics.json", "intrinsics.txt")


@dataclass
class _Pair:
    index: int
    path: Path
    path_prev: Path
    T_w_cur: np.ndarray | None
    T_w_prev: np.ndarray | None


class FramesSource(LazySource):
    """Consecutive image pairs of a folder, with intrinsics from a file or a horizontal field of view.

    Args:
        root: the image folder.
        intrinsics: intrinsics file; None = ``root/intrinsics.{yaml,yml,json,txt}``, else ``hfov_deg``.
        hfov_deg: horizontal field of view (degrees), used without an intrinsics file (approximate).
        step: index distance of a pair in name order.
        frames: at most this many pairs (None = all).
        fps: the folder's frame rate (Hz): ``meta["dt"] = (frames between the two images) / fps`` seconds.
        resize: None, ``"auto"`` (about :data:`~monostixels.data._lens.AUTO_PIXELS`, never upscaled), a
            factor, or ``(W, H)`` pixels.
        camera_height: camera height above the road (metres).
        pitch: camera pitch (radians, positive = looking down).
        poses: optional poses file (see the module docstring).
        mask: optional mask image, non-zero = ignore (see the module docstring), or ``auto``: a static
            region at the bottom found from images spread over the folder (a bonnet,
            :mod:`monostixels.data.static_regions`).

    Raises:
        InputError: missing root, empty folder, neither an intrinsics file nor ``hfov_deg``, a malformed
            intrinsics (or distortion) or poses file, a bad ``fps`` / ``resize`` / ``hfov_deg``, fewer than
            ``step + 1`` images, no readable image, a mask of another size than the first image; at access:
            unreadable image, an image of another size than the first.
    """

    def __init__(
        self,
        root: str | Path,
        *,
        intrinsics: str | Path | None = None,
        hfov_deg: float | None = None,
        step: int = 1,
        frames: int | None = None,
        fps: float = FOLDER_FPS,
        resize: float | Sequence[int] | str | None = None,
        camera_height: float = KITTI_CAMERA_HEIGHT_M,
        pitch: float = 0.0,
        poses: str | Path | None = None,
        mask: str | Path | None = None,
    ) -> None:
        self.root = require_dir(root, "frames data.root")
        if int(step) < 1:
            raise InputError(f"data.step: must be a positive number of frames, got {step}")
        if not (isinstance(fps, (int, float)) and not isinstance(fps, bool) and math.isfinite(fps) and fps > 0):
            raise InputError(f"data.fps: the folder's frame rate must be a positive number of frames a second, got {fps!r}")
        self.fps = float(fps)
        images = list_images(self.root, "frames data.root")
        if intrinsics is None:
            found = [self.root / n for n in INTRINSICS_NAMES if (self.root / n).is_file()]
            if not found and hfov_deg is None:
                raise InputError(
                    f"frames: no intrinsics: set data.intrinsics=FILE (or put one of {', '.join(INTRINSICS_NAMES)} in "
                    f"{self.root}) or data.hfov_deg=DEGREES (horizontal field of view, approximate)"
                )
            intrinsics = found[0] if found else None
        self.intrinsics_path = None if intrinsics is None else Path(intrinsics).expanduser()
        self._first = self._first_readable(images)
        self.size_in: tuple[int, int] = tuple(read_rgb(self._first).shape[-2:])  # type: ignore[assignment]
        H0, W0 = self.size_in
        self.size = working_size(resize, W0, H0)
        auto = mask == AUTO_MASK
        self.camera: Camera
        self.camera, self.intrinsics_source, self._warp = lens_camera(
            self.intrinsics_path, hfov_deg, self.size_in, self.size, camera_height, pitch, None if auto else mask,
            what="frames", frames_what=f"the images of {self.root}")
        if auto:
            self._warp.ignore = with_static_region(self._warp.ignore, self._sample(images, int(step)),
                                                   f"frames {self.root}")
        pose_of: list[np.ndarray | None] = [None] * len(images)
        if poses is not None:
            pose_of = self._match_poses(Path(poses).expanduser(), images)
        self.step = int(step)
        self._images, self._poses = images, pose_of
        self._index_of = {p: i for i, p in enumerate(images)}
        items = [
            _Pair(i, images[i], images[i - int(step)], pose_of[i], pose_of[i - int(step)])
            for i in range(int(step), len(images))
        ]
        self._items = limit_frames(items, frames, f"frames {self.root} ({len(images)} image(s), step {step})")
        logger.info("frames: %d frame pairs under %s (%dx%d -> %dx%d, %g fps, intrinsics %s)", len(self._items),
                    self.root, W0, H0, self.size[1], self.size[0], self.fps, self.intrinsics_source)

    @staticmethod
    def _first_readable(images: list[Path]) -> Path:
        """The first image that decodes (once: its pair reads it from the cache), whose size sets up the tables;
        unreadable ones before it are left to the pairs, which report them."""
        for p in images:
            try:
                read_rgb(p)
                return p
            except InputError:
                continue
        raise InputError(f"frames data.root: no image of {images[0].parent} can be read")

    @staticmethod
    def _match_poses(path: Path, images: list[Path]) -> list[np.ndarray | None]:
        ids, T = read_poses_file(path)
        if ids is None:
            if len(T) != len(images):
                raise InputError(f"poses: {path} has {len(T)} poses for {len(images)} images (one line per image, name order)")
            return list(T)
        by_id: dict[int, np.ndarray] = {}
        for i, M in zip(ids, T):
            try:
                by_id[int(i)] = M
            except ValueError as e:
                raise InputError(f"poses: {path} frame id {i!r} is not a number") from e
        out: list[np.ndarray | None] = []
        for img in images:
            n = int(img.stem) if img.stem.isdigit() else None
            out.append(by_id.get(n) if n is not None else None)
        if all(o is None for o in out):
            raise InputError(f"poses: no frame id of {path} matches an image name (numeric file stems) in {images[0].parent}")
        return out

    # --- sequences (keyframes) ------------------------------------------------------------------
    def _sequence_key(self, item: _Pair) -> str:
        return f"frames/{self.root}"

    def _back(self, item: _Pair, back: int) -> _Pair | None:
        j = item.index - int(back) * self.step
        if j < 0:
            return None
        return _Pair(item.index, item.path, self._images[j], item.T_w_cur, self._poses[j])

    def _pair_dt(self, item: _Pair) -> float:
        return (item.index - self._index_of[item.path_prev]) / self.fps

    def _pair_motion(self, item: _Pair) -> Motion | None:
        if item.T_w_cur is None or item.T_w_prev is None:
            return None
        return relative_motion(item.T_w_cur, item.T_w_prev)

    def _prev_name(self, item: _Pair) -> str:
        return item.path_prev.stem

    def _cur_name(self, item: _Pair) -> str:
        return item.path.stem

    def _read(self, path: Path, current: bool) -> torch.Tensor:
        """:func:`read_rgb`; a file that cannot be decoded is an :class:`UnreadableFrame` (skipped by the pairs)."""
        try:
            return read_rgb(path)
        except InputError as err:
            raise UnreadableFrame(str(err), name=path.stem, label=path.name, current=current) from None

    def _sample(self, images: list[Path], step: int) -> list[list[np.ndarray]]:
        """Runs of images ``step`` apart, spread over the whole folder
        (:func:`~monostixels.data.static_regions.spread_samples`; BGR, undistorted and resized), for the static
        region search; unreadable ones and ones of another size than the first readable one are left out (the
        pairs report them)."""
        used = images[::step]
        min_gap = max(1, round(AUTO_SPACING_S * self.fps / step))
        runs: list[list[np.ndarray]] = []
        for run in spread_samples(len(used), min_gap):
            runs.append([])
            for i in run:
                img = cv2.imread(str(used[i]), cv2.IMREAD_COLOR)
                if img is not None and img.shape[:2] == self._warp.size_in:
                    runs[-1].append(self._warp.image(img))
        return runs

    def _load(self, item: _Pair) -> FramePair:
        image, image_prev = self._read(item.path, True), self._read(item.path_prev, False)
        check_same_size(image, image_prev, f"image {item.path} (current)", f"image {item.path_prev} (previous)")
        image, image_prev = self._warped(image, item.path), self._warped(image_prev, item.path_prev)
        motion = self._pair_motion(item)
        meta: dict[str, Any] = {
            "source": "frames", "index": item.index, "path": str(item.path), "path_prev": str(item.path_prev),
            "intrinsics": self.intrinsics_source, "sequence": self._sequence_key(item), "frame": item.index,
            "frame_prev": self._index_of[item.path_prev], "name_prev": self._prev_name(item),
            "dt": self._pair_dt(item)}
        ignore = self._warp.ignore_mask()
        if ignore is not None:
            meta["ignore_mask"] = ignore
        return FramePair(image=image, image_prev=image_prev, camera=self.camera, motion=motion, gt=GroundTruth(),
                         name=item.path.stem, meta=meta)

    def _warped(self, image: torch.Tensor, path: Path) -> torch.Tensor:
        """(3, H, W) float RGB undistorted and resized (the size checked against the first image's)."""
        H, W = image.shape[-2:]
        if (H, W) != self._warp.size_in:
            raise InputError(f"frames: image {path} is {W}x{H}, the first image {self._first.name} "
                             f"{self._warp.size_in[1]}x{self._warp.size_in[0]}: every image must have that size")
        if not self._warp.changes_frames:
            return image
        hwc = np.ascontiguousarray(image.permute(1, 2, 0).numpy())
        return torch.from_numpy(np.ascontiguousarray(self._warp.image(hwc).transpose(2, 0, 1)))
