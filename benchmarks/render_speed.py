"""Speed of the synthetic renderer: one frame pair with ground truth at 1242 x 375.

Run from the repository root:

    nice -n 10 python benchmarks/render_speed.py --seeds 5

It renders one warm-up pair (builds the noise texture), then ``--seeds`` pairs (scene seeds
0..n-1), and prints the median wall-clock and CPU seconds per pair (images + all ground truth).

Measured 2026-11-22 on the project machine (2 CPU cores shared with 5 other jobs, load average
about 10), scale 1.0 (1242 x 375), 5 pairs:

    nice -n 10 python benchmarks/render_speed.py --seeds 5 --threads 1
        median wall 0.792 s/pair, median cpu 0.525 s/pair
    nice -n 10 python benchmarks/render_speed.py --seeds 5          (torch default, 2 threads)
        median wall 3.129 s/pair, median cpu 1.998 s/pair

With the cores oversubscribed, torch's two intra-op threads mostly wait on each other; for
data generation on a shared machine, ``--threads 1`` (``torch.set_num_threads(1)``) is faster.
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from monostixels.data.synthetic import render_pair


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5, help="number of timed frame pairs")
    ap.add_argument("--scale", type=float, default=1.0, help="resolution scale (1.0 = 1242 x 375)")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0 = torch default)")
    args = ap.parse_args()
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    render_pair(10_000, scale=args.scale)  # warm-up
    wall, cpu = [], []
    for s in range(args.seeds):
        t0, c0 = time.perf_counter(), time.process_time()
        render_pair(s, scale=args.scale)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    print(f"threads={torch.get_num_threads()} scale={args.scale} pairs={args.seeds}")
    print(f"median wall {statistics.median(wall):.3f} s/pair (min {min(wall):.3f}, max {max(wall):.3f})")
    print(f"median cpu  {statistics.median(cpu):.3f} s/pair")


if __name__ == "__main__":
    main()
