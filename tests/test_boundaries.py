"""Moving objects' tops at pixel rows (monostixels.post.boundaries)."""
from __future__ import annotations

import pytest
import torch

from monostixels._checks import InputError
from monostixels.post.boundaries import refine_object_tops, row_class_cost
from monostixels.core.classes import CLASS_NAMES, DYNAMIC_OBJECT, GROUND, NUM_CLASSES, SKY, STATIC_OBJECT
from monostixels.core.stixels import StixelWorld

H, W, WS = 60, 15, 5
K = torch.tensor([[50.0, 0.0, 7.0], [0.0, 50.0, 20.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
N_G = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
ROAD, BUILDING, VEHICLE, SKY_C = (CLASS_NAMES.index(c) for c in ("road", "building", "vehicle", "sky"))
ALPHA_L = 4.0


def _world(columns: list[list[tuple[int, int, int, int, float]]]) -> StixelWorld:
    """Stixels ``(v_top, v_bottom, type, class, depth in metres)`` per column, listed bottom to top."""
    cols, tops, bots, types, classes, ps = [], [], [], [], [], []
    for c, segs in enumerate(columns):
        for a, b, ty, cl, d in segs:
            cols.append(c), tops.append(a), bots.append(b), types.append(ty), classes.append(cl)
            ps.append(0.0 if ty == SKY else 1.0 / d)
    n = len(cols)
    return StixelWorld(
        column_width=WS, image_size=(H, W), K=K, ground_normal=N_G,
        column=torch.tensor(cols), v_top=torch.tensor(tops), v_bottom=torch.tensor(bots),
        type=torch.tensor(types), cls=torch.tensor(classes), inverse_depth=torch.tensor(ps, dtype=torch.float64),
        motion=torch.zeros(n, 3, dtype=torch.float64), cost=torch.zeros(n),
        tau=torch.zeros(n, 2, dtype=torch.float64), energy=torch.zeros(len(columns)))


def _scores(layers: list[tuple[int, int]], confidence: float = 0.8) -> torch.Tensor:
    """Class scores (10, H, W): ``layers`` of ``(first row, class)``, top to bottom, the same in every
    column; the other classes share ``1 - confidence``."""
    s = torch.full((NUM_CLASSES, H, W), (1.0 - confidence) / (NUM_CLASSES - 1))
    bounds = [row for row, _ in layers[1:]] + [H]
    for (row, cls), end in zip(layers, bounds):
        s[:, row:end] = (1.0 - confidence) / (NUM_CLASSES - 1)
        s[cls, row:end] = confidence
    return s


def test_row_class_cost_is_the_dps_term_per_row():
    s = _scores([(0, SKY_C), (37, VEHICLE)])
    s[VEHICLE, 50, 10:15] = torch.tensor([1.0, 0.6, 0.2, 0.0, 0.2])  # a ragged row in column 2
    s[ROAD] = 0.0
    cost = row_class_cost(s, WS, ALPHA_L)
    assert cost.shape == (NUM_CLASSES, H, 3) and cost.dtype == torch.float64
    assert float(cost[VEHICLE, 40, 0]) == pytest.approx(-torch.log(torch.tensor(0.8)).item(), rel=1e-6)
    # -log of the column's mean score, not the mean of -log (the DP's cell term, per row).
    assert float(cost[VEHICLE, 50, 2]) == pytest.approx(-torch.log(torch.tensor(0.4)).item(), rel=1e-6)
    # Capped at alpha_L: a score of 0 costs alpha_L (a score of ~0.022, 3.8).
    assert float(cost[ROAD].min()) == ALPHA_L
    assert float(cost[SKY_C, 40, 0]) == pytest.approx(-torch.log(torch.tensor(0.2 / 9)).item(), rel=1e-6)
    # A last column narrower than w_s is averaged over its own pixels.
    narrow = row_class_cost(s[:, :, :12], WS, ALPHA_L)
    assert narrow.shape == (NUM_CLASSES, H, 3)
    assert torch.allclose(narrow[:, :49, 2], cost[:, :49, 2])


def test_a_movers_top_moves_to_its_class_boundary():
    # A car's top is at row 37 in the scores; the DP put it on a cell edge one cell lower (40) against
    # the sky (column 0) and one cell higher (34) against a house 80 m away (column 1), so 3 rows of the
    # car got the sky's depth or the car the house's rows. A parked (static) car in column 2 keeps the
    # DP's top unless static objects are included.
    car, house = 6.0, 80.0
    world = _world([
        [(50, H - 1, GROUND, ROAD, 5.0), (40, 49, DYNAMIC_OBJECT, VEHICLE, car), (0, 39, SKY, SKY_C, 0.0)],
        [(50, H - 1, GROUND, ROAD, 5.0), (34, 49, DYNAMIC_OBJECT, VEHICLE, car), (0, 33, STATIC_OBJECT, BUILDING, house)],
        [(50, H - 1, GROUND, ROAD, 5.0), (40, 49, STATIC_OBJECT, VEHICLE, car), (0, 39, SKY, SKY_C, 0.0)],
    ])
    scores = torch.cat([_scores([(0, SKY_C), (37, VEHICLE), (50, ROAD)])[:, :, :5],
                        _scores([(0, BUILDING), (37, VEHICLE), (50, ROAD)])[:, :, 5:10],
                        _scores([(0, SKY_C), (37, VEHICLE), (50, ROAD)])[:, :, 10:]], dim=2)
    out = refine_object_tops(world, scores, rows=3, depth_ratio=1.5, alpha_L=ALPHA_L)
    assert out.v_top.tolist() == [50, 37, 0, 50, 37, 0, 50, 40, 0]
    assert out.v_bottom.tolist() == [H - 1, 49, 36, H - 1, 49, 36, H - 1, 49, 39]
    # The car's rows now have the car's depth; types, classes, depths, motion are the DP's.
    depth, ref = out.depth_map(), world.depth_map()
    assert torch.allclose(depth[37:40, :5], ref[45, :5].expand(3, 5))
    assert torch.allclose(depth[34:37, 5:10], ref[20, 5:10].expand(3, 5))
    for name in ("column", "type", "cls", "inverse_depth", "motion"):
        assert torch.equal(getattr(out, name), getattr(world, name))
    # The cars' ground contacts never move.
    cars = world.cls == VEHICLE
    assert torch.equal(out.v_bottom[cars], world.v_bottom[cars])
    everything = refine_object_tops(world, scores, rows=3, depth_ratio=1.5, alpha_L=ALPHA_L, objects="all")
    assert everything.v_top.tolist() == [50, 37, 0, 50, 37, 0, 50, 37, 0]
    # Beyond the search window the boundary stays: a top 4 rows off with rows=3 moves only 3.
    far = refine_object_tops(world, _scores([(0, SKY_C), (36, VEHICLE), (50, ROAD)]), rows=3, depth_ratio=1.5,
                             alpha_L=ALPHA_L)
    assert int(far.v_top[1]) == 37


def test_boundaries_that_do_not_separate_near_from_far_stay():
    scores = _scores([(0, SKY_C), (37, VEHICLE), (50, ROAD)])
    world = _world([
        # Object above an object at a similar depth (a truck's cab on its box): no depth gap.
        [(50, H - 1, GROUND, ROAD, 5.0), (40, 49, DYNAMIC_OBJECT, VEHICLE, 10.0), (0, 39, DYNAMIC_OBJECT, VEHICLE, 12.0)],
        # The nearer object is above (a branch over a far wall): not an object's top.
        [(50, H - 1, GROUND, ROAD, 5.0), (40, 49, DYNAMIC_OBJECT, VEHICLE, 40.0), (0, 39, STATIC_OBJECT, BUILDING, 8.0)],
        # Ground up to row 39, sky above (the horizon is not an object's top).
        [(40, H - 1, GROUND, ROAD, 5.0), (0, 39, SKY, SKY_C, 0.0)],
    ])
    out = refine_object_tops(world, scores, rows=3, depth_ratio=1.5, alpha_L=ALPHA_L, objects="all")
    assert torch.equal(out.v_top, world.v_top) and torch.equal(out.v_bottom, world.v_bottom)
    assert refine_object_tops(world, scores, rows=0, depth_ratio=1.5, alpha_L=ALPHA_L) is world


def test_every_stixel_keeps_at_least_one_row():
    # The car's class starts at row 39 in the scores, but a thin static stixel (rows 41-42, 30 m) lies
    # between the car's DP top (43) and a house above it: the car's top may rise only to row 42, so
    # the thin stixel keeps one row, and the rows still tile the column.
    scores = _scores([(0, BUILDING), (39, VEHICLE), (50, ROAD)])
    world = _world([[(50, H - 1, GROUND, ROAD, 5.0), (43, 49, DYNAMIC_OBJECT, VEHICLE, 6.0),
                     (41, 42, STATIC_OBJECT, BUILDING, 30.0), (0, 40, STATIC_OBJECT, BUILDING, 60.0)]])
    out = refine_object_tops(world, scores, rows=3, depth_ratio=1.5, alpha_L=ALPHA_L)
    assert out.v_top.tolist() == [50, 42, 41, 0] and out.v_bottom.tolist() == [H - 1, 49, 41, 40]
    # With static tops movable too, the thin stixel's own top is a candidate as well: the two could
    # meet inside it, so a stixel too thin to leave room for both keeps the DP's boundaries.
    out = refine_object_tops(world, scores, rows=3, depth_ratio=1.5, alpha_L=ALPHA_L, objects="all")
    assert torch.equal(out.v_top, world.v_top) and torch.equal(out.v_bottom, world.v_bottom)
    # With room (a house 12 rows tall above the car), the car's top goes to its class boundary.
    scores = _scores([(0, SKY_C), (31, BUILDING), (44, VEHICLE), (50, ROAD)])
    world = _world([[(50, H - 1, GROUND, ROAD, 5.0), (43, 49, DYNAMIC_OBJECT, VEHICLE, 6.0),
                     (31, 42, STATIC_OBJECT, BUILDING, 30.0), (0, 30, SKY, SKY_C, 0.0)]])
    out = refine_object_tops(world, scores, rows=3, depth_ratio=1.5, alpha_L=ALPHA_L, objects="all")
    assert out.v_top.tolist() == [50, 44, 31, 0]
    assert bool((out.v_top <= out.v_bottom).all())
    assert out.v_top[:-1].tolist() == [b + 1 for b in out.v_bottom[1:].tolist()]


def test_bad_settings_and_scores_are_named():
    world = _world([[(40, H - 1, GROUND, ROAD, 5.0), (0, 39, SKY, SKY_C, 0.0)]])
    scores = _scores([(0, SKY_C), (40, ROAD)])
    with pytest.raises(InputError, match="top_refine_rows"):
        refine_object_tops(world, scores, rows=-1, depth_ratio=1.5, alpha_L=ALPHA_L)
    with pytest.raises(InputError, match="top_refine_depth_ratio"):
        refine_object_tops(world, scores, rows=3, depth_ratio=0.5, alpha_L=ALPHA_L)
    with pytest.raises(InputError, match="top_refine_objects"):
        refine_object_tops(world, scores, rows=3, depth_ratio=1.5, alpha_L=ALPHA_L, objects="static")
    with pytest.raises(InputError, match="semantic scores"):
        refine_object_tops(world, scores[:, :30], rows=3, depth_ratio=1.5, alpha_L=ALPHA_L)


def test_pipeline_puts_movers_tops_where_the_ground_truth_has_them():
    # A render at half size with a real flow (DIS) and the ground-truth semantics: the DP's cell edges
    # cut off the tops of movers; refined, far fewer moving pixels get a background's depth.
    from monostixels.data.synthetic import render_pair
    from monostixels.pipeline import Pipeline, load_config
    from monostixels.build import pipeline_settings

    pair = render_pair(39, scale=0.5)
    g = pair.gt.depth.double()
    moving = pair.gt.moving & (g > 0) & (g <= 80)
    assert int(moving.sum()) > 2000
    err = {}
    for rows in (0, 3):
        cfg = load_config(["flow=dis", "semantic=gt", "motion=gt", f"solver.top_refine_rows={rows}"])
        d = Pipeline(pipeline_settings(cfg)).run(pair).stixels.depth_map().double().clamp(1e-3, 80.0)
        err[rows] = ((d - g).abs() / g)[moving]
    assert float(err[3].mean()) < 0.9 * float(err[0].mean())
    assert int((err[3] > 1).sum()) < int((err[0] > 1).sum()) / 2
