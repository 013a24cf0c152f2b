"""`run`'s pictures against ground truth: stixel boxes in the colour of their depth, the bird's-eye view
at metric positions, movers outlined, degenerate frames labelled."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from matplotlib import colormaps

from monostixels._checks import InputError
from monostixels.output.bev import BevView, bev_image, free_space, stixel_footprints
from monostixels.core.classes import DYNAMIC_OBJECT, GROUND, SKY, STATIC_OBJECT
from monostixels.core.status import FrameStatus
from monostixels.core.stixels import StixelWorld
from monostixels.output.viz import frame_notes, mover_groups, side_by_side, stixel_depth_overlay

# An asymmetric camera (fx != fy, cx, cy off centre), level ground at 1.65 m.
FX, FY, CX, CY, HEIGHT = 100.0, 95.0, 27.0, 18.0, 1.65
H, W, WS = 40, 64, 8
#: Horizontal distance of each column's object stixel (metres): near to far.
DIST = (4.0, 6.0, 9.0, 13.0, 20.0, 30.0, 45.0, 70.0)
LO, HI = 3.0, 80.0


def _world(types: tuple[int, ...] | None = None, motion: torch.Tensor | None = None, flags=None) -> StixelWorld:
    """Per column: ground rows 30-39, an object rows 10-29 at DIST[c] (GROUND in ``types``: more
    ground there instead, up to row 20), sky rows 0-9 (0-19)."""
    C = W // WS
    types = types or (STATIC_OBJECT,) * C
    col, top, bot, typ, cls, p = [], [], [], [], [], []
    for c in range(C):
        rows = ((GROUND, (30, 39), 1 / HEIGHT, 0), (types[c], (10, 29), 1 / DIST[c], 3), (SKY, (0, 9), 0.0, 9))
        if types[c] == GROUND:
            rows = ((GROUND, (20, 39), 1 / HEIGHT, 0), (SKY, (0, 19), 0.0, 9))
        for t, (a, b), pc, k in rows:
            col.append(c), top.append(a), bot.append(b), typ.append(t), p.append(pc)
            cls.append(6 if t == DYNAMIC_OBJECT else k)
    N = len(col)
    L = lambda x: torch.tensor(x, dtype=torch.long)  # noqa: E731
    return StixelWorld(
        column_width=WS, image_size=(H, W),
        K=torch.tensor([[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]], dtype=torch.float64),
        ground_normal=torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
        column=L(col), v_top=L(top), v_bottom=L(bot), type=L(typ), cls=L(cls),
        inverse_depth=torch.tensor(p, dtype=torch.float64),
        motion=torch.zeros(N, 3, dtype=torch.float64) if motion is None else motion,
        cost=torch.zeros(N, dtype=torch.float64), tau=torch.zeros(N, 2, dtype=torch.float64),
        energy=torch.zeros(C, dtype=torch.float64), status=FrameStatus.from_flags(flags or {}),
    )


def _jet_of_depth(z: float) -> np.ndarray:
    """The depth colour of docs/conventions.md, section 2, computed here independently: inverse
    depth, jet, 3..80 m."""
    x = np.clip((1 / z - 1 / HI) / (1 / LO - 1 / HI), 0.0, 1.0)
    return np.asarray(colormaps["jet"](x)[:3]) * 255.0


def _column_dir(c: int) -> np.ndarray:
    """Horizontal viewing direction of column c's centre (level ground: the ray with y = 0)."""
    uc = c * WS + (WS - 1) / 2
    d = np.array([(uc - CX) / FX, 0.0, 1.0])
    return d / np.linalg.norm(d)


def _object_z(c: int, u: float, v: float) -> float:
    """Depth z of pixel (u, v) on column c's object plane n^T X = DIST[c]."""
    n, ray = _column_dir(c), np.array([(u - CX) / FX, (v - CY) / FY, 1.0])
    return DIST[c] / float(n @ ray)


GREY = 0.5  # the image: uniform grey, so a blend is checkable


def test_each_stixel_box_has_the_colour_of_its_depth():
    img = torch.full((3, H, W), GREY)
    alpha, ground_alpha = 0.5, 0.3
    out = stixel_depth_overlay(img, _world(), min_depth=LO, max_depth=HI, alpha=alpha, ground_alpha=ground_alpha,
                               legend=False).astype(float)
    grey = round(GREY * 255)
    reds = []
    for c in range(W // WS):
        uc = c * WS + (WS - 1) / 2
        want = _jet_of_depth(_object_z(c, uc, 29))  # a stixel's depth: at its bottom-centre pixel
        for v, u in ((15, c * WS + 3), (20, c * WS + 4), (28, c * WS + 5)):  # inside the box
            assert np.abs(out[v, u] - ((1 - alpha) * grey + alpha * want)).max() <= 1.0, (c, v, u)
        # Its border (top row) is a darker shade of the same colour, opaque.
        assert np.abs(out[10, c * WS + 4] - 0.5 * want).max() <= 1.0
        reds.append(out[20, c * WS + 4, 0] - out[20, c * WS + 4, 2])
    assert reds[0] > 0 > reds[-1]  # near red ... far blue
    # Ground: a translucent tint of each pixel's own depth (level ground: z = h fy / (v - cy)).
    for v in (31, 36):
        want = _jet_of_depth(HEIGHT * FY / (v - CY))
        assert np.abs(out[v, 12] - ((1 - ground_alpha) * grey + ground_alpha * want)).max() <= 1.0
    assert (out[3:8, :] == grey).all()  # sky untouched


def test_overlay_checks_its_inputs():
    with pytest.raises(InputError, match="image_size"):
        stixel_depth_overlay(torch.zeros(3, H, W + 1), _world())
    with pytest.raises(InputError, match="alpha"):
        stixel_depth_overlay(torch.zeros(3, H, W), _world(), alpha=1.5)


def test_legend_shows_the_depth_scale():
    # A KITTI-size picture gets the scale (near red ... far dark blue) top right; the tiny one above does not.
    big = _world()
    big.image_size, big.column_width = (375, 1242), 1242 // 8 + 1
    img = torch.full((3, 375, 1242), GREY)
    with_legend = stixel_depth_overlay(img, big, min_depth=LO, max_depth=HI)
    plain = stixel_depth_overlay(img, big, min_depth=LO, max_depth=HI, legend=False)
    corner = with_legend[:80, -360:].reshape(-1, 3).astype(int)
    assert (with_legend != plain)[:80, -360:].any() and (with_legend == plain)[100:].all()
    dark_red, dark_blue = np.array([128, 0, 0]), np.array([0, 0, 128])
    assert (np.abs(corner - dark_red).max(1) <= 2).any() and (np.abs(corner - dark_blue).max(1) <= 2).any()


def test_movers_are_grouped_outlined_and_get_a_motion_arrow():
    types = (1, 1, 2, 2, 1, 2, 1, 1)  # a two-column mover and a one-column one
    N = 3 * len(types)
    motion = torch.zeros(N, 3, dtype=torch.float64)
    motion[3 * 2 + 1] = motion[3 * 3 + 1] = torch.tensor([0.3, 0.0, 0.0])  # to the right, 0.3 m per frame
    world = _world(types, motion)
    groups = mover_groups(world)
    assert [sorted(g.tolist()) for g in groups] == [[7, 10], [16]]
    img = torch.full((3, H, W), GREY)
    out = stixel_depth_overlay(img, world, min_depth=LO, max_depth=HI, legend=False)
    white = (out >= 250).all(-1)
    assert white[8:32, 14:34].any() and white[8:32, 38:50].any()  # outlines around both movers
    none = stixel_depth_overlay(img, world, min_depth=LO, max_depth=HI, legend=False, moving=np.zeros(N, bool))
    assert not (none >= 250).all(-1).any()
    # On a wide image: the right-moving group's arrow runs right from its bottom centre; still, it is a dot.
    moved, still = _world(types, motion), _world(types)
    for w in (moved, still):
        w.image_size, w.column_width = (H, 1242), 156
    big = torch.full((3, H, 1242), GREY)
    diff = (stixel_depth_overlay(big, moved, legend=False) != stixel_depth_overlay(big, still, legend=False)).any(-1)
    base_u = 2 * 156 + 155.5  # bottom centre of the group (columns 2-3)
    cols = np.flatnonzero(diff.any(0))
    assert cols.min() > base_u - 12 and cols.max() > base_u + 30
    # A one-column mover gets its outline, no arrow.
    sliver = motion.clone()
    sliver[3 * 5 + 1] = torch.tensor([0.3, 0.0, 0.0])
    lone = _world(types, sliver)
    lone.image_size, lone.column_width = (H, 1242), 156
    assert (stixel_depth_overlay(big, lone, legend=False) == stixel_depth_overlay(big, moved, legend=False)).all()
    with pytest.raises(InputError, match="moving"):
        mover_groups(world, np.zeros(3, bool))


def test_degenerate_frames_are_labelled():
    standing = {"degenerate_motion": True, "reason": "camera translation 0.000 m < solver.min_translation 0.05 m: ..."}
    failed = {"degenerate_motion": True, "reason": "too few ground vectors; camera translation 0.000 m < ..."}
    assert frame_notes(_world(flags=standing)) == ["camera standing: depths from the scene model"]
    assert frame_notes(_world(flags={**standing, "reason": "no translation (standing still): ..."})) == \
        ["camera standing: depths from the scene model"]
    assert frame_notes(_world(flags=failed)) == ["no camera motion estimate: depths from the scene model"]
    assert frame_notes(_world()) == []
    img = torch.full((3, 375, 1242), GREY)
    big = _world(flags=standing)
    big.image_size, big.column_width = (375, 1242), 156
    plain = _world()
    plain.image_size, plain.column_width = (375, 1242), 156
    a = stixel_depth_overlay(img, big, legend=False)
    b = stixel_depth_overlay(img, plain, legend=False)
    assert (a != b)[:40, :400].any() and (a == b)[60:].all()  # the label, top left
    yellow = (a[:40, :400, 0] > 200) & (a[:40, :400, 1] > 180) & (a[:40, :400, 2] < 80)
    assert yellow.any()
    assert (bev_image(_world(flags=standing)) != bev_image(_world())).any()


def test_footprints_are_at_the_metric_position_of_each_stixel():
    foot = stixel_footprints(_world())
    for c in range(W // WS):
        i = 3 * c + 1  # the object stixel of column c
        n = _column_dir(c)
        for j, u in enumerate((c * WS - 0.5, min(c * WS + WS, W) - 0.5)):
            e = np.array([(u - CX) / FX, 0.0, 1.0])
            e /= np.linalg.norm(e)
            X = DIST[c] / float(n @ e) * e  # on the stixel's plane, on the column edge's ray
            assert foot[i, j] == pytest.approx(X[[0, 2]], abs=1e-9)
        assert np.hypot(*foot[i].mean(0)) == pytest.approx(DIST[c], rel=1e-3)
    assert np.isnan(foot[0::3]).all() and np.isnan(foot[2::3]).all()  # ground and sky have none
    np.testing.assert_allclose(free_space(_world()), DIST)  # free up to each column's object


def test_bev_draws_each_stixel_at_its_metric_position():
    view = BevView(forward_m=80.0, lateral_m=40.0, px_per_m=10.0)
    # Objects in every second column, ground only between them (free to its top row: 1.65 m x fy / 2 rows).
    types = (STATIC_OBJECT, GROUND) * (W // WS // 2)
    world = _world(types)
    bev = bev_image(world, view, min_depth=LO, max_depth=HI).astype(float)
    foot = stixel_footprints(world)
    depth = world.depth.numpy()
    start = np.cumsum([0] + [2 if t == GROUND else 3 for t in types])
    for c in (0, 2, 4, 6):
        i = int(start[c]) + 1  # the object stixel of column c
        centre = foot[i].mean(0)
        col, row = np.round(view.to_pixel(*centre)).astype(int)
        assert np.abs(bev[row, col] - _jet_of_depth(float(depth[i]))).max() <= 2.0, c
        # Free space (light) 3 m nearer along the column's direction, none (dark) 3 m beyond.
        d = centre / np.linalg.norm(centre)
        for off, free in ((-3.0, True), (3.0, False)):
            cc, rr = np.round(view.to_pixel(*(centre + off * d))).astype(int)
            if 0 <= rr < bev.shape[0] and 0 <= cc < bev.shape[1]:
                assert (bev[rr, cc] > 190).all() if free else (bev[rr, cc] < 120).all(), (c, off, bev[rr, cc])
    # Outside the field of view (behind the image's left edge) nothing is seen.
    assert (bev[5, 2] < 60).all()


def test_bev_view_checks_and_figure_layout():
    with pytest.raises(InputError, match="px_per_m"):
        BevView(px_per_m=0.0)
    view = BevView(forward_m=30.0, lateral_m=10.0, px_per_m=5.0)
    assert view.size == (150, 100)
    assert view.to_pixel(0.0, 0.0) == pytest.approx([49.5, 149.5])
    assert view.to_pixel(-10.0, 30.0) == pytest.approx([-0.5, -0.5])
    left, right = np.zeros((40, 64, 3), np.uint8), np.full((150, 100, 3), 7, np.uint8)
    fig = side_by_side(left, right, gap=4)
    assert fig.shape == (40, 64 + 4 + round(100 * 40 / 150), 3) and (fig[:, 70:] == 7).all()
    assert math.isfinite(float(fig.mean()))
