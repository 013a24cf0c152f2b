"""Grey images: the package's one place that converts colour to grey.

- :func:`to_gray`: float grey in [0, 1] (ITU-R BT.601 luma weights) for the flow confidence's structure tensor
  and the ground's photometric search;
- :func:`to_gray_u8`: 8-bit grey for OpenCV's flow backends and the static-region search, kornia's
  ``rgb_to_grayscale`` / ``bgr_to_grayscale``, bit for bit OpenCV's fixed-point ``COLOR_RGB2GRAY`` /
  ``COLOR_BGR2GRAY`` (the same value for every one of the 2^24 colours).

kornia's float path is not used for :func:`to_gray`: it accumulates the channels with a fused multiply-add
(``torch.addcmul``), one float32 rounding step fewer than the weighted sum the package has always taken, so about
a fifth of the pixels would move by one unit in the last place, and with them the flow covariances.
"""
from __future__ import annotations

import numpy as np
import torch

from monostixels._checks import InputError, check_shape

__all__ = ["LUMA_WEIGHTS", "to_gray", "to_gray_u8"]

#: ITU-R BT.601 luma weights (R, G, B).
LUMA_WEIGHTS = (0.299, 0.587, 0.114)


def to_gray(image: torch.Tensor) -> torch.Tensor:
    """Grey image (H, W) float32 in [0, 1] from an RGB image (3, H, W) in [0, 1] (or grey (H, W))."""
    if image.dim() == 2:
        return image.float()
    check_shape(image, [3, "H", "W"], "image")
    if image.device.type != "cpu" or image.requires_grad:
        w = torch.tensor(LUMA_WEIGHTS, dtype=torch.float32).view(3, 1, 1)
        return (image.float() * w).sum(0)
    # numpy, channels added in order: the same float32 values as torch's weighted sum over the
    # channel axis, without torch's thread hand-offs (it runs in a thread beside the flow).
    x = image.numpy().astype(np.float32, copy=False)
    w = np.asarray(LUMA_WEIGHTS, dtype=np.float32)
    return torch.from_numpy(x[0] * w[0] + x[1] * w[1] + x[2] * w[2])


def to_gray_u8(image: np.ndarray | torch.Tensor, order: str = "rgb") -> np.ndarray:
    """(3, H, W) uint8 colour image, channels ``order`` (``"rgb"`` or ``"bgr"``) -> (H, W) uint8 grey, OpenCV's
    ``cvtColor`` values (kornia)."""
    from kornia.color import bgr_to_grayscale, rgb_to_grayscale

    x = torch.from_numpy(np.asarray(image)) if not isinstance(image, torch.Tensor) else image
    check_shape(x, [3, "H", "W"], "image")
    if x.dtype != torch.uint8:
        raise InputError(f"image: expected uint8 channels for an 8-bit grey image, got {x.dtype}")
    if order not in ("rgb", "bgr"):
        raise InputError(f"grey conversion: channel order must be 'rgb' or 'bgr', got {order!r}")
    grey = (rgb_to_grayscale if order == "rgb" else bgr_to_grayscale)(x)
    return grey[0].numpy()
