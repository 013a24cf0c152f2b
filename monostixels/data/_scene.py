"""Seeded layout of a synthetic street scene: road frame, ground pieces, boxes, ego-motion.

Everything here is geometry only (no colours). The world frame is the *current* camera frame
(x right, y down, z forward, metres; docs/conventions.md, section 2), so "current-camera
coordinates" and "world" coincide. The road runs along the unit vector ``f = Ry(a) e_z`` (road yaw
``a``) with lateral unit ``r = Ry(a) e_x``; road coordinates are ``e = r.X + e_off`` (lateral, right
positive, 0 = ego lane centre) and ``l = f.X`` (longitudinal, metres ahead).

Motion between the previous and the current frame:

- camera: ``X_prev = R X_cur + t`` for a static point (``R`` a yaw, ``t_y = 0``: the camera stays at
  its mounting height above the flat road);
- a moving box is displaced by ``Δ`` (on the ground plane, world = current-camera coordinates)
  from the previous to the current frame; a point of it satisfies ``X_prev = R (X_cur - Δ) + t``.
  Boxes translate only (no rotation between the frames).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from monostixels.core.geometry import KITTI_CAMERA_HEIGHT_M

__all__ = [
    "FRAME_INTERVAL_S",
    "KERB_HEIGHT_M",
    "LANE_WIDTH_M",
    "RoadLayout",
    "SceneBoxes",
    "SceneLayout",
    "sample_scene",
    "yaw_matrix",
]

#: Time between the previous and the current frame (seconds; KITTI records at 10 Hz).
FRAME_INTERVAL_S = 0.1
#: Height of the kerb / sidewalk above the road (metres; typical urban kerb).
KERB_HEIGHT_M = 0.15
#: Width of a driving lane (metres; typical urban lane).
LANE_WIDTH_M = 3.5
#: Width of a parking lane (metres).
PARKING_LANE_WIDTH_M = 2.3
#: Ego speed range (m/s): 8..15 m/s gives 0.8..1.5 m of translation per frame pair at 10 Hz.
EGO_SPEED_RANGE_MPS = (8.0, 15.0)
#: Largest ego yaw between the frames (radians; about 1 degree).
MAX_EGO_YAW_RAD = math.radians(1.0)
#: Largest angle between the road axis and the optical axis (radians).
MAX_ROAD_YAW_RAD = math.radians(2.0)
#: Lateral extent of the ground on each side of the road axis (metres).
GROUND_HALF_WIDTH_M = 60.0
#: The ground starts this far behind the camera (metres).
GROUND_START_M = -30.0

# Class ids (monostixels.core.classes.CLASS_NAMES order).
ROAD, SIDEWALK, TERRAIN, BUILDING, POLE, VEGETATION, VEHICLE, TWO_WHEELER, PERSON, SKY = range(10)

# Surface styles (texture programs) of boxes.
STYLE_PLAIN, STYLE_FACADE, STYLE_GLASS, STYLE_CLOTHES = range(4)


def yaw_matrix(yaw: float) -> np.ndarray:
    """Rotation (3, 3) about the vertical (camera y) axis; maps box-local to world coordinates.

    Convention: same as :func:`monostixels.core.geometry.rotation_yaw` (local z = box length axis maps
    to ``(sin yaw, 0, cos yaw)``).
    """
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


@dataclass
class RoadLayout:
    """Ground pieces in road coordinates (metres).

    Attributes:
        angle: road yaw ``a`` relative to the optical axis (radians).
        e_off: lateral position of the camera in road coordinates (metres, ego lane centre = 0).
        road_left, road_right: the road surface spans ``e in [-road_left, road_right]``.
        sidewalk_left, sidewalk_right: sidewalk widths beyond the kerbs (metres).
        height: camera height above the road (metres); raised ground lies ``KERB_HEIGHT_M`` higher.
        l_min, l_max: longitudinal extent of the ground (metres).
        e_max: lateral half extent of the ground (metres).
        markings: lane markings as ``(e_centre, half_width, dashed)`` (metres).
        dash_period, dash_length, dash_phase: dashed-line pattern along ``l`` (metres).
    """

    angle: float
    e_off: float
    road_left: float
    road_right: float
    sidewalk_left: float
    sidewalk_right: float
    height: float = KITTI_CAMERA_HEIGHT_M
    l_min: float = GROUND_START_M
    l_max: float = 120.0
    e_max: float = GROUND_HALF_WIDTH_M
    markings: list[tuple[float, float, bool]] = field(default_factory=list)
    dash_period: float = 9.0
    dash_length: float = 3.0
    dash_phase: float = 0.0

    @property
    def forward(self) -> np.ndarray:
        """Unit road direction ``f`` (3,) in world coordinates."""
        return np.array([math.sin(self.angle), 0.0, math.cos(self.angle)])

    @property
    def right(self) -> np.ndarray:
        """Unit lateral road direction ``r`` (3,) in world coordinates."""
        return np.array([math.cos(self.angle), 0.0, -math.sin(self.angle)])

    def to_world(self, e: float, l: float, y: float) -> np.ndarray:
        """World point (3,) of road coordinates ``(e, l)`` at camera-frame height ``y``."""
        p = self.right * (e - self.e_off) + self.forward * l
        p[1] = y
        return p

    def ground_y(self, e: float) -> float:
        """Camera-frame ``y`` of the ground at lateral position ``e`` (road or raised)."""
        return self.height if -self.road_left <= e <= self.road_right else self.height - KERB_HEIGHT_M


@dataclass
class SceneBoxes:
    """All boxes of a scene (numpy, float64; one row per box).

    Attributes:
        centre: (B, 3) current-frame centres (metres, world = current camera).
        half: (B, 3) half sizes along local x (width), y (height), z (length), metres.
        yaw: (B,) radians, local-to-world rotation :func:`yaw_matrix`.
        delta: (B, 3) world displacement previous -> current (metres; 0 for static boxes).
        cls: (B,) class ids. inst: (B,) instance ids (0 = stuff). style: (B,) texture program.
        obj: (B,) index into ``SceneLayout.objects`` or -1 for stuff.
    """

    centre: np.ndarray
    half: np.ndarray
    yaw: np.ndarray
    delta: np.ndarray
    cls: np.ndarray
    inst: np.ndarray
    style: np.ndarray
    obj: np.ndarray

    def __len__(self) -> int:
        return int(self.centre.shape[0])


@dataclass
class SceneLayout:
    """A sampled scene: road, boxes, camera motion and the object list for ``meta``."""

    road: RoadLayout
    boxes: SceneBoxes
    R: np.ndarray
    t: np.ndarray
    objects: list[dict[str, Any]]
    ego_speed: float


class _Builder:
    """Collects boxes and keeps simple footprint bookkeeping to avoid overlapping objects."""

    def __init__(self, road: RoadLayout, ahead_steps: int = 0) -> None:
        self.road = road
        self.ahead = int(ahead_steps)
        self.rows: list[tuple] = []
        self.objects: list[dict[str, Any]] = []
        self.footprints: list[tuple[float, float, float, float]] = []  # (e0, e1, l0, l1), swept
        self.next_inst = 1

    def free(self, e: float, l: float, half_e: float, half_l: float, d_e: float = 0.0, d_l: float = 0.0,
             margin: float = 0.4) -> bool:
        """Whether the footprint (previous to current position, and ``ahead`` steps on; swept) is free."""
        (e0, e1), (l0, l1) = self._sweep(e, d_e), self._sweep(l, d_l)
        e0, e1 = e0 - half_e - margin, e1 + half_e + margin
        l0, l1 = l0 - half_l - margin, l1 + half_l + margin
        return all(e1 < a0 or e0 > a1 or l1 < b0 or l0 > b1 for a0, a1, b0, b1 in self.footprints)

    def occupy(self, e: float, l: float, half_e: float, half_l: float, d_e: float = 0.0, d_l: float = 0.0) -> None:
        (e0, e1), (l0, l1) = self._sweep(e, d_e), self._sweep(l, d_l)
        self.footprints.append((e0 - half_e, e1 + half_e, l0 - half_l, l1 + half_l))

    def _sweep(self, x: float, d: float) -> tuple[float, float]:
        """Range of a coordinate ``x`` moving by ``d`` per step, from one step back to ``ahead`` steps on."""
        lo, hi = min(x, x - d), max(x, x - d)
        if self.ahead:
            lo, hi = min(lo, x + self.ahead * d), max(hi, x + self.ahead * d)
        return lo, hi

    def box(self, e: float, l: float, y_bottom: float, size: tuple[float, float, float], yaw_rel: float,
            cls: int, style: int, inst: int = 0, delta: np.ndarray | None = None, obj: int = -1) -> None:
        """Add a box standing at ``y_bottom`` (camera-frame y of its base) at road coords (e, l)."""
        w, h, ln = size
        c = self.road.to_world(e, l, y_bottom - h / 2)
        d = np.zeros(3) if delta is None else delta
        self.rows.append((c, (w / 2, h / 2, ln / 2), self.road.angle + yaw_rel, d, cls, inst, style, obj))

    def thing(self, cls: int, e: float, l: float, parts: list[tuple[float, float, float, float, int]],
              yaw_rel: float, d_e: float, d_l: float) -> None:
        """Add an object (instance) made of stacked parts ``(w, h, length, dl_offset, style)``.

        ``d_e``, ``d_l``: displacement previous -> current in road coordinates (metres).
        """
        inst = self.next_inst
        self.next_inst += 1
        road = self.road
        delta = road.right * d_e + road.forward * d_l
        delta[1] = 0.0
        y0 = road.ground_y(e)
        idx = len(self.objects)
        ca, sa = math.cos(yaw_rel), math.sin(yaw_rel)
        y = y0
        part_meta = []
        for w, h, ln, off, style in parts:
            # Offset along the object's own length axis (yaw_rel relative to the road).
            pe, pl = e + sa * off, l + ca * off
            self.box(pe, pl, y, (w, h, ln), yaw_rel, cls, style, inst, delta, idx)
            c = road.to_world(pe, pl, y - h / 2)
            part_meta.append({"centre": c.tolist(), "size": [w, h, ln], "yaw": road.angle + yaw_rel})
            y -= h
        height = y0 - y
        wmax = max(p[0] for p in parts)
        lmin = min(p[3] - p[2] / 2 for p in parts)
        lmax = max(p[3] + p[2] / 2 for p in parts)
        lc = (lmin + lmax) / 2
        centre = road.to_world(e + sa * lc, l + ca * lc, y0 - height / 2)
        moving = bool(np.linalg.norm(delta) > 0)
        self.objects.append({
            "class": cls,
            "instance": inst,
            "centre": centre.tolist(),
            "size": [wmax, height, lmax - lmin],
            "yaw": road.angle + yaw_rel,
            "delta": delta.tolist(),
            "moving": moving,
            "parts": part_meta,
        })

    def finish(self) -> SceneBoxes:
        if not self.rows:
            z = np.zeros((0, 3))
            zi = np.zeros((0,), dtype=np.int64)
            return SceneBoxes(z, z.copy(), np.zeros(0), z.copy(), zi, zi.copy(), zi.copy(), zi.copy())
        c, h, y, d, cl, ins, st, ob = zip(*self.rows)
        return SceneBoxes(
            centre=np.array(c, dtype=np.float64), half=np.array(h, dtype=np.float64),
            yaw=np.array(y, dtype=np.float64), delta=np.array(d, dtype=np.float64),
            cls=np.array(cl, dtype=np.int64), inst=np.array(ins, dtype=np.int64),
            style=np.array(st, dtype=np.int64), obj=np.array(ob, dtype=np.int64),
        )


def _count(rng: np.random.Generator, mean: float, density: float) -> int:
    """Poisson-like count scaled by density (deterministic given rng)."""
    lam = max(mean * density, 0.0)
    return int(rng.poisson(lam)) if lam > 0 else 0


def _vehicle_parts(rng: np.random.Generator) -> list[tuple[float, float, float, float, int]]:
    """Parts of a car (body + glass cabin) or, sometimes, a van (one tall box + windscreen strip)."""
    if rng.random() < 0.15:
        w, ln, h = rng.uniform(1.9, 2.2), rng.uniform(5.0, 6.5), rng.uniform(2.0, 2.7)
        return [(w, h, ln, 0.0, STYLE_PLAIN)]
    w, ln = rng.uniform(1.7, 1.95), rng.uniform(3.9, 4.8)
    hb, hc = rng.uniform(0.75, 0.95), rng.uniform(0.5, 0.65)
    lc = ln * rng.uniform(0.45, 0.6)
    return [(w, hb, ln, 0.0, STYLE_PLAIN), (w - 0.15, hc, lc, -ln * rng.uniform(0.0, 0.08), STYLE_GLASS)]


def _two_wheeler_parts(rng: np.random.Generator) -> list[tuple[float, float, float, float, int]]:
    """Bike (low, long) with the rider's torso above it; the whole object is class two_wheeler."""
    return [(0.55, rng.uniform(0.9, 1.1), rng.uniform(1.6, 1.9), 0.0, STYLE_PLAIN),
            (0.5, rng.uniform(0.7, 0.85), 0.45, -0.15, STYLE_CLOTHES)]


def _person_parts(rng: np.random.Generator) -> list[tuple[float, float, float, float, int]]:
    return [(rng.uniform(0.45, 0.6), rng.uniform(1.6, 1.9), rng.uniform(0.3, 0.4), 0.0, STYLE_CLOTHES)]


def sample_scene(seed: int, density: float = 1.0, ego_speed: float | None = None, ahead_steps: int = 0) -> SceneLayout:
    """Sample the geometry of one street scene from ``seed`` (numpy Generator stream ``[seed, 0]``).

    Args:
        seed: scene seed (non-negative int).
        density: multiplier of the number of objects (vehicles, persons, poles, trees).
        ego_speed: the ego speed (m/s) instead of the sampled one (the random stream is unchanged, so the
            scene is the same; the yaw per frame scales with the distance driven, and vehicles whose
            speed follows the ego's, e.g. the preceding car, follow it too). None = sampled.
        ahead_steps: movers keep their displacement for this many frames after the current one
            (sequences): their footprints are kept free over that whole sweep. 0 = one pair.

    Returns:
        The layout: road, boxes (current positions and displacements), camera motion, objects.
    """
    rng = np.random.default_rng([seed, 0])
    dt = FRAME_INTERVAL_S

    # Ego-motion: previous camera centre behind the current one along the mean heading.
    speed = rng.uniform(*EGO_SPEED_RANGE_MPS)
    psi = rng.uniform(-MAX_EGO_YAW_RAD, MAX_EGO_YAW_RAD)
    if ego_speed is not None:
        psi *= float(ego_speed) / speed  # same curvature of the path
        speed = float(ego_speed)
    s = speed * dt
    R = yaw_matrix(psi)
    c_prev = np.array([s * math.sin(psi / 2), 0.0, -s * math.cos(psi / 2)])
    t = -R @ c_prev

    extra_lane = rng.random() < 0.35
    park_r = PARKING_LANE_WIDTH_M if rng.random() < 0.75 else 0.0
    park_l = PARKING_LANE_WIDTH_M if rng.random() < 0.6 else 0.0
    lane_r = LANE_WIDTH_M / 2 + (LANE_WIDTH_M if extra_lane else 0.0)
    lane_l = LANE_WIDTH_M * 1.5
    road = RoadLayout(
        angle=rng.uniform(-MAX_ROAD_YAW_RAD, MAX_ROAD_YAW_RAD),
        e_off=rng.uniform(-0.3, 0.3),
        road_left=lane_l + park_l,
        road_right=lane_r + park_r,
        sidewalk_left=rng.uniform(2.0, 4.0),
        sidewalk_right=rng.uniform(2.0, 4.0),
        dash_period=rng.uniform(8.0, 12.0),
        dash_length=rng.uniform(2.5, 4.0),
        dash_phase=rng.uniform(0.0, 12.0),
    )
    road.markings.append((-LANE_WIDTH_M / 2, 0.07, True))  # centre line
    if extra_lane:
        road.markings.append((LANE_WIDTH_M / 2, 0.07, True))
    road.markings.append((lane_r, 0.08, False))  # edge lines towards parking lanes / kerb
    road.markings.append((-lane_l, 0.08, False))
    terr_r = rng.uniform(1.0, 4.0) if rng.random() < 0.6 else 0.0
    terr_l = rng.uniform(1.0, 4.0) if rng.random() < 0.6 else 0.0
    l_end = rng.uniform(65.0, 95.0)
    road.l_max = l_end + 20.0

    b = _Builder(road, ahead_steps)
    h_raised = road.height - KERB_HEIGHT_M

    # Buildings along both sides, with gaps, and a row across the road that ends the view.
    for side in (1, -1):
        kerb = road.road_right if side > 0 else road.road_left
        sw = road.sidewalk_right if side > 0 else road.sidewalk_left
        terr = terr_r if side > 0 else terr_l
        l = rng.uniform(-25.0, -10.0)
        while l < l_end - 5:
            length = rng.uniform(8.0, 25.0)
            if rng.random() < 0.3:
                l += rng.uniform(3.0, 9.0)  # gap between buildings
                continue
            depth = rng.uniform(8.0, 15.0)
            front = kerb + sw + terr + rng.uniform(0.0, 1.5)
            height = rng.uniform(5.0, 16.0)
            length = min(length, l_end - l)
            b.box(side * (front + depth / 2), l + length / 2, h_raised, (depth, height, length), 0.0,
                  BUILDING, STYLE_FACADE)
            l += length
    e = -GROUND_HALF_WIDTH_M
    while e < GROUND_HALF_WIDTH_M:
        width = rng.uniform(10.0, 30.0)
        width = min(width, GROUND_HALF_WIDTH_M - e)
        b.box(e + width / 2, l_end + 6.0, road.height, (width, rng.uniform(6.0, 18.0), 12.0),
              0.0, BUILDING, STYLE_FACADE)
        e += width

    # Poles near the kerbs, sometimes with a sign panel.
    for side in (1, -1):
        kerb = road.road_right if side > 0 else road.road_left
        step = 1.0 / max(density, 1e-3)
        l = rng.uniform(3.0, 15.0)
        while l < l_end - 5 and density > 0:
            ep = side * (kerb + 0.5)
            hp = rng.uniform(4.0, 8.0)
            b.box(ep, l, h_raised, (0.16, hp, 0.16), 0.0, POLE, STYLE_PLAIN)
            if rng.random() < 0.35:
                b.box(ep, l, h_raised - rng.uniform(2.0, 2.6), (0.7, 0.7, 0.06), 0.0, POLE, STYLE_PLAIN)
            b.occupy(ep, l, 0.3, 0.3)
            l += rng.uniform(12.0, 28.0) * step

    # Vegetation: trees (trunk + crown) in the terrain strip or on the sidewalk, hedges.
    for side in (1, -1):
        kerb = road.road_right if side > 0 else road.road_left
        sw = road.sidewalk_right if side > 0 else road.sidewalk_left
        terr = terr_r if side > 0 else terr_l
        et = kerb + sw + terr / 2 if terr > 0 else kerb + sw - 0.8
        l = rng.uniform(4.0, 20.0)
        while l < l_end - 5 and density > 0:
            if rng.random() < 0.7:
                ht, wc, hc = rng.uniform(1.8, 3.0), rng.uniform(2.0, 4.0), rng.uniform(2.0, 3.5)
                b.box(side * et, l, h_raised, (0.3, ht, 0.3), 0.0, VEGETATION, STYLE_PLAIN)
                b.box(side * et, l, h_raised - ht, (wc, hc, wc * rng.uniform(0.8, 1.2)), rng.uniform(0, 1.5),
                      VEGETATION, STYLE_PLAIN)
                b.occupy(side * et, l, 0.4, 0.4)
            elif terr > 0.9:
                lh = rng.uniform(3.0, 10.0)
                b.box(side * et, l, h_raised, (min(0.9, terr - 0.1), rng.uniform(0.8, 1.5), lh), 0.0,
                      VEGETATION, STYLE_PLAIN)
                b.occupy(side * et, l, 0.5, lh / 2)
            l += rng.uniform(8.0, 22.0) / max(density, 1e-3)

    # Moving vehicles first (they must exist), then parked ones around them.
    ego_e = 0.0
    def add_vehicle(e: float, l: float, yaw_rel: float, d_e: float, d_l: float, tries_l: tuple[float, float]) -> bool:
        for _ in range(12):
            parts = _vehicle_parts(rng)
            w, ln = parts[0][0], parts[0][2]
            half_e, half_l = (w / 2, ln / 2) if yaw_rel == 0.0 or abs(yaw_rel) == math.pi else (ln / 2, w / 2)
            if b.free(e, l, half_e, half_l, d_e, d_l):
                b.thing(VEHICLE, e, l, parts, yaw_rel, d_e, d_l)
                b.occupy(e, l, half_e, half_l, d_e, d_l)
                return True
            l = rng.uniform(*tries_l)
        return False

    if density > 0:
        # Preceding vehicle in the ego lane at nearly ego speed (SfM sees almost no parallax).
        n_prec = max(1, _count(rng, 1.0, density))
        for k in range(n_prec):
            v = speed + rng.uniform(-2.0, 2.0)
            lane_e = ego_e if k == 0 or not extra_lane else LANE_WIDTH_M
            rng_l = (7.0, 25.0) if k == 0 else (10.0, 50.0)
            add_vehicle(lane_e + rng.uniform(-0.3, 0.3), rng.uniform(*rng_l), 0.0, 0.0, v * dt, rng_l)
        if extra_lane:
            v = speed + rng.uniform(-4.0, 3.0)
            add_vehicle(LANE_WIDTH_M + rng.uniform(-0.3, 0.3), rng.uniform(6.0, 40.0), 0.0, 0.0, v * dt, (6.0, 40.0))
        # Oncoming vehicles in the opposite lane (parallel to the optical axis: epipolar-conformant).
        n_onc = max(1, _count(rng, 1.5, density))
        for k in range(n_onc):
            v = rng.uniform(7.0, 14.0)
            rng_l = (8.0, 30.0) if k == 0 else (10.0, 60.0)
            add_vehicle(-LANE_WIDTH_M + rng.uniform(-0.3, 0.3), rng.uniform(*rng_l), math.pi, 0.0, -v * dt, rng_l)
        # Crossing traffic: a vehicle or a two-wheeler moving laterally.
        if rng.random() < min(1.0, 0.45 * density):
            lc = rng.uniform(16.0, 40.0)
            v = rng.uniform(3.0, 8.0) * (1 if rng.random() < 0.5 else -1)
            ec = rng.uniform(-road.road_left + 3.0, road.road_right - 3.0)
            if rng.random() < 0.6:
                add_vehicle(ec, lc, math.pi / 2 * np.sign(v), v * dt, 0.0, (16.0, 40.0))
            else:
                parts = _two_wheeler_parts(rng)
                if b.free(ec, lc, 0.9, 0.3, v * dt, 0.0):
                    b.thing(TWO_WHEELER, ec, lc, parts, math.pi / 2 * np.sign(v), v * dt, 0.0)
                    b.occupy(ec, lc, 0.9, 0.3, v * dt, 0.0)
        # A cyclist ahead near the right edge of the ego lane.
        if rng.random() < min(1.0, 0.3 * density):
            v = rng.uniform(3.0, 7.0)
            ec, lc = LANE_WIDTH_M / 2 - 0.6 if not extra_lane else lane_r - 0.6, rng.uniform(8.0, 30.0)
            if b.free(ec, lc, 0.3, 0.9, 0.0, v * dt):
                b.thing(TWO_WHEELER, ec, lc, _two_wheeler_parts(rng), 0.0, 0.0, v * dt)
                b.occupy(ec, lc, 0.3, 0.9, 0.0, v * dt)

        # Parked vehicles in the parking lanes (both directions of facing).
        for side, width in ((1, park_r), (-1, park_l)):
            if width <= 0:
                continue
            ep = side * ((road.road_right if side > 0 else road.road_left) - width / 2)
            l = rng.uniform(3.0, 12.0)
            while l < 62.0:
                parts = _vehicle_parts(rng)
                ln = parts[0][2]
                if rng.random() < min(1.0, 0.75 * density) and b.free(ep, l + ln / 2, parts[0][0] / 2, ln / 2):
                    yaw_rel = 0.0 if side > 0 else (math.pi if rng.random() < 0.5 else 0.0)
                    b.thing(VEHICLE, ep + rng.uniform(-0.15, 0.15), l + ln / 2, parts, yaw_rel, 0.0, 0.0)
                    b.occupy(ep, l + ln / 2, parts[0][0] / 2, ln / 2)
                l += ln + rng.uniform(0.8, 8.0)
        # Parked bicycles on the sidewalk.
        for _ in range(_count(rng, 0.5, density)):
            side = 1 if rng.random() < 0.5 else -1
            kerb = road.road_right if side > 0 else road.road_left
            ec, lc = side * (kerb + 1.2), rng.uniform(6.0, 40.0)
            if b.free(ec, lc, 0.3, 0.9):
                b.thing(TWO_WHEELER, ec, lc, [(0.5, 1.0, 1.7, 0.0, STYLE_PLAIN)], 0.0, 0.0, 0.0)
                b.occupy(ec, lc, 0.3, 0.9)
        # Pedestrians on the sidewalks (some walking) and sometimes one crossing the road.
        for _ in range(max(1, _count(rng, 4.0, density))):
            side = 1 if rng.random() < 0.5 else -1
            kerb = road.road_right if side > 0 else road.road_left
            sw = road.sidewalk_right if side > 0 else road.sidewalk_left
            ec, lc = side * (kerb + rng.uniform(0.5, sw - 0.4)), rng.uniform(5.0, 45.0)
            d_e = d_l = 0.0
            if rng.random() < 0.6:
                d_l = rng.uniform(1.0, 1.8) * dt * (1 if rng.random() < 0.5 else -1)
            if b.free(ec, lc, 0.3, 0.3, d_e, d_l, margin=0.2):
                b.thing(PERSON, ec, lc, _person_parts(rng), 0.0, d_e, d_l)
                b.occupy(ec, lc, 0.3, 0.3, d_e, d_l)
        if rng.random() < min(1.0, 0.25 * density):
            ec, lc = rng.uniform(-road.road_left + 1.0, road.road_right - 1.0), rng.uniform(9.0, 25.0)
            d_e = rng.uniform(1.0, 1.8) * dt * (1 if rng.random() < 0.5 else -1)
            if b.free(ec, lc, 0.3, 0.3, d_e, 0.0, margin=0.2):
                b.thing(PERSON, ec, lc, _person_parts(rng), math.pi / 2, d_e, 0.0)
                b.occupy(ec, lc, 0.3, 0.3, d_e, 0.0)

    return SceneLayout(road=road, boxes=b.finish(), R=R, t=t, objects=b.objects, ego_speed=speed)
