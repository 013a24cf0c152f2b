"""Pictures: depth, semantic and flow colour maps, stixel overlays and paper-style figures.

All functions return RGB ``uint8`` arrays (H, W, 3); files are written with OpenCV through
:func:`monostixels.io.write_image` (RGB -> BGR at that boundary). No screen is needed: figures use
matplotlib's Agg canvas directly (no pyplot state).

Colour conventions (paper figures, SPEC section 2): depth is coloured by *inverse* depth with
matplotlib's ``jet``: close = red, far = dark blue, invalid (``<= 0``, NaN, inf, or 0 = no ground
truth) = black. Semantic classes use the Cityscapes palette (:data:`monostixels.classes.PALETTE`).
Optical flow uses the Middlebury colour wheel (Baker et al., "A Database and Evaluation
Methodology for Optical Flow", IJCV 2011).
"""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from monostixels._checks import InputError
from monostixels.classes import IGNORE_LABEL, PALETTE, TYPE_PALETTE
from monostixels.stixels import paint_index_map

__all__ = [
    "image_to_uint8",
    "COLORMAP_MIN_DEPTH_M",
    "COLORMAP_MAX_DEPTH_M",
    "depth_colormap",
    "semantic_colormap",
    "flow_colormap",
    "make_flow_colorwheel",
    "stixel_overlay",
    "paper_figure",
]

logger = logging.getLogger(__name__)

#: Default depth range of the colour map (metres): inverse depths 1/3 .. 1/80 span red .. dark
#: blue (conf/eval/default.yaml colormap_*); 80 m is the KITTI evaluation cap.
COLORMAP_MIN_DEPTH_M = 3.0
COLORMAP_MAX_DEPTH_M = 80.0
#: Middlebury colour wheel: number of hues in each transition (Baker et al. 2011, flowToColor):
#: red-yellow, yellow-green, green-cyan, cyan-blue, blue-magenta, magenta-red.
_WHEEL_SEGMENTS = (("RY", 15), ("YG", 6), ("GC", 4), ("CB", 11), ("BM", 13), ("MR", 6))
#: Colour of pixels with an unknown / invalid value.
_INVALID_RGB = (0, 0, 0)
#: Factor darkening a stixel's colour for its border.
_BORDER_SHADE = 0.5
_OVERLAY_MODES = ("type", "class", "depth")


def _to_numpy(x: torch.Tensor | np.ndarray, name: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    if isinstance(x, np.ndarray):
        return x
    raise InputError(f"{name}: expected a torch.Tensor or numpy array, got {type(x).__name__}")


def _jet(x: np.ndarray) -> np.ndarray:
    """matplotlib's ``jet`` of ``x`` in [0, 1] as float RGB (..., 3) in [0, 1]."""
    from matplotlib import colormaps

    return colormaps["jet"](x)[..., :3]


def depth_colormap(
    depth: torch.Tensor | np.ndarray,
    *,
    min_depth: float = COLORMAP_MIN_DEPTH_M,
    max_depth: float = COLORMAP_MAX_DEPTH_M,
) -> np.ndarray:
    """Colour a depth map by inverse depth (paper figures).

    ``1/depth`` is normalised so that ``1/max_depth -> 0`` (jet: dark blue) and
    ``1/min_depth -> 1`` (jet: dark red); depths outside ``[min_depth, max_depth]`` saturate.

    Args:
        depth: (H, W) depth z, metres. ``<= 0``, NaN and inf are invalid (black): negative
            triangulations, sky, and 0 = no ground truth.
        min_depth: depth shown in the reddest colour, metres.
        max_depth: depth shown in the darkest blue, metres.

    Returns:
        (H, W, 3) uint8 RGB.
    """
    d = _to_numpy(depth, "depth").astype(np.float64)
    if d.ndim != 2:
        raise InputError(f"depth: expected shape (H, W), got {d.shape}")
    if not (0 < min_depth < max_depth and math.isfinite(max_depth)):
        raise InputError(f"min_depth/max_depth: need 0 < min_depth < max_depth, got {min_depth}, {max_depth}")
    valid = np.isfinite(d) & (d > 0)
    inv = np.where(valid, 1.0 / np.where(valid, d, 1.0), 0.0)
    lo, hi = 1.0 / max_depth, 1.0 / min_depth
    x = np.clip((inv - lo) / (hi - lo), 0.0, 1.0)
    rgb = (_jet(x) * 255.0 + 0.5).astype(np.uint8)
    rgb[~valid] = _INVALID_RGB
    return rgb


def semantic_colormap(labels: torch.Tensor | np.ndarray) -> np.ndarray:
    """Colour class ids (H, W) 0..9 with the Cityscapes palette; 255 / unknown ids are black.

    Returns:
        (H, W, 3) uint8 RGB.
    """
    lab = _to_numpy(labels, "labels")
    if lab.ndim != 2:
        raise InputError(f"labels: expected shape (H, W), got {lab.shape}")
    if np.issubdtype(lab.dtype, np.floating):
        raise InputError("labels: expected integer class ids, got floating point")
    lut = np.zeros((256, 3), dtype=np.uint8)
    lut[: len(PALETTE)] = np.asarray(PALETTE, dtype=np.uint8)
    lab = lab.astype(np.int64)
    known = (lab >= 0) & (lab < len(PALETTE))
    return lut[np.where(known, lab, IGNORE_LABEL)]


def make_flow_colorwheel() -> np.ndarray:
    """The Middlebury colour wheel (55, 3) float in [0, 255], hue by hue (Baker et al. 2011)."""
    rows = []
    for name, n in _WHEEL_SEGMENTS:
        ramp = np.arange(n, dtype=np.float64) / n * 255.0
        full = np.full(n, 255.0)
        zero = np.zeros(n)
        seg = {
            "RY": (full, ramp, zero),          # red -> yellow
            "YG": (255.0 - ramp, full, zero),  # yellow -> green
            "GC": (zero, full, ramp),          # green -> cyan
            "CB": (zero, 255.0 - ramp, full),  # cyan -> blue
            "BM": (ramp, zero, full),          # blue -> magenta
            "MR": (full, zero, 255.0 - ramp),  # magenta -> red
        }[name]
        rows.append(np.stack(seg, axis=1))
    return np.concatenate(rows, axis=0)


def flow_colormap(flow: torch.Tensor | np.ndarray, *, max_flow: float | None = None) -> np.ndarray:
    """Colour optical flow (2, H, W) with the Middlebury colour wheel.

    Hue encodes direction, saturation the magnitude relative to ``max_flow`` (default: the
    largest finite magnitude in the image). Convention as in the Middlebury code: the angle is
    ``atan2(-f_v, -f_u)``, so flow pointing right is red, down orange-yellow, left cyan-blue and
    up blue-magenta (v grows downward).
    Non-finite flow is black.

    Args:
        flow: (2, H, W) flow (u, v components), pixels.
        max_flow: magnitude shown fully saturated, pixels.

    Returns:
        (H, W, 3) uint8 RGB.
    """
    f = _to_numpy(flow, "flow").astype(np.float64)
    if f.ndim != 3 or f.shape[0] != 2:
        raise InputError(f"flow: expected shape (2, H, W), got {f.shape}")
    fu, fv = f[0], f[1]
    valid = np.isfinite(fu) & np.isfinite(fv)
    fu = np.where(valid, fu, 0.0)
    fv = np.where(valid, fv, 0.0)
    mag = np.hypot(fu, fv)
    if max_flow is None:
        max_flow = float(mag[valid].max()) if valid.any() else 0.0
    scale = max_flow if max_flow > 0 else 1.0
    rad = np.clip(mag / scale, 0.0, 1.0)
    wheel = make_flow_colorwheel()
    ncols = wheel.shape[0]
    angle = np.arctan2(-fv, -fu) / np.pi  # -1..1
    fk = (angle + 1.0) / 2.0 * (ncols - 1)
    k0 = np.floor(fk).astype(np.int64)
    k1 = (k0 + 1) % ncols
    w = (fk - k0)[..., None]
    col = ((1 - w) * wheel[k0] + w * wheel[k1]) / 255.0  # H x W x 3
    # Saturation grows with the magnitude: white at zero flow, the wheel colour at max_flow.
    col = 1.0 - rad[..., None] * (1.0 - col)
    rgb = (col * 255.0 + 0.5).astype(np.uint8)
    rgb[~valid] = _INVALID_RGB
    return rgb


def image_to_uint8(image: torch.Tensor | np.ndarray) -> np.ndarray:
    """(3, H, W) float RGB in [0, 1] (or (H, W, 3) uint8) -> (H, W, 3) uint8."""
    img = _to_numpy(image, "image")
    if img.ndim == 3 and img.shape[0] == 3 and img.dtype != np.uint8:
        return (np.clip(img.transpose(1, 2, 0), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8:
        return img
    raise InputError(f"image: expected (3, H, W) float RGB in [0, 1] or (H, W, 3) uint8, got {img.shape} {img.dtype}")


def _stixel_index_map(stixels: Any, H: int, W: int) -> np.ndarray:
    """(H, W) int64 index of the stixel covering each pixel, -1 where none."""
    arrays = [torch.as_tensor(_to_numpy(getattr(stixels, k), f"stixels.{k}")) for k in ("column", "v_top", "v_bottom")]
    return paint_index_map(*arrays, int(stixels.column_width), (H, W)).numpy()


def stixel_overlay(
    image: torch.Tensor | np.ndarray,
    stixels: Any,
    *,
    mode: str = "type",
    alpha: float = 0.5,
    min_depth: float = COLORMAP_MIN_DEPTH_M,
    max_depth: float = COLORMAP_MAX_DEPTH_M,
) -> np.ndarray:
    """Draw stixels as filled rectangles blended over the image, each with a thin border.

    Convention: stixel column ``c`` spans ``u in [c * w, min((c + 1) * w, W))`` and rows
    ``v_top .. v_bottom`` inclusive. Border pixels (1 px: the top row of each stixel, its bottom
    row where no stixel follows below, and where the fill colour changes to the left) are drawn
    opaque in a darker shade of the stixel colour; neighbouring columns of equal colour merge
    into one outlined region.

    Args:
        image: (3, H, W) float RGB in [0, 1] (or (H, W, 3) uint8).
        stixels: object with ``column_width``, ``image_size`` (H, W) and flat (N,) tensors
            ``column``, ``v_top``, ``v_bottom``, ``type``, ``cls``, ``depth`` (metres)
            (:class:`monostixels.stixels.StixelWorld`).
        mode: ``"type"`` (ground / static / dynamic / sky colours), ``"class"`` (Cityscapes
            palette) or ``"depth"`` (inverse-depth jet; sky / invalid black).
        alpha: opacity of the fill, 0..1.
        min_depth, max_depth: colour-map range for ``mode="depth"``, metres.

    Returns:
        (H, W, 3) uint8 RGB.
    """
    if mode not in _OVERLAY_MODES:
        raise InputError(f"mode: expected one of {_OVERLAY_MODES}, got {mode!r}")
    if not 0.0 <= alpha <= 1.0:
        raise InputError(f"alpha: expected a value in [0, 1], got {alpha}")
    img = image_to_uint8(image)
    H, W = img.shape[:2]
    size = tuple(int(s) for s in stixels.image_size)
    if size != (H, W):
        raise InputError(f"stixels.image_size {size} differs from the image size {(H, W)} (H, W)")
    idx = _stixel_index_map(stixels, H, W)
    n = int(np.asarray(_to_numpy(stixels.column, "stixels.column")).size)
    if mode == "type":
        key = _to_numpy(stixels.type, "stixels.type").astype(np.int64).reshape(-1)
        colours = np.asarray(TYPE_PALETTE, dtype=np.uint8)[np.clip(key, 0, len(TYPE_PALETTE) - 1)]
    elif mode == "class":
        key = _to_numpy(stixels.cls, "stixels.cls").astype(np.int64).reshape(-1)
        colours = semantic_colormap(key[None, :])[0]
    else:
        depth = _to_numpy(stixels.depth, "stixels.depth").astype(np.float64).reshape(-1)
        colours = depth_colormap(depth[None, :], min_depth=min_depth, max_depth=max_depth)[0]
    if colours.shape[0] != n:
        raise InputError(f"stixels: {mode} attribute has {colours.shape[0]} entries, expected {n}")
    covered = idx >= 0
    fill = colours[np.where(covered, idx, 0)].astype(np.float64)
    out = img.astype(np.float64)
    out[covered] = (1.0 - alpha) * out[covered] + alpha * fill[covered]
    # Border (1 px): the top row of every stixel, its bottom row where nothing is drawn below, and
    # where the fill colour changes to the left (neighbouring columns of the same colour merge,
    # so objects read as outlined regions).
    key = np.where(covered, (fill[..., 0].astype(np.int64) << 16) | (fill[..., 1].astype(np.int64) << 8)
                   | fill[..., 2].astype(np.int64), -1)
    pad = np.pad(idx, ((1, 1), (0, 0)), constant_values=-1)
    kpad = np.pad(key, ((0, 0), (1, 0)), constant_values=-1)
    border = covered & ((pad[:-2] != idx) | (pad[2:] == -1) | (kpad[:, :-1] != key))
    out[border] = _BORDER_SHADE * fill[border]
    return (out + 0.5).astype(np.uint8)


def paper_figure(
    rows: Sequence[tuple[str, np.ndarray]],
    path: str | Path,
    ncols: int = 4,
    *,
    panel_width_in: float = 4.0,
    dpi: int = 150,
) -> Path:
    """Compose labelled panels into one PNG, like the paper's figures.

    Panels are laid out row-major, ``ncols`` per row (the paper: Image / Ground Truth /
    Baseline - SFM / Ours - Mono-Stixels), each titled with its label.

    Args:
        rows: ``(label, rgb)`` panels, ``rgb`` (H, W, 3) uint8.
        path: output PNG path (parent folders are created).
        ncols: panels per row.
        panel_width_in: width of one panel, inches.
        dpi: resolution of the figure.

    Returns:
        The path written.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from monostixels.io import write_image

    if len(rows) == 0:
        raise InputError("rows: no panels to draw")
    if ncols < 1:
        raise InputError(f"ncols: must be >= 1, got {ncols}")
    for label, rgb in rows:
        if not (isinstance(rgb, np.ndarray) and rgb.ndim == 3 and rgb.shape[2] == 3):
            raise InputError(f"panel {label!r}: expected an (H, W, 3) RGB array")
    ncols = min(ncols, len(rows))
    nrows = -(-len(rows) // ncols)
    aspect = max(r.shape[0] / r.shape[1] for _, r in rows)
    fig = Figure(figsize=(panel_width_in * ncols, (panel_width_in * aspect + 0.35) * nrows), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    for i, (label, rgb) in enumerate(rows):
        ax = fig.add_subplot(nrows, ncols, i + 1)
        ax.imshow(rgb, interpolation="nearest")
        ax.set_title(label, fontsize=10)
        ax.set_axis_off()
    fig.tight_layout(pad=0.3)
    canvas.draw()
    buf = np.asarray(canvas.buffer_rgba())[..., :3].copy()
    return write_image(path, buf)
