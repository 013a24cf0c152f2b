"""The ``monostixels`` command: ``demo``, ``eval``, ``run``, ``batch`` and ``calibrate``, configured through Hydra.

Usage::

    monostixels demo                                   # built-in synthetic scene, pictures under outputs/demo
    monostixels eval data=synthetic data.frames=20 flow=gt semantic=gt motion=gt out=o.json
    monostixels run data=frames data.root=my_frames    # stixels of a user's own images
    monostixels run data=video data.path=clip.mp4 data.hfov_deg=90   # a dashcam video
    monostixels run data=video data.path=clip.mp4 data.hfov_deg=90 output.rerun=true  # + a 3D recording
    monostixels run data=video data.path=0 data.hfov_deg=90 data.realtime=true   # camera 0, frames dropped while solving
    monostixels run data=kitti_raw data.root=drives preset=accurate   # the best inputs instead of preset=fast
    monostixels eval data=kitti_raw data.root=drives preset=fast      # measures exactly what `run` does
    monostixels batch batch.inputs='clips/*.mp4' batch.output=fleet data.hfov_deg=90  # many clips on Ray
    monostixels calibrate calibrate.images='camera_cal/*.jpg' calibrate.board=[9,6] calibrate.out=cam.yaml
    monostixels run data=video data.path=clip.mp4 data.intrinsics=cam.yaml   # undistorted with it
    monostixels eval --multirun prior.beta_mc=4,8,16   # any Hydra flag works after the sub-command
"""
from __future__ import annotations

import logging
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from omegaconf import DictConfig


__all__ = ["main", "COMMANDS"]

logger = logging.getLogger("monostixels")

COMMANDS = {
    "demo": "run the full pipeline on the built-in synthetic scene and write pictures under outputs/demo",
    "eval": "evaluate on a data source (data=...), print the paper's table, write out=FILE.json",
    "run": "stixels, pictures, depth, point clouds (and a video) for a data source, under outputs/run",
    "batch": "many clips (batch.inputs=DIR_OR_GLOB) in parallel on Ray into batch.output/stixels.parquet",
    "calibrate": "intrinsics and lens distortion from chessboard views (calibrate.images=GLOB) into calibrate.out",
}

#: The preset (conf/preset/) each command starts from unless ``preset=...`` is given: ``fast`` keeps up
#: with a camera (work carried from frame to frame), ``accurate`` is the best the package has. A preset
#: chooses the flow, semantic, motion, solver and stream options; a group given on the command line
#: (``flow=dis``) overrides its choice. ``eval`` has none (the oracle inputs of conf/config.yaml):
#: ``monostixels eval preset=fast ...`` measures exactly what ``run`` does by default.
_COMMAND_PRESETS = {"demo": "accurate", "run": "fast", "batch": "fast"}
#: Per-command defaults that are no preset's business: the demo's scene is one of our renders, read by
#: the net of our renders (the presets' net is the real-image one); batch reads video clips, so that
#: data.hfov_deg & co. can be given for every clip.
_COMMAND_EXTRAS = {"demo": ("semantic=fcn8s_synthetic",), "batch": ("data=video",)}
_COMMAND_DEFAULTS = {cmd: (f"preset={name}", *_COMMAND_EXTRAS.get(cmd, ())) for cmd, name in _COMMAND_PRESETS.items()}
#: Shipped model of a default semantic option (installed with the package, editable or not), and
#: what a command falls back to where the file is missing (a checkout without its models): ground
#: truth on the synthetic scene, no semantics on a user's frames.
_DEFAULT_MODELS = {"fcn8s_synthetic": "models/fcn8s_synthetic.onnx", "fcn8s": "models/fcn8s_real.onnx",
                   "fcn8s_int8": "models/fcn8s_real_int8.onnx"}
_MODEL_FALLBACK = {"demo": "semantic=gt", "run": "semantic=none", "batch": "semantic=none", "eval": "semantic=none"}


def preset_choice(preset: str, group: str) -> str | None:
    """The option of config group ``group`` that preset ``preset`` chooses (conf/preset/PRESET.yaml),
    None where it chooses none or there is no such preset (Hydra then names the unknown option)."""
    from omegaconf import OmegaConf

    import monostixels.conf

    path = Path(monostixels.conf.__file__).parent / "preset" / f"{preset}.yaml"
    if not path.is_file():
        return None
    for entry in OmegaConf.to_container(OmegaConf.load(path)).get("defaults", []):
        if isinstance(entry, dict):
            for key, value in entry.items():
                if key.replace("override", "").strip().lstrip("/") == group:
                    return str(value)
    return None


def command_overrides(cmd: str, args: list[str]) -> list[str]:
    """The overrides a command composes: its defaults (:data:`_COMMAND_DEFAULTS`) that ``args`` do not
    give, then ``args``. A default semantic net whose model file is missing falls back to
    :data:`_MODEL_FALLBACK` (with a warning) unless ``args`` name the semantic option."""
    given = {a.split("=", 1)[0].lstrip("+~") for a in args if "=" in a}
    defaults = [d for d in _COMMAND_DEFAULTS.get(cmd, ()) if d.split("=")[0] not in given]
    if "semantic" not in given and cmd in _MODEL_FALLBACK:
        chosen = [d.split("=", 1)[1] for d in defaults if d.startswith("semantic=")]
        preset = next((a.split("=", 1)[1] for a in [*args, *defaults] if a.startswith("preset=")), None)
        semantic = chosen[0] if chosen else (preset_choice(preset, "semantic") if preset else None)
        if semantic in _DEFAULT_MODELS and not _model_available(_DEFAULT_MODELS[semantic]):
            logger.warning("%s: %s not found; using %s", cmd, _DEFAULT_MODELS[semantic], _MODEL_FALLBACK[cmd])
            defaults = [d for d in defaults if not d.startswith("semantic=")] + [_MODEL_FALLBACK[cmd]]
    return defaults + list(args)


def _usage() -> str:
    lines = ["usage: monostixels COMMAND [key=value ...] [hydra flags]", "", "commands:"]
    width = max(len(k) for k in COMMANDS)
    lines += [f"  {k:<{width}} {v}" for k, v in COMMANDS.items()]
    lines += ["", "Config groups: preset camera prior solver data flow semantic motion stream eval output batch "
              "calibrate (see conf/).",
              "Show the composed config: monostixels eval --cfg job"]
    return "\n".join(lines)


def _model_available(path: str) -> bool:
    from monostixels.inputs.semantic import resolve_model_path

    try:
        resolve_model_path(path)
        return True
    except Exception:  # noqa: BLE001 — any failure means "not shipped here"
        return False


def main() -> None:
    """Entry point of the console script: pick the sub-command, hand the rest to Hydra."""
    argv = sys.argv[1:]
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(_usage())
        sys.exit(0 if argv else 2)
    cmd, rest = argv[0], argv[1:]
    if cmd not in COMMANDS:
        print(f"monostixels: unknown command {cmd!r}\n\n{_usage()}", file=sys.stderr)
        sys.exit(2)
    rest = command_overrides(cmd, rest)
    # Hydra flags (--cfg job, --multirun) first, then every key=value override: Hydra's argparse
    # cannot take overrides on both sides of a flag.
    overrides = [a for a in rest if "=" in a and not a.startswith("-")]
    flags = [a for a in rest if a not in overrides]
    sys.argv = [f"monostixels {cmd}", *flags, *overrides, f"command={cmd}"]
    from monostixels.config_schema import refuse_bad_overrides

    refuse_bad_overrides(cmd, flags, overrides)
    _hydra_main()


def _run_command(cfg: DictConfig) -> Any:
    from monostixels._checks import one_line_errors
    from monostixels._threads import set_threads

    logging.getLogger("monostixels").setLevel(str(cfg.log_level))

    # A user's bad input: one clear line, no traceback.
    @one_line_errors(f"monostixels {cfg.command}")
    def dispatch(cfg: DictConfig) -> Any:
        # One thread budget for torch, OpenCV and ONNX Runtime before any of them starts its pool.
        set_threads(cfg.get("threads", "auto"))
        if cfg.command in ("demo", "eval"):
            from monostixels.eval.command import demo, evaluate_command

            return demo(cfg) if cfg.command == "demo" else evaluate_command(cfg)
        if cfg.command == "batch":
            from monostixels.batch import run_batch

            return run_batch(cfg)
        if cfg.command == "calibrate":
            return _calibrate(cfg)
        return _run(cfg)

    with _logs_above_progress_bars():
        return dispatch(cfg)


@contextmanager
def _logs_above_progress_bars() -> Iterator[None]:
    """The root logger's console lines (Hydra's handler) written through ``tqdm.write``: a line clears the
    progress bars, is printed to the handler's stream, and the bars are drawn again below it, so that no log
    line breaks a bar. Other handlers (Hydra's log file) are left as they are; a root logger without a console
    handler is left alone."""
    from tqdm.contrib.logging import logging_redirect_tqdm

    console = any(isinstance(h, logging.StreamHandler) and h.stream in (sys.stdout, sys.stderr)
                  for h in logging.root.handlers)
    if not console:
        yield
        return
    with logging_redirect_tqdm([logging.root]):
        yield


def _hydra_main() -> None:
    import hydra

    import monostixels.config_schema  # noqa: F401 - registers the groups' schemas before Hydra composes

    @hydra.main(version_base="1.3", config_path="pkg://monostixels.conf", config_name="config")
    def _entry(cfg: DictConfig) -> Any:
        return _run_command(cfg)

    _entry()


# ------------------------------------------------------------------------------------------------
def _calibrate(cfg: DictConfig) -> float:
    """`calibrate`: chessboard views -> an intrinsics file with distortion; returns the RMS error (px)."""
    from monostixels._checks import config_params
    from monostixels.data.calibration import (CalibrateConfig, calibrate_images, calibration_lines,
                                              write_intrinsics_file)

    c = config_params(CalibrateConfig, cfg.calibrate, "calibrate")
    cal = calibrate_images(c.images, board=c.board, size=c.size)
    path = write_intrinsics_file(cal, c.out)
    for line in calibration_lines(cal, path):
        print(line)
    return cal.rms_px


def _run(cfg: DictConfig) -> None:
    """`run`: every pair of the source through the sequence layer into run's writers (output/writers.py)."""
    from tqdm import tqdm

    from monostixels._checks import InputError
    from monostixels.build import Purpose, build, build_source
    from monostixels.data.base import LiveSource
    from monostixels.data.sources import data_params
    from monostixels.output.writers import write_sequence

    src = build_source(cfg)
    live = isinstance(src, LiveSource)  # a camera, a URL or data.realtime: frames as they come, no length
    if not live and len(src) == 0:
        raise InputError(f"data source {cfg.data.name!r} (root {getattr(data_params(cfg.data), 'root', None)}) "
                         f"has no frame pairs")
    # The product build (monostixels.build): keyframes, tracks and TTC on sequences, no SfM baseline.
    built = build(cfg, Purpose.RUN, source=src, out=Path(cfg.outputs) / "run")
    with tqdm(total=None if live else len(src), desc="run", unit="frame") as bar:
        frames = write_sequence(built.runner.run(src, progress=bar), built.writers.all)
    for line in built.writers.report(frames):
        print(line)


if __name__ == "__main__":
    main()
