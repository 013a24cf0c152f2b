"""Semantic inputs on real frames: CamVid mIoU, KITTI stixel bottoms and LiDAR depth per backend.

For each semantic backend (``--backends``, each a list of overrides of the ``semantic`` group) it
runs the code behind ``monostixels eval``:

- ``camvid``: ``eval data=camvid data.split=test`` (our classes present in CamVid; every
  ``--camvid-step``-th image of the split),
- ``kitti``: ``eval data=kitti_raw`` on the labelled dev frames of the KITTI raw drive
  (``bottoms``: within 10 / 5 px, mean error) with ``flow=deepflow motion=mono``,
- ``lidar``: ``eval data=kitti_raw`` on the KITTI raw drive with LiDAR (mono-stixels and SfM
  ``rel`` / ``d1.25`` over LiDAR pixels),

and prints one markdown table (and ``--json FILE``). The named backends:

- ``none``: no semantic input,
- ``synthetic``: ``semantic=fcn8s_synthetic`` (our net of the renders),
- ``real``: ``semantic=fcn8s`` (our real-image net),
- ``cityscapes``: the shared Cityscapes ESPNetv2 (``semantic=cityscapes19`` with its 20th
  channel dropped; 384x1248 input for KITTI, 640x1024 for CamVid).

Command (repository root; ~25 min on the 2-core machine, the Cityscapes model is most of it)::

    OMP_NUM_THREADS=1 nice -n 10 python -m benchmarks.semantic_real --json runs/eval/semantic_real.json
"""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any

from monostixels.data.camvid import CamVidSource
from monostixels.build import build_source
from monostixels.eval.evaluate import evaluate
from monostixels.eval.semantic import evaluate_semantics
from monostixels.inputs.semantic import CITYSCAPES19_MAPPING
from monostixels.pipeline import load_config

__all__ = ["BACKENDS", "measure", "main"]

logger = logging.getLogger(__name__)

SHARED = Path("../shared")
_CS20 = "semantic.mapping=[" + ",".join(str(m) for m in (*CITYSCAPES19_MAPPING, -1)) + "]"
#: Overrides of each backend, per task (CamVid's 4:3 images suit the 640x1024 Cityscapes model).
BACKENDS: dict[str, dict[str, list[str]]] = {
    "none": {"any": ["semantic=none"]},
    "synthetic": {"any": ["semantic=fcn8s_synthetic"]},
    "real": {"any": ["semantic=fcn8s"]},
    "cityscapes": {
        "camvid": ["semantic=cityscapes19", f"semantic.model={SHARED}/models/espnetv2_cityscapes_640x1024.onnx", _CS20],
        "any": ["semantic=cityscapes19", f"semantic.model={SHARED}/models/espnetv2_cityscapes_384x1248.onnx", _CS20],
    },
}


def _overrides(backend: str, task: str) -> list[str]:
    b = BACKENDS[backend]
    return list(b.get(task, b["any"]))


def measure(backend: str, task: str, *, camvid_step: int = 1, extra: list[str] = ()) -> dict[str, Any]:
    """One backend on one task; returns the numbers of the table row."""
    if task == "camvid":
        if backend == "none":
            return {}
        cfg = load_config(["data=camvid", f"data.root={SHARED}/data/camvid", *_overrides(backend, task), *extra])
        rep = evaluate_semantics(cfg, CamVidSource(cfg.data.root, split="test", step=camvid_step))
        return {"camvid_miou": rep["semantic"]["miou"], "camvid_images": rep["frames"],
                "camvid_per_class_iou": rep["semantic"]["per_class_iou"]}
    common = ["flow=deepflow", "motion=mono", *_overrides(backend, task), *extra]
    if task == "kitti":
        cfg = load_config(["data=kitti_raw", f"data.root={SHARED}/data/kitti_raw", "data.only_labelled=true", *common])
        b = evaluate(cfg, build_source(cfg), dataset="kitti_raw")["bottoms"]
        return {"within_10px": b["within_10px"], "within_5px": b["within_5px"], "mae_px": b["mae_px"], "n": b["n"]}
    if task == "lidar":
        cfg = load_config(["data=kitti_raw", f"data.root={SHARED}/data/kitti_raw_lidar", *common])
        rep = evaluate(cfg, build_source(cfg), dataset="kitti_raw_lidar")
        mono, sfm = rep["methods"]["monostixels"]["overall"], rep["methods"]["sfm"]["overall"]
        return {"lidar_rel": mono["rel"], "lidar_d125": mono["d1.25"], "sfm_rel": sfm["rel"], "sfm_d125": sfm["d1.25"]}
    raise ValueError(f"unknown task {task!r}")


def _fmt(x: Any, digits: int = 3) -> str:
    return "–" if x is None else (f"{x:.{digits}f}" if isinstance(x, float) else str(x))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--backends", nargs="+", default=list(BACKENDS), choices=list(BACKENDS))
    ap.add_argument("--tasks", nargs="+", default=["camvid", "kitti", "lidar"], choices=["camvid", "kitti", "lidar"])
    ap.add_argument("--camvid-step", type=int, default=1, help="every n-th CamVid test image")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("extra", nargs="*", help="further overrides for every run (key=value)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    rows: dict[str, dict[str, Any]] = {}
    for backend in args.backends:
        rows[backend] = {}
        for task in args.tasks:
            rows[backend].update(measure(backend, task, camvid_step=args.camvid_step, extra=args.extra))
            print(backend, task, {k: v for k, v in rows[backend].items() if not isinstance(v, dict)}, flush=True)
    print("\n| semantic input | CamVid test mIoU | KITTI bottoms within 10 px | within 5 px | mean error px "
          "| LiDAR rel (mono-stixels / SfM) | LiDAR d1.25 (mono-stixels / SfM) |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for backend, r in rows.items():
        lidar_rel = f"{_fmt(r.get('lidar_rel'))} / {_fmt(r.get('sfm_rel'))}" if "lidar_rel" in r else "–"
        lidar_d = f"{_fmt(r.get('lidar_d125'))} / {_fmt(r.get('sfm_d125'))}" if "lidar_d125" in r else "–"
        print(f"| {backend} | {_fmt(r.get('camvid_miou'))} | {_fmt(r.get('within_10px'))} | {_fmt(r.get('within_5px'))} "
              f"| {_fmt(r.get('mae_px'), 1)} | {lidar_rel} | {lidar_d} |")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
