"""Time the column solver alone on a 1242x375 frame (w_s = 5) for several cell sizes r.

Inputs are the ground-truth flow, covariance and softened semantics of one synthetic frame, so
the DP sees a real street-scene column structure. Each setting is timed after a warm-up; the
median over repeats is reported with the peak resident memory of the process.

Usage::

    python benchmarks/solver_speed.py                   # r in {1, 2, 3, 5}, default solver config
    python benchmarks/solver_speed.py --json speed.json --repeats 5
    python benchmarks/solver_speed.py --stride 1        # every cell a hypothesis (the paper's set)

Measured numbers are in README.md ("Solver speed").
"""
from __future__ import annotations

import argparse
import json
import resource
import statistics
import time

import torch

from monostixels.data.synthetic import render_pair
from monostixels.energy import PriorParams
from monostixels.inputs.semantic import gt_scores
from monostixels.solver import SolverConfig, solve


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kilobytes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, nargs="+", default=[1, 2, 3, 5], help="cell sizes r to time")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--stride", type=int, default=None, help="solver.hypothesis_stride (default: config)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    ap.add_argument("--json", type=str, default=None, help="write {ms_per_frame: {r: ms}, peak_mb} here")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    pair = render_pair(0, scale=1.0)
    H, W = pair.size
    flow = pair.gt.flow.float()
    cov = (0.5**2) * torch.eye(2).expand(H, W, 2, 2).contiguous()
    scores = gt_scores(pair.gt.labels, confidence=0.9)
    prior = PriorParams.from_yaml()
    ms: dict[str, float] = {}
    print(f"solver on {W}x{H}, torch threads {torch.get_num_threads()}")
    for r in args.rows:
        over = {"cell_rows": r}
        if args.stride is not None:
            over["hypothesis_stride"] = args.stride
        cfg = SolverConfig.from_yaml(**over)
        times = []
        with torch.inference_mode():
            solve(flow, cov, scores, pair.camera, pair.motion, prior, cfg)  # warm-up
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                st = solve(flow, cov, scores, pair.camera, pair.motion, prior, cfg)
                times.append(time.perf_counter() - t0)
        ms[str(r)] = 1000 * statistics.median(times)
        print(f"r={r}: {ms[str(r)]:8.1f} ms/frame (median of {args.repeats}; stride {cfg.hypothesis_stride}; "
              f"{len(st)} stixels)  peak RSS {_peak_mb():.0f} MB", flush=True)
    out = {"ms_per_frame": ms, "peak_mb": _peak_mb()}
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
