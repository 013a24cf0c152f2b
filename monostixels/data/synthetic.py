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
same primitive at the same depth at the pixels around ``x_prev``; see
:func:`monostixels.data._render._flow_validity`),
10-class labels, instance ids, moving mask, camera motion and intrinsics.

Photometric consistency: a surface point has the same colour in both frames (texture in the
primitive's own coordinates, Lambert shading with a fixed sun, texture level of detail chosen from
the point's current-frame position), so warping the previous image by the ground-truth flow
reproduces the current image up to bilinear interpolation (tests/test_synthetic.py states the
bound). Sky colour depends on the world direction only; sky pixels carry the rotation-only flow
``K R K^-1`` but are not flow_valid (no depth).

The renderer itself: :mod:`monostixels.data._render`. Speed: ``benchmarks/render_speed.py``.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Iterator

import numpy as np
import torch

from monostixels._checks import InputError
from monostixels.data._render import _cast_grid, _flow_validity, _geometry, _render, _sample_appearance, _Surface
from monostixels.data._scene import FRAME_INTERVAL_S, KERB_HEIGHT_M, sample_scene
from monostixels.data.base import FramePair, GroundTruth, PreviousFrame, SourceAttributes
from monostixels.core.geometry import KITTI_CAMERA_HEIGHT_M, Camera, Motion, intrinsics

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


class SyntheticSource(SourceAttributes):
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


class SyntheticSequenceSource(SourceAttributes):
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
