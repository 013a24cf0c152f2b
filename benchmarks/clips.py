"""Every real clip of the shared data through ``run``'s sequence layer, scored per clip in one table.

Each clip runs as a user would run it: ``preset=fast``, the ``Pipeline`` and ``SequenceRunner`` of
:mod:`benchmarks.dashcam` (motion failures kept as frames without a result), the overrides of
:data:`CLIPS` (and, found by globbing ``city/``, :data:`CITY_KINDS`). The clips:

- ``highway``: ``dashcam/highway_solid_white_right.mp4``, 40 pairs of every second frame, a guessed 58 deg
  field of view and 1.4 m camera height (as :mod:`benchmarks.dashcam`);
- ``traffic``: the KITTI raw drive ``kitti_raw_traffic`` (``data=kitti_raw``, 1.65 m), its LiDAR as ground
  truth. Where ``data=kitti_raw`` cannot read that folder, its frames run as ``data=frames`` with the
  intrinsics of ``calib_cam_to_cam.txt``'s ``P_rect_02`` and each frame's LiDAR read from
  ``proj_depth/velodyne_raw/image_02/<frame>.png`` (metres x 256);
- every ``city/dad_*`` folder (DAD dashcam frames, 20 fps): ``data=frames data.hfov_deg=90 data.fps=20
  camera.height=1.3``;
- every ``city/*.mp4`` (phones and cheap dashcams: ``kochi_phone_city``, ``singapore_rain_phone``,
  ``freeway_reflections``): ``data=video data.hfov_deg=65 data.step=2``. Their field of view is a guess,
  and the camera height is the default: no clip states either.

Columns of the table (the JSON holds the same per clip, ``clips.<name>``, and every pair under
``per_pair``):

- ``pairs``: frame pairs run; ``failed``: those without a result (the motion failed);
- ``motion m/s/su/u``: pairs whose ``flags.camera_motion`` is ``metric`` / ``standing`` / ``scale_unknown``
  / ``unknown``; ``standing``: the share of pairs flagged ``standing``;
- ``scale from``: pairs per ``flags.scale_from`` (``-`` where the flag is absent);
- ``speed m/s``: the camera speed ``|t| / dt`` over the metric pairs whose scale is certain
  (``flags.scale_uncertain`` false, as in the run's summary), median [min, max];
- ``scale std``: the median of ``flags.scale_std`` (the scale's relative uncertainty), ``-`` where no pair
  has it;
- ``false movers %``: per frame, the image share of stixels typed ``dynamic_object`` outside the referee's
  vehicles and persons dilated by 15 px (:func:`benchmarks.dashcam.false_movers`); median / max over frames;
- ``TTC frames``: frames with a stixel's ``ttc_warning``, and their share of the pairs;
- ``TTC off ref``: frames with a warning stixel that has a pixel outside the referee's dilated vehicles and
  persons (a warning on a building, the road, a tree);
- ``LiDAR rel / d1.25`` and ``SfM rel / d1.25`` (clips with LiDAR): the dense depth of the stixels
  (``StixelWorld.depth_map``) and of the SfM baseline (``result.sfm_depth``, run on these clips only) against
  the LiDAR, over every LiDAR pixel of every frame, as ``monostixels eval`` scores them
  (:class:`monostixels.eval.metrics.DepthAccumulator`: invalid estimates set to 80 m, valid ones clamped to
  [0.001, 80] m, docs/conventions.md section 4.5); a failed frame counts with invalid estimates.

The referee (``--referee``, a Cityscapes ONNX model, by default
``../shared/models/espnetv2_cityscapes_640x1024.onnx`` where it exists) only scores; without one the false
movers and warnings off the referee are not measured (``-``).

Command over every clip (repository root)::

    python -m benchmarks.clips --json runs/eval/clips.json --md runs/eval/clips.md

``--clips highway dad_000528`` runs a subset, ``--frames N`` caps every clip at N pairs (``data.frames``),
``--data DIR`` reads the clips from another folder; words after the flags are ``monostixels run``
overrides applied to every clip.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import tempfile
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import cv2
import numpy as np
import torch
from tqdm import tqdm

from benchmarks.dashcam import _DILATE_PX, _MOVER_CLASSES, _referee, false_movers, pair_speed
from monostixels._checks import InputError
from monostixels.build import Purpose, build_runner
from monostixels.core.classes import DYNAMIC_OBJECT
from monostixels.build import build_source
from monostixels.eval.metrics import DepthAccumulator
from monostixels.pipeline import load_config
from monostixels.sequence.runner import SequenceStep

__all__ = ["Clip", "CLIPS", "CITY_KINDS", "FrameScore", "discover_clips", "warnings_off_referee", "summarize",
           "lidar_summary", "kitti_intrinsics", "markdown", "measure", "main"]

logger = logging.getLogger(__name__)

_REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = _REPO.parent / "shared" / "data"
DEFAULT_REFEREE = _REPO.parent / "shared" / "models" / "espnetv2_cityscapes_640x1024.onnx"
#: The values of ``flags.camera_motion`` (docs/conventions.md, section 4.4), in the table's order.
MOTION_KINDS = ("metric", "standing", "scale_unknown", "unknown")
#: The LiDAR depth PNGs of a KITTI drive (the depth benchmark's ``velodyne_raw``): metres x this, 0 = none.
_LIDAR_DIR = Path("proj_depth") / "velodyne_raw" / "image_02"
_LIDAR_PER_M = 256.0
#: KITTI raw's frame rate (Hz).
_KITTI_FPS = 10


@dataclass(frozen=True)
class Clip:
    """A clip and how a user runs it.

    Attributes:
        name: the clip's name in the table.
        overrides: ``monostixels run`` overrides; ``{data}`` stands for the data folder.
        lidar: whether the clip has LiDAR depth (then scored, with the SfM baseline).
        kitti_frames: a KITTI raw folder (``{data}``-relative) whose drive runs as ``data=frames`` where
            ``data=kitti_raw`` cannot read it; None = no such fallback.
    """

    name: str
    overrides: tuple[str, ...]
    lidar: bool = False
    kitti_frames: str | None = None

    def resolved(self, data: Path) -> list[str]:
        """The overrides with ``{data}`` replaced by ``data``."""
        return [o.replace("{data}", str(data)) for o in self.overrides]

    def found(self, data: Path) -> bool:
        """Whether the file or folder of its ``data.path`` / ``data.root`` override exists under ``data``."""
        paths = [o.split("=", 1)[1] for o in self.resolved(data) if o.startswith(("data.path=", "data.root="))]
        return all(Path(p).exists() for p in paths)


#: The fixed clips (module docstring).
CLIPS: tuple[Clip, ...] = (
    Clip("highway", ("data=video", "data.path={data}/dashcam/highway_solid_white_right.mp4", "data.hfov_deg=58",
                     "data.step=2", "data.frames=40", "camera.height=1.4")),
    Clip("traffic", ("data=kitti_raw", "data.root={data}/kitti_raw_traffic", "camera.height=1.65"),
         lidar=True, kitti_frames="kitti_raw_traffic"),
)
#: The clips found in ``city/``: a glob -> the overrides of each match (``{path}`` = the match).
CITY_KINDS: dict[str, tuple[str, ...]] = {
    "dad_*": ("data=frames", "data.root={path}", "data.hfov_deg=90", "data.fps=20", "camera.height=1.3"),
    "*.mp4": ("data=video", "data.path={path}", "data.hfov_deg=65", "data.step=2"),
}


def discover_clips(data: Path) -> list[Clip]:
    """The fixed clips (:data:`CLIPS`) found under ``data`` and every ``city/`` clip of a kind of :data:`CITY_KINDS`.

    A DAD entry must be a folder and an mp4 a file; names are the folder name or the file's stem.
    """
    clips = [c for c in CLIPS if c.found(data)]
    for pattern, overrides in CITY_KINDS.items():
        for path in sorted((data / "city").glob(pattern)):
            if path.is_dir() == pattern.startswith("dad_"):
                clips.append(Clip(path.stem, tuple(o.replace("{path}", str(path)) for o in overrides)))
    return clips


def kitti_intrinsics(calib: Path, camera: str = "02") -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` (pixels) of ``P_rect_<camera>`` in a KITTI ``calib_cam_to_cam.txt``."""
    for line in calib.read_text().splitlines():
        key, _, values = line.partition(":")
        if key.strip() == f"P_rect_{camera}":
            P = np.array(values.split(), dtype=np.float64).reshape(3, 4)
            return float(P[0, 0]), float(P[1, 1]), float(P[0, 2]), float(P[1, 2])
    raise InputError(f"{calib}: no P_rect_{camera} line")


def _kitti_frames_overrides(root: Path, tmp: Path) -> tuple[list[str], Path]:
    """``data=frames`` overrides for the (one) drive under a KITTI raw ``root``, and its LiDAR folder.

    The intrinsics come from the date folder's ``calib_cam_to_cam.txt``, written to ``tmp``; the images
    are not resized, so the LiDAR PNGs keep the frames' size.
    """
    images = sorted(root.glob("*/*_sync/image_02/data"))
    if not images:
        raise InputError(f"{root}: no DATE/DATE_drive_*_sync/image_02/data folder")
    drive = images[0].parents[1]
    fx, fy, cx, cy = kitti_intrinsics(drive.parent / "calib_cam_to_cam.txt")
    intr = tmp / "intrinsics.txt"
    intr.write_text(f"{fx} {fy} {cx} {cy}\n")
    return (["data=frames", f"data.root={images[0]}", f"data.intrinsics={intr}", f"data.fps={_KITTI_FPS}",
             "data.resize=null"], drive / _LIDAR_DIR)


def _lidar_depth(step: SequenceStep, lidar_dir: Path | None) -> torch.Tensor | None:
    """(H, W) LiDAR depth (m, 0 = none) of a step's frame: the source's ground truth, else the PNG named
    after the frame in ``lidar_dir``; None where neither exists."""
    gt = step.pair.gt
    if gt is not None and gt.depth is not None:
        return gt.depth
    png = None if lidar_dir is None else lidar_dir / f"{step.pair.name}.png"
    if png is None or not png.is_file():
        return None
    return torch.from_numpy(cv2.imread(str(png), cv2.IMREAD_UNCHANGED).astype(np.float32) / _LIDAR_PER_M)


@dataclass
class FrameScore:
    """What one pair of a clip scored (``None``: not measured, e.g. no referee or no metric motion).

    Attributes:
        pair: the pair's name. camera_motion, scale_from, scale_std: its flags (``scale_std`` relative).
        speed_mps: ``|t| / dt`` of a metric pair of a certain scale, m/s. failed: no result (the motion failed).
        false_mover_share: image share of moving stixels off the referee's movers.
        ttc_warnings: warning stixels. ttc_off_referee: warning stixels with a pixel off the referee's movers.
    """

    pair: str
    camera_motion: str | None = None
    scale_from: str | None = None
    scale_std: float | None = None
    speed_mps: float | None = None
    failed: bool = False
    false_mover_share: float | None = None
    ttc_warnings: int = 0
    ttc_off_referee: int | None = None


def warnings_off_referee(index_map: np.ndarray, warning: np.ndarray, near: np.ndarray) -> int:
    """Warning stixels that cover a pixel outside the referee's (dilated) movers.

    Args:
        index_map: (H, W) int, the stixel of each pixel (-1 = none), ``StixelWorld.index_map``.
        warning: (N,) bool, each stixel's ``ttc_warning``.
        near: (H, W) bool, the referee's vehicles and persons, dilated.
    """
    off = index_map[(index_map >= 0) & ~near]
    return int(np.unique(off[warning[off]]).size)


def _score(step: SequenceStep, classes: Callable[[Any], np.ndarray] | None, kernel: np.ndarray) -> FrameScore:
    """The :class:`FrameScore` of one step (the referee's ``classes`` of its pair, or None)."""
    res = step.result
    if res is None:
        return FrameScore(step.pair.name, failed=True)
    st = res.stixels
    kind = st.flags.get("camera_motion", "metric")
    score = FrameScore(step.pair.name, kind, st.flags.get("scale_from"), st.flags.get("scale_std"),
                       ttc_warnings=int(st.ttc_warning.sum()) if st.ttc_warning is not None else 0,
                       speed_mps=pair_speed(res))
    if classes is not None:
        referee = classes(step.pair)
        idx = st.index_map().numpy()
        moving = (idx >= 0) & (st.type.numpy()[np.clip(idx, 0, None)] == DYNAMIC_OBJECT)
        score.false_mover_share = false_movers(moving, referee, kernel)[0]
        near = cv2.dilate(np.isin(referee, _MOVER_CLASSES).astype(np.uint8), kernel).astype(bool)
        warn = st.ttc_warning.numpy() if st.ttc_warning is not None else np.zeros(len(st), bool)
        score.ttc_off_referee = warnings_off_referee(idx, warn, near)
    return score


def _stats(values: Sequence[float | None]) -> dict[str, float | None]:
    """Median, min and max of the values that are not None (all None where there are none)."""
    v = np.array([x for x in values if x is not None], dtype=np.float64)
    if v.size == 0:
        return {"median": None, "min": None, "max": None}
    return {"median": float(np.median(v)), "min": float(v.min()), "max": float(v.max())}


def summarize(frames: Sequence[FrameScore]) -> dict[str, Any]:
    """A clip's row (module docstring) from its pairs' scores; shares in 0..1, speeds in m/s."""
    n = len(frames)
    ok = [f for f in frames if not f.failed]
    refereed = [f for f in ok if f.ttc_off_referee is not None]
    warned = sum(f.ttc_warnings > 0 for f in ok)
    return {
        "pairs": n,
        "failed": n - len(ok),
        "camera_motion": {k: sum(f.camera_motion == k for f in ok) for k in MOTION_KINDS},
        "scale_from": dict(Counter(f.scale_from or "-" for f in ok)),
        "standing_share": sum(f.camera_motion == "standing" for f in ok) / max(n, 1),
        "speed_mps": _stats([f.speed_mps for f in ok]),
        "scale_std_median": _stats([f.scale_std for f in ok])["median"],
        "false_mover_share": ({k: v for k, v in _stats([f.false_mover_share for f in ok]).items() if k != "min"}
                              if refereed else None),
        "ttc_frames": warned,
        "ttc_frame_share": warned / max(n, 1),
        "ttc_off_referee_frames": sum(f.ttc_off_referee > 0 for f in refereed) if refereed else None,
    }


def lidar_summary(acc: DepthAccumulator) -> dict[str, float | int | None]:
    """``{"rel", "d1.25", "n"}`` of an accumulator (None where it counted no pixel)."""
    r = acc.result()
    return {k: (None if isinstance(r[k], float) and math.isnan(r[k]) else r[k]) for k in ("rel", "d1.25", "n")}


def _open(clip: Clip, data: Path, extra: list[str], tmp: Path) -> tuple[Any, Any, list[str], Path | None]:
    """The config, the source, the overrides used and the LiDAR PNG folder (None: the source's own ground
    truth) of a clip."""
    overrides = [*clip.resolved(data), *extra]
    try:
        cfg = load_config(["preset=fast", *overrides])
        return cfg, build_source(cfg.data, cfg.camera), overrides, None
    except InputError as err:
        if clip.kitti_frames is None:
            raise
        logger.warning("%s: %s; its frames run as data=frames", clip.name, err)
    frames, lidar_dir = _kitti_frames_overrides(data / clip.kitti_frames, tmp)
    overrides = [*frames, *(o for o in clip.resolved(data) if not o.startswith("data")), *extra]
    cfg = load_config(["preset=fast", *overrides])
    return cfg, build_source(cfg.data, cfg.camera), overrides, lidar_dir


def measure(clip: Clip, data: Path, extra: list[str], referee: str | None = None) -> dict[str, Any]:
    """Run one clip and score it (module docstring); the clip's JSON entry."""
    with tempfile.TemporaryDirectory() as tmp:
        cfg, src, overrides, lidar_dir = _open(clip, data, extra, Path(tmp))
        # As `monostixels run` builds it, with the SfM baseline where the clip has LiDAR to score it against.
        runner = build_runner(cfg, Purpose.RUN, sfm=clip.lidar)
        classes = _referee(referee)
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * _DILATE_PX + 1, 2 * _DILATE_PX + 1))
        ev = runner.pipeline.eval_cfg
        acc = {m: DepthAccumulator(min_depth=ev.min_depth, max_depth=ev.max_depth) for m in ("monostixels", "sfm")}
        frames: list[FrameScore] = []
        for step in tqdm(runner.run(src), total=len(src), desc=clip.name, unit="pair"):
            frames.append(_score(step, classes, kernel))
            gt = _lidar_depth(step, lidar_dir) if clip.lidar else None
            if gt is not None:
                nothing = torch.full(gt.shape, float("nan"))
                res = step.result
                acc["monostixels"].add(res.stixels.depth_map() if res is not None else nothing, gt)
                sfm = res.sfm_depth if res is not None else None
                acc["sfm"].add(sfm if sfm is not None else nothing, gt)
    report = summarize(frames)
    if clip.lidar:
        report["lidar"] = {m: lidar_summary(a) for m, a in acc.items()}
    report["overrides"] = overrides
    report["per_pair"] = [asdict(f) for f in frames]
    return report


def _fmt(x: float | None, spec: str = ".2f", scale: float = 1.0) -> str:
    return "-" if x is None else format(x * scale, spec)


def _row(name: str, r: dict[str, Any]) -> str:
    """One Markdown table row of a clip's report."""
    s = r["speed_mps"]
    fm = r["false_mover_share"] or {"median": None, "max": None}
    lidar = r.get("lidar", {})

    def depth(m: str) -> str:
        d = lidar.get(m)
        return "-" if d is None else f"{_fmt(d['rel'], '.3f')} / {_fmt(d['d1.25'], '.3f')}"

    cells = [name, f"{r['pairs']} ({r['failed']})", "/".join(str(r["camera_motion"][k]) for k in MOTION_KINDS),
             _fmt(r["standing_share"], ".0%"), ", ".join(f"{k} {v}" for k, v in sorted(r["scale_from"].items())),
             f"{_fmt(s['median'], '.1f')} [{_fmt(s['min'], '.1f')}, {_fmt(s['max'], '.1f')}]",
             _fmt(r["scale_std_median"]), f"{_fmt(fm['median'], '.2f', 100)} / {_fmt(fm['max'], '.2f', 100)}",
             f"{r['ttc_frames']} ({_fmt(r['ttc_frame_share'], '.0%')})", _fmt(r["ttc_off_referee_frames"], ".0f"),
             depth("monostixels"), depth("sfm")]
    return "| " + " | ".join(cells) + " |"


def markdown(clips: dict[str, dict[str, Any]]) -> str:
    """The Markdown table of the clips' reports (columns: module docstring)."""
    head = ["clip", "pairs (failed)", "motion m/s/su/u", "standing", "scale from", "speed m/s", "scale std",
            "false movers %", "TTC frames", "TTC off ref", "LiDAR rel / d1.25", "SfM rel / d1.25"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    return "\n".join(lines + [_row(n, r) for n, r in clips.items()]) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
    ap.add_argument("--clips", nargs="+", metavar="NAME", help="run only these clips")
    ap.add_argument("--frames", type=int, help="at most this many pairs a clip (data.frames)")
    ap.add_argument("--referee", default=str(DEFAULT_REFEREE) if DEFAULT_REFEREE.is_file() else None,
                    help="a Cityscapes ONNX model whose vehicles and persons referee movers and warnings")
    ap.add_argument("--json", type=Path, help="write the report here")
    ap.add_argument("--md", type=Path, help="write the Markdown table here")
    ap.add_argument("overrides", nargs="*", help="monostixels run overrides (key=value) for every clip")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    torch.set_grad_enabled(False)
    clips = {c.name: c for c in discover_clips(args.data)}
    unknown = [n for n in args.clips or [] if n not in clips]
    if unknown:
        ap.error(f"unknown clips {unknown}; found: {', '.join(clips)}")
    extra = [*args.overrides, *([f"data.frames={args.frames}"] if args.frames else [])]
    reports = {n: measure(clips[n], args.data, extra, args.referee) for n in (args.clips or clips)}
    table = markdown(reports)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"referee": args.referee, "clips": reports}, indent=2))
    if args.md:
        args.md.parent.mkdir(parents=True, exist_ok=True)
        args.md.write_text(table)
    print(table, end="")


if __name__ == "__main__":
    main()
