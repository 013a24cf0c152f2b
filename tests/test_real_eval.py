"""Real-image evaluation: data source -> pipeline -> `evaluate` report on the shared samples.

These run the same code as ``monostixels eval`` on one frame pair each, with the fast DIS flow
(``flow=dis``) and ``semantic=none``. They skip with a clear reason when ../shared/data is absent
(e.g. on a user's machine).
"""
from __future__ import annotations

from pathlib import Path

import pytest

from monostixels.core.classes import DYNAMIC_OBJECT
from monostixels.build import build_source
from monostixels.eval.evaluate import SPLITS, evaluate
from monostixels.pipeline import Pipeline, PipelineResult, load_config
from monostixels.build import pipeline_settings

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
KITTI_RAW = SHARED / "kitti_raw"
DDAD = SHARED / "ddad_dgp"
#: Stixel-bottom labels of the shared KITTI raw drive (StixelNet, BMVC 2015).
BOTTOMS = KITTI_RAW / "2011_09_30" / "2011_09_30_drive_0028_sync" / "stixel_bottoms_bmvc15.txt"
#: The first labelled frame of the shared drive.
FIRST_LABELLED_FRAME = 1111


def _labels_of_frame(frame: int) -> int:
    """Number of labelled columns of one raw frame in the labels file (column 3 = frame number)."""
    return sum(1 for line in BOTTOMS.read_text().splitlines()
               if line.split() and int(line.split()[2]) == frame)


@pytest.mark.skipif(not BOTTOMS.is_file(), reason=f"shared KITTI raw sample not found at {KITTI_RAW}")
def test_kitti_raw_labelled_frame_gives_bottoms_and_motion() -> None:
    """One labelled KITTI raw pair: `bottoms` counts every label of the frame, `motion` is measured."""
    cfg = load_config(["data=kitti_raw", f"data.root={KITTI_RAW}", "data.only_labelled=true", "data.frames=1",
                       "flow=dis", "semantic=none", "motion=mono"])
    src = build_source(cfg)
    assert src[0].name.endswith(str(FIRST_LABELLED_FRAME))
    report = evaluate(cfg, src, dataset="kitti_raw", progress=False)
    assert report["frames"] == 1
    b = report["bottoms"]
    assert b["n"] == _labels_of_frame(FIRST_LABELLED_FRAME) > 0
    assert 0.0 <= b["within_5px"] <= b["within_10px"] <= 1.0
    # Bottoms are rows of a 370-row image: a finite error below the image height.
    assert 0.0 <= b["mae_px"] < 370.0
    # The mono ego-motion is measured against the poses: the rotation between two frames 0.1 s
    # apart is small and the estimate must be within a degree of it.
    assert report["motion"]["rot_err_deg"] < 1.0
    # KITTI raw has no depth ground truth: no depth splits in the report.
    assert "overall" not in report["methods"]["monostixels"]


def _ddad_config(*extra: str):
    # Coarser columns and cells (4x fewer DP cells) keep the 1936 x 1216 frame fast in a test.
    return load_config(["data=ddad", f"data.root={DDAD}", "data.frames=1", "flow=dis", "semantic=none",
                        "motion=gt", "solver.column_width=10", "solver.cell_rows=6", *extra])


def _dynamic_share(res: PipelineResult) -> tuple[float, float]:
    """Share of the moving / static LiDAR pixels covered by dynamic-object stixels."""
    dyn = res.stixels.type_map() == DYNAMIC_OBJECT
    moving, has_depth = res.pair.gt.moving, res.pair.gt.depth > 0
    return float(dyn[moving].float().mean()), float(dyn[has_depth & ~moving].float().mean())


@pytest.mark.skipif(not DDAD.is_dir(), reason=f"shared DDAD (TRI dgp) sample not found at {DDAD}")
def test_ddad_report_has_three_splits_and_degenerate_flag() -> None:
    """One DDAD pair (the ego vehicle stands still) with the semantic=none priors: every split is
    scored, the frame is flagged, the scene-model depths of mono-stixels beat the SfM baseline
    (which has no baseline to triangulate from), and the dynamic type marks the moving cars but
    not the static scene."""
    cfg = _ddad_config("prior=nosem")
    results: list[PipelineResult] = []
    report = evaluate(cfg, build_source(cfg), dataset="ddad", progress=False, on_result=results.append)
    assert report["frames"] == 1 and len(results) == 1
    flags = results[0].stixels.flags
    assert flags["degenerate_motion"] is True
    assert "scene model" in flags["reason"]
    mono, sfm = report["methods"]["monostixels"], report["methods"]["sfm"]
    for split in SPLITS:
        assert mono[split]["n"] > 0, split
        assert mono[split]["n"] == sfm[split]["n"]  # every method is scored on the same pixels
    assert mono["static"]["n"] + mono["moving"]["n"] == mono["overall"]["n"]
    assert mono["overall"]["rel"] < sfm["overall"]["rel"]
    on_moving, on_static = _dynamic_share(results[0])
    assert on_moving > 0.5 and on_static < 0.2, (on_moving, on_static)


@pytest.mark.skipif(not DDAD.is_dir(), reason=f"shared DDAD (TRI dgp) sample not found at {DDAD}")
def test_ddad_without_dynamic_cost_the_dynamic_type_takes_everything() -> None:
    """Why semantic=none needs alpha_dyn > 0: without it (and without semantics) the 2-DOF dynamic
    type fits the static scene at least as well as the static types and covers most of it."""
    cfg = _ddad_config("prior.alpha_dyn=0", "semantic.prior_overrides.alpha_dyn=0")
    res = Pipeline(pipeline_settings(cfg)).run(build_source(cfg)[0])
    _, on_static = _dynamic_share(res)
    assert on_static > 0.5, on_static


LIDAR = SHARED / "kitti_raw_lidar"


@pytest.mark.skipif(not LIDAR.is_dir(), reason=f"shared KITTI raw LiDAR drive not found at {LIDAR}")
def test_kitti_raw_lidar_report_has_depth_motion_and_stixel_motion() -> None:
    """One pair of the LiDAR drive: depth metrics over LiDAR pixels (overall only: KITTI raw has no
    moving-object mask), the motion section against OXTS, and the stixel_motion share."""
    cfg = load_config(["data=kitti_raw", f"data.root={LIDAR}", "data.frames=1", "flow=dis", "semantic=none",
                       "motion=mono"])
    src = build_source(cfg)
    n_lidar = int((src[0].gt.depth > 0).sum())
    r = evaluate(cfg, src, dataset="kitti_raw", progress=False)
    for m in ("monostixels", "sfm"):
        assert r["methods"][m]["overall"]["n"] == n_lidar
        assert "static" not in r["methods"][m] and "moving" not in r["methods"][m]
    # Both methods place most LiDAR pixels within 25 % on this static street.
    assert r["methods"]["monostixels"]["overall"]["d1.25"] > 0.6
    mo = r["motion"]
    assert mo["reference"] == "oxts (velocity)" and mo["pairs"] == 1
    assert mo["rot_err_deg"] < 0.5 and mo["trans_dir_err_deg"] < 5.0 and mo["scale_rel_err_max"] < 0.3
    assert 0.0 <= r["stixel_motion"]["moving_share"] <= 1.0
    assert "static_moving_share" not in r["stixel_motion"]
