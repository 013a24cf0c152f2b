"""Time per frame of semantic ONNX nets, side by side in one run (the semantic stage's speed check).

Each file gets its own ONNX Runtime session with ``--threads`` intra-op threads (1 by default: what
one stage of the pipeline gets on a 2-core machine), one warm-up run, then ``--runs`` timed runs on
the same random input of ``--size`` (height width, multiples of 32; the default 384x1248 is a KITTI
frame), the files interleaved and their order alternated from run to run, so that a machine that
slows down or speeds up during the run weighs on every file alike. Reported per file: the median and
the minimum in milliseconds, and each file's median against the first file's (``ratio``).

Command (repository root; the net before the distillation from the repository's history)::

    mkdir -p runs && git show 64f5d07:models/fcn8s_real.onnx > runs/fcn8s_real_2026-11-30.onnx
    python -m benchmarks.semantic_speed runs/fcn8s_real_2026-11-30.onnx models/fcn8s_real.onnx --json s.json
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["measure", "main"]


def measure(files: list[str | Path], *, size: tuple[int, int] = (384, 1248), runs: int = 12,
            threads: int = 1, seed: int = 0) -> dict[str, Any]:
    """Interleaved timing of ``files`` (module docstring).

    Args:
        files: ONNX files with one image input (B, 3, H, W) float32.
        size: (H, W) of the input in pixels, each a multiple of 32.
        runs: timed runs per file.
        threads: ONNX Runtime intra-op threads per session.
        seed: of the random input.

    Returns:
        ``{"size", "threads", "runs", "files": [{"file", "median_ms", "min_ms", "ratio", "times_ms"}], "cpu",
        "onnxruntime", "int8_path"}`` (the last three: :func:`monostixels._cpu.runtime_report`'s, where the
        INT8 files ran).
    """
    import onnxruntime as ort

    from monostixels._cpu import cpu_info, int8_path

    if len(size) != 2 or any(int(s) <= 0 or int(s) % 32 for s in size):
        raise ValueError(f"--size {list(size)}: height and width must be positive multiples of 32")
    if runs < 1:
        raise ValueError(f"--runs {runs}: at least 1")
    missing = [str(f) for f in files if not Path(f).is_file()]
    if missing:
        raise FileNotFoundError(f"semantic_speed: no such ONNX file: {', '.join(missing)}")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(threads)
    opts.inter_op_num_threads = 1
    sessions = [ort.InferenceSession(str(f), opts, providers=["CPUExecutionProvider"]) for f in files]
    x = np.random.default_rng(seed).random((1, 3, int(size[0]), int(size[1])), dtype=np.float32)
    feeds = [{s.get_inputs()[0].name: x} for s in sessions]
    for s, feed in zip(sessions, feeds):
        s.run(None, feed)
    times: list[list[float]] = [[] for _ in files]
    for r in range(runs):
        order = range(len(files)) if r % 2 == 0 else reversed(range(len(files)))
        for i in order:
            t0 = time.perf_counter()
            sessions[i].run(None, feeds[i])
            times[i].append((time.perf_counter() - t0) * 1e3)
    medians = [statistics.median(t) for t in times]
    return {"size": [int(size[0]), int(size[1])], "threads": int(threads), "runs": int(runs),
            "files": [{"file": str(f), "median_ms": m, "min_ms": min(t), "ratio": m / medians[0], "times_ms": t}
                      for f, m, t in zip(files, medians, times)],
            "cpu": cpu_info(), "onnxruntime": ort.__version__, "int8_path": int8_path()}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="+", help="ONNX files; the first is the reference of 'ratio'")
    ap.add_argument("--size", type=int, nargs=2, default=[384, 1248], metavar=("H", "W"))
    ap.add_argument("--runs", type=int, default=12)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path, help="write the report here")
    args = ap.parse_args(argv)
    try:
        rep = measure(args.files, size=tuple(args.size), runs=args.runs, threads=args.threads)
    except (ValueError, FileNotFoundError) as e:
        raise SystemExit(f"error: {e}") from None
    print(f"{rep['cpu']['model']}, ONNX Runtime {rep['onnxruntime']}, INT8 path {rep['int8_path']}")
    for f in rep["files"]:
        print(f"{f['file']}: median {f['median_ms']:.1f} ms, min {f['min_ms']:.1f} ms, {f['ratio']:.3f}x the first")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rep, indent=1))


if __name__ == "__main__":
    main()
