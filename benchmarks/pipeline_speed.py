"""Seconds per stage of ``monostixels run``'s default configuration on the shared KITTI raw frames.

Composes the config exactly as ``monostixels run`` does (its default inputs, with the same
fallback where a default model file is missing), builds the pipeline as ``run`` does (no SfM
baseline, which only ``eval`` reads) and times every stage of ``Pipeline.run`` plus the dense
depth map ``run`` writes, on full-size frames of each data root. The first ``--warmup`` frames of
each root are not counted (model loading, kernel loading, caches); the table gives the median
over the other frames. ``total`` is the pair's own clock (with the default overlap, the flow and
the semantics run side by side, so it is less than the sum of the stages).

Usage::

    python benchmarks/pipeline_speed.py --json p.json
    python benchmarks/pipeline_speed.py --set flow=dis --json p_dis.json        # any config override
    python benchmarks/pipeline_speed.py --set semantic=fcn8s --frames 4 --roots ../shared/data/kitti_raw

Measured numbers: docs/results.md ("Speed") and docs/benchmarks.md.
"""
from __future__ import annotations

import os

# Before torch loads OpenMP (monostixels sets the same default on import).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
import types  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from monostixels import cli  # noqa: E402
from monostixels import pipeline as pipeline_mod  # noqa: E402
from monostixels.pipeline import Pipeline, load_config  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
#: The shared development frames (SPEC section 4: data/ beside SPEC.md): a labelled drive and a LiDAR drive.
DEFAULT_ROOTS = (REPO.parent / "shared/data/kitti_raw", REPO.parent / "shared/data/kitti_raw_lidar")


def run_overrides(sets: list[str]) -> list[str]:
    """``monostixels run``'s default inputs (with its missing-model fallback), then ``sets``."""
    given = {s.split("=", 1)[0] for s in sets}
    defaults = [d for d in cli._RUN_DEFAULTS if d.split("=")[0] not in given]
    for d in list(defaults):
        if d in cli._DEFAULT_MODELS and not cli._model_available(cli._DEFAULT_MODELS[d]):
            logging.warning("run: %s not found; using %s (as monostixels run does)", cli._DEFAULT_MODELS[d],
                            cli._MODEL_FALLBACK["run"])
            defaults[defaults.index(d)] = cli._MODEL_FALLBACK["run"]
    return defaults + sets


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--roots", nargs="+", default=[str(r) for r in DEFAULT_ROOTS], help="kitti_raw data roots")
    ap.add_argument("--frames", type=int, default=6, help="frame pairs per root (the first --warmup not counted)")
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--set", dest="sets", nargs="*", default=[], metavar="KEY=VALUE",
                    help="config overrides after run's defaults, e.g. flow=dis semantic=fcn8s")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    ap.add_argument("--clock", choices=["wall", "cpu"], default="wall",
                    help="cpu: stage times in CPU seconds of the process (all threads), which other jobs on a "
                         "shared machine inflate far less than wall time")
    ap.add_argument("--no-overlap", action="store_true",
                    help="semantics after the flow instead of beside it (Pipeline(overlap=False)); implied by --clock cpu, "
                         "where the stages' CPU seconds would otherwise mix")
    ap.add_argument("--json", type=str, default=None, help="write the per-stage medians and all frame times here")
    args = ap.parse_args()
    clock = time.perf_counter if args.clock == "wall" else time.process_time
    if args.clock == "cpu":
        # Pipeline.run times its stages with time.perf_counter: give it the CPU clock instead.
        pipeline_mod.time = types.SimpleNamespace(perf_counter=time.process_time)  # type: ignore[assignment]
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.threads:
        torch.set_num_threads(args.threads)
    overrides = run_overrides(list(args.sets))
    frames: list[dict[str, float]] = []
    cfg = None
    load0 = os.getloadavg()
    for root in args.roots:
        cfg = load_config(["data=kitti_raw", f"data.root={root}", f"data.frames={args.frames}", *overrides])
        src = cli._source(cfg)
        overlap = not (args.no_overlap or args.clock == "cpu")
        pipe = Pipeline(cfg, allow_motion_failure=True, sfm=False, overlap=overlap)  # as `monostixels run` builds it
        for k, pair in enumerate(src):
            res = pipe.run(pair)
            t0 = clock()
            res.stixels.depth_map()  # what `run` turns into its depth outputs
            sec = {k2: v for k2, v in res.seconds.items() if k2 != "wall"}
            sec["depth_map"] = clock() - t0
            # The pair's own clock: with overlap the flow and semantic stages run side by side.
            sec["total"] = res.seconds["wall"] + sec["depth_map"]
            print(f"{Path(root).name}/{pair.name}: " + " ".join(f"{k2} {v:.3f}" for k2, v in sec.items())
                  + ("  (warm-up)" if k < args.warmup else ""), flush=True)
            if k >= args.warmup:
                frames.append(sec)
    if not frames:
        raise SystemExit("no frames timed: raise --frames above --warmup")
    assert cfg is not None
    stages = list(dict.fromkeys(k for f in frames for k in f))
    med = {k: statistics.median(f.get(k, 0.0) for f in frames) for k in stages}
    H, W = pair.size
    print(f"\nmonostixels run, {W}x{H}, {len(frames)} frames after warm-up, {args.clock} clock, "
          f"torch threads {torch.get_num_threads()}, "
          f"load average {load0[0]:.2f} -> {os.getloadavg()[0]:.2f}")
    print(f"config: flow={cfg.flow.name} (scale {cfg.flow.get('scale', 1.0)}, refine {cfg.flow.get('refine', False)}) "
          f"semantic={cfg.semantic.name} motion={cfg.motion.name} solver.cell_rows={cfg.solver.cell_rows} "
          f"solver.backend={cfg.solver.backend}; semantics beside the flow: {overlap}")
    print(f"| stage | {args.clock} s / frame (median) |\n| --- | ---: |")
    for k in stages:
        print(f"| {k} | {med[k]:.3f} |")
    out = {"config": {"flow": str(cfg.flow.name), "semantic": str(cfg.semantic.name), "motion": str(cfg.motion.name),
                      "overrides": overrides, "overlap": overlap}, "image_size": [H, W], "frames": len(frames),
           "clock": args.clock, "torch_threads": torch.get_num_threads(), "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
           "loadavg": {"before": load0, "after": os.getloadavg()},
           "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
           "median_seconds": med, "per_frame": frames}
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
