"""Built-in synthetic street-scene benchmark (docs/conventions.md, section 6).

A seeded renderer of textured street scenes by vectorised torch ray casting against analytic
primitives: the ground (road plane, raised sidewalk/terrain plane at kerb height, vertical kerb
faces), oriented boxes (buildings, poles, vegetation, vehicles, two-wheelers, persons; yawed about
the vertical) and the sky at infinity. Every surface carries a procedural texture fixed to the
surface (multi-octave value noise in the primitive's local coordinates plus per-class patterns:
lane markings, paving, windows, clothes) with Lambert shading, so real optical-flow methods work.

Conventions (docs/conventions.md, section 2), restated where they are used:

- camera frame x right, y down, z forward; the *current* camera frame is the world frame;
- pixel centres at integer coordinates ``(u, v)``; ``x = (u, v, 1)``;
- camera motion ``X_prev = R X_cur + t`` for static points (forward driving: ``t_z > 0``);
- a moving object displaced by ``Δ`` (world = current-camera coordinates, on the ground plane)
  between the previous and the current frame: ``X_prev = R (X_cur - Δ) + t``;
- flow maps current to previous pixels: ``x_prev = x + f(x)``.

Ground truth per pair: depth (z in the current camera, metres, 0 on sky), flow and its validity
(``x_prev`` inside the previous image and the previous frame's ray cast sees the same face of the
same primitive at the same depth at the pixels around ``x_prev``; see :func:`_flow_validity`),
10-class labels, instance ids, moving mask, camera motion and intrinsics.

Photometric consistency: a surface point has the same colour in both frames (texture in the
primitive's own coordinates, Lambert shading with a fixed sun, texture level of detail chosen from
the point's current-frame position), so warping the previous image by the ground-truth flow
reproduces the current image up to bilinear interpolation (tests/test_synthetic.py states the
bound). Sky colour depends on the world direction only; sky pixels carry the rotation-only flow
``K R K^-1`` but are not flow_valid (no depth).

Speed: about 0.5 s of CPU time per 1242 x 375 pair with ground truth (one torch thread), see
``benchmarks/render_speed.py``.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Iterator

import numpy as np
import torch

from monostixels._checks import InputError
from monostixels.data._scene import (
    FRAME_INTERVAL_S,
    BUILDING, KERB_HEIGHT_M, PERSON, POLE, ROAD, SIDEWALK, SKY, STYLE_CLOTHES, STYLE_FACADE,
    STYLE_GLASS, TERRAIN, TWO_WHEELER, VEGETATION, VEHICLE, RoadLayout, SceneLayout, sample_scene,
)
from monostixels.data.base import FramePair, GroundTruth, PreviousFrame
from monostixels.geometry import KITTI_CAMERA_HEIGHT_M, Camera, Motion, intrinsics

__all__ = [
    "KITTI_IMAGE_SIZE",
    "KITTI_INTRINSICS",
    "render_pair",
    "synthetic_camera",
    "SyntheticSource",
    "SyntheticSequence",
    "SyntheticSequenceSource",
]

logger = logging.getLogger(__name__)

#: Full-resolution image size (H, W) in pixels (KITTI colour camera, rectified).
KITTI_IMAGE_SIZE = (375, 1242)
#: KITTI intrinsics (fx, fy, cx, cy) in pixels at full resolution (P_rect_02 of KITTI raw 2011_09_26).
KITTI_INTRINSICS = (721.5377, 721.5377, 609.5593, 172.854)
#: Scene seed of frame i of source seed s is ``s * SOURCE_SEED_STRIDE + i`` (common brief).
SOURCE_SEED_STRIDE = 100_000

#: Rays closer than this are ignored (metres) — avoids self-hits at the ray origin.
_T_EPS = 1e-4
#: Near plane used to bound a box's screen rectangle (metres).
_Z_NEAR = 0.05
#: A flow vector is valid when the previous camera's first hit through ``x_prev`` is the same
#: primitive at the same depth within this relative tolerance.
_FLOW_VALID_REL_TOL = 1e-3
#: Octaves of the surface texture: wavelengths (metres; each divides the tile) and amplitudes.
_TEXTURE_TILE_M = 20.48
_TEXTURE_TEXELS = 1024
_TEXTURE_TEXEL_M = _TEXTURE_TILE_M / _TEXTURE_TEXELS
_OCTAVE_PERIODS_M = tuple(_TEXTURE_TILE_M / n for n in (256, 96, 40, 16, 6))
_OCTAVE_AMPLITUDES = (0.55, 0.7, 0.8, 0.8, 0.9)
#: Seed of the (fixed) noise texture; scenes differ by offsets, octave weights and colours.
_TEXTURE_SEED = 20180521
#: Octaves finer than this many pixels at the surface point fade to their mean (mip-map-like
#: anti-aliasing; the footprint is computed from the current-frame position only, so the texture
#: stays fixed to the surface in both frames).
_OCTAVE_MIN_PIXELS = 2.0
#: Width of the anti-aliasing ramp of pattern edges (pixels); > 1 keeps bilinear warping exact-ish.
_EDGE_RAMP_PIXELS = 1.5
#: Smallest |cos(incidence)| used in the texture footprint (grazing ground).
_MIN_COS_INCIDENCE = 0.15

# Ground-piece primitive ids; boxes follow from _N_GROUND on, -1 = sky.
_PID_ROAD, _PID_RAISED, _PID_KERB_R, _PID_KERB_L = range(4)
_N_GROUND = 4


# ----------------------------------------------------------------------------------------------
# Texture
# ----------------------------------------------------------------------------------------------
_TEXTURE_CACHE: dict[str, torch.Tensor] = {}


def _noise_texture() -> torch.Tensor:
    """Periodic band-limited noise, one channel per octave: (1, O, T + 1, T + 1) float32 in ~[0, 1].

    Channel ``k`` has its energy around the wavelength ``_OCTAVE_PERIODS_M[k]``; the tile covers
    ``_TEXTURE_TILE_M`` metres and wraps (the extra last row/column repeats the first, so bilinear
    lookups of ``coordinate mod T`` are seamless). Built once from a fixed seed (FFT synthesis);
    scenes differ by per-surface offsets, octave weights and colours.
    """
    tex = _TEXTURE_CACHE.get("noise")
    if tex is not None:
        return tex
    gen = torch.Generator().manual_seed(_TEXTURE_SEED)
    T = _TEXTURE_TEXELS
    ky = torch.fft.fftfreq(T, d=1.0 / T)[:, None]  # cycles per tile
    kx = torch.fft.rfftfreq(T, d=1.0 / T)[None, :]
    k = torch.sqrt(kx * kx + ky * ky)
    chans = []
    for P in _OCTAVE_PERIODS_M:
        k0 = _TEXTURE_TILE_M / P
        amp = torch.exp(-(((k - k0) / (0.45 * k0)) ** 2))
        spec = torch.complex(torch.randn(k.shape, generator=gen), torch.randn(k.shape, generator=gen)) * amp
        img = torch.fft.irfft2(spec, s=(T, T))
        img = (img - img.mean()) / img.std()
        chans.append((0.5 + 0.2 * img).clamp(0, 1))
    tex = torch.stack(chans, 0)
    tex = torch.cat([tex, tex[:, :1]], 1)
    tex = torch.cat([tex, tex[:, :, :1]], 2)[None].float().contiguous()
    _TEXTURE_CACHE["noise"] = tex
    return tex


def _sample_texture(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Octave values (O, N) at surface coordinates ``a``, ``b`` (N,) metres (periodic tile)."""
    tex = _noise_texture()
    T = _TEXTURE_TEXELS
    ta = torch.remainder(a / _TEXTURE_TEXEL_M, T)
    tb = torch.remainder(b / _TEXTURE_TEXEL_M, T)
    # align_corners=True: texel i sits at -1 + 2 i / T over the T + 1 texels.
    grid = torch.stack([ta * (2.0 / T) - 1.0, tb * (2.0 / T) - 1.0], -1)[None, None]
    out = torch.nn.functional.grid_sample(tex, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out[0, :, 0]


# ----------------------------------------------------------------------------------------------
# Appearance
# ----------------------------------------------------------------------------------------------
@dataclass
class _Appearance:
    """Colours, lighting and texture parameters, indexed by material (independent of geometry).

    Materials: 0 road, 1 sidewalk, 2 terrain, 3 kerb, 4 + b box b.
    """

    sun: torch.Tensor          # (3,) unit vector towards the sun (world)
    ambient: float
    diffuse: float
    gain: float
    gamma: float
    octave_amp: torch.Tensor   # (O,) octave amplitudes
    rgb: torch.Tensor          # (M, 3) albedo per material
    rgb2: torch.Tensor         # (M, 3) second colour (windows, glass, trousers, dirt)
    amp: torch.Tensor          # (M,) texture contrast per material
    off: torch.Tensor          # (M, 2) texture offsets (metres)
    facade: torch.Tensor       # (M, 4) window period a, period b (metres), fraction a, fraction b
    marking_rgb: torch.Tensor  # (3,)
    sky_rgb: torch.Tensor      # (3, 3): horizon, zenith, clouds


def _hsv(rng: np.random.Generator, h: tuple[float, float], s: tuple[float, float], v: tuple[float, float]) -> list[float]:
    import colorsys
    return list(colorsys.hsv_to_rgb(rng.uniform(*h) % 1.0, rng.uniform(*s), rng.uniform(*v)))


def _class_colour(rng: np.random.Generator, cls: int, wide: bool) -> tuple[list[float], list[float]]:
    """Albedo and second colour of a box of class ``cls``; ``wide`` randomises hues freely."""
    if wide:
        return _hsv(rng, (0, 1), (0.0, 0.8), (0.2, 0.9)), _hsv(rng, (0, 1), (0.0, 0.8), (0.05, 0.6))
    if cls == BUILDING:
        choice = rng.integers(3)
        base = [_hsv(rng, (0.02, 0.08), (0.4, 0.65), (0.45, 0.7)),   # brick
                _hsv(rng, (0.08, 0.15), (0.15, 0.35), (0.6, 0.85)),  # plaster
                _hsv(rng, (0.0, 1.0), (0.0, 0.08), (0.4, 0.75))][choice]  # concrete
        return base, _hsv(rng, (0.55, 0.65), (0.1, 0.35), (0.1, 0.3))
    if cls == POLE:
        return _hsv(rng, (0, 1), (0, 0.1), (0.35, 0.65)), [0.3, 0.3, 0.3]
    if cls == VEGETATION:
        return _hsv(rng, (0.2, 0.33), (0.45, 0.8), (0.25, 0.5)), [0.2, 0.15, 0.1]
    if cls == VEHICLE:
        if rng.random() < 0.5:
            body = _hsv(rng, (0, 1), (0, 0.1), (0.1, 0.9))
        else:
            body = _hsv(rng, (0, 1), (0.5, 0.9), (0.3, 0.8))
        return body, _hsv(rng, (0.5, 0.65), (0.1, 0.3), (0.08, 0.2))
    if cls == TWO_WHEELER:
        return _hsv(rng, (0, 1), (0.2, 0.8), (0.15, 0.6)), _hsv(rng, (0, 1), (0.2, 0.8), (0.2, 0.7))
    if cls == PERSON:
        return _hsv(rng, (0, 1), (0.2, 0.8), (0.3, 0.85)), _hsv(rng, (0.55, 0.7), (0.2, 0.6), (0.1, 0.4))
    return [0.5, 0.5, 0.5], [0.3, 0.3, 0.3]


#: Texture contrast per class (vegetation and terrain busy, vehicles smooth-ish).
_CLASS_TEXTURE_AMP = {ROAD: 1.0, SIDEWALK: 0.9, TERRAIN: 1.4, BUILDING: 1.0, POLE: 0.8, VEGETATION: 1.7,
                      VEHICLE: 0.7, TWO_WHEELER: 0.9, PERSON: 0.9}


def _sample_appearance(layout: SceneLayout, seed: int, randomise: bool) -> _Appearance:
    """Appearance from its own random stream (``[seed, 1]``), independent of the geometry.

    Args:
        layout: the scene (only the number and classes of boxes are read).
        seed: appearance seed.
        randomise: domain randomisation (wide colours, contrast, lighting, gamma).
    """
    rng = np.random.default_rng([seed, 1])
    az = rng.uniform(-math.pi, math.pi)
    el = rng.uniform(math.radians(25), math.radians(65)) if not randomise else rng.uniform(math.radians(10), math.radians(85))
    sun = torch.tensor([math.cos(el) * math.sin(az), -math.sin(el), math.cos(el) * math.cos(az)], dtype=torch.float32)
    if randomise:
        ground = [_hsv(rng, (0, 1), (0, 0.5), (0.15, 0.7)) for _ in range(4)]
        ground2 = [_hsv(rng, (0, 1), (0, 0.6), (0.1, 0.7)) for _ in range(4)]
        marking = _hsv(rng, (0, 1), (0, 0.6), (0.6, 1.0))
        sky = [_hsv(rng, (0, 1), (0, 0.5), (0.5, 1.0)), _hsv(rng, (0, 1), (0, 0.8), (0.3, 1.0)), [0.95, 0.95, 0.95]]
        octave_amp = rng.uniform(0.2, 1.0, len(_OCTAVE_PERIODS_M))
    else:
        paving = _hsv(rng, (0.05, 0.12), (0.05, 0.2), (0.55, 0.72))
        ground = [_hsv(rng, (0.55, 0.7), (0.0, 0.08), (0.3, 0.42)),   # asphalt
                  paving,
                  _hsv(rng, (0.18, 0.3), (0.35, 0.6), (0.35, 0.5)),  # grass
                  [min(1.0, c * 1.1) for c in paving]]               # kerb stone
        ground2 = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], _hsv(rng, (0.06, 0.11), (0.3, 0.5), (0.3, 0.45)), [0.0, 0.0, 0.0]]
        marking = [0.9, 0.9, 0.88]
        sky = [[0.82, 0.87, 0.93], _hsv(rng, (0.55, 0.62), (0.35, 0.6), (0.75, 0.95)), [0.97, 0.97, 0.97]]
        octave_amp = np.array(_OCTAVE_AMPLITUDES)
    contrast = rng.uniform(0.9, 1.1) if not randomise else rng.uniform(0.4, 1.6)
    B = len(layout.boxes)
    rgb, rgb2, amp = list(ground), list(ground2), [contrast * _CLASS_TEXTURE_AMP[c] for c in (ROAD, SIDEWALK, TERRAIN, SIDEWALK)]
    for k in range(B):
        cls = int(layout.boxes.cls[k])
        a, b = _class_colour(rng, cls, randomise and rng.random() < 0.7)
        rgb.append(a)
        rgb2.append(b)
        amp.append(contrast * _CLASS_TEXTURE_AMP[cls])
    M = _N_GROUND + B
    facade = np.stack([rng.uniform(2.2, 4.0, M), rng.uniform(2.8, 3.6, M), rng.uniform(0.35, 0.65, M),
                       rng.uniform(0.4, 0.6, M)], 1)
    return _Appearance(
        sun=sun,
        ambient=float(rng.uniform(0.4, 0.55) if not randomise else rng.uniform(0.2, 0.8)),
        diffuse=float(rng.uniform(0.45, 0.6) if not randomise else rng.uniform(0.2, 0.9)),
        gain=float(rng.uniform(0.95, 1.1) if not randomise else rng.uniform(0.6, 1.4)),
        gamma=float(1.0 if not randomise else rng.uniform(0.75, 1.35)),
        octave_amp=torch.tensor(octave_amp / np.sum(octave_amp), dtype=torch.float32),
        rgb=torch.tensor(rgb, dtype=torch.float32),
        rgb2=torch.tensor(rgb2, dtype=torch.float32),
        amp=torch.tensor(amp, dtype=torch.float32),
        off=torch.tensor(rng.uniform(0, _TEXTURE_TILE_M, (M, 2)), dtype=torch.float32),
        facade=torch.tensor(facade, dtype=torch.float32),
        marking_rgb=torch.tensor(marking, dtype=torch.float32),
        sky_rgb=torch.tensor(sky, dtype=torch.float32),
    )


# ----------------------------------------------------------------------------------------------
# Ray casting
# ----------------------------------------------------------------------------------------------
@dataclass
class _Geometry:
    """The scene geometry at one time instant (current or previous), as plain arrays."""

    centre: np.ndarray    # (B, 3) float64 box centres at this time
    corners: np.ndarray   # (B, 8, 3) float64 world corners at this time
    layout: SceneLayout


def _geometry(layout: SceneLayout, shift: int) -> _Geometry:
    """The geometry ``shift`` frames after the current one (-1 = the previous frame): movers at ``c + shift Δ``."""
    bx = layout.boxes
    centre = bx.centre + shift * bx.delta if shift else bx.centre
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    local = signs[None] * bx.half[:, None, :]  # B x 8 x 3
    c, s = np.cos(bx.yaw), np.sin(bx.yaw)
    wx = c[:, None] * local[..., 0] + s[:, None] * local[..., 2]
    wz = -s[:, None] * local[..., 0] + c[:, None] * local[..., 2]
    corners = np.stack([wx, local[..., 1], wz], -1) + centre[:, None, :]
    return _Geometry(centre=centre, corners=corners, layout=layout)


_BOX_EDGES = [(i, j) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1]


def _screen_rects(geo: _Geometry, origin: np.ndarray, Rwc: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Pixel rectangles (B, 4) ``(u0, u1, v0, v1)`` (inclusive) bounding each box's image; empty if unseen.

    The part of a (convex) box in front of the near plane is the convex hull of its corners in
    front of it and of the edge crossings of the plane; its image is bounded by their projections.
    """
    H, W = size
    empty = np.array([1, 0, 1, 0])
    B = geo.corners.shape[0]
    if B == 0:
        return np.zeros((0, 4), dtype=np.int64)
    cam = (geo.corners - origin) @ Rwc  # B x 8 x 3; X_cam = Rwc^T (X - o)
    z = cam[..., 2]
    pts = [np.where((z >= _Z_NEAR)[..., None], cam, np.nan)]
    for i, j in _BOX_EDGES:
        zi, zj = z[:, i], z[:, j]
        cross = (zi - _Z_NEAR) * (zj - _Z_NEAR) < 0
        w = np.where(cross, (_Z_NEAR - zi) / np.where(cross, zj - zi, 1.0), 0.0)
        p = cam[:, i] + w[:, None] * (cam[:, j] - cam[:, i])
        pts.append(np.where(cross[:, None], p, np.nan)[:, None, :])
    P = np.concatenate(pts, 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = K[0, 0] * P[..., 0] / P[..., 2] + K[0, 2]
        v = K[1, 1] * P[..., 1] / P[..., 2] + K[1, 2]
    fin = np.isfinite(u)
    seen = fin.any(1)
    u0 = np.where(fin, u, np.inf).min(1)
    u1 = np.where(fin, u, -np.inf).max(1)
    v0 = np.where(fin, v, np.inf).min(1)
    v1 = np.where(fin, v, -np.inf).max(1)
    with np.errstate(invalid="ignore"):
        rect = np.stack([np.floor(u0) - 1, np.ceil(u1) + 1, np.floor(v0) - 1, np.ceil(v1) + 1], 1)
    rect = np.nan_to_num(rect, nan=0.0, posinf=1e9, neginf=-1e9)
    rect[:, 0:2] = np.clip(rect[:, 0:2], 0, W - 1)
    rect[:, 2:4] = np.clip(rect[:, 2:4], 0, H - 1)
    off = ~seen | (np.floor(u0) - 1 > W - 1) | (np.ceil(u1) + 1 < 0) | (np.floor(v0) - 1 > H - 1) | (np.ceil(v1) + 1 < 0)
    rect[off] = empty
    return rect.astype(np.int64)


def _box_slab(o: np.ndarray, Rwc: np.ndarray, centre: np.ndarray, half: np.ndarray, yaw: float,
              x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry ``t`` and hit mask of rays ``o + t Rwc (x, y, 1)`` with a box yawed about the vertical.

    ``Rwc`` must be a yaw too, so the world direction is ``(R00 x + R02, y, R20 x + R22)``: the
    x- and z-slab parameters depend on ``x`` only and the y-slab on ``y`` only. With ``x`` (1, w)
    and ``y`` (h, 1) (a pixel-grid rectangle) most work is 1D; with ``x``, ``y`` (n,) it is per ray.
    """
    c, s = math.cos(yaw), math.sin(yaw)
    dx = Rwc[0, 0] * x + Rwc[0, 2]
    dz = Rwc[2, 0] * x + Rwc[2, 2]
    ob = o - centre
    # local = Ry(yaw)^T world: lx = c x - s z, ly = y, lz = s x + c z
    olx, oly, olz = c * ob[0] - s * ob[2], ob[1], s * ob[0] + c * ob[2]
    dlx = c * dx - s * dz
    dlz = s * dx + c * dz

    def slab(oc: float, dc: torch.Tensor, hc: float) -> tuple[torch.Tensor, torch.Tensor]:
        inv = 1.0 / torch.where(dc.abs() > 1e-12, dc, torch.full_like(dc, 1e-12))
        t1 = (-hc - oc) * inv
        t2 = (hc - oc) * inv
        return torch.minimum(t1, t2), torch.maximum(t1, t2)

    ax, bx = slab(olx, dlx, half[0])
    az, bz = slab(olz, dlz, half[2])
    ay, by = slab(oly, y, half[1])
    tmin = torch.maximum(torch.maximum(ax, az), ay)
    tmax = torch.minimum(torch.minimum(bx, bz), by)
    return tmin, (tmax >= tmin) & (tmin > _T_EPS)


def _cast_ground(road: RoadLayout, o: np.ndarray, Rwc: np.ndarray, x: torch.Tensor, y: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """First hit ``t`` and ground-piece id of rays ``o + t Rwc (x, y, 1)``; inf / -1 where none.

    ``x``, ``y`` broadcast ((1, W) and (H, 1) for a grid, or (N,) and (N,)).
    """
    dx = Rwc[0, 0] * x + Rwc[0, 2]
    dz = Rwc[2, 0] * x + Rwc[2, 2]
    r, f = road.right, road.forward
    e_o = float(r @ o) + road.e_off
    l_o = float(f @ o)
    de = r[0] * dx + r[2] * dz
    dl = f[0] * dx + f[2] * dz
    shape = torch.broadcast_shapes(x.shape, y.shape)
    t_best = torch.full(shape, math.inf)
    pid = torch.full(shape, -1, dtype=torch.int64)
    safe_y = torch.where(y > 1e-9, y, torch.full_like(y, 1e-9))
    for k, y_plane in ((_PID_ROAD, road.height), (_PID_RAISED, road.height - KERB_HEIGHT_M)):
        t = (y_plane - o[1]) / safe_y
        e = e_o + t * de
        l = l_o + t * dl
        on_road = (e >= -road.road_left) & (e <= road.road_right)
        ok = (e.abs() <= road.e_max) & (l >= road.l_min) & (l <= road.l_max) & (y > 1e-9)
        ok = ok & (on_road if k == _PID_ROAD else ~on_road) & (t < t_best)
        t_best = torch.where(ok, t, t_best)
        pid = torch.where(ok, k, pid)
    safe_de = torch.where(de.abs() > 1e-9, de, torch.full_like(de, 1e-9))
    for k, e_plane in ((_PID_KERB_R, road.road_right), (_PID_KERB_L, -road.road_left)):
        t = (e_plane - e_o) / safe_de
        yy = o[1] + t * y
        l = l_o + t * dl
        ok = (yy >= road.height - KERB_HEIGHT_M) & (yy <= road.height) & (l >= road.l_min) & (l <= road.l_max)
        ok = ok & (t > _T_EPS) & (t < t_best)
        t_best = torch.where(ok, t, t_best)
        pid = torch.where(ok, k, pid)
    return t_best, pid


def _cast_grid(geo: _Geometry, origin: np.ndarray, Rwc: np.ndarray, K: np.ndarray, size: tuple[int, int]
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """First hit of every pixel ray of a camera at ``origin`` with yaw rotation ``Rwc`` (world-from-camera).

    Convention: pixel centres at integer ``(u, v)``; the ray of pixel ``x`` is ``Rwc K^-1 x`` (z = 1
    in the camera), so the ray parameter ``t`` of a hit is its depth ``z`` in that camera.

    Returns:
        t (H, W) float32 depth (inf on sky), pid (H, W) int64 primitive id (-1 sky, 0..3 ground
        pieces, 4 + b box b).
    """
    H, W = size
    x = ((torch.arange(W, dtype=torch.float32) - float(K[0, 2])) / float(K[0, 0]))[None, :]
    y = ((torch.arange(H, dtype=torch.float32) - float(K[1, 2])) / float(K[1, 1]))[:, None]
    t_best, pid = _cast_ground(geo.layout.road, origin, Rwc, x, y)
    bx = geo.layout.boxes
    rects = _screen_rects(geo, origin, Rwc, K, size)
    for b in range(rects.shape[0]):
        u0, u1, v0, v1 = (int(q) for q in rects[b])
        if u0 > u1 or v0 > v1:
            continue
        tmin, hit = _box_slab(origin, Rwc, geo.centre[b], bx.half[b], float(bx.yaw[b]),
                              x[:, u0:u1 + 1], y[v0:v1 + 1, :])
        tb = t_best[v0:v1 + 1, u0:u1 + 1]
        better = hit & (tmin < tb)
        tb.copy_(torch.where(better, tmin, tb))
        pb = pid[v0:v1 + 1, u0:u1 + 1]
        pb.copy_(torch.where(better, _N_GROUND + b, pb))
    return t_best, pid


def _cast_points(geo: _Geometry, origin: np.ndarray, Rwc: np.ndarray, K: np.ndarray, size: tuple[int, int],
                 u: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """First hit (t (N,), pid (N,)) of the rays through arbitrary pixel positions ``(u, v)`` (N,).

    Same conventions as :func:`_cast_grid`. Rays are sorted by row so that each box only tests the
    rays in the row band of its screen rectangle.
    """
    x = (u - float(K[0, 2])) / float(K[0, 0])
    y = (v - float(K[1, 2])) / float(K[1, 1])
    t_best, pid = _cast_ground(geo.layout.road, origin, Rwc, x, y)
    order = torch.argsort(v)
    vs, us, xs, ys = v[order], u[order], x[order], y[order]
    t_s, p_s = t_best[order], pid[order]
    bx = geo.layout.boxes
    rects = _screen_rects(geo, origin, Rwc, K, size)
    for b in range(rects.shape[0]):
        u0, u1, v0, v1 = (int(q) for q in rects[b])
        if u0 > u1 or v0 > v1:
            continue
        lo = int(torch.searchsorted(vs, torch.tensor(float(v0))))
        hi = int(torch.searchsorted(vs, torch.tensor(float(v1)), right=True))
        if hi <= lo:
            continue
        band = us[lo:hi]
        idx = torch.nonzero((band >= u0) & (band <= u1)).squeeze(1) + lo
        if idx.numel() == 0:
            continue
        tmin, hit = _box_slab(origin, Rwc, geo.centre[b], bx.half[b], float(bx.yaw[b]), xs[idx], ys[idx])
        better = hit & (tmin < t_s[idx])
        sel = idx[better]
        t_s[sel] = tmin[better]
        p_s[sel] = _N_GROUND + b
    t_best = torch.empty_like(t_s)
    t_best[order] = t_s
    pid = torch.empty_like(p_s)
    pid[order] = p_s
    return t_best, pid


# ----------------------------------------------------------------------------------------------
# Surfaces and shading
# ----------------------------------------------------------------------------------------------
def _band(x: torch.Tensor, half_width: float | torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
    """Anti-aliased indicator of ``|x| < half_width`` with a ramp ``_EDGE_RAMP_PIXELS`` footprints wide."""
    return ((half_width - x.abs()) / (_EDGE_RAMP_PIXELS * fp) + 0.5).clamp(0, 1)


def _periodic_band(x: torch.Tensor, period: float | torch.Tensor, frac: float | torch.Tensor,
                   fp: torch.Tensor) -> torch.Tensor:
    """Anti-aliased periodic pattern: 1 on a fraction ``frac`` of each period, fading to ``frac``
    where the period spans fewer than ~3 footprints."""
    m = torch.remainder(x, period) - period / 2
    pat = _band(m, frac * period / 2, fp)
    w = (period / (3 * fp) - 1).clamp(0, 1)
    return w * pat + (1 - w) * frac


@dataclass
class _Surface:
    """Surface attributes of every ray's hit (garbage where the ray hits nothing)."""

    normal: torch.Tensor    # (N, 3) world unit normals
    a: torch.Tensor         # (N,) surface coordinate 1 (metres)
    b: torch.Tensor         # (N,) surface coordinate 2 (metres; vertical on upright faces)
    ly: torch.Tensor        # (N,) local y / half height on boxes (-1 top .. 1 bottom)
    vertical: torch.Tensor  # (N,) bool, upright face
    face: torch.Tensor      # (N,) int face code (texture offsets)
    mat: torch.Tensor       # (N,) material: 0 road, 1 sidewalk, 2 terrain, 3 kerb, 4 + b box b
    cls: torch.Tensor       # (N,) class ids (sky where no hit)
    inst: torch.Tensor      # (N,) instance ids
    box: torch.Tensor       # (N,) box index or -1
    e: torch.Tensor         # (N,) road lateral coordinate
    l: torch.Tensor         # (N,) road longitudinal coordinate


def _surface(geo: _Geometry, P: torch.Tensor, pid: torch.Tensor) -> _Surface:
    """Surface attributes at points ``P`` (N, 3) world (at the geometry's time) of primitives ``pid`` (N,)."""
    layout = geo.layout
    road = layout.road
    bx = layout.boxes
    N = P.shape[0]
    r = torch.tensor(road.right, dtype=torch.float32)
    f = torch.tensor(road.forward, dtype=torch.float32)
    e = P @ r + road.e_off
    l = P @ f
    is_box = pid >= _N_GROUND
    bi = torch.where(is_box, pid - _N_GROUND, 0)
    B = len(bx)
    if B:
        centre = torch.tensor(geo.centre, dtype=torch.float32)[bi]
        half = torch.tensor(bx.half, dtype=torch.float32)[bi]
        c = torch.tensor(np.cos(bx.yaw), dtype=torch.float32)[bi]
        s = torch.tensor(np.sin(bx.yaw), dtype=torch.float32)[bi]
        Pm = P - centre
        lx = c * Pm[:, 0] - s * Pm[:, 2]
        lyy = Pm[:, 1]
        lz = s * Pm[:, 0] + c * Pm[:, 2]
        loc = torch.stack([lx, lyy, lz], -1)
        axis = (loc.abs() / half).argmax(1)
        sign = torch.where(loc.gather(1, axis[:, None]).squeeze(1) >= 0, 1.0, -1.0)
        nl = torch.zeros_like(loc).scatter_(1, axis[:, None], sign[:, None])
        nbox = torch.stack([c * nl[:, 0] + s * nl[:, 2], nl[:, 1], -s * nl[:, 0] + c * nl[:, 2]], -1)
        # Face coordinates: x-face -> (lz, ly); y-face -> (lx, lz); z-face -> (lx, ly).
        abox = torch.where(axis == 0, lz, lx)
        bbox = torch.where(axis == 1, lz, lyy)
        ly = lyy / half[:, 1]
        face_box = 4 + axis * 2 + (sign > 0).long()
        cls_box = torch.from_numpy(bx.cls)[bi]
        inst_box = torch.from_numpy(bx.inst)[bi]
        style_vertical = axis != 1
    else:
        nbox = torch.zeros(N, 3)
        abox = bbox = ly = torch.zeros(N)
        face_box = cls_box = inst_box = torch.zeros(N, dtype=torch.int64)
        style_vertical = torch.zeros(N, dtype=torch.bool)

    kerb = (pid == _PID_KERB_R) | (pid == _PID_KERB_L)
    up = torch.tensor([0.0, -1.0, 0.0])
    kerb_sign = torch.where(pid == _PID_KERB_R, -1.0, 1.0)[:, None]
    normal = torch.where(is_box[:, None], nbox, torch.where(kerb[:, None], kerb_sign * r, up))
    a = torch.where(is_box, abox, torch.where(kerb, l, e))
    b = torch.where(is_box, bbox, torch.where(kerb, P[:, 1], l))
    vertical = torch.where(is_box, style_vertical, kerb)
    face = torch.where(is_box, face_box, pid.clamp_min(0))
    sidewalk = ((e > road.road_right) & (e <= road.road_right + road.sidewalk_right)) | \
               ((e < -road.road_left) & (e >= -road.road_left - road.sidewalk_left))
    raised = pid == _PID_RAISED
    ground_cls = torch.where(raised, torch.where(sidewalk, SIDEWALK, TERRAIN), torch.where(kerb, SIDEWALK, ROAD))
    cls = torch.where(is_box, cls_box, torch.where(pid < 0, SKY, ground_cls))
    ground_mat = torch.where(raised, torch.where(sidewalk, 1, 2), torch.where(kerb, 3, 0))
    mat = torch.where(is_box, pid, ground_mat)
    inst = torch.where(is_box, inst_box, 0)
    box = torch.where(is_box, bi, -1)
    return _Surface(normal, a, b, torch.where(is_box, ly, 0.0), vertical, face, mat, cls, inst, box, e, l)


def _shade(app: _Appearance, layout: SceneLayout, surf: _Surface, P_cur: torch.Tensor, fx: float) -> torch.Tensor:
    """Colour (N, 3) of surface points; texture footprint from the *current-frame* position ``P_cur``.

    Everything is a function of the surface point (material, surface coordinates, current-frame
    position) and the world normal, so a point has the same colour in both frames.
    """
    dist = P_cur.norm(dim=1).clamp_min(1e-3)
    cosi = ((surf.normal * P_cur).sum(1).abs() / dist).clamp_min(_MIN_COS_INCIDENCE)
    fp = dist / (fx * cosi)       # metres per pixel on the surface (isotropic, conservative)
    fp_across = dist / fx         # metres per pixel across the viewing direction
    mat = surf.mat
    off = app.off[mat] + surf.face[:, None].float() * torch.tensor([3.1, 1.7])
    octaves = _sample_texture(surf.a + off[:, 0], surf.b + off[:, 1])  # O x N
    periods = torch.tensor(_OCTAVE_PERIODS_M)[:, None]
    w = ((periods / fp[None] - _OCTAVE_MIN_PIXELS) / _OCTAVE_MIN_PIXELS).clamp(0, 1)
    n = (app.octave_amp[:, None] * (w * octaves + (1 - w) * 0.5)).sum(0)   # in ~[0, 1], mean 0.5
    tex = 1 + app.amp[mat] * (n - 0.5) * 2.0
    c1, c2 = app.rgb[mat], app.rgb2[mat]
    cls = surf.cls
    is_box = surf.box >= 0
    albedo = c1 * tex[:, None]

    # Patterns are evaluated only on the pixels that carry them (index sets, not full-size masks).
    road = layout.road
    idx = torch.nonzero((cls == ROAD) & ~is_box).squeeze(1)
    if idx.numel():
        # Lane markings, anti-aliased across by the lateral footprint and along by fp.
        e, l, fpa, fpi, ni = surf.e[idx], surf.l[idx], fp_across[idx], fp[idx], n[idx]
        mark = torch.zeros_like(e)
        for ec, hw, dashed in road.markings:
            line = _band(e - ec, hw, fpa)
            if dashed:
                line = line * _periodic_band(l - road.dash_phase, road.dash_period,
                                             road.dash_length / road.dash_period, fpi)
            mark = torch.maximum(mark, line)
        mark = (mark * (0.85 + 0.6 * (ni - 0.5)))[:, None]
        albedo[idx] = albedo[idx] * (1 - mark) + app.marking_rgb * mark
    idx = torch.nonzero(mat == 1).squeeze(1)
    if idx.numel():
        # Sidewalk paving slabs (not on the kerb face).
        fpi = fp[idx]
        slab = _periodic_band(surf.a[idx], 0.6, 0.93, fpi) * _periodic_band(surf.b[idx], 0.6, 0.93, fpi)
        albedo[idx] = albedo[idx] * (0.75 + 0.25 * slab)[:, None]
    idx = torch.nonzero(mat == 2).squeeze(1)
    if idx.numel():
        # Terrain: grass and dirt patches from the coarsest octave.
        patch = ((octaves[-1, idx] - 0.45) * 5).clamp(0, 1)[:, None]
        albedo[idx] = (c1[idx] * (1 - patch) + c2[idx] * patch) * tex[idx, None]
    if len(layout.boxes):
        # Boxes: facades with windows, glass, two-tone clothes (second colour, own contrast).
        style = torch.from_numpy(layout.boxes.style)[surf.box.clamp_min(0)]
        facade = is_box & surf.vertical & (style == STYLE_FACADE)
        second = is_box & ((surf.vertical & (style == STYLE_GLASS)) | ((style == STYLE_CLOTHES) & (surf.ly > 0.05)))
        idx = torch.nonzero(facade | second).squeeze(1)
        if idx.numel():
            mi, ni, fpi = mat[idx], n[idx], fp[idx]
            tex2 = c2[idx] * (1 + app.amp[mi] * 1.2 * (ni - 0.5) * 2.0)[:, None]
            prm = app.facade[mi]
            win = _periodic_band(surf.a[idx], prm[:, 0], prm[:, 2], fpi) * \
                _periodic_band(surf.b[idx] + 0.7, prm[:, 1], prm[:, 3], fpi)
            win = torch.where(second[idx], 1.0, win)[:, None]
            albedo[idx] = albedo[idx] * (1 - win) + tex2 * win
    albedo = albedo.clamp(0, 1)
    lambert = (surf.normal @ app.sun).clamp_min(0)
    return albedo * (app.ambient + app.diffuse * lambert)[:, None]


def _sky(app: _Appearance, d: torch.Tensor) -> torch.Tensor:
    """Sky colour (N, 3) as a function of the world ray direction only (rotation-consistent)."""
    dn = d / d.norm(dim=1, keepdim=True)
    el = (-dn[:, 1]).clamp_min(0)
    w = (el * 3).clamp(0, 1)[:, None]
    col = app.sky_rgb[0] * (1 - w) + app.sky_rgb[1] * w
    proj = 40.0 / (el + 0.15)
    octaves = _sample_texture(dn[:, 0] * proj, dn[:, 2] * proj)
    cloud = 0.6 * octaves[-1] + 0.4 * octaves[-2]
    c = ((cloud - 0.5) * 3).clamp(0, 1)[:, None] * 0.8
    return col * (1 - c) + app.sky_rgb[2] * c


def _render(app: _Appearance, geo: _Geometry, t: torch.Tensor, pid: torch.Tensor, origin: np.ndarray,
            Rwc: np.ndarray, K: np.ndarray, shift: int) -> tuple[torch.Tensor, _Surface, torch.Tensor]:
    """Colours (3, H, W) of a cast grid (t, pid (H, W)), the surfaces (N = H W) and the hit mask (N,).

    ``shift``: the geometry is ``shift`` frames after the current time (-1 = previous); the texture
    footprint is then taken at each point's current-frame position ``P - shift Δ`` so every frame sees the
    same texture.
    """
    H, W = t.shape
    x = (torch.arange(W, dtype=torch.float32) - float(K[0, 2])) / float(K[0, 0])
    y = (torch.arange(H, dtype=torch.float32) - float(K[1, 2])) / float(K[1, 1])
    d_cam = torch.stack(torch.broadcast_tensors(x[None, :], y[:, None], torch.ones(1, 1)), -1).reshape(-1, 3)
    d = d_cam @ torch.tensor(Rwc, dtype=torch.float32).T
    t = t.reshape(-1)
    pid = pid.reshape(-1)
    hit = pid >= 0
    o = torch.tensor(origin, dtype=torch.float32)
    P = o + torch.where(hit, t, 1.0)[:, None] * d
    surf = _surface(geo, P, pid)
    P_cur = P
    if shift and len(geo.layout.boxes):
        delta = torch.tensor(geo.layout.boxes.delta, dtype=torch.float32)[surf.box.clamp_min(0)]
        P_cur = P + torch.where((surf.box >= 0)[:, None], delta if shift == -1 else -shift * delta, 0.0)
    colour = _shade(app, geo.layout, surf, P_cur, float(K[0, 0]))
    sky = torch.nonzero(~hit).squeeze(1)
    if sky.numel():
        colour[sky] = _sky(app, d[sky])
    colour = (colour * app.gain).clamp(0, 1) ** app.gamma
    return colour.T.reshape(3, H, W).contiguous(), surf, hit


def _flow_validity(t_prev: torch.Tensor, key_prev: torch.Tensor, key_cur: torch.Tensor, hit: torch.Tensor,
                   up: torch.Tensor, vp: torch.Tensor, zp: torch.Tensor) -> torch.Tensor:
    """Whether each current pixel's surface point is seen at ``x_prev`` in the previous frame.

    Valid where ``x_prev = (up, vp)`` lies inside the previous image, the previous frame's ray cast
    hits the current pixel's primitive face at all four pixel centres around ``x_prev``, and the inverse
    depth bilinearly interpolated there equals ``1 / z_prev`` of the point (relative tolerance
    ``_FLOW_VALID_REL_TOL``). Inverse depth is affine in the pixel coordinates on a plane, so on
    a planar face this is exactly "the previous-frame ray through ``x_prev`` hits the same
    surface point"; pixels whose bilinear neighbourhood straddles an occlusion boundary or a box
    edge are left out (they could not be compared photometrically either).

    Args:
        t_prev, key_prev: (H, W) previous-frame grid cast (depth, face key = primitive and face).
        key_cur: (N,) face key of each current pixel; hit: (N,) current pixel sees a surface.
        up, vp: (N,) float64 previous-frame pixel of each current pixel; zp: (N,) its depth (metres).

    Returns:
        (N,) bool.
    """
    H, W = t_prev.shape
    inside = hit & (zp > _Z_NEAR) & (up >= 0) & (up <= W - 1) & (vp >= 0) & (vp <= H - 1)
    cand = torch.nonzero(inside).squeeze(1)
    valid = torch.zeros_like(hit)
    if cand.numel() == 0:
        return valid
    uc, vc = up[cand], vp[cand]
    u0 = uc.floor().long().clamp(0, W - 1)
    v0 = vc.floor().long().clamp(0, H - 1)
    u1, v1 = (u0 + 1).clamp(max=W - 1), (v0 + 1).clamp(max=H - 1)
    wu, wv = uc - u0, vc - v0
    pflat, tflat = key_prev.reshape(-1), t_prev.reshape(-1).double()
    k = key_cur[cand]
    same = torch.ones_like(k, dtype=torch.bool)
    inv = torch.zeros_like(uc)
    for uu, vv, w in ((u0, v0, (1 - wu) * (1 - wv)), (u1, v0, wu * (1 - wv)), (u0, v1, (1 - wu) * wv), (u1, v1, wu * wv)):
        j = vv * W + uu
        same &= pflat[j] == k
        inv = inv + w / tflat[j]
    z = zp[cand]
    valid[cand] = same & ((inv * z - 1).abs() <= _FLOW_VALID_REL_TOL)
    return valid


# ----------------------------------------------------------------------------------------------
# Public API
# ----------------------------------------------------------------------------------------------
def _check_int(x: object, name: str, minimum: int) -> int:
    if isinstance(x, bool) or not isinstance(x, (int, np.integer)):
        raise InputError(f"{name}: expected an integer, got {x!r}")
    if int(x) < minimum:
        raise InputError(f"{name}: must be >= {minimum}, got {x}")
    return int(x)


def _check_scale(scale: object) -> float:
    if isinstance(scale, bool) or not isinstance(scale, (int, float, np.floating, np.integer)) or not math.isfinite(float(scale)):
        raise InputError(f"scale: expected a finite number, got {scale!r}")
    scale = float(scale)
    if not (0 < scale <= 4.0) or round(KITTI_IMAGE_SIZE[0] * scale) < 8:
        raise InputError(f"scale: must be in (0, 4] and give an image at least 8 pixels high, got {scale}")
    return scale


def _check_density(density: object) -> float:
    if isinstance(density, bool) or not isinstance(density, (int, float, np.floating, np.integer)) or not math.isfinite(float(density)):
        raise InputError(f"density: expected a finite number, got {density!r}")
    density = float(density)
    if not (0 <= density <= 10.0):
        raise InputError(f"density: must be in [0, 10], got {density}")
    return density


def synthetic_camera(scale: float = 1.0) -> Camera:
    """The camera of the synthetic benchmark: KITTI intrinsics scaled by ``scale``, KITTI height.

    Args:
        scale: resolution scale relative to 1242 x 375 (fx, fy, cx, cy are multiplied by it).

    Returns:
        Camera(K (3, 3) float64, height 1.65 m, ground normal (0, 1, 0)).
    """
    scale = _check_scale(scale)
    fx, fy, cx, cy = (x * scale for x in KITTI_INTRINSICS)
    K = intrinsics(fx, fy, cx, cy)
    return Camera(K=K, height=KITTI_CAMERA_HEIGHT_M, ground_normal=torch.tensor([0.0, 1.0, 0.0], dtype=K.dtype))


def render_pair(seed: int, *, scale: float = 1.0, density: float = 1.0,
                appearance_seed: int | None = None) -> FramePair:
    """Render a synthetic street-scene frame pair with its ground truth.

    Args:
        seed: scene seed (non-negative int); geometry and default appearance follow from it.
        scale: resolution scale; the images are ``round(375 scale) x round(1242 scale)`` pixels.
        density: multiplier of the number of objects (0 = empty street, 1 = default).
        appearance_seed: if given, colours, textures, lighting and contrast are randomised from it
            (domain randomisation), independently of the geometry.

    Returns:
        FramePair with image / image_prev (3, H, W) float32 RGB in [0, 1], camera (K, 1.65 m),
        motion ``X_prev = R X_cur + t`` (metres) and gt: depth (H, W) float32 metres (0 on sky),
        flow (2, H, W) float32 current -> previous pixels (static points ``X_prev = R X_cur + t``,
        points of a moving object ``X_prev = R (X_cur - Δ) + t``; sky: rotation only),
        flow_valid (H, W) bool (visible in both frames, inside the previous image), labels (H, W)
        int64 0..9, instances (H, W) int64 (0 = stuff), moving (H, W) bool. ``meta`` holds
        ``seed``, ``scene_seed``, ``appearance_seed``, ``ego_speed`` (m/s), ``road`` and
        ``objects`` (class, instance, centre (3,), size (w, h, l), yaw, delta (3,), moving, parts)
        in current-camera coordinates (metres, radians).
    """
    seed = _check_int(seed, "seed", 0)
    scale = _check_scale(scale)
    density = _check_density(density)
    if appearance_seed is not None:
        appearance_seed = _check_int(appearance_seed, "appearance_seed", 0)

    H, W = round(KITTI_IMAGE_SIZE[0] * scale), round(KITTI_IMAGE_SIZE[1] * scale)
    N = H * W
    camera = synthetic_camera(scale)
    K = camera.K.numpy()
    layout = sample_scene(seed, density)
    logger.debug("synthetic scene %d: %d boxes, %d objects (%d moving), ego speed %.1f m/s", seed,
                 len(layout.boxes), len(layout.objects), sum(o["moving"] for o in layout.objects), layout.ego_speed)
    app = _sample_appearance(layout, seed if appearance_seed is None else appearance_seed, appearance_seed is not None)

    with torch.no_grad():
        # Current frame: the world frame, camera at the origin.
        geo_cur = _geometry(layout, 0)
        eye, zero = np.eye(3), np.zeros(3)
        t_cur, pid_cur = _cast_grid(geo_cur, zero, eye, K, (H, W))
        img_cur, surf, hit = _render(app, geo_cur, t_cur, pid_cur, zero, eye, K, 0)

        # Previous frame: X_prev = R X + t, so the camera centre is -R^T t and world-from-camera
        # is R^T; moving boxes sit at X - Δ.
        R, tv = layout.R, layout.t
        o_prev, Rwc_prev = -R.T @ tv, R.T
        geo_prev = _geometry(layout, -1)
        t_prev, pid_prev = _cast_grid(geo_prev, o_prev, Rwc_prev, K, (H, W))
        img_prev, surf_prev, _ = _render(app, geo_prev, t_prev, pid_prev, o_prev, Rwc_prev, K, -1)

        # Ground-truth flow (float64): X_prev = R (X_cur - Δ) + t, projected; sky moves by R only.
        vv, uu = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
        u, v = uu.reshape(-1), vv.reshape(-1)
        ray = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones(N, dtype=torch.float64)], -1)
        depth = torch.where(hit, t_cur.reshape(-1).double(), 0.0)
        delta = torch.zeros(N, 3, dtype=torch.float64)
        if len(layout.boxes):
            box_delta = torch.tensor(layout.boxes.delta, dtype=torch.float64)[surf.box.clamp_min(0)]
            delta = torch.where((surf.box >= 0)[:, None], box_delta, 0.0)
        Rd, td = torch.tensor(R, dtype=torch.float64), torch.tensor(tv, dtype=torch.float64)
        Xp = torch.where(hit[:, None], (ray * depth[:, None] - delta) @ Rd.T + td, ray @ Rd.T)
        zp = Xp[:, 2]
        up = K[0, 0] * Xp[:, 0] / zp + K[0, 2]
        vp = K[1, 1] * Xp[:, 1] / zp + K[1, 2]
        flow = torch.stack([up - u, vp - v], 0)

        # Face key: primitive id and face (box faces differ in shading, so they count as surfaces).
        key_cur = pid_cur.reshape(-1) * 16 + surf.face
        key_prev = (pid_prev.reshape(-1) * 16 + surf_prev.face).view(H, W)
        valid = _flow_validity(t_prev, key_prev, key_cur, hit, up, vp, zp)

    labels = surf.cls
    instances = torch.where(hit, surf.inst, 0)
    moving_inst = [o["instance"] for o in layout.objects if o["moving"]]
    moving = torch.isin(instances, torch.tensor(moving_inst, dtype=torch.int64)) & (instances > 0)

    gt = GroundTruth(
        depth=depth.float().view(H, W),
        flow=flow.float().view(2, H, W),
        flow_valid=valid.view(H, W),
        labels=labels.view(H, W),
        instances=instances.view(H, W),
        moving=moving.view(H, W),
    )
    meta = {
        "seed": seed,
        "scene_seed": seed,
        "appearance_seed": appearance_seed,
        "ego_speed": layout.ego_speed,
        "road": {
            "angle": layout.road.angle, "e_off": layout.road.e_off,
            "road_left": layout.road.road_left, "road_right": layout.road.road_right,
            "sidewalk_left": layout.road.sidewalk_left, "sidewalk_right": layout.road.sidewalk_right,
            "kerb_height": KERB_HEIGHT_M,
        },
        "objects": layout.objects,
    }
    return FramePair(
        image=img_cur,
        image_prev=img_prev,
        camera=camera,
        motion=Motion(R=torch.tensor(R, dtype=torch.float64), t=torch.tensor(tv, dtype=torch.float64)),
        gt=gt,
        name=f"synthetic_{seed:06d}",
        meta=meta,
    )


class SyntheticSource:
    """A sequence of independent synthetic frame pairs (docs/conventions.md, section 6; config group
    ``data``).

    Frame ``i`` of source seed ``s`` is scene seed ``s * 100_000 + i``; its name is
    ``synthetic_{s}_{i:06d}``.

    Args:
        frames: number of frame pairs (>= 1).
        seed: source seed (>= 0).
        scale: resolution scale relative to 1242 x 375.
        density: scene density multiplier.
    """

    def __init__(self, frames: int, seed: int = 0, scale: float = 1.0, density: float = 1.0) -> None:
        self.frames = _check_int(frames, "frames", 1)
        self.seed = _check_int(seed, "seed", 0)
        if self.frames > SOURCE_SEED_STRIDE:
            raise InputError(f"frames: at most {SOURCE_SEED_STRIDE} per source seed, got {frames}")
        self.scale = _check_scale(scale)
        self.density = _check_density(density)

    def __len__(self) -> int:
        return self.frames

    def scene_seed(self, i: int) -> int:
        """Scene seed of frame ``i``."""
        return self.seed * SOURCE_SEED_STRIDE + i

    def __getitem__(self, i: int) -> FramePair:
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)):
            raise InputError(f"index: expected an integer, got {i!r}")
        i = int(i)
        if i < 0:
            i += self.frames
        if not 0 <= i < self.frames:
            raise IndexError(f"index {i} out of range for {self.frames} frames")
        pair = render_pair(self.scene_seed(i), scale=self.scale, density=self.density)
        pair.name = f"synthetic_{self.seed}_{i:06d}"
        pair.meta["seed"] = self.seed
        pair.meta["frame"] = i
        return pair

    def __iter__(self) -> Iterator[FramePair]:
        for i in range(self.frames):
            yield self[i]


# ----------------------------------------------------------------------------------------------
# Sequences: one scene, consecutive frames
# ----------------------------------------------------------------------------------------------
def _step_pose(R: np.ndarray, t: np.ndarray, step: int) -> tuple[np.ndarray, np.ndarray]:
    """(origin (3,), world-from-camera rotation (3, 3)) of the camera ``step`` frames after the world frame.

    The ego repeats the pair's motion every frame: ``X_{k-1} = R X_k + t``, so camera ``k`` maps into the
    world (camera 0) by ``M^k`` with ``M(X) = R X + t``; ``k = -1`` is ``M^-1`` (the previous frame of
    :func:`render_pair`).
    """
    if step < 0:
        Rwc, o = np.eye(3), np.zeros(3)
        for _ in range(-step):  # M^-1: X_k = R^T (X_{k-1} - t)
            o = Rwc @ (-R.T @ t) + o
            Rwc = Rwc @ R.T
        return o, Rwc
    Rwc, o = np.eye(3), np.zeros(3)
    for _ in range(step):
        o = Rwc @ t + o
        Rwc = Rwc @ R
    return o, Rwc


@dataclass
class _View:
    """One rendered frame of a sequence: image, grid cast, surfaces and the camera pose."""

    image: torch.Tensor     # (3, H, W)
    t: torch.Tensor         # (H, W) ray parameter = depth (rays have z = 1)
    pid: torch.Tensor       # (H, W) primitive ids (-1 = sky)
    surf: _Surface
    hit: torch.Tensor       # (N,) bool
    origin: np.ndarray      # (3,) camera centre in the world (camera 0)
    Rwc: np.ndarray         # (3, 3) world-from-camera rotation


class SyntheticSequence:
    """One street scene seen over consecutive frames: constant ego motion, movers at constant velocity.

    Frame ``j`` (0-based) is rendered ``j - 1`` frames after the current frame of :func:`render_pair` of
    the same seed, so ``pair(1, 0)`` shows the scene of ``render_pair(seed)`` (with a sequence's mover
    footprints kept free over ``length`` frames, the scene may hold fewer movers than the single pair).

    Args:
        seed: scene seed.
        length: frames after the first (pairs ``(j, j - 1)`` for ``j = 1..length``).
        scale, density, appearance_seed: as :func:`render_pair`.
        ego_speed: ego speed (m/s), None = the scene's own (8-15 m/s).
        cache: rendered frames kept for reuse (a keyframe pair reads frames rendered before).
    """

    def __init__(self, seed: int, length: int, *, scale: float = 1.0, density: float = 1.0,
                 ego_speed: float | None = None, appearance_seed: int | None = None, cache: int = 12) -> None:
        self.seed = _check_int(seed, "seed", 0)
        self.length = _check_int(length, "sequence_length", 1)
        self.scale = _check_scale(scale)
        density = _check_density(density)
        if ego_speed is not None and not (isinstance(ego_speed, (int, float)) and math.isfinite(ego_speed) and ego_speed >= 0):
            raise InputError(f"data.ego_speed_mps: a speed >= 0 m/s or null, got {ego_speed!r}")
        self.layout = sample_scene(self.seed, density, ego_speed=ego_speed, ahead_steps=self.length - 1)
        self.app = _sample_appearance(self.layout, self.seed if appearance_seed is None else appearance_seed,
                                      appearance_seed is not None)
        self.camera = synthetic_camera(self.scale)
        self.size = (round(KITTI_IMAGE_SIZE[0] * self.scale), round(KITTI_IMAGE_SIZE[1] * self.scale))
        self._cache: dict[int, _View] = {}
        self._cache_size = max(2, int(cache))

    def pose(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """(origin, world-from-camera rotation) of frame ``j``; the world is frame 1's camera."""
        return _step_pose(self.layout.R, self.layout.t, j - 1)

    def motion(self, j: int, k: int) -> Motion:
        """Camera motion from frame ``j`` to frame ``k``: ``X_k = R X_j + t``."""
        o_j, R_j = self.pose(j)
        o_k, R_k = self.pose(k)
        return Motion(R=torch.from_numpy(R_k.T @ R_j), t=torch.from_numpy(R_k.T @ (o_j - o_k)))

    def _view(self, j: int) -> _View:
        if j in self._cache:
            return self._cache[j]
        K = self.camera.K.numpy()
        o, Rwc = self.pose(j)
        with torch.no_grad():
            geo = _geometry(self.layout, j - 1)
            t, pid = _cast_grid(geo, o, Rwc, K, self.size)
            img, surf, hit = _render(self.app, geo, t, pid, o, Rwc, K, j - 1)
        view = _View(img, t, pid, surf, hit, o, Rwc)
        if len(self._cache) >= self._cache_size:
            self._cache.pop(min(self._cache))
        self._cache[j] = view
        return view

    def pair(self, j: int, k: int) -> FramePair:
        """Frame ``j`` (current) with frame ``k < j`` (previous) and the ground truth of frame ``j``.

        Ground truth as :func:`render_pair`, for the pair ``(j, k)`` (a mover has moved ``(j - k) Δ``),
        plus ``velocity`` (3, H, W) m/s in frame ``j``'s camera axes (0 on static surfaces, NaN on sky) and
        ``ttc`` (H, W) seconds: depth over the closing speed along the optical axis relative to the camera
        (inf where not closing, NaN on sky).
        """
        if not (0 <= k < j <= self.length):
            raise InputError(f"synthetic sequence: need 0 <= previous < current <= {self.length}, got {k}, {j}")
        H, W = self.size
        N = H * W
        K = self.camera.K.numpy()
        cur, prev = self._view(j), self._view(k)
        dt = FRAME_INTERVAL_S
        with torch.no_grad():
            vv, uu = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
            u, v = uu.reshape(-1), vv.reshape(-1)
            ray = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones(N, dtype=torch.float64)], -1)
            hit = cur.hit
            depth = torch.where(hit, cur.t.reshape(-1).double(), 0.0)
            delta = torch.zeros(N, 3, dtype=torch.float64)
            if len(self.layout.boxes):
                box_delta = torch.tensor(self.layout.boxes.delta, dtype=torch.float64)[cur.surf.box.clamp_min(0)]
                delta = torch.where((cur.surf.box >= 0)[:, None], box_delta, 0.0)
            Rj, oj = torch.from_numpy(cur.Rwc), torch.from_numpy(cur.origin)
            Rk, ok = torch.from_numpy(prev.Rwc), torch.from_numpy(prev.origin)
            Xw = (ray * depth[:, None]) @ Rj.T + oj - (j - k) * delta
            Xp = torch.where(hit[:, None], (Xw - ok) @ Rk, ray @ Rj.T @ Rk)
            zp = Xp[:, 2]
            up = K[0, 0] * Xp[:, 0] / zp + K[0, 2]
            vp = K[1, 1] * Xp[:, 1] / zp + K[1, 2]
            flow = torch.stack([up - u, vp - v], 0)
            key_cur = cur.pid.reshape(-1) * 16 + cur.surf.face
            key_prev = (prev.pid.reshape(-1) * 16 + prev.surf.face).view(H, W)
            valid = _flow_validity(prev.t, key_prev, key_cur, hit, up, vp, zp)
            # Velocities in frame j's camera axes; the camera moves by one frame's step per dt.
            vel = (delta / dt) @ Rj
            o_before, _ = self.pose(j - 1)
            v_cam = torch.from_numpy(cur.Rwc.T @ (cur.origin - o_before) / dt)
            closing = -(vel[:, 2] - v_cam[2])
            ttc = torch.where(closing > 1e-6, depth / closing.clamp_min(1e-6), torch.full_like(depth, math.inf))
            nan = torch.full_like(depth, math.nan)
            vel = torch.where(hit[:, None], vel, nan[:, None])
            ttc = torch.where(hit, ttc, nan)
        instances = torch.where(hit, cur.surf.inst, 0)
        moving_inst = [o["instance"] for o in self.layout.objects if o["moving"]]
        moving = torch.isin(instances, torch.tensor(moving_inst, dtype=torch.int64)) & (instances > 0)
        gt = GroundTruth(
            depth=depth.float().view(H, W), flow=flow.float().view(2, H, W), flow_valid=valid.view(H, W),
            labels=cur.surf.cls.view(H, W), instances=instances.view(H, W), moving=moving.view(H, W),
            velocity=vel.T.float().reshape(3, H, W).contiguous(), ttc=ttc.float().view(H, W),
        )
        meta = {"seed": self.seed, "scene_seed": self.seed, "ego_speed": self.layout.ego_speed,
                "objects": self.layout.objects, "frame": j, "frame_prev": k, "dt": dt * (j - k)}
        return FramePair(image=cur.image, image_prev=prev.image, camera=self.camera, motion=self.motion(j, k),
                         gt=gt, name=f"synthetic_{self.seed:06d}_{j:03d}", meta=meta)


class SyntheticSequenceSource:
    """Clips of consecutive synthetic frames (``data.sequence_length > 1``): keyframes and tracks run on them.

    Clip ``c`` of source seed ``s`` is :class:`SyntheticSequence` of scene seed ``s * 100_000 + c``; its
    pairs are frames ``j = 1..length`` with frame ``j - 1`` (``pair_back`` reaches further back). Pair
    names are ``synthetic_{s}_{c:06d}_{j:03d}``.

    Args:
        clips: number of clips (``data.frames``).
        length: frames per clip (``data.sequence_length``; pairs per clip).
        seed, scale, density: as :class:`SyntheticSource`.
        ego_speed: ego speed (m/s, ``data.ego_speed_mps``); None = each scene's own.
    """

    def __init__(self, clips: int, length: int, seed: int = 0, scale: float = 1.0, density: float = 1.0,
                 ego_speed: float | None = None) -> None:
        self.clips = _check_int(clips, "frames", 1)
        self.length = _check_int(length, "sequence_length", 1)
        self.seed = _check_int(seed, "seed", 0)
        if self.clips > SOURCE_SEED_STRIDE:
            raise InputError(f"frames: at most {SOURCE_SEED_STRIDE} clips per source seed, got {clips}")
        self.scale = _check_scale(scale)
        self.density = _check_density(density)
        self.ego_speed = None if ego_speed is None else float(ego_speed)
        if self.ego_speed is not None and not (math.isfinite(self.ego_speed) and self.ego_speed >= 0):
            raise InputError(f"data.ego_speed_mps: a speed >= 0 m/s or null, got {ego_speed!r}")
        self._clip: tuple[int, SyntheticSequence] | None = None

    def __len__(self) -> int:
        return self.clips * self.length

    def _locate(self, i: int) -> tuple[int, int]:
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)):
            raise InputError(f"index: expected an integer, got {i!r}")
        i = int(i) + (len(self) if int(i) < 0 else 0)
        if not 0 <= i < len(self):
            raise IndexError(f"index {i} out of range for {len(self)} frame pairs")
        return i // self.length, i % self.length + 1

    def sequence(self, clip: int) -> SyntheticSequence:
        """The clip's scene (the last one used is kept: its rendered frames are reused)."""
        if self._clip is None or self._clip[0] != clip:
            self._clip = (clip, SyntheticSequence(self.seed * SOURCE_SEED_STRIDE + clip, self.length, scale=self.scale,
                                                  density=self.density, ego_speed=self.ego_speed))
        return self._clip[1]

    def sequence_key(self, i: int) -> str:
        return f"synthetic/{self.seed}/{self._locate(i)[0]}"

    def previous_frames(self, i: int, window: int) -> list[PreviousFrame]:
        clip, j = self._locate(i)
        seq = self.sequence(clip)
        return [PreviousFrame(back=b, dt=FRAME_INTERVAL_S * b, motion=seq.motion(j, j - b),
                              name=f"synthetic_{self.seed}_{clip:06d}_{j - b:03d}")
                for b in range(1, min(int(window), j) + 1)]

    def pair_back(self, i: int, back: int) -> FramePair:
        clip, j = self._locate(i)
        pair = self.sequence(clip).pair(j, j - int(back))
        pair.name = f"synthetic_{self.seed}_{clip:06d}_{j:03d}"
        pair.meta.update({"seed": self.seed, "clip": clip, "sequence": self.sequence_key(i), "back": int(back),
                          "name_prev": f"synthetic_{self.seed}_{clip:06d}_{j - int(back):03d}"})
        return pair

    def __getitem__(self, i: int) -> FramePair:
        return self.pair_back(i, 1)

    def __iter__(self) -> Iterator[FramePair]:
        for i in range(len(self)):
            yield self[i]
