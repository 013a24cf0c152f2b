"""Soak: thousands of frames through the sequence layer of ``monostixels run``, looking for what grows.

The clip is a synthetic street (:class:`~monostixels.data.synthetic.SyntheticSequence`, a fixed ego
speed of 10 m/s, 1 m a frame) rendered once over ``--length`` frames and played **forward and back**
(0, 1, ..., L, L-1, ..., 0, 1, ...) into a 10 Hz mp4 of ``--frames + 1`` frames, with its intrinsics
beside it. The camera thus drives to the end of the street, reverses, drives back, and so on: its pose
never jumps, so the sequence layer sees one continuous drive of ``--frames`` pairs (a camera that
stops and turns back every L frames; the movers turn back with it) and never restarts. Objects leave
the view and come back, so tracks are born and die all along.

The clip is read as ``monostixels run data=video`` reads a file (``VideoSource``) and run as ``run``
runs it (:func:`monostixels.cli.command_overrides`: ``preset=fast``, ``output.rerun=false``, the same
``Pipeline`` and ``SequenceRunner``), each step's dense depth map made as ``run`` makes it; nothing is
written to disk. To keep 3000 steps cheap the images are small: ``--scale 0.25`` of KITTI's size
(94x310); the fast preset's choices are unchanged (DIS flow refined once, the FCN-8s every second
frame, monocular ego-motion, the stream carried from frame to frame).

Recorded per step: resident memory (``/proc/self/statm``), live tracks, the step's wall time, and the
sizes of the buffers that live from frame to frame (the sequence layer's kept frames, the stream's
kept frames, the source's decoded frames). ``rss_growth_mb`` is the resident memory at the end minus
that after the first 200 frames (the models, caches and allocator pools are warm by then).

``dropped`` comes from a second, shorter pass (``--realtime-frames``, default 300) of the same file
with ``data.realtime=true``: ``LiveVideoSource`` delivers the frames at the file's 10 Hz in wall time,
as a camera would, and drops the frames that arrive while one is solved.

Targets (issue 41): memory growth <= 50 MB, a track count with no growth trend, ``step_p99_s`` <= 2x
the median. Usage::

    python benchmarks/soak.py --json soak.json                      # 3000 frames
    python benchmarks/soak.py --frames 300 --realtime-frames 0      # a quick look
    python benchmarks/soak.py --set semantic=none --json s.json     # any override after the preset

Measured numbers: docs/results.md ("Soak").
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import statistics
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
from tqdm import tqdm

from monostixels import cli
from monostixels.build import Purpose, build_runner, build_source
from monostixels.pipeline import load_config
from monostixels.sequence import SequenceRunner

logger = logging.getLogger("soak")

#: The clip's frame rate (KITTI's): frame k is k / FPS seconds into the clip.
FPS = 10.0
#: The ego speed of the synthetic street (m/s): 1 m a frame at 10 Hz, so a street of 65-95 m holds 40 frames.
EGO_SPEED_MPS = 10.0
#: Frames after which memory counts as warm (``rss_growth_mb`` is measured from there).
WARM_FRAMES = 200
_PAGE_MB = os.sysconf("SC_PAGE_SIZE") / 2**20


def rss_mb() -> float:
    """Resident memory of this process now (MB; not the peak, which ``getrusage`` gives)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * _PAGE_MB


def pingpong_index(n: int, length: int) -> int:
    """Scene frame shown at clip frame ``n``: 0, 1, ..., length, length - 1, ..., 0, 1, ... (period 2 * length)."""
    k = n % (2 * length)
    return k if k <= length else 2 * length - k


def write_pingpong_clip(folder: Path, frames: int, *, seed: int = 3, scale: float = 0.25, length: int = 40) -> tuple[Path, Path]:
    """A ``frames + 1``-frame mp4 of a synthetic street played forward and back, and its intrinsics file.

    Args:
        folder: where ``soak.mp4`` and ``soak.intrinsics.yaml`` are written.
        frames: frame pairs the clip holds.
        seed: scene seed. scale: image size over KITTI's. length: scene frames of one way (>= 2).

    Returns:
        (video path, intrinsics path).
    """
    from monostixels.data.synthetic import SyntheticSequence

    seq = SyntheticSequence(seed, length, scale=scale, ego_speed=EGO_SPEED_MPS, cache=2)
    views: list[np.ndarray] = []
    for j in range(1, length + 1):  # each scene frame rendered once: pair (j, j - 1) holds frame j
        pair = seq.pair(j, j - 1)
        if j == 1:
            views.append(_bgr(pair.image_prev))
        views.append(_bgr(pair.image))
    folder.mkdir(parents=True, exist_ok=True)
    video = folder / "soak.mp4"
    H, W = views[0].shape[:2]
    vw = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), FPS, (W, H))
    for n in range(frames + 1):
        vw.write(views[pingpong_index(n, length)])
    vw.release()
    K = seq.camera.K
    intr = folder / "soak.intrinsics.yaml"
    intr.write_text(f"fx: {float(K[0, 0])}\nfy: {float(K[1, 1])}\ncx: {float(K[0, 2])}\ncy: {float(K[1, 2])}\n")
    return video, intr


def _bgr(image: Any) -> np.ndarray:
    """(3, H, W) float RGB in [0, 1] -> (H, W, 3) uint8 BGR for the video writer."""
    rgb = (image.clamp(0, 1).permute(1, 2, 0).numpy() * 255.0).round().astype(np.uint8)
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)


def soak_config(video: Path, intrinsics: Path, *, realtime: bool = False, sets: list[str] = ()) -> Any:
    """The config ``monostixels run data=video data.path=VIDEO preset=fast output.rerun=false SETS`` composes."""
    return load_config([f"data=video", f"data.path={video}", f"data.intrinsics={intrinsics}",
                        f"data.realtime={str(realtime).lower()}",
                        *cli.command_overrides("run", ["preset=fast", "output.rerun=false", *sets])])


def buffer_sizes(runner: SequenceRunner, source: Any) -> dict[str, int]:
    """Sizes of what lives from frame to frame: tracks, kept frames of the sequence layer, the stream, the source."""
    src = getattr(source, "_source", source)  # through the stream's lookahead wrapper
    kept = getattr(src, "_taken", None)
    if kept is None:
        kept = getattr(src, "_cache", ())
    stream = runner.stream
    return {"tracks": len(runner.tracks), "sequence_frames": len(runner.frames),
            "stream_frames": len(stream._frames), "source_frames": len(kept),
            "stream_chain_steps": sum(1 for f in stream._frames.values() if f.step is not None)}


@dataclass
class SoakRecord:
    """The series of one soak pass (one entry per processed step)."""

    rss_mb: list[float] = field(default_factory=list)
    tracks: list[int] = field(default_factory=list)
    stixels: list[int] = field(default_factory=list)
    step_s: list[float] = field(default_factory=list)
    buffers: list[dict[str, int]] = field(default_factory=list)
    failed: int = 0
    tracks_born: int = 0
    summary: dict[str, Any] | None = None


def run_soak(cfg: Any, frames: int | None = None, progress: bool = True,
             checkpoint: Callable[[SoakRecord], None] | None = None, every: int = 100) -> SoakRecord:
    """Run the config's source through the pipeline and sequence layer as ``monostixels run`` does; record the series.

    ``checkpoint`` is called with the record so far every ``every`` steps (a long soak that must be
    stopped still leaves its numbers).
    """
    src = build_source(cfg)
    runner = build_runner(cfg, Purpose.RUN)  # as `monostixels run` builds it
    pipe = runner.pipeline
    rec = SoakRecord()
    live = hasattr(src, "indices")
    bar = tqdm(total=None if live else len(src), desc="soak", unit="frame", disable=not progress, mininterval=2.0)
    last = time.perf_counter()
    for step in runner.run(src, progress=bar):
        if step.result is not None:
            step.result.stixels.depth_map()  # what `run` turns into its depth outputs
            rec.stixels.append(len(step.result.stixels))
        else:
            rec.failed += 1
        now = time.perf_counter()
        rec.step_s.append(now - last)
        rec.rss_mb.append(rss_mb())
        sizes = buffer_sizes(runner, runner.stream._lookahead or src)
        rec.tracks.append(sizes["tracks"])
        rec.buffers.append(sizes)
        rec.tracks_born = int(runner.tracks.next_id)  # ids given so far (the sequence never restarts here)
        last = now
        if checkpoint is not None and len(rec.step_s) % every == 0:
            checkpoint(rec)
        if frames is not None and len(rec.step_s) >= frames:
            break
    bar.close()
    if live:
        rec.summary = src.summary()
    return rec


def trend_per_1000(values: list[float]) -> float:
    """Least-squares slope of a series, per 1000 steps (0 for fewer than 2 values)."""
    if len(values) < 2:
        return 0.0
    x = np.arange(len(values), dtype=np.float64)
    return float(np.polyfit(x, np.asarray(values, dtype=np.float64), 1)[0] * 1000.0)


def report(rec: SoakRecord, realtime: SoakRecord | None) -> dict[str, Any]:
    """The JSON of a soak (module docstring): the headline numbers and the series beside them."""
    n = len(rec.step_s)
    warm = min(WARM_FRAMES, n - 1)
    steps = rec.step_s[1:] if n > 1 else rec.step_s  # the first step loads the models
    third = rec.tracks[2 * n // 3:]
    out: dict[str, Any] = {
        "frames": n,
        "rss_growth_mb": rec.rss_mb[-1] - rec.rss_mb[warm],
        "tracks_max": max(rec.tracks),
        "step_median_s": statistics.median(steps),
        "step_p99_s": float(np.percentile(steps, 99)),
        "dropped": None if realtime is None or realtime.summary is None else realtime.summary["frames_dropped"],
        "failed": rec.failed,
        "rss_mb_first": rec.rss_mb[0], "rss_mb_at_warm": rec.rss_mb[warm], "rss_mb_max_after_warm": max(rec.rss_mb[warm:]),
        "rss_trend_mb_per_1000": trend_per_1000(rec.rss_mb[warm:]),
        "stixels_max": max(rec.stixels, default=0), "tracks_born": rec.tracks_born, "tracks_died": rec.tracks_born - rec.tracks[-1],
        "tracks_trend_per_1000": trend_per_1000([float(t) for t in rec.tracks[warm:]]),
        "tracks_mean_first_third": float(np.mean(rec.tracks[: max(1, n // 3)])), "tracks_mean_last_third": float(np.mean(third)),
        "buffers_max": {k: max(b[k] for b in rec.buffers) for k in rec.buffers[0]},
        "series": {"rss_mb": rec.rss_mb, "tracks": rec.tracks, "step_s": rec.step_s, "stixels": rec.stixels,
                   "buffers": {k: [b[k] for b in rec.buffers] for k in rec.buffers[0]}},
    }
    if realtime is not None and realtime.summary is not None:
        s = realtime.summary
        out["realtime"] = {"fps": s["fps"], "frames_read": s["frames_read"], "frames_taken": s["frames_taken"],
                           "frames_dropped": s["frames_dropped"], "step_median_s": statistics.median(realtime.step_s),
                           "failed": realtime.failed}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=3000, help="frame pairs of the soak (default 3000)")
    ap.add_argument("--realtime-frames", type=int, default=300,
                    help="frames of the data.realtime=true pass at 10 Hz that counts the dropped frames (0 = none)")
    ap.add_argument("--scale", type=float, default=0.25, help="image size over KITTI's 1242x375 (default 0.25: 310x94)")
    ap.add_argument("--length", type=int, default=40, help="scene frames one way before the camera turns back")
    ap.add_argument("--seed", type=int, default=3, help="scene seed")
    ap.add_argument("--set", dest="sets", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides after the preset")
    ap.add_argument("--workdir", type=str, default=None, help="where the clip is written (default: a temporary folder)")
    ap.add_argument("--json", type=str, default=None, help="write the numbers and the series here")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("monostixels").setLevel(logging.WARNING)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.workdir or tmp)
        t0 = time.perf_counter()
        video, intr = write_pingpong_clip(folder, max(args.frames, args.realtime_frames), seed=args.seed,
                                          scale=args.scale, length=args.length)
        logger.info("clip %s: %d frames, forward and back over %d scene frames (%.1f s)", video,
                    max(args.frames, args.realtime_frames) + 1, args.length + 1, time.perf_counter() - t0)
        load0 = os.getloadavg()

        def checkpoint(rec: SoakRecord) -> None:
            if args.json:  # the numbers so far, marked incomplete
                Path(args.json).write_text(json.dumps({**report(rec, None), "complete": False}, indent=1))

        rec = run_soak(soak_config(video, intr, sets=args.sets), args.frames, checkpoint=checkpoint)
        rt = None
        if args.realtime_frames > 0:
            logger.info("realtime pass: %d frames at %g Hz", args.realtime_frames, FPS)
            rt = run_soak(soak_config(video, intr, realtime=True, sets=[*args.sets, f"data.end={args.realtime_frames + 1}"]))
        load1 = os.getloadavg()
    out = report(rec, rt)
    out.update({"complete": True, "scale": args.scale, "length": args.length, "seed": args.seed, "sets": args.sets,
                "loadavg": {"before": load0, "after": load1}})
    keys = ("frames", "rss_growth_mb", "tracks_max", "stixels_max", "step_median_s", "step_p99_s", "dropped", "failed", "tracks_born",
            "tracks_died", "tracks_trend_per_1000", "tracks_mean_first_third", "tracks_mean_last_third",
            "rss_trend_mb_per_1000", "buffers_max", "realtime")
    for k in keys:
        if k in out:
            print(f"{k}: {out[k]:.4g}" if isinstance(out[k], float) else f"{k}: {out[k]}")
    print(f"load average {load0[0]:.2f} -> {load1[0]:.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
