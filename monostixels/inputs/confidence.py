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

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from monostixels._checks import InputError, check_finite_fast, check_shape
from monostixels.core.grey import to_gray  # the structure tensor's grey image; named here as before

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


def structure_tensor(gray: torch.Tensor, window_sigma: float) -> torch.Tensor:
    """Gaussian-windowed structure tensor ``J = <∇I ∇I^T>`` (H, W, 2, 2) of a grey image (H, W).

    Gradients are central differences (Sobel normalised to intensity per pixel, ``/ 8``); the
    window is a Gaussian of standard deviation ``window_sigma`` pixels, normalised to sum 1, so
    ``J`` is a weighted *mean* (units: intensity^2 / pixel^2). Borders replicate the image.
    """
    check_shape(gray, ["H", "W"], "grey image")
    jxx, jxy, jyy = (torch.from_numpy(x) for x in _structure_tensor_parts(gray.float().numpy(), window_sigma))
    return torch.stack([torch.stack([jxx, jxy], -1), torch.stack([jxy, jyy], -1)], -2)


def _structure_tensor_parts(gray: np.ndarray, window_sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(J_xx, J_xy, J_yy)`` (H, W) float32 of :func:`structure_tensor` (OpenCV filters: single-threaded
    and much faster than the same filters as torch ops), strided views of one (H, W, 3) array."""
    g = np.ascontiguousarray(gray, dtype=np.float32)
    k = _odd_kernel_size(window_sigma)
    if g.ndim != 2 or min(g.shape) < k:
        # OpenCV's border handling is not safe for a window larger than the image (a segfault on
        # 40 x 12 frames): fail with the sizes instead.
        raise InputError(f"structure tensor: grey image of shape {g.shape} is smaller than its {k}x{k} window "
                         f"(window_sigma {window_sigma} px); need a 2-D image of at least {k}x{k} px")
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8.0, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 8.0, borderType=cv2.BORDER_REPLICATE)
    # The products written into one H x W x 3 array and blurred in place: every fresh full-size
    # temporary costs its page faults, several times the arithmetic on a frame (same values).
    prods = np.empty(g.shape + (3,), dtype=np.float32)
    np.multiply(gx, gx, out=prods[..., 0])
    np.multiply(gx, gy, out=prods[..., 1])
    np.multiply(gy, gy, out=prods[..., 2])
    cv2.GaussianBlur(prods, (k, k), window_sigma, dst=prods, sigmaY=window_sigma, borderType=cv2.BORDER_REPLICATE)
    return prods[..., 0], prods[..., 1], prods[..., 2]


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
    check_finite_fast(gray, "image")
    # Closed-form 2x2 algebra on the three entries (a, b; b, c), float64 numpy: the same numbers as
    # batched linalg on (H, W, 2, 2) tensors, several times faster and without torch's thread pool
    # (which stalls on a shared machine).
    if params.method == "constant":
        if fb_error is None:
            return (params.sigma**2) * torch.eye(2, dtype=torch.float32).expand(H, W, 2, 2).clone()
        a = np.full((H, W), params.sigma**2)
        b = np.zeros((H, W))
        c = a.copy()
    else:
        # Each step into arrays made here (in place where an input is not read again): the same
        # operations in the same order as the written formulas, without a fresh full-size
        # temporary for each (their page faults cost more than the arithmetic).
        ia, ib, ic = (x.astype(np.float64) for x in _structure_tensor_parts(gray.numpy(), params.window_sigma))
        # Effective number of pixels of a normalised Gaussian window: 1 / sum(w^2) = 4 pi sigma^2.
        n_eff = 4.0 * math.pi * params.window_sigma**2
        # Information matrix N J / noise^2 plus a prior of sigma_max^2: a textureless window gets sigma_max^2.
        k = n_eff / params.noise**2
        prior = 1.0 / params.sigma_max**2
        ia *= k
        ia += prior
        ib *= k
        ic *= k
        ic += prior
        det = ia * ic  # det = ia ic - ib^2 > 0: J is positive semi-definite, the prior positive definite
        det -= np.multiply(ib, ib, out=np.empty_like(det))
        # (a, b, c) = (ic, -ib, ia) / det
        a = np.divide(ic, det, out=ic)
        b = np.divide(np.negative(ib, out=ib), det, out=ib)
        c = np.divide(ia, det, out=ia)
    if fb_error is not None:
        check_shape(fb_error, [H, W], "fb_error")
        e = torch.nan_to_num(fb_error.float(), nan=float("inf"), posinf=float("inf"))
        # An unchecked / occluded pixel gets the ceiling: inf -> sigma_max before squaring.
        e = torch.clamp(params.fb_weight * e, max=params.sigma_max).double().numpy()
        e2 = e * e
        a += e2
        c += e2
    return _clip_eigenvalues(a, b, c, params.sigma_min**2, params.sigma_max**2, scratch=True)


def _clip_eigenvalues(a: np.ndarray, b: np.ndarray, c: np.ndarray, lo: float, hi: float, *,
                      scratch: bool = False) -> torch.Tensor:
    """Symmetric 2x2 matrices ``(a, b; b, c)`` (each (H, W)) with eigenvalues clipped to ``[lo, hi]``,
    as (H, W, 2, 2) float32.

    With ``C = m I + D`` (``m`` the mean eigenvalue, ``D`` the trace-free part of norm ``r`` = half
    the eigenvalue gap), clipping keeps the eigenvectors: ``C' = m' I + (r' / r) D`` with ``m'``, ``r'``
    from the clipped eigenvalues; ``r' <= r`` (clipping is 1-Lipschitz), and ``r = 0`` (isotropic)
    gives ``D = 0``.

    ``scratch``: ``a``, ``b``, ``c`` are float64 arrays the caller no longer needs, and are overwritten
    (no full-size temporaries: see :func:`flow_covariance`); else they are copied first.
    """
    if not scratch:
        a, b, c = (np.array(x, dtype=np.float64) for x in (a, b, c))
    m = np.add(a, c, out=np.empty_like(a))
    m *= 0.5
    h = np.subtract(a, c, out=a)
    h *= 0.5
    l1 = np.multiply(b, b, out=np.empty_like(b))
    r = np.multiply(h, h, out=c)
    r += l1
    np.sqrt(r, out=r)
    np.clip(np.add(m, r, out=l1), lo, hi, out=l1)
    l2 = np.clip(np.subtract(m, r, out=m), lo, hi, out=m)
    m2 = np.add(l1, l2, out=np.empty_like(l1))
    m2 *= 0.5
    r2 = np.subtract(l1, l2, out=l1)
    r2 *= 0.5
    l2.fill(0.0)
    ratio = np.divide(r2, r, out=l2, where=r > 0)
    out = np.empty(a.shape + (2, 2), dtype=np.float32)
    h *= ratio
    b *= ratio
    np.add(m2, h, out=out[..., 0, 0], casting="same_kind")
    np.subtract(m2, h, out=out[..., 1, 1], casting="same_kind")
    out[..., 0, 1] = b
    out[..., 1, 0] = b
    return torch.from_numpy(out)
