"""Video as the unit: keyframes, synthetic sequences, tracks, velocities and time to collision."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from monostixels._checks import InputError
from monostixels.data.base import PreviousFrame
from monostixels.build import build_source
from monostixels.data.synthetic import SyntheticSequence, render_pair
from monostixels.core.geometry import Motion, object_normals, pixel_rays
from monostixels.pipeline import Pipeline, load_config
from monostixels.build import pipeline_settings, sequence_settings
from monostixels.sequence import KeyframeParams, SequenceRunner, choose_keyframe
from monostixels.core.stixels import StixelWorld
from monostixels.sequence.tracking import TrackParams, Tracks
from monostixels.sequence.ttc import TtcParams, critical, time_to_collision


def _prev(back: int, tz: float | None, dt: float = 0.1) -> PreviousFrame:
    motion = None if tz is None else Motion(torch.eye(3, dtype=torch.float64), torch.tensor([0.0, 0.0, tz], dtype=torch.float64))
    return PreviousFrame(back=back, dt=dt * back, motion=motion, name=f"f{back}")


# ---------------------------------------------------------------------------------------------- keyframes
def test_keyframe_is_the_most_recent_frame_far_enough_on_a_hand_made_drive():
    # Driven distances 0.2, 0.45, 0.7, 0.9 m back: the paper's 0.5 m is first reached 3 frames back.
    cands = [_prev(1, 0.2), _prev(2, 0.45), _prev(3, 0.7), _prev(4, 0.9)]
    p = KeyframeParams(min_distance_m=0.5, window=4)
    assert choose_keyframe(cands, p, None, True, 0.05) == (3, pytest.approx(0.7))
    # Without ground truth the stream's speed estimate decides: 2 m/s, 0.1 s a frame -> 3 frames back.
    no_gt = [_prev(b, None) for b in (1, 2, 3, 4)]
    assert choose_keyframe(no_gt, p, 2.0, False, 0.05)[0] == 3
    # Fast driving: the previous frame; min_distance 0: always the previous frame.
    assert choose_keyframe(no_gt, p, 12.0, False, 0.05)[0] == 1
    assert choose_keyframe(cands, KeyframeParams(0.0, 4), None, True, 0.05)[0] == 1
    # Before any speed is known: the previous frame.
    assert choose_keyframe(no_gt, p, None, False, 0.05)[0] == 1


def test_keyframe_when_nothing_is_far_enough():
    p = KeyframeParams(min_distance_m=0.5, window=3)
    slow = [_prev(1, 0.05), _prev(2, 0.1), _prev(3, 0.15)]
    assert choose_keyframe(slow, p, None, True, 0.05)[0] == 3  # creeping: the most baseline there is
    standing = [_prev(1, 0.0), _prev(2, 1e-4), _prev(3, 2e-4)]
    # Standing: no baseline to gain; the movers' flow, chained, is measured over the whole window.
    assert choose_keyframe(standing, p, None, True, 0.05)[0] == 3
    # Without chaining a flow straight across the window loses the movers: the previous frame.
    assert choose_keyframe(standing, KeyframeParams(0.5, 3, chain_flow=False), None, True, 0.05)[0] == 1
    # ... and no longer ago than standing_max_s (frames 0.1 s apart: 0.25 s reaches 2 back; under one frame: 1).
    assert choose_keyframe(standing, KeyframeParams(0.5, 3, standing_max_s=0.25), None, True, 0.05)[0] == 2
    assert choose_keyframe(standing, KeyframeParams(0.5, 3, standing_max_s=0.05), None, True, 0.05)[0] == 1
    with pytest.raises(InputError, match="no earlier frame"):
        choose_keyframe([], p, None, True, 0.05)


@pytest.mark.parametrize("key,value,match", [
    ("keyframes.min_distance_m", -0.5, "min_distance_m"),
    ("keyframes.window", 0, "window"),
    ("keyframes.chain_flow", "maybe", "chain_flow"),
    ("keyframes.standing_max_s", 0, "standing_max_s"),
    ("temporal.accel_std_mps2", 0, "accel_std_mps2"),
    ("temporal.group_depth_ratio", -0.1, "group_depth_ratio"),
    ("temporal.eta_gate", -1, "eta_gate"),
    ("temporal.eta_interval_s", 0, "eta_interval_s"),
    ("ttc.warn_s", -1, "warn_s"),
    # A null is the user's value, not a request for the default: rejected, as every bad value is.
    ("temporal.eta_gate", "null", "eta_gate"),
    ("keyframes.window", "null", "window"),
    ("ttc.corridor_m", "null", "corridor_m"),
    ("+temporal.eta_gates", 3, "unknown setting"),
])
def test_bad_sequence_settings_are_named(key, value, match):
    # A value of the wrong type (or a null) is refused as the config composes, a bad number where it is read.
    with pytest.raises(InputError, match=match):
        SequenceRunner(sequence_settings(load_config(["data=synthetic", f"{key}={value}"])))


# ---------------------------------------------------------------------------------------------- synthetic sequences
def test_synthetic_sequence_ground_truth():
    seq = SyntheticSequence(100_003, 6, scale=0.25, ego_speed=3.0)
    # Frame 1 with frame 0 is the single pair of the same scene (no mover footprints extended: length 1).
    one = SyntheticSequence(100_003, 1, scale=0.25).pair(1, 0)
    ref = render_pair(100_003, scale=0.25)
    assert torch.equal(one.image, ref.image) and torch.equal(one.image_prev, ref.image_prev)
    assert torch.equal(one.gt.flow, ref.gt.flow)

    pair = seq.pair(5, 2)
    gt = pair.gt
    # Ego 3 m/s, 3 frames of 0.1 s: 0.9 m along a slightly curved path (the chord is shorter by < 1e-4).
    assert pair.motion.translation_norm == pytest.approx(0.9, rel=1e-4)
    assert pair.meta["dt"] == pytest.approx(0.3)
    static = (~gt.moving) & (gt.depth > 0)
    assert float(gt.velocity[:, static].abs().max()) == 0.0  # a static point's world velocity is 0
    movers = [o for o in seq.layout.objects if o["moving"]]
    assert movers
    R_wc = torch.from_numpy(seq.pose(5)[1])
    checked = 0
    for o in movers:
        m = gt.instances == o["instance"]
        if int(m.sum()) < 5:
            continue
        want = R_wc.T @ torch.tensor(o["delta"], dtype=torch.float64) / 0.1  # world -> camera 5 axes, m/s
        got = gt.velocity[:, m].double()
        assert torch.allclose(got, want[:, None].expand_as(got), atol=1e-4)
        checked += 1
    assert checked >= 1
    # TTC of static surfaces: depth over the ego speed (3 m/s; the yaw is small).
    ttc = gt.ttc[static & (gt.depth > 5)]
    assert torch.allclose(ttc, gt.depth[static & (gt.depth > 5)] / 3.0, rtol=0.02)
    # Photometric consistency of the keyframe pair along the ground-truth flow.
    H, W = pair.size
    vv, uu = torch.meshgrid(torch.arange(H).float(), torch.arange(W).float(), indexing="ij")
    f = gt.flow
    grid = torch.stack([(uu + f[0]) / (W - 1) * 2 - 1, (vv + f[1]) / (H - 1) * 2 - 1], -1)[None]
    warped = torch.nn.functional.grid_sample(pair.image_prev[None], grid, align_corners=True)[0]
    assert float((warped - pair.image).abs().mean(0)[gt.flow_valid].median()) < 0.01


def test_synthetic_sequence_source_and_bad_config():
    cfg = load_config(["data=synthetic", "data.frames=2", "data.sequence_length=4", "data.ego_speed_mps=0", "data.scale=0.2"])
    src = build_source(cfg)
    assert len(src) == 8
    assert src.sequence_key(3) != src.sequence_key(4)
    prev = src.previous_frames(2, 10)
    assert [p.back for p in prev] == [1, 2, 3] and all(p.motion.translation_norm == 0 for p in prev)
    with pytest.raises(InputError, match="sequence_length"):
        build_source(load_config(["data=synthetic", "data.sequence_length=0"]))
    with pytest.raises(InputError, match="ego_speed_mps"):
        build_source(load_config(["data=synthetic", "data.ego_speed_mps=3"]))  # only for sequences
    with pytest.raises(InputError, match="ego_speed_mps"):
        build_source(load_config(["data=synthetic", "data.sequence_length=3", "data.ego_speed_mps=-1"]))


# ---------------------------------------------------------------------------------------------- tracks and TTC
def _one_stixel_world(distance: float, lateral: float, dynamic: bool, motion: torch.Tensor) -> StixelWorld:
    """A frame with one object stixel whose middle point lies at (lateral, 0, distance) metres (camera)."""
    fx = 500.0
    K = torch.tensor([[fx, 0, 320.0], [0, fx, 120.0], [0, 0, 1.0]], dtype=torch.float64)
    u = 320.0 + fx * lateral / distance
    col = int(u // 5)
    ng = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    uc = torch.tensor([col * 5 + 2.0], dtype=torch.float64)
    n = object_normals(K, ng, uc)[0]
    ray = pixel_rays(K, uc, torch.tensor([120.0], dtype=torch.float64))[0]
    X = ray * distance  # z = distance on the row of the principal point
    p = 1.0 / float(n @ X)
    one = lambda x, dt=torch.long: torch.tensor([x], dtype=dt)  # noqa: E731
    return StixelWorld(column_width=5, image_size=(240, 640), K=K, ground_normal=ng, column=one(col),
                       v_top=one(100), v_bottom=one(140), type=one(2 if dynamic else 1), cls=one(6 if dynamic else 3),
                       inverse_depth=one(p, torch.float64), motion=motion[None].double(), cost=one(0.0, torch.float64),
                       tau=torch.zeros(1, 2, dtype=torch.float64), energy=torch.zeros(128, dtype=torch.float64))


def test_constant_velocity_track_converges_to_the_true_velocity():
    # A car 20 m ahead drives away at 4 m/s (camera standing, 10 Hz); its measured distance is noisy (5 %)
    # and so is its per-pair motion (30 %): the filtered velocity converges to 4 m/s (a filter told that
    # noise, for gentle accelerations, 0.5 m/s^2, averages over about two seconds).
    gen = torch.Generator().manual_seed(0)
    tracks = Tracks(TrackParams(accel_std_mps2=0.5, depth_std_rel=0.05, velocity_std_mps=0.1, velocity_std_rel=0.3))
    pose = torch.eye(4, dtype=torch.float64)
    v_true, dt = 4.0, 0.1
    errs, ids = [], set()
    for k in range(30):
        z = 20.0 + v_true * dt * k
        z_meas = z * (1 + 0.05 * float(torch.randn((), generator=gen)))
        dz = v_true * dt * (1 + 0.3 * float(torch.randn((), generator=gen)))
        w = _one_stixel_world(z_meas, 0.0, True, torch.tensor([0.0, 0.0, dz]))
        out = tracks.update(w, frame=k, time=k * dt, pose=pose, dt_pair=dt, degenerate=True)
        ids.add(int(out["track_id"][0]))
        errs.append(abs(float(out["velocity"][0, 2]) - v_true))
    assert len(ids) == 1  # one track all along
    assert np.mean(errs[-10:]) < 0.25
    assert np.mean(errs[-10:]) < 0.5 * np.mean([0.3 * v_true * math.sqrt(2 / math.pi)])  # beats one pair's error
    # Its filtered distance is steadier than the measurements.
    assert abs(float(out["position"][0, 2]) - (20.0 + v_true * dt * 29)) < 0.5


def test_static_stixel_is_held_by_its_track_without_baseline():
    tracks = Tracks(TrackParams())
    pose = torch.eye(4, dtype=torch.float64)
    w = _one_stixel_world(15.0, 1.0, False, torch.zeros(3))
    tracks.update(w, frame=0, time=0.0, pose=pose, dt_pair=0.1, degenerate=False)
    # The camera stops; the scene model puts the object at 25 m along the same ray: the track keeps its 15 m.
    out = tracks.update(_one_stixel_world(25.0, 25.0 / 15.0, False, torch.zeros(3)), frame=1, time=0.1, pose=pose,
                        dt_pair=0.1, degenerate=True)
    assert bool(out["carried"][0])
    assert float(out["position"][0, 2]) == pytest.approx(15.0, rel=0.02)
    assert float(out["velocity"][0].norm()) < 0.05


def test_a_stixel_whose_rows_changed_continues_its_track_through_the_flow():
    # A wall 15 m ahead, camera still: in frame 1 its stixel covers rows 80-118 instead of 100-140 (its foot
    # hidden). The track's point (row 120) lands outside it; through the (zero) flow half of its pixels land
    # in the wall's stixel of frame 0, so it continues that track. Without the flow it starts a new one, and
    # with overlap_min_share above the landing share too.
    import dataclasses
    pose = torch.eye(4, dtype=torch.float64)
    w0 = _one_stixel_world(15.0, 1.0, False, torch.zeros(3))
    w1 = dataclasses.replace(w0, v_top=torch.tensor([80]), v_bottom=torch.tensor([118]))
    zero = torch.zeros(2, 240, 640)
    ids = {}
    for name, params, flow in (("flow", TrackParams(), zero), ("no flow", TrackParams(), None),
                               ("share above", TrackParams(overlap_min_share=0.6), zero)):
        tracks = Tracks(params)
        first = tracks.update(w0, frame=0, time=0.0, pose=pose, dt_pair=0.1, degenerate=False)["track_id"][0]
        second = tracks.update(w1, frame=1, time=0.1, pose=pose, dt_pair=0.1, degenerate=False,
                               flow_to_last=flow, flow_reaches=0)["track_id"][0]
        ids[name] = (int(first), int(second))
    assert ids["flow"][0] == ids["flow"][1]
    assert ids["no flow"][0] != ids["no flow"][1]
    assert ids["share above"][0] != ids["share above"][1]  # 19 of 39 rows land: 0.49 < 0.6
    # A flow to another frame than the last updated one is not used.
    tracks = Tracks(TrackParams())
    first = int(tracks.update(w0, frame=0, time=0.0, pose=pose, dt_pair=0.1, degenerate=False)["track_id"][0])
    out = tracks.update(w1, frame=1, time=0.1, pose=pose, dt_pair=0.1, degenerate=False, flow_to_last=zero,
                        flow_reaches=-1)
    assert int(out["track_id"][0]) != first
    with pytest.raises(InputError, match="overlap_min_share"):
        TrackParams(overlap_min_share=1.5)


def test_a_movers_track_outlasts_one_wild_velocity_linked_through_the_flow():
    # A car 20 m ahead drives away at 4 m/s (camera still, 10 Hz). In frame 4 its pair's motion comes out
    # at -15 m/s where its position is right: linked through the flow to its 4-frame track it keeps the
    # track and the track's velocity; a second wild pair in a row starts a new track. Without the flow,
    # or with coast_min_age=0, the first wild pair starts a new track.
    pose = torch.eye(4, dtype=torch.float64)
    zero = torch.zeros(2, 240, 640)

    def drive(params: TrackParams, flow: torch.Tensor | None) -> list[tuple[int, float]]:
        tracks, out = Tracks(params), []
        for k in range(6):
            dz = 0.4 if k < 4 else -1.5
            w = _one_stixel_world(20.0 + 0.4 * k, 0.0, True, torch.tensor([0.0, 0.0, dz]))
            r = tracks.update(w, frame=k, time=0.1 * k, pose=pose, dt_pair=0.1, degenerate=True,
                              flow_to_last=flow, flow_reaches=k - 1)
            out.append((int(r["track_id"][0]), float(r["velocity"][0, 2])))
        return out

    coast = drive(TrackParams(), zero)
    assert len({i for i, _ in coast[:5]}) == 1 and coast[5][0] != coast[4][0]
    assert coast[4][1] == pytest.approx(4.0, abs=0.3)  # the track's velocity stands
    for params, flow in ((TrackParams(), None), (TrackParams(coast_min_age=0), zero)):
        plain = drive(params, flow)
        assert len({i for i, _ in plain[:4]}) == 1 and plain[4][0] != plain[3][0]
        assert plain[4][1] == pytest.approx(-15.0, abs=0.5)  # a new track at the wild pair
    with pytest.raises(InputError, match="coast_min_age"):
        TrackParams(coast_min_age=-1)


def test_time_to_collision_of_a_hand_made_closing_object():
    X = torch.tensor([[0.5, 0.0, 20.0], [3.5, 0.0, 20.0], [0.0, 0.0, 20.0], [0.0, 0.0, 10.0]], dtype=torch.float64)
    v = torch.tensor([[0.0, 0.0, -10.0], [0.0, 0.0, -10.0], [0.0, 0.0, 2.0], [-4.0, 0.0, -8.0]], dtype=torch.float64)
    ttc = time_to_collision(X, v)
    assert ttc.tolist()[:2] == pytest.approx([2.0, 2.0]) and math.isinf(ttc[2]) and ttc[3] == pytest.approx(1.25)
    warn = critical(X, v, ttc, TtcParams(warn_s=2.5, corridor_m=1.5))
    # In the path; beside it (3.5 m lateral); not closing; crossing into it (10 m ahead, 4 m/s sideways: x = -5 m).
    assert warn.tolist() == [True, False, False, False]
    # Not in the path now, though its contact would be (2.5 m to the left, drifting in at 1.7 m/s: the traffic
    # drive's pickup, whose wild velocity came from a wrong depth); a closing speed no road has (80 m/s).
    X2 = torch.tensor([[-2.5, 0.0, 5.8], [0.0, 0.0, 60.0]], dtype=torch.float64)
    v2 = torch.tensor([[1.7, 0.0, -4.4], [0.0, 0.0, -80.0]], dtype=torch.float64)
    ttc2 = time_to_collision(X2, v2)
    assert (ttc2 < 2.5).all()
    assert critical(X2, v2, ttc2, TtcParams(warn_s=2.5, corridor_m=1.5)).tolist() == [False, False]
    assert critical(X2, v2, ttc2, TtcParams(warn_s=2.5, corridor_m=3.0, max_closing_mps=100.0)).tolist() == [True, True]


def test_a_warning_needs_an_object_wider_than_one_column():
    from monostixels.core.stixels import StixelWorld
    from monostixels.sequence.ttc import object_wide

    # Columns 3-4 one object (overlapping rows), column 8 a lone sliver, column 10 beside column 9 but not
    # sharing a row with it; column 9 is not warned.
    cols, top, bot = [3, 4, 8, 9, 10], [10, 14, 30, 0, 20], [20, 25, 34, 5, 25]
    n = len(cols)
    world = StixelWorld(column_width=5, image_size=(40, 60), K=torch.eye(3, dtype=torch.float64),
                        ground_normal=torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), column=torch.tensor(cols),
                        v_top=torch.tensor(top), v_bottom=torch.tensor(bot), type=torch.full((n,), 2),
                        cls=torch.full((n,), 6), inverse_depth=torch.full((n,), 0.1, dtype=torch.float64),
                        motion=torch.zeros(n, 3, dtype=torch.float64), cost=torch.zeros(n),
                        tau=torch.zeros(n, 2, dtype=torch.float64), energy=torch.zeros(12))
    warn = torch.tensor([True, True, True, False, True])
    assert object_wide(warn, world).tolist() == [True, True, False, False, False]
    assert not object_wide(torch.zeros(n, dtype=torch.bool), world).any()


def test_a_warning_waits_for_its_track_to_be_confirmed():
    """A car closing in the path is warned about once its track has continued ttc.confirm_frames frames; a
    stixel critical in one frame only (a new track each time) never is."""
    from monostixels.sequence.ttc import confirmed

    params = TtcParams(confirm_frames=2)
    tracks, warned = Tracks(TrackParams()), []
    for f in range(5):  # 15 m ahead, closing at 10 m/s: TTC 1.5 s and less, in the path
        w = _object_world([15.0 - 1.0 * f], [-1.0])
        out = tracks.update(w, frame=f, time=0.1 * f, pose=torch.eye(4, dtype=torch.float64), dt_pair=0.1,
                            degenerate=True)
        X = torch.tensor([[0.0, 0.0, 15.0 - f]], dtype=torch.float64)
        crit = critical(X, torch.tensor([[0.0, 0.0, -10.0]], dtype=torch.float64), out["ttc"], params)
        assert bool(crit[0])  # critical in every frame ...
        warned.append(bool(confirmed(crit, out["age"], params)[0]))
    assert warned == [False, False, True, True, True]  # ... warned from the third frame on
    assert out["age"].tolist() == [4]
    one = torch.tensor([True])
    assert not bool(confirmed(one, torch.tensor([0]), params)[0])  # seen once
    assert bool(confirmed(one, None, params)[0]) and bool(confirmed(one, torch.tensor([0]), TtcParams(confirm_frames=0))[0])
    with pytest.raises(InputError, match="ttc.confirm_frames"):
        TtcParams(confirm_frames=-1)


def _object_world(distances: list[float], motions: list[float]) -> StixelWorld:
    """One dynamic object: stixels in adjacent columns about the principal point, rows 100-140, each at its
    distance (m) with its motion along the optical axis over the pair (m)."""
    fx = 500.0
    K = torch.tensor([[fx, 0, 320.0], [0, fx, 120.0], [0, 0, 1.0]], dtype=torch.float64)
    ng = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    cols = torch.arange(len(distances)) + 64
    uc = (cols * 5 + 2.0).double()
    n = object_normals(K, ng, uc)
    ray = pixel_rays(K, uc, torch.full((len(distances),), 120.0, dtype=torch.float64))
    X = ray * torch.tensor(distances, dtype=torch.float64)[:, None] / ray[:, 2:]
    p = 1.0 / (n * X).sum(1)
    k = len(distances)
    full = lambda x, dt=torch.long: torch.full((k,), x, dtype=dt)  # noqa: E731
    motion = torch.zeros(k, 3, dtype=torch.float64)
    motion[:, 2] = torch.tensor(motions, dtype=torch.float64)
    return StixelWorld(column_width=5, image_size=(240, 640), K=K, ground_normal=ng, column=cols,
                       v_top=full(100), v_bottom=full(140), type=full(2), cls=full(6), inverse_depth=p, motion=motion,
                       cost=full(0.0, torch.float64), tau=torch.zeros(k, 2, dtype=torch.float64),
                       energy=torch.zeros(128, dtype=torch.float64))


def test_ttc_is_free_of_each_stixels_scale_error():
    # A car 20 m ahead closes at 10 m/s (TTC 2 s; camera standing, 10 Hz). Its stixels' depths and motions
    # carry one monocular scale each (1.0, 1.1, 0.95): one stixel's motion over its own depth is the true
    # closing rate, while the object's median velocity over another stixel's depth would not be.
    scales = [1.0, 1.1, 0.95]
    w = _object_world([20.0 * s for s in scales], [-1.0 * s for s in scales])
    out = Tracks(TrackParams()).update(w, frame=0, time=0.0, pose=torch.eye(4, dtype=torch.float64), dt_pair=0.1,
                                       degenerate=True)
    assert len(set(out["track_id"].tolist())) == 3
    assert out["ttc"].tolist() == pytest.approx([2.0, 2.0, 2.0], rel=1e-6)
    # The velocity stays the object's median (one mover, one velocity): -10 m/s for all three.
    assert out["velocity"][:, 2].tolist() == pytest.approx([-10.0, -10.0, -10.0], rel=1e-6)


def _closing_ttc(params: TrackParams, factors: dict[int, float], dt_pair: float = 0.1) -> list[tuple[int, float, float]]:
    """(track id, TTC, true TTC) per frame of a car closing at 10 m/s from 20 m (camera standing, 10 Hz);
    at the frames in ``factors`` the pair's measured motion is that fraction of the true one."""
    tracks, out = Tracks(params), []
    for f in range(8):
        distance = 20.0 - 1.0 * f
        w = _object_world([distance], [-10.0 * dt_pair * factors.get(f, 1.0)])
        o = tracks.update(w, frame=f, time=0.1 * f, pose=torch.eye(4, dtype=torch.float64), dt_pair=dt_pair,
                          degenerate=True)
        out.append((int(o["track_id"][0]), float(o["ttc"][0]), distance / 10.0))
    return out


def test_ttc_gate_coasts_through_one_lost_pair_and_restarts_after_two():
    # Frame 5's pair measures 65 % of the closing speed (a lost flow): within the association gate, far
    # outside the closing rate's.
    gated = _closing_ttc(TrackParams(), {5: 0.65})
    assert len({t for t, _, _ in gated}) == 1  # one track throughout
    assert all(ttc == pytest.approx(true, rel=1e-6) for _, ttc, true in gated)  # the prediction stood
    ungated = _closing_ttc(TrackParams(eta_gate=0.0), {5: 0.65})
    assert ungated[5][1] > 1.005 * ungated[5][2]  # the Kalman update alone is pulled off
    # Two in a row: the track's rate is taken to be what is wrong and restarts at the measurement.
    twice = _closing_ttc(TrackParams(), {5: 0.65, 6: 0.65})
    assert twice[5][1] == pytest.approx(1.5, rel=1e-6)
    assert twice[6][1] == pytest.approx(1.4 / 0.65, rel=1e-6)


def test_a_longer_pair_weighs_more_in_the_closing_rate():
    # The same relative error in one pair's rate (80 % at frame 5): spread over a pair 0.4 s long it is a
    # smaller error in the rate than over 0.1 s (eta_interval_s / dt), and the filter follows it further.
    short = _closing_ttc(TrackParams(eta_gate=0.0), {5: 0.8}, dt_pair=0.1)
    long = _closing_ttc(TrackParams(eta_gate=0.0), {5: 0.8}, dt_pair=0.4)
    assert short[4][1] == pytest.approx(1.6, rel=1e-6) and long[4][1] == pytest.approx(1.6, rel=1e-6)
    assert 1.5 < short[5][1] < long[5][1] < 1.5 / 0.8


def test_sequence_eval_and_run_outputs(tmp_path):
    """End to end on a short synthetic clip with oracle inputs: keyframes, tracks, the temporal report, JSON."""
    from monostixels.eval.evaluate import evaluate

    ov = ["data=synthetic", "data.frames=1", "data.sequence_length=5", "data.ego_speed_mps=3", "data.scale=0.25",
          "flow=gt", "semantic=gt", "motion=gt"]
    cfg = load_config(ov)
    runner = SequenceRunner(sequence_settings(cfg))
    steps = list(runner.run(build_source(cfg)))
    # 0.3 m a frame: from the third frame on the pair reaches two frames back (0.6 m >= 0.5 m).
    assert [s.result.stixels.pair_info["frames_back"] for s in steps] == [1, 2, 2, 2, 2]
    st = steps[-1].result.stixels
    # The sequence layer's own result: the pair's stixels, untouched, and the tracks' fields beside them.
    frame = steps[-1].tracked
    assert frame.stixels.track_id is None and frame.stixels.pose is None
    assert torch.equal(frame.track_id, st.track_id) and frame.pose is steps[-1].result.pose
    assert frame.world().to_dict() == st.to_dict() and frame.pair_info == st.pair_info
    tracked = st.type != 3  # ground and objects; the sky is not tracked
    assert bool((st.track_id[tracked] >= 0).all()) and bool((st.track_id[~tracked] == -1).all())
    assert len(set(st.track_id[tracked].tolist())) == int(tracked.sum())  # one stixel per track
    d = st.to_dict()
    assert d["pair"]["frames_back"] == 2 and len(d["pose"]) == 4
    s0 = d["stixels"][0]
    assert {"track_id", "velocity", "ttc_s", "ttc_warning"} <= set(s0)
    back = StixelWorld.from_dict(json.loads(json.dumps(d)))
    assert torch.equal(back.track_id, st.track_id) and torch.allclose(back.velocity, st.velocity)
    assert torch.equal(torch.isinf(back.ttc_s), torch.isinf(st.ttc_s))
    st.save_npz(tmp_path / "s.npz")
    z = StixelWorld.load_npz(tmp_path / "s.npz")
    assert torch.equal(z.track_id, st.track_id) and z.pair_info == st.pair_info
    rep = evaluate(cfg, build_source(cfg), dataset="synthetic", progress=False)
    tmp = rep["temporal"]
    assert tmp["velocity_err_mps"] < 0.5 and tmp["static_speed_mps"] < 0.3
    assert tmp["ttc_rel_err"] < 0.1 and tmp["depth_jitter"] < 0.05
    off = evaluate(load_config(ov + ["temporal.enabled=false"]), build_source(cfg), dataset="synthetic", progress=False)
    assert off["temporal"]["tracking"] is False and rep["temporal"]["tracking"] is True
    # Independent pairs have no temporal section.
    single = evaluate(load_config(["data=synthetic", "data.scale=0.25", "flow=gt", "semantic=gt", "motion=gt"]),
                      build_source(load_config(["data=synthetic", "data.scale=0.25"])), dataset="synthetic", progress=False)
    assert "temporal" not in single


def test_a_failed_pair_is_not_a_later_pairs_partner():
    """A frame whose camera motion failed has no pose: a later keyframe pair reaches past it to a solved
    frame, and its pose chains through that frame (ground-truth motion: exactly)."""
    from monostixels.pipeline import MotionEstimationError

    ov = ["data=synthetic", "data.frames=1", "data.sequence_length=6", "data.ego_speed_mps=3", "data.scale=0.25",
          "flow=gt", "semantic=gt", "motion=gt"]
    cfg = load_config(ov)
    runner = SequenceRunner(sequence_settings(cfg))
    motion_for = runner.pipeline.motion_for

    def failing(pair, *args, **kwargs):
        if pair.name.endswith("_002"):
            raise MotionEstimationError(f"{pair.name}: camera motion could not be estimated (test)")
        return motion_for(pair, *args, **kwargs)

    runner.pipeline.motion_for = failing
    steps = list(runner.run(build_source(cfg)))
    assert steps[1].result is None and "test" in steps[1].error  # frame 2
    # 0.3 m a frame, keyframes at 0.5 m: frame 4 would pair with frame 2 (2 back); it reaches frame 1 instead.
    info = steps[3].result.stixels.pair_info
    assert info["frames_back"] == 3 and info["previous"].endswith("_001")
    pose = steps[3].result.pose
    assert float(pose[:3, 3].norm()) == pytest.approx(4 * 0.3, abs=1e-3)  # frame 4 is 1.2 m from frame 0
    assert steps[3].result.stixels.track_id.max() >= 0
    # Where every earlier frame of the window failed, the sequence starts again with the frame before.
    runner = SequenceRunner(sequence_settings(load_config(ov + ["keyframes.window=1"])))
    motion_for = runner.pipeline.motion_for
    runner.pipeline.motion_for = failing
    steps = list(runner.run(build_source(cfg)))
    assert steps[2].result.stixels.pair_info["frames_back"] == 1
    # ... its world is the frame before (frame 2), 0.3 m back, not frame 0.
    assert float(steps[2].result.pose[:3, 3].norm()) == pytest.approx(0.3, abs=1e-3)


def test_run_on_a_video_writes_tracks_velocities_and_ttc(tmp_path):
    """`monostixels run data=video` on a clip written from a rendered sequence: per-stixel track ids,
    velocities and TTC in stixels.json, the earlier frame of each pair, tracks that persist."""
    import subprocess
    import sys

    import cv2

    seq = SyntheticSequence(5, 5, scale=0.25, ego_speed=8.0)
    H, W = seq.size
    vw = cv2.VideoWriter(str(tmp_path / "clip.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (W, H))
    for j in range(6):
        im = seq.pair(j, j - 1).image if j else seq.pair(1, 0).image_prev
        vw.write(cv2.cvtColor((im.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR))
    vw.release()
    hfov = float(np.degrees(2 * np.arctan(W / 2 / float(seq.camera.K[0, 0]))))
    p = subprocess.run([sys.executable, "-m", "monostixels.cli", "run", "data=video", f"data.path={tmp_path / 'clip.mp4'}",
                        f"data.hfov_deg={hfov}", "flow=dis", "semantic=none"], cwd=tmp_path, capture_output=True,
                       text=True, timeout=900)
    assert p.returncode == 0, p.stderr
    dirs = sorted(d for d in (tmp_path / "outputs" / "run").iterdir() if d.is_dir())
    assert len(dirs) == 5
    ids = []
    for d in dirs:
        js = json.loads((d / "stixels.json").read_text())
        assert js["pair"]["previous"].startswith("clip_") and js["pair"]["frames_back"] >= 1
        obj = [s for s in js["stixels"] if s["type"] in ("static_object", "dynamic_object")]
        assert obj and all(s["track_id"] >= 0 for s in obj)
        assert all(len(s["velocity"]) == 3 and (s["ttc_s"] is None or s["ttc_s"] > 0) for s in js["stixels"])
        ids.append({s["track_id"] for s in obj})
    # Tracks continue from frame to frame (on this tiny, fast-flow clip about 40 % of a frame's stixels
    # continue a track of the frame before; nothing would without the association).
    assert np.mean([len(a & b) / len(b) for a, b in zip(ids, ids[1:])]) > 0.3


def test_a_pair_whose_camera_motion_is_unknown_shows_no_movers_and_no_warning(monkeypatch):
    """A pair whose metric motion is unknown (no scale, or no estimate at all) calls nothing moving, raises no
    collision warning, has no pose and is no later pair's partner; the frames around it are solved as before."""
    import monostixels.pipeline as pipeline_module
    from monostixels.core.classes import DYNAMIC_OBJECT
    from monostixels.inputs.motion import MotionEstimate
    from monostixels.output.viz import frame_notes

    ov = ["data=synthetic", "data.frames=1", "data.sequence_length=6", "data.ego_speed_mps=3", "data.scale=0.25",
          "flow=gt", "semantic=gt", "motion=gt"]
    cfg = load_config(ov)
    real = pipeline_module.estimate_motion

    def estimate(pair, flow, mcfg, semantic=None, **kw):
        est = real(pair, flow, mcfg, semantic, **kw)
        if pair.name.endswith("_002"):  # the direction known, not the length
            unit = Motion(est.motion.R, est.motion.t / est.motion.t.norm())
            return MotionEstimate(None, False, "no metric scale: test", 0.5, kind="scale_unknown", unit_motion=unit)
        if pair.name.endswith("_003"):
            return MotionEstimate(None, False, "too few usable flow vectors: test", 0.0, kind="unknown")
        return est

    monkeypatch.setattr(pipeline_module, "estimate_motion", estimate)
    runner = SequenceRunner(sequence_settings(cfg), Pipeline(pipeline_settings(cfg), allow_motion_failure=True))
    steps = list(runner.run(build_source(cfg)))
    worlds = [s.result.stixels for s in steps]
    assert any(bool((w.type == DYNAMIC_OBJECT).any()) for w in (worlds[0], worlds[4]))  # the scene has movers
    for w, kind, what in ((worlds[1], "scale_unknown", "speed"), (worlds[2], "unknown", "motion")):
        assert w.flags["camera_motion"] == kind and w.flags["degenerate_motion"]
        assert not bool((w.type == DYNAMIC_OBJECT).any()) and float(w.motion.abs().max()) == 0.0
        assert not bool(w.ttc_warning.any()) and bool(torch.isinf(w.ttc_s).all())
        assert bool((w.track_id == -1).all()) and w.pose is None and "pose" not in w.to_dict()
        assert frame_notes(w)[0].startswith(f"camera {what} unknown: no movers, no collision warnings")
    assert steps[1].tracked.pose is None and steps[1].tracked.stixels.status.motion.kind == "scale_unknown"
    # Frame 4 pairs past frames 2 and 3 with frame 1; its pose chains the known motions (0.3 m a frame).
    info = worlds[3].pair_info
    assert info["previous"].endswith("_001") and info["frames_back"] == 3
    assert float(steps[3].result.pose[:3, 3].norm()) == pytest.approx(4 * 0.3, abs=1e-3)
    assert worlds[3].flags["camera_motion"] == "metric" and worlds[3].flags["scale_from"] == "given"


def test_the_sequence_layer_owns_the_speed_prior():
    # The pipeline keeps nothing between pairs; the runner's MotionTrack is the one the pairs update.
    from monostixels.inputs.motion_track import MotionTrack

    ov = ["data=synthetic", "data.frames=1", "data.sequence_length=4", "data.ego_speed_mps=3", "data.scale=0.25",
          "flow=gt", "semantic=gt", "motion=mono"]
    cfg = load_config(ov)
    runner = SequenceRunner(sequence_settings(cfg))
    assert isinstance(runner.motion_track, MotionTrack) and not hasattr(runner.pipeline, "motion_track")
    seen = []
    update = runner.motion_track.update

    def spy(pair, est):
        seen.append(pair.name)
        return update(pair, est)

    runner.motion_track.update = spy
    steps = list(runner.run(build_source(cfg)))
    assert seen == [s.pair.name for s in steps] and len(seen) == 4
    assert SequenceRunner(sequence_settings(load_config(ov[:-1] + ["motion=gt"]))).motion_track is None
    assert SequenceRunner(sequence_settings(load_config(ov + ["motion.sequence_prior=false"]))).motion_track is None


def test_start_up_objects_leave_the_garbage_collector_once_after_the_first_pair(monkeypatch):
    """After the first solved pair every object then alive (libraries, configs, models) is frozen out of
    the collector's generations, once per process: later pairs freeze nothing more."""
    import gc

    from monostixels.sequence import runner as runner_mod

    monkeypatch.setattr(runner_mod, "_frozen", False)
    gc.unfreeze()
    try:
        cfg = load_config(["data=synthetic", "data.frames=1", "data.sequence_length=4", "data.scale=0.25",
                           "flow=gt", "semantic=gt", "motion=gt"])
        counts = [gc.get_freeze_count() for _ in SequenceRunner(sequence_settings(cfg)).run(build_source(cfg))]
        assert len(counts) >= 3 and counts[0] > 1000
        assert all(c <= counts[0] for c in counts[1:])  # frozen objects may still be freed; none are added
    finally:
        gc.unfreeze()
