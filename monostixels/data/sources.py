"""The one factory that turns the ``data`` config group into a sequence of frame pairs.

``make_source(cfg)`` dispatches on ``cfg.name`` (docs/conventions.md, section 4.8): ``synthetic``,
``kitti2015``, ``kitti_raw``, ``ddad``, ``frames``, ``video``. ``cfg`` is either the ``data`` group
or the whole config (with ``data`` and ``camera`` entries); the camera group supplies the default
mounting height and pitch.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from monostixels._checks import InputError, config_value
from monostixels.data.base import FramePair
from monostixels.core.geometry import KITTI_CAMERA_HEIGHT_M
from monostixels.inputs.static_regions import AUTO_MASK

__all__ = ["SOURCE_NAMES", "camera_mount", "make_source"]

logger = logging.getLogger(__name__)


def camera_mount(data: Any, camera: Any) -> tuple[float, float]:
    """(height metres, pitch radians): data.camera_height, else camera.height, else KITTI 1.65 m."""
    height = config_value(data, "camera_height", config_value(camera, "height", KITTI_CAMERA_HEIGHT_M))
    pitch = config_value(camera, "pitch", 0.0)
    return float(height), float(pitch)


def _frames(data: Any) -> int | None:
    n = config_value(data, "frames")
    return None if n is None else int(n)


def _synthetic(data: Any, camera: Any) -> Sequence[FramePair]:
    from monostixels.data.synthetic import SyntheticSequenceSource, SyntheticSource  # imported lazily

    length = config_value(data, "sequence_length", 1)
    if isinstance(length, bool) or not isinstance(length, int) or length < 1:
        raise InputError(f"data.sequence_length: frames per synthetic clip, an integer >= 1, got {length!r}")
    speed = config_value(data, "ego_speed_mps")
    if length == 1:
        if speed is not None:
            raise InputError("data.ego_speed_mps: only for synthetic sequences (data.sequence_length > 1)")
        return SyntheticSource(
            int(config_value(data, "frames", 1)),
            seed=int(config_value(data, "seed", 0)),
            scale=float(config_value(data, "scale", 1.0)),
            density=float(config_value(data, "density", 1.0)),
        )
    try:
        speed = None if speed is None else float(speed)
    except (TypeError, ValueError):
        raise InputError(f"data.ego_speed_mps: a speed in m/s or null, got {speed!r}") from None
    return SyntheticSequenceSource(
        int(config_value(data, "frames", 1)), length,
        seed=int(config_value(data, "seed", 0)),
        scale=float(config_value(data, "scale", 1.0)),
        density=float(config_value(data, "density", 1.0)),
        ego_speed=speed,
    )


def _kitti2015(data: Any, camera: Any) -> Sequence[FramePair]:
    from monostixels.data.kitti2015 import Kitti2015Source

    height, pitch = camera_mount(data, camera)
    scenes = config_value(data, "scenes")
    return Kitti2015Source(
        config_value(data, "root"),
        split=str(config_value(data, "split", "training")),
        previous=str(config_value(data, "previous", "auto")),
        frames=_frames(data),
        scenes=None if scenes is None else [int(s) for s in scenes],
        fx=config_value(data, "fx"), fy=config_value(data, "fy"), cx=config_value(data, "cx"), cy=config_value(data, "cy"),
        camera_height=height, pitch=pitch,
    )


def _kitti_raw(data: Any, camera: Any) -> Sequence[FramePair]:
    from monostixels.data.kitti_raw import KittiRawSource

    height, pitch = camera_mount(data, camera)
    date = config_value(data, "date")
    return KittiRawSource(
        config_value(data, "root"),
        date=None if date is None else str(date),
        drive=config_value(data, "drive"),
        step=int(config_value(data, "step", 1)),
        frames=_frames(data),
        only_labelled=bool(config_value(data, "only_labelled", False)),
        camera_height=height, pitch=pitch,
        oxts=str(config_value(data, "oxts", "velocity")),
    )


def _ddad(data: Any, camera: Any) -> Sequence[FramePair]:
    from monostixels.data.ddad import MOVING_THRESHOLD_M, DDADSource

    h = config_value(data, "camera_height")
    scene = config_value(data, "scene")
    return DDADSource(
        config_value(data, "root"),
        camera=str(config_value(data, "camera", "CAMERA_01")),
        lidar=str(config_value(data, "lidar", "LIDAR")),
        scene=None if scene is None else str(scene),
        frames=_frames(data),
        camera_height=None if h is None else float(h),  # None: estimated from the LiDAR ground
        moving_threshold=float(config_value(data, "moving_threshold", MOVING_THRESHOLD_M)),
    )


def _frames_folder(data: Any, camera: Any) -> Sequence[FramePair]:
    from monostixels.data.frames import FramesSource

    height, pitch = camera_mount(data, camera)
    intr = config_value(data, "intrinsics")
    poses = config_value(data, "poses")
    mask = config_value(data, "mask")
    return FramesSource(
        config_value(data, "root"),
        intrinsics=None if intr is None else Path(str(intr)),
        step=int(config_value(data, "step", 1)),
        frames=_frames(data),
        camera_height=height, pitch=pitch,
        poses=None if poses is None else Path(str(poses)),
        mask=_mask(mask),
    )


def _mask(value: Any) -> str | Path | None:
    """``data.mask``: None, ``auto`` (found from the frames: :mod:`monostixels.inputs.static_regions`) or an image file."""
    if value is None:
        return None
    return AUTO_MASK if str(value).strip().lower() == AUTO_MASK else Path(str(value))


def _video(data: Any, camera: Any, window: int = 10) -> Sequence[FramePair]:
    from monostixels.data.video import LiveVideoSource, VideoSource, is_live_path

    height, pitch = camera_mount(data, camera)
    intr, hfov, end, resize, mask = (config_value(data, k) for k in ("intrinsics", "hfov_deg", "end", "resize", "mask"))
    if resize is not None and not isinstance(resize, (int, float, str)):
        resize = list(resize)
    realtime = config_value(data, "realtime", False)
    if not isinstance(realtime, bool):
        raise InputError(f"data.realtime: true or false, got {realtime!r}")
    path = config_value(data, "path")
    common = dict(
        intrinsics=None if intr is None else Path(str(intr)),
        hfov_deg=None if hfov is None else float(hfov),
        step=int(config_value(data, "step", 1)),
        start=int(config_value(data, "start", 0)),
        end=None if end is None else int(end),
        resize=resize,
        frames=_frames(data),
        camera_height=height, pitch=pitch,
        mask=_mask(mask),
    )
    if realtime or is_live_path(path):
        # Frames as they come: a camera index, a URL, or a file read at its frame rate (data.realtime).
        return LiveVideoSource(path, realtime=realtime, window=window, **common)  # type: ignore[return-value]
    return VideoSource(path, **common)


def _camvid(data: Any, camera: Any) -> Sequence[FramePair]:
    # Single labelled images: no previous frame, no camera. `monostixels eval` scores them
    # through monostixels.eval.semantic instead of this factory.
    raise InputError(
        "data=camvid holds labelled single images, not frame pairs: only `monostixels eval data=camvid` "
        "uses it (semantic metrics; no flow, motion or stixels)"
    )


_FACTORIES: dict[str, Callable[[Any, Any], Sequence[FramePair]]] = {
    "synthetic": _synthetic,
    "kitti2015": _kitti2015,
    "kitti_raw": _kitti_raw,
    "ddad": _ddad,
    "frames": _frames_folder,
    "camvid": _camvid,
    "video": _video,
}
#: Names accepted in ``data.name``.
SOURCE_NAMES: tuple[str, ...] = tuple(_FACTORIES)


def make_source(cfg: Mapping[str, Any] | Any, camera: Mapping[str, Any] | Any | None = None) -> Sequence[FramePair]:
    """Build the data source named by ``cfg.name``.

    Args:
        cfg: the ``data`` config group (dict or OmegaConf node) — or the whole config, in which
            case ``cfg.data`` and ``cfg.camera`` are used.
        camera: the ``camera`` config group (``height`` metres, ``pitch`` radians); optional.

    Returns:
        A sequence of :class:`FramePair` (``len`` and indexing; images are read on access).

    Raises:
        InputError: unknown ``name``, or any bad input of the chosen source (missing root, files,
            calibration...), with a message naming it.
    """
    data = cfg
    if config_value(cfg, "data") is not None and config_value(cfg, "name") is None:
        data = config_value(cfg, "data")
        camera = camera if camera is not None else config_value(cfg, "camera")
    name = config_value(data, "name")
    if name not in _FACTORIES:
        raise InputError(f"data.name: unknown data source {name!r}; choose one of {', '.join(SOURCE_NAMES)}")
    if name != "video" and config_value(data, "realtime") is not None:
        raise InputError(f"data.realtime: only data=video reads frames as they come (a camera, a URL, a video file "
                         f"at its frame rate); data={name} is read from disk frame by frame")
    if name == "video":
        # A live source keeps as many frames as keyframe pairs may reach back.
        window = config_value(config_value(cfg, "keyframes"), "window", 10) if data is not cfg else 10
        return _video(data, camera, int(window))
    return _FACTORIES[name](data, camera)
