"""The commands that score the pipeline against ground truth: ``monostixels demo`` (one built-in synthetic pair)
and ``monostixels eval`` (a data source, docs/conventions.md, section 4.5); :mod:`monostixels.cli` dispatches to
them."""
from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import DictConfig

from monostixels.data.base import LiveSource, source_info
from monostixels.build import build_source
from monostixels.output.writers import DemoFiles, Frame, listed

__all__ = ["demo", "evaluate_command", "semantic_label"]

# The command line's logger, as when these were part of it: its records keep their name.
logger = logging.getLogger("monostixels")


def semantic_label(cfg: DictConfig) -> str:
    """``name (model file)`` of the semantic config, or its name where it has no model."""
    from omegaconf import OmegaConf

    model = OmegaConf.select(cfg, "semantic.model", throw_on_missing=False)
    return f"{cfg.semantic.name} ({model})" if model else str(cfg.semantic.name)


def demo(cfg: DictConfig) -> float:
    """`monostixels demo`: the pipeline and the SfM baseline on one built-in synthetic pair, their depth error
    printed and the pictures written under ``<outputs>/demo`` (docs/conventions.md, section 4.2); returns the
    stixels' total energy."""
    from monostixels._checks import InputError
    from monostixels.build import Purpose, build_pipeline, parse_settings
    from monostixels.data.sources import SyntheticDataConfig, data_params
    from monostixels.data.synthetic import SyntheticSource
    from monostixels.eval.metrics import depth_metrics

    out = Path(cfg.outputs) / "demo"
    data = data_params(cfg.data)
    if not isinstance(data, SyntheticDataConfig):
        raise InputError(f"demo: renders one of the built-in synthetic scenes (data=synthetic), not data={data.name}; "
                         f"use monostixels run or eval for data={data.name}")
    pair = SyntheticSource(1, seed=data.seed, scale=data.scale, density=data.density)[0]
    logger.info("demo: synthetic scene %s (%dx%d), flow=%s semantic=%s motion=%s", pair.name, pair.size[1],
                pair.size[0], cfg.flow.name,
                # fcn8s and fcn8s_synthetic share the backend name: say which model runs.
                semantic_label(cfg),
                cfg.motion.name)
    settings = parse_settings(cfg)
    res = build_pipeline(settings, Purpose.EVAL).run(pair)
    ev = settings.sequence.pipeline.eval
    files = DemoFiles(out, ev.colormap_min_depth, ev.colormap_max_depth)
    files.write(Frame(0, pair, res))
    files.close()
    st = res.stixels
    depth = st.depth_map()
    print(f"demo: {len(st)} stixels in {st.num_columns} columns (compactness {st.compactness}), "
          f"pipeline {res.total_seconds:.2f} s (solver {res.seconds['solver'] * 1000:.0f} ms)")
    if pair.gt.depth is not None:
        for name, d in (("mono-stixels", depth), ("SfM baseline", res.sfm_depth)):
            m = depth_metrics(d, pair.gt.depth, None, min_depth=ev.min_depth, max_depth=ev.max_depth)
            mv = depth_metrics(d, pair.gt.depth, pair.gt.moving, min_depth=ev.min_depth,
                               max_depth=ev.max_depth) if pair.gt.moving is not None else None
            extra = f", moving rel {mv['rel']:.3f}" if mv is not None and mv["n"] else ""
            print(f"  {name:<13} rel {m['rel']:.3f}  d1.25 {m['d1.25']:.3f}{extra}")
    if st.status.motion.degenerate:
        print(f"  note: {st.status.motion.reason}")
    print(f"wrote {len(files.names)} files under {out}/ (figure.png, stixels_overlay.png, stixels.json, ...)")
    return float(st.energy.sum())


def evaluate_command(cfg: DictConfig) -> float:
    """`monostixels eval`: the table of a data source printed, the report written to ``out``; returns the
    objective of Hydra's sweepers (lower is better): the depth's rel, 1 - mIoU for ``data=camvid``."""
    from monostixels.eval.evaluate import evaluate, write_report
    from monostixels.eval.report import format_table

    if str(cfg.data.name) == "camvid":
        return _evaluate_semantics(cfg)
    src = build_source(cfg)
    if isinstance(src, LiveSource):
        from monostixels._checks import InputError

        src.close()
        raise InputError("eval: a camera, a URL or data.realtime=true has no ground truth to score; "
                         "evaluate a recorded file (data.realtime=false) or use monostixels run")
    report = evaluate(cfg, src, dataset=str(cfg.data.name))
    print(format_table(report))
    if report.get("failed_frames"):
        print(f"camera motion could not be estimated on {len(report['failed_frames'])} frame(s), scored with no "
              f"estimate: {', '.join(report['failed_frames'])}")
    if report.get("skipped_frames"):
        skipped = source_info(src).skipped_frames
        print(f"{len(skipped)} unreadable frame(s) skipped: {listed(skipped)}")
    if cfg.out:
        path = write_report(report, cfg.out)
        print(f"wrote {path}")
    overall = report["methods"]["monostixels"].get("overall", {})
    # The return value is the objective of Hydra sweepers (lower is better).
    rel = overall.get("rel", float("nan"))
    return float(rel) if rel is not None else float("nan")


def _evaluate_semantics(cfg: DictConfig) -> float:
    """`eval data=camvid`: semantic metrics on labelled single images (no flow, motion, stixels)."""
    from monostixels.data.camvid import CamVidSource
    from monostixels.data.sources import data_params
    from monostixels.eval.evaluate import write_report
    from monostixels.eval.semantic import evaluate_semantics, format_semantic_table

    data = data_params(cfg.data)
    src = CamVidSource(data.root, split=data.split, frames=data.frames, step=data.step)
    report = evaluate_semantics(cfg, src)
    report["semantic_backend"] = semantic_label(cfg)
    print(format_semantic_table(report))
    if cfg.out:
        print(f"wrote {write_report(report, cfg.out)}")
    # The objective of Hydra sweepers is minimised.
    return 1.0 - float(report["semantic"]["miou"])
