"""Camera, camera motion, stixel planes and stixel homographies.

Conventions (docs/conventions.md, section 2), restated once here and relied on everywhere:

- Camera frame x right, y down, z forward (OpenCV). Pixel ``x = (u, v, 1)``, ``v`` grows downward.
- Flow maps a pixel of the *current* image to the *previous* one: ``x_prev = x + f(x)``.
- Camera motion ``(R, t)`` maps current-camera coordinates of a static point to previous-camera
  coordinates: ``X_prev = R X_cur + t`` (metres).
- A stixel lies on the plane ``n^T X = d`` (``d > 0``, metres) with inverse depth label ``p = 1/d``.
  Ground: ``n = n_g`` (points from the camera down to the ground), ``d`` = camera height above that
  piece of ground. Upright object: ``n`` = the horizontal viewing direction of the column, ``d`` =
  horizontal distance. Sky: ``p = 0``.
- Static stixel: ``H = K (R + p t n^T) K^-1``; dynamic stixel that moves by ``Δ`` on the ground:
  ``X_prev = R (X_cur - Δ) + t``, ``H = K (R + g n^T) K^-1`` with ``g = p (t - R Δ) = B (t̃x, t̃y)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from monostixels._checks import InputError, check_finite, check_rotation, check_shape

__all__ = [
    "KITTI_CAMERA_HEIGHT_M",
    "Camera",
    "Motion",
    "angle_deg",
    "intrinsics",
    "pixel_rays",
    "ground_basis",
    "object_normals",
    "horizon_row",
    "homography",
    "dynamic_homography",
    "apply_homography",
    "static_dof_system",
    "solve_static_dof",
    "dynamic_dof_system",
    "solve_dynamic_dof",
    "depth_on_ground",
    "dynamic_motion",
    "stixel_motion",
    "ray_plane_depth",
    "rotation_yaw",
]

#: Mounting height of the KITTI colour cameras above the road (metres; KITTI setup description).
KITTI_CAMERA_HEIGHT_M = 1.65


def intrinsics(fx: float, fy: float, cx: float, cy: float, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Pinhole matrix ``K`` (3, 3) from focal lengths and principal point (pixels)."""
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype)


def rotation_yaw(yaw: float, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Rotation (3, 3) about the camera y axis (down) by ``yaw`` radians."""
    c, s = math.cos(yaw), math.sin(yaw)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=dtype)


@dataclass
class Camera:
    """Intrinsics and mounting of one camera.

    Attributes:
        K: pinhole matrix (3, 3), pixels.
        height: camera height above the reference ground (metres).
        ground_normal: unit normal ``n_g`` (3,) of the ground, pointing from the camera down to
            the ground (``(0, 1, 0)`` for a level camera; a pitched camera tilts it).
    """

    K: torch.Tensor
    height: float = KITTI_CAMERA_HEIGHT_M
    ground_normal: torch.Tensor | None = None

    def __post_init__(self) -> None:
        check_shape(self.K, [3, 3], "K")
        check_finite(self.K, "K")
        K = self.K.double()
        if not (K[0, 0] > 0 and K[1, 1] > 0 and abs(float(K[2, 2]) - 1.0) < 1e-9 and float(K[2, :2].abs().max()) == 0.0):
            raise InputError(f"K: not a pinhole intrinsics matrix (fx, fy > 0, last row 0 0 1): {K.tolist()}")
        if not (math.isfinite(self.height) and self.height > 0):
            raise InputError(f"camera height: must be a positive number of metres, got {self.height}")
        if self.ground_normal is None:
            self.ground_normal = torch.tensor([0.0, 1.0, 0.0], dtype=self.K.dtype)
        check_shape(self.ground_normal, [3], "ground_normal")
        check_finite(self.ground_normal, "ground_normal")
        nrm = float(self.ground_normal.double().norm())
        if abs(nrm - 1.0) > 1e-6 or float(self.ground_normal[1]) <= 0:
            raise InputError(f"ground_normal: must be a unit vector pointing down (+y), got {self.ground_normal.tolist()}")

    @staticmethod
    def from_pitch(K: torch.Tensor, height: float = KITTI_CAMERA_HEIGHT_M, pitch: float = 0.0) -> "Camera":
        """Camera whose optical axis is pitched by ``pitch`` radians (positive = looking down)."""
        n = torch.tensor([0.0, math.cos(pitch), math.sin(pitch)], dtype=K.dtype)
        return Camera(K=K, height=height, ground_normal=n)


@dataclass
class Motion:
    """Camera motion of a frame pair: ``X_prev = R X_cur + t`` (metres).

    Attributes:
        R: rotation (3, 3).
        t: translation (3,), metres.
    """

    R: torch.Tensor
    t: torch.Tensor

    def __post_init__(self) -> None:
        check_rotation(self.R, "R (camera motion)")
        check_shape(self.t, [3], "t (camera motion)")
        check_finite(self.t, "t (camera motion)")

    @property
    def translation_norm(self) -> float:
        """Length of the camera translation (metres)."""
        return float(self.t.double().norm())


def pixel_rays(K: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Viewing rays ``K^-1 (u, v, 1)`` (..., 3) with unit z for pixels ``u``, ``v`` (...).

    Convention: ``(u, v)`` are pixel coordinates with ``v`` downward; a ray has ``z = 1``.
    """
    fx, fy, cx, cy = K[..., 0, 0], K[..., 1, 1], K[..., 0, 2], K[..., 1, 2]
    s = K[..., 0, 1]
    y = (v - cy) / fy
    x = (u - cx - s * y) / fx
    return torch.stack([x, y, torch.ones_like(x)], dim=-1)


def ground_basis(n_g: torch.Tensor) -> torch.Tensor:
    """Orthonormal basis ``B`` (..., 3, 2) of the ground plane orthogonal to ``n_g`` (..., 3).

    Column 0 points right (camera x projected onto the plane), column 1 forward (camera z
    projected), so ``g = B (t̃x, t̃y)`` has lateral and longitudinal components.
    """
    ez = torch.zeros_like(n_g)
    ez[..., 2] = 1.0
    fwd = ez - (ez * n_g).sum(-1, keepdim=True) * n_g
    fwd = fwd / fwd.norm(dim=-1, keepdim=True)
    right = torch.cross(n_g, fwd, dim=-1)
    return torch.stack([right, fwd], dim=-1)


def horizon_row(K: torch.Tensor, n_g: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Row ``v`` (...) where the viewing ray of column ``u`` is parallel to the ground."""
    r0 = pixel_rays(K, u, K[..., 1, 2].expand_as(u))
    # r(v) = r0 + (v - cy)/fy * e_y (zero skew assumed for this direction), r(v) . n_g = 0.
    return K[..., 1, 2] - K[..., 1, 1] * (r0 * n_g).sum(-1) / n_g[..., 1]


def object_normals(K: torch.Tensor, n_g: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Unit normals (..., 3) of upright stixels in columns ``u`` (...), facing the camera.

    Convention: the normal is the viewing ray of the column at its horizon row (the ray that is
    parallel to the ground), so it is orthogonal to ``n_g`` and points away from the camera;
    ``d = n^T X`` is the horizontal distance of the stixel.
    """
    v = horizon_row(K, n_g, u)
    r = pixel_rays(K, u, v)
    return r / r.norm(dim=-1, keepdim=True)


def homography(K: torch.Tensor, R: torch.Tensor, t: torch.Tensor, n: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Static stixel homography ``H = K (R + p t n^T) K^-1`` (..., 3, 3); ``x_prev ~ H x_cur``.

    Args:
        K: (..., 3, 3). R: (..., 3, 3). t: (..., 3) metres. n: (..., 3). p: (...) 1/metres.
    """
    M = R + p[..., None, None] * t[..., :, None] * n[..., None, :]
    return K @ M @ torch.linalg.inv(K)


def dynamic_homography(K: torch.Tensor, R: torch.Tensor, n: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Dynamic stixel homography ``H = K (R + g n^T) K^-1`` with ``g = p (t - R Δ)`` (..., 3)."""
    M = R + g[..., :, None] * n[..., None, :]
    return K @ M @ torch.linalg.inv(K)


def apply_homography(H: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Map pixels ``(u, v)`` (...) through ``H`` (..., 3, 3); returns ``(u', v')`` (...)."""
    x = torch.stack([u, v, torch.ones_like(u)], -1)
    y = (H @ x[..., None])[..., 0]
    return y[..., 0] / y[..., 2], y[..., 1] / y[..., 2]


def _flow_terms(K, R, u, v):
    """``a = K R K^-1 x`` (..., 3) and the ray ``K^-1 x`` (..., 3) of pixels (u, v)."""
    ray = pixel_rays(K, u, v)
    a = ((K @ R) @ ray[..., None])[..., 0]
    return a, ray


def static_dof_system(
    K: torch.Tensor, R: torch.Tensor, t: torch.Tensor, n: torch.Tensor,
    u: torch.Tensor, v: torch.Tensor, flow: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The linear system ``A p = b`` of one flow vector for a static stixel (1 DOF).

    From ``x_prev × (H x) = 0`` with ``H x = a + p s c``, ``a = K R K^-1 x``, ``s = n^T K^-1 x``,
    ``c = K t``: two equations ``p s (u' c_3 - c_1) = a_1 - u' a_3`` and the same in ``v'``.

    Args:
        K, R: (..., 3, 3); t, n: (..., 3); u, v: pixel (...); flow: (..., 2) current -> previous, px.

    Returns:
        A (..., 2) and b (..., 2).
    """
    a, ray = _flow_terms(K, R, u, v)
    s = (ray * n).sum(-1)
    c = (K @ t[..., None])[..., 0]
    up, vp = u + flow[..., 0], v + flow[..., 1]
    A = torch.stack([s * (up * c[..., 2] - c[..., 0]), s * (vp * c[..., 2] - c[..., 1])], -1)
    b = torch.stack([a[..., 0] - up * a[..., 2], a[..., 1] - vp * a[..., 2]], -1)
    return A, b


def solve_static_dof(A: torch.Tensor, b: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Least-squares ``p`` (...) of ``A p = b`` (A, b: (..., 2)); NaN where ``A`` is zero."""
    den = (A * A).sum(-1)
    p = (A * b).sum(-1) / den
    return torch.where(den > eps, p, torch.full_like(p, float("nan")))


def dynamic_dof_system(
    K: torch.Tensor, R: torch.Tensor, B: torch.Tensor, n: torch.Tensor,
    u: torch.Tensor, v: torch.Tensor, flow: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The system ``A (t̃x, t̃y) = b`` of one flow vector for a dynamic stixel (2 DOF).

    ``H x = a + s M τ`` with ``M = K B`` (3, 2): ``s (u' M_3 - M_1) τ = a_1 - u' a_3`` and in ``v'``.

    Returns:
        A (..., 2, 2) and b (..., 2).
    """
    a, ray = _flow_terms(K, R, u, v)
    s = (ray * n).sum(-1)
    M = K @ B  # (..., 3, 2)
    up, vp = u + flow[..., 0], v + flow[..., 1]
    row0 = s[..., None] * (up[..., None] * M[..., 2, :] - M[..., 0, :])
    row1 = s[..., None] * (vp[..., None] * M[..., 2, :] - M[..., 1, :])
    A = torch.stack([row0, row1], -2)
    b = torch.stack([a[..., 0] - up * a[..., 2], a[..., 1] - vp * a[..., 2]], -1)
    return A, b


def solve_dynamic_dof(A: torch.Tensor, b: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Exact ``τ = (t̃x, t̃y)`` (..., 2) of ``A τ = b`` (A (..., 2, 2)); NaN where singular."""
    det = A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0]
    tx = (A[..., 1, 1] * b[..., 0] - A[..., 0, 1] * b[..., 1]) / det
    ty = (A[..., 0, 0] * b[..., 1] - A[..., 1, 0] * b[..., 0]) / det
    tau = torch.stack([tx, ty], -1)
    ok = (det.abs() > eps)[..., None]
    return torch.where(ok, tau, torch.full_like(tau, float("nan")))


def depth_on_ground(
    K: torch.Tensor, n_obj: torch.Tensor, n_g: torch.Tensor, d_ground: torch.Tensor,
    u: torch.Tensor, v: torch.Tensor,
) -> torch.Tensor:
    """Inverse depth ``p`` (...) of an upright stixel whose bottom pixel ``(u, v)`` touches the ground.

    The ray through ``(u, v)`` meets the ground ``n_g^T X = d_ground`` at ``X``; ``p = 1 / (n_obj^T X)``.
    Rays at or above the horizon never meet the ground: ``p <= 0`` there.
    """
    ray = pixel_rays(K, u, v)
    return (ray * n_g).sum(-1) / (d_ground * (ray * n_obj).sum(-1))


def dynamic_motion(R: torch.Tensor, t: torch.Tensor, g: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Metric motion ``Δ`` (..., 3) of a dynamic stixel from ``g = p (t - R Δ)``: ``Δ = R^T (t - g / p)``."""
    return (R.transpose(-1, -2) @ (t - g / p[..., None])[..., None])[..., 0]


def stixel_motion(tau: torch.Tensor, p: torch.Tensor, n_g: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Metric motion ``Δ`` (n, 3) of dynamic stixels from their ``(t̃x, t̃y)`` ``tau`` (n, 2) and inverse depths
    ``p`` (n,), on the road plane of normal ``n_g`` (3,), the camera moving by ``R`` (3, 3), ``t`` (3,) (float64):
    ``g = B tau`` (:func:`ground_basis`), then :func:`dynamic_motion`."""
    g = tau.double() @ ground_basis(n_g.double()).T
    R, t = R.double(), t.double()
    return dynamic_motion(R.expand(g.shape[0], 3, 3), t.expand_as(g), g, p.double())


def ray_plane_depth(K: torch.Tensor, u: torch.Tensor, v: torch.Tensor, n: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Depth ``z`` (...) of pixel ``(u, v)`` on the plane ``p n^T X = 1``: ``z = 1 / (p n^T K^-1 x)``.

    Negative where the plane lies behind the camera along that ray (e.g. ground above the
    horizon); ``inf`` where ``p = 0`` (sky).
    """
    ray = pixel_rays(K, u, v)
    return 1.0 / (p * (ray * n).sum(-1))


def angle_deg(a: torch.Tensor, b: torch.Tensor) -> float:
    """Angle (degrees) between two vectors of the same length (e.g. (3,) translations); NaN if either is zero."""
    na, nb = float(a.norm()), float(b.norm())
    if na <= 0 or nb <= 0:
        return math.nan
    return math.degrees(math.acos(max(-1.0, min(1.0, float((a @ b) / (na * nb))))))
