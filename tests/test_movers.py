"""The post-solve mover check (monostixels.post.movers): standing-still objects lose their false motion,
crossing and oncoming movers keep theirs. Hand-made flow of a fronto-parallel wall."""
from __future__ import annotations

import math

import torch

from monostixels.core.classes import DYNAMIC_OBJECT, STATIC_OBJECT
from monostixels.core.geometry import Motion, apply_homography, homography, intrinsics, pixel_rays
from monostixels.post.movers import MoverCheckParams, check_movers
from monostixels.core.stixels import StixelWorld


def geometric(**kw) -> MoverCheckParams:
    """The purely geometric check (no kept classes, no dynamic-residual test, no isolated stand-still, no
    contact slivers) with ``kw`` on top: what these scenes test; the shipped check is the defaults."""
    return MoverCheckParams(**{"keep_classes": (), "max_dynamic_residual_ratio": math.inf, "isolated_stand_still": False,
                               "contact_sliver_rows": 0.0, **kw})

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
    out = check_movers(st, flow, MOTION, params=geometric())
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
    assert check_movers(st, flow, MOTION, params=geometric(enabled=False)) is st
    still = Motion(torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    assert check_movers(st, flow, still) is st


def test_an_uncertain_scale_leaves_only_the_movers_that_break_the_epipolar_constraint():
    # The same scene as above with a camera motion whose length is not trusted (motion.max_scale_std): the
    # oncoming car of column 1 (epipolar flow, its contact elsewhere) can no longer be told from a static
    # object at a wrong scale, and stands still, even as a kept class; the crossing mover stays dynamic.
    flow = _wall_flow(10.0)
    flow[0, :, 30:50] += 8.0
    types = [DYNAMIC_OBJECT, DYNAMIC_OBJECT, STATIC_OBJECT, DYNAMIC_OBJECT, DYNAMIC_OBJECT, DYNAMIC_OBJECT]
    st = _world([1 / 10.5, 1 / 4.0, 1 / 10.5, 1 / 10.0, 1 / 10.0, 1 / 10.0], types)
    st.cls[1] = 8  # a person: kept dynamic by the shipped check where the scale is known
    known = check_movers(st, flow, MOTION, params=MoverCheckParams())
    unsure = check_movers(st, flow, MOTION, params=MoverCheckParams(), scale_known=False)
    assert known.type[1] == DYNAMIC_OBJECT
    assert unsure.type[0] == STATIC_OBJECT and unsure.type[1] == STATIC_OBJECT and unsure.type[5] == STATIC_OBJECT
    assert unsure.type[3] == DYNAMIC_OBJECT and unsure.type[4] == DYNAMIC_OBJECT  # off the epipolar lines
    assert float(unsure.motion[1].norm()) == 0.0 and unsure.flags["static_checked"] == 3
    # Their depths stay the scene model's: the flow's static depth scales with the uncertain length.
    assert torch.equal(unsure.inverse_depth, st.inverse_depth)
    # The same decisions where the uncertain length is 20x short (every static depth triangulates to 0.5 m,
    # under the check's depth range): whether a flow fits the epipolar geometry does not depend on the length.
    short = Motion(MOTION.R, MOTION.t / 20.0)
    unsure_short = check_movers(st, flow, short, params=MoverCheckParams(), scale_known=False)
    assert torch.equal(unsure_short.type, unsure.type) and unsure_short.flags["static_checked"] == 3
    # A frame whose static objects' own flow lies 12 px off the epipolar lines (a rotation or direction as
    # uncertain as the length): an 8 px crossing flow is no motion of its own there; 30 px off still is.
    noisy = flow.clone()
    noisy[0, :, 20:30] += 12.0  # column 2, the static object
    noisy[0, :, 40:50] += 22.0  # column 4: 30 px
    loose = check_movers(st, noisy, MOTION, params=MoverCheckParams(), scale_known=False)
    assert loose.type[3] == STATIC_OBJECT and loose.type[4] == DYNAMIC_OBJECT
    # The distance it judges by: exact on the epipolar lines, the sideways offset off them.
    from monostixels.post.movers import epipolar_distance
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    exact = _wall_flow(10.0)
    on = epipolar_distance(K, MOTION.R, MOTION.t, u.flatten(), v.flatten(), exact[0].flatten(), exact[1].flatten())
    finite = torch.isfinite(on)
    assert float(on[finite].max()) < 1e-3
    # Only the epipole itself (pixel (32, 18), where t points) has no line: inf (the static quantile leaves it out).
    assert [(int(a), int(b)) for a, b in zip(u.flatten()[~finite], v.flatten()[~finite])] == [(32, 18)]
    foe_row = 18.0  # a pixel straight above the focus of expansion: its epipolar line is the column itself
    d = epipolar_distance(K, MOTION.R, MOTION.t, torch.tensor([32.0]), torch.tensor([foe_row - 15.0]),
                          torch.tensor([5.0]), torch.tensor([0.0]))
    assert abs(float(d) - 5.0) < 0.01


# A camera with a KITTI-like focal length, so that a depth difference shows as rows at the ground contact.
KC = intrinsics(500.0, 500.0, 90.0, 20.0)  # the columns lie 70-90 px left of the focus of expansion
HC, WC, H_CAM = 120, 20, 1.5


def _contact_world(d_model: float, upper: bool = False, sliver_rows: int = 0) -> StixelWorld:
    """Two columns: a dynamic object stixel standing on a ground stixel (height H_CAM) at the row where a
    plane at ``d_model`` meets the ground (the scene model's contact); optionally a dynamic stixel on top,
    and optionally a dynamic stixel ``sliver_rows`` tall between the object and the ground."""
    v_c = int(round(20.0 + 500.0 * H_CAM / d_model))  # contact row (camera looks straight ahead)
    v_o = v_c - sliver_rows  # the object's lower end
    cols, tops, bots, types, ps = [], [], [], [], []
    for c in range(2):
        segs = [(v_c, HC - 1, 0, 1.0 / H_CAM)]
        if sliver_rows:
            segs.append((v_o, v_c - 1, DYNAMIC_OBJECT, 1.0 / d_model))
        segs.append((30 if upper else 0, v_o - 1, DYNAMIC_OBJECT, 1.0 / d_model))
        if upper:
            segs.append((0, 29, DYNAMIC_OBJECT, 1.0 / d_model))
        for a, b, ty, p in segs:
            cols.append(c), tops.append(a), bots.append(b), types.append(ty), ps.append(p)
    n = len(cols)
    return StixelWorld(
        column_width=WS, image_size=(HC, WC), K=KC, ground_normal=N_G,
        column=torch.tensor(cols), v_top=torch.tensor(tops), v_bottom=torch.tensor(bots),
        type=torch.tensor(types), cls=torch.full((n,), 7), inverse_depth=torch.tensor(ps, dtype=torch.float64),
        motion=torch.tensor([[0.0, 0.0, 0.2]] * n, dtype=torch.float64), cost=torch.zeros(n),
        tau=torch.zeros(n, 2, dtype=torch.float64), energy=torch.zeros(2))


def _moving_wall_flow(depth: float, delta_z: float) -> torch.Tensor:
    """Exact flow (2, HC, WC) under MOTION of a wall ``z = depth`` that moves by ``delta_z`` metres forward
    (``X_prev = X_cur - Δ + t``): along the camera's own direction, so the flow stays on the epipolar lines."""
    v, u = torch.meshgrid(torch.arange(HC, dtype=torch.float64), torch.arange(WC, dtype=torch.float64), indexing="ij")
    t_rel = MOTION.t - torch.tensor([0.0, 0.0, delta_z], dtype=torch.float64)
    Hm = homography(KC, MOTION.R, t_rel, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64),
                    torch.tensor(1.0 / depth, dtype=torch.float64))
    up, vp = apply_homography(Hm, u, v)
    return torch.stack([up - u, vp - v]).float()


def test_mover_along_epipolar_lines_on_the_ground_stays_dynamic():
    # A two-wheeler 10 m ahead riding away at 0.25 m per frame (2.5 m/s), the camera 1 m per frame: its
    # flow is that of a static object at 13.3 m (d_model / d_s - 1 = -25 %) with a small residual; the old
    # rule (30 % relative depth window) made it static at 13.3 m. Its contact with the road says 10 m: a
    # static object at 13.3 m would meet the road 19 rows above the stixel's bottom (tolerance 12).
    flow = _moving_wall_flow(10.0, 0.25)
    st = _contact_world(10.0)
    old = check_movers(st, flow, MOTION, params=geometric(max_contact_gap_px=float("inf"), follow_below=False))
    assert old.flags["static_checked"] == 2  # the old rule flipped both columns
    out = check_movers(st, flow, MOTION, params=geometric())
    assert out.flags["static_checked"] == 0
    assert torch.equal(out.type, st.type) and torch.equal(out.inverse_depth, st.inverse_depth)
    # The upper part of the same moving object (stacked on it) stays dynamic too: the stack stands on the road.
    flow_u = _moving_wall_flow(10.0, 0.25)
    st_u = _contact_world(10.0, upper=True)
    old_u = check_movers(st_u, flow_u, MOTION, params=geometric(max_contact_gap_px=float("inf"), follow_below=False))
    assert old_u.flags["static_checked"] == 4
    assert check_movers(st_u, flow_u, MOTION, params=geometric()).flags["static_checked"] == 0


def test_parked_object_on_the_ground_still_becomes_static():
    # Parked 10.5 m away, the scene model says 10 m (5 % off, 3.6 rows at the contact): it stands still,
    # and so does the part stacked on it (compared with the lower part's static depth).
    flow = _wall_flow_kc(10.5)
    for upper in (False, True):
        st = _contact_world(10.0, upper=upper)
        out = check_movers(st, flow, MOTION, params=geometric())
        dyn = st.type == DYNAMIC_OBJECT
        assert out.flags["static_checked"] == int(dyn.sum())
        assert bool((out.type[dyn] == STATIC_OBJECT).all()) and float(out.motion[dyn].abs().max()) == 0.0
        d = 1.0 / out.inverse_depth[dyn]
        assert bool(((d / 10.5 - 1.0).abs() < 0.02).all())  # at the static fit's depth


def test_static_part_above_a_parked_object_follows_its_static_depth():
    # Lower part parked at 10.5 m (model 10 m); the stixel above it is a wall 14.7 m away that the
    # structural prior put at the lower part's depth: 10 / 14.7 - 1 is beyond the 30 % window, but against the
    # lower part's static depth (10.5 m) it is within it -> it stands still as well.
    flow = _wall_flow_kc(10.5)
    flow[:, :30] = _wall_flow_kc(14.7)[:, :30]
    st = _contact_world(10.0, upper=True)
    out = check_movers(st, flow, MOTION, params=geometric())
    assert out.flags["static_checked"] == 4
    no_follow = check_movers(st, flow, MOTION, params=geometric(follow_below=False))
    assert no_follow.flags["static_checked"] == 2


def _wall_flow_kc(depth: float) -> torch.Tensor:
    return _moving_wall_flow(depth, 0.0)


def test_kept_classes_stay_dynamic_where_the_geometry_cannot_tell():
    # A pedestrian 10 m ahead walking away at 0.05 m per frame: a static object at 10.5 m explains its flow
    # (5 %, 3.8 rows at the contact), so the geometric check makes it static; a kept class stays dynamic,
    # and so does the part stacked on it (the stack stands on the road).
    import dataclasses

    from monostixels.core.classes import CLASS_NAMES

    flow = _moving_wall_flow(10.0, 0.05)
    person, vehicle = CLASS_NAMES.index("person"), CLASS_NAMES.index("vehicle")
    for upper in (False, True):
        base = _contact_world(10.0, upper=upper)
        dyn = base.type == DYNAMIC_OBJECT
        walker = dataclasses.replace(base, cls=torch.where(dyn, person, 0))
        car = dataclasses.replace(base, cls=torch.where(dyn, vehicle, 0))
        keep = geometric(keep_classes=("person", "two_wheeler"))
        assert check_movers(walker, flow, MOTION, params=geometric()).flags["static_checked"] == int(dyn.sum())
        out = check_movers(walker, flow, MOTION, params=keep)
        assert out.flags["static_checked"] == 0
        assert torch.equal(out.type, walker.type) and torch.equal(out.inverse_depth, walker.inverse_depth)
        # Other classes are still decided by the geometry.
        assert check_movers(car, flow, MOTION, params=keep).flags["static_checked"] == int(dyn.sum())


def test_keep_classes_from_the_config_and_bad_names():
    import pytest
    from omegaconf import OmegaConf

    from monostixels._checks import InputError, config_params
    from monostixels.pipeline import load_config

    def params(cfg):
        return config_params(MoverCheckParams, cfg, "movers")

    assert OmegaConf.to_object(load_config([]).movers).keep_classes == ("person", "two_wheeler")
    assert params(OmegaConf.create({"keep_classes": []})).keep_classes == ()
    with pytest.raises(InputError, match="movers.keep_classes.*'pedestrian'"):
        params(OmegaConf.create({"keep_classes": ["person", "pedestrian"]}))
    with pytest.raises(InputError, match="movers.keep_classes"):
        params(OmegaConf.create({"keep_classes": "person"}))
    with pytest.raises(InputError, match="movers.max_dynamic_residual_ratio.*'lots'"):
        params(OmegaConf.create({"max_dynamic_residual_ratio": "lots"}))
    with pytest.raises(InputError, match="movers.max_dynamic_residual_ratio: expected a number, got 'lots'"):
        load_config(["movers.max_dynamic_residual_ratio=lots"])



def _ground_flow_kc() -> torch.Tensor:
    """Exact flow (2, HC, WC) under MOTION of the road H_CAM below the camera (rows below the horizon)."""
    v, u = torch.meshgrid(torch.arange(HC, dtype=torch.float64), torch.arange(WC, dtype=torch.float64), indexing="ij")
    Hm = homography(KC, MOTION.R, MOTION.t, N_G, torch.tensor(1.0 / H_CAM, dtype=torch.float64))
    up, vp = apply_homography(Hm, u, v)
    return torch.stack([up - u, vp - v]).float()


def test_dynamic_plane_must_explain_the_flow_markedly_better():
    # Column 0: the near road taken for an object (rows 40-119, 37 m to 8 m away), dynamic with no motion
    # at its median depth: neither the static nor that dynamic upright plane explains the flow of a
    # surface whose depth runs over the whole range (both residuals well above max_static_residual_px),
    # so no motion is detected. Column 1: a crossing mover 10 m away, 8 px sideways, whose dynamic plane
    # carries that motion: it stays dynamic.
    flow = _ground_flow_kc()
    flow[:, :, 10:] = _wall_flow_kc(10.0)[:, :, 10:]
    flow[0, :, 10:] += 8.0
    v, u = torch.meshgrid(torch.arange(40, HC, dtype=torch.float64), torch.arange(10, dtype=torch.float64), indexing="ij")
    ray = pixel_rays(KC.double(), u, v)
    n0 = ray[0, 5] * torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64)
    z = H_CAM / ray[..., 1]  # on the road
    d_road = float((z * (ray @ (n0 / n0.norm()))).median())
    dx = -8.0 * (10.0 + float(MOTION.t[2])) / float(KC[0, 0])

    def world(p1: float, motion1: torch.Tensor) -> StixelWorld:
        return StixelWorld(
            column_width=WS, image_size=(HC, WC), K=KC, ground_normal=N_G,
            column=torch.tensor([0, 1]), v_top=torch.tensor([40, 0]), v_bottom=torch.tensor([HC - 1, HC - 1]),
            type=torch.tensor([DYNAMIC_OBJECT] * 2), cls=torch.tensor([6, 6]),
            inverse_depth=torch.tensor([1.0 / d_road, p1], dtype=torch.float64),
            motion=torch.stack([torch.zeros(3, dtype=torch.float64), motion1]), cost=torch.zeros(2),
            tau=torch.zeros(2, 2, dtype=torch.float64), energy=torch.zeros(2))

    # Give the mover the static fit's depth (so that only the residual tests decide) and the motion that
    # makes its dynamic plane produce its flow there: g = p (t - Δ) equal to the true wall's.
    probe = check_movers(world(0.1, torch.tensor([dx, 0.0, 0.0], dtype=torch.float64)), flow, MOTION,
                         params=geometric(max_static_residual_px=float("inf"), min_depth_discrepancy=float("inf")))
    p1 = float(probe.inverse_depth[1])
    g = 0.1 * (MOTION.t - torch.tensor([dx, 0.0, 0.0], dtype=torch.float64))
    st = world(p1, MOTION.t - g / p1)
    off = check_movers(st, flow, MOTION, params=geometric())
    assert off.flags["static_checked"] == 0  # the residual test alone keeps both dynamic
    on = check_movers(st, flow, MOTION, params=geometric(max_dynamic_residual_ratio=0.3))
    assert on.type.tolist() == [STATIC_OBJECT, DYNAMIC_OBJECT]
    assert float(on.motion[0].abs().max()) == 0.0 and torch.equal(on.motion[1], st.motion[1])
    # Without the residual test the mover's flow would pass as static: its dynamic plane alone keeps it.
    assert check_movers(st, flow, MOTION, params=geometric(max_static_residual_px=float("inf"))).type[1] == STATIC_OBJECT
    # The static depth is the road points' median distance along the viewing direction.
    assert abs(1.0 / float(on.inverse_depth[0]) / d_road - 1.0) < 0.05


def test_background_above_a_parked_object_may_lie_behind_it():
    # Lower part parked at 10.5 m (model 10 m, made static); above it, the structural prior's stack holds the
    # background 20 m away (90 % behind the lower part's static depth). With allow_behind_still the
    # background stands still at its own depth; a stixel 40 % *nearer* than the object below stays dynamic.
    for d_up, behind in ((20.0, True), (6.0, False)):
        flow = _wall_flow_kc(10.5)
        flow[:, :30] = _wall_flow_kc(d_up)[:, :30]
        st = _contact_world(10.0, upper=True)
        upper = st.v_bottom == 29
        default = check_movers(st, flow, MOTION, params=geometric())
        assert bool((default.type[upper] == DYNAMIC_OBJECT).all())
        out = check_movers(st, flow, MOTION, params=geometric(allow_behind_still=True))
        assert bool((out.type[~upper & (st.type == DYNAMIC_OBJECT)] == STATIC_OBJECT).all())
        assert bool((out.type[upper] == (STATIC_OBJECT if behind else DYNAMIC_OBJECT)).all())
        if behind:
            assert bool(((1.0 / out.inverse_depth[upper]) / d_up - 1.0).abs().max() < 0.03)


def test_an_isolated_dynamic_stixel_stands_still():
    # A mover in columns 3-4 whose flow leaves the epipolar lines (4 px down); in a second scene only column
    # 3 carries the motion (a one-column sliver). The residual test keeps both dynamic; with
    # isolated_stand_still the two-column mover stays, the sliver (no dynamic neighbour) stands still at
    # the static fit's depth. A kept class is never made static.
    import dataclasses

    prm = geometric(isolated_stand_still=True)
    for cols, want_dynamic in (((3, 4), True), ((3,), False)):
        flow = _wall_flow(10.0)
        for c in cols:
            flow[1, :, c * WS:(c + 1) * WS] += 4.0
        types = [STATIC_OBJECT] * 6
        for c in cols:
            types[c] = DYNAMIC_OBJECT
        st = _world([1 / 10.0] * 6, types)
        assert check_movers(st, flow, MOTION, params=geometric()).flags["static_checked"] == 0
        out = check_movers(st, flow, MOTION, params=prm)
        assert bool((out.type[list(cols)] == DYNAMIC_OBJECT).all()) == want_dynamic
        if not want_dynamic:
            assert float(out.motion[3].abs().max()) == 0.0 and out.cls[3] == st.cls[3]
            walker = dataclasses.replace(st, cls=torch.full_like(st.cls, 8))
            kept = check_movers(walker, flow, MOTION, params=dataclasses.replace(prm, keep_classes=("person",)))
            assert kept.type[3] == DYNAMIC_OBJECT


def test_mover_on_a_contact_sliver_keeps_its_ground_contact():
    # flow=deepflow trusts sub-pixel flow, and the rows where a car meets the road (shadow, bumper)
    # become a stixel of their own whose flow is the road's. The same two-wheeler as above (10 m ahead,
    # riding away at 0.25 m per frame: static fit 13.3 m) stands on a 5-row sliver with the road's flow.
    v_c = int(round(20.0 + 500.0 * H_CAM / 10.0))  # 95: where the stack meets the road
    st = _contact_world(10.0, sliver_rows=5)
    flow = _moving_wall_flow(10.0, 0.25)
    flow[:, v_c - 5:] = _ground_flow_kc()[:, v_c - 5:]
    sliver, mover = torch.tensor([1, 4]), torch.tensor([2, 5])
    # Off: the sliver stands still (its flow is the road's), and the mover above it, compared only with
    # the sliver's static depth (10.4 m vs 13.3 m: within the 30 % window), stands still at 13.3 m.
    off = check_movers(st, flow, MOTION, params=geometric(contact_sliver_rows=0.0))
    assert bool((off.type[sliver] == STATIC_OBJECT).all()) and bool((off.type[mover] == STATIC_OBJECT).all())
    # On: the mover stands on the road through the sliver; a static object at 13.3 m would meet it 19 rows
    # above the contact (tolerance 12), so it keeps its motion and the contact's depth.
    on = check_movers(st, flow, MOTION, params=geometric(contact_sliver_rows=12.0))
    assert bool((on.type[sliver] == STATIC_OBJECT).all())
    assert bool((on.type[mover] == DYNAMIC_OBJECT).all()) and torch.equal(on.inverse_depth[mover], st.inverse_depth[mover])
    # A sliver taller than the setting is an object of its own: the old comparison applies.
    assert bool((check_movers(st, flow, MOTION, params=geometric(contact_sliver_rows=4.0)).type[mover] == STATIC_OBJECT).all())


def test_a_static_object_that_pulls_away_takes_the_scene_models_depth():
    # A truck 10 m ahead that the net calls a building (typed static) and that pulls away at 1.5 m per frame,
    # the camera 1 m: its flow triangulates behind the camera. It stands on the ground stixel below at the
    # contact row, so its depth becomes 10 m, and the stixel stacked on it takes that depth too. A static wall
    # at 10 m (its flow the camera's alone) keeps its depth.
    import dataclasses

    from monostixels.post.movers import settle_receding

    st = _contact_world(10.0, upper=True)
    st = dataclasses.replace(st, type=torch.where(st.type == DYNAMIC_OBJECT, STATIC_OBJECT, st.type),
                             cls=torch.full_like(st.cls, 3), inverse_depth=torch.where(
                                 st.type == DYNAMIC_OBJECT, torch.full_like(st.inverse_depth, 1 / 30.0), st.inverse_depth))
    out = settle_receding(st, _moving_wall_flow(10.0, 1.5), MOTION, H_CAM)
    obj = out.type == STATIC_OBJECT
    assert out.flags["receding_static"] == int(obj.sum()) == 4
    # Within 3 % of the 10 m it was made at: the contact is a pixel's lower edge (half a row off at 75 rows
    # below the horizon), and the stixel's plane faces the column's ray, not the wall's z.
    assert torch.allclose(1.0 / out.inverse_depth[obj], torch.full((4,), 10.0, dtype=torch.float64), rtol=0.03)
    assert float(st.inverse_depth[obj].max()) < 0.05  # it was at 30 m
    assert torch.equal(out.type, st.type) and torch.equal(out.cls, st.cls)
    still = settle_receding(st, _moving_wall_flow(10.0, 0.0), MOTION, H_CAM)
    assert still is st  # nothing recedes
