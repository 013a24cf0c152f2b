"""The synthetic scenes' renderer: textures, appearance, ray casting, surfaces and shading.

The machinery behind :mod:`monostixels.data.synthetic` (its docstring states the method and the
conventions): a :class:`~monostixels.data._scene.SceneLayout` becomes primitives (:func:`_geometry`),
rays are cast against them per pixel (:func:`_cast_points`, :func:`_cast_grid`), the hit surfaces are
textured in their own coordinates and Lambert-shaded (:func:`_render`), and the flow's validity is
read from both frames' casts (:func:`_flow_validity`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from monostixels.data._scene import (
    BUILDING, KERB_HEIGHT_M, PERSON, POLE, ROAD, SIDEWALK, SKY, STYLE_CLOTHES, STYLE_FACADE,
    STYLE_GLASS, TERRAIN, TWO_WHEELER, VEGETATION, VEHICLE, RoadLayout, SceneLayout,
)

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
