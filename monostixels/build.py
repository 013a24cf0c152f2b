"""What a command runs, built from the composed config in one place: the source, the runner (a
:class:`~monostixels.sequence.SequenceRunner` with its :class:`~monostixels.pipeline.Pipeline`) and ``run``'s
writers.

The config is parsed once here (:func:`parse_settings`: every group into its schema's dataclass,
monostixels.config_schema) and the typed settings are handed down, so that ``run``, ``eval``, ``demo``,
``batch`` and the benchmarks build the pipeline the same way. What differs between them is the purpose:

==========  =====================================================  ==========================================
purpose     pipeline                                               callers
==========  =====================================================  ==========================================
``RUN``     a failed motion flagged, not raised; no SfM baseline;  ``run``, ``batch``, the benchmarks that time
            the camera height the road implies reported beside a   or score what ``run`` does (pipeline_speed,
            given motion (``flags["camera_height_fit_m"]``)        soak, dashcam, clips)
``EVAL``    a failed motion raised (the evaluation scores it as    ``eval``, ``demo``, motion_kitti
            failed); the SfM baseline beside the stixels
==========  =====================================================  ==========================================

The height check is decided here, once, for every product build: it only runs with a metric motion given
from elsewhere (``motion=gt`` / ``file``), costs one ground fit per such pair, and is read by ``run``'s
summary; batch's rows do not carry it.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

from monostixels._checks import config_params
from monostixels.data.sources import make_source
from monostixels.output.viewer import OutputConfig
from monostixels.output.writers import RunWriters, run_writers
from monostixels.pipeline import Pipeline
from monostixels.sequence.runner import SequenceRunner, SequenceSettings

__all__ = ["Purpose", "Settings", "Built", "parse_settings", "build_source", "build_pipeline", "build_runner", "build"]


class Purpose(Enum):
    """What a build is for (module docstring)."""

    RUN = "run"
    EVAL = "eval"


@dataclass(frozen=True)
class Settings:
    """The composed config parsed once: the sequence layer's settings (``sequence.pipeline``: the pipeline's,
    ``sequence.pipeline.eval``: the ``eval`` group) and ``output``."""

    sequence: SequenceSettings
    output: OutputConfig


def parse_settings(cfg: Any) -> Settings:
    """Every group the builders read of the composed config ``cfg``, parsed once (``cfg`` may be settings already)."""
    if isinstance(cfg, Settings):
        return cfg
    return Settings(SequenceSettings.from_config(cfg), config_params(OutputConfig, cfg.get("output"), "output"))


def build_source(cfg: Any) -> Any:
    """The data source of the composed config (groups ``data`` and ``camera``; :func:`make_source`)."""
    return make_source(cfg)


def build_pipeline(settings: Settings | Any, purpose: Purpose, *, overlap: bool = True,
                   sfm: bool | None = None) -> Pipeline:
    """The per-pair pipeline for ``purpose`` (module docstring). ``sfm``: the SfM baseline, where a caller
    scores it against its own ground truth (None: the purpose's choice)."""
    settings = parse_settings(settings)
    run = purpose is Purpose.RUN
    return Pipeline(settings.sequence.pipeline, allow_motion_failure=run, sfm=not run if sfm is None else sfm,
                    overlap=overlap, report_height=run)


def build_runner(settings: Settings | Any, purpose: Purpose, *, overlap: bool = True,
                 sfm: bool | None = None) -> SequenceRunner:
    """The sequence runner (keyframes, tracks, TTC, the stream state) around :func:`build_pipeline`'s pipeline."""
    settings = parse_settings(settings)
    return SequenceRunner(settings.sequence, build_pipeline(settings, purpose, overlap=overlap, sfm=sfm))


@dataclass
class Built:
    """What :func:`build` made: the source, the runner and (given an output folder) ``run``'s writers."""

    settings: Settings
    source: Any
    runner: SequenceRunner
    writers: RunWriters | None = None

    @property
    def pipeline(self) -> Pipeline:
        return self.runner.pipeline


def build(cfg: Any, purpose: Purpose, *, source: Any = None, out: Path | None = None, overlap: bool = True,
          sfm: bool | None = None) -> Built:
    """The source of ``cfg`` (or ``source``), its runner for ``purpose`` and, where ``out`` is given, ``run``'s
    writers into it, from the composed config ``cfg`` parsed once.

    Raises:
        InputError: a bad setting (naming it), a source that cannot be opened, ``output.rerun=true`` without
            rerun-sdk.
    """
    src = build_source(cfg) if source is None else source
    settings = parse_settings(cfg)
    runner = build_runner(settings, purpose, overlap=overlap, sfm=sfm)
    writers = None if out is None else run_writers(cfg, src, out, ev=settings.sequence.pipeline.eval, output=settings.output)
    return Built(settings, src, runner, writers)
