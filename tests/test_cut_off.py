"""Movers cut off by the image's lower edge (monostixels.post.cut_off) against a truck's exact geometry."""
from __future__ import annotations

import math

import pytest
import torch

from monostixels._checks import InputError
from monostixels.core.classes import CLASS_NAMES, DYNAMIC_OBJECT, GROUND, SKY, STATIC_OBJECT
from monostixels.core.geometry import Motion, dynamic_motion, ground_basis
from monostixels.core.stixels import StixelWorld
from monostixels.post.cut_off import stand_cut_off
from monostixels.post.movers import MoverCheckParams

H, W, WS = 90, 300, 5
F, CX, CY, HEIGHT = 300.0, 149.5, 30.0, 1.5
K = torch.tensor([[F, 0.0, CX], [0.0, F, CY], [0.0, 0.0, 1.0]], dtype=torch.float64)
N_G = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
VEHICLE, BUILDING, ROAD = (CLASS_NAMES.index(c) for c in ("vehicle", "building", "road"))
SIDE_X = 2.0  # the truck's side, 2 m right of the camera, along the travel
BOTTOM_Z = F * HEIGHT / (H - 0.5 - CY)  # the bottom row's ground, 7.56 m ahead
MOTION = Motion(torch.eye(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))


def _u(c: int) -> float:
    return c * WS + (WS - 1) / 2


def _dist(c: int, z: float) -> float:
    """Plane distance (along the column's horizontal viewing direction) of a point ``z`` ahead in column ``c``."""
    return z * math.hypot(1.0, (_u(c) - CX) / F)


def _world(truck_from: int, car: tuple[int, int, float] | None = None) -> tuple[StixelWorld, dict[int, float]]:
    """A truck's side at x = 2 m over columns ``truck_from``..59: where its contact is in view a ground
    stixel and the truck standing on it, else the truck from the lower edge at the bottom row's ground
    with a second dynamic stixel and a building stacked on it; ``car = (first, last column, z)`` another
    vehicle standing on the road. Returns the world and each cut-off column's true plane distance."""
    rows: list[tuple[int, int, int, int, int, float]] = []  # column, top, bottom, type, class, p
    truth = {}
    for c in range(W // WS):
        if c >= truck_from:
            z = SIDE_X * F / (_u(c) - CX)
            v_c = CY + F * HEIGHT / z
            if v_c < H - 1:
                rows += [(c, int(v_c) + 1, H - 1, GROUND, ROAD, 1.0 / HEIGHT), (c, 5, int(v_c), DYNAMIC_OBJECT, VEHICLE, 1 / _dist(c, z))]
            else:
                p_b = 1.0 / _dist(c, BOTTOM_Z)
                rows += [(c, 40, H - 1, DYNAMIC_OBJECT, VEHICLE, p_b), (c, 20, 39, DYNAMIC_OBJECT, VEHICLE, p_b),
                         (c, 5, 19, STATIC_OBJECT, BUILDING, 1 / 30.0)]
                truth[c] = _dist(c, z)
        elif car is not None and car[0] <= c <= car[1]:
            v_c = CY + F * HEIGHT / car[2]
            rows += [(c, int(v_c) + 1, H - 1, GROUND, ROAD, 1.0 / HEIGHT), (c, 5, int(v_c), DYNAMIC_OBJECT, VEHICLE, 1 / _dist(c, car[2]))]
        else:
            rows += [(c, CY + 1, H - 1, GROUND, ROAD, 1.0 / HEIGHT), (c, 5, CY, STATIC_OBJECT, BUILDING, 1 / 40.0)]
        rows.append((c, 0, 4, SKY, CLASS_NAMES.index("sky"), 0.0))
    n = len(rows)
    t = lambda k, dt=torch.long: torch.tensor([r[k] for r in rows], dtype=dt)  # noqa: E731
    world = StixelWorld(column_width=WS, image_size=(H, W), K=K, ground_normal=N_G, column=t(0), v_top=t(1),
                        v_bottom=t(2), type=t(3), cls=t(4), inverse_depth=t(5, torch.float64),
                        motion=torch.zeros(n, 3, dtype=torch.float64), cost=torch.zeros(n),
                        tau=torch.full((n, 2), 0.02, dtype=torch.float64), energy=torch.zeros(W // WS))
    return world, truth


def test_a_truck_cut_off_by_the_lower_edge_stands_on_the_line_of_its_visible_contacts():
    world, truth = _world(36)
    assert len(truth) == 14  # columns 46-59: the truck's contact is below the image
    out = stand_cut_off(world, MOTION)
    d = 1.0 / out.inverse_depth
    for c, d_true in truth.items():
        ids = torch.nonzero(world.column == c).flatten()
        base, stacked, building = ids[0], ids[1], ids[2]
        assert abs(float(d[base]) / d_true - 1) < 1e-6, c
        assert float(d[stacked]) == float(d[base])  # the dynamic stixel stacked on it follows
        assert float(out.inverse_depth[building]) == float(world.inverse_depth[building])  # a static one does not
        assert float(d[base]) < float(1.0 / world.inverse_depth[base])  # nearer than the bottom row
        # Its motion follows its depth: g = p (t - R delta) is kept.
        g = world.tau[base].double() @ ground_basis(N_G).T
        want = dynamic_motion(torch.eye(3, dtype=torch.float64), MOTION.t, g, out.inverse_depth[base].double())
        assert torch.allclose(out.motion[base], want)
    moved = out.inverse_depth != world.inverse_depth
    assert int(moved.sum()) == 2 * len(truth)
    # Off: nothing moves.
    assert stand_cut_off(world, MOTION, contacts=0) is world


def test_contacts_of_another_object_are_not_taken():
    # Two contacts of the truck in view, then a car 20 m ahead: the depth jumps, too few contacts of one object.
    world, truth = _world(44, car=(36, 43, 20.0))
    assert len(truth) == 14
    assert stand_cut_off(world, MOTION) is world
    # With its own contacts in view it stands on them, the car's not taken.
    world, truth = _world(40, car=(30, 39, 20.0))
    out = stand_cut_off(world, MOTION)
    for c, d_true in truth.items():
        base = torch.nonzero(world.column == c).flatten()[0]
        assert abs(float(1.0 / out.inverse_depth[base]) / d_true - 1) < 1e-6


def test_bad_cut_off_settings_are_named():
    for bad in ({"cut_off_contacts": -1}, {"cut_off_max_rms_m": 0.0}, {"cut_off_max_jump": -0.1}):
        with pytest.raises(InputError, match=next(iter(bad))):
            MoverCheckParams(**bad)
