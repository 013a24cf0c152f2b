"""Presets, the stream state (work carried from frame to frame) and frames read as they come.

The warm-started stages are held to their cold start on synthetic sequences, with stated tolerances;
the overlap of consecutive pairs and the reuse of grey images must not change a single number.
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from monostixels import cli
from monostixels._checks import InputError
from monostixels.build import build_source
from monostixels.data.synthetic import SyntheticSequenceSource, render_pair
from monostixels.data.live_video import LiveVideoSource
from monostixels.data.video import VideoSource
from monostixels.inputs.flow import estimate_flow, flow_metrics
from monostixels.inputs.flow_backends import gray_u8, refine_flow
from monostixels.inputs.flow_chain import compose_flows
from monostixels.eval.metrics import motion_errors
from monostixels.pipeline import Pipeline, load_config
from monostixels.build import pipeline_settings, sequence_settings
from monostixels.sequence import SequenceRunner
from monostixels.sequence.stream import StreamParams, StreamState, warp_scores
from monostixels.core.stixels import StixelWorld

from tests.test_cli import _cli


# ---------------------------------------------------------------------------------------------- presets
def _choices(overrides: list[str]) -> dict[str, object]:
    c = load_config(overrides)
    return {"flow": (c.flow.name, c.flow.get("preset"), c.flow.get("refine"), c.flow.get("fb_consistency")),
            "semantic": (c.semantic.name, c.semantic.get("model")), "motion": c.motion.name,
            "solver": (c.solver.cell_rows, c.solver.column_width), "stream": dict(c.stream)}


def test_presets_compose_to_the_documented_groups():
    fast = _choices(["preset=fast"])
    # conf/preset/fast.yaml: flow=dis_refine (DIS medium + full-size refinement), the real-image net
    # in INT8, monocular ego-motion, the default solver, the warm stream.
    assert fast["flow"] == ("dis", "medium", True, False)
    assert fast["semantic"] == ("fcn8s", "models/fcn8s_real_int8.onnx") and fast["motion"] == "mono"
    assert fast["solver"] == (3, 5)
    assert fast["stream"] == {"flow_init": True, "semantic_every": 2, "motion_warm_start": True, "overlap": True}
    acc = _choices(["preset=accurate"])
    # DeepFlow (DIS-guided), refined at full size in 4 passes, checked forward-backward.
    assert acc["flow"] == ("deepflow", None, True, True) and load_config(["preset=accurate"]).flow.refine_passes == 4
    assert acc["semantic"] == ("fcn8s", "models/fcn8s_real.onnx") and acc["motion"] == "mono" and acc["solver"] == (3, 5)
    assert acc["stream"] == {"flow_init": False, "semantic_every": 1, "motion_warm_start": False, "overlap": True}
    # Without a preset: the oracle inputs of conf/config.yaml, nothing carried that changes a result.
    none = _choices([])
    assert none["flow"][0] == "gt" and none["semantic"][0] == "gt" and none["motion"] == "gt"
    assert not none["stream"]["flow_init"] and none["stream"]["semantic_every"] == 1


def test_an_explicit_group_beats_the_preset():
    assert _choices(["preset=fast", "flow=deepflow"])["flow"][0] == "deepflow"
    assert _choices(["flow=gt", "preset=fast"])["flow"][0] == "gt"  # order on the command line does not matter
    c = _choices(cli.command_overrides("run", ["semantic=none", "stream=cold"]))
    assert c["semantic"][0] == "none" and c["flow"][0] == "dis" and not c["stream"]["flow_init"]
    # A key of a group the preset chose stays overridable.
    assert load_config(["preset=fast", "flow.sigma_min=0.5"]).flow.sigma_min == 0.5


def test_commands_take_their_defaults_from_the_presets():
    assert cli.command_overrides("run", []) == ["preset=fast"]
    assert cli.command_overrides("batch", []) == ["preset=fast", "data=video"]
    assert cli.command_overrides("demo", []) == ["preset=accurate", "semantic=fcn8s_synthetic"]
    assert cli.command_overrides("run", ["preset=accurate"]) == ["preset=accurate"]
    assert cli.command_overrides("eval", ["data=synthetic"]) == ["data=synthetic"]  # eval: no preset
    assert cli.preset_choice("fast", "flow") == "dis_refine" and cli.preset_choice("accurate", "flow") == "deepflow"
    # `eval preset=fast` composes exactly what `run` composes (but the command).
    run = load_config(cli.command_overrides("run", ["data=kitti_raw"]) + ["command=run"])
    ev = load_config(cli.command_overrides("eval", ["preset=fast", "data=kitti_raw"]) + ["command=run"])
    assert run == ev


def test_a_missing_preset_model_falls_back_as_before(monkeypatch):
    monkeypatch.setattr(cli, "_model_available", lambda path: False)
    assert cli.command_overrides("run", []) == ["preset=fast", "semantic=none"]
    assert cli.command_overrides("demo", []) == ["preset=accurate", "semantic=gt"]
    assert cli.command_overrides("eval", ["preset=fast"]) == ["semantic=none", "preset=fast"]
    assert cli.command_overrides("run", ["semantic=fcn8s"]) == ["preset=fast", "semantic=fcn8s"]  # asked for: no fallback


@pytest.mark.parametrize("key,value,match", [
    ("stream.semantic_every", 0, "semantic_every"),
    ("stream.flow_init", "'maybe'", "stream.flow_init: expected true or false, got 'maybe'"),
    ("stream.semantic_every", "two", "stream.semantic_every: expected an integer, got 'two'"),
    ("+stream.warm", "true", "stream.warm: unknown setting"),
])
def test_bad_stream_settings_are_named(key, value, match):
    with pytest.raises(InputError, match=match):
        sequence_settings(load_config([f"{key}={value}"]))


def test_realtime_on_a_source_read_from_disk_is_refused():
    cfg = load_config(["data=synthetic", "+data.realtime=true"])
    with pytest.raises(InputError, match="data.realtime: only data=video"):
        build_source(cfg)


# ---------------------------------------------------------------------------------------------- warm starts
@pytest.fixture(scope="module")
def sequence() -> SyntheticSequenceSource:
    """One clip of 5 frames (4 pairs) at half KITTI size, constant ego speed."""
    return SyntheticSequenceSource(1, 4, seed=21, scale=0.5, ego_speed=10.0)


def test_warm_flow_is_as_good_as_the_cold_flow_on_a_synthetic_sequence(sequence):
    """Flow started from the last pair's flow (stream.flow_init) against ground truth: within 0.15 px
    EPE of the cold start on every pair (on our renders it is usually better)."""
    cfg = load_config(["preset=fast"]).flow
    state = StreamState(StreamParams(flow_init=True))
    warm_epe, cold_epe = [], []
    for i in range(len(sequence)):
        pair = sequence[i]
        c = state.carried(pair)
        if i > 0:
            assert c.flow_init is not None and c.grey_prev is not None
        warm = estimate_flow(pair, cfg, init=c.flow_init, grey_prev=c.grey_prev)
        cold = estimate_flow(pair, cfg)
        state.update(pair, grey=warm.grey, flow=warm.flow, semantic=None, semantic_fresh=True, motion=None, carried=c)
        warm_epe.append(flow_metrics(warm.flow, pair.gt.flow, pair.gt.flow_valid)["epe"])
        cold_epe.append(flow_metrics(cold.flow, pair.gt.flow, pair.gt.flow_valid)["epe"])
        # The kept grey image is the one of the same frame: the covariance and the cold flow's inputs.
        assert np.array_equal(warm.grey, cold.grey)
    assert warm_epe[0] == cold_epe[0]  # nothing carried into the first pair
    assert all(w <= c + 0.15 for w, c in zip(warm_epe, cold_epe)), (warm_epe, cold_epe)


def test_warm_motion_agrees_with_the_cold_motion_on_a_synthetic_sequence(sequence):
    """Ego-motion started from the last pair's (stream.motion_warm_start): RANSAC skipped, the
    photometric search's grid read around the prediction. Against the cold start on the same flow, per
    pair: rotation within 0.02 deg, translation direction within 0.5 deg, length within 3 % (the
    photometric minimum of these half-size renders is flat to ~2 %: the cold search itself moves by
    that from pair to pair); against ground truth the warm length is on average as good (+0.5 %)."""
    cfg = load_config(["preset=fast", "semantic=gt", "stream.flow_init=false", "motion.sequence_prior=false"])
    pipe = Pipeline(pipeline_settings(cfg), sfm=False)
    warm_state = StreamState(StreamParams(motion_warm_start=True))
    warm_used, err_warm, err_cold = 0, [], []
    for i in range(len(sequence)):
        pair = sequence[i]
        c = warm_state.carried(pair)
        flow, semantic, _ = pipe.inputs(pair, c)
        warm = pipe.motion_for(pair, flow, semantic, c.motion, c.interval_ratio)
        cold = pipe.motion_for(pair, flow, semantic)
        warm_state.update(pair, grey=flow.grey, flow=flow.flow, semantic=semantic, semantic_fresh=True, motion=warm,
                          carried=c)
        warm_used += "warm start" in warm.reason
        d = motion_errors(warm.motion, cold.motion)
        assert d["rot_err_deg"] < 0.02 and d["trans_dir_err_deg"] < 0.5 and d["scale_rel_err"] < 0.03, (i, d, warm.reason)
        err_warm.append(motion_errors(warm.motion, pair.motion)["scale_rel_err"])
        err_cold.append(motion_errors(cold.motion, pair.motion)["scale_rel_err"])
        if i == 0:
            assert warm.motion.t.tolist() == cold.motion.t.tolist()  # nothing to start from: the cold estimate
    assert warm_used == len(sequence) - 1  # every pair after the first started from its prediction
    assert np.mean(err_warm) <= np.mean(err_cold) + 0.005, (err_warm, err_cold)


def test_carried_scores_follow_the_flow():
    """Ground-truth labels of the previous frame carried by the true flow land on the current frame's labels."""
    seq = SyntheticSequenceSource(1, 2, seed=4, scale=0.5)
    first, second = seq[0], seq[1]
    prev_labels = first.gt.labels  # the labels of the frame that is `second`'s previous image
    scores = torch.nn.functional.one_hot(prev_labels.clamp(max=9), 10).permute(2, 0, 1).float()
    carried = warp_scores(scores, second.gt.flow)
    assert torch.allclose(carried.sum(0), torch.ones(second.size), atol=1e-5)
    ok = second.gt.flow_valid & (second.gt.labels < 10)
    agree = (carried.argmax(0) == second.gt.labels)[ok].double().mean()
    assert agree > 0.95
    # The same scores without the flow agree less: the warp does something.
    assert (prev_labels == second.gt.labels)[ok].double().mean() < agree - 0.05


def _stixels_of(cfg_overrides: list[str], source) -> list[StixelWorld]:
    cfg = load_config(cfg_overrides)
    runner = SequenceRunner(sequence_settings(cfg), Pipeline(pipeline_settings(cfg), sfm=False))
    out = [s.result.stixels for s in runner.run(source)]
    return out, runner


def _same(a: StixelWorld, b: StixelWorld) -> bool:
    return all(torch.equal(getattr(a, k), getattr(b, k)) for k in ("column", "v_top", "v_bottom", "type", "cls",
                                                                     "inverse_depth", "motion", "velocity"))


def test_overlapped_pairs_and_reused_grey_images_change_nothing(sequence):
    """stream.overlap (the next pair's inputs computed while this one is solved) and the grey image kept
    for the next pair give exactly the stixels of a stream computed one pair at a time from scratch."""
    base = ["flow=dis_refine", "semantic=gt", "motion=mono"]
    ref, r0 = _stixels_of(base + ["stream=cold", "stream.overlap=false"], sequence)
    ahead, r1 = _stixels_of(base + ["stream=cold", "stream.overlap=true"], sequence)
    assert r1.stream.ahead == len(sequence) - 1 and r0.stream.ahead == 0
    assert all(_same(a, b) for a, b in zip(ref, ahead))
    # Each pair as on its own (no state at all): the flow is the same as with the kept grey images.
    cfg = load_config(base)
    pipe = Pipeline(pipeline_settings(cfg), sfm=False)
    for i in (1, 3):
        assert torch.equal(pipe.run(sequence[i]).flow.flow, SequenceRunner(sequence_settings(cfg), pipe).pipeline.inputs(
            sequence[i], StreamState().carried(sequence[i]))[0].flow)
    # With the warm stream too, overlap changes nothing.
    warm, _ = _stixels_of(base + ["stream=warm", "stream.overlap=false"], sequence)
    warm_ahead, _ = _stixels_of(base + ["stream=warm", "stream.overlap=true"], sequence)
    assert all(_same(a, b) for a, b in zip(warm, warm_ahead))


def test_the_next_pairs_inputs_start_before_the_motion_and_its_motion_start_is_kept(sequence):
    """With stream.overlap the next pair's inputs start once this pair's inputs are known, before its
    camera motion: the motion, kept after it is estimated (StreamState.keep_motion), still starts the
    next pair's estimate (the essential matrix's warm start), and every pair after the first takes
    inputs computed ahead."""
    cfg = load_config(["flow=dis_refine", "semantic=gt", "motion=mono", "stream=warm", "stream.overlap=true"])
    runner = SequenceRunner(sequence_settings(cfg), Pipeline(pipeline_settings(cfg), sfm=False))
    reasons = [s.result.motion.reason for s in runner.run(sequence)]
    assert runner.stream.ahead == len(sequence) - 1
    assert "warm start" not in reasons[0] and all("warm start" in r for r in reasons[1:]), reasons


def test_composed_flows_follow_a_point_through_both_flows():
    """compose_flows(a, b) at x is a(x) + b(x + a(x)): exact for a linear b (bilinear sampling), away from the border."""
    H, W = 40, 60
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    a = np.stack([np.full((H, W), 2.5, np.float32), np.full((H, W), -1.25, np.float32)], -1)
    b = np.stack([0.05 * xx - 0.02 * yy + 1.0, 0.03 * yy + 0.5], -1).astype(np.float32)
    c = compose_flows(a, b)
    xa, ya = xx + 2.5, yy - 1.25
    expect = np.stack([2.5 + 0.05 * xa - 0.02 * ya + 1.0, -1.25 + 0.03 * ya + 0.5], -1)
    inner = (slice(4, H - 4), slice(4, W - 4))
    assert np.abs(c[inner] - expect[inner]).max() < 1e-4


@pytest.fixture(scope="module")
def slow_sequence() -> SyntheticSequenceSource:
    """One clip of 5 frames at half KITTI size, 3 m/s (0.3 m a frame): the 0.5 m keyframes reach two frames back."""
    return SyntheticSequenceSource(1, 4, seed=21, scale=0.5, ego_speed=3.0)


def test_keyframe_flow_is_chained_through_the_frames_between(slow_sequence):
    """keyframes.chain_flow: a pair two frames apart takes the flow of its frames to the frame between,
    composed and refined on the pair. Checked against the same chain built by hand from each pair's own
    flows, and against ground truth: closer to it than the flow computed across the pair directly."""
    base = ["flow=deepflow", "semantic=gt", "motion=gt", "stream.overlap=false"]
    cfg = load_config(base)
    runner = SequenceRunner(sequence_settings(cfg), Pipeline(pipeline_settings(cfg), sfm=False))
    steps = list(runner.run(slow_sequence))
    backs = [s.result.stixels.pair_info["frames_back"] for s in steps]
    chained = [s.result.flow.chained for s in steps]
    assert backs[1:] == [2, 2, 2] and chained == [1, 2, 2, 2]
    # By hand: frame 3 paired with frame 1 through frame 2 (flows of the consecutive pairs on their own).
    fc = cfg.flow
    p32, p21, p31 = slow_sequence.pair_back(2, 1), slow_sequence.pair_back(1, 1), steps[2].pair
    assert (p32.meta["frame"], p32.meta["frame_prev"], p21.meta["frame_prev"], p31.meta["frame_prev"]) == (3, 2, 1, 1)
    a, b = estimate_flow(p32, fc), estimate_flow(p21, fc)
    hwc = lambda x: np.ascontiguousarray(x.permute(1, 2, 0).numpy())  # noqa: E731
    fwd = compose_flows(hwc(a.flow), hwc(b.flow))
    want = refine_flow((gray_u8(p31.image), gray_u8(p31.image_prev)),
                       torch.from_numpy(np.ascontiguousarray(fwd.transpose(2, 0, 1))), fc.refine_passes)
    assert torch.allclose(steps[2].result.flow.flow, want, atol=1e-4)
    # Against ground truth, the same pairs with the flow across them.
    off = load_config(base + ["keyframes.chain_flow=false"])
    direct = list(SequenceRunner(sequence_settings(off), Pipeline(pipeline_settings(off), sfm=False)).run(slow_sequence))
    assert [s.result.flow.chained for s in direct] == [1, 1, 1, 1]
    epe = lambda st: np.mean([flow_metrics(s.result.flow.flow, s.pair.gt.flow, s.pair.gt.flow_valid)["epe"]  # noqa: E731
                              for s in st[1:]])
    assert epe(steps) < epe(direct), (epe(steps), epe(direct))


def test_chained_keyframe_flow_is_the_same_with_overlap(slow_sequence):
    """The next pair's inputs computed ahead (stream.overlap) chain through the same kept flows."""
    base = ["flow=dis_refine", "semantic=gt", "motion=gt"]
    ref, r0 = _stixels_of(base + ["stream.overlap=false"], slow_sequence)
    ahead, r1 = _stixels_of(base + ["stream.overlap=true"], slow_sequence)
    assert r1.stream.ahead >= 2 and all(_same(a, b) for a, b in zip(ref, ahead))


def test_a_pair_that_does_not_continue_the_stream_starts_cold():
    state = StreamState(StreamParams(flow_init=True, semantic_every=3, motion_warm_start=True))
    a = render_pair(1, scale=0.25)
    a.meta.update(sequence="s", frame=5, frame_prev=4, dt=0.1)
    flow = torch.zeros(2, *a.size)
    state.update(a, grey=np.zeros(a.size, np.uint8), flow=flow, semantic=torch.full((10, *a.size), 0.1),
                 semantic_fresh=True, motion=None, carried=state.carried(a))
    b = render_pair(2, scale=0.25)
    b.meta.update(sequence="s", frame=6, frame_prev=5, dt=0.1)
    assert state.carried(b).anything and state.carried(b).semantic is not None
    for meta in ({"sequence": "other"}, {"frame_prev": 3}, {"frame": 5}, {"dt": 0.5}):
        c = render_pair(2, scale=0.25)
        c.meta.update({"sequence": "s", "frame": 6, "frame_prev": 5, "dt": 0.1, **meta})
        got = state.carried(c)
        if "dt" in meta:  # the same frames, five times the interval: no flow to start from
            assert got.flow_init is None and got.grey_prev is not None
        else:
            assert not got.anything, meta
    state.drop()
    assert not state.carried(b).anything


# ---------------------------------------------------------------------------------------------- live frames
H, W, FPS = 64, 96, 30.0


def _write_clip(path: Path, n: int, fps: float = FPS) -> Path:
    """An mp4 of ``n`` textured frames moving right by 2 px a frame, the frame number drawn in it."""
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur((rng.random((H, W + 4 * n)) * 255).astype(np.uint8), (0, 0), 1.5)
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (W, H))
    assert vw.isOpened(), "OpenCV has no mp4v encoder"
    for k in range(n):
        img = cv2.cvtColor(np.ascontiguousarray(texture[:, 2 * k:2 * k + W]), cv2.COLOR_GRAY2BGR)
        vw.write(img)
    vw.release()
    return path


def test_streaming_reader_without_realtime_gives_the_pairs_of_the_file(tmp_path):
    clip = _write_clip(tmp_path / "c.mp4", 8)
    live = LiveVideoSource(clip, realtime=False, hfov_deg=80.0)
    offline = VideoSource(clip, hfov_deg=80.0)
    seen = []
    for i in live.indices():
        p, q = live[i], offline[i]
        assert torch.equal(p.image, q.image) and torch.equal(p.image_prev, q.image_prev)
        assert (p.meta["frame"], p.meta["frame_prev"]) == (q.meta["frame"], q.meta["frame_prev"]) == (i + 1, i)
        assert p.meta["dt"] == pytest.approx(1.0 / FPS) and p.meta["dropped_before"] == 0
        seen.append(i)
    assert seen == list(range(7))
    s = live.summary()
    assert s["frames_taken"] == 8 and s["frames_dropped"] == 0 and [f["frame"] for f in s["processed"]] == list(range(1, 8))


def test_streaming_reader_in_realtime_drops_what_arrives_while_busy(tmp_path):
    """A consumer slower than the frame rate gets the newest frame each time; the frames between are
    dropped, not queued, and the pairs are made of the frames taken."""
    clip = _write_clip(tmp_path / "c.mp4", 24)
    live = LiveVideoSource(clip, realtime=True, hfov_deg=80.0)
    taken = []
    for i in live.indices():
        pair = live[i]
        taken.append((pair.meta["frame"], pair.meta["frame_prev"], pair.meta["dropped_before"], pair.meta["dt"]))
        time.sleep(3.0 / FPS)  # three frame intervals of "solving"
    frames = [t[0] for t in taken]
    assert frames == sorted(frames) and len(frames) < 23  # fewer pairs than the file has
    for (cur, prev, dropped, dt), before in zip(taken, [(None,)] + taken):
        if before[0] is not None:
            assert prev == before[0]  # the previous frame is the one taken before, not a dropped one
            assert dropped == cur - prev - 1  # every frame between was dropped
            assert dt == pytest.approx((cur - prev) / FPS)
    assert max(t[2] for t in taken) >= 1
    s = live.summary()
    # Every frame read was taken or dropped; the drops are the gaps between taken frames.
    assert s["frames_dropped"] == sum(t[2] for t in taken) and s["frames_taken"] == len(taken) + 1
    assert s["frames_taken"] + s["frames_dropped"] == s["frames_read"] == 24
    assert [p["frame"] for p in s["processed"]] == frames


def test_bad_live_sources_fail_clearly(tmp_path):
    with pytest.raises(InputError, match="camera 97 cannot be opened"):
        LiveVideoSource(97, hfov_deg=80.0)
    with pytest.raises(InputError, match="no intrinsics"):
        LiveVideoSource(_write_clip(tmp_path / "c.mp4", 3), realtime=True)
    one = _write_clip(tmp_path / "one.mp4", 1)
    live = LiveVideoSource(one, realtime=True, hfov_deg=80.0)
    with pytest.raises(InputError, match="a pair needs two"):
        list(live.indices())


def test_run_in_realtime_drops_frames_and_says_which_were_processed(tmp_path):
    """`monostixels run data=video data.path=clip.mp4 data.realtime=true`: the clip arrives at 30 fps,
    solving takes longer, so frames are dropped (not queued); stream.json and each stixels.json say
    which frames were processed."""
    _write_clip(tmp_path / "clip.mp4", 30)
    p = _cli(["run", "data=video", "data.path=clip.mp4", "data.realtime=true", "data.hfov_deg=80", "flow=dis",
              "semantic=none"], tmp_path)
    out = tmp_path / "outputs" / "run"
    summary = json.loads((out / "stream.json").read_text())
    assert summary["realtime"] and summary["frames_read"] == 30 and summary["frames_dropped"] > 0
    processed = [f["frame"] for f in summary["processed"]]
    assert processed == sorted(processed) and len(processed) == summary["frames_taken"] - 1 < 29
    assert any(f["dropped_before"] > 0 for f in summary["processed"])
    dirs = sorted(d for d in out.iterdir() if d.is_dir())
    assert [d.name for d in dirs] == [f"clip_{k:06d}" for k in processed]
    # Each pair's partner is a frame processed before it, within keyframes.window (10) processed frames.
    # Which one (the oldest kept for a standing camera: test_sequence's keyframe tests) follows the last
    # pairs' speed and which of them had a known motion; which frames are processed, how far apart, and so
    # whether this pan reads as standing, turning or driving, depends on how fast the machine solves.
    seen = [summary["first_frame"]["frame"]]
    for d, f in zip(dirs, summary["processed"]):
        st = json.loads((d / "stixels.json").read_text())
        s = st["flags"]["stream"]
        prev = s["previous_frame"]
        assert s["frame"] == f["frame"] and s["realtime"] is True
        assert prev in seen[-10:]
        assert s["capture_time_s"] == pytest.approx(f["frame"] / FPS, abs=1e-6)
        assert s["previous_capture_time_s"] == pytest.approx(prev / FPS, abs=1e-6)
        assert st["pair"]["previous"] == f"clip_{prev:06d}"
        seen.append(f["frame"])
    assert "dropped while solving" in p.stdout
