"""Writing images, 16-bit depth PNGs and PLY point clouds (and reading the last two back).

Images are written with OpenCV (and read by :func:`monostixels.data._readers.read_rgb`, the package's one
image reader); the conversion BGR <-> RGB happens at that boundary, so everything inside the package
is RGB. Failures raise :class:`InputError` naming the
file (docs/conventions.md, section 7).
"""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import torch

from monostixels._checks import InputError, check_shape
from monostixels.core.geometry import pixel_rays

__all__ = [
    "KITTI_DEPTH_PNG_SCALE",
    "write_image",
    "write_depth_png16",
    "read_depth_png16",
    "depth_to_points",
    "write_ply",
    "read_ply",
]

logger = logging.getLogger(__name__)

#: KITTI depth PNGs store ``uint16 = depth_m * 256``, 0 = no depth (KITTI depth completion
#: devkit readme: "depth(u,v) = ((float)I(u,v))/256.0; valid(u,v) = I(u,v)>0").
KITTI_DEPTH_PNG_SCALE = 256.0
_UINT16_MAX = np.iinfo(np.uint16).max
_UINT8_MAX = 255.0

# PLY property types we read (PLY format spec, Turk 1994) -> numpy little-endian dtypes.
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
}


def write_image(path: str | Path, rgb: np.ndarray | torch.Tensor) -> Path:
    """Write an RGB image (H, W, 3) uint8 (or grey (H, W) uint8 / uint16), creating parent folders.

    Returns:
        The path written.

    Raises:
        InputError: wrong array, or OpenCV could not write the file (the message names it).
    """
    p = Path(path)
    arr = rgb.detach().cpu().numpy() if isinstance(rgb, torch.Tensor) else np.asarray(rgb)
    if arr.ndim == 3 and arr.shape[2] == 3 and arr.dtype == np.uint8:
        out = cv2.cvtColor(np.ascontiguousarray(arr), cv2.COLOR_RGB2BGR)
    elif arr.ndim == 2 and arr.dtype in (np.uint8, np.uint16):
        out = np.ascontiguousarray(arr)
    else:
        raise InputError(f"image for {p}: expected (H, W, 3) uint8 RGB or (H, W) uint8/uint16, got {arr.shape} {arr.dtype}")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        ok = cv2.imwrite(str(p), out)
    except (OSError, cv2.error) as exc:
        raise InputError(f"image file {p}: could not write it ({exc})") from exc
    if not ok:
        raise InputError(f"image file {p}: could not write it (unknown extension or unwritable folder)")
    return p


def write_depth_png16(path: str | Path, depth: torch.Tensor | np.ndarray) -> Path:
    """Write depth (H, W) metres as a KITTI-style 16-bit PNG: ``round(depth * 256)``, 0 = invalid.

    Non-finite and ``<= 0`` depths are written as 0 (invalid). Depths beyond the format's range
    (65535 / 256 = 255.996 m) are saturated to it, with a warning; tiny positive depths are
    written as 1 (1/256 m), never as 0, so a valid pixel stays valid.
    """
    d = depth.detach().cpu().double().numpy() if isinstance(depth, torch.Tensor) else np.asarray(depth, dtype=np.float64)
    if d.ndim != 2:
        raise InputError(f"depth for {path}: expected shape (H, W), got {d.shape}")
    valid = np.isfinite(d) & (d > 0)
    q = np.where(valid, np.round(np.where(valid, d, 0.0) * KITTI_DEPTH_PNG_SCALE), 0.0)
    over = q > _UINT16_MAX
    if over.any():
        logger.warning("%s: %d depths beyond %.3f m saturated", path, int(over.sum()), _UINT16_MAX / KITTI_DEPTH_PNG_SCALE)
    q = np.where(valid, np.clip(q, 1, _UINT16_MAX), 0).astype(np.uint16)
    return write_image(path, q)


def read_depth_png16(path: str | Path) -> torch.Tensor:
    """Read a KITTI-style 16-bit depth PNG as (H, W) float32 metres, 0 = invalid."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"depth file {p}: does not exist or is not a file")
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"depth file {p}: not a readable image")
    if img.ndim != 2 or img.dtype != np.uint16:
        raise InputError(f"depth file {p}: expected a single-channel 16-bit PNG, got {img.shape} {img.dtype}")
    return torch.from_numpy(img.astype(np.float32) / KITTI_DEPTH_PNG_SCALE)


def depth_to_points(
    depth: torch.Tensor,
    K: torch.Tensor,
    image: torch.Tensor | None = None,
    *,
    max_depth: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Back-project the valid pixels of a depth map into the current camera frame.

    Convention: ``X = z K^-1 (u, v, 1)``; camera x right, y down, z forward (metres).

    Args:
        depth: (H, W) depth z, metres; ``<= 0``, NaN, inf (and ``> max_depth``) are skipped.
        K: (3, 3) intrinsics.
        image: (3, H, W) float RGB in [0, 1] for the colours, or None (grey).
        max_depth: optional far limit, metres.

    Returns:
        ``points`` (N, 3) float32 metres and ``colors`` (N, 3) uint8 RGB, row-major pixel order.
    """
    check_shape(depth, ["H", "W"], "depth")
    check_shape(K, [3, 3], "K")
    H, W = depth.shape
    if image is not None:
        check_shape(image, [3, H, W], "image")
    d = depth.detach().double()
    valid = torch.isfinite(d) & (d > 0)
    if max_depth is not None:
        valid &= d <= max_depth
    v, u = torch.nonzero(valid, as_tuple=True)
    rays = pixel_rays(K.double(), u.double(), v.double())  # N x 3, z = 1
    pts = (rays * d[v, u][:, None]).float().numpy()
    if image is None:
        cols = np.full((pts.shape[0], 3), 128, dtype=np.uint8)
    else:
        rgb = image.detach().float().clamp(0, 1)[:, v, u].T  # N x 3
        cols = (rgb * _UINT8_MAX + 0.5).to(torch.uint8).numpy()
    return pts, cols


def write_ply(path: str | Path, points: np.ndarray | torch.Tensor, colors: np.ndarray | torch.Tensor) -> Path:
    """Write a coloured point cloud as binary little-endian PLY (MeshLab / Open3D compatible).

    Args:
        path: output file (parent folders are created).
        points: (N, 3) float, metres.
        colors: (N, 3) uint8 RGB.

    Returns:
        The path written.
    """
    p = Path(path)
    pts = points.detach().cpu().numpy() if isinstance(points, torch.Tensor) else np.asarray(points)
    cols = colors.detach().cpu().numpy() if isinstance(colors, torch.Tensor) else np.asarray(colors)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points for {p}: expected shape (N, 3), got {pts.shape}")
    if cols.shape != pts.shape:
        raise InputError(f"colors for {p}: expected shape {pts.shape} like points, got {cols.shape}")
    if cols.dtype != np.uint8:
        raise InputError(f"colors for {p}: expected uint8 RGB, got {cols.dtype}")
    if not np.isfinite(pts).all():
        raise InputError(f"points for {p}: contain NaN/inf")
    n = pts.shape[0]
    rec = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    rec["red"], rec["green"], rec["blue"] = cols[:, 0], cols[:, 1], cols[:, 2]
    header = (
        "ply\n"
        "format binary_little_endian 1.0\n"
        "comment monostixels point cloud: camera frame x right, y down, z forward (metres)\n"
        f"element vertex {n}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        "end_header\n"
    )
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        with open(p, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(rec.tobytes())
    except OSError as exc:
        raise InputError(f"PLY file {p}: could not write it ({exc})") from exc
    return p


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read the vertices of a binary little-endian PLY: ``points`` (N, 3) float32, ``colors`` (N, 3) uint8 or None.

    Only the ``vertex`` element is read, and it must be the first element (as :func:`write_ply`
    and most point-cloud tools write it).
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise InputError(f"PLY file {p}: cannot read it ({exc})") from exc
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise InputError(f"PLY file {p}: no PLY header")
    lines = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise InputError(f"PLY file {p}: only binary_little_endian 1.0 is supported")
    n, fields, current = 0, [], None
    for line in lines:
        tok = line.split()
        if tok and tok[0] == "element":
            if current is None and tok[1] != "vertex":
                raise InputError(f"PLY file {p}: the first element must be 'vertex'")
            current = tok[1]
            if current == "vertex":
                n = int(tok[2])
        elif tok and tok[0] == "property" and current == "vertex":
            if tok[1] == "list" or tok[1] not in _PLY_TYPES:
                raise InputError(f"PLY file {p}: unsupported vertex property {line!r}")
            fields.append((tok[2], _PLY_TYPES[tok[1]]))
    rec = np.frombuffer(data, dtype=np.dtype(fields), count=n, offset=end + len(b"end_header\n"))
    pts = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float32)
    names = rec.dtype.names or ()
    cols = np.stack([rec["red"], rec["green"], rec["blue"]], axis=1).astype(np.uint8) if "red" in names else None
    return pts, cols
