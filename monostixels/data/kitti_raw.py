"""KITTI raw sequences: left colour camera (camera 2) frame pairs with optional poses and
stixel-bottom labels.

Layout under ``root`` (KITTI raw "synced + rectified" download)::

    root/DATE/calib_cam_to_cam.txt                         P_rect_02 -> intrinsics
    root/DATE/DATE_drive_NNNN_sync/image_02/data/*.png|jpg  frames named by raw frame number
    root/DATE/DATE_drive_NNNN_sync/poses_cam0.txt           optional: "frame T_w_cam0 (3x4)"
    root/DATE/DATE_drive_NNNN_sync/stixel_bottoms_bmvc15.txt optional: "date drive frame x y split"
    root/DATE/DATE_drive_NNNN_sync/oxts/data/*.txt          optional: GPS/IMU records (camera motion)
    root/DATE/calib_imu_to_velo.txt, calib_velo_to_cam.txt  needed with oxts/ (the pose chain)
    root/DATE/DATE_drive_NNNN_sync/proj_depth/velodyne/image_02/*.npz       optional LiDAR depth
    root/DATE/DATE_drive_NNNN_sync/proj_depth/groundtruth/image_02/*.png    optional (KITTI depth benchmark)
    root/DATE/DATE_drive_NNNN_sync/proj_depth/velodyne_raw/image_02/*.png   optional (KITTI depth benchmark)
    root/DATE/DATE_drive_NNNN_sync/velodyne_points/data/*.bin  optional: raw scans (with calib_velo_to_cam.txt)
    root/DATE/DATE_drive_NNNN_sync/image_02/timestamps.txt  optional: frame times (frame interval)

A drive folder is ``DATE_drive_LABEL_sync``: ``LABEL`` is KITTI's 4-digit drive number
(``2011_09_26_drive_0023_sync``, frames named ``2011_09_26_drive_0023_0000000005``) or any other
label of letters, digits and ``-`` (``2011_09_26_drive_traffic_sync``, frames named
``2011_09_26_drive_traffic_0000000005``); only numbered drives can have stixel-bottom labels.

Pairs: current = frame ``n``, previous = frame ``n - step`` (raw frame numbers), for every ``n``
whose predecessor exists.

Camera motion: from ``poses_cam0.txt`` where present, else from the OXTS records (every KITTI raw
drive has them; ``oxts="velocity"`` or ``"position"``, see :func:`oxts_poses`), else none.
Depth ground truth: the LiDAR depth of the current frame (metres, z in camera 2, 0 = no return), from
the first of these a frame has (:data:`DEPTH_SOURCES`): the ``proj_depth/velodyne`` npz (this
package's format: a folder prepared with it keeps its numbers), the depth benchmark's
``proj_depth/groundtruth`` PNG (accumulated over neighbouring scans and cleaned: denser and truer than
one scan), its ``proj_depth/velodyne_raw`` PNG (one scan), the raw scan ``velodyne_points/data/*.bin``
projected here (:func:`project_velodyne`). ``meta["depth_from"]`` names the one used. KITTI raw has no moving-object mask, so ``gt.moving`` is
None and only the ``overall`` split is scored.

Convention: camera motion ``X_prev = R X_cur + t`` (docs/conventions.md, section 2) of *camera 2*.
The poses give ``T_w_cam0`` (rectified camera 0 to world, the KITTI odometry ground truth). Camera 2
is rectified with camera 0 (same rotation): ``P_rect_02 = K [I | b]`` so ``X_cam2 = X_cam0 + b``
with ``b = K^-1 P_rect_02[:, 3]`` (about 6 cm along x), hence ``T_w_cam2 = T_w_cam0 [I | -b]`` and
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
from monostixels.data._camera_files import (make_camera, projection_matrix, read_kitti_calib, read_poses_file,
                                            relative_motion)
from monostixels.data._lazy_source import LazySource, limit_frames
from monostixels.data._readers import list_images, read_image_pair, read_png16, require_dir, require_file
from monostixels.data.base import FramePair, GroundTruth
from monostixels.core.geometry import KITTI_CAMERA_HEIGHT_M, Camera, Motion

__all__ = [
    "KittiRawSource", "POSES_FILE", "BOTTOMS_FILE", "CALIB_FILE", "OXTS_MODES", "read_stixel_bottoms", "cam2_offset",
    "read_oxts", "oxts_poses", "read_timestamps", "read_lidar_npz", "read_depth_png", "imu_to_cam2",
    "velo_to_cam0_rect", "read_velodyne_bin", "project_velodyne", "DEPTH_SOURCES",
]

logger = logging.getLogger(__name__)

#: Per-date calibration file of the KITTI raw data.
CALIB_FILE = "calib_cam_to_cam.txt"
#: Optional per-drive poses: "10-digit raw frame number" + 12 numbers of ``T_w_cam0`` (3x4, metres).
POSES_FILE = "poses_cam0.txt"
#: Optional per-drive stixel-bottom labels (StixelNet, Levi et al. BMVC 2015): "date drive frame x y split".
BOTTOMS_FILE = "stixel_bottoms_bmvc15.txt"
#: Rectified projection matrix of the left colour camera (camera 2) in the calibration file.
P_RECT_KEY = "P_rect_02"

#: Calibration files of the OXTS -> camera chain (per date).
IMU_TO_VELO_FILE = "calib_imu_to_velo.txt"
VELO_TO_CAM_FILE = "calib_velo_to_cam.txt"
#: Per-drive GPS/IMU records, one text file per raw frame (KITTI raw devkit ``dataformat.txt``).
OXTS_DIR = Path("oxts") / "data"
#: LiDAR depth in camera 2: npz (key ``velodyne_depth``, metres) or depth-benchmark PNG (uint16).
LIDAR_NPZ_DIR = Path("proj_depth") / "velodyne" / "image_02"
LIDAR_NPZ_KEY = "velodyne_depth"
DEPTH_PNG_DIR = Path("proj_depth") / "groundtruth" / "image_02"
VELODYNE_RAW_PNG_DIR = Path("proj_depth") / "velodyne_raw" / "image_02"
#: Raw Velodyne scans: float32 ``x y z reflectance`` per return (Velodyne axes, metres).
VELODYNE_BIN_DIR = Path("velodyne_points") / "data"
#: Where a frame's LiDAR depth comes from, in the order of preference: (folder in the drive, file pattern).
DEPTH_SOURCES: tuple[tuple[Path, str], ...] = (
    (LIDAR_NPZ_DIR, "*.npz"), (DEPTH_PNG_DIR, "*.png"), (VELODYNE_RAW_PNG_DIR, "*.png"), (VELODYNE_BIN_DIR, "*.bin"),
)
#: KITTI depth benchmark PNGs store metres x 256 (devkit ``depth_read``), 0 = no measurement.
DEPTH_PNG_SCALE = 256.0
#: How the OXTS poses get their positions: integrated velocities, or GPS latitude/longitude.
OXTS_MODES = ("velocity", "position")
#: Earth radius of the KITTI raw devkit's Mercator projection (metres; WGS84 equatorial radius).
EARTH_RADIUS_M = 6378137.0
#: KITTI raw frame rate (Hz), used only when a drive has no timestamps file.
KITTI_RAW_FPS = 10.0
# OXTS record columns (dataformat.txt): lat lon alt roll pitch yaw vn ve vf vl vu ...
_OXTS_MIN_COLUMNS = 11
_VF, _VL, _VU = 8, 9, 10

_DATE_RE = re.compile(r"^\d{4}_\d{2}_\d{2}$")
#: ``DATE_drive_LABEL_sync``: LABEL = KITTI's 4-digit number, or any label of letters, digits and ``-``.
_DRIVE_RE = re.compile(r"^(\d{4}_\d{2}_\d{2})_drive_([A-Za-z0-9-]+)_sync$")


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


def _rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def read_oxts(folder: str | Path) -> dict[int, np.ndarray]:
    """GPS/IMU records of a drive.

    Args:
        folder: ``oxts/data`` with one ``NNNNNNNNNN.txt`` per raw frame (30 numbers: lat lon alt
            roll pitch yaw vn ve vf vl vu ..., KITTI raw ``dataformat.txt``; degrees, metres,
            radians, m/s).

    Returns:
        raw frame number -> (K,) float64 record (K >= 11).

    Raises:
        InputError: a file that is not named by its frame number, too short, or not numbers.
    """
    d = require_dir(folder, "kitti_raw oxts/data")
    out: dict[int, np.ndarray] = {}
    for f in sorted(d.glob("*.txt")):
        if not f.stem.isdigit():
            raise InputError(f"oxts: {f} is not named by its raw frame number (e.g. 0000000042.txt)")
        try:
            vals = np.array([float(x) for x in f.read_text().split()], dtype=np.float64)
        except ValueError as e:
            raise InputError(f"oxts: {f} holds something that is not a number") from e
        if vals.size < _OXTS_MIN_COLUMNS or not np.all(np.isfinite(vals[:_OXTS_MIN_COLUMNS])):
            raise InputError(f"oxts: {f} has {vals.size} values; expected the 30 of KITTI raw dataformat.txt "
                             f"(lat lon alt roll pitch yaw vn ve vf vl vu ...)")
        out[int(f.stem)] = vals
    if not out:
        raise InputError(f"oxts: {d} holds no NNNNNNNNNN.txt records")
    return out


def read_timestamps(path: str | Path) -> np.ndarray:
    """Seconds (N,) float64 of a KITTI raw ``timestamps.txt`` (``YYYY-MM-DD hh:mm:ss.fffffffff``
    per line, line ``i`` = raw frame ``i``), relative to the first line.

    Raises:
        InputError: a malformed line (named by file and line number).
    """
    p = require_file(path, "timestamps")
    secs: list[float] = []
    for ln, line in enumerate(p.read_text().splitlines(), start=1):
        line = line.strip()
        if not line:
            continue
        try:
            _, clock = line.split()
            hh, mm, ss = clock.split(":")
            secs.append(int(hh) * 3600.0 + int(mm) * 60.0 + float(ss))
        except ValueError as e:
            raise InputError(f"timestamps: {p} line {ln} is not 'YYYY-MM-DD hh:mm:ss.fff': {line!r}") from e
    t = np.asarray(secs)
    # A drive that passes midnight: unwrap the day.
    t = t + 86400.0 * np.cumsum(np.r_[0.0, np.diff(t) < -43200.0])
    return t - (t[0] if len(t) else 0.0)


def _rigid(calib: dict[str, np.ndarray], path: Path) -> np.ndarray:
    """4x4 transform from a KITTI ``R: 9 numbers`` / ``T: 3 numbers`` calibration file."""
    if "R" not in calib or "T" not in calib or calib["R"].size != 9 or calib["T"].size != 3:
        raise InputError(f"calibration: {path} needs 'R:' (9 numbers) and 'T:' (3 numbers)")
    T = np.eye(4)
    T[:3, :3] = calib["R"].reshape(3, 3)
    T[:3, 3] = calib["T"]
    return T


def velo_to_cam0_rect(date_folder: str | Path, what: str) -> np.ndarray:
    """(4, 4) from Velodyne to rectified camera 0: ``R_rect_00 T_cam0_velo`` (KITTI raw devkit;
    ``calib_velo_to_cam.txt`` R|T, ``calib_cam_to_cam.txt`` R_rect_00), metres.

    Args:
        date_folder: the ``DATE`` folder holding the calibration files.
        what: what needs it, for the messages (``"the OXTS poses"``).

    Raises:
        InputError: a missing calibration file or entry.
    """
    dd = Path(date_folder)
    p_vc, p_cc = dd / VELO_TO_CAM_FILE, dd / CALIB_FILE
    T_cam0_velo = _rigid(read_kitti_calib(require_file(p_vc, f"kitti_raw calibration for {what}")), p_vc)
    cc = read_kitti_calib(require_file(p_cc, "kitti_raw calibration"))
    if "R_rect_00" not in cc or cc["R_rect_00"].size != 9:
        raise InputError(f"calibration: {p_cc} has no R_rect_00 (9 numbers), needed for {what}")
    R_rect = np.eye(4)
    R_rect[:3, :3] = cc["R_rect_00"].reshape(3, 3)
    return R_rect @ T_cam0_velo


def imu_to_cam2(date_folder: str | Path, P_rect_02: np.ndarray) -> np.ndarray:
    """``T_cam2_imu`` (4, 4): IMU -> Velodyne -> camera 0 (rectified with ``R_rect_00``) -> camera 2.

    Convention (KITTI raw devkit): ``X_velo = T_velo_imu X_imu``, ``X_cam0 = R_rect_00 T_cam0_velo X_velo``,
    ``X_cam2 = X_cam0 + b`` with ``b = K^-1 P_rect_02[:, 3]`` (rectified cameras share the rotation).

    Raises:
        InputError: a missing calibration file or entry.
    """
    p_iv = Path(date_folder) / IMU_TO_VELO_FILE
    T_velo_imu = _rigid(read_kitti_calib(require_file(p_iv, "kitti_raw OXTS calibration")), p_iv)
    T_cam2_cam0 = np.eye(4)
    T_cam2_cam0[:3, 3] = cam2_offset(P_rect_02)
    return T_cam2_cam0 @ velo_to_cam0_rect(date_folder, "the OXTS poses") @ T_velo_imu


def oxts_poses(records: dict[int, np.ndarray], times: dict[int, float] | None = None, *,
               mode: str = "velocity") -> dict[int, np.ndarray]:
    """IMU-to-world poses ``T_w_imu`` (4, 4) from OXTS records (KITTI raw devkit ``convertOxtsToPose``).

    Orientation: ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (IMU axes x forward, y left, z up; world x east,
    y north, z up). Position:

    - ``"position"``: the devkit's Mercator projection of latitude/longitude with the scale
      ``cos(lat_0)`` of the first record, and the altitude. GPS positions jitter by a few cm.
    - ``"velocity"``: integrated velocities. ``vf, vl, vu`` are forward / left (parallel to the
      earth surface) and up, i.e. in the heading frame ``Rz(yaw)``; between consecutive records
      ``p_k = p_{k-1} + (Rz(yaw_{k-1}) v_{k-1} + Rz(yaw_k) v_k) / 2 * (t_k - t_{k-1})`` (trapezoid).
      Steadier from frame to frame (the GPS/IMU fuses its velocities from the IMU); drifts slowly
      over long distances, which frame-to-frame motion does not feel. Gaps in the frame numbers
      are integrated across (the trapezoid over the gap).

    Args:
        records: raw frame -> OXTS record (:func:`read_oxts`).
        times: raw frame -> seconds (needed for ``"velocity"``; default ``frame / 10 Hz``).
        mode: ``"velocity"`` or ``"position"``.

    Returns:
        raw frame -> ``T_w_imu`` (4, 4) float64, metres; the first frame's position is the origin.
    """
    if mode not in OXTS_MODES:
        raise InputError(f"data.oxts: unknown mode {mode!r}; choose one of {', '.join(OXTS_MODES)}")
    frames = sorted(records)
    lat0 = records[frames[0]][0]
    scale = np.cos(np.radians(lat0))
    out: dict[int, np.ndarray] = {}
    pos = np.zeros(3)
    origin = None
    prev: tuple[int, np.ndarray] | None = None
    for f in frames:
        r = records[f]
        R = _rot_z(r[5]) @ _rot_y(r[4]) @ _rot_x(r[3])
        if mode == "position":
            p = np.array([scale * np.radians(r[1]) * EARTH_RADIUS_M,
                          scale * EARTH_RADIUS_M * np.log(np.tan(np.radians(90.0 + r[0]) / 2.0)),
                          r[2]])
            origin = p if origin is None else origin
            pos = p - origin
        elif prev is not None:
            fp, rp = prev
            tp = times[fp] if times is not None else fp / KITTI_RAW_FPS
            tc = times[f] if times is not None else f / KITTI_RAW_FPS
            v_prev = _rot_z(rp[5]) @ rp[[_VF, _VL, _VU]]
            v_cur = _rot_z(r[5]) @ r[[_VF, _VL, _VU]]
            pos = pos + 0.5 * (v_prev + v_cur) * (tc - tp)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = pos
        out[f] = T
        prev = (f, r)
    return out


def read_lidar_npz(path: str | Path) -> np.ndarray:
    """LiDAR depth (H, W) float32 metres (z in camera 2; 0 = no return) from a ``proj_depth/velodyne`` npz.

    Raises:
        InputError: unreadable file, no ``velodyne_depth`` key, not 2-D, negative or non-finite values.
    """
    p = require_file(path, "LiDAR depth npz")
    try:
        with np.load(p) as z:
            if LIDAR_NPZ_KEY not in z.files:
                raise InputError(f"LiDAR depth npz: {p} has no {LIDAR_NPZ_KEY!r} array (has {', '.join(z.files)})")
            d = np.asarray(z[LIDAR_NPZ_KEY], dtype=np.float32)
    except (OSError, ValueError) as e:
        raise InputError(f"LiDAR depth npz: cannot read {p} ({e})") from e
    if d.ndim != 2:
        raise InputError(f"LiDAR depth npz: {p} {LIDAR_NPZ_KEY} has shape {d.shape}, expected (H, W)")
    if not np.all(np.isfinite(d)) or (d < 0).any():
        raise InputError(f"LiDAR depth npz: {p} holds negative or non-finite depths (0 = no return)")
    return d


def read_depth_png(path: str | Path) -> np.ndarray:
    """Depth (H, W) float32 metres from a KITTI depth-benchmark PNG (uint16, metres x 256, 0 = none).

    Raises:
        InputError: unreadable, or not a 1-channel 16-bit PNG.
    """
    return read_png16(require_file(path, "depth PNG"), 1).astype(np.float32) / DEPTH_PNG_SCALE


def read_velodyne_bin(path: str | Path) -> np.ndarray:
    """A raw Velodyne scan (N, 4) float32: ``x y z`` (metres, Velodyne axes: x forward, y left, z up) and
    reflectance, from a KITTI ``velodyne_points/data/*.bin`` (little-endian float32, 4 per return).

    Raises:
        InputError: unreadable, a size that is not a whole number of returns, non-finite coordinates.
    """
    p = require_file(path, "Velodyne scan")
    try:
        raw = np.fromfile(p, dtype="<f4")
    except OSError as e:
        raise InputError(f"Velodyne scan: cannot read {p} ({e})") from e
    if raw.size % 4:
        raise InputError(f"Velodyne scan: {p} holds {raw.size} float32 values, not a multiple of 4 (x y z reflectance)")
    pts = raw.reshape(-1, 4).astype(np.float32)
    if not np.all(np.isfinite(pts[:, :3])):
        raise InputError(f"Velodyne scan: {p} holds non-finite coordinates")
    return pts


def project_velodyne(points: np.ndarray, P_velo_to_img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """LiDAR depth (H, W) float32 metres from a scan: ``x = P_velo_to_img @ [X; 1]`` (KITTI raw devkit:
    ``P_rect_02 @ R_rect_00 @ Tr_velo_to_cam``), depth = ``x[2]`` (z in rectified camera 2), 0 = no return.

    Convention (the KITTI devkit's, as its MATLAB projection and the depth benchmark's maps do it): a return
    lands in the pixel ``(round(x[0] / x[2]) - 1, round(x[1] / x[2]) - 1)`` counted from 0 (MATLAB's
    1-based index of the rounded coordinate), rounding half up; only returns in front of the camera
    (``x[2] > 0``) and inside the image are kept, and of the returns in one pixel the nearest.

    Args:
        points: (N, 3+) Velodyne points, metres (further columns, the reflectance, are not used).
        P_velo_to_img: (3, 4) projection from Velodyne coordinates to pixels.
        size: (H, W) of the image.
    """
    H, W = int(size[0]), int(size[1])
    X = np.asarray(points, dtype=np.float64)[:, :3]
    x = np.asarray(P_velo_to_img, dtype=np.float64) @ np.vstack([X.T, np.ones(len(X))])
    z = x[2]
    front = z > 0
    x, z = x[:, front], z[front]
    col = np.floor(x[0] / z + 0.5).astype(np.int64) - 1
    row = np.floor(x[1] / z + 0.5).astype(np.int64) - 1
    inside = (col >= 0) & (col < W) & (row >= 0) & (row < H)
    idx, z = row[inside] * W + col[inside], z[inside]
    order = np.lexsort((z, idx))  # by pixel, nearest first
    idx, z = idx[order], z[order]
    first = np.r_[True, idx[1:] != idx[:-1]] if len(idx) else np.zeros(0, bool)
    depth = np.zeros(H * W, np.float32)
    depth[idx[first]] = z[first]
    return depth.reshape(H, W)


@dataclass
class _Drive:
    date: str
    drive: int | str  # KITTI's drive number, or the folder's label where it is not a 4-digit number
    folder: Path
    camera: Camera
    P_rect_02: np.ndarray
    images: dict[int, Path]
    poses: dict[int, np.ndarray] | None  # raw frame -> T_w_cam2 (4, 4)
    bottoms: dict[int, tuple[np.ndarray, list[str]]] | None
    motion_source: str = ""  # "poses_cam0.txt" | "oxts (velocity)" | ...
    depth_files: dict[int, Path] | None = None  # raw frame -> LiDAR npz / depth PNG / Velodyne scan
    times: dict[int, float] | None = None  # raw frame -> seconds
    P_velo: np.ndarray | None = None  # (3, 4) Velodyne -> pixels, where scans are projected

    @property
    def label(self) -> str:
        """The drive's name in frame names and sequence keys: ``0023`` (a number) or the folder's label."""
        return f"{self.drive:04d}" if isinstance(self.drive, int) else self.drive


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
        drive: only this drive (``28``, ``"0028"``, a label such as ``"traffic"``, or the folder name);
            None = all drives.
        step: frame distance of a pair (current ``n``, previous ``n - step``).
        frames: at most this many pairs (None = all).
        only_labelled: only pairs whose current frame has stixel-bottom labels.
        camera_height: camera height above the road (metres).
        pitch: camera pitch (radians, positive = looking down), tilts the ground normal.
        oxts: positions of the OXTS poses, ``"velocity"`` (integrated; default, steadier) or
            ``"position"`` (GPS lat/lon), see :func:`oxts_poses`.

    Ground truth: ``motion`` (from ``poses_cam0.txt``, else from ``oxts/``), ``gt.depth`` (LiDAR
    depth of the current frame where ``proj_depth/`` or ``velodyne_points/`` has it, in the order of
    :data:`DEPTH_SOURCES`), ``gt.bottoms`` (from the label file,
    for labelled frames). ``meta["dt"]``: seconds between the two frames (timestamps, else 10 Hz).

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
        oxts: str = "velocity",
    ) -> None:
        self.root = require_dir(root, "kitti_raw data.root")
        if oxts not in OXTS_MODES:
            raise InputError(f"data.oxts: unknown mode {oxts!r}; choose one of {', '.join(OXTS_MODES)}")
        self.oxts = oxts
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
                if p.is_dir() and m and (drive is None or _drive_matches(drive, p.name, _drive_id(m.group(2)))):
                    out.append(p)
        if not out:
            want = f" matching drive {drive}" if drive is not None else ""
            raise InputError(f"kitti_raw: no DATE_drive_NNNN_sync folders{want} under {', '.join(map(str, dates))} "
                             f"(a drive folder: DATE_drive_NNNN_sync, or DATE_drive_LABEL_sync with a label of letters, "
                             f"digits and -)")
        return out

    def _load_drive(self, folder: Path, camera_height: float, pitch: float) -> _Drive:
        m = _DRIVE_RE.match(folder.name)
        assert m is not None
        date, drive = m.group(1), _drive_id(m.group(2))
        calib_path = folder.parent / CALIB_FILE
        calib = read_kitti_calib(require_file(calib_path, f"kitti_raw calibration of {date}"))
        P = projection_matrix(calib, P_RECT_KEY, calib_path)
        camera = make_camera(P[0, 0], P[1, 1], P[0, 2], P[1, 2], camera_height, pitch)
        images: dict[int, Path] = {}
        for f in list_images(folder / "image_02" / "data", f"kitti_raw images of {folder.name}"):
            if not f.stem.isdigit():
                raise InputError(f"kitti_raw: image {f} is not named by its raw frame number (e.g. 0000000042.png)")
            images[int(f.stem)] = f
        times = None
        if (folder / "image_02" / "timestamps.txt").exists():
            t = read_timestamps(folder / "image_02" / "timestamps.txt")
            times = {i: float(x) for i, x in enumerate(t)}
        poses, motion_source = None, ""
        if (folder / POSES_FILE).exists():
            poses, motion_source = self._read_poses(folder / POSES_FILE, cam2_offset(P)), POSES_FILE
        elif (folder / OXTS_DIR).is_dir():
            records = read_oxts(folder / OXTS_DIR)
            # Velocities are integrated over the *image* times: the synced OXTS record of a frame is
            # the one nearest to it, and the OXTS timestamps jitter while the camera runs steadily;
            # integrated over the OXTS times, |t| would alternate from pair to pair.
            oxts_times = times
            if oxts_times is None and (folder / "oxts" / "timestamps.txt").exists():
                ot = read_timestamps(folder / "oxts" / "timestamps.txt")
                oxts_times = {i: float(x) for i, x in enumerate(ot)}
            if oxts_times is not None:
                missing = sorted(set(records) - set(oxts_times))
                if missing:
                    raise InputError(f"oxts: {folder} has no timestamp for frame {missing[0]}")
            T_cam2_imu = imu_to_cam2(folder.parent, P)
            T_imu_cam2 = np.linalg.inv(T_cam2_imu)
            poses = {f: T @ T_imu_cam2 for f, T in oxts_poses(records, oxts_times, mode=self.oxts).items()}
            motion_source = f"oxts ({self.oxts})"
        bottoms = None
        if (folder / BOTTOMS_FILE).exists():
            if not isinstance(drive, int):
                raise InputError(f"kitti_raw: {folder / BOTTOMS_FILE} names drives by number; the folder {folder.name} "
                                 f"has none (DATE_drive_NNNN_sync)")
            bottoms = read_stixel_bottoms(folder / BOTTOMS_FILE, date, drive)
        depth_files, counts = self._depth_files(folder)
        P_velo = None
        if counts[VELODYNE_BIN_DIR]:
            P_velo = P @ velo_to_cam0_rect(folder.parent, f"projecting the Velodyne scans of {folder.name}")
        logger.info("kitti_raw %s: %d images, motion from %s, LiDAR depth for %d frames%s", folder.name, len(images),
                    motion_source or "nothing", len(depth_files),
                    "".join(f", {n} from {sub}" for sub, n in counts.items() if n) if depth_files else "")
        return _Drive(date, drive, folder, camera, P, images, poses, bottoms, motion_source, depth_files or None, times,
                      P_velo)

    @staticmethod
    def _depth_files(folder: Path) -> tuple[dict[int, Path], dict[Path, int]]:
        """Raw frame -> the LiDAR depth file it takes (the first of :data:`DEPTH_SOURCES` that has the frame),
        and how many frames take each source."""
        depth_files: dict[int, Path] = {}
        counts: dict[Path, int] = {}
        for sub, pattern in DEPTH_SOURCES:
            counts[sub] = 0
            for f in sorted((folder / sub).glob(pattern)) if (folder / sub).is_dir() else []:
                if not f.stem.isdigit():
                    raise InputError(f"kitti_raw: depth file {f} is not named by its raw frame number")
                if int(f.stem) not in depth_files:
                    depth_files[int(f.stem)] = f
                    counts[sub] += 1
        return depth_files, counts

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

    # --- sequences (keyframes) ------------------------------------------------------------------
    def _sequence_key(self, item: _Pair) -> str:
        return f"kitti_raw/{item.drive.date}_drive_{item.drive.label}"

    def _back(self, item: _Pair, back: int) -> _Pair | None:
        prev = item.frame - int(back) * self.step
        return _Pair(item.drive, item.frame, prev) if prev in item.drive.images else None

    def _pair_dt(self, item: _Pair) -> float:
        d = item.drive
        if d.times is not None and item.frame in d.times and item.frame_prev in d.times:
            return d.times[item.frame] - d.times[item.frame_prev]
        return (item.frame - item.frame_prev) / KITTI_RAW_FPS

    def _pair_motion(self, item: _Pair) -> Motion | None:
        d = item.drive
        if d.poses is None or item.frame not in d.poses or item.frame_prev not in d.poses:
            return None
        return relative_motion(d.poses[item.frame], d.poses[item.frame_prev])

    def _prev_name(self, item: _Pair) -> str:
        return f"{item.drive.date}_drive_{item.drive.label}_{item.frame_prev:010d}"

    def _load(self, item: _Pair) -> FramePair:
        d = item.drive
        image, image_prev = read_image_pair(d.images[item.frame], d.images[item.frame_prev])
        motion = self._pair_motion(item)
        if motion is None and d.poses is not None:
            logger.warning("kitti_raw: %s lacks frame %d or %d: no ground-truth motion for this pair",
                           d.motion_source, item.frame, item.frame_prev)
        gt = GroundTruth()
        depth_from = None
        if d.depth_files is not None and item.frame in d.depth_files:
            f = d.depth_files[item.frame]
            depth_from = str(f.parent.relative_to(d.folder))
            if f.suffix == ".npz":
                depth = read_lidar_npz(f)
            elif f.suffix == ".bin":
                assert d.P_velo is not None
                depth = project_velodyne(read_velodyne_bin(f), d.P_velo, tuple(image.shape[-2:]))  # type: ignore[arg-type]
            else:
                depth = read_depth_png(f)
            if depth.shape != tuple(image.shape[-2:]):
                raise InputError(f"kitti_raw: depth {f} is {depth.shape[1]}x{depth.shape[0]}, image "
                                 f"{d.images[item.frame]} is {image.shape[-1]}x{image.shape[-2]}")
            gt.depth = torch.from_numpy(depth)
        dt = self._pair_dt(item)
        meta: dict = {"source": "kitti_raw", "date": d.date, "drive": d.drive, "frame": item.frame,
                      "frame_prev": item.frame_prev, "path": str(d.images[item.frame]),
                      "path_prev": str(d.images[item.frame_prev]), "dt": dt, "name_prev": self._prev_name(item),
                      "sequence": self._sequence_key(item), "motion_source": d.motion_source}
        if depth_from is not None:
            meta["depth_from"] = depth_from
        if d.bottoms is not None and item.frame in d.bottoms:
            pts, splits = d.bottoms[item.frame]
            gt.bottoms = torch.from_numpy(pts.copy())
            meta["bottoms_split"] = sorted(set(splits))
        return FramePair(
            image=image, image_prev=image_prev, camera=d.camera, motion=motion, gt=gt,
            name=f"{d.date}_drive_{d.label}_{item.frame:010d}", meta=meta,
        )


def _drive_id(label: str) -> int | str:
    """A drive folder's label as its id: KITTI's 4-digit number as an int, any other label as it is."""
    return int(label) if len(label) == 4 and label.isdigit() else label


def _drive_matches(want: int | str, folder_name: str, drive: int | str) -> bool:
    s = str(want)
    if s in (folder_name, str(drive)):
        return True
    return s.isdigit() and isinstance(drive, int) and int(s) == drive
