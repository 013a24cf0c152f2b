"""A dashcam clip through the sequence layer, scored on what a driver would see go wrong.

No ground truth exists for a user's dashcam footage; these numbers need none:

- ``no_metric_share``: the share of pairs without a metric camera motion (``flags.camera_motion`` other than
  ``metric`` / ``standing``), and ``degenerate_consistent``: whether ``flags.degenerate_motion`` is true
  exactly for those pairs (no standing camera on a highway);
- ``ttc_warnings``: stixels warned as closing within ``ttc.warn_s`` in the camera's path, over all frames
  (nothing on a highway clip closes within 2 s: every one is false);
- ``false_mover_share``: per frame, the share of the image covered by stixels typed moving outside the
  vehicles and persons of a referee segmentation (``--referee``, a Cityscapes model; its masks dilated by
  15 px), the mean over frames; without ``--referee`` it is not measured; ``false_mover_rows``: the same
  share split by tenths of the image height, top to bottom (they sum to ``false_mover_share``: where
  the false movers lie, e.g. the near road at the bottom, whose flow fails at highway speed);
- ``speed_mps``: the camera speed ``|t| / dt`` of each pair with a metric motion whose scale is certain
  (``flags.scale_uncertain`` false; ``scale_uncertain`` counts the others), its ``speed_mean_mps``,
  coefficient of variation ``speed_cv``, ``speed_median_mps`` and ``speed_range_mps`` (a highway: 15-40 m/s,
  steady). The shared clip's dashes give a yardstick: 12 frames per 12.19 m dash period at 25 fps, about
  25 m/s.

Command (repository root; about 2 minutes for 40 pairs on 2 cores, the referee most of it)::

    python -m benchmarks.dashcam --json runs/eval/dashcam.json \\
        --referee ../shared/models/espnetv2_cityscapes_640x1024.onnx \\
        data.path=../shared/data/dashcam/highway_solid_white_right.mp4 data.hfov_deg=58 data.step=2 \\
        data.frames=40 camera.height=1.4

The words after the flags are ``monostixels run`` overrides (``data=video`` and ``preset=fast`` are set first).
"""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from tqdm import tqdm

from monostixels.core.classes import DYNAMIC_OBJECT
from monostixels.build import Purpose, build
from monostixels.inputs.motion import NO_METRIC_MOTION
from monostixels.pipeline import load_config

__all__ = ["false_movers", "pair_speed", "measure", "add_report_arguments", "write_report", "main"]

logger = logging.getLogger(__name__)

#: Our class ids of the referee's movers (vehicle, two_wheeler, person) and the dilation of their masks (px).
_MOVER_CLASSES = (6, 7, 8)
_DILATE_PX = 15
#: The Cityscapes trainId -> our classes mapping of ``semantic=cityscapes19`` (its 20th channel dropped).
_CITYSCAPES20 = "[0,1,3,3,3,4,4,4,5,2,9,8,8,6,6,6,6,7,7,-1]"


def _referee(model: str | None) -> Any:
    """The referee's class map of a pair's current image, (H, W) int64, or None without a model."""
    if model is None:
        return None
    from monostixels.inputs.semantic import estimate_semantics

    cfg = load_config(["semantic=cityscapes19", f"semantic.model={model}", f"semantic.mapping={_CITYSCAPES20}"]).semantic

    def classes(pair: Any) -> np.ndarray:
        return estimate_semantics(pair, cfg).argmax(0).numpy()

    return classes


def false_movers(moving: np.ndarray, referee: np.ndarray, kernel: np.ndarray) -> tuple[float, list[float]]:
    """Share of the image in moving stixels away from the referee's movers, in all and per tenth of the rows.

    Args:
        moving: (H, W) bool, pixels of stixels typed moving.
        referee: (H, W) the referee's class per pixel (our ids); vehicle, two-wheeler and person are movers.
        kernel: the structuring element their masks are dilated with.

    Returns:
        The share of all pixels, and the same count split into 10 bands of rows (top first), each
        divided by all pixels (so the bands sum to the share).
    """
    near = cv2.dilate(np.isin(referee, _MOVER_CLASSES).astype(np.uint8), kernel).astype(bool)
    false = moving & ~near
    rows_per_band = np.bincount(np.nonzero(false)[0] * 10 // false.shape[0], minlength=10)
    return float(false.mean()), (rows_per_band / false.size).tolist()


def pair_speed(result: Any) -> float | None:
    """The camera speed ``|t| / dt`` (m/s) of a pair's result where its motion is metric and its scale certain
    (``flags.scale_uncertain`` false), else None: the speed the run's summary counts."""
    st = result.stixels
    if st.flags.get("camera_motion", "metric") != "metric" or st.flags.get("scale_uncertain"):
        return None
    return float(result.motion.motion.translation_norm / st.pair_info["dt_s"])


def measure(overrides: list[str], referee: str | None = None) -> dict[str, Any]:
    """Run the clip of ``overrides`` and score it (module docstring); returns the JSON report."""
    cfg = load_config(["data=video", "preset=fast", *overrides])
    built = build(cfg, Purpose.RUN)  # as `monostixels run` builds it
    src, runner = built.source, built.runner
    classes = _referee(referee)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * _DILATE_PX + 1, 2 * _DILATE_PX + 1))
    rows: list[dict[str, Any]] = []
    for step in tqdm(runner.run(src), total=len(src), desc="dashcam", unit="pair"):
        st = step.result.stixels
        kind = st.flags.get("camera_motion", "metric")
        row: dict[str, Any] = {"pair": step.pair.name, "camera_motion": kind, "scale_from": st.flags.get("scale_from"),
                               "degenerate_motion": bool(st.flags.get("degenerate_motion", False)),
                               "ttc_warnings": int(st.ttc_warning.sum()) if st.ttc_warning is not None else 0,
                               "speed_mps": pair_speed(step.result)}
        if classes is not None:
            idx = st.index_map()
            moving = (idx >= 0) & (st.type[idx.clamp(min=0)] == DYNAMIC_OBJECT)
            row["false_mover_share"], row["false_mover_rows"] = false_movers(moving.numpy(), classes(step.pair), kernel)
        rows.append(row)
    n = len(rows)
    no_metric = [r for r in rows if r["camera_motion"] in NO_METRIC_MOTION]
    speeds = np.array([r["speed_mps"] for r in rows if r["speed_mps"] is not None])
    report: dict[str, Any] = {
        "pairs": n,
        "no_metric_share": len(no_metric) / max(n, 1),
        "degenerate_consistent": all(r["degenerate_motion"] == (r["camera_motion"] not in ("metric",)) for r in rows),
        "ttc_warnings": sum(r["ttc_warnings"] for r in rows),
        "speed_mean_mps": float(speeds.mean()) if len(speeds) else None,
        "speed_cv": float(speeds.std() / speeds.mean()) if len(speeds) > 1 else None,
        "speed_median_mps": float(np.median(speeds)) if len(speeds) else None,
        "speed_range_mps": [float(speeds.min()), float(speeds.max())] if len(speeds) else None,
        "scale_uncertain": sum(1 for r in rows if r["camera_motion"] == "metric" and r["speed_mps"] is None),
        "overrides": overrides,
        "per_pair": rows,
    }
    if classes is not None:
        report["false_mover_share"] = float(np.mean([r["false_mover_share"] for r in rows]))
        report["false_mover_rows"] = np.mean([r["false_mover_rows"] for r in rows], axis=0).tolist()
    return report


def add_report_arguments(ap: argparse.ArgumentParser) -> None:
    """The options every dashcam-style benchmark takes: ``--json``, ``--referee`` and the run overrides."""
    ap.add_argument("--json", type=Path, help="write the report here")
    ap.add_argument("--referee", help="a Cityscapes ONNX model whose vehicles and persons referee the movers")
    ap.add_argument("overrides", nargs="*", help="monostixels run overrides (key=value)")


def write_report(rep: dict[str, Any], path: Path | None) -> None:
    """Print the report without its pairs, and write all of it to ``path`` (JSON) where given."""
    print(json.dumps({k: v for k, v in rep.items() if k != "per_pair"}, indent=2))
    if path:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(rep, indent=2))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_report_arguments(ap)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    torch.set_grad_enabled(False)
    write_report(measure(args.overrides, args.referee), args.json)


if __name__ == "__main__":
    main()
