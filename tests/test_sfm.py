"""The SfM baseline: exact triangulation of a static scene, and its failure on movers."""
from __future__ import annotations

import math

import pytest
import torch

from monostixels._checks import InputError
from monostixels.post.sfm import triangulate, triangulate_depth, triangulate_points
from monostixels.core.geometry import Motion, intrinsics, rotation_yaw

H, W = 18, 27  # H != W
K = intrinsics(fx=52.0, fy=61.0, cx=14.3, cy=8.1)  # fx != fy, cx != cy


def _flow_of_points(X_cur: torch.Tensor, X_prev: torch.Tensor) -> torch.Tensor:
    """Flow (2, H, W) current -> previous of pixels whose 3D point is X_cur (H, W, 3) now and X_prev before."""
    x0 = X_cur @ K.T
    x1 = X_prev @ K.T
    u0, v0 = x0[..., 0] / x0[..., 2], x0[..., 1] / x0[..., 2]
    u1, v1 = x1[..., 0] / x1[..., 2], x1[..., 1] / x1[..., 2]
    return torch.stack([u1 - u0, v1 - v0])


def _points(depth: torch.Tensor) -> torch.Tensor:
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    return rays * depth[..., None]


def test_exact_flow_of_a_static_scene_gives_the_true_depth():
    g = torch.Generator().manual_seed(3)
    depth = 5.0 + 45.0 * torch.rand(H, W, generator=g, dtype=torch.float64)
    motion = Motion(R=rotation_yaw(0.04), t=torch.tensor([0.25, -0.04, 1.1], dtype=torch.float64))
    X = _points(depth)
    flow = _flow_of_points(X, X @ motion.R.T + motion.t)
    res = triangulate(flow, K, motion)
    assert bool(res.valid.all())
    assert res.depth.dtype == torch.float64
    rel = ((res.depth - depth).abs() / depth).max()
    assert float(rel) < 1e-6
    assert torch.equal(triangulate_depth(flow, K, motion), res.depth)


def test_inverted_motion_direction_does_not_fit():
    # Guards the conventions: the inverse motion must not reproduce the depth.
    g = torch.Generator().manual_seed(4)
    depth = 5.0 + 45.0 * torch.rand(H, W, generator=g, dtype=torch.float64)
    motion = Motion(R=rotation_yaw(0.04), t=torch.tensor([0.25, -0.04, 1.1], dtype=torch.float64))
    X = _points(depth)
    flow = _flow_of_points(X, X @ motion.R.T + motion.t)
    inverse = Motion(R=motion.R.T, t=-(motion.R.T @ motion.t))
    wrong = triangulate(flow, K, inverse)
    right = wrong.valid & ((wrong.depth - depth).abs() / depth < 1e-3)
    assert float(right.double().mean()) < 0.1


def test_epipolar_conformant_mover_gets_a_wrong_depth():
    # Camera drives 1 m forward (X_prev = X_cur + (0, 0, 1)); a preceding vehicle drives 0.5 m
    # forward in the same time: X_prev = (X_cur - Δ) + t with Δ = (0, 0, 0.5). Its flow is that of a
    # static point at twice the distance along the same ray: the baseline reports 2 z.
    depth = torch.full((H, W), 20.0, dtype=torch.float64)
    t = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    motion = Motion(R=torch.eye(3, dtype=torch.float64), t=t)
    X = _points(depth)
    delta = torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64)
    res = triangulate(_flow_of_points(X, X - delta + t), K, motion)
    away = res.parallax > 1e-3  # the epipole pixel (cx, cy) itself carries no depth
    assert bool(res.valid[away].all())
    assert torch.allclose(res.depth[away], 2.0 * depth[away], rtol=1e-9)


def test_mover_faster_than_the_camera_triangulates_behind_and_is_flagged():
    # The vehicle drives 2 m forward while the camera drives 1 m: the rays meet behind the camera.
    depth = torch.full((H, W), 15.0, dtype=torch.float64)
    t = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    motion = Motion(R=torch.eye(3, dtype=torch.float64), t=t)
    X = _points(depth)
    delta = torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)
    res = triangulate(_flow_of_points(X, X - delta + t), K, motion)
    away = res.parallax > 1e-3
    assert bool(away.sum() > 0.9 * H * W)
    assert not bool(res.valid[away].any())
    assert bool((res.depth[away] < 0).all())
    # |depth| is the mirrored point (-X): the sign, not the magnitude, says "invalid".
    assert torch.allclose(res.depth[away], -depth[away], rtol=1e-9)


def test_no_translation_means_no_depth():
    motion = Motion(R=rotation_yaw(0.02), t=torch.zeros(3, dtype=torch.float64))
    X = _points(torch.full((H, W), 10.0, dtype=torch.float64))
    res = triangulate(_flow_of_points(X, X @ motion.R.T), K, motion)
    assert not bool(res.valid.any())
    assert bool(torch.isinf(res.depth).all() and (res.depth > 0).all())


def test_float32_flow_and_bad_input():
    depth = torch.full((H, W), 12.0, dtype=torch.float64)
    motion = Motion(R=rotation_yaw(-0.03), t=torch.tensor([0.1, 0.0, 0.9], dtype=torch.float64))
    X = _points(depth)
    flow = _flow_of_points(X, X @ motion.R.T + motion.t).float()
    d = triangulate_depth(flow, K.float(), motion)
    assert d.dtype == torch.float32
    far_from_epipole = triangulate(flow, K, motion).parallax > 5e-3
    assert torch.allclose(d[far_from_epipole].double(), depth[far_from_epipole], rtol=1e-3)
    bad = flow.clone()
    bad[1, 2, 3] = math.nan
    with pytest.raises(InputError, match="flow"):
        triangulate_depth(bad, K, motion)
    with pytest.raises(InputError, match="flow"):
        triangulate_depth(flow[0], K, motion)


def test_triangulate_points_is_triangulate_at_those_pixels():
    # The movers triangulate a stixel's pixels only: the same numbers as the full-frame baseline there.
    K = intrinsics(300.0, 300.0, 40.0, 30.0).double()
    motion = Motion(rotation_yaw(math.radians(1.0)).double(), torch.tensor([0.05, -0.02, 0.8], dtype=torch.float64))
    g = torch.Generator().manual_seed(2)
    flow = (torch.randn(2, 60, 80, generator=g) * 4.0).double()
    full = triangulate(flow, K, motion)
    v = torch.randint(0, 60, (200,), generator=g)
    u = torch.randint(0, 80, (200,), generator=g)
    depth, valid, parallax = triangulate_points(K, motion.R, motion.t, u.double(), v.double(), flow[0, v, u], flow[1, v, u])
    assert torch.equal(depth, full.depth[v, u]) and torch.equal(valid, full.valid[v, u])
    assert torch.equal(parallax, full.parallax[v, u])
    assert (~valid).any() and valid.any()  # behind a camera too
