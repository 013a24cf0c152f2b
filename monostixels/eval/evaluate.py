"""`monostixels eval`: run the pipeline over a data source and score it (SPEC section 4 contract)."""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import torch
from omegaconf import DictConfig
from tqdm import tqdm

from monostixels.classes import DYNAMIC_OBJECT, STATIC_OBJECT
from monostixels.data.base import FramePair
from monostixels.eval.metrics import (
    DepthAccumulator,
    SemanticAccumulator,
    bottoms_metrics,
    dense_compactness,
    stixel_compactness,
)
from monostixels.inputs.flow import flow_metrics
from monostixels.inputs.motion import motion_errors
from monostixels.pipeline import MotionEstimationError, Pipeline, PipelineResult
from monostixels.stixels import StixelWorld

__all__ = ["evaluate", "predicted_bottoms", "write_report", "SPLITS"]

logger = logging.getLogger(__name__)

#: Pixel sets of the depth metrics: all ground truth, and split by the moving-object mask.
SPLITS = ("overall", "static", "moving")


def predicted_bottoms(stixels: StixelWorld, u: torch.Tensor) -> torch.Tensor:
    """Row (float, NaN where none) where the lowest object stixel of the column of each ``u`` ends.

    Args:
        stixels: the result of one frame.
        u: (N,) pixel columns of labelled stixel bottoms.
    """
    col = (u.long() // stixels.column_width).clamp(0, stixels.num_columns - 1)
    is_obj = (stixels.type == STATIC_OBJECT) | (stixels.type == DYNAMIC_OBJECT)
    out = torch.full((len(u),), float("nan"))
    for k, c in enumerate(col.tolist()):
        rows = stixels.v_bottom[(stixels.column == c) & is_obj]
        if len(rows):
            out[k] = float(rows.max())  # lowest in the image = largest row
    return out


def _nan_to_none(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _nan_to_none(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_nan_to_none(v) for v in x]
    return x


def write_report(report: dict, path: str | Path) -> Path:
    """Write the report as strict JSON (NaN, e.g. an empty split, becomes null)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(_nan_to_none(report), indent=2))
    return path


def evaluate(cfg: DictConfig, source: Iterable[FramePair], *, dataset: str, progress: bool = True,
             on_result: Any = None) -> dict:
    """Run the pipeline on every pair of ``source`` and build the SPEC section 4 report.

    Args:
        cfg: composed config (flow, semantic, motion, prior, solver, eval groups).
        source: frame pairs (a data source).
        dataset: the report's ``dataset`` name.
        progress: show a progress bar over frames.
        on_result: optional callback ``f(PipelineResult)`` (e.g. to save pictures).

    Returns:
        the report dict (metrics as fractions, rmse in metres). A frame whose camera motion
        cannot be estimated is scored with no estimate (every ground-truth pixel clamped as
        invalid) and listed under ``failed_frames``.
    """
    pipe = Pipeline(cfg)
    lo, hi = float(cfg.eval.min_depth), float(cfg.eval.max_depth)
    acc = {m: {s: DepthAccumulator(min_depth=lo, max_depth=hi) for s in SPLITS} for m in ("monostixels", "sfm")}
    n_stixels: list[int] = []
    n_pixels: list[int] = []
    seconds: list[float] = []
    flow_stats: list[dict[str, float]] = []
    motion_stats: list[dict[str, float]] = []
    degenerate = 0
    sem_acc = SemanticAccumulator()
    sem_used = False
    bottoms_pred: list[float] = []
    bottoms_gt: list[float] = []
    has_depth = False
    failed: list[str] = []
    frames = 0
    try:
        total = len(source)  # type: ignore[arg-type]
    except TypeError:
        total = None
    for pair in tqdm(source, total=total, desc=f"eval {dataset}", disable=not progress, unit="frame"):
        frames += 1
        gt = pair.gt
        try:
            res: PipelineResult | None = pipe.run(pair)
        except MotionEstimationError as err:
            # Not dropped: the frame counts, with no estimate (clamped like any invalid depth).
            logger.warning("%s; scored with invalid estimates", err)
            failed.append(pair.name)
            res = None
        n_stixels.append(len(res.stixels) if res is not None else 0)
        n_pixels.append(pair.size[0] * pair.size[1])
        if gt.depth is not None:
            has_depth = True
            moving = gt.moving if gt.moving is not None else torch.zeros(pair.size, dtype=torch.bool)
            nothing = torch.full(pair.size, float("nan"))
            pred = ({"monostixels": res.stixels.depth_map(), "sfm": res.sfm_depth} if res is not None
                    else {"monostixels": nothing, "sfm": nothing})
            for s, mask in zip(SPLITS, (None, ~moving, moving)):
                for m in acc:
                    acc[m][s].add(pred[m], gt.depth, mask)
        if res is None:
            continue
        st = res.stixels
        seconds.append(res.total_seconds)
        if gt.flow is not None and str(cfg.flow.name) != "gt":
            flow_stats.append(flow_metrics(res.flow.flow, gt.flow, gt.flow_valid))
        if pair.motion is not None and str(cfg.motion.name) != "gt":
            if res.motion.degenerate:
                degenerate += 1
            else:
                motion_stats.append(motion_errors(res.motion.motion, pair.motion))
        if res.semantic is not None and str(cfg.semantic.name) != "gt" and gt.labels is not None:
            sem_used = True
            sem_acc.add(res.semantic.argmax(0), gt.labels)
        if gt.bottoms is not None and len(gt.bottoms):
            bottoms_pred += predicted_bottoms(st, gt.bottoms[:, 0]).tolist()
            bottoms_gt += gt.bottoms[:, 1].tolist()
        if on_result is not None:
            on_result(res)
    if frames == 0:
        raise ValueError(f"eval: the data source {dataset!r} yielded no frame pairs")

    report: dict[str, Any] = {"dataset": dataset, "frames": frames, "methods": {}}
    mono = {s: acc["monostixels"][s].result() for s in SPLITS} if has_depth else {}
    sfm = {s: acc["sfm"][s].result() for s in SPLITS} if has_depth else {}
    report["methods"]["monostixels"] = {**mono, "compactness": stixel_compactness(n_stixels),
                                        "seconds_per_frame": float(np.mean(seconds))}
    report["methods"]["sfm"] = {**sfm, "compactness": dense_compactness(n_pixels)}
    if failed:
        report["failed_frames"] = failed
    if flow_stats:
        report["flow"] = {str(cfg.flow.name): {k: float(np.mean([f[k] for f in flow_stats])) for k in ("epe", "fl_all")}}
    if motion_stats or degenerate:
        report["motion"] = {k: float(np.median([m[k] for m in motion_stats])) if motion_stats else float("nan")
                            for k in ("rot_err_deg", "trans_dir_err_deg", "scale_rel_err")}
        if degenerate:
            report["motion"]["degenerate_frames"] = degenerate
    if sem_used:
        report["semantic"] = sem_acc.result()
    if bottoms_gt:
        b = bottoms_metrics(bottoms_pred, bottoms_gt)
        report["bottoms"] = {k: b[k] for k in ("mae_px", "within_5px", "within_10px", "n")}
    return report
