"""File reading helpers of the data sources, each failing with an ``InputError`` that names the file
(docs/conventions.md, section 7): images, 16-bit PNG ground truth, masks, image folders.

Images are read with OpenCV and converted from BGR to RGB here, at the boundary.
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from pathlib import Path

import cv2
import numpy as np
import torch

from monostixels._checks import InputError, check_same_size

__all__ = [
    "IMAGE_EXTENSIONS",
    "MAX_U8",
    "require_dir",
    "require_file",
    "read_rgb",
    "read_image_pair",
    "read_png16",
    "read_mask_file",
    "list_images",
]


#: File name endings accepted as images (lower case).
IMAGE_EXTENSIONS: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".bmp", ".ppm", ".pgm", ".tif", ".tiff")


#: Largest value of an 8-bit / 16-bit image channel, used to scale images to [0, 1].
MAX_U8 = 255.0


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
        scale = MAX_U8
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
