"""Writers: where a sequence's results go, one frame at a time (docs/conventions.md, sections 4.2, 4.3 and 4.6).

``monostixels run`` and ``monostixels batch`` hand every frame of a sequence to a list of writers through one
loop, :func:`write_sequence`: each writer gets every frame once, in order (:meth:`Writer.write`), and is closed
once (:meth:`Writer.close`), also where the sequence fails part-way (then with the error, so that a writer
finishing a summary can leave it unwritten).

- :class:`FrameFiles`: ``run``'s per-frame folder (overlay.png, bev.png, figure.png, depth.png, depth16.png,
  stixels.json, stixels.npz, points.ply);
- :class:`Videos`: ``run``'s video.mp4 (overlay above depth) and bev.mp4;
- :class:`Recording`: the Rerun recording (``output.rerun=true``, :mod:`monostixels.output.viewer`);
- :class:`RunSummary`: ``run``'s summary.json (and stream.json of a live source);
- :class:`StixelRows`: ``batch``'s rows of one clip, a ``pyarrow.Table`` of :data:`SCHEMA_FIELDS`, written by
  :func:`write_partition`;
- :class:`DemoFiles`: ``demo``'s pictures and stixels of its one pair.

:func:`run_writers` builds ``run``'s list from the settings the builder (:mod:`monostixels.build`) parsed.
"""
from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Sequence

import numpy as np
import torch

from monostixels._checks import InputError
from monostixels.core.classes import CLASS_NAMES, TYPE_NAMES
from monostixels.data.base import LiveSource, Source, source_info
from monostixels.inputs.motion_base import NO_METRIC_MOTION, MotionKind
from monostixels.output.scene3d import PoseChain, frame_time, optional_field, reference_points, to_world

if TYPE_CHECKING:  # the settings' types, for the annotations only
    from monostixels.data.sources import CameraConfig, _Data
    from monostixels.output.viewer import OutputConfig
    from monostixels.pipeline import EvalConfig

__all__ = ["Frame", "Writer", "write_sequence", "Pictures", "FramePictures", "FrameFiles", "video_fps", "Videos",
           "Recording", "RunSummary", "RunWriters", "run_writers", "camera_report", "camera_summary",
           "HEIGHT_WARN_SHARE", "SCHEMA_FIELDS", "frame_rows", "arrow_schema", "StixelRows", "write_partition",
           "DemoFiles", "listed"]

logger = logging.getLogger(__name__)


@dataclass
class Frame:
    """One processed frame pair as the writers see it.

    Attributes:
        index: its position in the sequence, 0-based (``run``'s ``frame_NNNNNN``, batch's ``frame``).
        pair: the FramePair. result: its PipelineResult.
    """

    index: int
    pair: Any
    result: Any


class Writer:
    """One output of a sequence. :func:`write_sequence` calls :meth:`write` once per frame, in order, then
    :meth:`close` once; this base class writes nothing."""

    def write(self, frame: Frame) -> None:
        """Write (or collect) one frame."""

    def close(self, error: BaseException | None = None) -> None:
        """Finish the output; ``error``: what stopped the sequence, None where every frame was written."""


def write_sequence(steps: Iterable[Any], writers: Sequence[Writer]) -> int:
    """Hand every step of a sequence (``.pair`` and ``.result``, as :class:`SequenceRunner` yields them) to each
    writer in order, then close every writer once.

    Writers are closed in order also where the sequence or a writer fails, with that error; a writer whose
    ``close`` fails does not keep the others from closing, and its error is raised after them.

    Returns:
        The number of frames written.
    """
    count = 0
    error: BaseException | None = None
    try:
        for index, step in enumerate(steps):
            frame = Frame(index, step.pair, step.result)
            for w in writers:
                w.write(frame)
            count += 1
    except BaseException as e:
        error = e
        raise
    finally:
        _close_all(writers, error)
    return count


def _close_all(writers: Sequence[Writer], error: BaseException | None) -> None:
    failed: BaseException | None = None
    for w in writers:
        try:
            w.close(error)
        except Exception as e:  # noqa: BLE001 — the others still close; the first failure is raised below
            if error is not None or failed is not None:
                logger.error("closing %s failed too: %s", type(w).__name__, e)
            else:
                failed = e
    if failed is not None:
        raise failed


def listed(names: list[str], most: int = 20) -> str:
    """``a, b, c`` of the first ``most`` names, ``... (N more)`` for the rest: a line stays a line."""
    return ", ".join(names[:most]) + (f", ... ({len(names) - most} more)" if len(names) > most else "")


# ------------------------------------------------------------------------------------------------ run
@dataclass
class Pictures:
    """A frame's pictures (:class:`FramePictures`)."""

    depth: torch.Tensor  # (H, W) metres, the stixels' depth map
    overlay: np.ndarray  # (H, W, 3) uint8 RGB
    bev: np.ndarray  # bird's-eye view, uint8 RGB
    depth_colour: np.ndarray  # (H, W, 3) uint8 RGB


class FramePictures:
    """The pictures of a frame (its depth map, overlay, bird's-eye view and depth colour map), drawn once for
    every writer that shows them. ``min_depth``, ``max_depth``: the colour range, metres."""

    def __init__(self, min_depth: float, max_depth: float) -> None:
        self.min_depth, self.max_depth = min_depth, max_depth
        self._frame: Frame | None = None
        self._pictures: Pictures | None = None

    def of(self, frame: Frame) -> Pictures:
        """The pictures of ``frame`` (kept until the next frame is asked for)."""
        if self._frame is not frame or self._pictures is None:
            from monostixels.output.bev import bev_image
            from monostixels.output.viz import depth_colormap, stixel_depth_overlay

            lo, hi = self.min_depth, self.max_depth
            st = frame.result.stixels
            depth = st.depth_map()
            self._pictures = Pictures(depth, stixel_depth_overlay(frame.pair.image, st, min_depth=lo, max_depth=hi),
                                       bev_image(st, min_depth=lo, max_depth=hi),
                                       depth_colormap(depth, min_depth=lo, max_depth=hi))
            self._frame = frame
        return self._pictures


class FrameFiles(Writer):
    """``run``'s files of each frame, under ``out/<pair name>/`` (``frame_NNNNNN`` where a pair has no name)."""

    NAMES = ("overlay.png", "bev.png", "figure.png", "depth.png", "depth16.png", "stixels.json", "stixels.npz",
             "points.ply")

    def __init__(self, out: Path, pictures: FramePictures) -> None:
        self.out, self.pictures = Path(out), pictures

    def write(self, frame: Frame) -> None:
        from monostixels.output.io import depth_to_points, write_depth_png16, write_image, write_ply
        from monostixels.output.viz import side_by_side

        pair, st = frame.pair, frame.result.stixels
        d = self.out / (pair.name or f"frame_{frame.index:06d}")
        p = self.pictures.of(frame)
        write_image(d / "overlay.png", p.overlay)
        write_image(d / "bev.png", p.bev)
        write_image(d / "figure.png", side_by_side(p.overlay, p.bev))
        write_image(d / "depth.png", p.depth_colour)
        finite = torch.where(torch.isfinite(p.depth) & (p.depth > 0), p.depth, torch.zeros_like(p.depth))
        write_depth_png16(d / "depth16.png", finite)
        st.save_json(d / "stixels.json")
        st.save_npz(d / "stixels.npz")
        pts, cols = depth_to_points(finite, pair.camera.K, pair.image, max_depth=self.pictures.max_depth)
        write_ply(d / "points.ply", pts, cols)


#: Frame rate of `run`'s videos when the source has none (image folders): slow enough to look at.
_VIDEO_FPS = 5.0


def video_fps(src: Source) -> float:
    """The videos' frame rate: the rate of the used frames of a video source, else 5 fps."""
    info = source_info(src)
    fps, step = info.fps, info.step
    return float(fps) / max(int(step), 1) if fps else _VIDEO_FPS


class Videos(Writer):
    """``run``'s ``out/video.mp4`` (the overlay above the depth map) and ``out/bev.mp4`` (the bird's-eye view),
    mp4v at ``fps``; each opened at its first frame (its size)."""

    NAMES = ("video.mp4", "bev.mp4")

    def __init__(self, out: Path, fps: float, pictures: FramePictures) -> None:
        self.out, self.fps, self.pictures = Path(out), fps, pictures
        self._open: dict[str, Any] = {}

    @property
    def written(self) -> bool:
        """Whether a video was started."""
        return bool(self._open)

    def write(self, frame: Frame) -> None:
        import cv2

        p = self.pictures.of(frame)
        for name, rgb in (("video.mp4", np.concatenate([p.overlay, p.depth_colour], axis=0)), ("bev.mp4", p.bev)):
            if name not in self._open:
                self.out.mkdir(parents=True, exist_ok=True)
                self._open[name] = cv2.VideoWriter(str(self.out / name), cv2.VideoWriter_fourcc(*"mp4v"), self.fps,
                                                   (rgb.shape[1], rgb.shape[0]))
                if not self._open[name].isOpened():
                    raise InputError(f"run: OpenCV cannot write the video {self.out / name} (no mp4v encoder)")
            self._open[name].write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))

    def close(self, error: BaseException | None = None) -> None:
        for v in self._open.values():
            v.release()


class Recording(Writer):
    """The Rerun recording of a run (:func:`monostixels.output.viewer.open_recorder`); :attr:`path` after
    :meth:`close`: the ``.rrd`` file, None where ``output.rerun`` is off."""

    def __init__(self, hook: Any) -> None:
        self.hook = hook
        self.path: Path | None = None

    def write(self, frame: Frame) -> None:
        self.hook.log_frame(frame.index, frame.pair, frame.result)

    def close(self, error: BaseException | None = None) -> None:
        self.path = self.hook.close()


#: A camera height the road implies that differs from the setting by more than this share is warned about.
HEIGHT_WARN_SHARE = 0.2


def camera_report(flags: list[dict[str, Any]], height: float) -> dict[str, Any]:
    """What a run's pairs say about its camera (``run/summary.json`` ``camera``): the pairs, those with a
    metric motion (``metric``, standing ones included) and without (``no_metric_motion``), where the metric
    scales came from (``scale_from``: counts), the height assumed (``height_m``) and, where a given motion
    let the road say, the median height it implies (``height_fit_m``, else None) over ``height_fits`` pairs; the
    camera speed of the moving metric pairs whose scale is certain (``speed_mps``: ``median``, ``min``, ``max`` m/s
    and ``pairs``, else None) and the pairs whose scale was too uncertain to tell movers (``scale_uncertain``):
    their lengths are not counted in the speed (one such pair read 0.9 m/s on a 26 m/s highway stand-in,
    docs/results.md, "A distorted lens with a bonnet")."""
    kinds = [f.get("camera_motion", MotionKind.METRIC) for f in flags]
    metric = sum(k not in NO_METRIC_MOTION for k in kinds)
    sources: dict[str, int] = {}
    for f in flags:
        if f.get("scale_from"):
            sources[f["scale_from"]] = sources.get(f["scale_from"], 0) + 1
    fits = [float(f["camera_height_fit_m"]) for f in flags if f.get("camera_height_fit_m") is not None]
    speeds = [float(f["speed_mps"]) for f in flags if f.get("speed_mps") is not None and not f.get("scale_uncertain")]
    uncertain = sum(bool(f.get("scale_uncertain")) for f in flags)
    return {"pairs": len(flags), "metric": metric, "no_metric_motion": len(flags) - metric,
            "scale_from": dict(sorted(sources.items())), "height_m": height,
            "height_fit_m": float(np.median(fits)) if fits else None, "height_fits": len(fits),
            "speed_mps": ({"median": float(np.median(speeds)), "min": min(speeds), "max": max(speeds),
                           "pairs": len(speeds)} if speeds else None),
            "scale_uncertain": uncertain}


def camera_summary(report: dict[str, Any]) -> list[str]:
    """The run's summary lines of its camera (:func:`camera_report`): how many pairs had a metric motion and
    where the scale came from, and the camera height assumed beside the one the road implies.

    A height that differs from the implied one by more than :data:`HEIGHT_WARN_SHARE` is also logged as a
    warning: every depth and speed of a monocular run scales with it.
    """
    by = ", ".join(f"{v} {k}" for k, v in report["scale_from"].items())
    unknown = report["no_metric_motion"]
    lines = [f"camera motion metric on {report['metric']} of {report['pairs']} pair(s)" + (f" (scale: {by})" if by else "")
             + (f"; {unknown} without a metric motion (no movers, no collision warnings there)" if unknown else "")]
    sp, unsure = report.get("speed_mps"), report.get("scale_uncertain", 0)
    if sp is not None:
        lines.append(f"camera speed median {sp['median']:.1f} m/s, range {sp['min']:.1f}-{sp['max']:.1f} m/s over "
                     f"{sp['pairs']} moving pair(s)"
                     + (f"; {unsure} more with an uncertain scale, not counted (no movers along the epipolar lines, "
                        f"no collision warnings there)" if unsure else ""))
    elif unsure:
        lines.append(f"camera speed unknown: {unsure} moving pair(s), each with an uncertain scale (no movers along "
                     f"the epipolar lines, no collision warnings there)")
    height, med = report["height_m"], report["height_fit_m"]
    line = f"camera height {height:.2f} m (camera.height; depths and speeds scale with it)"
    if med is not None:
        line += f"; the road implies {med:.2f} m (median of {report['height_fits']} pair(s))"
        if abs(med / height - 1.0) > HEIGHT_WARN_SHARE:
            logger.warning("camera.height %.2f m differs from the %.2f m the road implies by %.0f %%: set camera.height",
                           height, med, 100.0 * abs(med / height - 1.0))
    lines.append(line)
    return lines


class RunSummary(Writer):
    """``run``'s ``out/summary.json`` (and ``out/stream.json`` of a live source), written at :meth:`close` where
    every frame was; :attr:`lines`: what the run prints of them.

    Args:
        out: ``<outputs>/run``. src: the data source (its skipped frames, restarts, live summary).
        data_name: ``data.name``. height: the camera height assumed, metres.

    Raises (at close):
        InputError: no frame pair was made and unreadable frames were skipped.
    """

    def __init__(self, out: Path, src: Source, data_name: str, height: float) -> None:
        self.out, self.src, self.data_name, self.height = Path(out), src, data_name, height
        self.camera: list[dict[str, Any]] = []  # each pair's flags: its camera-motion kind, scale source, height fit
        self.skipped: list[str] = []
        self.stream: Path | None = None
        self.lines: list[str] = []

    def write(self, frame: Frame) -> None:
        st = frame.result.stixels
        info = st.pair_info or {}
        speed = (info["driven_m"] / info["dt_s"] if info.get("driven_m") is not None and info.get("dt_s")
                 and st.status.motion.kind == MotionKind.METRIC else None)
        self.camera.append({**st.status.to_flags(), "speed_mps": speed})

    def close(self, error: BaseException | None = None) -> None:
        if error is not None:
            return
        from monostixels._cpu import runtime_report
        from monostixels.data._lazy_source import MAX_SKIPPED_FRAMES

        src, out = self.src, self.out
        written = len(self.camera)
        self.skipped = skipped = source_info(src).skipped_frames
        if written == 0 and skipped:
            raise InputError(f"run: no frame pair could be made: {len(skipped)} unreadable frame(s) skipped "
                             f"({listed(skipped)}); a pair needs two readable frames at most "
                             f"{MAX_SKIPPED_FRAMES + 1} frames apart")
        if isinstance(src, LiveSource):
            # Which frames were processed (and how many dropped): docs/conventions.md, section 4.3
            # (data.realtime).
            self.stream = out / "stream.json"
            out.mkdir(parents=True, exist_ok=True)
            summary = src.summary()
            self.stream.write_text(json.dumps(summary, indent=2))
            if summary["realtime"]:
                self.lines.append(f"{summary['frames_taken']} of {summary['frames_read']} frames taken, "
                                  f"{summary['frames_dropped']} dropped while solving (realtime); {self.stream}")
        out.mkdir(parents=True, exist_ok=True)
        restarts = source_info(src).restarts
        # What the run made of its input; unreadable frames are listed, never dropped silently.
        cam = camera_report(self.camera, self.height)
        # platform: the CPU, ONNX Runtime's INT8 path and the solver's build (docs/conventions.md, section 4.3).
        run_summary = {"data": self.data_name, "frame_pairs": written, "skipped_frames": skipped,
                       "sequence_restarts": restarts, "camera": cam, "platform": runtime_report()}
        (out / "summary.json").write_text(json.dumps(run_summary, indent=2))
        self.lines += camera_summary(cam)


@dataclass
class RunWriters:
    """``run``'s writers (:func:`run_writers`), in the order they are closed: :attr:`all`."""

    out: Path
    files: FrameFiles
    videos: Videos | None
    recording: Recording
    summary: RunSummary
    all: list[Writer] = field(init=False)

    def __post_init__(self) -> None:
        self.all = [w for w in (self.files, self.videos, self.recording, self.summary) if w is not None]

    def report(self, frames: int) -> list[str]:
        """The lines ``run`` prints after its ``frames`` frame pairs: the summary's, then where everything went."""
        out, skipped = self.out, self.summary.skipped
        stream, recording = self.summary.stream, self.recording.path
        videos = self.videos is not None and self.videos.written
        last = (f"{frames} frame pair(s) -> {out}/<frame>/ {' '.join(FrameFiles.NAMES)}"
                + (f"; videos {out / 'video.mp4'} {out / 'bev.mp4'}" if videos else "")
                + (f"; 3D recording {recording} (open it with: rerun {recording})" if recording else "")
                + (f"; processed frames {stream}" if stream else "")
                + (f"; {len(skipped)} unreadable frame(s) skipped: {listed(skipped)}" if skipped else "")
                + f"; {out / 'summary.json'}")
        return [f"run: {line}" for line in [*self.summary.lines, last]]


def run_writers(src: Source, out: Path, *, data: _Data, camera: CameraConfig, ev: EvalConfig,
                output: OutputConfig) -> RunWriters:
    """``run``'s writers of source ``src`` into ``out`` (``<outputs>/run``): the per-frame files, the videos (a
    sequence: any video, or more than one pair), the Rerun recording (``output.rerun``) and the summary.
    ``data``, ``camera``, ``ev``, ``output``: the ``data``, ``camera``, ``eval`` and ``output`` groups' settings
    (their dataclasses; :func:`monostixels.build.build_writers` reads them from a config).

    Raises:
        InputError: ``output.rerun=true`` without rerun-sdk installed (before any frame runs).
    """
    from monostixels.data.sources import camera_mount
    from monostixels.output.viewer import open_recorder

    pictures = FramePictures(ev.colormap_min_depth, ev.colormap_max_depth)
    sequence = str(data.name) == "video" or len(src) > 1  # a live source is a video: its length is not asked
    return RunWriters(out, FrameFiles(out, pictures), Videos(out, video_fps(src), pictures) if sequence else None,
                      Recording(open_recorder(out, src, ev=ev, output=output)),
                      RunSummary(out, src, str(data.name), camera_mount(data, camera)[0]))


# ------------------------------------------------------------------------------------------------ batch
#: Columns of batch's dataset (besides the partition column ``clip``): name, Arrow type, meaning.
#: Temporal columns (track_id, velocity_*, ttc_s) are null where the pipeline does not provide them.
SCHEMA_FIELDS: tuple[tuple[str, str, str], ...] = (
    ("frame", "int32", "index of the frame pair in the clip, 0-based (run's `frame` timeline)"),
    ("frame_name", "string", "the pair's name (run's per-frame folder)"),
    ("timestamp", "float64", "seconds of the current frame into the video; null where unknown"),
    ("dt", "float64", "seconds between the pair's two frames; null where unknown"),
    ("column", "int32", "stixel column (width solver.column_width pixels)"),
    ("v_top", "int32", "top pixel row (inclusive, v down)"),
    ("v_bottom", "int32", "bottom pixel row (inclusive)"),
    ("type", "string", "ground | static_object | dynamic_object | sky"),
    ("class", "string", "one of the 10 classes (docs/conventions.md, section 2)"),
    ("inverse_depth", "float64", "plane label p, 1/metres"),
    ("depth", "float64", "depth z of the stixel's reference pixel, metres; null for sky (= stixels.json)"),
    ("x", "float64", "world position of that pixel on the stixel's plane, metres (world = first camera, "
                     "x right, y down, z forward); null for sky"),
    ("y", "float64", ""),
    ("z", "float64", ""),
    ("motion_x", "float64", "motion Δ of a dynamic stixel between the pair's frames, current camera "
                            "frame, metres (0 otherwise; = stixels.json `motion`)"),
    ("motion_y", "float64", ""),
    ("motion_z", "float64", ""),
    ("track_id", "int64", "track of the stixel (sequence layer); null where absent"),
    ("velocity_x", "float64", "world velocity, m/s (sequence layer); null where absent"),
    ("velocity_y", "float64", ""),
    ("velocity_z", "float64", ""),
    ("ttc_s", "float64", "time to collision, s, inf when not closing (sequence layer); null where absent"),
    ("degenerate_motion", "bool", "the frame's camera motion was degenerate: depths from the scene model"),
)


def frame_rows(index: int, pair: Any, res: Any, pose: np.ndarray, fps: float | None) -> dict[str, list]:
    """Columns (:data:`SCHEMA_FIELDS`) of one frame's stixels, one entry per stixel.

    Args:
        index: the pair's index in the clip. pair: the FramePair. res: its PipelineResult.
        pose: (4, 4) camera-to-world of the pair's current frame (world = the clip's first camera).
        fps: the video's frame rate, or None.
    """
    world = res.stixels
    n = len(world)
    depth = world.depth.double().numpy()
    X = to_world(pose, reference_points(world))
    motion = world.motion.double().numpy().reshape(-1, 3)
    track, vel, ttc = (optional_field(world, k) for k in ("track_id", "velocity", "ttc_s"))
    vel = None if vel is None else np.asarray(vel, dtype=np.float64).reshape(-1, 3)
    dt = pair.info.dt

    def finite(a: np.ndarray) -> list[float | None]:
        return [float(v) if math.isfinite(v) else None for v in a]

    return {
        "frame": [int(index)] * n,
        "frame_name": [str(pair.name)] * n,
        "timestamp": [frame_time(pair, fps)] * n,
        "dt": [None if dt is None else float(dt)] * n,
        "column": world.column.tolist(),
        "v_top": world.v_top.tolist(),
        "v_bottom": world.v_bottom.tolist(),
        "type": [TYPE_NAMES[int(t)] for t in world.type],
        "class": [CLASS_NAMES[int(c)] for c in world.cls],
        "inverse_depth": world.inverse_depth.double().tolist(),
        "depth": finite(depth),  # sky: inf -> null, as stixels.json writes it
        "x": finite(X[:, 0]), "y": finite(X[:, 1]), "z": finite(X[:, 2]),
        "motion_x": motion[:, 0].tolist(), "motion_y": motion[:, 1].tolist(), "motion_z": motion[:, 2].tolist(),
        "track_id": [None] * n if track is None else [None if int(t) < 0 else int(t) for t in track],
        "velocity_x": [None] * n if vel is None else vel[:, 0].tolist(),
        "velocity_y": [None] * n if vel is None else vel[:, 1].tolist(),
        "velocity_z": [None] * n if vel is None else vel[:, 2].tolist(),
        "ttc_s": [None] * n if ttc is None else [float(v) for v in np.asarray(ttc, dtype=np.float64)],
        "degenerate_motion": [world.status.motion.is_degenerate] * n,
    }


def arrow_schema() -> Any:
    """The Arrow schema of a clip's file (:data:`SCHEMA_FIELDS`, all nullable)."""
    import pyarrow as pa

    types = {"int32": pa.int32(), "int64": pa.int64(), "float64": pa.float64(), "string": pa.string(),
             "bool": pa.bool_()}
    return pa.schema([pa.field(name, types[t]) for name, t, _ in SCHEMA_FIELDS])


class StixelRows(Writer):
    """``batch``'s rows of one clip (:func:`frame_rows`, world = the clip's first camera): :attr:`table`, a
    ``pyarrow.Table`` of :data:`SCHEMA_FIELDS` after :meth:`close` where every frame was written, else None;
    :attr:`frames`: the frames written. ``fps``: the video's frame rate, or None."""

    def __init__(self, fps: float | None) -> None:
        self.fps = fps
        self.frames = 0
        self.table: Any = None
        self._poses = PoseChain()
        self._columns: dict[str, list] = {name: [] for name, _, _ in SCHEMA_FIELDS}

    def write(self, frame: Frame) -> None:
        rows = frame_rows(frame.index, frame.pair, frame.result, self._poses.update(frame.pair, frame.result), self.fps)
        for k, v in rows.items():
            self._columns[k].extend(v)
        self.frames += 1

    def close(self, error: BaseException | None = None) -> None:
        if error is None:
            import pyarrow as pa

            self.table = pa.Table.from_pydict(self._columns, schema=arrow_schema())


def write_partition(folder: Path, table: Any) -> Path:
    """Write one clip's rows as ``folder/part-0.parquet`` (``stixels.parquet/clip=NAME``), atomically: the
    folder's older parquet files are removed first."""
    import pyarrow.parquet as pq

    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("*.parquet"):
        old.unlink()
    tmp = folder / "part-0.parquet.tmp"
    pq.write_table(table, tmp)
    os.replace(tmp, folder / "part-0.parquet")
    return folder / "part-0.parquet"


# ------------------------------------------------------------------------------------------------ demo
class DemoFiles(Writer):
    """``demo``'s pictures of its pair, the paper's figure, stixels.json and stixels.npz, under ``out``
    (docs/conventions.md, section 4.2); :attr:`names`: the files written. ``min_depth``, ``max_depth``: the
    colour range, metres."""

    def __init__(self, out: Path, min_depth: float, max_depth: float) -> None:
        self.out, self.min_depth, self.max_depth = Path(out), min_depth, max_depth
        self.names: list[str] = []

    def write(self, frame: Frame) -> None:
        from monostixels.output.bev import bev_image
        from monostixels.output.io import write_image
        from monostixels.output.viz import (depth_colormap, flow_colormap, image_to_uint8, paper_figure,
                                            semantic_colormap, stixel_depth_overlay, stixel_overlay)

        pair, res, lo, hi = frame.pair, frame.result, self.min_depth, self.max_depth
        img, st = pair.image, res.stixels
        rgb = image_to_uint8(img)
        pics = {
            "input.png": rgb,
            "input_previous.png": image_to_uint8(pair.image_prev),
            "flow.png": flow_colormap(res.flow.flow),
            "stixels_overlay.png": stixel_overlay(img, st, mode="type"),
            "stixels_semantic.png": stixel_overlay(img, st, mode="class", alpha=0.7),
            "stixels_depth.png": stixel_depth_overlay(img, st, min_depth=lo, max_depth=hi),
            "bev.png": bev_image(st, min_depth=lo, max_depth=hi),
            "depth_stixels.png": depth_colormap(st.depth_map(), min_depth=lo, max_depth=hi),
            "depth_sfm.png": depth_colormap(res.sfm_depth, min_depth=lo, max_depth=hi),
        }
        if res.semantic is not None:
            pics["semantics.png"] = semantic_colormap(res.semantic.argmax(0))
        if pair.gt.depth is not None:
            pics["depth_ground_truth.png"] = depth_colormap(pair.gt.depth, min_depth=lo, max_depth=hi)
        for name, pic in pics.items():
            write_image(self.out / name, pic)
        panels = [("Image", rgb), ("Ground Truth", pics.get("depth_ground_truth.png", rgb)),
                  ("Baseline - SFM", pics["depth_sfm.png"]), ("Ours - Mono-Stixels", pics["depth_stixels.png"]),
                  ("Input flow", pics["flow.png"]), ("Input semantic", pics.get("semantics.png", rgb)),
                  ("Mono-stixel types", pics["stixels_overlay.png"]), ("Mono-stixel semantic", pics["stixels_semantic.png"])]
        paper_figure(panels, self.out / "figure.png", ncols=4)
        st.save_json(self.out / "stixels.json")
        st.save_npz(self.out / "stixels.npz")
        self.names += [*pics, "figure.png", "stixels.json", "stixels.npz"]
