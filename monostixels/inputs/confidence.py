"""Flow confidence: the one place that turns flow quality into a flow covariance ``C_v``.

The stixel energy weighs each flow residual with the inverse of a per-pixel 2x2 covariance
``C_v`` (pixels^2). Every flow backend gets its covariance from :func:`flow_covariance`, so the
meaning of "confidence" is defined once:

- ``constant``: ``C_v = sigma^2 I``.
- ``structure_tensor`` (Förstner 1987, the local least-squares view of Lucas-Kanade): if the
  flow of a pixel is the least-squares solution of the brightness-constancy equations
  ``∇I^T f = -I_t`` over a window of ``N`` pixels with intensity noise ``σ_n``, its covariance is
  ``σ_n^2 (N J)^-1`` with ``J`` the (window-averaged) structure tensor ``<∇I ∇I^T>``. Along an
  edge ``J`` is rank one: the flow is unknown along the edge (large variance) and well known
  across it; in a textureless patch ``J ≈ 0`` and the variance is large in every direction
  (the aperture problem, quantified).
- Forward-backward consistency (optional, for backends that can run both ways): the
  round-trip error ``e = |f(x) + b(x + f(x))|`` (pixels), with ``b`` the flow from the previous
  to the current image, adds ``(κ e)^2 I`` — occlusions and mismatches get a large variance.

Eigenvalues of ``C_v`` are clipped to ``[sigma_min^2, sigma_max^2]``: the floor keeps the
energy from trusting any flow vector more than the backend's sub-pixel accuracy, the ceiling
keeps ``C_v`` finite (a textureless pixel then contributes almost nothing, but stays
well-defined). The result is always symmetric positive definite.

Units: image intensities in [0, 1] (grey value of the RGB input), gradients per pixel,
covariances in pixels^2.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import kornia
import torch
import torch.nn.functional as F

from monostixels._checks import InputError, check_finite, check_shape

__all__ = [
    "ConfidenceParams",
    "CONFIDENCE_METHODS",
    "to_gray",
    "structure_tensor",
    "fb_consistency_error",
    "flow_covariance",
]

logger = logging.getLogger(__name__)

#: Methods accepted by :func:`flow_covariance` (``flow.confidence`` in the config).
CONFIDENCE_METHODS = ("constant", "structure_tensor")

#: ITU-R BT.601 luma weights (R, G, B) for the grey image of the structure tensor.
_LUMA_WEIGHTS = (0.299, 0.587, 0.114)


@dataclass
class ConfidenceParams:
    """Parameters of :func:`flow_covariance` (the `flow` config group carries the same keys).

    Attributes:
        method: ``constant`` or ``structure_tensor``.
        sigma: flow standard deviation (pixels) of ``constant``; also the default floor.
        noise: intensity noise ``σ_n`` of the images (grey values in [0, 1]); 0.01 ≈ 2.5/255,
            JPEG/sensor noise of street imagery.
        window_sigma: standard deviation (pixels) of the Gaussian window of the structure tensor.
        sigma_min: smallest flow standard deviation (pixels) any pixel gets.
        sigma_max: largest flow standard deviation (pixels) any pixel gets.
        fb_weight: ``κ`` of the forward-backward term (dimensionless; 0 disables it).
    """

    method: str = "structure_tensor"
    sigma: float = 0.5
    noise: float = 0.01
    window_sigma: float = 2.0
    sigma_min: float = 0.25
    sigma_max: float = 20.0
    fb_weight: float = 1.0

    def __post_init__(self) -> None:
        if self.method not in CONFIDENCE_METHODS:
            raise InputError(f"flow.confidence: unknown method {self.method!r}, expected one of {CONFIDENCE_METHODS}")
        for name in ("sigma", "noise", "window_sigma", "sigma_min", "sigma_max"):
            val = float(getattr(self, name))
            if not (math.isfinite(val) and val > 0):
                raise InputError(f"flow confidence parameter {name}: must be a positive number, got {val}")
        if self.sigma_min > self.sigma_max:
            raise InputError(f"flow confidence: sigma_min ({self.sigma_min}) > sigma_max ({self.sigma_max})")
        if not (math.isfinite(self.fb_weight) and self.fb_weight >= 0):
            raise InputError(f"flow confidence parameter fb_weight: must be >= 0, got {self.fb_weight}")


def to_gray(image: torch.Tensor) -> torch.Tensor:
    """Grey image (H, W) float32 in [0, 1] from an RGB image (3, H, W) in [0, 1] (or grey (H, W))."""
    if image.dim() == 2:
        return image.float()
    check_shape(image, [3, "H", "W"], "image")
    w = torch.tensor(_LUMA_WEIGHTS, dtype=torch.float32).view(3, 1, 1)
    return (image.float() * w).sum(0)


def structure_tensor(gray: torch.Tensor, window_sigma: float) -> torch.Tensor:
    """Gaussian-windowed structure tensor ``J = <∇I ∇I^T>`` (H, W, 2, 2) of a grey image (H, W).

    Gradients are central differences (kornia ``spatial_gradient``, Sobel normalised to
    intensity per pixel); the window is a Gaussian of standard deviation ``window_sigma``
    pixels, normalised to sum 1, so ``J`` is a weighted *mean* (units: intensity^2 / pixel^2).
    """
    check_shape(gray, ["H", "W"], "grey image")
    g = kornia.filters.spatial_gradient(gray[None, None].float(), mode="sobel", order=1, normalized=True)
    gx, gy = g[:, :, 0], g[:, :, 1]  # 1 x 1 x H x W each
    prods = torch.cat([gx * gx, gx * gy, gy * gy], dim=1)  # 1 x 3 x H x W
    k = _odd_kernel_size(window_sigma)
    prods = kornia.filters.gaussian_blur2d(prods, (k, k), (window_sigma, window_sigma), border_type="replicate")
    jxx, jxy, jyy = prods[0]
    return torch.stack([torch.stack([jxx, jxy], -1), torch.stack([jxy, jyy], -1)], -2)


def _odd_kernel_size(sigma: float) -> int:
    """Gaussian kernel size covering +-3 sigma, odd, at least 3."""
    return max(3, 2 * int(math.ceil(3.0 * sigma)) + 1)


def fb_consistency_error(flow: torch.Tensor, flow_back: torch.Tensor) -> torch.Tensor:
    """Round-trip error ``|f(x) + b(x + f(x))|`` (H, W), pixels.

    Args:
        flow: (2, H, W) current -> previous, pixels (``x_prev = x + f``).
        flow_back: (2, H, W) previous -> current, pixels, sampled bilinearly at ``x + f``.

    Returns:
        (H, W) float32 error in pixels; pixels whose ``x + f`` leaves the image get ``inf``
        (no way to check them: treated as occluded).
    """
    check_shape(flow, [2, "H", "W"], "flow")
    check_shape(flow_back, [2, "H", "W"], "flow_back")
    _, H, W = flow.shape
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    up, vp = u + flow[0], v + flow[1]
    # grid_sample coordinates with align_corners=True: -1 = centre of pixel 0, +1 = centre of pixel W-1.
    grid = torch.stack([2 * up / max(W - 1, 1) - 1, 2 * vp / max(H - 1, 1) - 1], -1)[None]
    back = F.grid_sample(flow_back[None].float(), grid, mode="bilinear", padding_mode="border", align_corners=True)[0]
    err = (flow + back).norm(dim=0)
    inside = (up >= 0) & (up <= W - 1) & (vp >= 0) & (vp <= H - 1)
    return torch.where(inside, err, torch.full_like(err, float("inf")))


def flow_covariance(
    image: torch.Tensor,
    params: ConfidenceParams,
    fb_error: torch.Tensor | None = None,
) -> torch.Tensor:
    """Per-pixel flow covariance ``C_v`` (H, W, 2, 2), pixels^2, symmetric positive definite.

    Args:
        image: the current image (3, H, W) RGB in [0, 1] (or grey (H, W)); the flow is defined on
            its pixel grid.
        params: method and its parameters (see :class:`ConfidenceParams`).
        fb_error: optional forward-backward round-trip error (H, W), pixels (``inf`` = unchecked
            / occluded); adds ``(fb_weight * e)^2 I`` before clipping.

    Returns:
        (H, W, 2, 2) float32 covariance; eigenvalues in ``[sigma_min^2, sigma_max^2]``
        (``constant``: exactly ``sigma^2 I`` unless ``fb_error`` is given).
    """
    gray = to_gray(image)
    H, W = gray.shape
    check_finite(gray, "image")
    eye = torch.eye(2, dtype=torch.float32)
    if params.method == "constant":
        cov = (params.sigma**2) * eye.expand(H, W, 2, 2).clone()
        if fb_error is None:
            return cov
    else:
        J = structure_tensor(gray, params.window_sigma).double()
        # Effective number of pixels of a normalised Gaussian window: 1 / sum(w^2) = 4 pi sigma^2.
        n_eff = 4.0 * math.pi * params.window_sigma**2
        # Information matrix N J / noise^2 plus a prior of sigma_max^2: a textureless window gets sigma_max^2.
        info = J * (n_eff / params.noise**2) + (1.0 / params.sigma_max**2) * torch.eye(2, dtype=torch.float64)
        cov = torch.linalg.inv(info).float()
    if fb_error is not None:
        check_shape(fb_error, [H, W], "fb_error")
        e = torch.nan_to_num(fb_error.float(), nan=float("inf"), posinf=float("inf"))
        # An unchecked / occluded pixel gets the ceiling: inf -> sigma_max before squaring.
        e = torch.clamp(params.fb_weight * e, max=params.sigma_max)
        cov = cov + (e * e)[..., None, None] * eye
    return _clip_eigenvalues(cov, params.sigma_min**2, params.sigma_max**2)


def _clip_eigenvalues(cov: torch.Tensor, lo: float, hi: float) -> torch.Tensor:
    """Clip the eigenvalues of symmetric 2x2 matrices (..., 2, 2) to ``[lo, hi]`` (closed form)."""
    a, b, c = cov[..., 0, 0].double(), 0.5 * (cov[..., 0, 1] + cov[..., 1, 0]).double(), cov[..., 1, 1].double()
    mean = 0.5 * (a + c)
    rad = torch.sqrt((0.5 * (a - c)) ** 2 + b * b)
    l1, l2 = mean + rad, mean - rad  # l1 >= l2
    # Eigenvector of l1: (b, l1 - a) or (l1 - c, b); choose the better-conditioned one.
    v1 = torch.stack([b, l1 - a], -1)
    v1b = torch.stack([l1 - c, b], -1)
    use_b = v1b.norm(dim=-1) > v1.norm(dim=-1)
    v1 = torch.where(use_b[..., None], v1b, v1)
    n = v1.norm(dim=-1, keepdim=True)
    iso = (n[..., 0] < 1e-30)
    v1 = torch.where(iso[..., None], torch.tensor([1.0, 0.0], dtype=v1.dtype).expand_as(v1), v1 / n.clamp_min(1e-300))
    v2 = torch.stack([-v1[..., 1], v1[..., 0]], -1)
    l1, l2 = l1.clamp(lo, hi), l2.clamp(lo, hi)
    out = l1[..., None, None] * v1[..., :, None] * v1[..., None, :] + l2[..., None, None] * v2[..., :, None] * v2[..., None, :]
    return out.float()
