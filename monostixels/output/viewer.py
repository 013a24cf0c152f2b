"""A 3D recording of `monostixels run` for the Rerun viewer (``output.rerun=true``).

``monostixels run ... output.rerun=true`` writes ``<outputs>/run/recording.rrd``; ``rerun FILE.rrd``
opens it. Needs the optional extra: ``pip install -e ".[viewer]"`` (``rerun-sdk``).

Entities, per frame on the ``frame`` timeline (the pair's index in the run) and, for videos, on
``time`` (seconds into the video):

- ``world``: the first camera's frame, declared to the viewer as x right, y down, z forward (RDF,
  docs/conventions.md, section 2); ``world/trajectory``: the camera centres so far.
- ``world/camera``: the camera pose (camera-to-world, chained ego-motion, see
  :class:`monostixels.output.scene3d.PoseChain`); ``world/camera/image``: its pinhole (K, image size) with
  ``rgb`` (the image) and ``depth`` (the stixel depth map, metres) below it;
  ``world/camera/points``: the point cloud of the depth map (camera frame, every k-th pixel).
- ``world/stixels``: one box per static or dynamic object stixel (world frame), coloured by class
  or by depth, labelled with track id and TTC where the sequence layer provides them;
  ``world/movers``: an arrow per dynamic stixel, its velocity (m/s, world frame) where known,
  else its motion between the pair's frames (metres).
- ``log``: a line per frame whose camera motion was degenerate.

Ground and sky stixels are not drawn as boxes: the point cloud shows the road. The settings: the config
group ``output`` (:class:`OutputConfig`).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch

from monostixels._checks import InputError, choice
from monostixels.core.classes import DYNAMIC_OBJECT, PALETTE
from monostixels.data.base import source_info
from monostixels.pipeline import EvalConfig
from monostixels.output.scene3d import PoseChain, frame_time, optional_field, reference_points, stixel_boxes, to_world

__all__ = ["RerunColors", "OutputConfig", "RecordingHook", "RerunRecorder", "open_recorder", "require_rerun"]

#: ``output.rerun_colors``: the colour of the recorded stixel boxes (OmegaConf refuses any other name).
RerunColors = choice("RerunColors", "class depth", __name__)


@dataclass
class OutputConfig:
    """What ``monostixels run`` writes beside its per-frame files (docs/conventions.md, section 4.3): the
    schema of the config group ``output`` (monostixels.config_schema).

    Attributes:
        rerun: write a 3D recording for the Rerun viewer, ``<outputs>/run/recording.rrd`` (needs the optional
            extra: ``pip install -e ".[viewer]"``).
        rerun_colors: colour of the stixel boxes: ``class`` (Cityscapes palette) or ``depth`` (inverse depth,
            as depth.png).
        rerun_point_stride: the point cloud holds every k-th pixel in each direction (1 = all; about 15 bytes
            per point per frame: a KITTI frame takes ~0.4 MB with 4, ~7 MB with 1).
        rerun_jpeg_quality: JPEG quality of the recorded images (1-100), or None for raw RGB (3 bytes per
            pixel per frame).
    """

    rerun: bool = False
    rerun_colors: RerunColors = RerunColors["class"]
    rerun_point_stride: int = 4
    rerun_jpeg_quality: Optional[int] = 85

logger = logging.getLogger(__name__)

#: Name of the recording file under ``<outputs>/run``.
RECORDING_NAME = "recording.rrd"
#: Depth image units: 1/256 m per step in uint16, as depth16.png (KITTI's depth PNG scale).
_DEPTH_UNITS_PER_M = 256.0
_UINT16_MAX = 65535
#: Colour of the velocity arrows (RGB), apart from every class colour.
_ARROW_RGB = (255, 200, 0)
#: Default 3D eye, world frame (y down), metres: left of, above and behind the first camera,
#: looking at the road 15 m ahead.
_EYE_OFFSET_M = (-4.0, -9.0, -14.0)
_EYE_TARGET_M = (0.0, 0.0, 15.0)
#: Drawn size of the camera: its axes and the distance of its image plane (metres).
_AXIS_LENGTH_M = 0.8
_IMAGE_PLANE_M = 1.5


def require_rerun() -> Any:
    """Import ``rerun`` or fail with the install command of the extra that provides it."""
    try:
        import rerun as rr
    except ImportError as e:
        raise InputError('output.rerun=true needs rerun-sdk, the optional "viewer" extra: '
                         'pip install -e ".[viewer]" (or pip install rerun-sdk)') from e
    return rr


class RecordingHook:
    """What ``monostixels run`` calls per frame and at the end; this one records nothing."""

    path: Path | None = None

    def log_frame(self, index: int, pair: Any, res: Any) -> None:
        """Record frame ``index`` (the pair's position in the run)."""

    def close(self) -> Path | None:
        """Finish the recording; returns its path, None where nothing was recorded."""
        return None


class RerunRecorder(RecordingHook):
    """Writes a Rerun recording (``.rrd``) of a run, one frame pair at a time.

    Args:
        path: the ``.rrd`` file to write (its folder is created).
        fps: the video's frame rate for the ``time`` timeline (None: no time timeline).
        colors: ``"class"`` (Cityscapes palette) or ``"depth"`` (inverse depth, like depth.png).
        point_stride: point cloud of every k-th pixel in each direction (1 = all pixels).
        jpeg_quality: JPEG quality (1-100) of the stored images, or None for raw RGB.
        min_depth, max_depth: colour range of ``colors="depth"`` (metres); the point cloud
            stops at ``max_depth``.

    Raises:
        InputError: rerun-sdk is not installed; a bad ``colors``, ``point_stride`` or ``jpeg_quality``.
    """

    def __init__(self, path: str | Path, *, fps: float | None = None, colors: RerunColors | str = "class", point_stride: int = 4,
                 jpeg_quality: int | None = 85, min_depth: float = 2.0, max_depth: float = 80.0) -> None:
        rr = require_rerun()
        if colors not in RerunColors.__members__:  # the config's value is one (RerunColors); a caller's may not be
            raise InputError(f"output.rerun_colors: expected one of {', '.join(RerunColors.__members__)}, got {colors!r}")
        if int(point_stride) < 1:
            raise InputError(f"output.rerun_point_stride: must be a positive number of pixels, got {point_stride}")
        if jpeg_quality is not None and not 1 <= int(jpeg_quality) <= 100:
            raise InputError(f"output.rerun_jpeg_quality: must be in 1..100 or null (raw), got {jpeg_quality}")
        self._rr = rr
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.fps = float(fps) if fps else None
        self.colors, self.point_stride = colors, int(point_stride)
        self.jpeg_quality = None if jpeg_quality is None else int(jpeg_quality)
        self.min_depth, self.max_depth = float(min_depth), float(max_depth)
        self.frames = 0
        self._poses = PoseChain()
        self._centres: list[np.ndarray] = []
        self._rec = rr.RecordingStream("monostixels", recording_id=self.path.stem)
        self._rec.save(str(self.path))
        # Frames are indexed by our own timelines; the wall clock of logging means nothing here.
        self._rec.set_log_time_enabled(False)
        self._rec.set_log_tick_enabled(False)
        self._rec.log("world", rr.ViewCoordinates.RDF, static=True)
        self._rec.log("world/camera", rr.TransformAxes3D(_AXIS_LENGTH_M), static=True)
        self._send_blueprint()

    def _send_blueprint(self) -> None:
        """Default layout: the 3D world (seen from above and behind the camera, following it) beside
        the camera image and the depth image; side panels folded away, the timeline kept."""
        try:
            import rerun.blueprint as rrb
        except ImportError:  # the recording is complete without a layout
            return
        eye = rrb.EyeControls3D(position=_EYE_OFFSET_M, look_target=_EYE_TARGET_M, eye_up=(0.0, -1.0, 0.0),
                                )
        self._rec.send_blueprint(rrb.Blueprint(
            rrb.Horizontal(
                # Not the depth image: the viewer would draw it as a second point cloud, in false colours.
                rrb.Spatial3DView(origin="world", name="3D", eye_controls=eye,
                                  contents=["+ /world/**", "- /world/camera/image/depth"]),
                rrb.Vertical(rrb.Spatial2DView(origin="world/camera/image", name="image",
                                               contents=["world/camera/image/rgb"]),
                             rrb.Spatial2DView(origin="world/camera/image", name="depth",
                                               contents=["world/camera/image/depth"])),
                column_shares=[3, 2]),
            rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
            rrb.TimePanel(state="collapsed")))

    # ------------------------------------------------------------------ per frame
    def _box_colors(self, world: Any, index: np.ndarray) -> np.ndarray:
        """RGB (M, 3) uint8 of the boxes of stixels ``index``."""
        if self.colors == "class":
            return np.asarray(PALETTE, dtype=np.uint8)[world.cls[index].numpy()]
        from monostixels.output.viz import depth_colormap

        depth = world.depth[index].double().numpy()
        return depth_colormap(depth[None, :], min_depth=self.min_depth, max_depth=self.max_depth)[0]

    @staticmethod
    def _labels(world: Any, index: np.ndarray) -> list[str] | None:
        """``#track TTC s`` per box where the sequence layer gives track ids or TTCs, else None."""
        track, ttc = optional_field(world, "track_id"), optional_field(world, "ttc_s")
        if track is None and ttc is None:
            return None
        labels = []
        for i in index:
            parts = [] if track is None or int(track[i]) < 0 else [f"#{int(track[i])}"]
            if ttc is not None and math.isfinite(float(ttc[i])):
                parts.append(f"TTC {float(ttc[i]):.1f} s")
            labels.append(" ".join(parts))
        return labels

    def _mover_vectors(self, pair: Any, world: Any, pose: np.ndarray, dyn: np.ndarray) -> np.ndarray:
        """World-frame arrow (M, 3) of dynamic stixels ``dyn``: velocity m/s where known, else motion."""
        velocity = optional_field(world, "velocity")
        if velocity is not None:
            return np.asarray(velocity, dtype=np.float64).reshape(-1, 3)[dyn]
        # Δ: the object's displacement between the pair's frames, current camera frame, metres.
        delta = world.motion.double().numpy()[dyn] @ pose[:3, :3].T
        dt = pair.info.dt
        return delta / float(dt) if dt else delta

    def log_frame(self, index: int, pair: Any, res: Any) -> None:
        """Record one frame pair's result: camera, image, depth, points, stixel boxes, mover arrows.

        Args:
            index: the frame's position in the run (the ``frame`` timeline).
            pair: the :class:`~monostixels.data.base.FramePair`. res: its
                :class:`~monostixels.pipeline.PipelineResult` (optionally with ``pose`` (4, 4)).
        """
        from monostixels.output.io import depth_to_points
        from monostixels.output.viz import image_to_uint8

        rr, rec = self._rr, self._rec
        world = res.stixels
        pose = self._poses.update(pair, res)
        rec.set_time("frame", sequence=int(index))
        t = frame_time(pair, self.fps)
        if t is not None:
            rec.set_time("time", duration=t)
        H, W = pair.size
        K = pair.camera.K.double().numpy()
        rec.log("world/camera", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        rec.log("world/camera/image", rr.Pinhole(image_from_camera=K, resolution=[W, H],
                                                 camera_xyz=rr.ViewCoordinates.RDF,
                                                 image_plane_distance=_IMAGE_PLANE_M))
        image = rr.Image(image_to_uint8(pair.image))
        rec.log("world/camera/image/rgb", image.compress(self.jpeg_quality) if self.jpeg_quality else image)
        depth = world.depth_map()
        finite = torch.where(torch.isfinite(depth) & (depth > 0), depth, torch.zeros_like(depth))
        d16 = np.clip(np.round(finite.double().numpy() * _DEPTH_UNITS_PER_M), 0, _UINT16_MAX).astype(np.uint16)
        rec.log("world/camera/image/depth", rr.DepthImage(d16, meter=_DEPTH_UNITS_PER_M))
        s = self.point_stride
        pts, cols = depth_to_points(finite[::s, ::s], _scaled_K(K, s), pair.image[:, ::s, ::s],
                                    max_depth=self.max_depth)
        rec.log("world/camera/points", rr.Points3D(pts, colors=cols, radii=rr.Radius.ui_points(2.0)))

        boxes = stixel_boxes(world)
        R = pose[:3, :3] @ boxes.rotations if len(boxes) else np.zeros((0, 3, 3))
        from scipy.spatial.transform import Rotation

        quats = Rotation.from_matrix(R).as_quat() if len(boxes) else np.zeros((0, 4))  # x y z w
        rec.log("world/stixels", rr.Boxes3D.from_fields(
            clear_unset=True, centers=to_world(pose, boxes.centers), half_sizes=boxes.half_sizes,
            quaternions=quats, colors=self._box_colors(world, boxes.index),
            labels=self._labels(world, boxes.index), fill_mode="solid"))

        dyn = np.nonzero(world.type.numpy() == DYNAMIC_OBJECT)[0]
        origins = to_world(pose, reference_points(world)[dyn])
        vectors = self._mover_vectors(pair, world, pose, dyn) if len(dyn) else np.zeros((0, 3))
        ok = np.isfinite(origins).all(-1) & np.isfinite(vectors).all(-1) & (np.linalg.norm(vectors, axis=-1) > 0)
        rec.log("world/movers", rr.Arrows3D(origins=origins[ok], vectors=vectors[ok], colors=[_ARROW_RGB]))

        self._centres.append(pose[:3, 3].copy())
        rec.log("world/trajectory", rr.LineStrips3D([np.asarray(self._centres)]))
        if world.status.motion.degenerate:
            rec.log("log", rr.TextLog(f"{pair.name}: {world.status.motion.reason or 'degenerate camera motion'}",
                                      level="WARN"))
        self.frames += 1

    def close(self) -> Path:
        """Flush the recording to disk; returns its path."""
        self._rec.flush()
        self._rec.disconnect()
        logger.info("rerun: %d frame(s) -> %s (open it with: rerun %s)", self.frames, self.path, self.path)
        return self.path


def _scaled_K(K: np.ndarray, stride: int) -> torch.Tensor:
    """Intrinsics of an image subsampled as ``img[::s, ::s]``: pixel ``u' = u / s``."""
    S = np.diag([1.0 / stride, 1.0 / stride, 1.0])
    return torch.from_numpy(S @ K)


def open_recorder(out: Path, src: Any, *, ev: EvalConfig, output: OutputConfig) -> RecordingHook:
    """The recording hook of ``monostixels run``: a :class:`RerunRecorder` writing
    ``out/recording.rrd`` where ``output.rerun`` is true, else one that records nothing.

    Args:
        out: ``<outputs>/run``. src: the data source (its ``fps``, for videos, gives the ``time`` timeline).
        ev, output: the ``eval`` and ``output`` groups' settings.

    Raises:
        InputError: ``output.rerun=true`` without rerun-sdk installed (checked before any frame runs).
    """
    if not output.rerun:
        return RecordingHook()
    return RerunRecorder(out / RECORDING_NAME, fps=source_info(src).fps, colors=output.rerun_colors,
                         point_stride=output.rerun_point_stride, jpeg_quality=output.rerun_jpeg_quality,
                         min_depth=ev.colormap_min_depth, max_depth=ev.colormap_max_depth)
