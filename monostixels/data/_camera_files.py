"""The camera's files, each failing with an ``InputError`` that names the file (docs/conventions.md,
section 7): KITTI calibration files, intrinsics files (with the lens distortion and the image size they
were made for) and pose files; the camera and the camera motion they give.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Mapping, NamedTuple, Sequence

import numpy as np
import torch

from monostixels._checks import InputError
from monostixels.data._readers import require_file
from monostixels.core.geometry import Camera, Motion, intrinsics

__all__ = [
    "read_kitti_calib",
    "projection_matrix",
    "DISTORTION_LENGTHS",
    "read_intrinsics_file",
    "read_distortion",
    "read_intrinsics_size",
    "check_intrinsics_size",
    "read_poses_file",
    "relative_motion",
    "make_camera",
]


def read_kitti_calib(path: str | Path) -> dict[str, np.ndarray]:
    """Parse a KITTI calibration file of ``key: v1 v2 ...`` lines.

    Lines whose values are not all numbers (e.g. ``calib_time: 09-Jan-2012 13:59:33``) are skipped.

    Returns:
        key -> float64 vector of that line's numbers.

    Raises:
        InputError: the file is missing or has no numeric entry.
    """
    p = require_file(path, "calibration")
    out: dict[str, np.ndarray] = {}
    for line in p.read_text(errors="replace").splitlines():
        if ":" not in line:
            continue
        key, _, rest = line.partition(":")
        try:
            vals = np.array([float(x) for x in rest.split()], dtype=np.float64)
        except ValueError:
            continue
        if vals.size:
            out[key.strip()] = vals
    if not out:
        raise InputError(f"calibration: {p} has no 'key: numbers' lines (not a KITTI calibration file)")
    return out


def projection_matrix(calib: Mapping[str, np.ndarray], key: str, path: str | Path) -> np.ndarray:
    """The 3x4 matrix ``key`` (e.g. ``P_rect_02``) of a parsed calibration file, checked.

    Raises:
        InputError: the key is missing, has the wrong number of values, or is not a pinhole
            projection (fx, fy > 0, finite).
    """
    if key not in calib:
        raise InputError(f"calibration: {path} has no {key} entry (have {', '.join(sorted(calib))})")
    v = calib[key]
    if v.size != 12 or not np.all(np.isfinite(v)):
        raise InputError(f"calibration: {path} entry {key} must hold 12 finite numbers, got {v.size}")
    P = v.reshape(3, 4)
    if not (P[0, 0] > 0 and P[1, 1] > 0 and P[2, 2] == 1.0):
        raise InputError(f"calibration: {path} entry {key} is not a rectified projection matrix: {P.tolist()}")
    return P


_INTRINSIC_KEYS = ("fx", "fy", "cx", "cy")


#: Lengths of an OpenCV distortion vector accepted in an intrinsics file: ``k1 k2 p1 p2`` (4),
#: ``k1 k2 p1 p2 k3`` (5, what ``monostixels calibrate`` writes), ``k1 k2 p1 p2 k3 k4 k5 k6`` (8, the
#: rational model).
DISTORTION_LENGTHS: tuple[int, ...] = (4, 5, 8)


def read_intrinsics_file(path: str | Path) -> tuple[float, float, float, float]:
    """Read pinhole intrinsics ``(fx, fy, cx, cy)`` (pixels) from a small file.

    Accepted formats (chosen by the file's content, not only its ending):

    - YAML or JSON mapping with keys ``fx, fy, cx, cy`` (``fy`` may be omitted: ``fy = fx``), or
      with a key ``K`` holding the 3x3 matrix (nested list or 9 numbers, row-major); optionally a key
      ``distortion`` with the lens distortion coefficients (see :func:`read_distortion`) and keys
      ``width``, ``height``: the image size they hold for (see :func:`check_intrinsics_size`);
    - text with ``key: value`` / ``key = value`` lines for ``fx, fy, cx, cy`` (and ``distortion``);
    - text with just numbers: 4 numbers ``fx fy cx cy`` or 9 numbers (K row-major).

    Raises:
        InputError: missing file, unparsable content, missing keys, non-positive focal lengths, or a
            malformed ``distortion`` entry.
    """
    return _read_intrinsics(path).pinhole


def read_distortion(path: str | Path) -> np.ndarray | None:
    """The lens distortion coefficients of an intrinsics file (its ``distortion`` key), if any.

    Convention: OpenCV's order and model, ``distortion: [k1, k2, p1, p2, k3]`` (radial ``k``,
    tangential ``p``; 4 or 8 numbers are accepted too, see :data:`DISTORTION_LENGTHS`), for the
    normalised coordinates of the file's ``fx, fy, cx, cy``. Barrel distortion (dashcams) has
    ``k1 < 0``.

    Returns:
        (N,) float64 coefficients, N in :data:`DISTORTION_LENGTHS`; None where the file has no
        ``distortion`` key (or ``distortion: null``) or holds only numbers.

    Raises:
        InputError: as :func:`read_intrinsics_file`; a ``distortion`` entry that is not a list of
            4, 5 or 8 finite numbers (naming the file and the key).
    """
    return _read_intrinsics(path).distortion


def read_intrinsics_size(path: str | Path) -> tuple[int, int] | None:
    """(H, W) pixels that an intrinsics file says it holds for (its ``width`` and ``height`` keys), or None.

    Raises:
        InputError: as :func:`read_intrinsics_file`; ``width`` / ``height`` that are not positive integers.
    """
    return _read_intrinsics(Path(path).expanduser()).size


def check_intrinsics_size(path: str | Path, size: tuple[int, int], what: str) -> None:
    """Fail when an intrinsics file says which image size it holds for and ``size`` differs.

    The optional keys ``width`` and ``height`` (pixels; ``monostixels calibrate`` writes them) give
    that size: intrinsics and distortion of one size do not fit frames of another (a different
    sensor mode may crop as well as scale), so they are not rescaled silently.

    Args:
        path: the intrinsics file.
        size: (H, W) of the stored frames.
        what: the frames' name for the message (``"the video's frames"``).

    Raises:
        InputError: the sizes differ (both named), or ``width`` / ``height`` are not positive integers.
    """
    p = Path(path).expanduser()
    stated = read_intrinsics_size(p)
    if stated is not None and tuple(stated) != tuple(size):
        raise InputError(f"intrinsics: {p} holds for {stated[1]}x{stated[0]} images (width, height), {what} are "
                         f"{size[1]}x{size[0]}; calibrate at that size (or scale fx, fy, cx, cy and drop width, height)")


class _IntrinsicsFile(NamedTuple):
    pinhole: tuple[float, float, float, float]
    distortion: np.ndarray | None
    size: tuple[int, int] | None  # (H, W) from the width / height keys


def _read_intrinsics(path: str | Path) -> _IntrinsicsFile:
    p = require_file(path, "intrinsics")
    text = p.read_text(errors="replace")
    got = _parse_intrinsics(text, p)
    fx, fy, cx, cy = got.pinhole
    if not all(math.isfinite(v) for v in got.pinhole) or fx <= 0 or fy <= 0:
        raise InputError(f"intrinsics: {p} gives fx={fx}, fy={fy}, cx={cx}, cy={cy}; need finite values, fx, fy > 0")
    return got


def _parse_intrinsics(text: str, p: Path) -> _IntrinsicsFile:
    """(fx, fy, cx, cy), the distortion coefficients and the stated image size (None: not given) of an
    intrinsics file's text."""
    data: Any = None
    stripped = text.strip()
    if not stripped:
        raise InputError(f"intrinsics: {p} is empty")
    if stripped[0] in "{[":
        try:
            data = json.loads(stripped)
        except json.JSONDecodeError as e:
            raise InputError(f"intrinsics: {p} is not valid JSON ({e})") from e
    else:
        nums = stripped.replace(",", " ").split()
        try:
            numbers = [float(x) for x in nums]
        except ValueError:
            numbers = None
        if numbers is not None:
            return _IntrinsicsFile(_from_numbers(numbers, p), None, None)
        import yaml  # PyYAML ships with Hydra (omegaconf)

        try:
            data = yaml.safe_load(text.replace("=", ":"))
        except yaml.YAMLError as e:
            raise InputError(f"intrinsics: {p} is neither YAML/JSON nor 'fx fy cx cy' numbers ({e})") from e
    if isinstance(data, list):
        try:
            return _IntrinsicsFile(_from_numbers([float(x) for x in np.asarray(data, dtype=np.float64).ravel()], p),
                                   None, None)
        except (TypeError, ValueError) as e:
            raise InputError(f"intrinsics: {p} holds a list that is not numbers") from e
    if not isinstance(data, dict):
        raise InputError(f"intrinsics: {p} must be a mapping with fx, fy, cx, cy (or K)")
    distortion = _distortion(data.get("distortion"), p)
    size = _stated_size(data, p)
    if "K" in data:
        try:
            K = _from_numbers([float(x) for x in np.asarray(data["K"], dtype=np.float64).ravel()], p)
            return _IntrinsicsFile(K, distortion, size)
        except (TypeError, ValueError) as e:
            raise InputError(f"intrinsics: {p} entry K is not a 3x3 matrix of numbers") from e
    if "fy" not in data and "fx" in data:
        data = {**data, "fy": data["fx"]}
    missing = [k for k in _INTRINSIC_KEYS if k not in data]
    if missing:
        raise InputError(f"intrinsics: {p} lacks {', '.join(missing)} (need fx, fy, cx, cy in pixels, or K)")
    try:
        return _IntrinsicsFile(tuple(float(data[k]) for k in _INTRINSIC_KEYS), distortion, size)  # type: ignore[arg-type]
    except (TypeError, ValueError) as e:
        raise InputError(f"intrinsics: {p} has a non-numeric value among fx, fy, cx, cy") from e


def _stated_size(data: Mapping[str, Any], p: Path) -> tuple[int, int] | None:
    """(H, W) from the optional ``width`` and ``height`` keys of an intrinsics mapping."""
    if data.get("width") is None and data.get("height") is None:
        return None
    w, h = data.get("width"), data.get("height")
    if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in (w, h)):
        raise InputError(f"intrinsics: {p} keys width, height must both be positive integers (pixels), got {w!r}, {h!r}")
    return int(h), int(w)  # type: ignore[arg-type]


def _distortion(value: Any, p: Path) -> np.ndarray | None:
    """The ``distortion`` entry of an intrinsics mapping, checked (None when absent or null)."""
    if value is None:
        return None
    want = "a list of 5 numbers [k1, k2, p1, p2, k3] (OpenCV's order; 4 or 8 also accepted)"
    if not isinstance(value, (list, tuple)):
        raise InputError(f"intrinsics: {p} key distortion must be {want}, got {value!r}")
    try:
        d = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"intrinsics: {p} key distortion must be {want}; it holds a non-number") from e
    if d.ndim == 2 and 1 in d.shape:  # OpenCV prints its coefficients as a 1 x N matrix
        d = d.ravel()
    if d.ndim != 1 or d.size not in DISTORTION_LENGTHS:
        raise InputError(f"intrinsics: {p} key distortion holds {d.size} numbers; it must be {want}")
    if not np.all(np.isfinite(d)):
        raise InputError(f"intrinsics: {p} key distortion holds NaN/inf: {d.tolist()}")
    return d


def _from_numbers(numbers: Sequence[float], p: Path) -> tuple[float, float, float, float]:
    if len(numbers) == 4:
        return numbers[0], numbers[1], numbers[2], numbers[3]
    if len(numbers) == 9:
        K = np.asarray(numbers).reshape(3, 3)
        if K[0, 1] != 0 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
            raise InputError(f"intrinsics: {p} 3x3 matrix is not a pinhole K (no skew, last row 0 0 1): {K.tolist()}")
        return K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    raise InputError(f"intrinsics: {p} holds {len(numbers)} numbers; expected 4 (fx fy cx cy) or 9 (K)")


def read_poses_file(path: str | Path) -> tuple[list[str] | None, np.ndarray]:
    """Read camera-to-world poses ``T_w_cam`` (metres), one per line.

    Line formats (all lines of a file alike; ``#`` starts a comment):

    - 13 values: a frame id (e.g. the 10-digit KITTI raw frame number) then the 3x4 row-major
      ``T_w_cam`` (the ``poses_cam0.txt`` of the shared KITTI raw sample);
    - 12 values: the 3x4 row-major ``T_w_cam`` of the i-th frame (KITTI odometry format);
    - 16 values: the 4x4 row-major ``T_w_cam`` of the i-th frame.

    Returns:
        (ids, poses): ids = the frame ids as strings (13-value format) or None (order-based
        formats); poses = (N, 4, 4) float64 camera-to-world matrices.

    Raises:
        InputError: missing file, non-numeric values, mixed/unknown line lengths, or a rotation
            block that is not a rotation.
    """
    p = require_file(path, "poses")
    ids: list[str] = []
    mats: list[np.ndarray] = []
    width = None
    for ln, line in enumerate(p.read_text(errors="replace").splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        if width is None:
            width = len(parts)
            if width not in (12, 13, 16):
                raise InputError(f"poses: {p} line {ln} has {width} values; expected 12, 13 (id + 12) or 16")
        elif len(parts) != width:
            raise InputError(f"poses: {p} line {ln} has {len(parts)} values, earlier lines {width}")
        if width == 13:
            ids.append(parts[0])
            parts = parts[1:]
        try:
            v = np.array([float(x) for x in parts], dtype=np.float64)
        except ValueError as e:
            raise InputError(f"poses: {p} line {ln} holds a non-numeric value") from e
        T = np.eye(4)
        T[: v.size // 4] = v.reshape(-1, 4)
        if not np.all(np.isfinite(T)):
            raise InputError(f"poses: {p} line {ln} holds NaN/inf")
        if width == 16 and not np.allclose(T[3], [0, 0, 0, 1]):
            raise InputError(f"poses: {p} line {ln}: last row of a 4x4 pose must be 0 0 0 1")
        R = T[:3, :3]
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-3 or abs(np.linalg.det(R) - 1) > 1e-3:
            raise InputError(f"poses: {p} line {ln}: rotation block is not a rotation matrix")
        mats.append(T)
    if not mats:
        raise InputError(f"poses: {p} holds no poses")
    return (ids if width == 13 else None), np.stack(mats)


def relative_motion(T_w_cur: np.ndarray, T_w_prev: np.ndarray, offset: np.ndarray | None = None) -> Motion:
    """Camera motion of a pair from two camera-to-world poses (4, 4).

    Convention: ``X_prev = R X_cur + t`` (docs/conventions.md, section 2);
    ``T_prev_cur = T_w_prev^-1 T_w_cur``, ``R = T_prev_cur[:3, :3]``, ``t = T_prev_cur[:3, 3]``
    (metres). The rotation is re-orthonormalised (SVD) to remove the rounding of text files.
    ``offset`` (3,): the position of the image camera in the posed camera's frame, ``X_img = X_pose + offset``
    (the same orientation; KITTI camera 2 against camera-0 poses), or None.
    """
    T = np.linalg.solve(T_w_prev, T_w_cur)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))]) @ Vt  # a rotation, never a reflection
    t = T[:3, 3].copy()
    if offset is not None:
        # X_img_prev = R (X_img_cur - o) + t + o.
        t = t + (np.eye(3) - R) @ np.asarray(offset, dtype=np.float64)
    return Motion(R=torch.from_numpy(R), t=torch.from_numpy(np.ascontiguousarray(t)))


def make_camera(fx: float, fy: float, cx: float, cy: float, height: float, pitch: float = 0.0,
                ground_normal: np.ndarray | None = None) -> Camera:
    """Camera from intrinsics (pixels), mounting height (metres) and pitch (radians) or normal."""
    K = intrinsics(float(fx), float(fy), float(cx), float(cy))
    if ground_normal is not None:
        return Camera(K=K, height=float(height), ground_normal=torch.from_numpy(np.asarray(ground_normal, dtype=np.float64)))
    return Camera.from_pitch(K, height=float(height), pitch=float(pitch))
