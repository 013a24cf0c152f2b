"""`monostixels eval`: run the pipeline over a data source and score it (docs/conventions.md,
section 4.5)."""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from tqdm import tqdm

from monostixels.build import Purpose, build_runner
from monostixels.core.classes import DYNAMIC_OBJECT, STATIC_OBJECT
from monostixels.data.base import FramePair, SequenceSource, SequentialSource, source_info
from monostixels.eval.metrics import (
    DepthAccumulator,
    SemanticAccumulator,
    bottoms_metrics,
    dense_compactness,
    motion_errors,
    stixel_compactness,
)
from monostixels.inputs.flow import flow_metrics
from monostixels.eval.temporal import TemporalAccumulator
from monostixels.core.stixels import StixelWorld

__all__ = ["evaluate", "predicted_bottoms", "moving_stixel_mask", "frame_interval", "write_report", "SPLITS", "MOTION_KEYS"]

logger = logging.getLogger(__name__)

#: Pixel sets of the depth metrics: all ground truth, and split by the moving-object mask.
SPLITS = ("overall", "static", "moving")
#: Per-pair camera-motion errors (:func:`monostixels.eval.metrics.motion_errors`) summarised by their median.
MOTION_KEYS = ("rot_err_deg", "trans_dir_err_deg", "trans_dir_err_xz_deg", "scale_rel_err")


def frame_interval(pair: FramePair, default: float) -> float:
    """Seconds between the two frames of ``pair``: ``info.dt``, else the difference of
    ``info.timestamp`` and ``info.timestamp_prev`` (numbers in microseconds as DDAD writes
    them, or ISO-8601), else ``default``."""
    info = pair.info
    if info.dt:
        return float(info.dt)
    a, b = info.timestamp, info.timestamp_prev
    if a is not None and b is not None:
        try:
            d = (float(a) - float(b)) * 1e-6
        except (TypeError, ValueError):
            from datetime import datetime

            try:
                iso = [datetime.fromisoformat(str(x).replace("Z", "+00:00")) for x in (a, b)]
                d = (iso[0] - iso[1]).total_seconds()
            except ValueError:
                d = 0.0
        if d > 0:
            return d
    return default


def moving_stixel_mask(stixels: StixelWorld, dt: float, speed_mps: float) -> torch.Tensor:
    """Pixels (H, W) bool in stixels whose estimated world motion is faster than ``speed_mps``.

    Args:
        stixels: the result of one frame: its world ``velocity`` (N, 3) m/s where the sequence layer
            set it (filtered by the tracks), else ``motion`` (N, 3) metres between the two frames.
        dt: seconds between the two frames.
        speed_mps: speed threshold (m/s).
    """
    velocity = getattr(stixels, "velocity", None)
    if velocity is not None:
        speed = velocity.double().norm(dim=1)
    else:
        speed = stixels.motion.double().norm(dim=1) / dt
    fast = torch.cat([speed > speed_mps, torch.zeros(1, dtype=torch.bool)])  # index -1 = no stixel
    return fast[stixels.index_map()]


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


def evaluate(cfg: DictConfig, source: SequenceSource, *, dataset: str, progress: bool = True,
             on_result: Any = None) -> dict:
    """Run the pipeline on every pair of ``source`` and build the report (docs/conventions.md, 4.5).

    Args:
        cfg: composed config (flow, semantic, motion, prior, solver, eval groups), or its settings parsed once
            (:func:`monostixels.build.parse_settings`); the runner is the evaluation's build (monostixels.build).
        source: frame pairs (a data source).
        dataset: the report's ``dataset`` name.
        progress: show a progress bar over frames.
        on_result: optional callback ``f(PipelineResult)`` (e.g. to save pictures).

    Returns:
        the report dict (metrics as fractions, rmse in metres). A frame whose camera motion
        cannot be estimated is scored with no estimate (every ground-truth pixel clamped as
        invalid) and listed under ``failed_frames``. Frames the source could not read are skipped (their
        pairs are not scored) and counted under ``skipped_frames``.
    """
    runner = build_runner(cfg, Purpose.EVAL)
    ev = runner.pipeline.eval_cfg
    lo, hi = ev.min_depth, ev.max_depth
    # An input that is the ground truth itself (flow=gt, ...) is not scored against it.
    pipe = runner.pipeline
    flow_name, motion_name, semantic_name = pipe.flow_cfg.name, pipe.motion_cfg.name, pipe.semantic_cfg.name
    temporal = TemporalAccumulator(lo, hi)
    sequential = isinstance(source, SequentialSource) and len(source) > 0 and source.sequence_key(0) is not None
    last_frame: tuple[Any, str, torch.Tensor | None] | None = None  # sequence, name, pose of the last frame
    acc = {m: {s: DepthAccumulator(min_depth=lo, max_depth=hi) for s in SPLITS} for m in ("monostixels", "sfm")}
    n_stixels: list[int] = []
    n_pixels: list[int] = []
    seconds: list[float] = []
    flow_stats: list[dict[str, float]] = []
    motion_stats: list[dict[str, float]] = []
    gt_motion_source = None
    degenerate = 0
    sem_acc = SemanticAccumulator()
    sem_used = False
    bottoms_pred: list[float] = []
    bottoms_gt: list[float] = []
    has_depth = False
    has_moving_gt = False
    # stixel_motion: pixels in moving stixels / all pixels, and among ground-truth static (moving) pixels.
    mv_counts = {"all": [0, 0], "static": [0, 0], "moving": [0, 0], "moving_mask": [0, 0]}
    speed_mps, default_dt = ev.moving_speed_mps, ev.frame_interval_s
    failed: list[str] = []
    frames = 0
    try:
        total = len(source)  # type: ignore[arg-type]
    except TypeError:
        total = None
    bar = tqdm(total=total, desc=f"eval {dataset}", disable=not progress, unit="frame")
    for step in runner.run(source, progress=bar):
        frames += 1
        pair, res = step.pair, step.result
        gt = pair.gt
        if res is None:
            # Not dropped: the frame counts, with no estimate (clamped like any invalid depth).
            logger.warning("%s; scored with invalid estimates", step.error)
            failed.append(pair.name)
        n_stixels.append(len(res.stixels) if res is not None else 0)
        n_pixels.append(pair.size[0] * pair.size[1])
        if gt.depth is not None:
            has_depth = True
            nothing = torch.full(pair.size, float("nan"))
            pred = ({"monostixels": res.stixels.depth_map(), "sfm": res.sfm_depth} if res is not None
                    else {"monostixels": nothing, "sfm": nothing})
            # Without a moving-object mask (KITTI raw) only "overall" is scored: a static split
            # would claim knowledge the data does not have.
            splits = zip(SPLITS, (None, ~gt.moving, gt.moving)) if gt.moving is not None else [("overall", None)]
            has_moving_gt |= gt.moving is not None
            for s, mask in splits:
                for m in acc:
                    acc[m][s].add(pred[m], gt.depth, mask)
        if res is None:
            last_frame = None
            continue
        st = res.stixels
        if sequential:
            seq = pair.info.sequence
            gt_motion = None
            if last_frame is not None and last_frame[0] == seq:
                cands = source.previous_frames(step.index, 1)
                if cands and cands[0].name == last_frame[1]:
                    gt_motion = cands[0].motion
            temporal.add(st, res.pose, gt, pair.info, gt_motion,
                         last_frame[2] if last_frame is not None and last_frame[0] == seq else None)
            last_frame = (seq, pair.name, res.pose)
        dt = frame_interval(pair, default_dt)
        fast = moving_stixel_mask(st, dt, speed_mps)
        mv_counts["all"][0] += int(fast.sum())
        mv_counts["all"][1] += fast.numel()
        if gt.moving is not None:
            # Pixels the ground truth knows: with depth ground truth those with a measurement.
            known = gt.depth > 0 if gt.depth is not None else torch.ones_like(gt.moving)
            parts = [("static", known & ~gt.moving), ("moving_mask", known & gt.moving)]
            if gt.velocity is not None:
                # The recall of movers faster than the threshold the estimate is held to: a mover at
                # 0.5 m/s is in the moving mask, yet a perfect estimate does not call it fast.
                fast_gt = torch.nan_to_num(gt.velocity.double(), nan=0.0).norm(dim=0) > speed_mps
                parts.append(("moving", known & gt.moving & fast_gt))
            else:
                parts.append(("moving", known & gt.moving))
            for k, sel in parts:
                mv_counts[k][0] += int((fast & sel).sum())
                mv_counts[k][1] += int(sel.sum())
        seconds.append(res.total_seconds)
        if gt.flow is not None and flow_name != "gt":
            flow_stats.append(flow_metrics(res.flow.flow, gt.flow, gt.flow_valid))
        if pair.motion is not None and motion_name != "gt":
            if res.motion.degenerate:
                degenerate += 1
            else:
                motion_stats.append(motion_errors(res.motion.motion, pair.motion))
                if pair.info.motion_source is not None:
                    gt_motion_source = pair.info.motion_source
        if res.semantic is not None and semantic_name != "gt" and gt.labels is not None:
            sem_used = True
            sem_acc.add(res.semantic.argmax(0), gt.labels)
        if gt.bottoms is not None and len(gt.bottoms):
            bottoms_pred += predicted_bottoms(st, gt.bottoms[:, 0]).tolist()
            bottoms_gt += gt.bottoms[:, 1].tolist()
        if on_result is not None:
            on_result(res)
    bar.close()
    if frames == 0:
        raise ValueError(f"eval: the data source {dataset!r} yielded no frame pairs")

    report: dict[str, Any] = {"dataset": dataset, "frames": frames, "methods": {}}
    scored = (SPLITS if has_moving_gt else ("overall",)) if has_depth else ()
    mono = {s: acc["monostixels"][s].result() for s in scored}
    sfm = {s: acc["sfm"][s].result() for s in scored}
    report["methods"]["monostixels"] = {**mono, "compactness": stixel_compactness(n_stixels),
                                        "seconds_per_frame": float(np.mean(seconds)) if seconds else float("nan")}
    report["methods"]["sfm"] = {**sfm, "compactness": dense_compactness(n_pixels)}
    if failed:
        report["failed_frames"] = failed
    skipped = source_info(source).skipped_frames
    if skipped:
        # Unreadable frames the source skipped (monostixels.data._lazy_source.LazySource): counted, never silent.
        report["skipped_frames"] = len(skipped)
    if flow_stats:
        report["flow"] = {flow_name: {k: float(np.mean([f[k] for f in flow_stats])) for k in ("epe", "fl_all")}}
    if motion_stats or degenerate:
        report["motion"] = {k: float(np.median([m[k] for m in motion_stats])) if motion_stats else float("nan")
                            for k in MOTION_KEYS}
        report["motion"]["scale_rel_err_max"] = (float(np.max([m["scale_rel_err"] for m in motion_stats]))
                                                 if motion_stats else float("nan"))
        report["motion"]["pairs"] = len(motion_stats)
        report["motion"]["reference"] = str(gt_motion_source or "ground truth")
        if degenerate:
            report["motion"]["degenerate_frames"] = degenerate
    if mv_counts["all"][1]:
        sm: dict[str, Any] = {"moving_share": mv_counts["all"][0] / mv_counts["all"][1], "speed_mps": speed_mps}
        if mv_counts["static"][1]:
            sm["static_moving_share"] = mv_counts["static"][0] / mv_counts["static"][1]
        if mv_counts["moving"][1]:
            sm["moving_recall"] = mv_counts["moving"][0] / mv_counts["moving"][1]
        if mv_counts["moving_mask"][1] and mv_counts["moving_mask"] != mv_counts["moving"]:
            sm["moving_recall_mask"] = mv_counts["moving_mask"][0] / mv_counts["moving_mask"][1]
        report["stixel_motion"] = sm
    if sequential and temporal.frames:
        report["temporal"] = {**temporal.result(), "tracking": bool(runner.track_params.enabled),
                              "keyframes_min_distance_m": runner.keyframes.min_distance_m}
    if sem_used:
        report["semantic"] = sem_acc.result()
    if bottoms_gt:
        b = bottoms_metrics(bottoms_pred, bottoms_gt)
        report["bottoms"] = {k: b[k] for k in ("mae_px", "within_5px", "within_10px", "n")}
    return report
