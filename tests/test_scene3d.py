"""Stixels in 3D (monostixels.output.scene3d): reference points, boxes, chained poses, frame times.

Asymmetric camera (fx != fy, cx, cy off-centre, H != W) so a transposition or sign slip cannot pass.
"""
from __future__ import annotations

import logging
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from monostixels.core.classes import DYNAMIC_OBJECT, GROUND, SKY, STATIC_OBJECT
from monostixels.core.geometry import Motion
from monostixels.output.scene3d import PoseChain, frame_time, optional_field, reference_points, stixel_boxes, to_world
from monostixels.core.stixels import StixelWorld
from monostixels.data.base import FrameInfo

FX, FY, CX, CY = 410.0, 380.0, 147.3, 52.6
H, W, WS = 120, 320, 8


def _world(ground_normal=(0.0, 1.0, 0.0)) -> StixelWorld:
    """Columns 5 (left of cx), 18 (at cx: u 144..151, centre 147.5) and 33 (right): ground, an object, sky."""
    K = torch.tensor([[FX, 0, CX], [0, FY, CY], [0, 0, 1]], dtype=torch.float64)
    rows = []  # column, v_top, v_bottom, type, class, inverse depth
    for c, obj_type, d in ((5, STATIC_OBJECT, 12.0), (18, DYNAMIC_OBJECT, 7.5), (33, STATIC_OBJECT, 20.0)):
        rows += [(c, 90, H - 1, GROUND, 0, 1 / 1.65), (c, 40, 89, obj_type, 6 if obj_type == DYNAMIC_OBJECT else 3, 1 / d),
                 (c, 0, 39, SKY, 9, 0.0)]
    col, top, bot, typ, cls, p = (torch.tensor(x) for x in zip(*rows))
    n = len(rows)
    motion = torch.zeros(n, 3, dtype=torch.float64)
    motion[typ == DYNAMIC_OBJECT] = torch.tensor([0.1, 0.0, 0.4], dtype=torch.float64)
    return StixelWorld(column_width=WS, image_size=(H, W), K=K, ground_normal=torch.tensor(ground_normal, dtype=torch.float64),
                       column=col.long(), v_top=top.long(), v_bottom=bot.long(), type=typ.long(), cls=cls.long(),
                       inverse_depth=p.double(), motion=motion, cost=torch.zeros(n, dtype=torch.float64),
                       tau=torch.zeros(n, 2, dtype=torch.float64), energy=torch.zeros(40, dtype=torch.float64))


def _project(X: np.ndarray) -> np.ndarray:
    return np.stack([FX * X[..., 0] / X[..., 2] + CX, FY * X[..., 1] / X[..., 2] + CY], -1)


def test_reference_points_have_the_depth_of_the_stixel():
    st = _world()
    X = reference_points(st)
    depth = st.depth.double().numpy()
    sky = st.type.numpy() == SKY
    assert np.isnan(X[sky]).all()
    assert np.allclose(X[~sky, 2], depth[~sky], rtol=1e-6)
    # The pixel it projects to: column centre, bottom row (ground) or middle row (objects).
    uv = _project(X[~sky])
    c, top, bot = (st.column.numpy()[~sky], st.v_top.numpy()[~sky], st.v_bottom.numpy()[~sky])
    ground = st.type.numpy()[~sky] == GROUND
    assert np.allclose(uv[:, 0], c * WS + (WS - 1) / 2, atol=1e-6)
    assert np.allclose(uv[:, 1], np.where(ground, bot, (top + bot) // 2), atol=1e-6)
    # The ground point lies on the ground plane (y = camera height for a level camera).
    assert np.allclose(X[~sky][ground, 1], 1.65, atol=1e-9)


@pytest.mark.parametrize("pitch_deg", [0.0, 4.0])
def test_boxes_are_the_object_stixels_standing_on_their_planes(pitch_deg):
    a = math.radians(pitch_deg)
    ng = np.array([0.0, math.cos(a), math.sin(a)])  # camera pitched: the ground normal tilts
    st = _world(tuple(ng))
    boxes = stixel_boxes(st)
    objects = np.nonzero(np.isin(st.type.numpy(), (STATIC_OBJECT, DYNAMIC_OBJECT)))[0]
    assert boxes.index.tolist() == objects.tolist()
    for k, i in enumerate(boxes.index):
        Rb, c, h = boxes.rotations[k], boxes.centers[k], boxes.half_sizes[k]
        assert np.allclose(Rb.T @ Rb, np.eye(3), atol=1e-9) and np.linalg.det(Rb) > 0
        assert np.allclose(Rb[:, 1], ng, atol=1e-9)  # down = the ground normal
        assert abs(Rb[:, 2] @ ng) < 1e-9 and Rb[2, 2] > 0  # depth axis horizontal, away from the camera
        # The front face is on the stixel's plane n^T X = 1/p (n = the depth axis).
        front = c - Rb[:, 2] * h[2]
        assert Rb[:, 2] @ front == pytest.approx(1 / float(st.inverse_depth[i]), rel=1e-9)
        # The four corners of the pixel region (pixel edges) lie in the front face.
        u0, u1 = st.column[i].item() * WS - 0.5, (st.column[i].item() + 1) * WS - 0.5
        v0, v1 = st.v_top[i].item() - 0.5, st.v_bottom[i].item() + 0.5
        n = Rb[:, 2]
        for u, v in ((u0, v0), (u1, v0), (u0, v1), (u1, v1)):
            r = np.array([(u - CX) / FX, (v - CY) / FY, 1.0])
            P = r * (Rb[:, 2] @ front) / (r @ n)
            local = Rb.T @ (P - c)
            assert np.all(np.abs(local[:2]) <= h[:2] + 1e-9) and local[2] == pytest.approx(-h[2])
        # Tight: for a level camera the face projects onto the stixel's rows (a column's two pixel
        # edges meet the plane at slightly different depths: the box bounds both, within 0.1 px).
        if pitch_deg == 0.0:
            top, bottom = c - Rb[:, 2] * h[2] - Rb[:, 1] * h[1], c - Rb[:, 2] * h[2] + Rb[:, 1] * h[1]
            assert _project(top)[1] == pytest.approx(v0, abs=0.1)
            assert _project(bottom)[1] == pytest.approx(v1, abs=0.1)
    # The column at the principal point faces straight ahead, its face exactly the column's pixels.
    k = int(np.nonzero(st.column.numpy()[boxes.index] == 18)[0][0])
    if pitch_deg == 0.0:
        face = boxes.centers[k] - boxes.rotations[k][:, 2] * boxes.half_sizes[k][2]
        left, right = (face - s * boxes.rotations[k][:, 0] * boxes.half_sizes[k][0] for s in (1, -1))
        assert _project(left)[0] == pytest.approx(18 * WS - 0.5, abs=0.05)
        assert _project(right)[0] == pytest.approx(19 * WS - 0.5, abs=0.05)


def _pair(meta: dict, name: str = "") -> SimpleNamespace:
    """A stand-in pair: what a source writes (``meta``) and its typed view (``info``)."""
    return SimpleNamespace(meta=meta, info=FrameInfo.of(meta), name=name)


def _res(R: np.ndarray, t: np.ndarray, **extra) -> SimpleNamespace:
    m = Motion(torch.from_numpy(R), torch.from_numpy(t))
    return SimpleNamespace(motion=SimpleNamespace(motion=m), **extra)


def _rot_y(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def test_pose_chain_maps_every_frame_into_the_first_camera():
    """A static point seen in each frame lands on the same world point: X_w = T_w_k X_k."""
    rng = np.random.default_rng(0)
    motions = [(_rot_y(d), rng.normal(size=3)) for d in (3.0, -5.0, 8.0)]  # X_{k-1} = R X_k + t
    X_w = np.array([1.5, 0.7, 9.0])
    chain = PoseChain()
    X_k = X_w.copy()  # frame 0 = the world
    for k, (R, t) in enumerate(motions, start=1):
        X_k = R.T @ (X_k - t)  # the same point in camera k
        pair = _pair({"source": "video", "frame": k, "frame_prev": k - 1}, name=f"f{k}")
        T = chain.update(pair, _res(R, t))
        assert np.allclose(to_world(T, X_k), X_w, atol=1e-9)
    # Forward 1 m: the camera centre is at z = +1 in the world.
    T = PoseChain().update(_pair({}), _res(np.eye(3), np.array([0.0, 0.0, 1.0])))
    assert np.allclose(T[:3, 3], [0, 0, 1])


def test_pose_chain_keeps_the_recent_frames_only():
    """A camera left running: the chain keeps a bounded number of poses and still chains the last frames."""
    from monostixels.output.scene3d import _KEPT_POSES

    chain = PoseChain()
    R, t = _rot_y(0.5), np.array([0.0, 0.0, 1.0])
    step = np.eye(4)
    step[:3, :3], step[:3, 3] = R, t
    T = np.eye(4)
    for k in range(1, 3 * _KEPT_POSES):
        T = T @ step
        got = chain.update(_pair({"source": "video", "frame": k, "frame_prev": k - 1}, name=f"f{k}"),
                           _res(R, t))
        assert np.allclose(got, T)
        assert len(chain._poses) <= _KEPT_POSES
    # A keyframe pair reaching back 10 frames still finds its previous frame's pose.
    k = 3 * _KEPT_POSES
    back = chain.update(_pair({"source": "video", "frame": k, "frame_prev": k - 10}, name="f"), _res(R, t))
    assert np.allclose(back, chain._poses[("frame", k - 10)] @ step)


def test_pose_chain_follows_the_previous_frame_not_the_previous_pair(caplog):
    """Image folders with step 2: pairs (2, 0), (3, 1), (4, 2): frame 4 chains on frame 2."""
    chain = PoseChain()
    M = {k: (_rot_y(k), np.array([0.1 * k, 0.0, 1.0])) for k in (2, 3, 4)}

    def pair(k):
        return _pair({"path": f"{k}.png", "path_prev": f"{k - 2}.png"}, name=f"{k}")

    T2 = chain.update(pair(2), _res(*M[2]))
    with caplog.at_level(logging.WARNING, logger="monostixels.output.scene3d"):
        chain.update(pair(3), _res(*M[3]))  # frame 1 was never a current frame: approximate, said once
    assert "pose is unknown" in caplog.text
    T4 = chain.update(pair(4), _res(*M[4]))
    step = np.eye(4)
    step[:3, :3], step[:3, 3] = M[4]
    assert np.allclose(T4, T2 @ step)
    # A pose from the sequence layer wins over the chain.
    given = np.eye(4)
    given[:3, 3] = [5, 6, 7]
    assert np.allclose(chain.update(pair(5), _res(*M[4], pose=torch.from_numpy(given))), given)


def test_frame_time_and_optional_fields():
    assert frame_time(_pair({"source": "video", "frame": 7}), 10.0) == pytest.approx(0.7)
    assert frame_time(_pair({"source": "video", "frame": 7}), None) is None
    assert frame_time(_pair({"source": "frames", "index": 7}), 10.0) is None
    assert frame_time(_pair({"time_s": 3.25}), None) == 3.25
    st = _world()
    assert optional_field(st, "track_id") is None
    st.track_id = torch.arange(len(st))  # as the sequence layer will add it
    assert optional_field(st, "track_id").tolist() == list(range(len(st)))
