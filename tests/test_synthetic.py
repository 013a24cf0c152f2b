"""Validity of the synthetic street-scene renderer (docs/conventions.md, section 6).

The renderer's ground truth is checked against quantities computed independently here:
photometric consistency of the two rendered images under the ground-truth flow, analytic
ray-plane / ray-box distances, the flow of static ground against the plane homography, and the
moving mask against the object list.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from monostixels._checks import InputError
from monostixels.core.classes import CLASS_NAMES
from monostixels.data._render import _cast_points, _geometry
from monostixels.data.synthetic import KITTI_INTRINSICS, SyntheticSource, render_pair
from monostixels.data._scene import sample_scene
from monostixels.core.geometry import apply_homography, homography

SCALE = 0.25
SEEDS = (0, 1, 2)
#: Photometric bounds of the warping test (RGB in [0, 1], valid pixels, scale 0.5): the residual
#: comes only from bilinear interpolation of the previous image between pixel centres (the
#: texture is band-limited to periods >= 2 pixels, so this stays small).
PHOTO_MEAN_BOUND = 0.01
PHOTO_P95_BOUND = 0.03
ROAD, SIDEWALK, TERRAIN, SKY = 0, 1, 2, 9
H_CAM, KERB = 1.65, 0.15


@pytest.fixture(scope="module")
def pairs():
    return {s: render_pair(s, scale=SCALE) for s in SEEDS}


@pytest.fixture(scope="module")
def half_res_pair():
    return render_pair(7, scale=0.5)


def _pixel_rays(pair):
    H, W = pair.size
    K = pair.camera.K.double()
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    ray = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    return u, v, ray


def test_image_size_and_intrinsics():
    pair = render_pair(4, scale=SCALE)
    H, W = round(375 * SCALE), round(1242 * SCALE)
    assert pair.image.shape == (3, H, W) and pair.image_prev.shape == (3, H, W)
    assert pair.gt.flow.shape == (2, H, W) and pair.gt.depth.shape == (H, W)
    fx, fy, cx, cy = KITTI_INTRINSICS
    K = pair.camera.K
    assert torch.allclose(K, torch.tensor([[fx * SCALE, 0, cx * SCALE], [0, fy * SCALE, cy * SCALE], [0, 0, 1]],
                                          dtype=K.dtype))
    assert pair.camera.height == pytest.approx(H_CAM)
    assert float(pair.image.min()) >= 0 and float(pair.image.max()) <= 1


def test_warp_previous_by_flow_reproduces_current(half_res_pair):
    """Bilinear warp of image_prev by the gt flow matches image on flow_valid pixels."""
    pair = half_res_pair
    H, W = pair.size
    u, v, _ = _pixel_rays(pair)
    f = pair.gt.flow.double()
    gx = (u + f[0]) / (W - 1) * 2 - 1
    gy = (v + f[1]) / (H - 1) * 2 - 1
    grid = torch.stack([gx, gy], -1)[None].float()
    warped = torch.nn.functional.grid_sample(pair.image_prev[None], grid, mode="bilinear", align_corners=True)[0]
    err = (warped - pair.image).abs().mean(0)[pair.gt.flow_valid]
    assert pair.gt.flow_valid.float().mean() > 0.7
    assert float(err.mean()) < PHOTO_MEAN_BOUND
    assert float(err.quantile(0.95)) < PHOTO_P95_BOUND
    # The bound is meaningful: the unwarped previous image is far off on the same pixels.
    raw = (pair.image_prev - pair.image).abs().mean(0)[pair.gt.flow_valid]
    assert float(raw.mean()) > 3 * PHOTO_MEAN_BOUND


def test_flow_valid_points_are_visible_in_previous_frame():
    """Exact check: the previous camera's ray through x_prev hits the same point (ray cast)."""
    seed = 5
    pair = render_pair(seed, scale=SCALE)
    H, W = pair.size
    u, v, ray = _pixel_rays(pair)
    valid = pair.gt.flow_valid
    up = (u + pair.gt.flow[0].double())[valid]
    vp = (v + pair.gt.flow[1].double())[valid]
    layout = sample_scene(seed, 1.0)
    R, t = pair.motion.R.double().numpy(), pair.motion.t.double().numpy()
    geo = _geometry(layout, -1)
    t_hit, pid = _cast_points(geo, -R.T @ t, R.T, pair.camera.K.numpy(), (H, W), up.float(), vp.float())
    # Depth of the point in the previous camera from the ground truth.
    X = ray[valid] * pair.gt.depth.double()[valid][:, None]
    inst = pair.gt.instances[valid]
    delta = torch.zeros_like(X)
    for o in pair.meta["objects"]:
        delta[inst == o["instance"]] = torch.tensor(o["delta"], dtype=torch.float64)
    z_prev = ((X - delta) @ torch.from_numpy(R).T + torch.from_numpy(t))[:, 2]
    assert bool((pid >= 0).all())
    rel = (t_hit.double() - z_prev).abs() / z_prev
    assert float(rel.max()) < 2e-3


def test_depth_of_ground_is_analytic(pairs):
    """Road: z = h fy / (v - cy); terrain: the raised plane h - kerb; sidewalk: raised plane or kerb face."""
    for pair in pairs.values():
        u, v, ray = _pixel_rays(pair)
        K = pair.camera.K.double()
        depth = pair.gt.depth.double()
        lab = pair.gt.labels
        below = v > K[1, 2] + 1
        road = (lab == ROAD) & below
        z_road = H_CAM * K[1, 1] / (v - K[1, 2])
        assert road.sum() > 100
        assert torch.allclose(depth[road], z_road[road], rtol=1e-4)
        z_raised = (H_CAM - KERB) * K[1, 1] / (v - K[1, 2])
        terr = (lab == TERRAIN) & below
        if terr.any():
            assert torch.allclose(depth[terr], z_raised[terr], rtol=1e-4)
        # Sidewalk pixels: on the raised plane, or on a kerb face (vertical plane at the road edge).
        side = (lab == SIDEWALK) & below
        on_plane = (depth - z_raised).abs() <= 1e-4 * z_raised
        road_meta = pair.meta["road"]
        a = road_meta["angle"]
        r = torch.tensor([math.cos(a), 0.0, -math.sin(a)], dtype=torch.float64)
        e = (ray * depth[..., None]) @ r + road_meta["e_off"]
        on_kerb = ((e - road_meta["road_right"]).abs() < 1e-3) | ((e + road_meta["road_left"]).abs() < 1e-3)
        assert bool((on_plane | on_kerb)[side].all())
        assert float(on_plane[side].float().mean()) > 0.5


def _ray_box_entry(ray: torch.Tensor, centre, size, yaw) -> torch.Tensor:
    """Independent float64 slab test: entry t of rays (N, 3) from the origin; inf where missed."""
    c, s = math.cos(yaw), math.sin(yaw)
    Rl = torch.tensor([[c, 0, -s], [0, 1, 0], [s, 0, c]], dtype=torch.float64)  # world -> local
    o = -(Rl @ torch.tensor(centre, dtype=torch.float64))
    d = ray @ Rl.T
    half = torch.tensor(size, dtype=torch.float64) / 2
    t1 = (-half - o) / d
    t2 = (half - o) / d
    tmin = torch.minimum(t1, t2).amax(-1)
    tmax = torch.maximum(t1, t2).amin(-1)
    return torch.where((tmax >= tmin) & (tmin > 0), tmin, torch.full_like(tmin, math.inf))


def test_depth_of_objects_is_analytic_ray_box_distance(pairs):
    """Every pixel of an object instance has depth = first ray/box intersection of its parts."""
    checked = 0
    for pair in pairs.values():
        _, _, ray = _pixel_rays(pair)
        depth = pair.gt.depth.double()
        for o in pair.meta["objects"]:
            m = pair.gt.instances == o["instance"]
            if not m.any():
                continue
            t = torch.stack([_ray_box_entry(ray[m], p["centre"], p["size"], p["yaw"]) for p in o["parts"]]).amin(0)
            assert torch.isfinite(t).all()
            assert torch.allclose(depth[m], t, rtol=1e-4, atol=1e-4)
            checked += int(m.sum())
    assert checked > 200


def test_static_ground_flow_matches_plane_homography(pairs):
    """Road pixels (static, plane n = (0, 1, 0), d = h) move by H = K (R + t n^T / h) K^-1."""
    for pair in pairs.values():
        u, v, _ = _pixel_rays(pair)
        road = (pair.gt.labels == ROAD) & (v > pair.camera.K[1, 2] + 1)
        K = pair.camera.K.double()
        Hm = homography(K, pair.motion.R.double(), pair.motion.t.double(),
                        torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), torch.tensor(1.0 / H_CAM, dtype=torch.float64))
        up, vp = apply_homography(Hm, u[road], v[road])
        f = pair.gt.flow.double()
        assert float((up - u[road] - f[0][road]).abs().max()) < 1e-3
        assert float((vp - v[road] - f[1][road]).abs().max()) < 1e-3


def test_motion_convention_forward_driving(pairs):
    for pair in pairs.values():
        t = pair.motion.t
        assert 0.7 < float(t[2]) < 1.6 and abs(float(t[1])) < 1e-9
        yaw = math.degrees(math.atan2(float(pair.motion.R[0, 2]), float(pair.motion.R[0, 0])))
        assert abs(yaw) <= 1.0 + 1e-9
        # Forward driving: the previous frame was taken further back, so a road point near the
        # image bottom appeared closer to the horizon there (flow points up, v decreases).
        lab = pair.gt.labels
        H = pair.size[0]
        bottom_road = lab[-max(2, H // 10):] == ROAD
        assert float(pair.gt.flow[1][-max(2, H // 10):][bottom_road].mean()) < 0


def test_moving_mask_is_union_of_moving_instances(pairs):
    for pair in pairs.values():
        objects = pair.meta["objects"]
        moving_ids = [o["instance"] for o in objects if o["moving"]]
        expected = torch.isin(pair.gt.instances, torch.tensor(moving_ids, dtype=torch.int64)) & (pair.gt.instances > 0)
        assert torch.equal(pair.gt.moving, expected)
        for o in objects:
            d = np.linalg.norm(o["delta"])
            assert (d > 0.05) if o["moving"] else (d == 0.0)
            assert abs(o["delta"][1]) < 1e-12  # displacement on the ground plane
        # Moving pixels follow X_prev = R (X_cur - delta) + t (independent reprojection).
        u, v, ray = _pixel_rays(pair)
        K, R, t = pair.camera.K.double(), pair.motion.R.double(), pair.motion.t.double()
        for o in objects:
            m = pair.gt.instances == o["instance"]
            if not (o["moving"] and m.any()):
                continue
            X = ray[m] * pair.gt.depth.double()[m][:, None]
            Xp = (X - torch.tensor(o["delta"], dtype=torch.float64)) @ R.T + t
            xp = Xp @ K.T
            f = pair.gt.flow.double()
            assert torch.allclose(xp[:, 0] / xp[:, 2] - u[m], f[0][m], atol=1e-3)
            assert torch.allclose(xp[:, 1] / xp[:, 2] - v[m], f[1][m], atol=1e-3)
        # Stuff (instance 0) never moves.
        assert not bool(pair.gt.moving[pair.gt.instances == 0].any())


def test_scene_contains_preceding_and_oncoming_traffic(pairs):
    for pair in pairs.values():
        a = pair.meta["road"]["angle"]
        fwd = np.array([math.sin(a), 0.0, math.cos(a)])
        along = [float(np.dot(o["delta"], fwd)) for o in pair.meta["objects"] if o["class"] == 6 and o["moving"]]
        assert any(x > 0.3 for x in along), "no preceding vehicle"
        assert any(x < -0.3 for x in along), "no oncoming vehicle"
        assert pair.gt.moving.any()


def test_labels_in_range_and_consistent(pairs):
    seen = set()
    for pair in pairs.values():
        lab = pair.gt.labels
        assert lab.dtype == torch.int64
        assert int(lab.min()) >= 0 and int(lab.max()) < len(CLASS_NAMES)
        assert torch.equal(pair.gt.depth == 0, lab == SKY)
        # Instances only on things (vehicle, two-wheeler, person).
        things = (lab >= 6) & (lab <= 8)
        assert torch.equal(pair.gt.instances > 0, things)
        seen |= set(torch.unique(lab).tolist())
    assert {0, 1, 3, 4, 5, 6, 8, 9} <= seen


def test_deterministic_and_seed_dependent():
    a = render_pair(11, scale=SCALE)
    b = render_pair(11, scale=SCALE)
    c = render_pair(12, scale=SCALE)
    assert torch.equal(a.image, b.image) and torch.equal(a.image_prev, b.image_prev)
    assert torch.equal(a.gt.flow, b.gt.flow) and torch.equal(a.gt.labels, b.gt.labels)
    assert not torch.equal(a.image, c.image)
    assert not torch.equal(a.gt.depth, c.gt.depth)


def test_appearance_seed_changes_looks_not_geometry():
    a = render_pair(13, scale=SCALE)
    b = render_pair(13, scale=SCALE, appearance_seed=1)
    c = render_pair(13, scale=SCALE, appearance_seed=2)
    for p in (b, c):
        assert torch.equal(p.gt.depth, a.gt.depth) and torch.equal(p.gt.labels, a.gt.labels)
        assert torch.equal(p.gt.flow, a.gt.flow)
    assert (b.image - a.image).abs().mean() > 0.05
    assert (b.image - c.image).abs().mean() > 0.05


def test_density_scales_object_count():
    n0 = len(render_pair(21, scale=SCALE, density=0.0).meta["objects"])
    n1 = np.mean([len(sample_scene(s, 1.0).objects) for s in range(21, 26)])
    n2 = np.mean([len(sample_scene(s, 2.0).objects) for s in range(21, 26)])
    assert n0 == 0
    assert n2 > n1 > 0


def test_source_seeds_and_names():
    src = SyntheticSource(3, seed=2, scale=SCALE)
    assert len(src) == 3
    pair = src[1]
    assert pair.name == "synthetic_2_000001"
    assert pair.meta["scene_seed"] == 2 * 100_000 + 1
    assert torch.equal(pair.image, render_pair(200_001, scale=SCALE).image)
    names = [p.name for p in src]
    assert names == ["synthetic_2_000000", "synthetic_2_000001", "synthetic_2_000002"]
    with pytest.raises(IndexError):
        src[3]


@pytest.mark.parametrize("kwargs, name", [
    ({"seed": -1}, "seed"),
    ({"seed": 1.5}, "seed"),
    ({"seed": 0, "scale": 0.0}, "scale"),
    ({"seed": 0, "scale": float("nan")}, "scale"),
    ({"seed": 0, "density": -1.0}, "density"),
    ({"seed": 0, "density": float("inf")}, "density"),
    ({"seed": 0, "appearance_seed": "x"}, "appearance_seed"),
])
def test_render_pair_bad_arguments(kwargs, name):
    seed = kwargs.pop("seed")
    with pytest.raises(InputError, match=name):
        render_pair(seed, **kwargs)


@pytest.mark.parametrize("args, kwargs, name", [
    ((0,), {}, "frames"),
    ((1.5,), {}, "frames"),
    ((2,), {"seed": -3}, "seed"),
    ((2,), {"scale": -1.0}, "scale"),
    ((2,), {"density": "high"}, "density"),
])
def test_source_bad_arguments(args, kwargs, name):
    with pytest.raises(InputError, match=name):
        SyntheticSource(*args, **kwargs)
