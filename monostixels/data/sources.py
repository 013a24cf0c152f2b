"""The one factory that turns the ``data`` config group into a sequence of frame pairs.

``make_source(data, camera)`` dispatches on ``data.name`` (docs/conventions.md, section 4.8): ``synthetic``,
``kitti2015``, ``kitti_raw``, ``ddad``, ``frames``, ``video``. ``data`` is the ``data`` group's settings and
``camera`` the ``camera`` group's, which supplies the default mounting height and pitch; the builder
(:func:`monostixels.build.build_source`) reads both from a config.

Each option of ``data`` has its settings dataclass (:data:`DATA_SCHEMAS`, by ``name``), its schema in the
package config (monostixels.config_schema); ``camera``'s is :class:`CameraConfig`. A dict given by a library
user is read through the same dataclasses (:func:`data_params`).
"""
from __future__ import annotations

import logging
from pathlib import Path
from dataclasses import dataclass
from typing import Any, Callable, List, Optional, Union

from monostixels._checks import InputError, choice, config_params, option_params
from monostixels.data.base import FOLDER_FPS, Source
from monostixels.core.geometry import KITTI_CAMERA_HEIGHT_M
from monostixels.data.static_regions import AUTO_MASK

__all__ = ["SOURCE_NAMES", "DATA_SCHEMAS", "KittiSplit", "KittiPrevious", "CamVidSplit", "KittiOxts", "CameraConfig", "SyntheticDataConfig", "Kitti2015DataConfig",
           "KittiRawDataConfig", "DdadDataConfig", "FramesDataConfig", "VideoDataConfig", "CamVidDataConfig",
           "camera_mount", "data_params", "make_source"]

logger = logging.getLogger(__name__)

# The choices among names of the data settings: OmegaConf refuses any other value (monostixels._checks.Choice).
KittiSplit = choice("KittiSplit", "training testing", __name__)  # KITTI 2015's folders
KittiPrevious = choice("KittiPrevious", "auto 11 09", __name__)  # the partner of KITTI 2015's frame _10
CamVidSplit = choice("CamVidSplit", "train val test", __name__)  # CamVid's lists
KittiOxts = choice("KittiOxts", "velocity position", __name__)  # where KITTI raw's OXTS positions come from


@dataclass
class CameraConfig:
    """Camera mounting: the schema of the config group ``camera`` (monostixels.config_schema). The
    intrinsics come from the data source (calibration files or the renderer).

    Attributes:
        height: height of the camera above the road (metres); a data source's ``camera_height`` replaces
            it. KITTI's colour cameras: 1.65 m (KITTI setup description).
        pitch: pitch of the optical axis (radians; positive = looking down); tilts the ground normal.
    """

    height: float = KITTI_CAMERA_HEIGHT_M
    pitch: float = 0.0


@dataclass
class SyntheticDataConfig:
    """``data=synthetic``: the built-in street scenes (docs/conventions.md, section 6).

    Attributes:
        root: not read (the scenes are rendered); every data option has one.
        frames: frame pairs, or clips where ``sequence_length > 1``.
        seed: source seed; frame ``i`` is scene seed ``seed x 100000 + i``.
        scale: resolution relative to KITTI's 1242x375.
        density: multiplier of the number of objects in a scene.
        sequence_length: frames per clip: 1 = independent frame pairs; N > 1 = ``frames`` clips of N
            consecutive frame pairs of one scene (constant ego motion, movers at constant velocity), with
            keyframes and tracks.
        ego_speed_mps: ego speed of the clips (m/s; 0 = a standing camera); None = each scene's own (8-15 m/s).
    """

    name: str = "synthetic"
    root: Optional[str] = None
    frames: int = 1
    seed: int = 0
    scale: float = 1.0
    density: float = 1.0
    sequence_length: int = 1
    ego_speed_mps: Optional[float] = None


@dataclass
class Kitti2015DataConfig:
    """``data=kitti2015``: KITTI Scene Flow 2015 in its official layout (docs/conventions.md, section 4.8).

    Attributes:
        root: the folder holding ``training/`` (and ``testing/``).
        split: ``training`` | ``testing``.
        previous: partner of the reference frame ``_10`` (always the current image): ``auto`` = ``_09``
            where present (true temporal order, no flow ground truth), else ``_11``; ``"11"`` = ``_11``
            used time-reversed as the previous frame (KITTI's flow_occ 10->11 is then our current->previous
            ground truth); ``"09"`` = require ``_09`` (multiview extension).
        frames: at most this many frame pairs (None = every scene).
        scenes: scene numbers to read (None = all).
        fx, fy, cx, cy: intrinsics (pixels) used only where ``<split>/calib_cam_to_cam/`` is absent (a
            warning is logged): the 2011_09_26 camera of scene 000000 (P_rect_02). ``fy`` None = ``fx``.
        camera_height: camera height above the road (metres); None = ``camera.height``.
    """

    name: str = "kitti2015"
    root: Optional[str] = None
    split: KittiSplit = KittiSplit.training
    previous: KittiPrevious = KittiPrevious.auto
    frames: Optional[int] = None
    scenes: Optional[List[int]] = None
    fx: Optional[float] = 721.5377
    fy: Optional[float] = None
    cx: Optional[float] = 609.5593
    cy: Optional[float] = 172.854
    camera_height: Optional[float] = None


@dataclass
class KittiRawDataConfig:
    """``data=kitti_raw``: KITTI raw synced+rectified drives (docs/conventions.md, section 4.8), with their
    poses, OXTS, stixel-bottom labels and LiDAR depth where present.

    Attributes:
        root: the folder of the ``YYYY_MM_DD`` date folders.
        date: only this date (``YYYY_MM_DD``); None = every one found.
        drive: only this drive (its number or folder name); None = every one.
        step: pair = (frame n, frame n - step), raw frame numbers.
        frames: at most this many frame pairs (None = all).
        only_labelled: only pairs whose current frame has stixel-bottom labels.
        camera_height: camera height above the road (metres); None = ``camera.height``.
        oxts: where the OXTS poses' positions come from: ``velocity`` (integrated vf/vl/vu; steadier frame
            to frame) or ``position`` (GPS latitude/longitude, jitters by a few cm).
    """

    name: str = "kitti_raw"
    root: Optional[str] = None
    date: Optional[str] = None
    drive: Optional[Union[int, str]] = None
    step: int = 1
    frames: Optional[int] = None
    only_labelled: bool = False
    camera_height: Optional[float] = None
    oxts: KittiOxts = KittiOxts.velocity


@dataclass
class DdadDataConfig:
    """``data=ddad``: DDAD / TRI dgp scenes (docs/conventions.md, section 4.8).

    Attributes:
        root: the folder of ``scene_dataset_v1.0.json``.
        camera: camera datum (``CAMERA_01`` = the front camera).
        lidar: the LiDAR datum of the depth ground truth.
        scene: only this scene folder (e.g. ``scene_01``); None = every scene.
        frames: at most this many frame pairs (None = all).
        camera_height: camera height above the road (metres); None = estimated per pair from the LiDAR
            ground in front of the vehicle and the camera extrinsics (``camera.height`` is not used).
        moving_threshold: a tracked 3D box moving more than this between the two timesteps is a moving
            object (metres).
    """

    name: str = "ddad"
    root: Optional[str] = None
    camera: str = "CAMERA_01"
    lidar: str = "LIDAR"
    scene: Optional[str] = None
    frames: Optional[int] = None
    camera_height: Optional[float] = None
    moving_threshold: float = 0.2


@dataclass
class FramesDataConfig:
    """``data=frames``: a folder of images of your own camera (sorted by name = temporal order), with an
    intrinsics file or a horizontal field of view.

    Attributes:
        root: the folder of images.
        intrinsics: the intrinsics file: YAML/JSON ``{fx, fy, cx, cy}`` (pixels) or ``{K: 3x3}``, or text
            ``fx fy cx cy`` / the 9 numbers of K; with ``distortion: [k1, k2, p1, p2, k3]`` (OpenCV's order,
            as ``monostixels calibrate`` writes it) the images are undistorted. None =
            ``<root>/intrinsics.yaml`` (or .yml/.json/.txt), else ``hfov_deg``. A file wins over ``hfov_deg``
            (a warning says so).
        hfov_deg: without an intrinsics file, the horizontal field of view (degrees), as for ``data=video``:
            fx = fy = (W/2) / tan(hfov/2), principal point at the image centre. Approximate.
        step: pair = (image i, image i - step) in name order.
        frames: at most this many frame pairs (None = all).
        fps: the folder's frame rate (Hz; a 20 fps dashcam's frames: 20): a pair's interval is step / fps
            seconds, which velocities and TTC use.
        resize: resize of the (undistorted) images, the intrinsics with them, as for ``data=video``: ``auto``
            (about 0.5 megapixels, never upscaled), None (as stored), a factor or ``[W, H]`` pixels.
        camera_height: camera height above the road (metres); None = ``camera.height``.
        poses: camera-to-world poses (a line per image: 12 or 16 numbers, or an image number and 12), the
            ground-truth motion; None = no motion (estimate it with ``motion=mono``).
        mask: pixels to ignore: ``auto`` (a still region at the bottom, a bonnet, found from the first
            images: :mod:`monostixels.data.static_regions`), a mask image of the images' size (PNG;
            non-zero = ignore), undistorted with them, or None (every pixel).
    """

    name: str = "frames"
    root: Optional[str] = None
    intrinsics: Optional[str] = None
    hfov_deg: Optional[float] = None
    step: int = 1
    frames: Optional[int] = None
    fps: float = FOLDER_FPS
    # auto, a factor or [W, H]: no one type (working_size checks it).
    resize: Any = "auto"
    camera_height: Optional[float] = None
    poses: Optional[str] = None
    mask: Optional[str] = AUTO_MASK


@dataclass
class VideoDataConfig:
    """``data=video``: a video file of your own camera, a camera or a stream (docs/conventions.md, section 4.8).

    Attributes:
        path: the video file (what OpenCV's FFmpeg backend decodes), a camera index (0, 1, ...) or a URL
            (``rtsp://``, ``http://``...); a camera or URL is read as its frames come.
        realtime: frames that arrive while one is being solved are dropped, not queued: each pair is the
            newest frame and the frames taken before it (a file is then read at its frame rate, as a camera
            would deliver it); ``run`` writes which frames it processed (``<outputs>/run/stream.json``,
            ``flags.stream`` in each stixels.json). False: every (step-th) frame is processed.
        intrinsics: intrinsics file (pixels of the stored video; formats as for ``data=frames``, its
            ``distortion`` undistorts every frame).
        hfov_deg: without an intrinsics file, the horizontal field of view (degrees): fx = fy =
            (W/2) / tan(hfov/2), principal point at the image centre. Approximate: no lens distortion, no
            off-centre principal point; depths scale with fx.
        step: video frames between the two frames of a pair (a 30 fps dashcam: 3 gives KITTI's 10 Hz).
        start: first video frame used (0-based).
        end: the frame before which to stop (None = the end).
        resize: resize of the (undistorted) frames, the intrinsics with them: ``auto`` (about 0.5
            megapixels, e.g. 1280x720 -> 942x530; smaller frames and 960x540 stay as they are, never
            upscaled), None (as stored), a factor (0.5) or ``[W, H]`` pixels.
        mask: pixels to ignore: ``auto`` (a still region at the bottom, a bonnet or a dashboard reflection,
            found from the clip's first frames), a mask image of the stored frame size (PNG; non-zero =
            ignore), undistorted and resized with the frames, or None (every pixel).
        frames: at most this many frame pairs (None = all).
        camera_height: camera height above the road (metres); None = ``camera.height``.
    """

    name: str = "video"
    path: Optional[Union[int, str]] = None
    realtime: bool = False
    intrinsics: Optional[str] = None
    hfov_deg: Optional[float] = None
    step: int = 1
    start: int = 0
    end: Optional[int] = None
    # auto, a factor or [W, H]: no one type (working_size checks it).
    resize: Any = "auto"
    mask: Optional[str] = AUTO_MASK
    frames: Optional[int] = None
    camera_height: Optional[float] = None


@dataclass
class CamVidDataConfig:
    """``data=camvid``: CamVid's labelled single images (SegNet split), for ``eval``'s semantic metrics only
    (:mod:`monostixels.data.camvid`).

    Attributes:
        root: the CamVid folder.
        split: ``train`` | ``val`` | ``test``.
        frames: at most this many images (None = all), every ``step``-th image of the split's list.
        step: see ``frames``.
    """

    name: str = "camvid"
    root: Optional[str] = None
    split: CamVidSplit = CamVidSplit.test
    frames: Optional[int] = None
    step: int = 1


#: The schema of each option of the config group ``data`` by its ``name`` (monostixels.config_schema).
DATA_SCHEMAS: dict[str, type] = {
    "synthetic": SyntheticDataConfig, "kitti2015": Kitti2015DataConfig, "kitti_raw": KittiRawDataConfig,
    "ddad": DdadDataConfig, "frames": FramesDataConfig, "video": VideoDataConfig, "camvid": CamVidDataConfig,
}

_Data = Union[SyntheticDataConfig, Kitti2015DataConfig, KittiRawDataConfig, DdadDataConfig, FramesDataConfig,
              VideoDataConfig, CamVidDataConfig]


def data_params(data: Any) -> _Data:
    """The settings of a ``data`` config node (or dict) as its option's dataclass (:data:`DATA_SCHEMAS`)."""
    return option_params(DATA_SCHEMAS, data, "data")


def camera_mount(data: Any, camera: Any) -> tuple[float, float]:
    """(height metres, pitch radians): data.camera_height, else camera.height (KITTI's 1.65 m by default)."""
    cam = config_params(CameraConfig, camera, "camera")
    height = getattr(data_params(data), "camera_height", None)
    return float(cam.height if height is None else height), float(cam.pitch)


def _synthetic(data: SyntheticDataConfig, camera: Any) -> Source:
    from monostixels.data.synthetic import SyntheticSequenceSource, SyntheticSource  # imported lazily

    length, speed = data.sequence_length, data.ego_speed_mps
    if length < 1:
        raise InputError(f"data.sequence_length: frames per synthetic clip, an integer >= 1, got {length!r}")
    if length == 1:
        if speed is not None:
            raise InputError("data.ego_speed_mps: only for synthetic sequences (data.sequence_length > 1)")
        return SyntheticSource(data.frames, seed=data.seed, scale=data.scale, density=data.density)
    return SyntheticSequenceSource(data.frames, length, seed=data.seed, scale=data.scale, density=data.density,
                                   ego_speed=speed)


def _kitti2015(data: Kitti2015DataConfig, camera: Any) -> Source:
    from monostixels.data.kitti2015 import Kitti2015Source

    height, pitch = camera_mount(data, camera)
    return Kitti2015Source(
        data.root, split=data.split, previous=data.previous, frames=data.frames, scenes=data.scenes,
        fx=data.fx, fy=data.fy, cx=data.cx, cy=data.cy, camera_height=height, pitch=pitch,
    )


def _kitti_raw(data: KittiRawDataConfig, camera: Any) -> Source:
    from monostixels.data.kitti_raw import KittiRawSource

    height, pitch = camera_mount(data, camera)
    return KittiRawSource(
        data.root, date=data.date, drive=data.drive, step=data.step, frames=data.frames,
        only_labelled=data.only_labelled, camera_height=height, pitch=pitch, oxts=data.oxts,
    )


def _ddad(data: DdadDataConfig, camera: Any) -> Source:
    from monostixels.data.ddad import DDADSource

    return DDADSource(
        data.root, camera=data.camera, lidar=data.lidar, scene=data.scene, frames=data.frames,
        camera_height=data.camera_height,  # None: estimated from the LiDAR ground
        moving_threshold=data.moving_threshold,
    )


def _frames_folder(data: FramesDataConfig, camera: Any) -> Source:
    from monostixels.data.frames import FramesSource

    height, pitch = camera_mount(data, camera)
    return FramesSource(
        data.root,
        intrinsics=None if data.intrinsics is None else Path(data.intrinsics),
        hfov_deg=data.hfov_deg, step=data.step, frames=data.frames, fps=data.fps, resize=_resize(data.resize),
        camera_height=height, pitch=pitch, poses=None if data.poses is None else Path(data.poses),
        mask=_mask(data.mask),
    )


def _resize(value: Any) -> Any:
    """``data.resize`` as :func:`monostixels.data._lens.working_size` takes it: a config list as a list."""
    if value is not None and not isinstance(value, (int, float, str)):
        return list(value)
    return value


def _mask(value: str | None) -> str | Path | None:
    """``data.mask``: None, ``auto`` (found from the frames: :mod:`monostixels.data.static_regions`) or an image file."""
    if value is None:
        return None
    return AUTO_MASK if value.strip().lower() == AUTO_MASK else Path(value)


def _video(data: VideoDataConfig, camera: Any, window: int = 10) -> Source:
    from monostixels.data.live_video import LiveVideoSource, is_live_path
    from monostixels.data.video import VideoSource

    height, pitch = camera_mount(data, camera)
    common = dict(
        intrinsics=None if data.intrinsics is None else Path(data.intrinsics),
        hfov_deg=data.hfov_deg, step=data.step, start=data.start, end=data.end, resize=_resize(data.resize),
        frames=data.frames, camera_height=height, pitch=pitch, mask=_mask(data.mask),
    )
    if data.realtime or is_live_path(data.path):
        # Frames as they come: a camera index, a URL, or a file read at its frame rate (data.realtime).
        return LiveVideoSource(data.path, realtime=data.realtime, window=window, **common)
    return VideoSource(data.path, **common)


def _camvid(data: CamVidDataConfig, camera: Any) -> Source:
    # Single labelled images: no previous frame, no camera. `monostixels eval` scores them
    # through monostixels.eval.semantic instead of this factory.
    raise InputError(
        "data=camvid holds labelled single images, not frame pairs: only `monostixels eval data=camvid` "
        "uses it (semantic metrics; no flow, motion or stixels)"
    )


_FACTORIES: dict[str, Callable[[Any, Any], Source]] = {
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


def make_source(data: _Data, camera: CameraConfig | None = None, *, window: int = 10) -> Source:
    """Build the data source named by ``data.name``.

    Args:
        data: the ``data`` group's settings, the dataclass of its option (:data:`DATA_SCHEMAS`; read from a
            config by :func:`monostixels.build.build_source`).
        camera: the ``camera`` group's settings (``height`` metres, ``pitch`` radians); None: the defaults.
        window: frames a live source keeps (``keyframes.window``: as many as keyframe pairs may reach back).

    Returns:
        A :class:`~monostixels.data.base.SequenceSource` of :class:`FramePair` (``len`` and indexing; images
        are read on access), or, for a camera, a URL or ``data.realtime``, a
        :class:`~monostixels.data.base.LiveSource` (frames as they come).

    Raises:
        InputError: any bad input of the chosen source (missing root, files, calibration...), with a message
            naming it.
    """
    if not isinstance(data, tuple(DATA_SCHEMAS.values())):
        raise TypeError(f"make_source: expected the data group's settings (one of {', '.join(c.__name__ for c in DATA_SCHEMAS.values())}), "
                        f"got {type(data).__name__}; from a config: monostixels.build.build_source")
    camera = camera if camera is not None else CameraConfig()
    if data.name == "video":
        return _video(data, camera, window)
    return _FACTORIES[data.name](data, camera)
