"""The `monostixels` command end to end (subprocess: Hydra, packaged config, files written)."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from monostixels.core.stixels import StixelWorld

REPO = Path(__file__).resolve().parents[1]


def _cli(args: list[str], cwd: Path, check: bool = True) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "2")}
    p = subprocess.run([sys.executable, "-m", "monostixels.cli", *args], cwd=cwd, env=env,
                       capture_output=True, text=True, timeout=900)
    if check and p.returncode != 0:
        raise AssertionError(f"monostixels {' '.join(args)} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}")
    return p


def test_usage_and_unknown_command(tmp_path):
    p = _cli([], tmp_path, check=False)
    assert p.returncode == 2 and "demo" in p.stdout and "eval" in p.stdout
    p = _cli(["fly"], tmp_path, check=False)
    assert p.returncode == 2 and "unknown command 'fly'" in p.stderr


def test_demo_writes_pictures_and_stixels(tmp_path):
    """`monostixels demo` with its default inputs (the best the package has), at a small scale."""
    p = _cli(["demo", "data.scale=0.5"], tmp_path)
    out = tmp_path / "outputs" / "demo"
    for name in ("figure.png", "stixels_overlay.png", "stixels_depth.png", "bev.png", "depth_stixels.png", "depth_sfm.png",
                 "flow.png", "input.png"):
        img = cv2.imread(str(out / name))
        assert img is not None and img.size > 0, name
    st = StixelWorld.load_json(out / "stixels.json")
    assert st.image_size == (round(375 * 0.5), round(1242 * 0.5))
    assert len(st) >= st.num_columns  # at least one stixel per column
    # The demo prints its depth error against ground truth: mono-stixels beat the SfM baseline.
    rel = {line.split()[0]: float(re.search(r" rel ([0-9.]+)", line).group(1)) for line in p.stdout.splitlines()
           if line.strip().startswith(("mono-stixels", "SfM"))}
    assert rel["mono-stixels"] < rel["SfM"], p.stdout


def test_eval_writes_contract_json(tmp_path):
    p = _cli(["eval", "data=synthetic", "data.frames=2", "data.scale=0.25", "flow=gt", "semantic=gt",
              "motion=gt", "out=r.json"], tmp_path)
    r = json.loads((tmp_path / "r.json").read_text())
    assert r["dataset"] == "synthetic" and r["frames"] == 2
    keys = {"rel", "rmse", "d1.1", "d1.25", "d1.25^2", "d1.25^3", "n"}
    for m in ("monostixels", "sfm"):
        for split in ("overall", "static", "moving"):
            assert set(r["methods"][m][split]) == keys
        assert r["methods"][m]["overall"]["n"] == r["methods"][m]["static"]["n"] + r["methods"][m]["moving"]["n"]
    assert set(r["methods"]["monostixels"]) == {"overall", "static", "moving", "compactness", "seconds_per_frame"}
    assert set(r["methods"]["sfm"]) == {"overall", "static", "moving", "compactness"}
    # Oracle inputs: mono-stixels are good, SfM fails on movers; stixels are far more compact.
    mono, sfm = r["methods"]["monostixels"], r["methods"]["sfm"]
    assert mono["overall"]["d1.25"] > 0.9 and sfm["moving"]["rel"] > 0.5
    assert mono["compactness"] * 20 < sfm["compactness"]
    assert "Mono-Stixels" in p.stdout and "Rel. error" in p.stdout


def test_run_on_a_folder_of_frames(tmp_path):
    """`monostixels run data=frames`: per-frame pictures, depth PNG, stixels, point cloud, video."""
    from monostixels.data.synthetic import render_pair

    pair0 = render_pair(3, scale=0.25)
    frames = tmp_path / "frames"
    frames.mkdir()
    # A three-image sequence: the previous image of pair 3, then its current image, then again.
    imgs = [pair0.image_prev, pair0.image, pair0.image]
    for k, im in enumerate(imgs):
        rgb = (im.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
        cv2.imwrite(str(frames / f"{k:04d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    K = pair0.camera.K
    (frames / "intrinsics.yaml").write_text(f"fx: {float(K[0, 0])}\nfy: {float(K[1, 1])}\ncx: {float(K[0, 2])}\ncy: {float(K[1, 2])}\n")
    # run's own input defaults (preset=fast: DIS refined, the real-image semantic net, monocular ego-motion,
    # work carried from frame to frame): no ground truth needed.
    p = _cli(["run", "data=frames", f"data.root={frames}"], tmp_path)
    out = tmp_path / "outputs" / "run"
    dirs = sorted(d for d in out.iterdir() if d.is_dir())
    assert len(dirs) == 2
    for d in dirs:
        for name in ("overlay.png", "bev.png", "figure.png", "depth.png", "depth16.png", "stixels.json", "stixels.npz",
                     "points.ply"):
            assert (d / name).is_file(), (d, name)
        assert cv2.imread(str(d / "depth16.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint16
        overlay, bev, fig = (cv2.imread(str(d / n)) for n in ("overlay.png", "bev.png", "figure.png"))
        assert overlay.shape[:2] == pair0.size and fig.shape[0] == overlay.shape[0] and fig.shape[1] > overlay.shape[1]
    assert (out / "video.mp4").stat().st_size > 0 and (out / "bev.mp4").stat().st_size > 0
    assert "2 frame pair(s)" in p.stdout
    # What it ran on (docs/conventions.md, section 4.3): the CPU's flags, ONNX Runtime's INT8 path, the kernel's build.
    import onnxruntime

    from monostixels._cpu import cpu_info, int8_path

    ran_on = json.loads((out / "summary.json").read_text())["platform"]
    assert ran_on["cpu"] == cpu_info() and ran_on["int8_path"] == int8_path()
    assert ran_on["onnxruntime"] == onnxruntime.__version__
    assert ran_on["solver_build"] is None or "-ffp-contract=off" in ran_on["solver_build"]


@pytest.mark.parametrize("case", ["missing_intrinsics", "empty", "unreadable", "sizes"])
def test_run_fails_clearly(tmp_path, case):
    frames = tmp_path / "f"
    frames.mkdir()
    img = np.full((40, 60, 3), 128, np.uint8)
    if case != "empty":
        cv2.imwrite(str(frames / "0000.png"), img)
        cv2.imwrite(str(frames / "0001.png"), img if case != "sizes" else img[:30])
    if case == "unreadable":
        (frames / "0001.png").write_bytes(b"not a png")
    if case != "missing_intrinsics":
        (frames / "intrinsics.yaml").write_text("fx: 50\nfy: 50\ncx: 30\ncy: 20\n")
    p = _cli(["run", "data=frames", f"data.root={frames}", "flow=dis", "semantic=none", "motion=mono"], tmp_path, check=False)
    assert p.returncode != 0
    err = p.stderr.lower()
    assert "error" in err and "traceback" not in err
    assert {"missing_intrinsics": "intrinsics", "empty": "f", "unreadable": "0001.png", "sizes": "size"}[case] in err


SHARED = REPO.parent / "shared" / "data"


@pytest.mark.skipif(not (SHARED / "kitti2015").is_dir(), reason="shared KITTI 2015 sample (../shared/data/kitti2015) not present")
def test_run_on_the_kitti2015_pair(tmp_path):
    """Ego-motion fails on this pair; `run` still writes its outputs, flagged, from the scene model."""
    p = _cli(["run", "data=kitti2015", f"data.root={SHARED / 'kitti2015'}", "flow=dis", "semantic=none", "motion=mono"], tmp_path)
    d = tmp_path / "outputs" / "run"
    (frame,) = [x for x in d.iterdir() if x.is_dir()]
    st = StixelWorld.load_json(frame / "stixels.json")
    assert st.image_size == (375, 1242) and len(st) >= st.num_columns
    assert (frame / "points.ply").stat().st_size > 0
    # The depth-coloured stixel overlay, the bird's-eye view and both side by side.
    overlay, bev, fig = (cv2.imread(str(frame / n)) for n in ("overlay.png", "bev.png", "figure.png"))
    assert overlay.shape[:2] == (375, 1242) and bev.shape[0] > 0 and fig.shape[0] == 375
    assert "1 frame pair(s)" in p.stdout


def test_semantic_none_carries_its_prior_overrides():
    from monostixels.pipeline import Pipeline, load_config
    from monostixels.build import pipeline_settings

    assert Pipeline(pipeline_settings(load_config(["semantic=none"]))).prior.alpha_dyn == 0.25
    assert Pipeline(pipeline_settings(load_config(["semantic=gt"]))).prior.alpha_dyn == 0.0
    assert Pipeline(pipeline_settings(load_config(["semantic=none", "semantic.prior_overrides.alpha_dyn=1.5"]))).prior.alpha_dyn == 1.5


def test_run_on_a_video(tmp_path):
    """`monostixels run data=video`: a clip the test writes from rendered frames -> per-frame outputs and the overlay video."""
    from monostixels.data.synthetic import render_pair

    pair = render_pair(3, scale=0.25)
    H, W = pair.size
    vw = cv2.VideoWriter(str(tmp_path / "clip.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (W, H))
    for im in (pair.image_prev, pair.image, pair.image):
        vw.write(cv2.cvtColor((im.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR))
    vw.release()
    K = pair.camera.K
    hfov = float(np.degrees(2 * np.arctan(W / 2 / float(K[0, 0]))))
    p = _cli(["run", "data=video", f"data.path={tmp_path / 'clip.mp4'}", f"data.hfov_deg={hfov}", "flow=dis", "semantic=none"], tmp_path)
    out = tmp_path / "outputs" / "run"
    dirs = sorted(d for d in out.iterdir() if d.is_dir())
    assert [d.name for d in dirs] == ["clip_000001", "clip_000002"]
    for d in dirs:
        st = StixelWorld.load_json(d / "stixels.json")
        assert st.image_size == (H, W) and len(st) >= st.num_columns
    cap = cv2.VideoCapture(str(out / "video.mp4"))
    n = 0
    while cap.read()[0]:
        n += 1
    assert n == 2 and "2 frame pair(s)" in p.stdout


@pytest.mark.parametrize("case", ["missing", "no_intrinsics", "one_frame"])
def test_run_video_fails_clearly(tmp_path, case):
    path = tmp_path / "clip.mp4"
    if case != "missing":
        vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (64, 48))
        for _ in range(1 if case == "one_frame" else 3):
            vw.write(np.full((48, 64, 3), 90, np.uint8))
        vw.release()
    args = ["run", "data=video", f"data.path={path}", "flow=dis", "semantic=none"] + ([] if case == "no_intrinsics" else ["data.hfov_deg=90"])
    p = _cli(args, tmp_path, check=False)
    err = p.stderr.lower()
    assert p.returncode != 0 and "error" in err and "traceback" not in err
    assert {"missing": "does not exist", "no_intrinsics": "hfov_deg", "one_frame": "at least two"}[case] in err


def test_calibrate_writes_an_intrinsics_file(tmp_path):
    """`monostixels calibrate`: chessboard views -> intrinsics.yaml (fx fy cx cy distortion), the RMS error and
    the boards found printed, the views without a board named."""
    from monostixels.data._camera_files import read_distortion, read_intrinsics_file
    from tests._boards import write_board_views

    K = np.array([[330.0, 0.0, 203.0], [0.0, 325.0, 148.0], [0.0, 0.0, 1.0]])
    views = tmp_path / "cal"
    write_board_views(views, K, np.array([-0.22, 0.04, 0.0, 0.0, 0.0]), (300, 400), n=4)
    cv2.imwrite(str(views / "view_blank.png"), np.full((300, 400), 128, np.uint8))
    p = _cli(["calibrate", f"calibrate.images={views}/*.png", "calibrate.board=[9,6]", "calibrate.out=cam/intr.yaml"],
             tmp_path)
    assert "board found in 4 of 5 images" in p.stdout and "no board in: view_blank.png" in p.stdout
    rms = float(re.search(r"RMS reprojection error ([0-9.]+) px", p.stdout).group(1))
    assert rms < 0.5
    fx, fy, cx, cy = read_intrinsics_file(tmp_path / "cam" / "intr.yaml")
    assert fx == pytest.approx(330.0, rel=0.02) and read_distortion(tmp_path / "cam" / "intr.yaml")[0] < 0


@pytest.mark.parametrize("case", ["no_match", "no_board"])
def test_calibrate_fails_clearly(tmp_path, case):
    images = tmp_path / "imgs"
    images.mkdir()
    if case == "no_board":
        for k in range(3):
            cv2.imwrite(str(images / f"{k}.jpg"), np.full((60, 80, 3), 50 * k, np.uint8))
    p = _cli(["calibrate", f"calibrate.images={images}/*.jpg"], tmp_path, check=False)
    err = p.stderr.lower()
    assert p.returncode == 1 and "traceback" not in err
    line = next(ln for ln in p.stderr.splitlines() if "error" in ln)
    assert line.startswith("monostixels calibrate: error: calibrate.images:") and f"{images}/*.jpg" in line
    assert {"no_match": "no image file matches", "no_board": "found in 0 of the 3 images"}[case] in line
    assert not (tmp_path / "intrinsics.yaml").exists()


def _one_error_line(stderr: str) -> str:
    """The stderr of a run that failed on a bad input: exactly one `error:` line, no traceback."""
    lines = [ln for ln in stderr.splitlines() if "error:" in ln]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    return lines[0]


@pytest.mark.parametrize("size", [(12, 40), (2, 2), (1, 1000)])
def test_run_on_frames_below_the_minimum_size_fails_clearly(tmp_path, size):
    """A 40x12 frame killed the process (a segfault in OpenCV); now one line naming the size and the minimum."""
    from monostixels._checks import MIN_FRAME_SIZE

    H, W = size
    frames = tmp_path / "f"
    frames.mkdir()
    rng = np.random.default_rng(0)
    for k in range(2):
        cv2.imwrite(str(frames / f"{k:04d}.png"), (rng.random((H, W, 3)) * 255).astype(np.uint8))
    (frames / "intrinsics.yaml").write_text(f"fx: {W}\nfy: {W}\ncx: {W / 2}\ncy: {H / 2}\n")
    p = _cli(["run", "data=frames", f"data.root={frames}", "flow=dis", "semantic=none"], tmp_path, check=False)
    assert p.returncode == 1
    line = _one_error_line(p.stderr)
    assert f"{W}x{H}" in line and f"{MIN_FRAME_SIZE[1]}x{MIN_FRAME_SIZE[0]}" in line


def test_pipeline_refuses_a_frame_below_the_minimum_size():
    from monostixels._checks import MIN_FRAME_SIZE, InputError
    from monostixels.data.base import FramePair
    from monostixels.core.geometry import Camera, intrinsics
    from monostixels.pipeline import Pipeline, load_config
    from monostixels.build import pipeline_settings

    H, W = MIN_FRAME_SIZE[0] - 1, 200
    img = torch.rand(3, H, W)
    pair = FramePair(image=img, image_prev=img.clone(), camera=Camera(K=intrinsics(100.0, 100.0, W / 2, H / 2)), name="tiny")
    with pytest.raises(InputError, match=rf"tiny: frame of {W}x{H}"):
        Pipeline(pipeline_settings(load_config(["flow=dis", "semantic=none", "motion=mono"]))).run(pair)


@pytest.mark.parametrize("option, key, what", [("data.hfov_deg=wide", "data.hfov_deg", "a number"),
                                                ("data.step=two", "data.step", "an integer"),
                                                ("prior.alpha_L=big", "prior.alpha_L", "a number")])
def test_numeric_option_given_as_text_fails_clearly(tmp_path, option, key, what):
    """Text for a number option: one line naming the option (was a bare 'could not convert string to float')."""
    clip = tmp_path / "clip.mp4"
    vw = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (64, 48))
    for k in range(3):
        vw.write(np.full((48, 64, 3), 60 + 20 * k, np.uint8))
    vw.release()
    p = _cli(["run", "data=video", f"data.path={clip}", "data.hfov_deg=90", option, "flow=dis", "semantic=none"],
             tmp_path, check=False)
    assert p.returncode == 1
    value = option.split("=", 1)[1]
    assert _one_error_line(p.stderr).endswith(f"error: {key}: expected {what}, got '{value}'")


def test_number_checks_name_the_option():
    from dataclasses import dataclass

    from monostixels._checks import InputError, check_number, config_params, numeric_text_error

    @dataclass
    class P:
        gain: float = 1.0
        label: str = "x"

    assert config_params(P, {"gain": "2.5", "label": "y"}, "grp") == P(2.5, "y")
    with pytest.raises(InputError, match=r"^grp\.gain: expected a number, got 'wide'$"):
        config_params(P, {"gain": "wide"}, "grp")
    with pytest.raises(InputError, match=r"^grp\.loss: unknown setting; known: gain, label$"):
        config_params(P, {"loss": 1.0}, "grp")
    assert check_number("3", "n", int) == 3
    with pytest.raises(InputError, match="n: expected an integer, got '2.5'"):
        check_number("2.5", "n", int)
    with pytest.raises(InputError, match="expected a number, got True"):
        check_number(True, "flag")
    cfg = {"data": {"hfov_deg": "wide", "name": "video"}, "prior": {"beta_mc": 25.0}}
    try:
        float(cfg["data"]["hfov_deg"])
    except ValueError as e:
        err = numeric_text_error(cfg, e)
    assert str(err) == "data.hfov_deg: expected a number, got 'wide'"
    assert numeric_text_error(cfg, ValueError("could not convert string to float: 'other'")) is None
    assert numeric_text_error(cfg, ValueError("something else")) is None


def test_run_logs_each_frame_warning_once(tmp_path):
    """`run data=frames` with a field of view and a frame rate: a standing pair's warning is logged once (not
    again by the command), and so is the field-of-view warning."""
    from monostixels.data.synthetic import render_pair

    pair = render_pair(3, scale=0.25)
    frames = tmp_path / "frames"
    frames.mkdir()
    for k, im in enumerate([pair.image_prev, pair.image, pair.image]):  # the last pair stands still
        rgb = (im.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
        cv2.imwrite(str(frames / f"{k:04d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    p = _cli(["run", "data=frames", f"data.root={frames}", "data.hfov_deg=60", "data.fps=20", "flow=dis",
              "semantic=none", "keyframes.min_distance_m=0"], tmp_path)
    out = p.stdout + p.stderr
    warnings = [ln.split("] - ", 1)[1] for ln in out.splitlines() if "[WARNING] - " in ln]
    standing = [w for w in warnings if w.startswith("0002: ")]
    assert len(standing) == 1 and "flow carries no depth" in standing[0], out
    assert len(warnings) == len(set(warnings)), out
    assert sum("horizontal field of view of 60 deg" in w for w in warnings) == 1
    st = json.loads((tmp_path / "outputs" / "run" / "0002" / "stixels.json").read_text())
    assert st["flags"].get("degenerate_motion")


def test_log_lines_are_written_above_the_progress_bar(capsys):
    """A console log line during a bar clears the bar and stands on its own line (tqdm.write), instead of being
    glued to the end of the bar."""
    import logging

    from tqdm import tqdm

    from monostixels.cli import _logs_above_progress_bars

    handler = logging.StreamHandler(sys.stdout)
    handler.setFormatter(logging.Formatter("[%(levelname)s] - %(message)s"))
    root, before = logging.getLogger(), list(logging.getLogger().handlers)
    root.handlers = [handler]
    try:
        with _logs_above_progress_bars():
            bar = tqdm(total=3, desc="run", file=sys.stdout, mininterval=0)
            bar.update(1)
            logging.getLogger("monostixels.test").warning("a frame's warning")
            bar.update(2)
            bar.close()
        assert root.handlers == [handler]  # given back after the command
    finally:
        root.handlers = before
    out = capsys.readouterr().out
    at = out.index("[WARNING] - a frame's warning")
    assert out[at - 1] in "\r\n", repr(out[max(0, at - 40): at + 10])
    assert out.count("a frame's warning") == 1
