"""The result type: maps, compactness and JSON / NPZ round trips."""
from __future__ import annotations

import json

import pytest
import torch

from monostixels._checks import InputError
from monostixels.core.energy import PriorParams
from monostixels.core.solver import SolverConfig, solve
from monostixels.core.stixels import StixelWorld

from tests import _planes


@pytest.fixture(scope="module")
def world() -> StixelWorld:
    flow, cov, scores, _ = _planes.build_scene()
    return solve(flow, cov, scores, _planes.CAM, _planes.MOTION, PriorParams.from_yaml(),
                 SolverConfig.from_yaml(column_width=_planes.WS, cell_rows=3, dtype="float64"))


def _same(a: StixelWorld, b: StixelWorld) -> None:
    for k in ("column", "v_top", "v_bottom", "type", "cls"):
        assert torch.equal(getattr(a, k), getattr(b, k)), k
    for k in ("inverse_depth", "motion", "cost", "tau", "energy", "K", "ground_normal"):
        assert torch.allclose(getattr(a, k).double(), getattr(b, k).double(), rtol=1e-12, atol=1e-12), k
    assert a.flags == b.flags and a.image_size == b.image_size and a.column_width == b.column_width


def test_json_round_trip(world, tmp_path):
    world.save_json(tmp_path / "s.json")
    back = StixelWorld.load_json(tmp_path / "s.json")
    _same(world, back)
    d = json.loads((tmp_path / "s.json").read_text())
    assert d["compactness"] == 3 * len(world)
    assert {s["type"] for s in d["stixels"]} >= {"ground", "static_object", "dynamic_object", "sky"}


def test_npz_round_trip(world, tmp_path):
    world.save_npz(tmp_path / "s.npz")
    _same(world, StixelWorld.load_npz(tmp_path / "s.npz"))


def test_maps_cover_image_and_match_stixels(world):
    H, W = world.image_size
    idx = world.index_map()
    assert bool((idx >= 0).all())
    sem = world.semantic_map()
    typ = world.type_map()
    k = len(world) // 2
    c, v = int(world.column[k]), int(world.v_top[k])
    assert int(sem[v, c * world.column_width]) == int(world.cls[k])
    assert int(typ[v, c * world.column_width]) == int(world.type[k])
    depth = world.depth_map()
    assert bool(torch.isinf(depth[typ == 3]).all())  # sky
    assert bool((depth[(typ == 1) | (typ == 2)] > 0).all())
    assert world.compactness == 3 * len(world)


def test_bad_files(tmp_path):
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(InputError, match="bad.json"):
        StixelWorld.load_json(tmp_path / "bad.json")
    (tmp_path / "other.json").write_text(json.dumps({"format": "x"}))
    with pytest.raises(InputError, match="unknown format"):
        StixelWorld.load_json(tmp_path / "other.json")
    with pytest.raises(InputError, match="missing.npz"):
        StixelWorld.load_npz(tmp_path / "missing.npz")


def test_neighbours_and_segment_medians_against_loops():
    from monostixels.core.stixels import neighbours, segment_lower_median

    g = torch.Generator().manual_seed(1)
    col = torch.randint(0, 8, (40,), generator=g)
    top = torch.randint(0, 30, (40,), generator=g)
    bot = top + torch.randint(0, 10, (40,), generator=g)
    got = neighbours(col, top, bot)
    for i in range(40):
        for j in range(40):
            rows_i, rows_j = set(range(int(top[i]), int(bot[i]) + 1)), set(range(int(top[j]), int(bot[j]) + 1))
            assert bool(got[i, j]) == (abs(int(col[i]) - int(col[j])) == 1 and bool(rows_i & rows_j)), (i, j)
    assert got.any() and not got.all()
    # Lower medians of segments laid out one after the other (an empty one gives NaN).
    counts = torch.tensor([3, 0, 4, 1])
    values = torch.tensor([5.0, 1.0, 3.0, 9.0, 2.0, 7.0, 2.0, 4.0], dtype=torch.float64)
    seg = torch.repeat_interleave(torch.arange(4), counts)
    med = segment_lower_median(values, seg, counts)
    assert med[0] == 3.0 and torch.isnan(med[1]) and med[2] == 2.0 and med[3] == 4.0


def test_frame_status_writes_the_flags_of_stixels_json_and_reads_them_back(world):
    """The typed status is written as the flags of docs/conventions.md (section 4.4), in the pipeline's order."""
    from monostixels.core.status import FrameStatus, MotionKind, MotionStatus, ScaleFrom, StreamFrames

    status = FrameStatus(MotionStatus(degenerate=False, kind=MotionKind.METRIC, scale_from=ScaleFrom.ROAD_MARKS,
                                      scale_std=0.05, scale_uncertain=False, camera_height_fit_m=1.6))
    status.counts.static_checked, status.counts.carried_stixels = 3, 2
    status.motion.add_reason("static depths carried")
    status.stream = StreamFrames(frame=5, capture_time_s=0.5, previous_frame=4, previous_capture_time_s=0.4,
                                 dropped_before=0, realtime=True)
    flags = status.to_flags()
    assert list(flags) == ["degenerate_motion", "static_checked", "camera_height_fit_m", "camera_motion", "scale_from",
                           "scale_std", "scale_uncertain", "stream", "carried_stixels", "reason"]
    assert flags["camera_motion"] == "metric" and type(flags["camera_motion"]) is str
    assert FrameStatus.from_flags(flags) == status
    # A degenerate frame's reason follows its flag (the solver sets both).
    deg = FrameStatus(MotionStatus(degenerate=True, reason="camera translation 0.000 m < ..."))
    assert list(deg.to_flags()) == ["degenerate_motion", "reason"]
    assert FrameStatus().to_flags() == {}
    world.status = status
    with pytest.raises(TypeError):
        world.flags["reason"] = "x"  # read only: set the status instead
    assert StixelWorld.from_dict(world.to_dict()).status == status
