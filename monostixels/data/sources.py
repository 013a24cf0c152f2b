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

from monostixels._checks import InputError
from monostixels.data.base import FramePair
from monostixels.geometry import KITTI_CAMERA_HEIGHT_M
from monostixels.static_regions import AUTO_MASK

__all__ = ["SOURCE_NAMES", "camera_mount", "make_source"]

logger = logging.getLogger(__name__)


def _get(cfg: Any, key: str, default: Any = None) -> Any:
    """``cfg[key]`` for a dict or an OmegaConf node, ``default`` when absent or null."""
    if cfg is None:
        return default
    try:
        value = cfg.get(key, default)
    except AttributeError:
        value = getattr(cfg, key, default)
    return default if value is None else value


def camera_mount(data: Any, camera: Any) -> tuple[float, float]:
    """(height metres, pitch radians): data.camera_height, else camera.height, else KITTI 1.65 m."""
    height = _get(data, "camera_height", _get(camera, "height", KITTI_CAMERA_HEIGHT_M))
    pitch = _get(camera, "pitch", 0.0)
    return float(height), float(pitch)


def _frames(data: Any) -> int | None:
    n = _get(data, "frames")
    return None if n is None else int(n)


def _synthetic(data: Any, camera: Any) -> Sequence[FramePair]:
    from monostixels.data.synthetic import SyntheticSequenceSource, SyntheticSource  # imported lazily

    length = _get(data, "sequence_length", 1)
    if isinstance(length, bool) or not isinstance(length, int) or length < 1:
        raise InputError(f"data.sequence_length: frames per synthetic clip, an integer >= 1, got {length!r}")
    speed = _get(data, "ego_speed_mps")
    if length == 1:
        if speed is not None:
            raise InputError("data.ego_speed_mps: only for synthetic sequences (data.sequence_length > 1)")
        return SyntheticSource(
            int(_get(data, "frames", 1)),
            seed=int(_get(data, "seed", 0)),
            scale=float(_get(data, "scale", 1.0)),
            density=float(_get(data, "density", 1.0)),
        )
    try:
        speed = None if speed is None else float(speed)
    except (TypeError, ValueError):
        raise InputError(f"data.ego_speed_mps: a speed in m/s or null, got {speed!r}") from None
    return SyntheticSequenceSource(
        int(_get(data, "frames", 1)), length,
        seed=int(_get(data, "seed", 0)),
        scale=float(_get(data, "scale", 1.0)),
        density=float(_get(data, "density", 1.0)),
        ego_speed=speed,
    )


def _kitti2015(data: Any, camera: Any) -> Sequence[FramePair]:
    from monostixels.data.kitti2015 import Kitti2015Source

    height, pitch = camera_mount(data, camera)
    scenes = _get(data, "scenes")
    return Kitti2015Source(
        _get(data, "root"),
        split=str(_get(data, "split", "training")),
        previous=str(_get(data, "previous", "auto")),
        frames=_frames(data),
        scenes=None if scenes is None else [int(s) for s in scenes],
        fx=_get(data, "fx"), fy=_get(data, "fy"), cx=_get(data, "cx"), cy=_get(data, "cy"),
        camera_height=height, pitch=pitch,
    )


def _kitti_raw(data: Any, camera: Any) -> Sequence[FramePair]:
    from monostixels.data.kitti_raw import KittiRawSource

    height, pitch = camera_mount(data, camera)
    date = _get(data, "date")
    return KittiRawSource(
        _get(data, "root"),
        date=None if date is None else str(date),
        drive=_get(data, "drive"),
        step=int(_get(data, "step", 1)),
        frames=_frames(data),
        only_labelled=bool(_get(data, "only_labelled", False)),
        camera_height=height, pitch=pitch,
        oxts=str(_get(data, "oxts", "velocity")),
    )


def _ddad(data: Any, camera: Any) -> Sequence[FramePair]:
    from monostixels.data.ddad import MOVING_THRESHOLD_M, DDADSource

    h = _get(data, "camera_height")
    scene = _get(data, "scene")
    return DDADSource(
        _get(data, "root"),
        camera=str(_get(data, "camera", "CAMERA_01")),
        lidar=str(_get(data, "lidar", "LIDAR")),
        scene=None if scene is None else str(scene),
        frames=_frames(data),
        camera_height=None if h is None else float(h),  # None: estimated from the LiDAR ground
        moving_threshold=float(_get(data, "moving_threshold", MOVING_THRESHOLD_M)),
    )


def _frames_folder(data: Any, camera: Any) -> Sequence[FramePair]:
    from monostixels.data.frames import FramesSource

    height, pitch = camera_mount(data, camera)
    intr = _get(data, "intrinsics")
    poses = _get(data, "poses")
    mask = _get(data, "mask")
    return FramesSource(
        _get(data, "root"),
        intrinsics=None if intr is None else Path(str(intr)),
        step=int(_get(data, "step", 1)),
        frames=_frames(data),
        camera_height=height, pitch=pitch,
        poses=None if poses is None else Path(str(poses)),
        mask=_mask(mask),
    )


def _mask(value: Any) -> str | Path | None:
    """``data.mask``: None, ``auto`` (found from the frames: :mod:`monostixels.static_regions`) or an image file."""
    if value is None:
        return None
    return AUTO_MASK if str(value).strip().lower() == AUTO_MASK else Path(str(value))


def _video(data: Any, camera: Any, window: int = 10) -> Sequence[FramePair]:
    from monostixels.data.video import LiveVideoSource, VideoSource, is_live_path

    height, pitch = camera_mount(data, camera)
    intr, hfov, end, resize, mask = (_get(data, k) for k in ("intrinsics", "hfov_deg", "end", "resize", "mask"))
    if resize is not None and not isinstance(resize, (int, float, str)):
        resize = list(resize)
    realtime = _get(data, "realtime", False)
    if not isinstance(realtime, bool):
        raise InputError(f"data.realtime: true or false, got {realtime!r}")
    path = _get(data, "path")
    common = dict(
        intrinsics=None if intr is None else Path(str(intr)),
        hfov_deg=None if hfov is None else float(hfov),
        step=int(_get(data, "step", 1)),
        start=int(_get(data, "start", 0)),
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
    if _get(cfg, "data") is not None and _get(cfg, "name") is None:
        data = _get(cfg, "data")
        camera = camera if camera is not None else _get(cfg, "camera")
    name = _get(data, "name")
    if name not in _FACTORIES:
        raise InputError(f"data.name: unknown data source {name!r}; choose one of {', '.join(SOURCE_NAMES)}")
    if name != "video" and _get(data, "realtime") is not None:
        raise InputError(f"data.realtime: only data=video reads frames as they come (a camera, a URL, a video file "
                         f"at its frame rate); data={name} is read from disk frame by frame")
    if name == "video":
        # A live source keeps as many frames as keyframe pairs may reach back.
        window = _get(_get(cfg, "keyframes"), "window", 10) if data is not cfg else 10
        return _video(data, camera, int(window))
    return _FACTORIES[name](data, camera)
