"""Convention tests: asymmetric intrinsics (fx != fy, cx != cy), non-zero yaw, float64."""
from __future__ import annotations

import math

import pytest
import torch

from monostixels._checks import InputError
from monostixels.core.geometry import (
    Camera,
    Motion,
    apply_homography,
    depth_on_ground,
    dynamic_dof_system,
    dynamic_homography,
    dynamic_motion,
    ground_basis,
    homography,
    horizon_row,
    intrinsics,
    object_normals,
    pixel_rays,
    ray_plane_depth,
    rotation_yaw,
    solve_dynamic_dof,
    solve_static_dof,
    static_dof_system,
)

K = intrinsics(718.0, 702.5, 611.2, 181.9)
R = rotation_yaw(math.radians(1.7)) @ torch.tensor(
    [[1, 0, 0], [0, math.cos(0.01), -math.sin(0.01)], [0, math.sin(0.01), math.cos(0.01)]], dtype=torch.float64)
T = torch.tensor([0.05, -0.01, 1.2], dtype=torch.float64)
PITCH = 0.03
CAM = Camera.from_pitch(K, height=1.65, pitch=PITCH)
N_G = CAM.ground_normal


def _rotation_about(axis: torch.Tensor, angle: float) -> torch.Tensor:
    """Rodrigues rotation (3, 3) by ``angle`` radians about the unit ``axis``."""
    k = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def project(X: torch.Tensor) -> torch.Tensor:
    x = (K @ X[..., None])[..., 0]
    return x[..., :2] / x[..., 2:]


def test_pixel_rays_hand_computed():
    r = pixel_rays(K, torch.tensor(711.2, dtype=torch.float64), torch.tensor(141.9, dtype=torch.float64))
    assert torch.allclose(r, torch.tensor([100 / 718.0, -40 / 702.5, 1.0], dtype=torch.float64))


def test_ground_basis_and_normals_are_orthogonal():
    B = ground_basis(N_G)
    assert torch.allclose(B.T @ B, torch.eye(2, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(B.T @ N_G, torch.zeros(2, dtype=torch.float64), atol=1e-12)
    assert float(B[0, 0]) > 0.99 and float(B[2, 1]) > 0.99  # right, forward
    u = torch.tensor([10.0, 611.2, 1200.0], dtype=torch.float64)
    n = object_normals(K, N_G, u)
    assert torch.allclose(n @ N_G, torch.zeros(3, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(n.norm(dim=-1), torch.ones(3, dtype=torch.float64))
    # The normal is the viewing ray of the column at its horizon row.
    v = horizon_row(K, N_G, u)
    r = pixel_rays(K, u, v)
    assert torch.allclose(r / r.norm(dim=-1, keepdim=True), n, atol=1e-12)
    assert float(n[0, 0]) < 0 < float(n[2, 0])  # a left column looks left


def _points_on_plane(n: torch.Tensor, d: float, g: torch.Generator) -> torch.Tensor:
    """Random 3D points (N, 3) on n^T X = d in front of the camera."""
    pts = []
    while len(pts) < 40:
        ray = torch.cat([torch.rand(2, generator=g, dtype=torch.float64) - 0.5, torch.ones(1, dtype=torch.float64)])
        s = float(ray @ n)
        if s > 1e-3:
            X = ray * d / s
            if 1.0 < float(X[2]) < 80:
                pts.append(X)
    return torch.stack(pts)


@pytest.mark.parametrize("kind", ["ground", "object", "dynamic", "sky"])
def test_homographies_move_points_like_3d_motion(kind):
    """x_prev ~ H x_cur reproduces the projection of the 3D motion to 1e-6 px."""
    g = torch.Generator().manual_seed(3)
    delta = torch.tensor([0.4, 0.0, 0.9], dtype=torch.float64)
    delta = delta - (delta @ N_G) * N_G  # on the ground plane
    if kind == "ground":
        n, d = N_G, 1.65
    elif kind == "sky":
        n, d = N_G, 1e12
    else:
        n, d = object_normals(K, N_G, torch.tensor(400.0, dtype=torch.float64)), 14.0
    X = _points_on_plane(n, d, g) if kind != "sky" else torch.tensor([[3e9, -1e9, 1e12]], dtype=torch.float64) + 0
    p = torch.tensor(0.0 if kind == "sky" else 1.0 / d, dtype=torch.float64)
    if kind == "dynamic":
        Xp = (R @ (X - delta).T).T + T
        Hm = dynamic_homography(K, R, n, p * (T - R @ delta))
    else:
        Xp = (R @ X.T).T + T
        Hm = homography(K, R, T, n, p)
    x, xp = project(X), project(Xp)
    up, vp = apply_homography(Hm, x[:, 0], x[:, 1])
    assert torch.allclose(torch.stack([up, vp], -1), xp, atol=1e-6)


def test_dof_systems_recover_labels_exactly():
    g = torch.Generator().manual_seed(5)
    n_o = object_normals(K, N_G, torch.tensor(800.0, dtype=torch.float64))
    B = ground_basis(N_G)
    for kind in ("ground", "object", "dynamic"):
        n, d = (N_G, 1.65) if kind == "ground" else (n_o, 11.0)
        X = _points_on_plane(n, d, g)[:5]
        delta = (B @ torch.tensor([0.3, -0.7], dtype=torch.float64)) if kind == "dynamic" else torch.zeros(3, dtype=torch.float64)
        Xp = (R @ (X - delta).T).T + T
        x, xp = project(X), project(Xp)
        flow = xp - x
        if kind == "dynamic":
            # The 2-DOF model: camera and object translate on the ground plane and the camera
            # turns about the ground normal, so g = p (t - R Δ) lies in the ground plane.
            Rg = _rotation_about(N_G, math.radians(1.7))
            Tg = T - (T @ N_G) * N_G
            Xp = (Rg @ (X - delta).T).T + Tg
            flow = project(Xp) - x
            A, b = dynamic_dof_system(K, Rg, B, n, x[:, 0], x[:, 1], flow)
            tau = solve_dynamic_dof(A, b)
            gvec = tau @ B.T
            assert torch.allclose(gvec, ((Tg - Rg @ delta) / d).expand_as(gvec), atol=1e-9)
            # Δ from g and the true inverse depth.
            dlt = dynamic_motion(Rg.expand(5, 3, 3), Tg.expand(5, 3), gvec, torch.full((5,), 1 / d, dtype=torch.float64))
            assert torch.allclose(dlt, delta.expand_as(dlt), atol=1e-9)
        else:
            A, b = static_dof_system(K, R, T, n, x[:, 0], x[:, 1], flow)
            assert torch.allclose(solve_static_dof(A, b), torch.full((5,), 1 / d, dtype=torch.float64), rtol=1e-9)


def test_depth_on_ground_and_ray_plane_depth():
    n_o = object_normals(K, N_G, torch.tensor(300.0, dtype=torch.float64))
    # A point on the ground 12 m ahead-left, projected: its object plane passes through it.
    Xg = torch.tensor([-2.0, 0.0, 12.0], dtype=torch.float64)
    Xg = Xg + (1.65 - Xg @ N_G) * N_G
    u, v = project(Xg)
    p = depth_on_ground(K, n_o, N_G, torch.tensor(1.65, dtype=torch.float64), u, v)
    assert math.isclose(1 / float(p), float(Xg @ n_o), rel_tol=1e-9)
    assert math.isclose(float(ray_plane_depth(K, u, v, n_o, p)), float(Xg[2]), rel_tol=1e-9)
    assert math.isclose(float(ray_plane_depth(K, u, v, N_G, torch.tensor(1 / 1.65, dtype=torch.float64))), float(Xg[2]), rel_tol=1e-9)
    # Above the horizon the ray never meets the ground.
    v_up = horizon_row(K, N_G, u) - 5
    assert float(depth_on_ground(K, n_o, N_G, torch.tensor(1.65, dtype=torch.float64), u, v_up)) < 0


def test_camera_and_motion_validation():
    with pytest.raises(InputError, match="camera height"):
        Camera(K, height=-1.0)
    with pytest.raises(InputError, match="ground_normal"):
        Camera(K, ground_normal=torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64))
    with pytest.raises(InputError, match="not a rotation"):
        Motion(torch.diag(torch.tensor([1.0, 1.0, -1.0])), torch.zeros(3))
    with pytest.raises(InputError, match="t \\(camera motion\\)"):
        Motion(torch.eye(3), torch.tensor([0.0, float("nan"), 1.0]))
    assert math.isclose(Motion(torch.eye(3), torch.tensor([3.0, 0.0, 4.0])).translation_norm, 5.0)
