"""Camera motion backends (monostixels.inputs.motion): mono on analytic flow, poses files, errors."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from monostixels._checks import InputError
from monostixels.data.base import FramePair
from monostixels.core.geometry import Camera, Motion, homography, intrinsics, pixel_rays, rotation_yaw
from monostixels.inputs.flow import FlowResult
from monostixels.eval.metrics import motion_errors
from monostixels.inputs.motion import estimate_motion, load_poses

H, W = 375, 1242
HEIGHT = 1.65


def _rot(yaw_deg: float, pitch_deg: float, roll_deg: float) -> torch.Tensor:
    p, r = math.radians(pitch_deg), math.radians(roll_deg)
    Rx = torch.tensor([[1, 0, 0], [0, math.cos(p), -math.sin(p)], [0, math.sin(p), math.cos(p)]], dtype=torch.float64)
    Rz = torch.tensor([[math.cos(r), -math.sin(r), 0], [math.sin(r), math.cos(r), 0], [0, 0, 1]], dtype=torch.float64)
    return rotation_yaw(math.radians(yaw_deg)) @ Rx @ Rz


def _camera() -> Camera:
    # Asymmetric intrinsics (fx != fy, cx != W/2, cy != H/2) so a transposition cannot pass.
    return Camera(K=intrinsics(720.0, 705.0, 600.0, 170.0), height=HEIGHT)


def _scene_planes() -> list[tuple[torch.Tensor, float]]:
    """Ground, left/right walls, a far wall: planes n^T X = d (current camera, metres)."""
    return [
        (torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), HEIGHT),   # ground, 1.65 m below
        (torch.tensor([-1.0, 0.0, 0.0], dtype=torch.float64), 6.0),     # left wall x = -6
        (torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), 8.0),      # right wall x = 8
        (torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), 60.0),     # far wall z = 60
    ]


def _analytic_flow(cam: Camera, motion: Motion, noise_px: float = 0.0, seed: int = 0,
                   planes: list[tuple[torch.Tensor, float]] | None = None) -> torch.Tensor:
    """Flow (2, H, W) current -> previous of the plane scene, via the stixel homographies."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    ray = pixel_rays(cam.K, u, v)
    best = torch.full((H, W), math.inf, dtype=torch.float64)
    flow = torch.zeros(2, H, W, dtype=torch.float64)
    x = torch.stack([u, v, torch.ones_like(u)], -1)
    for n, d in planes or _scene_planes():
        z = d / (ray @ n)  # depth along the unit-z ray
        hit = (z > 0) & (z < best)
        Hm = homography(cam.K, motion.R, motion.t, n, torch.tensor(1.0 / d, dtype=torch.float64))
        y = x @ Hm.T
        fu, fv = y[..., 0] / y[..., 2] - u, y[..., 1] / y[..., 2] - v
        flow[0] = torch.where(hit, fu, flow[0])
        flow[1] = torch.where(hit, fv, flow[1])
        best = torch.where(hit, z, best)
    if noise_px > 0:
        gen = torch.Generator().manual_seed(seed)
        flow = flow + noise_px * torch.randn(flow.shape, generator=gen, dtype=torch.float64)
    return flow.float()


def _pair_and_flow(motion: Motion, noise_px: float = 0.05, flow: torch.Tensor | None = None):
    cam = _camera()
    img = torch.zeros(3, H, W)
    pair = FramePair(image=img, image_prev=img, camera=cam, name="planes")
    f = _analytic_flow(cam, motion, noise_px) if flow is None else flow
    cov = (0.25 * torch.eye(2)).expand(H, W, 2, 2).contiguous()
    return pair, FlowResult(flow=f, cov=cov, seconds=0.0, backend="analytic")


MONO = OmegaConf.create({"name": "mono"})


def test_mono_recovers_known_motion_with_metric_scale():
    gt = Motion(R=_rot(0.8, -0.3, 0.1), t=torch.tensor([0.06, 0.01, 0.95], dtype=torch.float64))
    pair, fr = _pair_and_flow(gt)
    est = estimate_motion(pair, fr, MONO)
    assert est.motion is not None and not est.degenerate, est.reason
    e = motion_errors(est.motion, gt)
    assert e["rot_err_deg"] < 0.01
    assert e["trans_dir_err_deg"] < 0.05
    # Metric scale from the ground and the 1.65 m mounting height.
    assert e["scale_rel_err"] < 0.005
    assert est.inlier_ratio > 0.9


def test_mono_ignores_a_moving_object_and_uses_semantics():
    gt = Motion(R=_rot(-0.5, 0.2, 0.0), t=torch.tensor([-0.03, 0.0, 0.7], dtype=torch.float64))
    cam = _camera()
    flow = _analytic_flow(cam, gt, 0.05)
    # A "vehicle" in the lower middle moving on its own: its flow is shifted by 6 px to the left.
    flow[0, 200:330, 500:800] -= 6.0
    pair, fr = _pair_and_flow(gt, flow=flow)
    est = estimate_motion(pair, fr, MONO)
    e = motion_errors(est.motion, gt)
    assert e["rot_err_deg"] < 0.01 and e["trans_dir_err_deg"] < 0.05 and e["scale_rel_err"] < 0.005, est.reason
    # With semantic scores marking it as a vehicle (class 6) and the rest as road (class 0).
    sem = torch.zeros(10, H, W)
    sem[0] = 1.0
    sem[0, 200:330, 500:800] = 0.0
    sem[6, 200:330, 500:800] = 1.0
    est_s = estimate_motion(pair, fr, MONO, semantic=sem)
    e_s = motion_errors(est_s.motion, gt)
    assert e_s["rot_err_deg"] < 0.01 and e_s["trans_dir_err_deg"] < 0.05 and e_s["scale_rel_err"] < 0.005, est_s.reason


def test_mono_takes_the_sign_of_the_translation_from_the_road():
    # Stop-and-go traffic (the KITTI traffic drive, frames 2-7): a truck beside the camera fills most of the
    # view, the semantic net calls it a building, and it pulls ahead faster than the camera drives. Its flow is
    # epipolar (it moves along the camera's axis), so it is an inlier of the essential matrix, and it votes
    # for a camera driving backwards. The road, which cannot move, gives the sign. (Here two trucks, one on
    # each side, leave a strip of road.)
    gt = Motion(R=_rot(0.2, 0.0, 0.0), t=torch.tensor([0.0, 0.0, 0.4], dtype=torch.float64))
    cam = _camera()
    truck_delta = torch.tensor([0.0, 0.0, 1.2], dtype=torch.float64)  # it moves 1.2 m forward, the camera 0.4 m
    relative = Motion(R=gt.R, t=gt.t - gt.R @ truck_delta)  # X_prev = R (X - Δ) + t
    ground = [(torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), HEIGHT)]
    # Their sides 0.4 m right and left of the camera.
    truck = [(torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), 0.4), (torch.tensor([-1.0, 0.0, 0.0], dtype=torch.float64), 0.4)]
    flow_road = _analytic_flow(cam, gt, 0.05, planes=ground)
    flow_truck = _analytic_flow(cam, relative, 0.05, seed=1, planes=truck)
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    ray = pixel_rays(cam.K, u, v)
    z_road = torch.where(ray[..., 1] > 0, HEIGHT / ray[..., 1], torch.full_like(u, math.inf))
    z_truck = torch.where(ray[..., 0] != 0, 0.4 / ray[..., 0].abs(), torch.full_like(u, math.inf))
    on_truck = z_truck < z_road
    flow = torch.where(on_truck[None], flow_truck, flow_road)
    sem = torch.zeros(10, H, W)
    sem[0] = (~on_truck).float()   # road
    sem[3] = on_truck.float()      # "building"
    assert on_truck.float().mean() > 0.5  # the truck outvotes the road
    pair, fr = _pair_and_flow(gt, flow=flow)
    est = estimate_motion(pair, fr, MONO, semantic=sem)
    assert est.motion is not None and est.kind == "metric", est.reason
    e = motion_errors(est.motion, gt)
    assert e["trans_dir_err_deg"] < 1.0 and e["scale_rel_err"] < 0.05, est.reason
    assert "direction reversed by the road" in est.reason


def test_mono_fits_a_tilted_road_and_the_pipeline_can_use_it():
    from monostixels.pipeline import Pipeline, load_config
    from monostixels.build import pipeline_settings

    # The road falls away 2 degrees (camera pitched up against it): level ground is the configured model.
    a = math.radians(2.0)
    n_true = torch.tensor([0.0, math.cos(a), math.sin(a)], dtype=torch.float64)
    planes = [(n_true, HEIGHT), *_scene_planes()[1:]]
    gt = Motion(R=_rot(0.4, 0.0, 0.0), t=torch.tensor([0.02, 0.0, 0.9], dtype=torch.float64))
    cam = _camera()
    pair, fr = _pair_and_flow(gt, flow=_analytic_flow(cam, gt, 0.05, planes=planes))
    est = estimate_motion(pair, fr, MONO)
    assert est.motion is not None and est.ground_normal is not None, est.reason
    angle = math.degrees(math.acos(float(est.ground_normal @ n_true)))
    assert angle < 0.1
    assert motion_errors(est.motion, gt)["scale_rel_err"] < 0.01
    # The pipeline solves with the fitted normal only when asked to.
    for use, want in ((True, est.ground_normal), (False, cam.ground_normal)):
        pipe = Pipeline(pipeline_settings(load_config(["motion=mono", f"motion.use_ground_normal={str(use).lower()}"])))
        got = pipe.camera_for(pair, est).ground_normal
        assert torch.allclose(got.double(), want.double(), atol=1e-9)
    # Ground truth / poses motion has no fitted plane: the configured one stays.
    pair.motion = gt
    est_gt = estimate_motion(pair, fr, OmegaConf.create({"name": "gt"}))
    assert est_gt.ground_normal is None
    assert Pipeline(pipeline_settings(load_config(["motion=mono"]))).camera_for(pair, est_gt) is pair.camera


def _road_and_walls(cam: Camera, planes: list[tuple[torch.Tensor, float]]) -> torch.Tensor:
    """(10, H, W) scores of the plane scene: road where the ground plane (the first) is the nearest,
    building (class 3) on the walls."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    ray = pixel_rays(cam.K, u, v)
    depth = torch.stack([torch.where(ray @ n > 0, d / (ray @ n), torch.tensor(math.inf, dtype=torch.float64))
                         for n, d in planes])
    road = depth.argmin(0) == 0
    sem = torch.zeros(10, H, W)
    sem[0][road] = 1.0
    sem[3][~road] = 1.0
    return sem


@pytest.mark.parametrize("turned", [True, False])
def test_the_scene_model_meets_the_road_in_the_plane_of_travel(monkeypatch, turned):
    # A phone on the windscreen looks down 12 degrees and is configured level (camera.pitch 0): beyond the
    # road fit's cone around the configured normal, so the scene model (walls standing on the road) gives
    # the length. The car drives along its road, so t lies in the road plane: the scene model meets the
    # road through that plane. Through the configured level normal its length comes out far off.
    import monostixels.inputs.motion as motion_mod

    if not turned:
        monkeypatch.setattr(motion_mod, "travel_normal", lambda n_g, t: n_g)
    a = math.radians(12.0)
    n_true = torch.tensor([0.0, math.cos(a), math.sin(a)], dtype=torch.float64)
    planes = [(n_true, HEIGHT), *_scene_planes()[1:]]
    forward = torch.tensor([0.0, -math.sin(a), math.cos(a)], dtype=torch.float64)  # along the road
    gt = Motion(R=_rot(0.4, 0.0, 0.0), t=0.9 * forward + torch.tensor([0.02, 0.0, 0.0], dtype=torch.float64))
    cam = _camera()
    pair, fr = _pair_and_flow(gt, flow=_analytic_flow(cam, gt, 0.05, planes=planes))
    est = estimate_motion(pair, fr, MONO, semantic=_road_and_walls(cam, planes))
    if turned:
        assert est.kind == "metric" and est.scale_from == "scene", est.reason
        assert motion_errors(est.motion, gt)["scale_rel_err"] < 0.03
    else:  # through the configured level road: no metric length, or one far off
        assert est.kind != "metric" or motion_errors(est.motion, gt)["scale_rel_err"] > 0.1, est.reason


@pytest.mark.parametrize("grade_deg", [1.5, -1.5])
def test_the_scene_models_uncertainty_covers_a_road_tilted_against_the_plane_of_travel(monkeypatch, grade_deg):
    # The car drives level, the road ahead climbs (or falls) 1.5 deg: the walls' contacts lie on that road, not
    # on the plane of travel, and each contact's depth is off by about δ z / h. Every column shares the tilt, so
    # the scene model's error does not average out over its ~300 columns: its uncertainty must say so, and the
    # road's own (right) length must not be called contradicted.
    import monostixels.inputs.motion as motion_mod
    from monostixels.inputs import motion_scene

    d = math.radians(grade_deg)
    planes = [(torch.tensor([0.0, math.cos(d), -math.sin(d)], dtype=torch.float64), HEIGHT), *_scene_planes()[1:]]
    gt = Motion(R=_rot(0.3, 0.0, 0.0), t=torch.tensor([0.02, 0.0, 0.9], dtype=torch.float64))
    cam = _camera()
    pair, fr = _pair_and_flow(gt, flow=_analytic_flow(cam, gt, 0.05, planes=planes))
    sem = _road_and_walls(cam, planes)

    def scene_with(tilt_std: float):
        seen = []

        def record(*args, **kwargs):
            seen.append(motion_scene.scene_scale(*args, **kwargs, tilt_std=tilt_std))
            return seen[-1]

        monkeypatch.setattr(motion_mod, "scene_scale", record)
        est = estimate_motion(pair, fr, MONO, semantic=sem)
        return seen[0], est

    # Given the tilt it cannot rule out (here the road's own), the uncertainty covers the error.
    scene, est = scene_with(math.radians(abs(grade_deg)))
    err = abs(math.log(scene.scale / float(gt.t.norm())))
    assert 0.1 < err < 2 * scene.std, scene
    assert est.kind == "metric" and est.scale_from == "ground_flow" and est.scale_std < 0.05, est.reason
    # Without the shared tilt, the same samples claim a few percent and make the right road length uncertain.
    assert scene_with(motion_scene.GRADE_STD)[0].std < scene.std
    blind, est_blind = scene_with(0.0)
    assert blind.scale == scene.scale and err > 4 * blind.std
    assert est_blind.scale_std > 0.1


def test_travel_normal_is_the_nearest_normal_across_the_translation():
    from monostixels.inputs.motion import travel_normal

    n_g = np.array([0.0, 1.0, 0.0])
    t = np.array([0.1, -0.3, 2.0])
    n = travel_normal(n_g, t)
    assert abs(float(n @ t)) < 1e-12 and abs(float(np.linalg.norm(n)) - 1.0) < 1e-12
    # The nearest such unit vector: no other one across t is closer to n_g (a dense check on the circle).
    d = t / np.linalg.norm(t)
    e1 = n
    e2 = np.cross(d, e1)
    angles = np.linspace(0, 2 * np.pi, 3601)
    ring = np.cos(angles)[:, None] * e1 + np.sin(angles)[:, None] * e2
    assert float(n @ n_g) >= float((ring @ n_g).max()) - 1e-12
    assert np.array_equal(travel_normal(n_g, np.zeros(3)), n_g)  # standing: the configured normal


def test_mono_reports_an_opencv_failure_of_the_essential_matrix(monkeypatch):
    # OpenCV's 5-point solver can assert on a near-degenerate sample (solvePoly); the pair fails, the run goes on.
    import cv2

    from monostixels.inputs import motion as motion_mod

    def fails(*args, **kwargs):
        raise cv2.error("OpenCV(5.1.0) mathfuncs.cpp:1601: error: (-215:Assertion failed) ... in function 'solvePoly'")

    monkeypatch.setattr(motion_mod.cv2, "findEssentialMat", fails)
    pair, fr = _pair_and_flow(Motion(R=_rot(0.8, -0.3, 0.1), t=torch.tensor([0.06, 0.01, 0.95], dtype=torch.float64)))
    est = estimate_motion(pair, fr, MONO)
    assert est.motion is None and not est.degenerate
    assert "essential matrix: OpenCV failed" in est.reason and "solvePoly" in est.reason


def test_mono_flags_pure_rotation_and_standing_still():
    R = _rot(1.0, 0.4, 0.0)
    gt = Motion(R=R, t=torch.zeros(3, dtype=torch.float64))
    pair, fr = _pair_and_flow(gt, noise_px=0.05)
    est = estimate_motion(pair, fr, MONO)
    assert est.degenerate and "pure rotation" in est.reason
    assert est.motion is not None and float(est.motion.t.abs().max()) == 0.0
    assert motion_errors(est.motion, gt)["rot_err_deg"] < 0.01
    still = Motion(R=torch.eye(3, dtype=torch.float64), t=torch.zeros(3, dtype=torch.float64))
    pair, fr = _pair_and_flow(still, noise_px=0.1)
    est = estimate_motion(pair, fr, MONO)
    assert est.degenerate and "standing still" in est.reason
    assert est.kind == "standing" and est.scale_from is None


def test_mono_bad_flow():
    gt = Motion(R=torch.eye(3, dtype=torch.float64), t=torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    pair, fr = _pair_and_flow(gt, noise_px=0.0)
    fr.flow[0, 10, 10] = float("nan")
    with pytest.raises(InputError, match="non-finite"):
        estimate_motion(pair, fr, MONO)
    fr.flow = torch.zeros(2, 10, 10)
    with pytest.raises(InputError, match="flow"):
        estimate_motion(pair, fr, MONO)
    with pytest.raises(InputError, match="motion.name"):
        estimate_motion(pair, fr, OmegaConf.create({"name": "imu"}))


def test_motion_errors_hand_computed():
    a = Motion(R=rotation_yaw(math.radians(1.0)), t=torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64))
    b = Motion(R=torch.eye(3, dtype=torch.float64), t=torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    e = motion_errors(a, b)
    assert e["rot_err_deg"] == pytest.approx(1.0, rel=1e-9)
    assert e["trans_dir_err_deg"] == pytest.approx(90.0)
    assert e["scale_rel_err"] == pytest.approx(1.0)
    assert motion_errors(b, b)["rot_err_deg"] == pytest.approx(0.0, abs=1e-9)


def _pose(R: np.ndarray, c: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, c
    return T


@pytest.mark.parametrize("numbered", [False, True])
def test_file_backend(tmp_path, numbered):
    R1 = rotation_yaw(math.radians(2.0)).numpy()
    poses = [_pose(np.eye(3), np.zeros(3)), _pose(np.eye(3), np.array([0.0, 0.0, 1.0])), _pose(R1, np.array([0.1, 0.0, 2.0]))]
    lines = []
    for i, T in enumerate(poses):
        nums = " ".join(f"{x:.9e}" for x in T[:3].ravel())
        lines.append(f"{i + 100:010d} {nums}" if numbered else nums)
    path = tmp_path / "poses.txt"
    path.write_text("\n".join(lines) + "\n")
    base = 100 if numbered else 0
    assert sorted(load_poses(path)) == [base, base + 1, base + 2]
    img = torch.zeros(3, 8, 8)
    cam = Camera(K=intrinsics(10.0, 10.0, 4.0, 4.0))
    pair = FramePair(image=img, image_prev=img, camera=cam, name="f", meta={"frame_index": base + 2, "frame_index_prev": base + 1})
    est = estimate_motion(pair, None, OmegaConf.create({"name": "file", "path": str(path)}))
    # X_prev = T_w_prev^-1 T_w_cur X_cur: prev camera at z = 1, current at (0.1, 0, 2) yawed 2 deg.
    assert torch.allclose(est.motion.R, torch.from_numpy(R1), atol=1e-8)
    assert torch.allclose(est.motion.t, torch.tensor([0.1, 0.0, 1.0], dtype=torch.float64), atol=1e-8)
    # A camera offset (KITTI camera 2 vs camera 0): t' = t + (I - R) o.
    est_o = estimate_motion(pair, None, OmegaConf.create({"name": "file", "path": str(path), "offset": [0.5, 0.0, 0.0]}))
    want = torch.tensor([0.1, 0.0, 1.0], dtype=torch.float64) + (torch.eye(3, dtype=torch.float64) - torch.from_numpy(R1)) @ torch.tensor([0.5, 0.0, 0.0], dtype=torch.float64)
    assert torch.allclose(est_o.motion.t, want, atol=1e-8)
    with pytest.raises(InputError, match="no pose for frame 7"):
        estimate_motion(FramePair(image=img, image_prev=img, camera=cam, meta={"frame_index": 7, "frame_index_prev": base}),
                        None, OmegaConf.create({"name": "file", "path": str(path)}))
    with pytest.raises(InputError, match="frame_index"):
        estimate_motion(FramePair(image=img, image_prev=img, camera=cam), None, OmegaConf.create({"name": "file", "path": str(path)}))
    with pytest.raises(InputError, match="not found"):
        estimate_motion(pair, None, OmegaConf.create({"name": "file", "path": str(tmp_path / "missing.txt")}))
    bad = tmp_path / "bad.txt"
    bad.write_text("1 2 3\n")
    with pytest.raises(InputError, match="motion.path: poses: .* 3 values; expected 12, 13"):
        load_poses(bad)
    # The same formats as the data sources' poses: comments, 4x4 rows; frame ids must be numbers.
    four = tmp_path / "four.txt"
    four.write_text("# T_w_cam, 4x4\n" + "\n".join(" ".join(f"{x:.9e}" for x in T.ravel()) for T in poses) + "\n")
    assert np.allclose(load_poses(four)[2], poses[2]) and sorted(load_poses(four)) == [0, 1, 2]
    named = tmp_path / "named.txt"
    named.write_text("".join(f"frame{i} " + " ".join(f"{x:.9e}" for x in T[:3].ravel()) + "\n" for i, T in enumerate(poses)))
    with pytest.raises(InputError, match="frame id 'frame0' is not a frame number"):
        load_poses(named)


def test_gt_backend_requires_motion():
    img = torch.zeros(3, 8, 8)
    cam = Camera(K=intrinsics(10.0, 10.0, 4.0, 4.0))
    with pytest.raises(InputError, match="ground-truth camera motion"):
        estimate_motion(FramePair(image=img, image_prev=img, camera=cam, name="x"), None, OmegaConf.create({"name": "gt"}))
    m = Motion(R=torch.eye(3, dtype=torch.float64), t=torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    est = estimate_motion(FramePair(image=img, image_prev=img, camera=cam, motion=m), None, OmegaConf.create({"name": "gt"}))
    assert est.motion is m and not est.degenerate
    still = Motion(R=torch.eye(3, dtype=torch.float64), t=torch.tensor([2e-6, 0.0, 1e-6], dtype=torch.float64))
    est = estimate_motion(FramePair(image=img, image_prev=img, camera=cam, motion=still), None, OmegaConf.create({"name": "gt"}))
    assert est.degenerate and "no translation" in est.reason


@pytest.mark.slow
def test_mono_on_real_kitti_frames():
    """Real KITTI raw frames: rotation and scale against the poses (translation direction: see report)."""
    from pathlib import Path

    import cv2

    root = Path(__file__).parents[2] / "shared" / "data" / "kitti_raw" / "2011_09_30"
    if not root.is_dir():
        pytest.skip(f"KITTI raw sample not found at {root} (shared development data)")
    drive = root / "2011_09_30_drive_0028_sync"
    P = None
    for line in (root / "calib_cam_to_cam.txt").read_text().splitlines():
        if line.startswith("P_rect_02:"):
            P = np.array([float(x) for x in line.split()[1:]]).reshape(3, 4)
    cam = Camera(K=torch.from_numpy(P[:, :3].copy()), height=HEIGHT)

    def rgb(path: Path) -> torch.Tensor:
        return torch.from_numpy(cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)).permute(2, 0, 1).float() / 255.0

    from monostixels.inputs.flow import estimate_flow
    from monostixels.inputs.motion import relative_motion

    poses = load_poses(drive / "poses_cam0.txt")
    i = 1114
    cur, prev = drive / "image_02" / "data" / f"{i:010d}.jpg", drive / "image_02" / "data" / f"{i - 1:010d}.jpg"
    gt = relative_motion(poses[i], poses[i - 1], np.array([P[0, 3] / P[0, 0], 0.0, 0.0]))
    pair = FramePair(image=rgb(cur), image_prev=rgb(prev), camera=cam, name=str(i))
    fr = estimate_flow(pair, OmegaConf.create({"name": "dis", "preset": "medium"}))
    est = estimate_motion(pair, fr, MONO)
    e = motion_errors(est.motion, gt)
    assert e["rot_err_deg"] < 0.1, est.reason
    assert e["scale_rel_err"] < 0.1, est.reason


def test_mono_scale_from_the_images_when_the_road_flow_fails():
    from monostixels.data.synthetic import render_pair
    from monostixels.inputs.semantic import estimate_semantics

    pair = render_pair(3, scale=0.5)
    sem = estimate_semantics(pair, OmegaConf.create({"name": "gt"}))
    road = pair.gt.labels == 0
    # The flow is exact except on the road, where it is garbage (as large displacements make it).
    g = torch.Generator().manual_seed(0)
    flow = pair.gt.flow.clone()
    flow[:, road] = 20.0 * torch.randn(2, int(road.sum()), generator=g)
    cov = (0.25 * torch.eye(2)).expand(*pair.size, 2, 2).contiguous()
    fr = FlowResult(flow=flow, cov=cov, seconds=0.0, backend="corrupted")
    est = estimate_motion(pair, fr, MONO, semantic=sem)
    assert est.motion is not None and "photometric" in est.reason, est.reason
    e = motion_errors(est.motion, pair.motion)
    assert e["scale_rel_err"] < 0.02 and e["trans_dir_err_deg"] < 0.5
    # The renderer's road is level: the photometric road normal is the camera's "down".
    n = est.ground_normal.double()
    assert math.degrees(math.acos(float(n @ pair.camera.ground_normal.double()))) < 0.5
    # Without it, the scene model gives the length: the buildings' and poles' flow depths against their
    # ground contacts at the camera height.
    scene = estimate_motion(pair, fr, OmegaConf.create({"name": "mono", "photometric_scale": False}), semantic=sem)
    assert scene.kind == "metric" and scene.scale_from == "scene", scene.reason
    assert motion_errors(scene.motion, pair.motion)["scale_rel_err"] < 2 * scene.scale_std < 0.15
    # Both switched off, the same pair has no metric scale (reported, not guessed).
    off = estimate_motion(pair, fr, OmegaConf.create({"name": "mono", "photometric_scale": False, "scene_scale": False}),
                          semantic=sem)
    assert off.motion is None and "no metric scale" in off.reason
    # ... but the camera moves, and its direction is known: kept, for a sequence's speed to scale.
    assert off.kind == "scale_unknown" and off.unit_motion is not None
    assert motion_errors(off.unit_motion, pair.motion)["trans_dir_err_deg"] < 0.5
    assert float(off.unit_motion.t.norm()) == pytest.approx(1.0)
    assert est.kind == "metric" and est.scale_from == "photometric"
    # Images that do not show the motion: no clear minimum, no estimate.
    noise = torch.rand(3, *pair.size, generator=g)
    blind = FramePair(image=noise, image_prev=torch.rand(3, *pair.size, generator=g), camera=pair.camera, name="noise")
    none = estimate_motion(blind, fr, OmegaConf.create({"name": "mono", "scene_scale": False}), semantic=sem)
    assert none.motion is None and "photometric" in none.reason
    # The scene model needs no image: the flow of the house fronts over their contacts still says it.
    assert estimate_motion(blind, fr, MONO, semantic=sem).scale_from == "scene"


def _track_pair(frame: int, seq: str = "s", dt: float = 0.1):
    from monostixels.data.base import FramePair
    from monostixels.core.geometry import Camera, intrinsics

    cam = Camera(K=intrinsics(10.0, 10.0, 2.0, 2.0), height=1.65,
                 ground_normal=torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    img = torch.zeros(3, 4, 4)
    return FramePair(img, img, cam, meta={"sequence": seq, "frame": frame, "frame_prev": frame - 1, "dt": dt})


def _est(norm: float):
    from monostixels.core.geometry import Motion
    from monostixels.inputs.motion import MotionEstimate

    t = torch.tensor([0.0, 0.0, norm], dtype=torch.float64)
    return MotionEstimate(Motion(torch.eye(3, dtype=torch.float64), t), False, "ok", 1.0)


def test_motion_track_rejects_a_scale_outlier_and_keeps_direction():
    from monostixels.inputs.motion_track import MotionTrack, MotionTrackParams

    tr = MotionTrack(MotionTrackParams())
    # 0.9 m per frame, one pair measured 14 % too long (KITTI raw drive 0023 pair 6 with semantics).
    meas = [0.90, 0.91, 0.89, 0.90, 1.026, 0.90]
    ests = [tr.update(_track_pair(k + 1), dataclasses.replace(_est(m), scale_from="ground_flow")) for k, m in enumerate(meas)]
    out = [float(e.motion.t[2]) for e in ests]
    assert out[0] == pytest.approx(0.90)  # the first pair is its own
    assert abs(out[4] / 0.90 - 1) < 0.02  # the outlier is replaced by the prediction ...
    assert ests[4].scale_from == "sequence"  # ... and says where its length came from
    assert [e.scale_from for e in ests[:4]] == ["ground_flow"] * 4  # filtered, still the pairs' own
    assert all(abs(o / 0.90 - 1) < 0.02 for o in out)
    # A single pair alone, another sequence, or a gap: unchanged.
    assert float(MotionTrack().update(_track_pair(1), _est(1.3)).motion.t[2]) == pytest.approx(1.3)
    assert float(tr.update(_track_pair(8), _est(1.3)).motion.t[2]) == pytest.approx(1.3)  # frame 7 missing
    assert float(tr.update(_track_pair(9, seq="other"), _est(0.5)).motion.t[2]) == pytest.approx(0.5)


def _unit(direction=(0.0, 0.0, 1.0)):
    from monostixels.core.geometry import Motion
    from monostixels.inputs.motion import MotionEstimate

    t = torch.tensor(direction, dtype=torch.float64)
    unit = Motion(torch.eye(3, dtype=torch.float64), t / t.norm())
    return MotionEstimate(None, False, "no metric scale: test", 0.5, kind="scale_unknown", unit_motion=unit)


def test_motion_track_holds_the_speed_over_pairs_without_a_scale():
    from monostixels.inputs.motion_track import MotionTrack, MotionTrackParams

    tr = MotionTrack(MotionTrackParams(scale_hold_s=0.25))
    for k in range(4):  # 20 m/s at 10 Hz
        out = tr.update(_track_pair(k + 1), _est(2.0))
        assert out.scale_from is None and out.kind == "metric"
    # The road gives no scale: the direction is the pair's own, the length the sequence's speed.
    held = tr.update(_track_pair(5), _unit((0.1, 0.0, 1.0)))
    assert held.kind == "metric" and held.scale_from == "sequence" and not held.degenerate
    assert float(held.motion.t.norm()) == pytest.approx(2.0, rel=0.01)
    assert float(held.motion.t[0] / held.motion.t[2]) == pytest.approx(0.1)
    assert "scale from the sequence" in held.reason
    # 0.25 s at most: two more pairs of 0.1 s are held (0.2 s), the third is not.
    assert tr.update(_track_pair(6), _unit()).scale_from == "sequence"
    late = tr.update(_track_pair(7), _unit())
    assert late.kind == "scale_unknown" and late.motion is None
    # A measured pair in between starts the count again.
    tr = MotionTrack(MotionTrackParams(scale_hold_s=0.15))
    for k, e in enumerate([_est(2.0), _est(2.0), _unit(), _est(2.0), _unit()]):
        out = tr.update(_track_pair(k + 1), e)
    assert out.scale_from == "sequence"
    # The held length grows uncertain with the time held (its variance predicted, not updated).
    tr = MotionTrack(MotionTrackParams(scale_hold_s=10.0))
    for k in range(3):
        tr.update(_track_pair(k + 1), _est(2.0))
    stds = [tr.update(_track_pair(k + 4), _unit()).scale_std for k in range(30)]
    assert all(b > a for a, b in zip(stds, stds[1:]))
    assert stds[0] < tr.params.max_scale_std < stds[-1]  # held long enough, it is no longer trusted
    # No speed yet (the first pair), another sequence, or a gap: nothing to hold.
    assert MotionTrack().update(_track_pair(1), _unit()).kind == "scale_unknown"
    # One pair's length is never held: uncorroborated, it may be the error (a first pair at a sixth of the speed).
    tr = MotionTrack()
    tr.update(_track_pair(1), _est(2.0))
    assert tr.update(_track_pair(2), _unit()).kind == "scale_unknown"
    assert tr.update(_track_pair(9), _unit()).kind == "scale_unknown"  # frame 8 missing
    assert MotionTrack(MotionTrackParams(scale_hold_s=0.0)).update(_track_pair(1), _unit()).motion is None


def _scene_est(length: float, reach: float, elevation_deg: float, std: float = 0.05):
    from monostixels.core.geometry import Motion
    from monostixels.inputs.motion import MotionEstimate

    e = math.radians(elevation_deg)  # t toward the ground normal (0, 1, 0): the direction of travel's elevation
    t = length * torch.tensor([0.0, math.sin(e), math.cos(e)], dtype=torch.float64)
    return MotionEstimate(Motion(torch.eye(3, dtype=torch.float64), t), False, "ok", 1.0, scale_from="scene",
                          scale_std=std, scene_reach=reach)


def test_the_scene_models_length_is_uncertain_by_the_directions_scatter_at_its_contacts_distance():
    from monostixels.inputs.motion_track import DIRECTION_PRIOR_STD, MotionTrack

    # A steady direction of travel (a calibrated car camera): contacts 16 camera heights away still give a length.
    tr = MotionTrack()
    for k in range(4):
        out = tr.update(_track_pair(k + 1), _scene_est(1.0, 16.0, 0.05 * (-1) ** k))
    assert out.kind == "metric" and out.scale_from == "scene"
    assert math.degrees(tr.direction_scatter()) == pytest.approx(0.1 / math.sqrt(2), rel=0.01)
    # A direction that swings by 2 deg from pair to pair (a phone at a slow crawl, DAD 487's first pairs read
    # 0.85 deg): the plane of travel may be tilted by 1.4 deg, and at 16 camera heights that is 40 % in the
    # length. No metric length, not a certain one: the pair's direction is kept.
    tr = MotionTrack()
    outs = [tr.update(_track_pair(k + 1), _scene_est(1.0, 16.0, 1.0 * (-1) ** k)) for k in range(4)]
    assert [o.kind for o in outs] == ["scale_unknown"] * 4 and all(o.motion is None for o in outs)
    assert outs[-1].unit_motion is not None and "no metric length" in outs[-1].reason
    assert math.degrees(tr.direction_scatter()) == pytest.approx(2 / math.sqrt(2), rel=0.01)
    # Near contacts carry the same scatter lightly (3 camera heights: 7 %).
    near = tr.update(_track_pair(5), _scene_est(1.0, 3.0, 1.0))
    assert near.kind == "metric" and near.scale_from == "scene"
    # Before a sequence shows its scatter, the prior: the first pair's far contacts give no length, and its
    # near ones one as uncertain as the prior tilt makes it at their distance.
    assert MotionTrack().update(_track_pair(1), _scene_est(1.0, 16.0, 0.0)).kind == "scale_unknown"
    first = MotionTrack().update(_track_pair(1), _scene_est(1.0, 3.0, 0.0))
    assert first.scale_std == pytest.approx(math.hypot(0.05, DIRECTION_PRIOR_STD * 3))
    assert 16.0 * DIRECTION_PRIOR_STD > 0.15
    # A length from the road is not the scene model's: its direction's scatter does not touch it.
    tr = MotionTrack()
    road = [tr.update(_track_pair(k + 1), dataclasses.replace(_scene_est(1.0, 16.0, 1.0 * (-1) ** k),
                                                              scale_from="ground_flow", scene_reach=None))
            for k in range(4)]
    assert all(o.kind == "metric" for o in road)


def test_motion_track_follows_a_real_speed_change():
    from monostixels.inputs.motion_track import MotionTrack

    tr = MotionTrack()
    # Braking at 3 m/s^2 from 10 m/s at 10 Hz: 1.0, 0.97, 0.94, ... m per frame. A constant-velocity
    # model lags behind a steady deceleration, but never gates the true measurements out.
    truth = [1.0 - 0.03 * k for k in range(10)]
    out = [float(tr.update(_track_pair(k + 1), _est(m)).motion.t[2]) for k, m in enumerate(truth)]
    assert all(abs(o / t - 1) < 0.04 for o, t in zip(out, truth))
    assert out[-1] < 0.8  # it follows: 0.73 m true, 1.0 m at the start


def test_motion_track_restarts_after_a_first_pair_far_off():
    from monostixels.inputs.motion_track import MotionTrack

    # The first pair 25 % long, then a car slowing from 0.53 to 0.44 m a frame (drive 0028's profile):
    # the second pair contradicts a track of one pair, which has no more support than it: the track
    # restarts at the second pair at once, that pair marked uncertain (its disagreement with the first).
    truth = [0.53 - 0.015 * k for k in range(7)]
    meas = [0.53 * 1.25] + truth[1:]
    tr = MotionTrack()
    ests = [tr.update(_track_pair(k + 1), _est(m)) for k, m in enumerate(meas)]
    out = [float(e.motion.t[2]) for e in ests]
    assert out[1] == pytest.approx(truth[1])  # the pair's own length, not the first pair's held
    assert ests[1].scale_std == pytest.approx(math.log(meas[0] / truth[1]), rel=0.05)  # the disagreement
    assert ests[1].scale_std > tr.params.max_scale_std  # uncertain: its movers and warnings fail safe
    assert all(e.scale_std < tr.params.max_scale_std for e in ests[2:])  # confirmed from the third pair on
    assert all(abs(o / t - 1) < 0.04 for o, t in zip(out[1:], truth[1:]))  # the lag of a steady slowing, as above
    # A confirmed track outvoted by one pair keeps its prediction for that pair, marked uncertain.
    tr = MotionTrack()
    ests = [tr.update(_track_pair(k + 1), _est(m)) for k, m in enumerate([0.5, 0.5, 0.5, 0.8])]
    assert float(ests[3].motion.t[2]) == pytest.approx(0.5, rel=0.01) and ests[3].scale_from == "sequence"
    assert ests[3].scale_std == pytest.approx(math.log(0.8 / 0.5), rel=0.05)
    # Two outliers in a row that disagree with each other (+25 %, then -25 % of the truth): neither is taken.
    tr = MotionTrack()
    out = [float(tr.update(_track_pair(k + 1), _est(m)).motion.t[2]) for k, m in enumerate([0.9, 0.9, 1.12, 0.68, 0.9])]
    assert all(abs(o / 0.9 - 1) < 0.02 for o in out)


def test_motion_track_filters_the_normal_over_chained_pairs():
    import dataclasses

    from monostixels.inputs.motion_track import MotionTrack

    def pair(frame: int, prev: int, seq: str = "s"):
        p = _track_pair(frame, seq)
        p.meta["frame_prev"] = prev
        return p

    def tilted(deg: float) -> torch.Tensor:
        a = math.radians(deg)
        return torch.tensor([0.0, math.cos(a), math.sin(a)], dtype=torch.float64)

    def pitch(est) -> float:
        return math.degrees(math.atan2(float(est.ground_normal[2]), float(est.ground_normal[1])))

    def level_then(pairs, last, tilt_deg=1.5):
        """Level fits on ``pairs``, then a ``tilt_deg`` fit on ``last``: its filtered pitch and the track."""
        tr = MotionTrack()
        for frame, prev in pairs:
            tr.update(pair(frame, prev), dataclasses.replace(_est(0.3), ground_normal=tilted(0.0)))
        return pitch(tr.update(pair(*last), dataclasses.replace(_est(0.3), ground_normal=tilted(tilt_deg)))), tr

    # Consecutive pairs: a 1.5 degree fit is fused with the level ones before it.
    assert 0.1 < level_then([(1, 0), (2, 1), (3, 2)], (4, 3))[0] < 1.2
    # A pair back to the last pair's earlier frame continues the filter from that frame's normal.
    assert 0.1 < level_then([(1, 0), (2, 1), (3, 2)], (4, 2))[0] < 1.2
    # Keyframe pairs reaching back past it keep their own fit (it matches their own scale).
    assert level_then([(1, 0), (2, 0), (3, 1)], (4, 2))[0] == pytest.approx(1.5, abs=1e-9)
    # A gate: a fit 8 degrees off is an outlier, the prediction stands.
    gated, tr = level_then([(1, 0), (2, 1), (3, 2)], (4, 3), tilt_deg=8.0)
    assert abs(gated) < 0.01
    # Another sequence starts again: its first fit is its own.
    out = tr.update(pair(5, 4, seq="other"), dataclasses.replace(_est(0.3), ground_normal=tilted(1.5)))
    assert torch.allclose(out.ground_normal, tilted(1.5), atol=1e-9)


def test_the_road_implies_the_camera_height_beside_a_given_motion():
    """With a metric motion from elsewhere (motion=gt), a wrong camera.height shows: the road implies the true one."""
    import dataclasses

    from monostixels.data.synthetic import render_pair
    from monostixels.output.writers import camera_report, camera_summary
    from monostixels.pipeline import Pipeline, load_config
    from monostixels.build import pipeline_settings

    pair = render_pair(2, scale=0.5)
    true_h = pair.camera.height
    wrong = dataclasses.replace(pair, camera=dataclasses.replace(pair.camera, height=true_h * 1.3))
    cfg = load_config(["data.scale=0.5", "flow=gt", "semantic=gt", "motion=gt"])
    res = Pipeline(pipeline_settings(cfg), sfm=False, report_height=True).run(wrong)
    fit = res.stixels.flags["camera_height_fit_m"]
    assert abs(fit / true_h - 1) < 0.03, (fit, true_h)
    assert "camera_height_fit_m" not in Pipeline(pipeline_settings(cfg), sfm=False).run(wrong).stixels.flags  # only when asked
    lines = camera_summary(camera_report([res.stixels.flags], wrong.camera.height))
    assert lines[0].startswith("camera motion metric on 1 of 1 pair(s) (scale: 1 given)")
    assert f"the road implies {fit:.2f} m" in lines[1] and f"camera height {wrong.camera.height:.2f} m" in lines[1]
    mixed = [{"camera_motion": "metric", "scale_from": "photometric"}, {"camera_motion": "metric", "scale_from": "sequence"},
             {"camera_motion": "scale_unknown"}, {"camera_motion": "standing"}]
    rep = camera_report(mixed, 1.4)
    assert rep["metric"] == 3 and rep["no_metric_motion"] == 1 and rep["height_fit_m"] is None
    assert camera_summary(rep)[0] == ("camera motion metric on 3 of 4 pair(s) (scale: 1 photometric, 1 sequence); "
                                             "1 without a metric motion (no movers, no collision warnings there)")
    assert rep["speed_mps"] is None and rep["scale_uncertain"] == 0  # no speeds given
    # The camera speed of the moving metric pairs of a certain scale: median and range; the pairs of an
    # uncertain scale are counted apart, their lengths left out.
    mixed[0]["speed_mps"], mixed[1]["speed_mps"] = 12.0, 0.9
    mixed[1]["scale_uncertain"] = True
    mixed.append({"camera_motion": "metric", "scale_from": "road_marks", "speed_mps": 9.0})
    mixed.append({"camera_motion": "metric", "scale_from": "road_marks", "speed_mps": 10.0, "scale_uncertain": False})
    rep = camera_report(mixed, 1.4)
    assert rep["speed_mps"] == {"median": 10.0, "min": 9.0, "max": 12.0, "pairs": 3} and rep["scale_uncertain"] == 1
    assert camera_summary(rep)[1].startswith("camera speed median 10.0 m/s, range 9.0-12.0 m/s over 3 moving pair(s); "
                                             "1 more with an uncertain scale, not counted")
    only_unsure = [{"camera_motion": "metric", "speed_mps": 3.0, "scale_uncertain": True}]
    rep = camera_report(only_unsure, 1.4)
    assert rep["speed_mps"] is None
    assert camera_summary(rep)[1].startswith("camera speed unknown: 1 moving pair(s), each with an uncertain scale")


def test_road_marks_are_read_only_where_the_road_flow_falls_short_of_the_stream_prediction(monkeypatch):
    """On a stream, a flow of the ground within FLOW_NEAR_PREDICTION of the predicted length is taken as
    it is (the road marks are not read: they could not override it); well short of it, the marks are
    read; without a prediction they are read as before. The scale is the flow's either way here."""
    from monostixels.inputs import motion as motion_mod
    from monostixels.inputs.motion import FLOW_NEAR_PREDICTION, MotionEstimate

    calls = []
    real = motion_mod.road_marks_scale

    def counted(*args, **kwargs):
        calls.append(kwargs.get("start"))
        return real(*args, **kwargs)

    monkeypatch.setattr(motion_mod, "road_marks_scale", counted)
    gt = Motion(R=_rot(0.8, -0.3, 0.1), t=torch.tensor([0.06, 0.01, 0.95], dtype=torch.float64))
    pair, fr = _pair_and_flow(gt)  # blank images: no photometric minimum, the flow of the ground decides

    def prior(length: float) -> MotionEstimate:
        t = gt.t / gt.t.norm() * length
        return MotionEstimate(Motion(gt.R.clone(), t), False, "ok", 1.0)

    true_len = float(gt.t.norm())
    runs = {}
    for name, p in (("scratch", None), ("near", prior(true_len * 1.05)), ("short", prior(true_len / (0.9 * FLOW_NEAR_PREDICTION)))):
        calls.clear()
        est = estimate_motion(pair, fr, MONO, prior=p)
        assert est.motion is not None and est.scale_from == "ground_flow", est.reason
        assert motion_errors(est.motion, gt)["scale_rel_err"] < 0.005
        runs[name] = len(calls)
    assert runs == {"scratch": 1, "near": 0, "short": 1}


def test_the_scene_model_checks_the_road_and_stands_in_where_it_gives_none():
    from monostixels.inputs.motion import MotionEstimate
    from monostixels.inputs.motion_scene import with_scene_scale
    from monostixels.inputs.motion_scene import SceneScale
    from monostixels.inputs.motion_track import MonoMotionConfig

    prm = MonoMotionConfig()
    R = torch.eye(3, dtype=torch.float64)
    t = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    road = MotionEstimate(Motion(R, t), False, "ok", 0.9, scale_from="ground_flow")
    # Agreeing within two standard deviations of their difference: the road's own measurement error.
    agree = with_scene_scale(road, SceneScale(1.05, 0.03, 40), t.numpy(), prm)
    assert agree.scale_std == pytest.approx(prm.scale_meas_std) and float(agree.motion.t.norm()) == 1.0
    # Twice the road's length: one of them is wrong, the pair is uncertain by the difference.
    clash = with_scene_scale(road, SceneScale(2.0, 0.03, 40), t.numpy(), prm)
    assert clash.scale_std == pytest.approx(math.log(2.0)) and clash.scale_std > prm.max_scale_std
    assert clash.scale_from == "ground_flow" and float(clash.motion.t.norm()) == 1.0
    # No length from the road: the scene model's, where it is certain enough; else still unknown.
    unknown = MotionEstimate(None, False, "no metric scale", 0.9, kind="scale_unknown", unit_motion=Motion(R, t))
    taken = with_scene_scale(unknown, SceneScale(0.8, 0.05, 40), t.numpy(), prm)
    assert taken.kind == "metric" and taken.scale_from == "scene" and float(taken.motion.t.norm()) == pytest.approx(0.8)
    assert taken.scale_std == pytest.approx(0.05)
    assert with_scene_scale(unknown, SceneScale(0.8, 0.3, 40), t.numpy(), prm).kind == "scale_unknown"


def _car_rays(R: np.ndarray, t: np.ndarray, n: int = 800, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Ray pairs (current, previous; (n, 3), z = 1) of static points 8-80 m ahead under ``X_prev = R X_cur + t``."""
    rng = np.random.default_rng(seed)
    X = np.stack([rng.uniform(-15, 15, n), rng.uniform(-4, 1.6, n), rng.uniform(8, 80, n)], 1)
    Xp = X @ R.T + t
    return X / X[:, 2:3], Xp / Xp[:, 2:3]


def test_a_cars_motion_replaces_a_sideways_travel_that_explains_no_more():
    """A car moves along its heading: its chord turns by half the yaw. A free estimate that travels sideways
    (the lateral direction traded against the yaw) is refitted as a car's motion, which recovers the true
    pose; one within the bound is left exactly as it is."""
    from monostixels.inputs.motion import _as_car_motion
    from monostixels.inputs.motion_base import MonoParams
    from monostixels.inputs.epipolar import car_offsets_deg, sampson, skew

    n_g = np.array([0.0, 1.0, 0.0])
    yaw = math.radians(0.6)
    R = _rot(0.6, 0.0, 0.0).numpy()
    t = np.array([math.sin(yaw / 2), 0.02, math.cos(yaw / 2)])  # the chord, 1 deg of pitch on the car
    t /= np.linalg.norm(t)
    a, b = _car_rays(R, t)
    fs = 0.5 / 720.0
    params = MonoParams()
    inl = np.ones(len(a), dtype=bool)
    assert car_offsets_deg(R, t, n_g)[0] < 1e-9
    # Within the bound: nothing changes (no refit).
    R1, t1, inl1, note, unit = _as_car_motion(R, t, inl, n_g, a, b, fs, params)
    assert R1 is R and t1 is t and inl1 is inl and note == "" and unit is None
    # A sideways estimate: 80 deg off a car's travel, the yaw 1.5 deg off.
    R_bad = _rot(2.1, 0.0, 0.0).numpy()
    t_bad = np.array([0.985, 0.02, 0.17])
    assert car_offsets_deg(R_bad, t_bad, n_g)[0] > 60
    R2, t2, inl2, note, unit = _as_car_motion(R_bad, t_bad, inl, n_g, a, b, fs, params)
    assert unit is None and "a car's motion" in note
    assert math.degrees(math.acos(min(1.0, float(t2 @ t)))) < 0.1
    assert np.abs(R2 - R).max() < 1e-4
    assert inl2.mean() > 0.99 and np.abs(sampson(skew(t2) @ R2, a, b)).max() < fs
    # Travelling 35 deg up off the road plane is no car's either (the bound: car_max_elevation_deg, 20).
    t_up = np.array([0.0, -math.sin(math.radians(35)), math.cos(math.radians(35))])
    assert car_offsets_deg(R, t_up, n_g)[1] > 34
    R3, t3, _, note, unit = _as_car_motion(R, t_up, inl, n_g, a, b, fs, params)
    assert unit is None and "off the road plane" in note
    assert math.degrees(math.acos(min(1.0, float(t3 @ t)))) < 0.1
    for bad in ({"car_max_azimuth_deg": -1.0}, {"car_max_elevation_deg": 91.0}, {"car_min_inlier_share": 0.0}):
        with pytest.raises(InputError, match=next(iter(bad))):
            MonoParams(**bad)


def test_a_flow_that_fits_no_cars_motion_has_no_metric_length():
    """A camera looking sideways from the car sees the travel as sideways: no car's motion explains its
    flow, so the estimate keeps only a direction and reports no length (``scale_unknown``) instead of a
    speed from a motion no car makes; with ``car_motion=false`` the free estimate stands."""
    gt = Motion(R=_rot(0.1, 0.0, 0.0), t=torch.tensor([0.9, 0.0, 0.1], dtype=torch.float64))
    pair, fr = _pair_and_flow(gt)
    est = estimate_motion(pair, fr, MONO)
    assert est.kind.value == "scale_unknown" and est.motion is None, est.reason
    assert "fits no car's motion" in est.reason
    free = estimate_motion(pair, fr, OmegaConf.create({"name": "mono", "car_motion": False}))
    assert free.motion is not None and free.kind.value == "metric"
    assert motion_errors(free.motion, gt)["trans_dir_err_deg"] < 0.1
