"""Colour maps, stixel overlays, figures, and the image / depth PNG / PLY readers and writers."""
from __future__ import annotations

import math
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

from monostixels._checks import InputError
from monostixels.core.classes import PALETTE, TYPE_PALETTE
from monostixels.core.geometry import intrinsics
from monostixels.data._readers import read_rgb
from monostixels.output.io import (
    KITTI_DEPTH_PNG_SCALE,
    depth_to_points,
    read_depth_png16,
    read_ply,
    write_depth_png16,
    write_image,
    write_ply,
)
from monostixels.output.viz import depth_colormap, flow_colormap, paper_figure, semantic_colormap, stixel_overlay


# ---------------------------------------------------------------- colour maps

def test_depth_colormap_close_red_far_dark_blue_invalid_black():
    depth = torch.tensor([[4.0, 60.0, 0.0, -3.0, math.nan, math.inf, 1.0, 500.0]])
    rgb = depth_colormap(depth, min_depth=4.0, max_depth=60.0)
    assert rgb.shape == (1, 8, 3) and rgb.dtype == np.uint8
    assert tuple(rgb[0, 0]) == (128, 0, 0)  # jet(1): dark red, closest
    assert tuple(rgb[0, 1]) == (0, 0, 128)  # jet(0): dark blue, farthest
    for i in (2, 3, 4, 5):  # 0 (no gt), negative, NaN, inf: black
        assert tuple(rgb[0, i]) == (0, 0, 0)
    assert tuple(rgb[0, 6]) == (128, 0, 0)  # closer than min_depth saturates to red
    assert tuple(rgb[0, 7]) == (0, 0, 128)  # farther than max_depth saturates to dark blue


def test_depth_colormap_is_linear_in_inverse_depth():
    lo, hi = 5.0, 80.0
    harmonic_mid = 2.0 / (1.0 / lo + 1.0 / hi)  # inverse depth half-way: jet(0.5), green
    arithmetic_mid = 0.5 * (lo + hi)  # far in inverse depth: bluish
    rgb = depth_colormap(np.array([[harmonic_mid, arithmetic_mid]]), min_depth=lo, max_depth=hi)
    r, g, b = (int(c) for c in rgb[0, 0])
    assert g > 200 and r < 160 and b < 160
    r2, g2, b2 = (int(c) for c in rgb[0, 1])
    assert r2 == 0 and g2 == 0 and b2 > 150  # linear in depth would give jet(0.5): green


def test_semantic_colormap_palette_and_ignore():
    lab = torch.tensor([[0, 6, 9], [255, 3, 12]])
    rgb = semantic_colormap(lab)
    assert tuple(rgb[0, 0]) == PALETTE[0]
    assert tuple(rgb[0, 1]) == PALETTE[6]
    assert tuple(rgb[0, 2]) == PALETTE[9]
    assert tuple(rgb[1, 0]) == (0, 0, 0) and tuple(rgb[1, 2]) == (0, 0, 0)
    assert tuple(rgb[1, 1]) == PALETTE[3]


def test_flow_colormap_middlebury_directions():
    # right, left, up, down at full magnitude; zero flow; NaN.
    fu = torch.tensor([[4.0, -4.0, 0.0, 0.0, 0.0, math.nan]])
    fv = torch.tensor([[0.0, 0.0, -4.0, 4.0, 0.0, 0.0]])
    rgb = flow_colormap(torch.stack([fu, fv]), max_flow=4.0).astype(int)
    right, left, up, down, zero, nan = (rgb[0, i] for i in range(6))
    assert right[0] == 255 and right[1] < 30  # red
    assert left[0] < 30 and left[1] > 150 and left[2] > 200  # cyan-blue
    assert up[2] > 200 and up[1] < 30  # blue-magenta
    assert down[0] > 200 and down[1] > 100 and down[2] < 30  # orange-yellow
    assert tuple(zero) == (255, 255, 255)  # no motion: white
    assert tuple(nan) == (0, 0, 0)


# ---------------------------------------------------------------- overlay

def _tiny_world():
    # H = 6, W = 7, w = 3: columns u 0..2, 3..5 and 6 (the last one narrower).
    return SimpleNamespace(
        column_width=3,
        image_size=(6, 7),
        column=torch.tensor([0, 0, 2]),
        v_top=torch.tensor([4, 1, 0]),
        v_bottom=torch.tensor([5, 3, 5]),
        type=torch.tensor([0, 2, 3]),
        cls=torch.tensor([0, 6, 9]),
        inverse_depth=torch.tensor([1 / 1.65, 1 / 10.0, 0.0]),
        depth=torch.tensor([8.0, 10.0, math.inf]),
    )


def test_stixel_overlay_fill_border_and_uncovered():
    img = torch.ones(3, 6, 7)  # white
    out = stixel_overlay(img, _tiny_world(), mode="type", alpha=0.5).astype(int)
    dyn = np.array(TYPE_PALETTE[2])
    ground = np.array(TYPE_PALETTE[0])
    # Interior of the dynamic stixel (rows 2..3, u 1..2; the ground below draws the boundary):
    # half white, half colour.
    for v, u in ((2, 1), (2, 2), (3, 2)):
        assert np.abs(out[v, u] - (0.5 * 255 + 0.5 * dyn)).max() <= 1
    # Its border (top row 1, left u = 0): darker colour, opaque.
    for v, u in ((1, 1), (1, 2), (2, 0), (3, 0)):
        assert np.abs(out[v, u] - 0.5 * dyn).max() <= 1
    # The ground below: top row 4 and last row 5 (nothing below) are border.
    for v, u in ((4, 1), (5, 2)):
        assert np.abs(out[v, u] - 0.5 * ground).max() <= 1
    # Uncovered: row 0 of column 0 and the whole middle column stay white.
    assert (out[0, 0] == 255).all() and (out[:, 3:6] == 255).all()
    # Column 2 covers only u = 6: sky colour there.
    sky = np.array(TYPE_PALETTE[3])
    assert np.abs(out[2, 6] - 0.5 * sky).max() <= 1  # left border of a 1-px column


def test_stixel_overlay_merges_equal_neighbours_only():
    # Two columns of width 2, one stixel each, rows 0..3 of a 5 x 4 image.
    def world(types):
        return SimpleNamespace(
            column_width=2, image_size=(5, 4), column=torch.tensor([0, 1]), v_top=torch.tensor([0, 0]),
            v_bottom=torch.tensor([3, 3]), type=torch.tensor(types), cls=torch.tensor([0, 0]),
            inverse_depth=torch.tensor([0.1, 0.1]), depth=torch.tensor([10.0, 10.0]),
        )

    img = torch.ones(3, 5, 4)
    same = stixel_overlay(img, world([1, 1]), mode="type", alpha=0.5).astype(int)
    diff = stixel_overlay(img, world([1, 2]), mode="type", alpha=0.5).astype(int)
    static, dyn = np.array(TYPE_PALETTE[1]), np.array(TYPE_PALETTE[2])
    assert np.abs(same[1, 2] - (0.5 * 255 + 0.5 * static)).max() <= 1  # merged: no border at u = 2
    assert np.abs(diff[1, 2] - 0.5 * dyn).max() <= 1  # colour change: border at u = 2
    assert (same[4] == 255).all()  # row 4 uncovered


def test_stixel_overlay_class_and_depth_modes():
    img = torch.zeros(3, 6, 7)  # black: the blend is alpha * colour
    world = _tiny_world()
    cls = stixel_overlay(img, world, mode="class", alpha=1.0)
    assert tuple(cls[2, 1]) == PALETTE[6]
    dep = stixel_overlay(img, world, mode="depth", alpha=1.0, min_depth=5.0, max_depth=80.0)
    expect = depth_colormap(np.array([[10.0]]), min_depth=5.0, max_depth=80.0)[0, 0]
    assert tuple(dep[2, 1]) == tuple(expect)
    assert tuple(dep[2, 6]) == (0, 0, 0)  # sky (inf depth): black
    with pytest.raises(InputError, match="mode"):
        stixel_overlay(img, world, mode="height")
    with pytest.raises(InputError, match="image_size"):
        stixel_overlay(torch.zeros(3, 6, 8), world)


def test_paper_figure_layout(tmp_path):
    red = np.zeros((30, 50, 3), np.uint8)
    red[..., 0] = 255
    blue = np.zeros((30, 50, 3), np.uint8)
    blue[..., 2] = 255
    path = paper_figure([("Ground Truth", red), ("Mono-Stixels", blue)], tmp_path / "fig" / "f.png", ncols=2, dpi=50)
    img = (read_rgb(path).numpy().transpose(1, 2, 0) * 255).round().astype(int)
    is_red = (img[..., 0] == 255) & (img[..., 1] == 0) & (img[..., 2] == 0)
    is_blue = (img[..., 0] == 0) & (img[..., 1] == 0) & (img[..., 2] == 255)
    assert is_red.sum() > 100 and is_blue.sum() > 100
    # Panels side by side, in order: red left of blue, same rows.
    assert np.nonzero(is_red)[1].max() < np.nonzero(is_blue)[1].min()


# ---------------------------------------------------------------- io

def test_write_read_image_roundtrip_and_channel_order(tmp_path):
    rgb = np.zeros((4, 5, 3), np.uint8)
    rgb[..., 0] = 200  # red
    rgb[1, 2] = (10, 20, 30)
    p = write_image(tmp_path / "a" / "b" / "img.png", rgb)
    assert tuple(cv2.imread(str(p))[0, 0]) == (0, 0, 200)  # on disk: BGR
    back = read_rgb(p)
    assert back.shape == (3, 4, 5) and back.dtype == torch.float32
    assert np.array_equal((back.numpy().transpose(1, 2, 0) * 255).round().astype(np.uint8), rgb)


def test_image_errors_name_the_file(tmp_path):
    missing = tmp_path / "nope.png"
    with pytest.raises(InputError, match="nope.png"):
        read_rgb(missing)
    junk = tmp_path / "junk.png"
    junk.write_text("not an image")
    with pytest.raises(InputError, match="junk.png"):
        read_rgb(junk)
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(InputError, match="out.png"):
        write_image(blocker / "out.png", np.zeros((2, 2, 3), np.uint8))


def test_depth_png16_roundtrip_kitti_encoding(tmp_path):
    depth = torch.tensor([[1.0, 12.3456, 0.0], [-2.0, math.nan, 80.0]])
    p = write_depth_png16(tmp_path / "d.png", depth)
    raw = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    assert raw[0, 0] == 256 and raw[0, 1] == round(12.3456 * KITTI_DEPTH_PNG_SCALE) and raw[1, 2] == 80 * 256
    assert raw[0, 2] == 0 and raw[1, 0] == 0 and raw[1, 1] == 0  # invalid -> 0
    back = read_depth_png16(p)
    assert abs(float(back[0, 1]) - 12.3456) <= 0.5 / KITTI_DEPTH_PNG_SCALE
    assert float(back[1, 2]) == 80.0 and float(back[1, 0]) == 0.0


def test_depth_to_points_back_projection_asymmetric_K():
    K = intrinsics(fx=100.0, fy=120.0, cx=2.5, cy=1.0)
    depth = torch.tensor([[10.0, 0.0, 20.0], [5.0, -1.0, math.inf]])
    image = torch.zeros(3, 2, 3)
    image[:, 0, 2] = torch.tensor([1.0, 0.5, 0.0])
    pts, cols = depth_to_points(depth, K, image)
    assert pts.shape == (3, 3) and cols.dtype == np.uint8
    # Row-major valid pixels: (v=0,u=0), (0,2), (1,0).
    expected = np.array([
        [10 * (0 - 2.5) / 100, 10 * (0 - 1.0) / 120, 10],
        [20 * (2 - 2.5) / 100, 20 * (0 - 1.0) / 120, 20],
        [5 * (0 - 2.5) / 100, 5 * (1 - 1.0) / 120, 5],
    ])
    assert np.allclose(pts, expected, atol=1e-5)
    assert tuple(cols[1]) == (255, 128, 0)
    assert len(depth_to_points(depth, K, image, max_depth=15.0)[0]) == 2


def test_ply_roundtrip_and_header(tmp_path):
    g = np.random.default_rng(0)
    pts = g.normal(size=(17, 3)).astype(np.float32) * 10
    cols = g.integers(0, 256, size=(17, 3), dtype=np.uint8)
    p = write_ply(tmp_path / "c.ply", pts, cols)
    data = p.read_bytes()
    header = data[: data.index(b"end_header\n") + len(b"end_header\n")].decode()
    lines = header.splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    props = [l for l in lines if l.startswith("property")]
    assert props == [
        "property float x", "property float y", "property float z",
        "property uchar red", "property uchar green", "property uchar blue",
    ]
    assert "element vertex 17" in lines
    assert len(data) == len(header) + 17 * (3 * 4 + 3)
    # The first vertex as raw little-endian bytes.
    assert np.frombuffer(data, "<f4", 3, len(header)).tolist() == pts[0].tolist()
    p2, c2 = read_ply(p)
    assert np.array_equal(p2, pts) and np.array_equal(c2, cols)
    with pytest.raises(InputError, match="colors"):
        write_ply(tmp_path / "bad.ply", pts, cols.astype(np.float32))
