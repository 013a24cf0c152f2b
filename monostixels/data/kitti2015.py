"""KITTI Scene Flow 2015: reference frames with disparity, moving-object and flow ground truth.

Layout under ``root`` (official ``data_scene_flow`` + ``data_scene_flow_calib``; ``root`` may be
the folder that holds ``training/`` or the split folder itself)::

    training/image_2/NNNNNN_10.png      reference (current) frame
    training/image_2/NNNNNN_11.png      the next frame in time
    training/image_2/NNNNNN_09.png      the frame before (only with the multiview extension)
    training/calib_cam_to_cam/NNNNNN.txt P_rect_02 -> intrinsics (optional: else config values)
    training/disp_occ_0/NNNNNN_10.png    disparity of frame 10 (uint16, /256, 0 = invalid)
    training/obj_map/NNNNNN_10.png       foreground-object ids of frame 10 (0 = background)
    training/flow_occ/NNNNNN_10.png      flow 10 -> 11 (uint16 u, v, valid)

Direction (our flow convention maps current -> previous, docs/conventions.md, section 2): the
reference frame ``_10`` is always the *current* image. Its partner ("previous") is chosen by
``previous``:

- ``"11"``: the ``_11`` frame, i.e. the pair is used **time-reversed** (the "previous" image is
  one frame in the future). KITTI's ``flow_occ`` (forward flow 10 -> 11) is then exactly our
  current -> previous flow, so flow ground truth is provided. A camera that drives forward
  appears to drive backwards (``t_z < 0`` in ``X_prev = R X_cur + t``).
- ``"09"``: the ``_09`` frame (multiview extension), true temporal order; no flow ground truth
  (KITTI has none for 10 -> 09).
- ``"auto"`` (default): ``_09`` where that file exists, else ``_11``.

``meta["previous"]`` and ``meta["time_reversed"]`` say which was used for every pair. KITTI 2015
has no poses: ``motion`` is None.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from monostixels._checks import InputError
from monostixels.data._camera_files import make_camera, projection_matrix, read_kitti_calib
from monostixels.data._lazy_source import LazySource, limit_frames
from monostixels.data._readers import read_image_pair, read_png16, require_dir, require_file
from monostixels.data.base import FramePair, GroundTruth
from monostixels.core.geometry import KITTI_CAMERA_HEIGHT_M, Camera

__all__ = [
    "Kitti2015Source",
    "KITTI_STEREO_BASELINE_M",
    "KITTI_DISP_SCALE",
    "KITTI_FLOW_OFFSET",
    "KITTI_FLOW_SCALE",
    "decode_disparity",
    "decode_flow",
]

logger = logging.getLogger(__name__)

#: Stereo baseline between the KITTI colour cameras 2 and 3 (metres; KITTI setup description,
#: Geiger et al. IJRR 2013: "baseline 54 cm"). depth = fx * baseline / disparity.
KITTI_STEREO_BASELINE_M = 0.54
#: KITTI disparity PNGs store disparity * 256 as uint16, 0 = no ground truth (devkit readme).
KITTI_DISP_SCALE = 256.0
#: KITTI flow PNGs store flow * 64 + 2^15 as uint16 per component, third channel = valid (devkit).
KITTI_FLOW_OFFSET = 2.0**15
KITTI_FLOW_SCALE = 64.0
#: Reference frame suffix and its neighbours.
_REF, _NEXT, _PREV = "_10", "_11", "_09"
_PREVIOUS_CHOICES = ("auto", "11", "09")


def decode_disparity(raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """KITTI uint16 disparity (H, W) -> (disparity pixels float32, valid bool)."""
    valid = raw > 0
    return raw.astype(np.float32) / KITTI_DISP_SCALE, valid


def decode_flow(raw_bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """KITTI uint16 flow PNG as read by OpenCV (H, W, 3) BGR -> (flow (2, H, W) px, valid (H, W)).

    The file stores (R, G, B) = (u, v, valid); OpenCV returns them as (B, G, R).
    """
    u = (raw_bgr[:, :, 2].astype(np.float32) - KITTI_FLOW_OFFSET) / KITTI_FLOW_SCALE
    v = (raw_bgr[:, :, 1].astype(np.float32) - KITTI_FLOW_OFFSET) / KITTI_FLOW_SCALE
    valid = raw_bgr[:, :, 0] > 0
    flow = np.stack([u, v]) * valid[None]
    return flow, valid


@dataclass
class _Scene:
    index: str
    image: Path
    image_prev: Path
    previous: str
    camera: Camera
    calib_source: str


class Kitti2015Source(LazySource):
    """Frame pairs of KITTI Scene Flow 2015 (reference frame ``_10`` is the current image).

    Args:
        root: folder holding ``training/`` (or the split folder itself).
        split: ``training`` or ``testing``.
        previous: ``"auto"``, ``"11"`` (time-reversed pair, flow ground truth available) or
            ``"09"`` (see the module docstring).
        frames: at most this many pairs (None = all).
        scenes: only these scene numbers (e.g. ``[0, 5]``); None = all.
        fx, fy, cx, cy: intrinsics (pixels) used only when the split has no ``calib_cam_to_cam``
            folder (a warning is logged); ``fy`` None = ``fx``.
        camera_height: camera height above the road (metres).
        pitch: camera pitch (radians, positive = looking down).

    Ground truth (where the files exist): ``gt.depth`` from ``disp_occ_0`` (fx * 0.54 m /
    disparity, 0 = none), ``gt.instances`` and ``gt.moving`` from ``obj_map`` (the KITTI
    moving-object mask = obj_map > 0, docs/conventions.md, section 4.8),
    ``gt.flow``/``gt.flow_valid`` from ``flow_occ`` only for the time-reversed ``_11`` pairs.
    ``motion`` is None (no poses in KITTI 2015).

    Raises:
        InputError: missing root / image folder / calibration file, no intrinsics at all, no
            scenes, ``_09`` requested but missing.
    """

    def __init__(
        self,
        root: str | Path,
        *,
        split: str = "training",
        previous: str = "auto",
        frames: int | None = None,
        scenes: list[int] | None = None,
        fx: float | None = None,
        fy: float | None = None,
        cx: float | None = None,
        cy: float | None = None,
        camera_height: float = KITTI_CAMERA_HEIGHT_M,
        pitch: float = 0.0,
    ) -> None:
        base = require_dir(root, "kitti2015 data.root")
        self.folder = base if (base / "image_2").is_dir() else base / split
        image_dir = require_dir(self.folder / "image_2", f"kitti2015 image folder ({split})")
        previous = str(previous)
        if previous not in _PREVIOUS_CHOICES:
            raise InputError(f"data.previous: must be one of {_PREVIOUS_CHOICES}, got {previous!r}")
        refs = sorted(image_dir.glob(f"*{_REF}.png"))
        if scenes is not None:
            wanted = {int(s) for s in scenes}
            refs = [r for r in refs if int(r.stem[: -len(_REF)]) in wanted]
        if not refs:
            raise InputError(f"kitti2015: {image_dir} holds no NNNNNN_10.png reference frames"
                             + (f" for scenes {sorted(int(s) for s in scenes)}" if scenes is not None else ""))
        calib_dir = self.folder / "calib_cam_to_cam"
        if not calib_dir.is_dir():
            if fx is None or cx is None or cy is None:
                raise InputError(
                    f"kitti2015: no calibration folder {calib_dir} and no data.fx/data.cx/data.cy in the config"
                )
            logger.warning("kitti2015: no %s; using config intrinsics fx=%s fy=%s cx=%s cy=%s for every scene",
                           calib_dir, fx, fy if fy is not None else fx, cx, cy)
        items: list[_Scene] = []
        # Limit first so that only the used scenes need their neighbour and calibration files.
        refs = limit_frames(refs, frames, f"kitti2015 {image_dir}")
        for ref in refs:
            idx = ref.stem[: -len(_REF)]
            nxt, prv = image_dir / f"{idx}{_NEXT}.png", image_dir / f"{idx}{_PREV}.png"
            if previous == "09" or (previous == "auto" and prv.exists()):
                partner, which = require_file(prv, f"kitti2015 previous frame of scene {idx}"), "09"
            else:
                partner, which = require_file(nxt, f"kitti2015 neighbour frame of scene {idx}"), "11"
            if calib_dir.is_dir():
                cpath = require_file(calib_dir / f"{idx}.txt", f"kitti2015 calibration of scene {idx}")
                P = projection_matrix(read_kitti_calib(cpath), "P_rect_02", cpath)
                cam = make_camera(P[0, 0], P[1, 1], P[0, 2], P[1, 2], camera_height, pitch)
                src = str(cpath)
            else:
                cam = make_camera(float(fx), float(fy if fy is not None else fx), float(cx), float(cy),  # type: ignore[arg-type]
                                  camera_height, pitch)
                src = "config"
            items.append(_Scene(idx, ref, partner, which, cam, src))
        self._items = items
        logger.info("kitti2015: %d frame pairs under %s", len(self._items), self.folder)

    def _load(self, item: _Scene) -> FramePair:
        image, image_prev = read_image_pair(item.image, item.image_prev)
        H, W = image.shape[-2:]
        gt = GroundTruth()
        fx = float(item.camera.K[0, 0])
        disp_path = self.folder / "disp_occ_0" / f"{item.index}{_REF}.png"
        if disp_path.exists():
            disp, valid = decode_disparity(self._gt_png(disp_path, 1, (H, W)))
            depth = np.zeros_like(disp)
            depth[valid] = fx * KITTI_STEREO_BASELINE_M / disp[valid]
            gt.depth = torch.from_numpy(depth)
        obj_path = self.folder / "obj_map" / f"{item.index}{_REF}.png"
        if obj_path.exists():
            obj = self._obj_map(obj_path, (H, W))
            gt.instances = torch.from_numpy(obj.astype(np.int64))
            gt.moving = torch.from_numpy(obj > 0)
        flow_path = self.folder / "flow_occ" / f"{item.index}{_REF}.png"
        if item.previous == "11" and flow_path.exists():
            # flow_occ is the forward flow 10 -> 11; with _11 as "previous" it is current -> previous.
            flow, fvalid = decode_flow(self._gt_png(flow_path, 3, (H, W)))
            # Pixels without ground truth carry no flow value at all (NaN), not a decoded 0.
            flow = np.where(fvalid[None], flow, np.nan).astype(np.float32)
            gt.flow = torch.from_numpy(flow)
            gt.flow_valid = torch.from_numpy(fvalid)
        meta = {"source": "kitti2015", "scene": item.index, "previous": item.previous,
                "time_reversed": item.previous == "11", "calibration": item.calib_source,
                "path": str(item.image), "path_prev": str(item.image_prev),
                "baseline_m": KITTI_STEREO_BASELINE_M}
        return FramePair(image=image, image_prev=image_prev, camera=item.camera, motion=None, gt=gt,
                         name=f"kitti2015_{item.index}", meta=meta)

    @staticmethod
    def _gt_png(path: Path, channels: int, size: tuple[int, int]) -> np.ndarray:
        raw = read_png16(path, channels)
        if raw.shape[:2] != size:
            raise InputError(f"kitti2015: ground truth {path} is {raw.shape[:2]} (H, W), image is {size}")
        return raw

    @staticmethod
    def _obj_map(path: Path, size: tuple[int, int]) -> np.ndarray:
        obj = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if obj is None:
            raise InputError(f"kitti2015: cannot read object map {path}")
        if obj.ndim == 3:
            raise InputError(f"kitti2015: object map {path} must be a single-channel id image, got {obj.shape[2]} channels")
        if obj.shape[:2] != size:
            raise InputError(f"kitti2015: object map {path} is {obj.shape[:2]} (H, W), image is {size}")
        return obj
