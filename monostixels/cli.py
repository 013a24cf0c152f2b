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

import json
import logging
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch
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
    _refuse_bad_settings(cmd, flags, overrides)
    _hydra_main()


def _refuse_bad_settings(cmd: str, flags: list[str], overrides: list[str]) -> None:
    """An override of a group with a schema (monostixels.config_schema) that Hydra refuses (an unknown
    key, a value of the wrong type): one line naming the option and exit 1, as for any bad input (Hydra
    itself would print its composition error over several lines). Sweeps (their overrides are ranges)
    are left to Hydra."""
    if {"--multirun", "-m"} & set(flags):
        return
    from monostixels.config_schema import SCHEMAS, check_overrides

    groups = {g for g, _, _ in SCHEMAS}
    if not any(o.lstrip("+~").split("=", 1)[0].split(".", 1)[0] in groups for o in overrides):
        return  # the packaged options compose (tests/test_config_schema.py): only a user's value can fail
    error = check_overrides([*overrides, f"command={cmd}"])
    if error is not None:
        print(f"monostixels {cmd}: error: {error}", file=sys.stderr)
        sys.exit(1)


def _run_command(cfg: DictConfig) -> Any:
    from monostixels._checks import one_line_errors
    from monostixels._threads import set_threads

    logging.getLogger("monostixels").setLevel(str(cfg.log_level))

    # A user's bad input: one clear line, no traceback.
    @one_line_errors(f"monostixels {cfg.command}")
    def dispatch(cfg: DictConfig) -> Any:
        # One thread budget for torch, OpenCV and ONNX Runtime before any of them starts its pool.
        set_threads(cfg.get("threads", "auto"))
        if cfg.command == "demo":
            return _demo(cfg)
        if cfg.command == "eval":
            return _eval(cfg)
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
def _source(cfg: DictConfig):
    from monostixels.data.sources import make_source

    return make_source(cfg)


def _semantic_label(cfg: DictConfig) -> str:
    """``name (model file)`` of the semantic config, or its name where it has no model."""
    from omegaconf import OmegaConf

    model = OmegaConf.select(cfg, "semantic.model", throw_on_missing=False)
    return f"{cfg.semantic.name} ({model})" if model else str(cfg.semantic.name)


def _demo(cfg: DictConfig) -> float:
    from monostixels._checks import InputError, config_params
    from monostixels.data.sources import SyntheticDataConfig, data_params
    from monostixels.data.synthetic import SyntheticSource
    from monostixels.eval.metrics import depth_metrics
    from monostixels.pipeline import EvalConfig, Pipeline
    from monostixels.output.bev import bev_image
    from monostixels.output.viz import (depth_colormap, flow_colormap, image_to_uint8, paper_figure, semantic_colormap,
                                 stixel_depth_overlay, stixel_overlay)

    out = Path(cfg.outputs) / "demo"
    data = data_params(cfg.data)
    if not isinstance(data, SyntheticDataConfig):
        raise InputError(f"demo: renders one of the built-in synthetic scenes (data=synthetic), not data={data.name}; "
                         f"use monostixels run or eval for data={data.name}")
    pair = SyntheticSource(1, seed=data.seed, scale=data.scale, density=data.density)[0]
    logger.info("demo: synthetic scene %s (%dx%d), flow=%s semantic=%s motion=%s", pair.name, pair.size[1],
                pair.size[0], cfg.flow.name,
                # fcn8s and fcn8s_synthetic share the backend name: say which model runs.
                _semantic_label(cfg),
                cfg.motion.name)
    res = Pipeline(cfg).run(pair)
    ev = config_params(EvalConfig, cfg.eval, "eval")
    lo, hi = ev.colormap_min_depth, ev.colormap_max_depth
    img = pair.image
    rgb = image_to_uint8(img)
    st = res.stixels
    depth = st.depth_map()
    pics = {
        "input.png": rgb,
        "input_previous.png": image_to_uint8(pair.image_prev),
        "flow.png": flow_colormap(res.flow.flow),
        "stixels_overlay.png": stixel_overlay(img, st, mode="type"),
        "stixels_semantic.png": stixel_overlay(img, st, mode="class", alpha=0.7),
        "stixels_depth.png": stixel_depth_overlay(img, st, min_depth=lo, max_depth=hi),
        "bev.png": bev_image(st, min_depth=lo, max_depth=hi),
        "depth_stixels.png": depth_colormap(depth, min_depth=lo, max_depth=hi),
        "depth_sfm.png": depth_colormap(res.sfm_depth, min_depth=lo, max_depth=hi),
    }
    if res.semantic is not None:
        pics["semantics.png"] = semantic_colormap(res.semantic.argmax(0))
    if pair.gt.depth is not None:
        pics["depth_ground_truth.png"] = depth_colormap(pair.gt.depth, min_depth=lo, max_depth=hi)
    from monostixels.output.io import write_image

    for name, pic in pics.items():
        write_image(out / name, pic)
    panels = [("Image", rgb), ("Ground Truth", pics.get("depth_ground_truth.png", rgb)),
              ("Baseline - SFM", pics["depth_sfm.png"]), ("Ours - Mono-Stixels", pics["depth_stixels.png"]),
              ("Input flow", pics["flow.png"]), ("Input semantic", pics.get("semantics.png", rgb)),
              ("Mono-stixel types", pics["stixels_overlay.png"]), ("Mono-stixel semantic", pics["stixels_semantic.png"])]
    paper_figure(panels, out / "figure.png", ncols=4)
    st.save_json(out / "stixels.json")
    st.save_npz(out / "stixels.npz")
    print(f"demo: {len(st)} stixels in {st.num_columns} columns (compactness {st.compactness}), "
          f"pipeline {res.total_seconds:.2f} s (solver {res.seconds['solver'] * 1000:.0f} ms)")
    if pair.gt.depth is not None:
        for name, d in (("mono-stixels", depth), ("SfM baseline", res.sfm_depth)):
            m = depth_metrics(d, pair.gt.depth, None, min_depth=ev.min_depth, max_depth=ev.max_depth)
            mv = depth_metrics(d, pair.gt.depth, pair.gt.moving, min_depth=ev.min_depth,
                               max_depth=ev.max_depth) if pair.gt.moving is not None else None
            extra = f", moving rel {mv['rel']:.3f}" if mv is not None and mv["n"] else ""
            print(f"  {name:<13} rel {m['rel']:.3f}  d1.25 {m['d1.25']:.3f}{extra}")
    if st.flags.get("degenerate_motion"):
        print(f"  note: {st.flags.get('reason')}")
    print(f"wrote {len(pics) + 3} files under {out}/ (figure.png, stixels_overlay.png, stixels.json, ...)")
    return float(st.energy.sum())


def _eval(cfg: DictConfig) -> float:
    from monostixels.eval.evaluate import evaluate, write_report
    from monostixels.eval.report import format_table

    if str(cfg.data.name) == "camvid":
        return _eval_semantics(cfg)
    src = _source(cfg)
    if hasattr(src, "indices"):
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
        skipped = list(getattr(src, "skipped_frames", []))
        print(f"{len(skipped)} unreadable frame(s) skipped: {_listed(skipped)}")
    if cfg.out:
        path = write_report(report, cfg.out)
        print(f"wrote {path}")
    overall = report["methods"]["monostixels"].get("overall", {})
    # The return value is the objective of Hydra sweepers (lower is better).
    rel = overall.get("rel", float("nan"))
    return float(rel) if rel is not None else float("nan")


def _eval_semantics(cfg: DictConfig) -> float:
    """`eval data=camvid`: semantic metrics on labelled single images (no flow, motion, stixels)."""
    from monostixels.data.camvid import CamVidSource
    from monostixels.data.sources import data_params
    from monostixels.eval.evaluate import write_report
    from monostixels.eval.semantic import evaluate_semantics, format_semantic_table

    data = data_params(cfg.data)
    src = CamVidSource(data.root, split=data.split, frames=data.frames, step=data.step)
    report = evaluate_semantics(cfg, src)
    report["semantic_backend"] = _semantic_label(cfg)
    print(format_semantic_table(report))
    if cfg.out:
        print(f"wrote {write_report(report, cfg.out)}")
    # The objective of Hydra sweepers is minimised.
    return 1.0 - float(report["semantic"]["miou"])


def _calibrate(cfg: DictConfig) -> float:
    """`calibrate`: chessboard views -> an intrinsics file with distortion; returns the RMS error (px)."""
    from monostixels._checks import config_params
    from monostixels.data.calibration import CalibrateConfig, calibrate_images, write_intrinsics_file

    c = config_params(CalibrateConfig, cfg.calibrate, "calibrate")
    cal = calibrate_images(c.images, board=c.board, size=c.size)
    path = write_intrinsics_file(cal, c.out)
    H, W = cal.size
    k1, k2, p1, p2, k3 = cal.distortion
    print(f"calibrate: {cal.board[0]}x{cal.board[1]} board found in {len(cal.boards)} of {len(cal.images)} images "
          f"({W}x{H}); RMS reprojection error {cal.rms_px:.3f} px")
    if cal.no_board:
        print(f"  no board in: {', '.join(p.name for p in cal.no_board)}")
    if cal.other_size:
        print(f"  skipped (not {W}x{H}): {', '.join(p.name for p in cal.other_size)}")
    print(f"  fx {cal.fx:.2f}  fy {cal.fy:.2f}  cx {cal.cx:.2f}  cy {cal.cy:.2f} px; "
          f"distortion k1 {k1:.4f} k2 {k2:.4f} p1 {p1:.5f} p2 {p2:.5f} k3 {k3:.4f}")
    print(f"wrote {path} (use it: data.intrinsics={path})")
    return cal.rms_px


#: Frame rate of `run`'s overlay video when the source has none (image folders): slow enough to look at.
_OVERLAY_VIDEO_FPS = 5.0


def _video_fps(src: Any) -> float:
    """Overlay video frame rate: the rate of the used frames of a video source, else 5 fps."""
    fps, step = getattr(src, "fps", None), getattr(src, "step", 1)
    return float(fps) / max(int(step), 1) if fps else _OVERLAY_VIDEO_FPS


def _run(cfg: DictConfig) -> None:
    import cv2
    from tqdm import tqdm

    from monostixels._checks import InputError, config_params
    from monostixels._cpu import runtime_report
    from monostixels.output.bev import bev_image
    from monostixels.data._io import MAX_SKIPPED_FRAMES
    from monostixels.data.sources import camera_mount, data_params
    from monostixels.output.io import depth_to_points, write_depth_png16, write_image, write_ply
    from monostixels.pipeline import EvalConfig, Pipeline
    from monostixels.sequence import SequenceRunner
    from monostixels.output.viewer import open_recorder
    from monostixels.output.viz import depth_colormap, side_by_side, stixel_depth_overlay

    src = _source(cfg)
    live = hasattr(src, "indices")  # a camera, a URL or data.realtime: frames as they come, no length
    if not live and len(src) == 0:
        raise InputError(f"data source {cfg.data.name!r} (root {getattr(data_params(cfg.data), 'root', None)}) "
                         f"has no frame pairs")
    # The SfM baseline is for eval/demo only; with a given motion the camera height the road implies is reported.
    pipe = Pipeline(cfg, allow_motion_failure=True, sfm=False, report_height=True)
    runner = SequenceRunner(cfg, pipe)  # keyframes, tracks and TTC on sequences
    out = Path(cfg.outputs) / "run"
    ev = config_params(EvalConfig, cfg.eval, "eval")
    lo, hi = ev.colormap_min_depth, ev.colormap_max_depth
    videos: dict[str, Any] = {}
    written = 0
    camera: list[dict[str, Any]] = []  # each pair's flags: its camera-motion kind, scale source, height fit
    recorder = open_recorder(cfg, out, src)  # output.rerun=true: a 3D recording, else a no-op
    bar = tqdm(total=None if live else len(src), desc="run", unit="frame")
    for step in runner.run(src, progress=bar):
        pair, res = step.pair, step.result
        recorder.log_frame(written, pair, res)
        st = res.stixels
        d = out / (pair.name or f"frame_{written:06d}")
        depth = st.depth_map()
        overlay = stixel_depth_overlay(pair.image, st, min_depth=lo, max_depth=hi)
        bev = bev_image(st, min_depth=lo, max_depth=hi)
        dcol = depth_colormap(depth, min_depth=lo, max_depth=hi)
        write_image(d / "overlay.png", overlay)
        write_image(d / "bev.png", bev)
        write_image(d / "figure.png", side_by_side(overlay, bev))
        write_image(d / "depth.png", dcol)
        finite = torch.where(torch.isfinite(depth) & (depth > 0), depth, torch.zeros_like(depth))
        write_depth_png16(d / "depth16.png", finite)
        st.save_json(d / "stixels.json")
        st.save_npz(d / "stixels.npz")
        pts, cols = depth_to_points(finite, pair.camera.K, pair.image, max_depth=hi)
        write_ply(d / "points.ply", pts, cols)
        if str(cfg.data.name) == "video" or len(src) > 1:
            # video.mp4: the overlay above the depth map; bev.mp4: the bird's-eye view.
            for name, rgb in (("video.mp4", np.concatenate([overlay, dcol], axis=0)), ("bev.mp4", bev)):
                if name not in videos:
                    out.mkdir(parents=True, exist_ok=True)
                    videos[name] = cv2.VideoWriter(str(out / name), cv2.VideoWriter_fourcc(*"mp4v"), _video_fps(src),
                                                   (rgb.shape[1], rgb.shape[0]))
                    if not videos[name].isOpened():
                        raise InputError(f"run: OpenCV cannot write the video {out / name} (no mp4v encoder)")
                videos[name].write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        info = st.pair_info or {}
        speed = (info["driven_m"] / info["dt_s"] if info.get("driven_m") is not None and info.get("dt_s")
                 and st.flags.get("camera_motion") == "metric" else None)
        camera.append({**st.flags, "speed_mps": speed})
        written += 1
    bar.close()
    for v in videos.values():
        v.release()
    recording = recorder.close()
    skipped = list(getattr(src, "skipped_frames", []))
    if written == 0 and skipped:
        raise InputError(f"run: no frame pair could be made: {len(skipped)} unreadable frame(s) skipped "
                         f"({_listed(skipped)}); a pair needs two readable frames at most "
                         f"{MAX_SKIPPED_FRAMES + 1} frames apart")
    stream = None
    if live:
        # Which frames were processed (and how many dropped): docs/conventions.md, section 4.3
        # (data.realtime).
        stream = out / "stream.json"
        out.mkdir(parents=True, exist_ok=True)
        summary = src.summary()
        stream.write_text(json.dumps(summary, indent=2))
        if summary["realtime"]:
            print(f"run: {summary['frames_taken']} of {summary['frames_read']} frames taken, "
                  f"{summary['frames_dropped']} dropped while solving (realtime); {stream}")
    out.mkdir(parents=True, exist_ok=True)
    restarts = list(getattr(src, "restarts", []))
    # What the run made of its input; unreadable frames are listed, never dropped silently.
    cam = camera_report(camera, camera_mount(cfg.data, cfg.camera)[0])
    # platform: the CPU, ONNX Runtime's INT8 path and the solver's build (docs/conventions.md, section 4.3).
    run_summary = {"data": str(cfg.data.name), "frame_pairs": written, "skipped_frames": skipped,
                   "sequence_restarts": restarts, "camera": cam, "platform": runtime_report()}
    (out / "summary.json").write_text(json.dumps(run_summary, indent=2))
    for line in camera_summary(cam):
        print(f"run: {line}")
    print(f"run: {written} frame pair(s) -> {out}/<frame>/ overlay.png bev.png figure.png depth.png depth16.png "
          f"stixels.json stixels.npz points.ply" + (f"; videos {out / 'video.mp4'} {out / 'bev.mp4'}" if videos else "")
          + (f"; 3D recording {recording} (open it with: rerun {recording})" if recording else "")
          + (f"; processed frames {stream}" if stream else "")
          + (f"; {len(skipped)} unreadable frame(s) skipped: {_listed(skipped)}" if skipped else "")
          + f"; {out / 'summary.json'}")


#: A camera height the road implies that differs from the setting by more than this share is warned about.
HEIGHT_WARN_SHARE = 0.2


def camera_report(flags: list[dict[str, Any]], height: float) -> dict[str, Any]:
    """What a run's pairs say about its camera (``run/summary.json`` ``camera``): the pairs, those with a
    metric motion (``metric``, standing ones included) and without (``no_metric_motion``), where the metric
    scales came from (``scale_from``: counts), the height assumed (``height_m``) and, where a given motion
    let the road say, the median height it implies (``height_fit_m``, else None) over ``height_fits`` pairs; the
    camera speed of the moving metric pairs (``speed_mps``: ``median``, ``min``, ``max`` m/s and ``pairs``, else
    None) and the pairs whose scale was too uncertain to tell movers (``scale_uncertain``)."""
    from monostixels.inputs.motion import NO_METRIC_MOTION

    kinds = [f.get("camera_motion", "metric") for f in flags]
    metric = sum(k not in NO_METRIC_MOTION for k in kinds)
    sources: dict[str, int] = {}
    for f in flags:
        if f.get("scale_from"):
            sources[f["scale_from"]] = sources.get(f["scale_from"], 0) + 1
    fits = [float(f["camera_height_fit_m"]) for f in flags if f.get("camera_height_fit_m") is not None]
    speeds = [float(f["speed_mps"]) for f in flags if f.get("speed_mps") is not None]
    uncertain = sum(bool(f.get("scale_uncertain")) for f in flags)
    return {"pairs": len(flags), "metric": metric, "no_metric_motion": len(flags) - metric,
            "scale_from": dict(sorted(sources.items())), "height_m": height,
            "height_fit_m": float(np.median(fits)) if fits else None, "height_fits": len(fits),
            "speed_mps": ({"median": float(np.median(speeds)), "min": min(speeds), "max": max(speeds),
                           "pairs": len(speeds)} if speeds else None),
            "scale_uncertain": uncertain}


def camera_summary(report: dict[str, Any]) -> list[str]:
    """The run's summary lines of its camera (:func:`camera_report`): how many pairs had a metric motion and
    where the scale came from, and the camera height assumed beside the one the road implies.

    A height that differs from the implied one by more than :data:`HEIGHT_WARN_SHARE` is also logged as a
    warning: every depth and speed of a monocular run scales with it.
    """
    by = ", ".join(f"{v} {k}" for k, v in report["scale_from"].items())
    unknown = report["no_metric_motion"]
    lines = [f"camera motion metric on {report['metric']} of {report['pairs']} pair(s)" + (f" (scale: {by})" if by else "")
             + (f"; {unknown} without a metric motion (no movers, no collision warnings there)" if unknown else "")]
    sp, unsure = report.get("speed_mps"), report.get("scale_uncertain", 0)
    if sp is not None:
        lines.append(f"camera speed median {sp['median']:.1f} m/s, range {sp['min']:.1f}-{sp['max']:.1f} m/s over "
                     f"{sp['pairs']} moving pair(s)"
                     + (f"; {unsure} with an uncertain scale (no movers along the epipolar lines, no collision "
                        f"warnings there)" if unsure else ""))
    height, med = report["height_m"], report["height_fit_m"]
    line = f"camera height {height:.2f} m (camera.height; depths and speeds scale with it)"
    if med is not None:
        line += f"; the road implies {med:.2f} m (median of {report['height_fits']} pair(s))"
        if abs(med / height - 1.0) > HEIGHT_WARN_SHARE:
            logger.warning("camera.height %.2f m differs from the %.2f m the road implies by %.0f %%: set camera.height",
                           height, med, 100.0 * abs(med / height - 1.0))
    lines.append(line)
    return lines


def _listed(names: list[str], most: int = 20) -> str:
    """``a, b, c`` of the first ``most`` names, ``... (N more)`` for the rest: a line stays a line."""
    return ", ".join(names[:most]) + (f", ... ({len(names) - most} more)" if len(names) > most else "")



if __name__ == "__main__":
    main()
