"""What a command runs, built from the composed config in one place: the source, the runner (a
:class:`~monostixels.sequence.SequenceRunner` with its :class:`~monostixels.pipeline.Pipeline`) and ``run``'s
writers.

The config is parsed once here (:func:`parse_settings`: every group into its schema's dataclass,
monostixels.config_schema) and the typed settings are handed down, so that ``run``, ``eval``, ``demo``,
``batch`` and the benchmarks build the pipeline the same way. Nothing below this module takes the config
itself: :class:`~monostixels.pipeline.Pipeline`, :class:`~monostixels.sequence.SequenceRunner`,
:func:`~monostixels.data.sources.make_source` and :func:`~monostixels.output.writers.run_writers` take the
settings (:func:`pipeline_settings`, :func:`sequence_settings`, :func:`build_source`, :func:`build_writers`
read them from a config). What differs between the commands is the purpose:

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

import dataclasses
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

from monostixels._checks import InputError, config_params, is_unset
from monostixels.core.energy import PriorConfig
from monostixels.core.solver import SolverConfig
from monostixels.data.base import KeyframeParams, Source
from monostixels.data.sources import SOURCE_NAMES, CameraConfig, data_params, make_source
from monostixels.inputs.flow_config import flow_params
from monostixels.inputs.motion_track import motion_params
from monostixels.inputs.semantic import semantic_params
from monostixels.output.viewer import OutputConfig
from monostixels.output.writers import RunWriters, run_writers
from monostixels.pipeline import EvalConfig, Pipeline, PipelineSettings
from monostixels.post.movers import MoverCheckParams
from monostixels.sequence.runner import SequenceRunner, SequenceSettings
from monostixels.sequence.stream import StreamParams
from monostixels.sequence.tracking import TrackParams
from monostixels.sequence.ttc import TtcParams

__all__ = ["Purpose", "Settings", "Built", "pipeline_settings", "sequence_settings", "parse_settings", "build_source",
           "build_pipeline", "build_runner", "build_writers", "build"]


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


def pipeline_settings(cfg: Any) -> PipelineSettings:
    """What a :class:`~monostixels.pipeline.Pipeline` reads of the composed config ``cfg`` (a DictConfig, or a
    plain dict of one), each group parsed into its schema's dataclass (a bad value: an InputError naming it)."""
    semantic = semantic_params(cfg["semantic"])
    prior = config_params(PriorConfig, cfg.get("prior"), "prior")
    # A semantic mode may carry prior values of its own: without semantics (semantic=none) the
    # 2-DOF dynamic type needs a cost (alpha_dyn) or it explains every column; see conf/semantic/none.yaml.
    overrides = getattr(semantic, "prior_overrides", None)
    if overrides:
        prior = config_params(PriorConfig, {**dataclasses.asdict(prior), **overrides}, "semantic.prior_overrides")
    return PipelineSettings(
        flow=flow_params(cfg["flow"]), semantic=semantic, motion=motion_params(cfg["motion"]),
        eval=config_params(EvalConfig, cfg.get("eval"), "eval"), prior=prior,
        solver=config_params(SolverConfig, cfg.get("solver"), "solver"),
        movers=config_params(MoverCheckParams, cfg.get("movers"), "movers"), threads=cfg.get("threads", "auto"))


def sequence_settings(cfg: Any) -> SequenceSettings:
    """What a :class:`~monostixels.sequence.SequenceRunner` reads of the composed config ``cfg``: the pipeline's
    settings and the groups ``keyframes``, ``temporal``, ``ttc`` and ``stream``."""
    return SequenceSettings(
        pipeline=pipeline_settings(cfg),
        keyframes=config_params(KeyframeParams, cfg.get("keyframes"), "keyframes"),
        temporal=config_params(TrackParams, cfg.get("temporal"), "temporal"),
        ttc=config_params(TtcParams, cfg.get("ttc"), "ttc"),
        stream=config_params(StreamParams, cfg.get("stream"), "stream"))


def parse_settings(cfg: Any) -> Settings:
    """Every group the builders read of the composed config ``cfg``, parsed once (``cfg`` may be settings already)."""
    if isinstance(cfg, Settings):
        return cfg
    return Settings(sequence_settings(cfg), config_params(OutputConfig, cfg.get("output"), "output"))


def build_source(cfg: Any, camera: Any = None) -> Source:
    """The data source of a config (:func:`~monostixels.data.sources.make_source`).

    Args:
        cfg: the whole composed config (its ``data`` and ``camera`` groups, and ``keyframes.window``: the
            frames a live source keeps), or the ``data`` group alone (a config node or a plain dict).
        camera: the ``camera`` group where ``cfg`` is the ``data`` group; None: the schema's defaults.

    Raises:
        InputError: an unknown ``data.name``, a bad setting (naming it), or a source that cannot be opened.
    """
    data = cfg
    whole = hasattr(cfg, "keys") and "data" in cfg and "name" not in cfg
    if whole:
        data = cfg["data"]
        camera = camera if camera is not None else cfg.get("camera")
    name = (data or {}).get("name") if hasattr(data, "keys") or data is None else getattr(data, "name", None)
    if name not in SOURCE_NAMES:
        raise InputError(f"data.name: unknown data source {name!r}; choose one of {', '.join(SOURCE_NAMES)}")
    # Before the schema's own refusal of the key: say what the setting is for.
    if name != "video" and hasattr(data, "keys") and not is_unset(data, "realtime"):
        raise InputError(f"data.realtime: only data=video reads frames as they come (a camera, a URL, a video file "
                         f"at its frame rate); data={name} is read from disk frame by frame")
    params = data_params(data)
    cam = config_params(CameraConfig, camera, "camera")
    if name == "video" and whole:
        # A live source keeps as many frames as keyframe pairs may reach back (10 without a keyframes group).
        return make_source(params, cam, window=config_params(KeyframeParams, cfg.get("keyframes"), "keyframes").window)
    return make_source(params, cam)


def build_writers(cfg: Any, src: Source, out: Path, settings: Settings | None = None) -> RunWriters:
    """``run``'s writers (:func:`~monostixels.output.writers.run_writers`) of source ``src`` into ``out``, from the
    composed config ``cfg`` (groups ``data``, ``camera``, ``eval``, ``output``; ``settings``: parsed already)."""
    settings = parse_settings(cfg if settings is None else settings)
    return run_writers(src, out, data=data_params(cfg["data"]),
                       camera=config_params(CameraConfig, cfg.get("camera"), "camera"),
                       ev=settings.sequence.pipeline.eval, output=settings.output)


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
    writers = None if out is None else build_writers(cfg, src, out, settings)
    return Built(settings, src, runner, writers)
