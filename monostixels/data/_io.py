"""File reading helpers shared by the data sources, each failing with an ``InputError`` that names
the file (docs/conventions.md, section 7): images, 16-bit PNG ground truth, KITTI calibration files,
intrinsics files and pose files.

Images are read with OpenCV and converted from BGR to RGB here, at the boundary.
"""
from __future__ import annotations

import json
import logging
import math
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Any, Iterator, Mapping, NamedTuple, Sequence

import cv2
import numpy as np
import torch

from monostixels._checks import InputError, check_same_size
from monostixels.data.base import FramePair, PreviousFrame
from monostixels.core.geometry import Camera, Motion, intrinsics

__all__ = [
    "IMAGE_EXTENSIONS",
    "read_rgb",
    "read_png16",
    "read_image_pair",
    "list_images",
    "read_kitti_calib",
    "projection_matrix",
    "read_intrinsics_file",
    "read_distortion",
    "check_intrinsics_size",
    "read_mask_file",
    "DISTORTION_LENGTHS",
    "read_poses_file",
    "relative_motion",
    "make_camera",
    "require_dir",
    "require_file",
    "LazySource",
    "MAX_SKIPPED_FRAMES",
    "PairSkipped",
    "UnreadableFrame",
    "limit_frames",
]

logger = logging.getLogger(__name__)


#: File name endings accepted as images (lower case).
IMAGE_EXTENSIONS: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".bmp", ".ppm", ".pgm", ".tif", ".tiff")

#: Largest value of an 8-bit / 16-bit image channel, used to scale images to [0, 1].
_MAX_U8 = 255.0
_MAX_U16 = 65535.0


def require_dir(path: str | Path, what: str) -> Path:
    """Return ``path`` as a Path, or raise ``InputError`` naming ``what`` if it is not a folder."""
    if path is None or str(path) == "":
        raise InputError(f"{what}: no folder given (set it in the config, e.g. data.root=/path/to/data)")
    p = Path(path).expanduser()
    if not p.is_dir():
        raise InputError(f"{what}: folder {p} does not exist")
    return p


def require_file(path: str | Path, what: str) -> Path:
    """Return ``path`` as a Path, or raise ``InputError`` naming ``what`` if it is not a file."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise InputError(f"{what}: file {p} does not exist")
    return p


def read_rgb(path: str | Path) -> torch.Tensor:
    """Read an image file as float RGB.

    Grey images are replicated to three channels, an alpha channel is dropped, 16-bit images are
    scaled by 65535.

    Args:
        path: image file (any format OpenCV reads).

    Returns:
        (3, H, W) float32 RGB in [0, 1].

    Raises:
        InputError: the file is missing or OpenCV cannot decode it.
    """
    p = require_file(path, "image")
    img = _decoded(p)
    if img.dtype == np.uint8:
        scale = _MAX_U8
    elif img.dtype == np.uint16:
        scale = _MAX_U16
    else:
        raise InputError(f"image: {p} has unsupported pixel type {img.dtype} (expected 8 or 16 bit)")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    elif img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    else:
        raise InputError(f"image: {p} has {img.shape[2]} channels (expected 1, 3 or 4)")
    return torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1))).float() / scale


#: Decoded images kept (a sequence's frame is the current image of one pair and the previous image of
#: the next, or of the next few with keyframes): not decoded twice.
_DECODED_KEPT = 4
_decoded_cache: "OrderedDict[tuple[str, int, int], np.ndarray]" = OrderedDict()
_decoded_lock = threading.Lock()


def _decoded(p: Path) -> np.ndarray:
    """``cv2.imread(p, IMREAD_UNCHANGED)`` of an existing file, from the last few decoded ones when its
    path, size and modification time are the same (the array is not handed out: callers convert it)."""
    st = p.stat()
    key = (str(p.resolve()), st.st_mtime_ns, st.st_size)
    with _decoded_lock:
        img = _decoded_cache.get(key)
        if img is not None:
            _decoded_cache.move_to_end(key)
            return img
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise InputError(f"image: cannot read {p} (not an image file OpenCV can decode, or corrupt)")
    img.flags.writeable = False
    with _decoded_lock:
        _decoded_cache[key] = img
        while len(_decoded_cache) > _DECODED_KEPT:
            _decoded_cache.popitem(last=False)
    return img


def read_image_pair(path_cur: str | Path, path_prev: str | Path) -> tuple[torch.Tensor, torch.Tensor]:
    """Read the current and the previous image and check that they have the same size.

    Returns:
        (image, image_prev), each (3, H, W) float32 RGB in [0, 1].

    Raises:
        InputError: a file is unreadable, or the two images differ in size (both paths named).
    """
    img = read_rgb(path_cur)
    img_prev = read_rgb(path_prev)
    check_same_size(img, img_prev, f"image {path_cur} (current)", f"image {path_prev} (previous)")
    return img, img_prev


def read_png16(path: str | Path, channels: int) -> np.ndarray:
    """Read a 16-bit PNG ground-truth file (KITTI disparity / flow) without conversion.

    Args:
        path: the PNG.
        channels: expected channels (1 for disparity, 3 for flow).

    Returns:
        (H, W) or (H, W, 3) uint16 array; channel order as stored by OpenCV (BGR).
    """
    p = require_file(path, "ground-truth PNG")
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"ground-truth PNG: cannot read {p}")
    got = 1 if img.ndim == 2 else img.shape[2]
    if img.dtype != np.uint16 or got != channels:
        raise InputError(
            f"ground-truth PNG: {p} is {got}-channel {img.dtype}, expected {channels}-channel uint16 (KITTI format)"
        )
    return img


def read_mask_file(path: str | Path, size: tuple[int, int], what: str = "data.mask") -> np.ndarray:
    """Read a user's mask image: non-zero (in any colour channel; alpha is not looked at) = ignore.

    Args:
        path: the image (a PNG drawn on a frame as stored: before undistortion and ``data.resize``).
        size: (H, W) the frames' stored size, which the mask must have.
        what: the input's name for messages.

    Returns:
        (H, W) bool, True = ignore.

    Raises:
        InputError: missing or undecodable file, a size other than ``size`` (both sizes named), or a mask
            that ignores every pixel.
    """
    p = require_file(path, what)
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise InputError(f"{what}: cannot read {p} (not an image file OpenCV can decode)")
    H, W = size
    if img.shape[:2] != (H, W):
        raise InputError(f"{what}: {p} is {img.shape[1]}x{img.shape[0]} pixels, the frames are {W}x{H} "
                         f"(draw the mask on a frame as stored, before data.resize)")
    mask = (img[..., :3].max(axis=2) if img.ndim == 3 else img) > 0
    if mask.all():
        raise InputError(f"{what}: {p} ignores every pixel (non-zero = ignore; leave the pixels to use at 0)")
    return mask


def list_images(folder: str | Path, what: str = "image folder") -> list[Path]:
    """Image files of ``folder`` sorted by name; ``InputError`` when the folder is missing or empty."""
    d = require_dir(folder, what)
    files = sorted(p for p in d.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)
    if not files:
        raise InputError(f"{what}: {d} holds no image files ({', '.join(IMAGE_EXTENSIONS)})")
    return files


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
    stated = _read_intrinsics(p).size
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


class LazySource(Sequence[FramePair]):
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
