"""Sustained seconds per frame of ``monostixels run`` over the shared KITTI raw drives, per preset and stage.

Composes the config as ``monostixels run`` does (``preset=fast`` is its default; ``preset=accurate`` the
most accurate inputs; with the same fallback where a default model file is missing), builds the
pipeline and the sequence layer as ``run`` does (no SfM baseline, which only ``eval`` reads) and runs
each drive in order, frame by frame: keyframes, the stream state carried from frame to frame
(``stream``), tracks. The first ``--warmup`` frames of each drive are not counted (model loading,
kernel loading, and the stream has nothing to carry yet); the table gives the median over the others.

Stages: each stage's own time within ``Pipeline.run`` (flow and semantics may run side by side, and
with ``stream.overlap`` they run for the next pair while this one's motion is estimated and it is solved), the dense depth map
``run`` turns into its outputs, ``waiting`` (for the next pair's inputs computed ahead: where the flow
is the longer of the two chains) and ``sequence`` (reading the images, keyframes, tracks, time to
collision: the rest of a step of the sequence layer). ``total`` is the step's own clock from one frame
to the next, depth map included: what a stream of frames sustains. ``cpu`` is the CPU time of the
whole process over that step (every thread) and ``main_thread_cpu`` that of the sequence layer's
thread alone: on a shared machine, where the wall clock measures the other jobs too,
``max(cpu / cores, main_thread_cpu)`` bounds what an idle machine with that many cores would take
(from below: waiting is not counted).

Usage::

    python benchmarks/pipeline_speed.py --json p.json                       # both presets, both drives
    python benchmarks/pipeline_speed.py --presets fast --set flow=dis --json p_dis.json   # any override
    python benchmarks/pipeline_speed.py --clock cpu --frames 6 --roots ../shared/data/kitti_raw
    python benchmarks/pipeline_speed.py --presets accurate --frames 12 --video clip.mp4 --video-set data.hfov_deg=58

``--video`` times each preset on a clip as well (``data=video``, whose ``data.resize=auto`` default brings a
720p or 1080p clip to about 0.5 megapixels), after the drives: the JSON's ``presets.<preset>.video_seconds``
and ``video_per_kitti`` (its total over the drives' total, in the same run).

The JSON's ``median_seconds`` (docs/conventions.md, section 4.7) is that of the first preset measured
(``fast``, what ``run`` does, unless ``--presets`` says otherwise); ``presets`` holds each preset's. Measured numbers:
docs/results.md ("Speed", "Threads and the DIS yardstick") and docs/benchmarks.md. On 2026-12-04, on a 2-core
machine shared with other jobs (load average 9-15, DIS itself 93-139 ms), ``preset=fast`` took 7.3-10.1x DIS
after the thread budget (``python benchmarks/pipeline_speed.py --presets fast --json p.json``) and 9.8-10.5x
before it, 0.67 against 0.66-0.73 CPU seconds a frame; with every pool left spinning (``MONOSTIXELS_SPIN=1``)
14.7-17.6x and 0.79-0.80 CPU seconds. On 2026-12-07, the development machine idle (DIS 36-42 ms), five runs
of ``--presets fast --json p.json`` interleaved with the tree of the day before: 5.4-7.3x DIS (median 6.2x),
0.220-0.306 s a frame (median 0.232), against 6.7-8.2x and 0.277-0.324 s.
"""
from __future__ import annotations

import os

# Before torch and OpenCV load their pools: idle threads sleep (what `import monostixels` does first).
from monostixels._threads import quiet_spinning

quiet_spinning()

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
import types  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from monostixels import cli  # noqa: E402
from monostixels import pipeline as pipeline_mod  # noqa: E402
from monostixels.build import Purpose, build  # noqa: E402
from monostixels.pipeline import load_config  # noqa: E402
from monostixels._threads import available_cores, set_threads, spinning  # noqa: E402
from monostixels._cpu import runtime_report  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
#: The shared development frames (../shared/data beside the checkout): a labelled drive and a LiDAR
#: drive.
DEFAULT_ROOTS = (REPO.parent / "shared/data/kitti_raw", REPO.parent / "shared/data/kitti_raw_lidar")
#: The presets measured by default: run's own first.
PRESETS = ("fast", "accurate")
#: The yardstick's frame size (KITTI's, width x height).
DIS_SIZE = (1242, 375)


def dis_pair(roots: list[str]) -> tuple[np.ndarray, np.ndarray, str]:
    """A KITTI-size (375, 1242) uint8 grey pair: the first two frames of the first drive found, else a render."""
    for root in roots:
        frames = sorted(p for p in Path(root).glob("*/*_sync/image_02/data/*") if p.suffix in (".png", ".jpg"))
        if len(frames) >= 2:
            a, b = (cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in frames[:2])
            if a is not None and b is not None:
                size = DIS_SIZE
                return cv2.resize(a, size), cv2.resize(b, size), f"{frames[0].parent}: {frames[0].name}, {frames[1].name}"
    from monostixels.data.synthetic import SyntheticSource
    from monostixels.inputs.flow_backends import gray_u8

    pair = SyntheticSource(1, seed=0)[0]
    a, b = (cv2.resize(gray_u8(x.float()), DIS_SIZE) for x in (pair.image, pair.image_prev))
    return a, b, "synthetic scene 0"


def time_dis(roots: list[str], repeats: int) -> tuple[float, str]:
    """Median wall seconds of OpenCV DIS (medium preset) on a KITTI-size grey pair, after one warm-up.

    OpenCV gets every core this process may use while the yardstick runs, whatever ``--threads`` gives
    the pipeline: DIS runs its patch search on OpenCV's threads, and a yardstick timed on fewer of them
    would be slower and flatter every ratio to it.
    """
    a, b, source = dis_pair(roots)
    pipeline_threads = cv2.getNumThreads()
    cv2.setNumThreads(available_cores())
    try:
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        dis.calc(a, b, None)  # warm-up: allocation, the thread pool started
        times = []
        for _ in range(max(1, repeats)):
            t0 = time.perf_counter()
            dis.calc(a, b, None)
            times.append(time.perf_counter() - t0)
    finally:
        cv2.setNumThreads(pipeline_threads)
    return statistics.median(times), source


def onnx_threads() -> int:
    """Intra-op threads of the ONNX Runtime sessions alive in this process (their largest; 0 = none)."""
    import gc

    try:
        import onnxruntime as ort
    except ImportError:
        return 0
    counts = []
    # The sequence layer freezes its start-up objects (the sessions among them) out of the collector's
    # lists: back in for the search, then frozen again.
    frozen = gc.get_freeze_count() > 0
    gc.unfreeze()
    objects = gc.get_objects()
    if frozen:
        gc.freeze()
    for obj in objects:
        if isinstance(obj, ort.InferenceSession):
            n = obj.get_session_options().intra_op_num_threads
            # 0: ONNX Runtime's own default, one thread per physical core.
            counts.append(n if n > 0 else (os.cpu_count() or 1))
    return max(counts, default=0)


def thread_counts() -> dict[str, int]:
    """Threads in use now: torch's intra-op, OpenCV's pool, the ONNX Runtime sessions' intra-op."""
    return {"torch": torch.get_num_threads(), "opencv": cv2.getNumThreads(), "onnxruntime": onnx_threads()}


def run_overrides(preset: str, sets: list[str]) -> list[str]:
    """What ``monostixels run preset=PRESET SETS...`` composes (its defaults and missing-model fallback)."""
    return cli.command_overrides("run", [f"preset={preset}", *sets])


def kitti_sources(roots: list[str], frames: int | None) -> list[tuple[str, list[str]]]:
    """The data overrides of each KITTI raw drive root, named by the root."""
    return [(root, ["data=kitti_raw", f"data.root={root}", *([f"data.frames={frames}"] if frames else [])])
            for root in roots]


def video_source(path: str, frames: int | None, sets: list[str]) -> list[tuple[str, list[str]]]:
    """The data overrides of a video clip (``data=video``; ``sets`` e.g. ``data.hfov_deg=58``), named by its path."""
    return [(path, ["data=video", f"data.path={path}", f"data.frames={frames or 20}", *sets])]


def medians(frames: list[dict[str, float]], stages: list[str]) -> dict[str, float]:
    """Per-stage median seconds over ``frames`` (a stage a frame lacks counts as 0)."""
    return {k: statistics.median(f.get(k, 0.0) for f in frames) for k in stages}


def time_preset(preset: str, sources: list[tuple[str, list[str]]], sets: list[str], warmup: int, overlap: bool,
                clock: Any) -> tuple[list[dict[str, float]], Any, list[str], list[int], dict[str, int]]:
    """Per-frame stage times of one preset over the sources (``(name, data overrides)``: :func:`kitti_sources`,
    :func:`video_source`), in order (warm-up frames left out), and torch's and OpenCV's thread counts while
    the frames ran (an overlapped stream gives torch one thread less while it runs: ``torch_threads``)."""
    overrides = run_overrides(preset, sets)
    out: list[dict[str, float]] = []
    cfg, size, running = None, [], {}
    for root, data in sources:
        cfg = load_config([*data, *overrides])
        built = build(cfg, Purpose.RUN, overlap=overlap)  # as `monostixels run` builds it
        src, runner, pipe = built.source, built.runner, built.pipeline
        last, cpu_last, main_last, waited_last = clock(), time.process_time(), time.thread_time(), 0.0
        for k, step in enumerate(runner.run(src)):
            res = step.result
            t0 = clock()
            res.stixels.depth_map()  # what `run` turns into its depth outputs
            now = clock()
            sec = {k2: v for k2, v in res.seconds.items() if k2 not in ("wall", "inputs", "inputs_ahead")}
            sec["depth_map"] = now - t0
            # From the last frame's end to this one's: the images read, the pair solved, tracks, depth map.
            sec["total"] = now - last
            # The pipeline's own clock on this step (inputs computed ahead ran during the last one).
            own = res.seconds["wall"] - res.seconds.get("inputs_ahead", 0.0)
            # Waiting for the pair ahead (stream.overlap): its flow and semantics are not done yet.
            waited = runner.stream.waited_s
            sec["waiting"], waited_last = waited - waited_last, waited
            sec["sequence"] = max(sec["total"] - sec["depth_map"] - own - sec["waiting"], 0.0)
            # CPU seconds of the step: all threads of the process, and this (the sequence layer's) thread.
            cpu, main = time.process_time(), time.thread_time()
            sec["cpu"], sec["main_thread_cpu"] = cpu - cpu_last, main - main_last
            last, cpu_last, main_last = now, cpu, main
            size = list(step.pair.size)
            running = {"torch": torch.get_num_threads(), "opencv": cv2.getNumThreads()}
            print(f"{preset} {Path(root).name}/{step.pair.name}: " + " ".join(f"{k2} {v:.3f}" for k2, v in sec.items())
                  + ("  (warm-up)" if k < warmup else ""), flush=True)
            if k >= warmup:
                out.append(sec)
    return out, cfg, overrides, size, running


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", nargs="+", default=list(PRESETS), help="presets to time (the first one's medians "
                    "are the JSON's median_seconds)")
    ap.add_argument("--roots", nargs="+", default=[str(r) for r in DEFAULT_ROOTS], help="kitti_raw data roots")
    ap.add_argument("--frames", type=int, default=None, help="frame pairs per root (default: all; the first --warmup "
                    "not counted)")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--set", dest="sets", nargs="*", default=[], metavar="KEY=VALUE",
                    help="config overrides after the preset, e.g. flow=dis stream.semantic_every=3")
    ap.add_argument("--threads", type=int, default=None, help="threads of torch, OpenCV and ONNX Runtime (config key "
                    "threads; default auto: the cores this process may use)")
    ap.add_argument("--clock", choices=["wall", "cpu"], default="wall",
                    help="cpu: stage times in CPU seconds of the process (all threads), which other jobs on a "
                         "shared machine inflate far less than wall time")
    ap.add_argument("--no-overlap", action="store_true",
                    help="semantics after the flow instead of beside it (Pipeline(overlap=False)); implied by --clock cpu, "
                         "where the stages' CPU seconds would otherwise mix (as would stream.overlap's, also off then)")
    ap.add_argument("--video", default=None, help="also time each preset on this clip (data=video, data.resize=auto), "
                    "after the drives: the JSON's video_seconds and video_per_kitti")
    ap.add_argument("--video-set", dest="video_sets", nargs="*", default=[], metavar="KEY=VALUE",
                    help="data overrides of --video, e.g. data.hfov_deg=58 data.step=2 (data.frames: --frames, else 20)")
    ap.add_argument("--dis-repeats", type=int, default=15, help="timed repeats of the DIS yardstick (after a warm-up)")
    ap.add_argument("--json", type=str, default=None, help="write the per-stage medians and all frame times here")
    args = ap.parse_args()
    clock = time.perf_counter if args.clock == "wall" else time.process_time
    if args.clock == "cpu":
        # Pipeline.run times its stages with time.perf_counter: give it the CPU clock instead.
        pipeline_mod.time = types.SimpleNamespace(perf_counter=time.process_time)  # type: ignore[assignment]
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    # As `monostixels run` does at start-up (config key `threads`): torch, OpenCV, ONNX Runtime.
    set_threads(args.threads or "auto")
    overlap = not (args.no_overlap or args.clock == "cpu")
    load0 = os.getloadavg()
    # The yardstick first and again at the end: the machine's speed while the presets ran lies between.
    dis_times = [time_dis(args.roots, args.dis_repeats)]
    results: dict[str, dict[str, Any]] = {}
    size: list[int] = []
    for preset in args.presets:
        # The CPU clock counts every thread: stages must then run one after the other (no pair ahead).
        sets = list(args.sets) + (["stream.overlap=false"] if args.clock == "cpu" else [])
        frames, cfg, overrides, size, running = time_preset(preset, kitti_sources(args.roots, args.frames), sets,
                                                            args.warmup, overlap, clock)
        if not frames:
            raise SystemExit("no frames timed: raise --frames above --warmup")
        stages = list(dict.fromkeys(k for f in frames for k in f))
        med = medians(frames, stages)
        results[preset] = {
            "config": {"flow": str(cfg.flow.name), "flow_preset": cfg.flow.get("preset"), "flow_scale": cfg.flow.get("scale"),
                       "semantic": str(cfg.semantic.name), "semantic_model": cfg.semantic.get("model"),
                       "motion": str(cfg.motion.name), "stream": dict(cfg.stream), "overrides": overrides, "overlap": overlap},
            "frames": len(frames), "median_seconds": med, "per_frame": frames,
            "cpu_seconds_per_frame": med.get("cpu"), "threads": {**thread_counts(), **running}}
        if args.video:
            vframes, _, _, vsize, _ = time_preset(preset, video_source(args.video, args.frames, args.video_sets), sets,
                                               args.warmup, overlap, clock)
            if not vframes:
                raise SystemExit("no video frames timed: raise --frames above --warmup")
            vmed = medians(vframes, [k for k in stages if k in vframes[0]])
            results[preset].update({"video_seconds": vmed, "video_frames": len(vframes), "video_size": vsize,
                                    "video_per_kitti": vmed["total"] / med["total"]})
    dis_times.append(time_dis(args.roots, args.dis_repeats))
    dis_s = statistics.median([t for t, _ in dis_times])
    load1 = os.getloadavg()
    torch_counts = ", ".join(f"{n} {r['threads']['torch']}" for n, r in results.items())
    print(f"\nmonostixels run, {args.clock} clock, medians over the frames after {args.warmup} warm-up frame(s) of each "
          f"drive, torch threads while they ran: {torch_counts}, load average {load0[0]:.2f} -> {load1[0]:.2f}")
    names = list(results)
    stages = list(dict.fromkeys(k for r in results.values() for k in r["median_seconds"]))
    print("| stage | " + " | ".join(f"`preset={n}` ({results[n]['frames']} frames)" for n in names) + " |")
    print("| --- |" + " ---: |" * len(names))
    for k in stages:
        print(f"| {k} | " + " | ".join(f"{results[n]['median_seconds'].get(k, 0.0):.3f}" for n in names) + " |")
    cores = os.cpu_count() or 1
    for n in names:
        m = results[n]["median_seconds"]
        if args.clock == "wall":  # with the pair ahead computed in a second thread
            bound = max(m["cpu"] / cores, m["main_thread_cpu"])
            results[n]["idle_bound_seconds"] = bound
            print(f"{n}: idle {cores}-core bound max(cpu / {cores}, main thread) = {bound:.3f} s per frame")
    for n in names:
        results[n]["total_per_dis"] = results[n]["median_seconds"]["total"] / dis_s
        print(f"{n}: total {results[n]['median_seconds']['total']:.3f} s = {results[n]['total_per_dis']:.1f} x DIS "
              f"({dis_s * 1000:.1f} ms, medium, {DIS_SIZE[0]}x{DIS_SIZE[1]}: {dis_times[0][1]}); "
              f"CPU {results[n]['cpu_seconds_per_frame']:.3f} s per frame; threads {results[n]['threads']}")
    for n in names:
        if "video_seconds" in results[n]:
            print(f"{n}: video {args.video} at its working size {results[n]['video_size']}: total "
                  f"{results[n]['video_seconds']['total']:.3f} s = {results[n]['video_per_kitti']:.2f} x the KITTI frames'")
    for n in names:
        c = results[n]["config"]
        print(f"{n}: flow={c['flow']} (preset {c['flow_preset']}, scale {c['flow_scale']}) "
              f"semantic={c['semantic']} ({c['semantic_model']}) motion={c['motion']} stream={c['stream']}")
    out = {"presets": results, "median_seconds": results[names[0]]["median_seconds"], "preset": names[0],
           "clock": args.clock, "torch_threads": results[names[0]]["threads"]["torch"],
           "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"), "spinning": spinning(), "loadavg": {"before": load0, "after": load1},
           "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, "roots": args.roots}
    out["image_size"] = size
    out.update({"dis_ms": dis_s * 1000.0, "dis_ms_runs": [t * 1000.0 for t, _ in dis_times], "dis_pair": dis_times[0][1],
                "total_per_dis": results[names[0]]["total_per_dis"], "threads": results[names[0]]["threads"],
                "cpu_seconds_per_frame": results[names[0]]["cpu_seconds_per_frame"]})
    out.update(runtime_report())  # cpu, onnxruntime, int8_path, solver_build: where the numbers were measured
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
