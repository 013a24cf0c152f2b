"""Image regions that never move: a bonnet in view, a dashboard reflection at the bottom of the picture.

A dashcam films part of its own car. Those pixels stay where they are while the scene streams past, so
their flow says "no motion": the ego-motion would read them as a standing camera, the movers as an object
driving along with us. They are excluded from every stage (:func:`apply_ignore_mask`).

:func:`find_static_region` finds such a region from a few runs of frames spread over the clip
(:func:`spread_samples`: a camera that stands at the start drives later), without optical flow (at
highway speed the flow on the near road is unreliable, and a flow of zero there would look static too):

- a pair (two neighbours in a run) counts only where the scene above any bonnet changes in it (the band
  of :data:`ABOVE_SHARE` above the highest region allowed, :data:`MIN_MOVING_ABOVE`); at a standing camera
  the road keeps as still as a bonnet. At least :data:`MIN_PAIRS` must count;
- a pixel carries evidence only where the later frame of a counted pair has texture (grey-value gradient
  above :data:`TEXTURE_GRAD`); there it is *static* in that pair where the window around it keeps its
  pattern (:func:`still_pixels`: a change of exposure or a fraction of a pixel of shake keeps it, a scene
  that moves past does not);
- the image is cut into vertical strips of :data:`STRIP_PX` pixels; a row of a strip is static where
  :data:`STATIC_SHARE` of its textured pixels are, else moving (without texture it says nothing). Each
  strip is read from the bottom up: its static part is the run of rows below the first moving row, up to
  its last static row (rows without texture in between are allowed, :data:`GAP_SHARE`); a strip without
  a moving row says nothing;
- the region is kept only where it spans most of the width (:data:`MIN_WIDTH_SHARE` of the strips, as a
  bonnet does), stays below :data:`MAX_HEIGHT_SHARE` of the image, and the scene above it moves (most of
  the texture in the :data:`ABOVE_SHARE` of the image above it changes, :data:`MIN_MOVING_ABOVE`): at a
  standing camera, where nearly nothing moves, the road would look as still as a bonnet.

Only regions touching the bottom edge are found; anything else (a logo, a timestamp) is for the user's
own mask (``data.mask=FILE``).
"""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Any, Sequence

import cv2
import numpy as np
import torch

from monostixels._checks import InputError
from monostixels.core.grey import to_gray, to_gray_u8

__all__ = ["AUTO_MASK", "AUTO_BURSTS", "AUTO_BURST", "AUTO_SPACING_S", "spread_samples", "still_pixels",
           "find_static_region", "with_static_region", "IgnoreMask", "apply_ignore_mask", "crop_ignored"]

logger = logging.getLogger(__name__)

#: ``data.mask=auto``: the data source looks for a static region itself (:func:`with_static_region`).
AUTO_MASK = "auto"
#: Frames it reads for that: AUTO_BURSTS runs of AUTO_BURST frames AUTO_SPACING_S apart (seconds: the scene
#: moves, the exposure hardly changes), spread over the whole clip (:func:`spread_samples`): a camera that
#: stands at the start moves later.
AUTO_BURSTS = 4
AUTO_BURST = 4
AUTO_SPACING_S = 0.2
#: Grey-value gradient (Sobel 3x3 of a [0, 1] image) above which a pixel has texture to judge motion by.
TEXTURE_GRAD = 0.25
#: A textured pixel is static in a pair where the grey values of the STILL_WINDOW x STILL_WINDOW window around
#: it correlate by at least STILL_NCC between the two frames (zero-mean normalised cross-correlation). A grey
#: value difference (0.03) missed the Kochi phone's whole dashboard (the exposure follows the scene, the phone
#: shakes on its mount: 30-55 % of its textured pixels kept their value); NCC 0.9 was chosen on that clip's
#: samples and checked on seven others (docs/experiments.md, "Static regions through exposure and shake").
STILL_WINDOW = 7
STILL_NCC = 0.9
#: Width (pixels) of the vertical strips read from the bottom up.
STRIP_PX = 16
#: A row of a strip is static where at least this share of its textured pixels (over all pairs) is static,
#: else moving; it says nothing with fewer than MIN_EVIDENCE textured pixels.
STATIC_SHARE = 0.8
MIN_EVIDENCE = 3
#: Rows without evidence (no texture) that a strip's static part may hold above its last static row,
#: as a share of the image height (at least 3 rows); the part ends there.
GAP_SHARE = 0.05
#: Above the region (this share of the image height), at least MIN_MOVING_ABOVE of the textured pixels must
#: change: the scene moves past the camera.
ABOVE_SHARE = 0.25
MIN_MOVING_ABOVE = 0.4
#: Pairs in which the scene moves (as MIN_MOVING_ABOVE asks of the band just above the highest region allowed)
#: needed to find a region: the others, at a standing camera, are left out.
MIN_PAIRS = 2
#: The region must cover at least this share of the strips (a bonnet spans the picture) ...
MIN_WIDTH_SHARE = 0.6
#: ... and no strip's part may reach above this share of the image height.
MAX_HEIGHT_SHARE = 0.4


def _grey(frame: np.ndarray) -> np.ndarray:
    """(H, W) float32 grey in [0, 1] of a frame (H, W) or (H, W, 3) BGR, uint8 or float in [0, 1]."""
    if frame.ndim == 3 and frame.dtype == np.uint8:
        frame = to_gray_u8(frame.transpose(2, 0, 1), order="bgr")  # the frames as read: OpenCV's 8-bit grey
    elif frame.ndim == 3:
        frame = to_gray(torch.from_numpy(np.ascontiguousarray(frame[..., ::-1].transpose(2, 0, 1), np.float32))).numpy()
    g = frame.astype(np.float32)
    return g / 255.0 if frame.dtype == np.uint8 else g


def still_pixels(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(H, W) bool: where the window around a pixel keeps its pattern from grey image ``a`` to ``b`` (H, W),
    float: their zero-mean normalised cross-correlation over :data:`STILL_WINDOW` at least :data:`STILL_NCC`."""
    def box(x: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(x, cv2.CV_32F, (STILL_WINDOW, STILL_WINDOW))

    ma, mb = box(a), box(b)
    cov = box(a * b) - ma * mb
    var = (box(a * a) - ma * ma) * (box(b * b) - mb * mb)
    return cov >= STILL_NCC * np.sqrt(np.maximum(var, 1e-12))


def spread_samples(n: int, min_gap: int = 1, bursts: int = AUTO_BURSTS, burst: int = AUTO_BURST) -> list[list[int]]:
    """Runs of up to ``burst`` indices ``min_gap`` apart, up to ``bursts`` of them spread evenly over ``0 .. n-1``
    (the first starts at 0, the last ends near ``n - 1``; they do not overlap): the frames of a clip to look for
    a static region in, compared within each run."""
    if n < 0 or min_gap < 1 or bursts < 1 or burst < 2:
        raise InputError(f"static region: bad sampling n={n}, min_gap={min_gap}, bursts={bursts}, burst={burst}")
    length = min(burst, (n - 1) // min_gap + 1) if n else 0
    if length < 1:
        return []
    span = (length - 1) * min_gap  # index distance within a run
    room = n - 1 - span
    k = max(1, min(bursts, room // (span + 1) + 1))
    starts = sorted({round(i * room / max(1, k - 1)) for i in range(k)})
    return [[s + j * min_gap for j in range(length)] for s in starts]


def find_static_region(frames: Sequence[np.ndarray], runs: Sequence[int] | None = None) -> np.ndarray:
    """The region at the bottom of the picture that stays still while the scene moves (module docstring).

    Args:
        frames: at least 3 frames of one clip, in time order and some way apart (a few tenths of a second:
            the scene must move between them), (H, W) grey or (H, W, 3) BGR, uint8 or float in [0, 1].
        runs: the frames are runs of these lengths (:func:`spread_samples`), each frame compared with the one
            before it in its run; None = one run.

    Returns:
        (H, W) bool, True = static (to be ignored); all False where no such region is found.
    """
    if len(frames) < 3:
        raise InputError(f"static region: needs at least 3 frames, got {len(frames)}")
    grey = [_grey(f) for f in frames]
    H, W = grey[0].shape
    if any(g.shape != (H, W) for g in grey):
        raise InputError("static region: the frames differ in size")
    runs = [len(frames)] if runs is None else [int(r) for r in runs]
    if sum(runs) != len(frames) or min(runs) < 1:
        raise InputError(f"static region: runs {runs} do not split {len(frames)} frames")
    firsts = set(np.cumsum([0] + runs[:-1]).tolist())  # a run's first frame has no frame before it
    static = np.zeros((H, W), np.float32)
    textured_n = np.zeros((H, W), np.float32)
    band = slice(int((1.0 - MAX_HEIGHT_SHARE - ABOVE_SHARE) * H), int((1.0 - MAX_HEIGHT_SHARE) * H))
    informative = 0
    for k in range(1, len(grey)):
        if k in firsts:
            continue
        a, b = grey[k - 1], grey[k]
        grad = np.hypot(cv2.Sobel(b, cv2.CV_32F, 1, 0), cv2.Sobel(b, cv2.CV_32F, 0, 1))
        textured = grad > TEXTURE_GRAD
        still = textured & still_pixels(a, b)
        # A pair in which the scene above any bonnet keeps still (the camera stands, nothing passes) cannot
        # tell a bonnet from the road: it is left out.
        n_band = float(textured[band].sum())
        if n_band < MIN_EVIDENCE or 1.0 - float(still[band].sum()) / n_band < MIN_MOVING_ABOVE:
            continue
        informative += 1
        textured_n += textured
        static += still
    if informative < MIN_PAIRS:
        return np.zeros((H, W), bool)
    mask = np.zeros((H, W), bool)
    strips = list(range(0, W, STRIP_PX))
    gap_max = max(3, int(GAP_SHARE * H))
    top = np.full(len(strips), -1, dtype=np.int64)  # first row of each strip's static part; -1 = no evidence
    for k, u0 in enumerate(strips):
        s_row = static[:, u0:u0 + STRIP_PX].sum(1)
        n_row = textured_n[:, u0:u0 + STRIP_PX].sum(1)
        known = n_row >= MIN_EVIDENCE
        is_static = known & (s_row >= STATIC_SHARE * n_row)
        is_moving = known & ~is_static
        last, gap, moved = H, 0, False
        for r in range(H - 1, -1, -1):
            if is_moving[r]:
                moved = True
                break
            if is_static[r]:
                last, gap = r, 0
            elif last < H:
                gap += 1  # rows without evidence above static ones: the region ends after a few
                if gap > gap_max:
                    break
        if moved or gap > gap_max:
            top[k] = last  # H: the strip moves down to its bottom row
    decided = top >= 0
    found = decided & (top < H)
    if decided.sum() == 0 or found.sum() < MIN_WIDTH_SHARE * len(strips):
        return mask
    if (H - top[found]).max() > MAX_HEIGHT_SHARE * H:
        return mask
    # The camera must be moving: above the region, most of the texture changes (a standing camera, where the
    # whole scene keeps still, has no bonnet to tell apart).
    above = slice(max(0, int(top[found].min()) - int(ABOVE_SHARE * H)), int(top[found].min()))
    n_above = float(textured_n[above].sum())
    if n_above < MIN_EVIDENCE or 1.0 - float(static[above].sum()) / n_above < MIN_MOVING_ABOVE:
        return mask
    # A bonnet's edge is smooth: each strip's top as the median over it and its decided neighbours.
    smooth = np.full(len(strips), H, dtype=np.int64)
    for k in range(len(strips)):
        window = top[max(0, k - 2):k + 3]
        window = window[window >= 0]
        if len(window):
            smooth[k] = int(np.median(window))
    for k, u0 in enumerate(strips):
        mask[smooth[k]:, u0:u0 + STRIP_PX] = True
    if not mask.any():
        return mask
    logger.info("static region at the bottom: rows %d-%d of %d (%.1f %% of the image)",
                int(smooth.min()), H - 1, H, 100.0 * mask.mean())
    return mask


def with_static_region(ignore: torch.Tensor | None, runs: Sequence[Sequence[np.ndarray]],
                       what: str) -> torch.Tensor | None:
    """``ignore`` (H, W) bool or None, with the static region of the runs of frames ``runs``
    (:func:`find_static_region`) added; ``what`` names the clip in the log. Fewer than 3 frames, or no two in a
    run: ``ignore`` as it is."""
    frames = [f for run in runs for f in run]
    if len(frames) < 3 or all(len(run) < 2 for run in runs):
        logger.info("%s: too few frames to look for a static region (bonnet)", what)
        return ignore
    found = find_static_region(frames, [len(run) for run in runs if run])
    if not found.any():
        logger.info("%s: no static region (bonnet) found", what)
        return ignore
    logger.info("%s: static region (bonnet) ignored: %.1f %% of the image", what, 100.0 * found.mean())
    mask = torch.from_numpy(found)
    return mask if ignore is None else ignore | mask


@dataclass
class IgnoreMask:
    """How a pair's ignore mask (``pair.meta["ignore_mask"]``, (H, W) bool, True = ignore) is applied.

    Attributes:
        crop_rows: the rows kept, ``[0, crop_rows)``: below them every pixel of every row is ignored, and the
            pair is solved without them (the outputs keep the full size; those rows get no stixel).
        pixels: (crop_rows, W) bool, the ignored pixels left above the cut (or None).
    """

    crop_rows: int
    pixels: torch.Tensor | None


def apply_ignore_mask(mask: torch.Tensor, size: tuple[int, int]) -> IgnoreMask:
    """Split an ignore mask (H, W) into the full rows cut off at the bottom and the pixels left above them."""
    H, W = size
    if tuple(mask.shape) != (H, W):
        raise InputError(f"ignore mask: size {tuple(mask.shape)} differs from the frame's {(H, W)}")
    full = mask.bool().all(1)
    crop = H
    while crop > 0 and bool(full[crop - 1]):
        crop -= 1
    if crop < H // 2:
        raise InputError(f"ignore mask: it leaves {crop} of {H} rows: too little of the picture to solve")
    rest = mask[:crop].bool()
    return IgnoreMask(crop, rest if bool(rest.any()) else None)


def crop_ignored(pair: Any) -> Any:
    """A frame pair without the bottom rows its ignore mask (``meta["ignore_mask"]``) covers whole: a bonnet.

    The rest of the mask goes to ``meta["ignore_pixels"]`` (or None) and the pair itself to
    ``meta["full_pair"]``, from which the outputs take back the frame's size; the intrinsics stay (rows are
    cut below, the principal point does not move). A pair without a mask, or one cropped already, is
    returned as it is.
    """
    mask = pair.info.ignore_mask
    if mask is None:
        return pair
    split = apply_ignore_mask(torch.as_tensor(mask), pair.size)
    rows = split.crop_rows

    def cut(x: torch.Tensor | None) -> torch.Tensor | None:
        if x is None or x.dim() < 2 or tuple(x.shape[-2:]) != tuple(pair.size):
            return x
        return x[..., :rows, :]

    gt = dataclasses.replace(pair.gt, **{f.name: cut(getattr(pair.gt, f.name)) for f in dataclasses.fields(pair.gt)
                                         if f.name != "bottoms"})
    meta = {k: v for k, v in pair.meta.items() if k != "ignore_mask"}
    meta["ignore_pixels"] = split.pixels
    meta["full_pair"] = pair
    return dataclasses.replace(pair, image=pair.image[:, :rows], image_prev=pair.image_prev[:, :rows], gt=gt, meta=meta)
