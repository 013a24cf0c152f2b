"""Resampling of the flow (``cfg.scale``, image backends): the images downscaled before a backend runs, its
flow and covariance brought back to the input size, an image warped by a flow.

The dense estimate may run on the images downscaled by ``scale`` in (0, 1] (area averaging); its flow is
upsampled bilinearly to the input size and its vectors multiplied by the size ratio (module docstring of
:mod:`monostixels.inputs.flow`).
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import Any, Callable

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from monostixels._checks import InputError
from monostixels.inputs.flow_config import flow_params

__all__ = ["MIN_SCALED_SIDE", "at_scale", "downscale", "flow_scale", "remap", "scaled_size", "upsample_cov", "upsample_flow"]


def flow_scale(cfg: Any) -> float:
    """``cfg.scale`` (1 for ``gt``): the factor the images are downscaled by before an image backend runs.

    Raises:
        InputError: not a number in (0, 1].
    """
    scale = getattr(flow_params(cfg), "scale", 1.0)
    if not (math.isfinite(scale) and 0.0 < scale <= 1.0):
        raise InputError(f"flow.scale: must be in (0, 1] (1 = full resolution), got {scale}")
    return scale


#: Smallest image side (px) an image backend is run at (DIS patches are 8 px, its pyramid needs more).
MIN_SCALED_SIDE = 16


def scaled_size(H: int, W: int, scale: float) -> tuple[int, int]:
    """(h, w) of an (H, W) image downscaled by ``scale``; an error if a side falls below 16 px."""
    h, w = max(1, round(H * scale)), max(1, round(W * scale))
    if min(h, w) < MIN_SCALED_SIDE:
        raise InputError(f"flow.scale: {scale} turns the {W}x{H} images into {w}x{h}; "
                         f"each side must stay >= {MIN_SCALED_SIDE} px (raise flow.scale)")
    return h, w


def downscale(image: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """(C, H, W) float image resampled to ``size`` = (h, w) by area averaging (OpenCV INTER_AREA)."""
    h, w = size
    arr = np.ascontiguousarray(image.float().permute(1, 2, 0).numpy())
    small = cv2.resize(arr, (w, h), interpolation=cv2.INTER_AREA)
    if small.ndim == 2:
        small = small[..., None]
    return torch.from_numpy(np.ascontiguousarray(small.transpose(2, 0, 1)))


def upsample_flow(flow: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Flow (2, h, w) in pixels of its grid -> (2, H, W) in pixels of the ``size`` = (H, W) grid.

    Convention: pixel centres map as ``u_full = (u + 0.5) W / w - 0.5`` (``align_corners=False``),
    so a displacement of ``du`` grid pixels is ``du W / w`` full-size pixels (and ``dv H / h``).
    """
    H, W = size
    h, w = flow.shape[-2:]
    up = F.interpolate(flow[None].float(), size=(H, W), mode="bilinear", align_corners=False)[0]
    return up * torch.tensor([W / w, H / h], dtype=torch.float32).view(2, 1, 1)


def upsample_cov(cov: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Covariance (h, w, 2, 2) in grid pixels^2 -> (H, W, 2, 2) in full-size pixels^2: ``D C D``
    with ``D = diag(W / w, H / h)``, interpolated bilinearly (a convex combination of symmetric
    positive definite matrices stays positive definite, within the same eigenvalue bounds)."""
    H, W = size
    h, w = cov.shape[:2]
    d = torch.tensor([W / w, H / h], dtype=torch.float32)
    scaled = cov.float() * (d[:, None] * d[None, :])
    flat = scaled.reshape(h, w, 4).permute(2, 0, 1)[None]  # 1 x 4 x h x w
    up = F.interpolate(flat, size=(H, W), mode="bilinear", align_corners=False)[0]
    return up.permute(1, 2, 0).reshape(H, W, 2, 2).contiguous()


@lru_cache(maxsize=4)
def _pixel_grid(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates ``(u, v)`` (h, w) float32 of an (h, w) grid, read-only (shared between calls)."""
    xx, yy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    xx.flags.writeable = yy.flags.writeable = False
    return xx, yy


def remap(img: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """``img`` sampled at ``x + flow(x)`` (bilinear, border replicated); flow (H, W, 2) pixels."""
    xx, yy = _pixel_grid(*flow.shape[:2])
    return cv2.remap(img, xx + flow[..., 0], yy + flow[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def at_scale(calc: Callable[[np.ndarray, np.ndarray], np.ndarray], a: np.ndarray, b: np.ndarray,
              scale: float) -> np.ndarray:
    """``calc(a, b)`` (an (h, w, 2) flow of two grey images) run at ``scale``, returned at full size, full-size pixels."""
    if scale == 1.0:
        return calc(a, b)
    H, W = a.shape
    h, w = scaled_size(H, W, scale)
    small = calc(cv2.resize(a, (w, h), interpolation=cv2.INTER_AREA), cv2.resize(b, (w, h), interpolation=cv2.INTER_AREA))
    return upsample_flow(torch.from_numpy(np.ascontiguousarray(small.transpose(2, 0, 1))), (H, W)).permute(1, 2, 0).numpy()
