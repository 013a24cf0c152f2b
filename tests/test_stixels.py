"""The result type: maps, compactness and JSON / NPZ round trips."""
from __future__ import annotations

import json

import pytest
import torch

from monostixels._checks import InputError
from monostixels.energy import PriorParams
from monostixels.solver import SolverConfig, solve
from monostixels.stixels import StixelWorld

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
