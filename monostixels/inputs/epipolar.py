"""Two-view geometry of the monocular camera motion (:mod:`monostixels.inputs.motion`, steps 2-3).

The rotation-only fit that tells a standing or turning camera, the Sampson distance of ray pairs to an
essential matrix, the nonlinear refinement of ``(R, t̂)`` (free, or as a car moves) and the cheirality
test of the sign of ``t``.
Convention: ``X_prev = R X_cur + t`` (docs/conventions.md, section 2); rays with ``z = 1``.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from monostixels.core.geometry import ground_basis
from monostixels.inputs.ground import rays

__all__ = ["car_axes", "car_offsets_deg", "fit_rotation", "max_eigenvalue_at_most", "sampson", "skew", "refine_pose",
           "refine_car_pose", "cheirality_sign"]


def _project(K: np.ndarray, X: np.ndarray) -> np.ndarray:
    x = X @ K.T
    return x[:, :2] / x[:, 2:3]


def fit_rotation(K: np.ndarray, p_cur: np.ndarray, p_prev: np.ndarray, iters: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Best rotation-only motion (trimmed Procrustes on unit rays); returns R and pixel residuals (N,)."""
    a = rays(K, p_cur)
    b = rays(K, p_prev)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    use = np.ones(len(a), dtype=bool)
    R = np.eye(3)
    for _ in range(iters):
        U, _, Vt = np.linalg.svd(b[use].T @ a[use])  # maximise sum b^T R a
        R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        res = np.linalg.norm(_project(K, a @ R.T) - p_prev, axis=1)
        use = res <= max(np.median(res) * 2.0, 1e-6)
    return R, res


def max_eigenvalue_at_most(cov: np.ndarray, bound: float) -> np.ndarray:
    """Mask (N,): the largest eigenvalue of each symmetric (N, 2, 2) matrix is <= ``bound``.

    ``bound I - C`` positive semi-definite: both diagonal entries and the determinant >= 0
    (the lower triangle is read, as ``eigvalsh`` reads it). For float32 covariances this is exact
    in float64 (the products need at most ~50 bits), where an eigen-solver rounds; much faster
    than ``torch.linalg.eigvalsh`` on the grid vectors of a frame.
    """
    c = cov.astype(np.float64)
    pa, pd = bound - c[:, 0, 0], bound - c[:, 1, 1]
    b = c[:, 1, 0]
    return (pa >= 0) & (pd >= 0) & (pa * pd >= b * b)


def sampson(E: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Sampson distance (N,) of ray pairs (z = 1) under ``b^T E a = 0``, in normalised units."""
    Ea = a @ E.T
    Etb = b @ E
    num = np.sum(b * Ea, axis=1)
    den = Ea[:, 0] ** 2 + Ea[:, 1] ** 2 + Etb[:, 0] ** 2 + Etb[:, 1] ** 2
    return num / np.sqrt(np.maximum(den, 1e-30))


def skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def refine_pose(R: np.ndarray, t: np.ndarray, a: np.ndarray, b: np.ndarray, f_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Nonlinear refinement of ``(R, t̂)`` minimising the Sampson distance (soft-L1) over ray pairs."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    # t on the unit sphere: t = normalize(t0 + B beta), B a basis of the tangent plane at t0.
    t0 = t / np.linalg.norm(t)
    B = np.linalg.svd(t0[None])[2][1:].T  # (3, 2)

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Rx = Rotation.from_rotvec(x[:3]).as_matrix() @ R
        tx = t0 + B @ x[3:]
        return Rx, tx / np.linalg.norm(tx)

    def fun(x: np.ndarray) -> np.ndarray:
        Rx, tx = unpack(x)
        return sampson(skew(tx) @ Rx, a, b)

    sol = least_squares(fun, np.zeros(5), loss="soft_l1", f_scale=f_scale, method="trf", x_scale="jac")
    return unpack(sol.x)


def car_axes(n_g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The forward and right axes (3,), (3,) of a car on the road plane with unit normal ``n_g`` (3,) (down):
    the camera's ``z`` and ``n_g x z`` laid on the plane (:func:`monostixels.core.geometry.ground_basis`)."""
    B = ground_basis(torch.from_numpy(np.asarray(n_g, dtype=np.float64))).numpy()
    return B[:, 1], B[:, 0]


def _yaw(R: np.ndarray, n_g: np.ndarray) -> float:
    """The rotation of ``R`` (3, 3) about the road normal ``n_g`` (radians): its rotation vector along ``n_g``."""
    from scipy.spatial.transform import Rotation

    return float(Rotation.from_matrix(R).as_rotvec() @ n_g)


def car_offsets_deg(R: np.ndarray, t: np.ndarray, n_g: np.ndarray) -> tuple[float, float]:
    """How far (degrees) the travel direction ``t`` (3,) lies from a car's on the road plane (normal ``n_g``,
    down): ``(azimuth, elevation)``. A car moves along its heading, so between two frames its camera's
    chord turns by half the yaw of ``R``: the azimuth (0-90) is the angle on the plane between the axis of
    ``t`` and that chord (``t`` and ``-t`` alike: the sign is decided elsewhere); the elevation (0-90) the
    angle between ``t`` and the plane."""
    f, r = car_axes(n_g)
    az = math.atan2(float(t @ r), float(t @ f)) - _yaw(R, n_g) / 2.0
    az = abs((az + math.pi / 2) % math.pi - math.pi / 2)  # the axis: t and -t alike
    el = math.asin(min(1.0, abs(float(t @ n_g)) / float(np.linalg.norm(t))))
    return math.degrees(az), math.degrees(el)


def refine_car_pose(R: np.ndarray, n_g: np.ndarray, a: np.ndarray, b: np.ndarray, f_scale: float,
                    max_elevation_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t̂)`` of a camera on a car (Sampson distance, soft-L1, over ray pairs ``a``, ``b`` (N, 3)), from
    the rotation ``R``: the translation is the car's chord, its heading (``car_axes``) turned by half the
    yaw of the rotation, lifted off the road plane by at most ``max_elevation_deg`` (the camera's pitch on
    the car and the road's grade). Four degrees of freedom where the free pose has five: the one taken away
    is the lateral direction, which trades against the yaw where the parallax is small (Scaramuzza et al.,
    ICRA 2009)."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    f, r = car_axes(n_g)

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Rx = Rotation.from_rotvec(x[:3]).as_matrix() @ R
        h = _yaw(Rx, n_g) / 2.0
        tx = math.cos(h) * f + math.sin(h) * r + x[3] * n_g
        return Rx, tx / np.linalg.norm(tx)

    def fun(x: np.ndarray) -> np.ndarray:
        Rx, tx = unpack(x)
        return sampson(skew(tx) @ Rx, a, b)

    e = math.tan(math.radians(max_elevation_deg))
    lo, hi = np.array([-np.inf, -np.inf, -np.inf, -e]), np.array([np.inf, np.inf, np.inf, e])
    sol = least_squares(fun, np.zeros(4), loss="soft_l1", f_scale=f_scale, method="trf", x_scale="jac", bounds=(lo, hi))
    return unpack(sol.x)


def cheirality_sign(R: np.ndarray, t: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """+1 if ``(R, t)`` puts more of the ray pairs (current ``a``, previous ``b``, (N, 3)) in front of both
    cameras than ``(R, -t)``, else -1. Depths from ``λ_a R a + t = λ_b b``: ``λ_a = -(b × t)·(b × Ra) /
    |b × Ra|²``, ``λ_b = (Ra × t)·(Ra × b) / |Ra × b|²`` (both change sign with ``t``)."""
    Ra = a @ R.T
    bra = np.cross(b, Ra)
    den = np.maximum(np.einsum("ij,ij->i", bra, bra), 1e-30)
    lam_a = -np.einsum("ij,ij->i", np.cross(b, t[None]), bra) / den
    lam_b = -np.einsum("ij,ij->i", np.cross(Ra, t[None]), bra) / den
    front = int(np.count_nonzero((lam_a > 0) & (lam_b > 0)))
    behind = int(np.count_nonzero((lam_a < 0) & (lam_b < 0)))
    return 1.0 if front >= behind else -1.0
