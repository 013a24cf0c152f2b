"""The structure-from-motion baseline: per-pixel triangulation of dense flow and camera motion.

Paper ("Metric and Baseline"): "a traditional structure-from-motion method by performing a
triangulation (Hartley & Zisserman) for each image point based on a dense optical flow field and
camera motion", fed with exactly the same flow and camera motion as the mono-stixels.

Method: the midpoint method (Hartley & Zisserman, sec. 12.5 discussion): for each pixel the
viewing ray of the current camera and the ray of its flow correspondence in the previous camera
are intersected in the least-squares sense, and the midpoint of their common perpendicular is
taken. With exact flow from a static scene the rays intersect and the midpoint is the true point.

Convention (docs/conventions.md, section 2): flow maps current -> previous, ``x_prev = x + f(x)``;
camera motion ``X_prev = R X_cur + t`` (metres). The returned depth is ``z`` in the *current*
camera.

Failure mode by design (what the paper shows): a point that moves in the world is triangulated
as if it were static. An epipolar-conformant mover (e.g. a vehicle driving ahead along the
camera's direction of travel) gets a wrong but plausible-looking depth; one that moves faster
than the camera away from it triangulates behind the camera (negative depth).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import torch

from monostixels._checks import InputError, check_finite, check_shape
from monostixels.core.geometry import Motion, pixel_rays

__all__ = ["DEFAULT_MIN_PARALLAX_RAD", "Triangulation", "triangulate", "triangulate_depth", "triangulate_points"]

logger = logging.getLogger(__name__)

#: Rays whose angle is below this (radians) carry no depth. A numerical guard only: 1 px at the
#: KITTI focal length (~721 px) subtends 1.4e-3 rad (see conf/eval/default.yaml).
DEFAULT_MIN_PARALLAX_RAD = 1e-6


@dataclass
class Triangulation:
    """Result of the per-pixel triangulation.

    Attributes:
        depth: (H, W) ``z`` of the triangulated point in the current camera, metres. Encoding of
            invalid pixels (``valid`` False): ``+inf`` where the rays are (nearly) parallel
            (no parallax: points at infinity, the epipole, no camera translation); a negative
            value ``-|z|`` where the point lies behind the current or the previous camera.
        valid: (H, W) bool, a finite point in front of both cameras.
        parallax: (H, W) angle between the two viewing rays, radians.
    """

    depth: torch.Tensor
    valid: torch.Tensor
    parallax: torch.Tensor


def triangulate(
    flow: torch.Tensor,
    K: torch.Tensor,
    motion: Motion,
    *,
    min_parallax_rad: float = DEFAULT_MIN_PARALLAX_RAD,
) -> Triangulation:
    """Triangulate every pixel of the current image from its flow and the camera motion.

    Convention: pixel ``(u, v)`` has its flow correspondence at ``(u + f_u, v + f_v)`` in the
    previous image; ``X_prev = R X_cur + t``. The previous camera centre in current coordinates
    is ``c = -R^T t`` and a previous-camera ray ``r'`` is ``R^T r'`` in current coordinates.
    Computed in float64; returned in the dtype of ``flow``.

    Args:
        flow: (2, H, W) current -> previous optical flow, pixels.
        K: (3, 3) camera intrinsics (same camera for both frames).
        motion: camera motion of the pair.
        min_parallax_rad: rays with a smaller angle are invalid (depth ``+inf``).

    Returns:
        :class:`Triangulation` with depth (H, W) metres, valid (H, W), parallax (H, W) radians.
    """
    check_shape(flow, [2, "H", "W"], "flow")
    check_finite(flow, "flow")
    check_shape(K, [3, 3], "K")
    check_finite(K, "K")
    if not isinstance(motion, Motion):
        raise InputError(f"motion: expected a monostixels.core.geometry.Motion, got {type(motion).__name__}")
    if not (math.isfinite(min_parallax_rad) and min_parallax_rad >= 0):
        raise InputError(f"min_parallax_rad: must be a non-negative number, got {min_parallax_rad}")
    out_dtype = flow.dtype if flow.is_floating_point() else torch.float32
    f = flow.double()
    Kd = K.double().to(f.device)
    R = motion.R.double().to(f.device)
    t = motion.t.double().to(f.device)
    H, W = f.shape[-2:]
    v, u = torch.meshgrid(
        torch.arange(H, dtype=torch.float64, device=f.device),
        torch.arange(W, dtype=torch.float64, device=f.device),
        indexing="ij",
    )
    depth, valid, parallax = triangulate_points(Kd, R, t, u, v, f[0], f[1], min_parallax_rad)
    if motion.translation_norm == 0.0:
        logger.warning("SfM baseline: camera translation is zero, no pixel can be triangulated")
    return Triangulation(depth=depth.to(out_dtype), valid=valid, parallax=parallax.to(out_dtype))


def triangulate_points(K: torch.Tensor, R: torch.Tensor, t: torch.Tensor, u: torch.Tensor, v: torch.Tensor,
                       fu: torch.Tensor, fv: torch.Tensor, min_parallax_rad: float = DEFAULT_MIN_PARALLAX_RAD
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The midpoint triangulation of :func:`triangulate` for pixels ``(u, v)`` with flow ``(fu, fv)`` (any
    one shape, e.g. (H, W) or (N,); float64 throughout, as ``K``, ``R`` and ``t``).

    Returns ``(depth, valid, parallax)`` of that shape, encoded as :class:`Triangulation` (metres;
    ``+inf`` without parallax, ``-|z|`` behind a camera; radians).
    """
    d0 = pixel_rays(K, u, v)  # ... x 3, current ray (z = 1)
    d1 = pixel_rays(K, u + fu, v + fv) @ R  # ... x 3, previous ray in current coords (R^T r')
    c1 = -(R.T @ t)  # previous camera centre in current coordinates
    # Closest points s0 d0 and c1 + s1 d1 of the two rays: minimise |s0 d0 - c1 - s1 d1|^2.
    a = (d0 * d0).sum(-1)
    b = (d0 * d1).sum(-1)
    c = (d1 * d1).sum(-1)
    d = (d0 * c1).sum(-1)
    e = (d1 * c1).sum(-1)
    den = a * c - b * b  # = |d0|^2 |d1|^2 sin^2(angle)
    sin2 = (den / (a * c)).clamp(0.0, 1.0)
    parallax = torch.asin(sin2.sqrt())
    no_parallax = parallax <= min_parallax_rad
    safe = torch.where(no_parallax, torch.ones_like(den), den)
    s0 = (c * d - b * e) / safe
    s1 = (b * d - a * e) / safe
    X = 0.5 * (s0[..., None] * d0 + c1 + s1[..., None] * d1)  # midpoint, current coords
    z = X[..., 2]
    z_prev = (X @ R.T + t)[..., 2]
    behind = (z <= 0) | (z_prev <= 0)
    depth = torch.where(behind, -z.abs(), z)
    depth = torch.where(no_parallax, torch.full_like(z, math.inf), depth)
    return depth, ~behind & ~no_parallax, parallax


def triangulate_depth(
    flow: torch.Tensor,
    K: torch.Tensor,
    motion: Motion,
    *,
    min_parallax_rad: float = DEFAULT_MIN_PARALLAX_RAD,
) -> torch.Tensor:
    """Depth (H, W) of the SfM baseline in the current camera, metres.

    Same as ``triangulate(...).depth``: invalid pixels are ``+inf`` (no parallax) or negative
    (behind a camera); the depth metrics clamp both to the evaluation range, the depth colour
    map paints them black.

    Args:
        flow: (2, H, W) current -> previous optical flow, pixels.
        K: (3, 3) intrinsics.
        motion: camera motion ``X_prev = R X_cur + t``.
        min_parallax_rad: rays with a smaller angle give ``+inf``.
    """
    return triangulate(flow, K, motion, min_parallax_rad=min_parallax_rad).depth
