"""Pictures: depth, semantic and flow colour maps, stixel overlays and paper-style figures.

``run``'s picture is :func:`stixel_depth_overlay`: every object stixel a box in the colour of its
depth, the ground a translucent tint of its per-pixel depth, movers outlined with a motion arrow,
a legend of the depth scale, and frame notes such as a standing camera. The bird's-eye view is
:mod:`monostixels.output.bev`.

All functions return RGB ``uint8`` arrays (H, W, 3); files are written with OpenCV through
:func:`monostixels.output.io.write_image` (RGB -> BGR at that boundary). No screen is needed: figures use
matplotlib's Agg canvas directly (no pyplot state).

Colour conventions (paper figures, docs/conventions.md, section 2): depth is coloured by *inverse*
depth with matplotlib's ``jet``: close = red, far = dark blue, invalid (``<= 0``, NaN, inf, or 0 =
no ground truth) = black. Semantic classes use the Cityscapes palette
(:data:`monostixels.core.classes.PALETTE`). Optical flow uses the Middlebury colour wheel (Baker et al.,
"A Database and Evaluation Methodology for Optical Flow", IJCV 2011), drawn by torchvision's ``flow_to_image``.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from monostixels._checks import InputError
from monostixels.core.classes import DYNAMIC_OBJECT, GROUND, IGNORE_LABEL, PALETTE, STATIC_OBJECT, TYPE_PALETTE
from monostixels.core.geometry import pixel_rays
from monostixels.inputs.motion import NO_METRIC_MOTION, MotionKind
from monostixels.core.stixels import neighbours, paint_index_map
from monostixels.core.status import FrameStatus

__all__ = [
    "image_to_uint8",
    "COLORMAP_MIN_DEPTH_M",
    "COLORMAP_MAX_DEPTH_M",
    "depth_colormap",
    "semantic_colormap",
    "flow_colormap",
    "stixel_overlay",
    "stixel_depth_overlay",
    "mover_groups",
    "frame_notes",
    "draw_notes",
    "side_by_side",
    "paper_figure",
]

logger = logging.getLogger(__name__)

#: Default depth range of the colour map (metres): inverse depths 1/3 .. 1/80 span red .. dark
#: blue (conf/eval/default.yaml colormap_*); 80 m is the KITTI evaluation cap.
COLORMAP_MIN_DEPTH_M = 3.0
COLORMAP_MAX_DEPTH_M = 80.0
#: Colour of pixels with an unknown / invalid value.
_INVALID_RGB = (0, 0, 0)
#: Factor darkening a stixel's colour for its border.
_BORDER_SHADE = 0.5
_OVERLAY_MODES = ("type", "class", "depth")
#: Outline and arrow colour of moving objects (RGB): white reads on every colour of the jet map.
_MOVER_RGB = (255, 255, 255)
#: Outline and label of stixels closing within the time-to-collision warning (RGB).
_TTC_RGB = (255, 30, 30)
#: Motion arrows show a mover's displacement over this many frames (5 = 0.5 s at KITTI's 10 Hz):
#: one frame's motion is a few pixels.
MOTION_ARROW_FRAMES = 5.0
#: Fewest columns of a moving object that gets an arrow (a one-column sliver gets its outline only).
_ARROW_MIN_COLUMNS = 2
#: Longest motion arrow in an image, as a fraction of its width.
_ARROW_MAX_FRACTION = 0.08
#: Depth labels offered on the legend's scale (metres); those outside the colour-map range are dropped.
_LEGEND_TICKS_M = (1.0, 2.0, 3.0, 5.0, 10.0, 20.0, 40.0, 80.0, 150.0, 300.0)
#: Reference width (px) at which text is drawn at scale 1 (KITTI's 1242 px).
_TEXT_REF_WIDTH = 1242.0


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


def flow_colormap(flow: torch.Tensor | np.ndarray, *, max_flow: float | None = None) -> np.ndarray:
    """Colour optical flow (2, H, W) with the Middlebury colour wheel (torchvision's ``flow_to_image``).

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
    from monostixels._torchvision import torchvision

    f = _to_numpy(flow, "flow").astype(np.float64)
    if f.ndim != 3 or f.shape[0] != 2:
        raise InputError(f"flow: expected shape (2, H, W), got {f.shape}")
    valid = np.isfinite(f).all(axis=0)
    f = np.where(valid, f, 0.0)
    mag = np.hypot(f[0], f[1])
    if max_flow is None:
        max_flow = float(mag[valid].max()) if valid.any() else 0.0
    scale = max_flow if max_flow > 0 else 1.0
    # flow_to_image saturates at the image's largest magnitude: magnitudes are clipped to max_flow, and one
    # extra column holding a vector of exactly max_flow (cut off again) makes that the largest.
    f = f * (scale / np.maximum(mag, scale))
    pinned = np.concatenate([f, np.broadcast_to(np.array([scale, 0.0])[:, None, None], (2, f.shape[1], 1))], axis=2)
    rgb = torchvision.utils.flow_to_image(torch.from_numpy(pinned).float()).permute(1, 2, 0).numpy()[:, :-1]
    rgb = np.ascontiguousarray(rgb)
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


def _image_and_index_map(image: torch.Tensor | np.ndarray, stixels: Any) -> tuple[np.ndarray, np.ndarray]:
    """The image as (H, W, 3) uint8 and the (H, W) index of the stixel covering each pixel (-1: none)."""
    img = image_to_uint8(image)
    H, W = img.shape[:2]
    size = tuple(int(s) for s in stixels.image_size)
    if size != (H, W):
        raise InputError(f"stixels.image_size {size} differs from the image size {(H, W)} (H, W)")
    return img, _stixel_index_map(stixels, H, W)


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
            (:class:`monostixels.core.stixels.StixelWorld`).
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
    img, idx = _image_and_index_map(image, stixels)
    H, W = img.shape[:2]
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


def mover_groups(stixels: Any, moving: np.ndarray | None = None) -> list[np.ndarray]:
    """Moving objects: groups of moving stixels in adjacent columns whose rows overlap.

    Args:
        stixels: a :class:`monostixels.core.stixels.StixelWorld` (or an object with its fields).
        moving: (N,) bool, the stixels to group; default the dynamic object stixels.

    Returns:
        One (K,) int64 array of stixel indices per group, largest first.
    """
    col = _to_numpy(stixels.column, "stixels.column").astype(np.int64).reshape(-1)
    top = _to_numpy(stixels.v_top, "stixels.v_top").astype(np.int64).reshape(-1)
    bot = _to_numpy(stixels.v_bottom, "stixels.v_bottom").astype(np.int64).reshape(-1)
    if moving is None:
        moving = _to_numpy(stixels.type, "stixels.type").reshape(-1) == DYNAMIC_OBJECT
    moving = np.asarray(moving, dtype=bool).reshape(-1)
    if moving.shape != col.shape:
        raise InputError(f"moving: expected one flag per stixel ({col.size}), got {moving.size}")
    ids = np.flatnonzero(moving)
    parent = {int(i): int(i) for i in ids}

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    near = neighbours(*(torch.from_numpy(x[ids]) for x in (col, top, bot))).numpy()
    for a, b in zip(*np.nonzero(np.triu(near))):  # each pair of neighbours once
        parent[root(int(ids[b]))] = root(int(ids[a]))
    groups: dict[int, list[int]] = {}
    for i in ids:
        groups.setdefault(root(int(i)), []).append(int(i))
    return sorted((np.asarray(g, dtype=np.int64) for g in groups.values()), key=len, reverse=True)


def frame_notes(stixels: Any) -> list[str]:
    """What a reader must know about a frame before trusting its depths, as short lines.

    A frame flagged ``degenerate_motion`` (the camera barely translates, docs/conventions.md,
    section 7) has its depths from the scene model: ground at the camera height, objects standing on
    it; on sequences static objects seen before with a baseline keep their tracks' depths
    (``status.counts.carried_stixels``). A frame whose camera motion is unknown (``status.motion.kind``
    ``scale_unknown`` / ``unknown``) says that it shows no movers and raises no collision warning.
    """
    status: FrameStatus = getattr(stixels, "status", None) or FrameStatus()
    motion = status.motion
    if motion.kind in NO_METRIC_MOTION:
        # Said first and plainly: the frame shows no movers and raises no collision warning.
        what = "speed" if motion.kind == MotionKind.SCALE_UNKNOWN else "motion"
        return [f"camera {what} unknown: no movers, no collision warnings; depths from the scene model"]
    if not motion.degenerate:
        return []
    reason = motion.reason
    carried = int(status.counts.carried_stixels or 0)
    source = "the scene model" + (" and tracks" if carried else "")
    # The solver's own reason ("camera translation ... m < ...") or the ego-motion's ("no translation").
    if reason.startswith(("camera translation", "no translation")):
        return [f"camera standing: depths from {source}"]
    return [f"no camera motion estimate: depths from {source}"]


def _text_scale(width: int) -> float:
    return float(np.clip(width / _TEXT_REF_WIDTH, 0.45, 2.0))


def draw_notes(rgb: np.ndarray, notes: Sequence[str], *, corner: str = "top-left", scale: float | None = None) -> np.ndarray:
    """Write text lines on a dark box in a corner of ``rgb`` (H, W, 3) uint8, in place; returns it.

    ``scale``: text size (1 = for a 1242 px wide image); default from the image width.
    """
    import cv2

    if not notes:
        return rgb
    H, W = rgb.shape[:2]
    k = _text_scale(W) if scale is None else float(scale)
    font, fs, th = cv2.FONT_HERSHEY_SIMPLEX, 0.5 * k, max(1, round(1.2 * k))
    sizes = [cv2.getTextSize(n, font, fs, th)[0] for n in notes]
    pad, lh = round(5 * k), max(h for _, h in sizes) + round(7 * k)
    bw, bh = max(w for w, _ in sizes) + 2 * pad, lh * len(notes) + pad
    x0 = pad if corner.endswith("left") else W - bw - pad
    y0 = pad if corner.startswith("top") else H - bh - pad
    x1, y1 = min(W, x0 + bw), min(H, y0 + bh)
    rgb[y0:y1, x0:x1] = (0.3 * rgb[y0:y1, x0:x1]).astype(np.uint8)
    for i, n in enumerate(notes):
        cv2.putText(rgb, n, (x0 + pad, y0 + (i + 1) * lh - round(3 * k)), font, fs, (255, 220, 0), th, cv2.LINE_AA)
    return rgb


def _legend_ticks(min_depth: float, max_depth: float, x_of: Any, min_gap: float) -> list[float]:
    """Depth labels for the scale: the range's ends and round values between them that do not crowd."""
    cands = sorted({min_depth, max_depth, *[t for t in _LEGEND_TICKS_M if min_depth < t < max_depth]})
    ticks = [cands[0]]
    for t in cands[1:]:
        if x_of(t) - x_of(ticks[-1]) >= min_gap:
            ticks.append(t)
        elif t == max_depth:
            ticks[-1] = t  # keep the far end
    return ticks


def _draw_depth_legend(rgb: np.ndarray, min_depth: float, max_depth: float, movers: bool) -> None:
    """The depth scale (inverse-depth jet, near left) in the top-right corner, in place."""
    import cv2

    H, W = rgb.shape[:2]
    k = _text_scale(W)
    font, fs, th = cv2.FONT_HERSHEY_SIMPLEX, 0.42 * k, max(1, round(k))
    pad, bar_w, bar_h = round(6 * k), round(230 * k), round(9 * k)
    title = "stixel depth [m]"
    key = f"white outline: moving, arrow: {MOTION_ARROW_FRAMES:g} frames" if movers else ""
    tw = max(cv2.getTextSize(t, font, fs, th)[0][0] for t in (title, key))
    lh = cv2.getTextSize("0", font, fs, th)[0][1] + round(6 * k)
    bw = max(bar_w, tw) + 2 * pad
    bh = pad + lh + bar_h + lh + (lh if movers else 0) + pad
    if bw > W or bh > H // 2:
        return  # too small an image for a legend
    x0, y0 = W - bw - pad, pad
    rgb[y0:y0 + bh, x0:x0 + bw] = (0.3 * rgb[y0:y0 + bh, x0:x0 + bw]).astype(np.uint8)
    white = (255, 255, 255)
    cv2.putText(rgb, title, (x0 + pad, y0 + pad + lh - round(5 * k)), font, fs, white, th, cv2.LINE_AA)
    bx, by = x0 + pad, y0 + pad + lh
    lo, hi = 1.0 / max_depth, 1.0 / min_depth
    frac = np.linspace(1.0, 0.0, bar_w)  # near (1/min_depth) on the left
    bar = (_jet(frac) * 255.0 + 0.5).astype(np.uint8)
    rgb[by:by + bar_h, bx:bx + bar_w] = bar[None]

    def x_of(d: float) -> float:
        return bx + (1.0 - (1.0 / d - lo) / (hi - lo)) * (bar_w - 1)

    for t in _legend_ticks(min_depth, max_depth, x_of, min_gap=cv2.getTextSize("80", font, fs, th)[0][0] + 6 * k):
        x = round(x_of(t))
        label = f"{t:g}"
        lw = cv2.getTextSize(label, font, fs, th)[0][0]
        rgb[by + bar_h:by + bar_h + round(3 * k), max(bx, x - th // 2):x + th // 2 + 1] = white
        xl = int(np.clip(x - lw // 2, bx, bx + bar_w - lw))
        cv2.putText(rgb, label, (xl, by + bar_h + lh), font, fs, white, th, cv2.LINE_AA)
    if movers:
        cv2.putText(rgb, key, (x0 + pad, by + bar_h + 2 * lh), font, fs, white, th, cv2.LINE_AA)


def _stixel_bottom_points(stixels: Any) -> np.ndarray:
    """3D point (N, 3) at each stixel's bottom-centre pixel on its plane (camera frame, metres)."""
    W = int(stixels.image_size[1])
    w = int(stixels.column_width)
    col = torch.as_tensor(_to_numpy(stixels.column, "stixels.column")).double()
    uc = (col * w + torch.clamp(col * w + w, max=W) - 1) / 2
    ray = pixel_rays(torch.as_tensor(_to_numpy(stixels.K, "stixels.K")).double(), uc,
                     torch.as_tensor(_to_numpy(stixels.v_bottom, "stixels.v_bottom")).double())
    p = torch.as_tensor(_to_numpy(stixels.inverse_depth, "stixels.inverse_depth")).double()
    s = 1.0 / (p * (ray * stixels.normals().double()).sum(-1))
    return (s[:, None] * ray).numpy()


def _draw_arrow(rgb: np.ndarray, a: np.ndarray, b: np.ndarray, thickness: int) -> None:
    """A white arrow with a dark edge from pixel ``a`` to ``b`` (a dot where they nearly coincide)."""
    import cv2

    pa, pb = tuple(int(round(x)) for x in a), tuple(int(round(x)) for x in b)
    if np.hypot(*(b - a)) < 3 * thickness:
        cv2.circle(rgb, pa, 2 * thickness, (0, 0, 0), -1, cv2.LINE_AA)
        cv2.circle(rgb, pa, 2 * thickness - 1, _MOVER_RGB, -1, cv2.LINE_AA)
        return
    cv2.arrowedLine(rgb, pa, pb, (0, 0, 0), thickness + 2, cv2.LINE_AA, tipLength=0.25)
    cv2.arrowedLine(rgb, pa, pb, _MOVER_RGB, thickness, cv2.LINE_AA, tipLength=0.25)


def _mover_arrows(rgb: np.ndarray, stixels: Any, groups: list[np.ndarray], motion: np.ndarray, frames: float,
                  thickness: int) -> None:
    """One arrow per moving object of at least two columns: its bottom-centre point moved by ``frames`` x
    its mean motion, projected."""
    K = _to_numpy(stixels.K, "stixels.K").astype(np.float64)
    pts = _stixel_bottom_points(stixels)
    col = _to_numpy(stixels.column, "stixels.column").reshape(-1)
    for g in groups:
        if np.unique(col[g]).size < _ARROW_MIN_COLUMNS:
            continue
        base, delta = pts[g].mean(0), motion[g].mean(0)
        if not (np.isfinite(base).all() and np.isfinite(delta).all()) or base[2] <= 0:
            continue
        step = frames
        if base[2] + step * delta[2] < 0.5 * base[2]:  # coming closer: stop half-way to the camera
            step = 0.5 * base[2] / max(-delta[2], 1e-9)
        tip = base + step * delta
        pa, pb = K @ base, K @ tip
        a, b = pa[:2] / pa[2], pb[:2] / pb[2]
        cap = _ARROW_MAX_FRACTION * rgb.shape[1]
        if np.hypot(*(b - a)) > cap:  # a fast or false mover: keep the direction, not the length
            b = a + (b - a) * cap / np.hypot(*(b - a))
        _draw_arrow(rgb, a, b, thickness)


def stixel_depth_overlay(
    image: torch.Tensor | np.ndarray,
    stixels: Any,
    *,
    min_depth: float = COLORMAP_MIN_DEPTH_M,
    max_depth: float = COLORMAP_MAX_DEPTH_M,
    alpha: float = 0.5,
    ground_alpha: float = 0.3,
    moving: np.ndarray | None = None,
    motion: torch.Tensor | np.ndarray | None = None,
    notes: Sequence[str] = (),
    legend: bool = True,
    ttc_warning: np.ndarray | None = None,
) -> np.ndarray:
    """Draw the stixels over the image: each object a box in the colour of its depth.

    Convention: colours as :func:`depth_colormap` (inverse-depth jet, close = red, far = dark
    blue). An object stixel (static or dynamic) is a box filled with the colour of its depth
    (:attr:`StixelWorld.depth`, at its bottom centre) at opacity ``alpha``, with an opaque 1 px
    border in a darker shade where it meets another stixel or nothing. Ground is tinted by its
    per-pixel depth at ``ground_alpha``; sky is left as it is. Moving stixels get a white outline
    per moving object and an arrow of its motion over :data:`MOTION_ARROW_FRAMES` frames.
    Frame notes (:func:`frame_notes`, then ``notes``) go top left, the legend top right.

    Args:
        image: (3, H, W) float RGB in [0, 1] (or (H, W, 3) uint8).
        stixels: a :class:`monostixels.core.stixels.StixelWorld` of the image.
        min_depth, max_depth: colour-map range, metres.
        alpha, ground_alpha: fill opacity of objects and of the ground, 0..1.
        moving: (N,) bool, the stixels to outline as moving; default the dynamic ones.
        motion: (N, 3) motion of each stixel between the two frames (camera frame, metres), for the
            arrows; default ``stixels.motion``.
        notes: more lines for the top-left box (e.g. warnings of a caller).
        legend: draw the depth scale.
        ttc_warning: (N,) bool, stixels closing within the TTC warning time in the camera's path
            (:mod:`monostixels.sequence.ttc`): a red outline and their time to collision; default
            ``stixels.ttc_warning`` where the sequence layer set it.

    Returns:
        (H, W, 3) uint8 RGB.
    """
    import cv2

    for name, a in (("alpha", alpha), ("ground_alpha", ground_alpha)):
        if not 0.0 <= a <= 1.0:
            raise InputError(f"{name}: expected a value in [0, 1], got {a}")
    img, idx = _image_and_index_map(image, stixels)
    H, W = img.shape[:2]
    typ = _to_numpy(stixels.type, "stixels.type").astype(np.int64).reshape(-1)
    n = typ.size
    depth = _to_numpy(stixels.depth, "stixels.depth").astype(np.float64).reshape(-1)
    colours = depth_colormap(depth[None, :], min_depth=min_depth, max_depth=max_depth)[0].astype(np.float64)
    safe = np.where(idx >= 0, idx, 0)
    pix_type = np.where(idx >= 0, typ[safe], -1)
    is_obj = (pix_type == STATIC_OBJECT) | (pix_type == DYNAMIC_OBJECT)
    out = img.astype(np.float64)
    # Ground: a light tint of each pixel's own depth (a ground stixel spans many depths).
    gdepth = _to_numpy(stixels.depth_map(), "depth map").astype(np.float64)
    ground = (pix_type == GROUND) & np.isfinite(gdepth) & (gdepth > 0)
    gcol = depth_colormap(np.where(ground, gdepth, 1.0), min_depth=min_depth, max_depth=max_depth).astype(np.float64)
    out[ground] = (1.0 - ground_alpha) * out[ground] + ground_alpha * gcol[ground]
    fill = colours[safe]
    out[is_obj] = (1.0 - alpha) * out[is_obj] + alpha * fill[is_obj]
    # Border (1 px) of every object box: its top and bottom rows, its left edge, and its right edge
    # where no object stixel continues the row (between two boxes one line, not two).
    up = np.pad(idx, ((1, 0), (0, 0)), constant_values=-1)[:-1]
    down = np.pad(idx, ((0, 1), (0, 0)), constant_values=-1)[1:]
    left = np.pad(idx, ((0, 0), (1, 0)), constant_values=-1)[:, :-1]
    right_obj = np.pad(is_obj, ((0, 0), (0, 1)), constant_values=False)[:, 1:]
    border = is_obj & ((up != idx) | (down != idx) | (left != idx) | ~right_obj)
    out[border] = _BORDER_SHADE * fill[border]
    rgb = np.ascontiguousarray((out + 0.5).astype(np.uint8))  # OpenCV draws on C-ordered arrays
    # Moving objects: outline and motion arrow.
    groups = mover_groups(stixels, moving)
    if groups:
        mot = _to_numpy(stixels.motion if motion is None else motion, "motion").astype(np.float64).reshape(-1, 3)
        if mot.shape[0] != n:
            raise InputError(f"motion: expected ({n}, 3), got {mot.shape}")
        th = max(1, round(_text_scale(W) * 2))
        members = np.zeros(n, dtype=bool)
        members[np.concatenate(groups)] = True
        mask = (idx >= 0) & members[safe]
        contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(rgb, contours, -1, _MOVER_RGB, th, cv2.LINE_8)  # crisp: boxes are pixel-aligned
        _mover_arrows(rgb, stixels, groups, mot, MOTION_ARROW_FRAMES, th)
    warn = getattr(stixels, "ttc_warning", None) if ttc_warning is None else ttc_warning
    ttc_notes: list[str] = []
    if warn is not None:
        warn = _to_numpy(warn, "ttc_warning").astype(bool).reshape(-1)
        if warn.shape[0] != n:
            raise InputError(f"ttc_warning: expected ({n},), got {warn.shape}")
        if warn.any():
            ttc_notes = _ttc_marks(rgb, stixels, idx, warn)
    if legend:
        _draw_depth_legend(rgb, min_depth, max_depth, movers=bool(groups))
    draw_notes(rgb, [*frame_notes(stixels), *ttc_notes, *notes])
    return rgb


def _ttc_marks(rgb: np.ndarray, stixels: Any, idx: np.ndarray, warn: np.ndarray) -> list[str]:
    """Outline the warned stixels (N,) in red with each region's least time to collision; the notes line."""
    import cv2

    H, W = idx.shape
    ttc = _to_numpy(stixels.ttc_s, "ttc_s").astype(np.float64).reshape(-1)
    safe = np.where(idx >= 0, idx, 0)
    mask = ((idx >= 0) & warn[safe]).astype(np.uint8)
    th = max(2, round(_text_scale(W) * 3))
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(rgb, contours, -1, _TTC_RGB, th, cv2.LINE_8)
    scale = _text_scale(W) * 0.6
    for c in contours:
        x, y, w, h = cv2.boundingRect(c)
        region = idx[y:y + h, x:x + w]
        inside = region[(region >= 0) & warn[np.where(region >= 0, region, 0)]]
        t = float(np.min(ttc[inside])) if inside.size else float("nan")
        label = f"TTC {t:.1f} s"
        (tw, tht), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
        org = (int(np.clip(x, 0, max(0, W - tw))), int(max(tht + 2, y - 4)))
        cv2.putText(rgb, label, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(rgb, label, org, cv2.FONT_HERSHEY_SIMPLEX, scale, _TTC_RGB, 1, cv2.LINE_AA)
    return [f"TTC warning: {len(contours)} object(s) closing in the path"]


def side_by_side(left: np.ndarray, right: np.ndarray, *, gap: int = 4) -> np.ndarray:
    """``left`` and ``right`` (H, W, 3) uint8 next to each other, ``right`` scaled to ``left``'s height."""
    import cv2

    for name, a in (("left", left), ("right", right)):
        if not (isinstance(a, np.ndarray) and a.ndim == 3 and a.shape[2] == 3 and a.dtype == np.uint8):
            raise InputError(f"{name}: expected an (H, W, 3) uint8 RGB array")
    H = left.shape[0]
    w = max(1, round(right.shape[1] * H / right.shape[0]))
    r = cv2.resize(right, (w, H), interpolation=cv2.INTER_AREA if H < right.shape[0] else cv2.INTER_LINEAR)
    return np.concatenate([left, np.full((H, gap, 3), 255, np.uint8), r], axis=1)


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

    from monostixels.output.io import write_image

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
