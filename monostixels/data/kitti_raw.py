"""KITTI raw sequences: left colour camera (camera 2) frame pairs with optional poses and
stixel-bottom labels.

Layout under ``root`` (KITTI raw "synced + rectified" download)::

    root/DATE/calib_cam_to_cam.txt                         P_rect_02 -> intrinsics
    root/DATE/DATE_drive_NNNN_sync/image_02/data/*.png|jpg  frames named by raw frame number
    root/DATE/DATE_drive_NNNN_sync/poses_cam0.txt           optional: "frame T_w_cam0 (3x4)"
    root/DATE/DATE_drive_NNNN_sync/stixel_bottoms_bmvc15.txt optional: "date drive frame x y split"

Pairs: current = frame ``n``, previous = frame ``n - step`` (raw frame numbers), for every ``n``
whose predecessor exists.

Convention: camera motion ``X_prev = R X_cur + t`` (SPEC section 2) of *camera 2*. The poses give
``T_w_cam0`` (rectified camera 0 to world, the KITTI odometry ground truth). Camera 2 is rectified
with camera 0 (same rotation): ``P_rect_02 = K [I | b]`` so ``X_cam2 = X_cam0 + b`` with
``b = K^-1 P_rect_02[:, 3]`` (about 6 cm along x), hence ``T_w_cam2 = T_w_cam0 [I | -b]`` and
``T_prev_cur = T_w_cam2(prev)^-1 T_w_cam2(cur)``. A forward-driving camera gives ``t_z > 0``: the
static scene is farther away in the previous frame.
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from monostixels._checks import InputError
from monostixels.data._io import (
    LazySource,
    limit_frames,
    list_images,
    make_camera,
    projection_matrix,
    read_image_pair,
    read_kitti_calib,
    read_poses_file,
    relative_motion,
    require_dir,
    require_file,
)
from monostixels.data.base import FramePair, GroundTruth
from monostixels.geometry import KITTI_CAMERA_HEIGHT_M, Camera, Motion

__all__ = ["KittiRawSource", "POSES_FILE", "BOTTOMS_FILE", "CALIB_FILE", "read_stixel_bottoms", "cam2_offset"]

logger = logging.getLogger(__name__)

#: Per-date calibration file of the KITTI raw data.
CALIB_FILE = "calib_cam_to_cam.txt"
#: Optional per-drive poses: "10-digit raw frame number" + 12 numbers of ``T_w_cam0`` (3x4, metres).
POSES_FILE = "poses_cam0.txt"
#: Optional per-drive stixel-bottom labels (StixelNet, Levi et al. BMVC 2015): "date drive frame x y split".
BOTTOMS_FILE = "stixel_bottoms_bmvc15.txt"
#: Rectified projection matrix of the left colour camera (camera 2) in the calibration file.
P_RECT_KEY = "P_rect_02"

_DATE_RE = re.compile(r"^\d{4}_\d{2}_\d{2}$")
_DRIVE_RE = re.compile(r"^(\d{4}_\d{2}_\d{2})_drive_(\d{4})_sync$")


def cam2_offset(P_rect_02: np.ndarray) -> np.ndarray:
    """Offset ``b`` (3,) metres with ``X_cam2 = X_cam0 + b`` for rectified cameras: ``K^-1 P[:, 3]``."""
    return np.linalg.solve(P_rect_02[:, :3], P_rect_02[:, 3])


def read_stixel_bottoms(path: str | Path, date: str, drive: int) -> dict[int, tuple[np.ndarray, list[str]]]:
    """Stixel-bottom labels of one drive.

    Args:
        path: ``stixel_bottoms_bmvc15.txt`` (whitespace-separated ``date drive frame x y split``; the
            date may be written without the year, e.g. ``09_30``).
        date: the drive's date ``YYYY_MM_DD``.
        drive: the drive number.

    Returns:
        raw frame number -> ((N, 2) float32 ``(u, v)`` pixels, N split names).

    Raises:
        InputError: a malformed line (named by file and line number).
    """
    p = require_file(path, "stixel-bottom labels")
    out: dict[int, tuple[list[tuple[float, float]], list[str]]] = {}
    for ln, line in enumerate(p.read_text(errors="replace").splitlines(), start=1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        if len(parts) < 5:
            raise InputError(f"stixel-bottom labels: {p} line {ln} has {len(parts)} columns; expected 'date drive frame x y split'")
        try:
            l_drive, frame, x, y = int(parts[1]), int(parts[2]), float(parts[3]), float(parts[4])
        except ValueError as e:
            raise InputError(f"stixel-bottom labels: {p} line {ln} has a non-numeric drive/frame/x/y") from e
        if not date.endswith(parts[0]) or l_drive != drive:
            continue
        pts, splits = out.setdefault(frame, ([], []))
        pts.append((x, y))
        splits.append(parts[5] if len(parts) > 5 else "")
    return {f: (np.asarray(v, dtype=np.float32).reshape(-1, 2), s) for f, (v, s) in out.items()}


@dataclass
class _Drive:
    date: str
    drive: int
    folder: Path
    camera: Camera
    P_rect_02: np.ndarray
    images: dict[int, Path]
    poses: dict[int, np.ndarray] | None  # raw frame -> T_w_cam2 (4, 4)
    bottoms: dict[int, tuple[np.ndarray, list[str]]] | None


@dataclass
class _Pair:
    drive: _Drive
    frame: int
    frame_prev: int


class KittiRawSource(LazySource):
    """Frame pairs of KITTI raw drives (camera 2), with ground-truth motion and stixel bottoms
    where the optional files exist.

    Args:
        root: folder holding the ``DATE`` folders.
        date: only this date (``2011_09_30``); None = all dates found.
        drive: only this drive (``28``, ``"0028"`` or the folder name); None = all drives.
        step: frame distance of a pair (current ``n``, previous ``n - step``).
        frames: at most this many pairs (None = all).
        only_labelled: only pairs whose current frame has stixel-bottom labels.
        camera_height: camera height above the road (metres).
        pitch: camera pitch (radians, positive = looking down), tilts the ground normal.

    Ground truth: ``motion`` (from ``poses_cam0.txt``), ``gt.bottoms`` (from the label file, for
    labelled frames); nothing else (KITTI raw has no dense depth/flow here).

    Raises:
        InputError: missing root / date / drive / calibration, empty image folder, malformed
            poses or labels, no pairs.
    """

    def __init__(
        self,
        root: str | Path,
        *,
        date: str | None = None,
        drive: int | str | None = None,
        step: int = 1,
        frames: int | None = None,
        only_labelled: bool = False,
        camera_height: float = KITTI_CAMERA_HEIGHT_M,
        pitch: float = 0.0,
    ) -> None:
        self.root = require_dir(root, "kitti_raw data.root")
        if int(step) < 1:
            raise InputError(f"data.step: must be a positive number of frames, got {step}")
        self.step = int(step)
        drives = self._find_drives(date, drive)
        items: list[_Pair] = []
        for folder in drives:
            d = self._load_drive(folder, camera_height, pitch)
            for n in sorted(d.images):
                if n - self.step not in d.images:
                    continue
                if only_labelled and (d.bottoms is None or n not in d.bottoms):
                    continue
                items.append(_Pair(d, n, n - self.step))
        what = f"kitti_raw {self.root}" + (" (only_labelled: no labelled frame with a predecessor)" if only_labelled else "")
        self._items = limit_frames(items, frames, what)
        logger.info("kitti_raw: %d frame pairs from %d drive(s) under %s", len(self._items), len(drives), self.root)

    def _find_drives(self, date: str | None, drive: int | str | None) -> list[Path]:
        if date is not None:
            dates = [require_dir(self.root / str(date), f"kitti_raw date {date}")]
        else:
            dates = sorted(p for p in self.root.iterdir() if p.is_dir() and _DATE_RE.match(p.name))
            if not dates:
                raise InputError(f"kitti_raw data.root: {self.root} holds no YYYY_MM_DD date folders")
        out: list[Path] = []
        for dd in dates:
            for p in sorted(dd.iterdir()):
                m = _DRIVE_RE.match(p.name)
                if p.is_dir() and m and (drive is None or _drive_matches(drive, p.name, int(m.group(2)))):
                    out.append(p)
        if not out:
            want = f" matching drive {drive}" if drive is not None else ""
            raise InputError(f"kitti_raw: no DATE_drive_NNNN_sync folders{want} under {', '.join(map(str, dates))}")
        return out

    def _load_drive(self, folder: Path, camera_height: float, pitch: float) -> _Drive:
        m = _DRIVE_RE.match(folder.name)
        assert m is not None
        date, drive = m.group(1), int(m.group(2))
        calib_path = folder.parent / CALIB_FILE
        calib = read_kitti_calib(require_file(calib_path, f"kitti_raw calibration of {date}"))
        P = projection_matrix(calib, P_RECT_KEY, calib_path)
        camera = make_camera(P[0, 0], P[1, 1], P[0, 2], P[1, 2], camera_height, pitch)
        images: dict[int, Path] = {}
        for f in list_images(folder / "image_02" / "data", f"kitti_raw images of {folder.name}"):
            if not f.stem.isdigit():
                raise InputError(f"kitti_raw: image {f} is not named by its raw frame number (e.g. 0000000042.png)")
            images[int(f.stem)] = f
        poses = None
        if (folder / POSES_FILE).exists():
            poses = self._read_poses(folder / POSES_FILE, cam2_offset(P))
        bottoms = None
        if (folder / BOTTOMS_FILE).exists():
            bottoms = read_stixel_bottoms(folder / BOTTOMS_FILE, date, drive)
        return _Drive(date, drive, folder, camera, P, images, poses, bottoms)

    @staticmethod
    def _read_poses(path: Path, b: np.ndarray) -> dict[int, np.ndarray]:
        ids, T_w_cam0 = read_poses_file(path)
        if ids is None:
            raise InputError(
                f"poses: {path} must start each line with the raw frame number (13 values: frame + 3x4 T_w_cam0)"
            )
        # Rectified camera 2 = rectified camera 0 shifted: X_cam0 = X_cam2 - b.
        T_cam0_cam2 = np.eye(4)
        T_cam0_cam2[:3, 3] = -b
        out: dict[int, np.ndarray] = {}
        for i, T in zip(ids, T_w_cam0):
            try:
                out[int(i)] = T @ T_cam0_cam2
            except ValueError as e:
                raise InputError(f"poses: {path} has a frame id {i!r} that is not a number") from e
        return out

    def _load(self, item: _Pair) -> FramePair:
        d = item.drive
        image, image_prev = read_image_pair(d.images[item.frame], d.images[item.frame_prev])
        motion: Motion | None = None
        if d.poses is not None:
            if item.frame in d.poses and item.frame_prev in d.poses:
                motion = relative_motion(d.poses[item.frame], d.poses[item.frame_prev])
            else:
                logger.warning("kitti_raw: %s lacks frame %d or %d: no ground-truth motion for this pair",
                               d.folder / POSES_FILE, item.frame, item.frame_prev)
        gt = GroundTruth()
        meta: dict = {"source": "kitti_raw", "date": d.date, "drive": d.drive, "frame": item.frame,
                      "frame_prev": item.frame_prev, "path": str(d.images[item.frame]),
                      "path_prev": str(d.images[item.frame_prev])}
        if d.bottoms is not None and item.frame in d.bottoms:
            pts, splits = d.bottoms[item.frame]
            gt.bottoms = torch.from_numpy(pts.copy())
            meta["bottoms_split"] = sorted(set(splits))
        return FramePair(
            image=image, image_prev=image_prev, camera=d.camera, motion=motion, gt=gt,
            name=f"{d.date}_drive_{d.drive:04d}_{item.frame:010d}", meta=meta,
        )


def _drive_matches(want: int | str, folder_name: str, number: int) -> bool:
    s = str(want)
    if s == folder_name:
        return True
    return s.isdigit() and int(s) == number
