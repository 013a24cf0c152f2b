"""The post-solve mover check (monostixels.movers): standing-still objects lose their false motion,
crossing and oncoming movers keep theirs. Hand-made flow of a fronto-parallel wall."""
from __future__ import annotations

import torch

from monostixels.classes import DYNAMIC_OBJECT, STATIC_OBJECT
from monostixels.geometry import Motion, apply_homography, homography, intrinsics, pixel_rays
from monostixels.movers import MoverCheckParams, check_movers
from monostixels.stixels import StixelWorld

H, W, WS = 40, 60, 10
K = intrinsics(50.0, 48.0, 31.0, 18.0)
N_G = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
MOTION = Motion(torch.eye(3, dtype=torch.float64), torch.tensor([0.02, 0.0, 1.0], dtype=torch.float64))


def _wall_flow(depth: float) -> torch.Tensor:
    """Exact flow (2, H, W) of a wall ``z = depth`` (normal (0, 0, 1)) under MOTION."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    Hm = homography(K, MOTION.R, MOTION.t, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64),
                    torch.tensor(1.0 / depth, dtype=torch.float64))
    up, vp = apply_homography(Hm, u, v)
    return torch.stack([up - u, vp - v]).float()


def _world(p: list[float], types: list[int]) -> StixelWorld:
    n = len(p)
    return StixelWorld(
        column_width=WS, image_size=(H, W), K=K, ground_normal=N_G,
        column=torch.arange(n), v_top=torch.zeros(n, dtype=torch.long), v_bottom=torch.full((n,), H - 1),
        type=torch.tensor(types), cls=torch.full((n,), 6), inverse_depth=torch.tensor(p, dtype=torch.float64),
        motion=torch.tensor([[0.0, 0.0, 0.06]] * n, dtype=torch.float64), cost=torch.zeros(n),
        tau=torch.zeros(n, 2, dtype=torch.float64), energy=torch.zeros(-(-W // WS)))


def test_standing_still_vs_crossing_vs_oncoming():
    flow = _wall_flow(10.0)
    # Columns 3-4: a crossing mover, 8 px sideways (leaves the epipolar lines).
    flow[0, :, 30:50] += 8.0
    # Column 0: the scene model put it 5 % too far: a parked car read as moving 0.06 m / frame.
    # Column 1: the model puts it at 4 m: an oncoming car (flow looks like 10 m, contact says 4 m).
    # Column 2: a static object stixel (never touched). Columns 3, 4: the crossing mover.
    st = _world([1 / 10.5, 1 / 4.0, 1 / 10.5, 1 / 10.0, 1 / 10.0, 1 / 10.0],
                [DYNAMIC_OBJECT, DYNAMIC_OBJECT, STATIC_OBJECT, DYNAMIC_OBJECT, DYNAMIC_OBJECT, DYNAMIC_OBJECT])
    out = check_movers(st, flow, MOTION, params=MoverCheckParams())
    # Column normals are horizontal viewing directions, not the wall's (0, 0, 1): the static fit is
    # the median over the column's pixels of their distance along the normal, d = z (n . r), z = 10 m.
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(WS, dtype=torch.float64), indexing="ij")
    want = float((10.0 * (pixel_rays(K.double(), u, v) @ st.normals()[0].double())).median())
    assert abs(1.0 / float(out.inverse_depth[0]) - want) < 1e-3
    # A vehicle standing still: a static object stixel, class kept, no motion.
    assert float(out.motion[0].norm()) == 0.0 and out.type[0] == STATIC_OBJECT and out.cls[0] == 6
    assert torch.equal(out.tau[0], torch.zeros(2, dtype=out.tau.dtype))
    for k in (1, 2, 3, 4):
        assert float(out.inverse_depth[k]) == float(st.inverse_depth[k]) and torch.equal(out.motion[k], st.motion[k])
        assert out.type[k] == st.type[k]
    assert out.flags["static_checked"] == 2  # columns 0 and 5 (5: the wall beside the mover)
    # Disabled, or without translation: unchanged.
    assert check_movers(st, flow, MOTION, params=MoverCheckParams(enabled=False)) is st
    still = Motion(torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    assert check_movers(st, flow, still) is st
