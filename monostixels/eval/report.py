"""Paper-style result tables from the evaluation report (docs/conventions.md, section 4.5, paper
Table II).

The report dict is what ``monostixels eval ... out=FILE.json`` writes::

    {"dataset": str, "frames": int,
     "methods": {"monostixels": {"overall": M, "static": M, "moving": M, "compactness": float,
                                 "seconds_per_frame": float},
                 "sfm": {"overall": M, "static": M, "moving": M, "compactness": float}},
     # optional: "flow", "motion", "stixel_motion", "temporal", "semantic", "bottoms"}

Rows: compactness, then overall / static / moving x (Rel. error %, RMSE m, the four threshold
accuracies %); columns: the SfM baseline, then Mono-Stixels (then any other method).
"""
from __future__ import annotations

import math
from typing import Any

__all__ = ["METHOD_LABELS", "format_table", "markdown_table"]

#: Column headers of the known methods, in the paper's order.
METHOD_LABELS: dict[str, str] = {"sfm": "SfM baseline", "monostixels": "Mono-Stixels"}
_SPLITS = ("overall", "static", "moving")
#: (key in M, row label, scale to the printed unit, decimals)
_METRIC_ROWS: tuple[tuple[str, str, float, int], ...] = (
    ("rel", "Rel. error [%]", 100.0, 2),
    ("rmse", "RMSE [m]", 1.0, 2),
    ("d1.1", "d<1.1 [%]", 100.0, 2),
    ("d1.25", "d<1.25 [%]", 100.0, 2),
    ("d1.25^2", "d<1.25^2 [%]", 100.0, 2),
    ("d1.25^3", "d<1.25^3 [%]", 100.0, 2),
    ("n", "pixels evaluated", 1.0, 0),
)
_MISSING = "-"


def _num(x: Any, scale: float = 1.0, decimals: int = 2) -> str:
    """A number scaled and rounded, or '-' when absent / NaN."""
    if x is None or not isinstance(x, (int, float)) or (isinstance(x, float) and not math.isfinite(x)):
        return _MISSING
    if decimals == 0:
        return f"{int(round(x * scale)):d}"
    return f"{x * scale:.{decimals}f}"


def _kilo(x: Any) -> str:
    """Compactness in thousands as in the paper ('5.69 k')."""
    if x is None or not isinstance(x, (int, float)) or not math.isfinite(x):
        return _MISSING
    return f"{x / 1000.0:.2f} k"


def _methods(report: dict) -> list[str]:
    methods = report.get("methods", {}) or {}
    known = [m for m in METHOD_LABELS if m in methods]
    return known + sorted(m for m in methods if m not in METHOD_LABELS)


def _main_rows(report: dict) -> tuple[list[str], list[tuple[str, str, str, list[str]]]]:
    """Header and ``(group, split label, metric, cells)`` rows of the main table."""
    methods = _methods(report)
    data = report.get("methods", {}) or {}
    header = [METHOD_LABELS.get(m, m) for m in methods]
    rows: list[tuple[str, str, str, list[str]]] = [
        ("compactness", "", "Compactness", [_kilo(data[m].get("compactness")) for m in methods])
    ]
    for split in _SPLITS:
        for i, (key, label, scale, dec) in enumerate(_METRIC_ROWS):
            cells = [_num((data[m].get(split) or {}).get(key), scale, dec) for m in methods]
            rows.append((split, split.capitalize() if i == 0 else "", label, cells))
    rows.append(("time", "", "Seconds per frame", [_num(data[m].get("seconds_per_frame"), 1.0, 3) for m in methods]))
    return header, rows


def _extra_sections(report: dict) -> list[tuple[str, list[str], list[list[str]]]]:
    """Optional sections as ``(title, header, rows)``."""
    out: list[tuple[str, list[str], list[list[str]]]] = []
    flow = report.get("flow")
    if flow:
        rows = [[name, _num(v.get("epe"), 1.0, 3), _num(v.get("fl_all"), 100.0, 2)] for name, v in flow.items()]
        out.append(("Optical flow", ["backend", "EPE [px]", "Fl-all [%]"], rows))
    motion = report.get("motion")
    if motion:
        rows = [
            ["rotation error [deg] (median)", _num(motion.get("rot_err_deg"), 1.0, 3)],
            ["translation direction error [deg] (median)", _num(motion.get("trans_dir_err_deg"), 1.0, 3)],
            ["horizontal (x, z) direction error [deg] (median)", _num(motion.get("trans_dir_err_xz_deg"), 1.0, 3)],
            ["scale error abs(norm(t) / norm(t_gt) - 1) [%] (median)", _num(motion.get("scale_rel_err"), 100.0, 2)],
            ["scale error [%] (largest over pairs)", _num(motion.get("scale_rel_err_max"), 100.0, 2)],
        ]
        if motion.get("reference"):
            rows.append(["against", str(motion["reference"])])
        out.append(("Camera motion", ["metric", "value"], rows))
    sm = report.get("stixel_motion")
    if sm:
        rows = [[f"image pixels in stixels moving > {_num(sm.get('speed_mps'), 1.0, 1)} m/s [%]",
                 _num(sm.get("moving_share"), 100.0, 2)]]
        if "static_moving_share" in sm:
            rows.append(["of ground-truth static pixels [%]", _num(sm.get("static_moving_share"), 100.0, 2)])
        if "moving_recall_mask" in sm:
            rows.append([f"of ground-truth movers faster than {_num(sm.get('speed_mps'), 1.0, 1)} m/s [%]",
                         _num(sm.get("moving_recall"), 100.0, 2)])
            rows.append(["of all ground-truth moving pixels [%]", _num(sm.get("moving_recall_mask"), 100.0, 2)])
        elif "moving_recall" in sm:
            rows.append(["of ground-truth moving pixels [%]", _num(sm.get("moving_recall"), 100.0, 2)])
        out.append(("Stixel motion", ["metric", "value"], rows))
    tmp = report.get("temporal")
    if tmp:
        rows = [["tracking", "on" if tmp.get("tracking") else "off"],
                ["velocity error, moving pixels [m/s]", _num(tmp.get("velocity_err_mps"), 1.0, 3)],
                ["speed of static object pixels [m/s]", _num(tmp.get("static_speed_mps"), 1.0, 3)],
                ["TTC relative error, closing < 10 s", _num(tmp.get("ttc_rel_err"), 1.0, 3)],
                ["depth jitter frame to frame", _num(tmp.get("depth_jitter"), 1.0, 4)]]
        out.append(("Temporal", ["metric", "value"], rows))
    sem = report.get("semantic")
    if sem:
        rows = [["mIoU", _num(sem.get("miou"), 100.0, 2)]]
        rows += [[f"IoU {name}", _num(v, 100.0, 2)] for name, v in (sem.get("per_class_iou") or {}).items()]
        out.append(("Semantic segmentation [%]", ["metric", "value"], rows))
    bot = report.get("bottoms")
    if bot:
        rows = [
            ["mean abs. error [px]", _num(bot.get("mae_px"), 1.0, 2)],
            ["within 5 px [%]", _num(bot.get("within_5px"), 100.0, 2)],
            ["within 10 px [%]", _num(bot.get("within_10px"), 100.0, 2)],
            ["labelled columns", _num(bot.get("n"), 1.0, 0)],
        ]
        if "missing" in bot:
            rows.append(["columns without object stixel", _num(bot.get("missing"), 1.0, 0)])
        out.append(("Stixel bottoms", ["metric", "value"], rows))
    return out


def _title(report: dict) -> str:
    return f"Dataset: {report.get('dataset', '?')}, frames: {report.get('frames', '?')}"


def format_table(report: dict) -> str:
    """The report as plain-text tables (paper Table II layout, then the optional sections).

    Args:
        report: the evaluation report dict (module docstring; docs/conventions.md, section 4.5).

    Returns:
        Multi-line text for a terminal.
    """
    header, rows = _main_rows(report)
    w0 = max(len(s) for _, s, _, _ in rows)
    w1 = max(len(m) for _, _, m, _ in rows)
    wc = [max([len(h)] + [len(r[3][j]) for r in rows]) for j, h in enumerate(header)]
    lines = [_title(report)]
    line = f"{'':<{w0}}  {'Metric':<{w1}}" + "".join(f"  {h:>{w}}" for h, w in zip(header, wc))
    rule = "-" * len(line)
    lines += [line]
    group = None
    for g, split, metric, cells in rows:
        if g != group:
            lines.append(rule)
            group = g
        lines.append(f"{split:<{w0}}  {metric:<{w1}}" + "".join(f"  {c:>{w}}" for c, w in zip(cells, wc)))
    for title, hdr, srows in _extra_sections(report):
        widths = [max([len(hdr[j])] + [len(r[j]) for r in srows]) for j in range(len(hdr))]
        lines += ["", title]
        first = "  ".join(f"{h:<{widths[0]}}" if j == 0 else f"{h:>{widths[j]}}" for j, h in enumerate(hdr))
        lines += [first, "-" * len(first)]
        for r in srows:
            lines.append("  ".join(f"{c:<{widths[0]}}" if j == 0 else f"{c:>{widths[j]}}" for j, c in enumerate(r)))
    return "\n".join(lines)


def markdown_table(report: dict) -> str:
    """The report as Markdown tables (for docs), same content as :func:`format_table`."""
    header, rows = _main_rows(report)
    lines = [f"**{_title(report)}**", ""]
    lines.append("| Split | Metric | " + " | ".join(header) + " |")
    lines.append("|---|---|" + "---:|" * len(header))
    for _, split, metric, cells in rows:
        lines.append(f"| {split} | {metric} | " + " | ".join(cells) + " |")
    for title, hdr, srows in _extra_sections(report):
        lines += ["", f"**{title}**", ""]
        lines.append("| " + " | ".join(hdr) + " |")
        lines.append("|---|" + "---:|" * (len(hdr) - 1))
        for r in srows:
            lines.append("| " + " | ".join(r) + " |")
    return "\n".join(lines)
