"""DDAD / TRI dgp scenes: one camera's consecutive samples with LiDAR depth, pose-based camera
motion and a moving-object mask from tracked 3D boxes.

Layout under ``root`` (TRI dgp "scene dataset")::

    root/scene_dataset_v1.0.json            optional: scene_splits -> scene json file names
    root/SCENE/scene_<hash>.json            samples (timesteps) and data (datums)
    root/SCENE/calibration/<key>.json       names, intrinsics, extrinsics (sensor -> vehicle)
    root/SCENE/rgb/CAMERA_01/<ts>.jpg       images
    root/SCENE/point_cloud/LIDAR/<ts>.npz   "data": (N, 4+) X, Y, Z, INTENSITY in the LiDAR frame
    root/SCENE/bounding_box_3d/LIDAR/<ts>.json  3D boxes in the LiDAR frame with instance ids

JSON structure read here (dgp protos, as JSON):

- scene: ``samples[i] = {"id": {"timestamp": ISO-8601, ...}, "datum_keys": [...],
  "calibration_key": str}``; ``data[j] = {"key": str, "id": {"name": "CAMERA_01" | "LIDAR",
  "timestamp": ...}, "datum": {"image": {...}} | {"point_cloud": {...}}}``. (The datums'
  ``prev_key``/``next_key`` links are not used: samples are ordered by timestamp.)
- image / point_cloud datum: ``filename`` (relative to the scene folder), ``annotations``
  (``"1"`` = bounding_box_3d file), ``pose`` = sensor -> world as
  ``{"rotation": {"qw", "qx", "qy", "qz"}, "translation": {"x", "y", "z"}}``.
- calibration: parallel lists ``names``, ``intrinsics`` (``fx, fy, cx, cy, skew``) and
  ``extrinsics`` (sensor -> vehicle body pose, same pose format).
- box: ``{"box": {"pose" (box -> sensor), "length" (along box x), "width" (y), "height" (z)},
  "instance_id", "class_id", "num_points"}``.

Pairs: current = sample ``i``, previous = sample ``i - 1`` (consecutive timesteps). Camera motion
from the camera datum poses (``X_prev = R X_cur + t``, docs/conventions.md, section 2): no
translation is faked — the shared sample's ego vehicle stands still and ``|t|`` is millimetres.
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from monostixels._checks import InputError
from monostixels.data._camera_files import make_camera, relative_motion
from monostixels.data._lazy_source import LazySource, limit_frames
from monostixels.data._readers import read_image_pair, require_dir, require_file
from monostixels.data.base import FramePair, GroundTruth
from monostixels.core.geometry import Motion

__all__ = [
    "DDADSource",
    "MOVING_THRESHOLD_M",
    "pose_matrix",
    "project_points",
    "estimate_ground_height",
]

logger = logging.getLogger(__name__)

#: A tracked box whose centre moves more than this in the world between the two timesteps of a
#: pair is a moving object (metres; above box-annotation jitter of a few cm, below the ~0.4 m a
#: pedestrian walks in the 1 s between the shared sample's timesteps).
MOVING_THRESHOLD_M = 0.2
#: LiDAR points closer than this to the camera plane are not projected (metres).
MIN_DEPTH_M = 0.1
#: Ground-height estimate: LiDAR points in this patch in front of the vehicle (vehicle frame,
#: x forward, y left, metres) vote in a histogram of z with this bin width; the points within
#: ``GROUND_BAND_M`` of the best bin give the ground height (their median).
GROUND_PATCH_X_M = (3.0, 15.0)
GROUND_PATCH_Y_M = 4.0
GROUND_BIN_M = 0.05
GROUND_BAND_M = 0.1
#: Annotation key of 3D boxes in a datum's ``annotations`` (dgp AnnotationType BOUNDING_BOX_3D).
_BOX3D_KEY = "1"
_SCENE_DATASET = "scene_dataset_v1.0.json"


def pose_matrix(pose: dict[str, Any], what: str) -> np.ndarray:
    """4x4 float64 transform from a dgp pose dict (unit quaternion ``qw, qx, qy, qz`` + translation)."""
    try:
        q = pose["rotation"]
        t = pose["translation"]
        w, x, y, z = (float(q.get(k, 0.0)) for k in ("qw", "qx", "qy", "qz"))
        tr = [float(t.get(k, 0.0)) for k in ("x", "y", "z")]
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise InputError(f"{what}: malformed pose {pose!r} (need rotation qw qx qy qz, translation x y z)") from e
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not math.isfinite(n) or abs(n - 1.0) > 1e-3:
        raise InputError(f"{what}: pose rotation quaternion has norm {n}, expected 1")
    w, x, y, z = w / n, x / n, y / n, z / n
    T = np.eye(4)
    T[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    T[:3, 3] = tr
    return T


def project_points(X_cam: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project camera-frame points, keeping the nearest point per pixel.

    Convention: pixel centres at integer coordinates; a point falls into pixel
    ``(round(u), round(v))``.

    Args:
        X_cam: (N, 3) points in the camera frame (metres).
        K: (3, 3) intrinsics.
        size: (H, W).

    Returns:
        (rows, cols, idx): pixel indices (M,) and the index (M,) into ``X_cam`` of the nearest
        point of each hit pixel (points behind the camera or outside the image are dropped).
    """
    H, W = size
    z = X_cam[:, 2]
    front = np.nonzero(z > MIN_DEPTH_M)[0]
    uvw = X_cam[front] @ K.T
    u = np.round(uvw[:, 0] / uvw[:, 2]).astype(np.int64)
    v = np.round(uvw[:, 1] / uvw[:, 2]).astype(np.int64)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    idx, u, v = front[inside], u[inside], v[inside]
    # Nearest point per pixel: sort by depth, keep the first occurrence of every pixel.
    order = np.argsort(z[idx], kind="stable")
    lin = (v * W + u)[order]
    _, first = np.unique(lin, return_index=True)
    keep = order[first]
    return v[keep], u[keep], idx[keep]


def estimate_ground_height(points_vehicle: np.ndarray) -> float:
    """Height (vehicle-frame z, metres) of the road in front of the vehicle from LiDAR points.

    Args:
        points_vehicle: (N, 3) LiDAR points in the vehicle frame (x forward, y left, z up).

    Raises:
        InputError: too few points in the patch in front of the vehicle.
    """
    x, y, z = points_vehicle.T
    m = (x > GROUND_PATCH_X_M[0]) & (x < GROUND_PATCH_X_M[1]) & (np.abs(y) < GROUND_PATCH_Y_M)
    zs = z[m]
    if zs.size < 50:
        raise InputError("ddad: too few LiDAR points in front of the vehicle to estimate the ground; set data.camera_height")
    bins = np.arange(zs.min(), zs.max() + GROUND_BIN_M, GROUND_BIN_M)
    if bins.size < 2:
        return float(np.median(zs))
    hist, edges = np.histogram(zs, bins=bins)
    centre = 0.5 * (edges[hist.argmax()] + edges[hist.argmax() + 1])
    return float(np.median(zs[np.abs(zs - centre) < GROUND_BAND_M]))


def _load_json(path: Path, what: str) -> Any:
    p = require_file(path, what)
    try:
        return json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{what}: {p} is not valid JSON ({e})") from e


@dataclass
class _Sample:
    timestamp: str
    camera: dict[str, Any]  # image datum
    lidar: dict[str, Any] | None  # point_cloud datum
    calibration_key: str


@dataclass
class _Scene:
    folder: Path
    name: str
    samples: list[_Sample]
    calib_cache: dict[str, dict[str, Any]] = field(default_factory=dict)


@dataclass
class _Pair:
    scene: _Scene
    cur: _Sample
    prev: _Sample


class DDADSource(LazySource):
    """Frame pairs of one camera of TRI dgp (DDAD) scenes.

    Args:
        root: dataset folder (holding ``scene_dataset_v1.0.json`` and/or scene folders), or a
            scene folder.
        camera: camera datum name (``CAMERA_01`` = front camera).
        lidar: LiDAR datum name used for depth ground truth.
        scene: only this scene folder name (e.g. ``scene_01``); None = all scenes.
        frames: at most this many pairs (None = all).
        camera_height: camera height above the road (metres); None = estimated from the LiDAR
            ground in front of the vehicle (calibration extrinsics give the camera's height in the
            vehicle frame).
        moving_threshold: box displacement (metres) above which an object counts as moving.

    The ground normal comes from the calibration (the vehicle's up axis in the camera frame,
    i.e. the road is assumed parallel to the vehicle's x-y plane).

    Ground truth: ``motion`` (from the camera poses), ``gt.depth`` (LiDAR of the current
    timestep projected into the current camera, nearest point per pixel, 0 = none),
    ``gt.moving`` (True at LiDAR pixels whose point lies inside a 3D box that moved by more than
    ``moving_threshold`` between the timesteps; defined on depth pixels only, False elsewhere),
    ``meta["moving_instances"]``.

    Raises:
        InputError: missing root / scene / calibration / camera / files, malformed JSON or poses.
    """

    def __init__(
        self,
        root: str | Path,
        *,
        camera: str = "CAMERA_01",
        lidar: str = "LIDAR",
        scene: str | None = None,
        frames: int | None = None,
        camera_height: float | None = None,
        moving_threshold: float = MOVING_THRESHOLD_M,
    ) -> None:
        self.root = require_dir(root, "ddad data.root")
        self.camera_name = str(camera)
        self.lidar_name = str(lidar)
        self.camera_height = camera_height
        self.moving_threshold = float(moving_threshold)
        items: list[_Pair] = []
        for sf in self._scene_files(scene):
            sc = self._load_scene(sf)
            for i in range(1, len(sc.samples)):
                items.append(_Pair(sc, sc.samples[i], sc.samples[i - 1]))
        self._items = limit_frames(items, frames, f"ddad {self.root} (scenes need at least two samples)")
        logger.info("ddad: %d frame pairs of %s under %s", len(self._items), self.camera_name, self.root)

    # --- indexing -------------------------------------------------------------------------------
    def _scene_files(self, scene: str | None) -> list[Path]:
        files: list[Path] = []
        ds = self.root / _SCENE_DATASET
        if ds.exists():
            data = _load_json(ds, "ddad scene dataset")
            for split in (data.get("scene_splits") or {}).values():
                for fn in split.get("filenames", []):
                    p = self.root / fn
                    if p not in files:
                        files.append(p)
        else:
            files = sorted(self.root.glob("scene_*.json")) + sorted(self.root.glob("*/scene_*.json"))
        if scene is not None:
            files = [f for f in files if f.parent.name == str(scene)]
            if not files:
                raise InputError(f"ddad: scene {scene!r} not found under {self.root}")
        if not files:
            raise InputError(f"ddad: no scene_*.json files under {self.root}")
        for f in files:
            require_file(f, "ddad scene")
        return files

    def _load_scene(self, path: Path) -> _Scene:
        js = _load_json(path, "ddad scene")
        try:
            data = {d["key"]: d for d in js["data"]}
            raw_samples = js["samples"]
        except (KeyError, TypeError) as e:
            raise InputError(f"ddad scene: {path} lacks 'data'/'samples' (not a dgp scene file)") from e
        samples: list[_Sample] = []
        for s in raw_samples:
            cam = lid = None
            for k in s.get("datum_keys", []):
                if k not in data:
                    raise InputError(f"ddad scene: {path} sample refers to a missing datum {k}")
                d = data[k]
                name = d.get("id", {}).get("name")
                if name == self.camera_name:
                    cam = d["datum"].get("image")
                elif name == self.lidar_name:
                    lid = d["datum"].get("point_cloud")
            if cam is None:
                raise InputError(f"ddad scene: {path} has a sample without camera {self.camera_name!r}")
            samples.append(_Sample(str(s.get("id", {}).get("timestamp", "")), cam, lid, str(s.get("calibration_key", ""))))
        samples.sort(key=lambda s: s.timestamp)  # ISO-8601 strings sort chronologically
        return _Scene(path.parent, path.parent.name, samples)

    def _calibration(self, sc: _Scene, key: str) -> dict[str, Any]:
        if key not in sc.calib_cache:
            calib = _load_json(sc.folder / "calibration" / f"{key}.json", "ddad calibration")
            try:
                names = list(calib["names"])
                by_name = {n: (calib["intrinsics"][i], calib["extrinsics"][i]) for i, n in enumerate(names)}
            except (KeyError, IndexError, TypeError) as e:
                raise InputError(f"ddad calibration: {sc.folder / 'calibration' / key}.json lacks names/intrinsics/extrinsics") from e
            sc.calib_cache[key] = by_name
        return sc.calib_cache[key]

    # --- sequences (keyframes) ------------------------------------------------------------------
    def _sequence_key(self, item: _Pair) -> str:
        return f"ddad/{item.scene.name}/{self.camera_name}"

    def _back(self, item: _Pair, back: int) -> _Pair | None:
        i = item.scene.samples.index(item.cur) - int(back)
        return _Pair(item.scene, item.cur, item.scene.samples[i]) if i >= 0 else None

    def _pair_dt(self, item: _Pair) -> float | None:
        a, b = _iso_seconds(item.cur.timestamp), _iso_seconds(item.prev.timestamp)
        return a - b if a is not None and b is not None else None

    def _pair_motion(self, item: _Pair) -> Motion:
        sc = item.scene
        return relative_motion(pose_matrix(item.cur.camera.get("pose", {}), f"ddad {sc.name} {self.camera_name} pose"),
                               pose_matrix(item.prev.camera.get("pose", {}), f"ddad {sc.name} {self.camera_name} pose"))

    def _prev_name(self, item: _Pair) -> str:
        return f"ddad_{item.scene.name}_{self.camera_name}_{Path(item.prev.camera['filename']).stem}"

    # --- loading --------------------------------------------------------------------------------
    def _load(self, item: _Pair) -> FramePair:
        sc = item.scene
        calib = self._calibration(sc, item.cur.calibration_key)
        cpath = sc.folder / "calibration" / f"{item.cur.calibration_key}.json"
        if self.camera_name not in calib:
            raise InputError(f"ddad calibration: {cpath} has no camera {self.camera_name}")
        intr, extr = calib[self.camera_name]
        try:
            fx, fy, cx, cy = (float(intr[k]) for k in ("fx", "fy", "cx", "cy"))
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"ddad calibration: {cpath} intrinsics of {self.camera_name} lack fx/fy/cx/cy") from e
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        T_vehicle_cam = pose_matrix(extr, f"ddad calibration {cpath} extrinsics of {self.camera_name}")

        image, image_prev = read_image_pair(sc.folder / item.cur.camera["filename"], sc.folder / item.prev.camera["filename"])
        H, W = image.shape[-2:]
        T_w_cam = pose_matrix(item.cur.camera.get("pose", {}), f"ddad {sc.name} {self.camera_name} pose")
        motion = self._pair_motion(item)

        # Ground normal: vehicle up axis (+z) expressed in the camera frame, negated (points down).
        n_g = -T_vehicle_cam[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        gt = GroundTruth()
        meta: dict[str, Any] = {"source": "ddad", "scene": sc.name, "camera": self.camera_name,
                                "timestamp": item.cur.timestamp, "timestamp_prev": item.prev.timestamp,
                                "path": str(sc.folder / item.cur.camera["filename"]),
                                "path_prev": str(sc.folder / item.prev.camera["filename"]),
                                "sequence": self._sequence_key(item), "name_prev": self._prev_name(item),
                                "frame": sc.samples.index(item.cur), "frame_prev": sc.samples.index(item.prev)}
        dt = self._pair_dt(item)
        if dt is not None and dt > 0:
            meta["dt"] = dt
        height = self.camera_height
        if item.cur.lidar is not None:
            pts_lidar, T_w_lidar, T_vehicle_lidar = self._lidar(sc, item.cur.lidar, calib, cpath)
            # LiDAR -> world -> current camera (poses already include the ego motion between the
            # LiDAR and camera timestamps).
            T_cam_lidar = np.linalg.solve(T_w_cam, T_w_lidar)
            X_cam = pts_lidar @ T_cam_lidar[:3, :3].T + T_cam_lidar[:3, 3]
            rows, cols, idx = project_points(X_cam, K, (H, W))
            depth = np.zeros((H, W), dtype=np.float32)
            depth[rows, cols] = X_cam[idx, 2]
            gt.depth = torch.from_numpy(depth)
            moving_pts, moving_ids, vel_pts = self._moving_points(sc, item, pts_lidar, T_w_lidar)
            if moving_pts is not None:
                moving = np.zeros((H, W), dtype=bool)
                moving[rows, cols] = moving_pts[idx]
                gt.moving = torch.from_numpy(moving)
                meta["moving_instances"] = moving_ids
                dt = self._pair_dt(item)
                if vel_pts is not None and dt is not None and dt > 0:
                    # Box displacement per second, world axes -> current camera axes; NaN off the LiDAR.
                    vel = np.full((3, H, W), np.nan, dtype=np.float32)
                    vel[:, rows, cols] = ((vel_pts[idx] / dt) @ T_w_cam[:3, :3]).T
                    gt.velocity = torch.from_numpy(vel)
            if height is None:
                pts_vehicle = pts_lidar @ T_vehicle_lidar[:3, :3].T + T_vehicle_lidar[:3, 3]
                ground_z = estimate_ground_height(pts_vehicle)
                height = float(T_vehicle_cam[2, 3] - ground_z)
                meta["camera_height_source"] = "lidar ground estimate"
        if height is None:
            raise InputError(f"ddad: scene {sc.name} has no {self.lidar_name} datum to estimate the camera height; set data.camera_height")
        meta.setdefault("camera_height_source", "config")
        meta["camera_height_m"] = height
        camera = make_camera(fx, fy, cx, cy, height, ground_normal=n_g / np.linalg.norm(n_g))
        return FramePair(image=image, image_prev=image_prev, camera=camera, motion=motion, gt=gt,
                         name=f"ddad_{sc.name}_{self.camera_name}_{Path(item.cur.camera['filename']).stem}", meta=meta)

    def _lidar(self, sc: _Scene, datum: dict[str, Any], calib: dict[str, Any], cpath: Path
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        path = require_file(sc.folder / datum["filename"], "ddad point cloud")
        try:
            with np.load(path) as z:
                pts = np.asarray(z["data"], dtype=np.float64)
        except (OSError, ValueError, KeyError) as e:
            raise InputError(f"ddad point cloud: cannot read {path} (expected an npz with a 'data' (N, >=3) array)") from e
        if pts.ndim != 2 or pts.shape[1] < 3:
            raise InputError(f"ddad point cloud: {path} 'data' has shape {pts.shape}, expected (N, >=3)")
        T_w_lidar = pose_matrix(datum.get("pose", {}), f"ddad point cloud pose of {path}")
        if self.lidar_name not in calib:
            raise InputError(f"ddad calibration: {cpath} has no sensor {self.lidar_name}")
        T_vehicle_lidar = pose_matrix(calib[self.lidar_name][1], f"ddad calibration {cpath} extrinsics of {self.lidar_name}")
        return pts[:, :3], T_w_lidar, T_vehicle_lidar

    def _boxes(self, sc: _Scene, datum: dict[str, Any] | None) -> list[dict[str, Any]] | None:
        if datum is None or _BOX3D_KEY not in (datum.get("annotations") or {}):
            return None
        js = _load_json(sc.folder / datum["annotations"][_BOX3D_KEY], "ddad 3D boxes")
        return list(js.get("annotations", []))

    def _moving_points(self, sc: _Scene, item: _Pair, pts: np.ndarray, T_w_lidar: np.ndarray
                       ) -> tuple[np.ndarray | None, list[int], np.ndarray | None]:
        """Per LiDAR point: inside a box that moved more than the threshold, and the world displacement
        (N, 3) metres previous -> current of the box it lies in (0 outside boxes, NaN in a box without a
        previous pose); (None, [], None) without boxes."""
        boxes_cur = self._boxes(sc, item.cur.lidar)
        boxes_prev = self._boxes(sc, item.prev.lidar)
        if boxes_cur is None or boxes_prev is None or item.prev.lidar is None:
            return None, [], None
        T_w_lidar_prev = pose_matrix(item.prev.lidar.get("pose", {}), f"ddad {sc.name} {self.lidar_name} pose")
        prev_centre = {}
        for b in boxes_prev:
            T = T_w_lidar_prev @ pose_matrix(b["box"]["pose"], f"ddad box {b.get('instance_id')}")
            prev_centre[b["instance_id"]] = T[:3, 3]
        inside_moving = np.zeros(len(pts), dtype=bool)
        displacement = np.zeros((len(pts), 3))
        moving_ids: list[int] = []
        for b in boxes_cur:
            iid = b["instance_id"]
            T_lidar_box = pose_matrix(b["box"]["pose"], f"ddad box {iid}")
            T_box_lidar = np.linalg.inv(T_lidar_box)
            Xb = pts @ T_box_lidar[:3, :3].T + T_box_lidar[:3, 3]
            half = 0.5 * np.array([b["box"]["length"], b["box"]["width"], b["box"]["height"]], dtype=np.float64)
            inside = np.all(np.abs(Xb) <= half, axis=1)
            if iid not in prev_centre:
                displacement[inside] = np.nan  # new track: its motion is unknown, so it is not marked moving
                continue
            d = (T_w_lidar @ T_lidar_box)[:3, 3] - prev_centre[iid]
            displacement[inside] = d
            if float(np.linalg.norm(d)) <= self.moving_threshold:
                continue
            moving_ids.append(int(iid))
            inside_moving |= inside
        return inside_moving, moving_ids, displacement


def _iso_seconds(stamp: str) -> float | None:
    """Seconds since the epoch of an ISO-8601 timestamp (``2463-05-15T00:38:59.203480Z``), None if unparsable."""
    from datetime import datetime

    try:
        return datetime.fromisoformat(str(stamp).replace("Z", "+00:00")).timestamp()
    except ValueError:
        return None
