"""Leave-one-source-out checks of a distilled semantic net (train/semantic.py ``data.soft``).

For a student ``.pt`` (a training checkpoint such as ``<run_dir>/best.pt``, or an export) and the
holdout it was trained without, it measures:

- ``teacher``: on the held-out entries of the teacher cache (``python -m train.teacher_labels``),
  the mIoU and pixel agreement of the student's most likely class against the teacher's (our 10
  classes; classes absent from both are not counted), per held-out source; the student runs as the
  ``fcn8s`` backend does (the window resized to the focal length ``--focal-px``), the comparison
  is at the cache's resolution (half the teacher's input), without the rows where training gives the
  teacher no say (``data.soft.void_below``: the dashcam's bottom quarter, where the teacher calls the
  lane a vehicle);
- ``kitti``: stixel bottoms on the labelled frames of KITTI drive 0028
  (``benchmarks.semantic_real``: ``flow=deepflow motion=mono``), unseen when the holdout names
  ``kitti_0028``;
- ``camvid_val`` / ``camvid_test``: CamVid mIoU (``eval data=camvid``); val is never trained on
  (``data.soft.weights.camvid_val: 0``), test is when ``camvid_test`` has a weight;
- ``lidar``: mono-stixels ``rel`` / ``d1.25`` on the LiDAR drive 0023.

Command (repository root; a few minutes per task on the shared 2-core machine)::

    OMP_NUM_THREADS=1 nice -n 19 python -m benchmarks.distill_loso --weights runs/semantic/loso_k28_dash2/best.pt \\
        --holdout '[{source: kitti_0028}, {source: dashcam, frames: [110, 221]}]' --tasks teacher kitti camvid_val \\
        --json runs/eval/loso_k28_dash2.json
"""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from omegaconf import OmegaConf
from tqdm import tqdm

from monostixels.eval.metrics import SemanticAccumulator

__all__ = ["teacher_agreement", "measure", "main"]

logger = logging.getLogger(__name__)

SHARED = Path("../shared")
TASKS = ("teacher", "kitti", "camvid_val", "camvid_test", "lidar")


@torch.no_grad()
def teacher_agreement(weights: str | Path, entries: list, *, focal_px: float,
                      void_below: dict[str, float] | None = None) -> dict[str, dict[str, Any]]:
    """Student vs teacher on cached entries, per source.

    Args:
        weights: the student ``.pt`` (``load_fcn8s``).
        entries: ``SoftEntry`` items (``train.teacher_labels.read_manifest``).
        focal_px: focal length the windows are resized to (the backend's ``semantic.focal_px``).
        void_below: per source, the fraction of the frame height from which the teacher's labels are
            not compared (training's ``data.soft.void_below``: rows where the teacher is known wrong).

    Returns:
        ``{source: {"miou", "agreement", "per_class_iou", "entries"}}``.
    """
    import cv2

    from monostixels.inputs.semantic import TorchSegmenter
    from train.semantic import void_rows
    from train.teacher_labels import load_entry

    seg = TorchSegmenter(weights)
    acc: dict[str, SemanticAccumulator] = {}
    agree: dict[str, list[float]] = {}
    for e in tqdm(entries, desc="teacher agreement", mininterval=10):
        bgr = cv2.imread(e.image, cv2.IMREAD_COLOR)
        x0, y0, x1, y1 = e.box
        rgb = torch.from_numpy(cv2.cvtColor(bgr[y0:y1, x0:x1], cv2.COLOR_BGR2RGB)).permute(2, 0, 1).float() / 255.0
        probs = seg(rgb, scale=focal_px / e.fx)  # (10, h, w) at the window's size
        teacher = load_entry(e.probs)
        student = F.interpolate(probs[None], size=teacher.shape[-2:], mode="area")[0]
        s, t = student.argmax(0), teacher.argmax(0)
        if e.source in (void_below or {}):
            keep = ~void_rows(e.box, bgr.shape[0], t.shape[0], void_below[e.source])
            s, t = s[keep], t[keep]
        acc.setdefault(e.source, SemanticAccumulator()).add(s, t)
        agree.setdefault(e.source, []).append(float((s == t).float().mean()))
    out = {}
    for src, a in acc.items():
        r = a.result(classes=None)
        out[src] = {"miou": r["miou"], "agreement": sum(agree[src]) / len(agree[src]),
                    "per_class_iou": r["per_class_iou"], "entries": len(agree[src])}
    return out


def _semantic_overrides(weights: str | Path) -> list[str]:
    # The training checkpoint through the torch runtime of the fcn8s backend (same preprocessing).
    return ["semantic=fcn8s", "semantic.runtime=torch", f"semantic.weights={Path(weights).resolve()}"]


def measure(task: str, weights: str | Path, *, holdout: list, manifest: str | Path, focal_px: float,
            views: list[str] | None = None, void_below: dict[str, float] | None = None) -> dict[str, Any]:
    """One task of the table for one student; see the module docstring."""
    if task == "teacher":
        from train.semantic import held_out
        from train.teacher_labels import read_manifest

        entries = [e for e in read_manifest(manifest) if held_out(e.source, e.frame, holdout)
                   and (views is None or e.view.split("_")[0] in views)]
        return {"teacher": teacher_agreement(weights, entries, focal_px=focal_px, void_below=void_below)}
    if task in ("camvid_val", "camvid_test"):
        from monostixels.data.camvid import CamVidSource
        from monostixels.eval.semantic import evaluate_semantics
        from monostixels.pipeline import load_config

        cfg = load_config(["data=camvid", f"data.root={SHARED}/data/camvid", *_semantic_overrides(weights)])
        rep = evaluate_semantics(cfg, CamVidSource(cfg.data.root, split=task.split("_")[1]))
        return {f"{task}_miou": rep["semantic"]["miou"], f"{task}_per_class_iou": rep["semantic"]["per_class_iou"]}
    if task in ("kitti", "lidar"):
        from benchmarks.semantic_real import measure as real_measure

        # "real" = semantic=fcn8s; the overrides after it point the backend at this student.
        return real_measure("real", task, extra=_semantic_overrides(weights)[1:])
    raise ValueError(f"unknown task {task!r}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--weights", type=Path, required=True, help="student .pt (checkpoint or export)")
    ap.add_argument("--holdout", default="[]", help="the run's data.soft.holdout (YAML list)")
    ap.add_argument("--manifest", default="runs/teacher/espnetv2/manifest.jsonl")
    ap.add_argument("--focal-px", type=float, default=480.0)
    ap.add_argument("--views", nargs="*", default=["full"], help="cache views to compare on (full, zoom2)")
    ap.add_argument("--tasks", nargs="+", default=["teacher", "kitti", "camvid_val"], choices=TASKS)
    ap.add_argument("--void-below", nargs="*", default=None, metavar="SOURCE=FRACTION",
                    help="rows of a source not compared with the teacher (default: data.soft.void_below of "
                    "conf/train_semantic_soft.yaml)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    holdout = OmegaConf.to_container(OmegaConf.create({"h": OmegaConf.create(args.holdout)}))["h"]
    if args.void_below is None:
        soft = OmegaConf.load(Path(__file__).resolve().parents[1] / "conf" / "train_semantic_soft.yaml").data.soft
        void_below = {str(k): float(v) for k, v in (soft.get("void_below") or {}).items()}
    else:
        void_below = {k: float(v) for k, v in (item.split("=", 1) for item in args.void_below)}
    row: dict[str, Any] = {"weights": str(args.weights), "holdout": holdout, "void_below": void_below}
    for task in args.tasks:
        res = measure(task, args.weights, holdout=holdout, manifest=args.manifest, focal_px=args.focal_px,
                      views=args.views or None, void_below=void_below)
        row.update(res)
        print(task, json.dumps(res, default=str)[:600], flush=True)
        if args.json:
            # After every task: a later task that fails keeps the earlier numbers.
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(row, indent=1, default=str))
    t = row.get("teacher", {})
    cells = [f"{src} {v['miou']:.3f} / {v['agreement']:.3f}" for src, v in t.items()]
    print(f"\n| student | holdout | mIoU / agreement vs teacher (held out) | KITTI 0028 bottoms 10 px | CamVid val | "
          f"CamVid test | LiDAR rel / d1.25 |\n|---|---|---|---:|---:|---:|---:|\n"
          f"| {args.weights} | {args.holdout} | {'; '.join(cells) or '–'} | {row.get('within_10px', '–')} | "
          f"{row.get('camvid_val_miou', '–')} | {row.get('camvid_test_miou', '–')} | "
          f"{row.get('lidar_rel', '–')} / {row.get('lidar_d125', '–')} |")


if __name__ == "__main__":
    main()
