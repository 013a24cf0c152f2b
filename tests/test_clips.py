"""The clip benchmark's scoring on small worlds with known answers, its LiDAR numbers against hand-computed
ones, and the clips it finds in a data folder (no clip is run)."""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

from benchmarks.clips import (Clip, FrameScore, _lidar_depth, _score, discover_clips, kitti_intrinsics,
                              lidar_summary, markdown, summarize, warnings_off_referee)
from monostixels.core.classes import DYNAMIC_OBJECT, GROUND, STATIC_OBJECT
from monostixels.core.status import FrameStatus, MotionKind, MotionStatus, ScaleFrom
from monostixels.core.stixels import StixelWorld
from monostixels.eval.metrics import DepthAccumulator

H, W, WS = 20, 8, 4  # image rows, columns, column width: two stixel columns
VEHICLE = 6


def _world(warning: list[bool]) -> StixelWorld:
    """Column 0: ground below a dynamic stixel; column 1: ground below a static one (rows 0-9 above 10-19)."""
    n = 4

    def t(v: list, dtype: torch.dtype = torch.int64) -> torch.Tensor:
        return torch.tensor(v, dtype=dtype)

    return StixelWorld(
        column_width=WS, image_size=(H, W), K=torch.tensor([[10.0, 0, 4], [0, 12.0, 10], [0, 0, 1]]),
        ground_normal=t([0.0, -1.0, 0.0], torch.float32), column=t([0, 0, 1, 1]), v_top=t([10, 0, 10, 0]),
        v_bottom=t([19, 9, 19, 9]), type=t([GROUND, DYNAMIC_OBJECT, GROUND, STATIC_OBJECT]), cls=t([0, 6, 0, 4]),
        inverse_depth=torch.full((n,), 0.1), motion=torch.zeros(n, 3), cost=torch.zeros(n), tau=torch.zeros(n, 2),
        energy=torch.zeros(2), status=FrameStatus(MotionStatus(kind=MotionKind.METRIC, scale_from=ScaleFrom.ROAD_MARKS, scale_std=0.1)),
        ttc_warning=torch.tensor(warning), pair_info={"dt_s": 0.1})


def _step(world: StixelWorld, name: str = "000001") -> SimpleNamespace:
    motion = SimpleNamespace(motion=SimpleNamespace(translation_norm=1.5))
    result = SimpleNamespace(stixels=world, motion=motion)
    return SimpleNamespace(pair=SimpleNamespace(name=name, gt=None), result=result)


def test_a_dynamic_stixel_off_the_referees_vehicle_is_a_false_mover_and_a_warning_off_it_is_counted():
    referee = np.zeros((H, W), np.int64)
    referee[0:10, 4:8] = VEHICLE  # the referee's car is the static stixel of column 1
    kernel = np.ones((1, 1), np.uint8)  # no dilation
    on_car = _score(_step(_world([False, False, False, True])), lambda pair: referee, kernel)
    assert on_car.false_mover_share == pytest.approx(40 / 160)  # the dynamic stixel: 10 rows x 4 px
    assert on_car.ttc_warnings == 1 and on_car.ttc_off_referee == 0
    assert on_car.speed_mps == pytest.approx(15.0) and on_car.scale_std == 0.1
    referee[:] = 0
    referee[0:10, 0:4] = VEHICLE  # now the mover is on the car and the warning on nothing the referee knows
    off_car = _score(_step(_world([False, False, False, True])), lambda pair: referee, kernel)
    assert off_car.false_mover_share == 0.0 and off_car.ttc_off_referee == 1
    # A pair whose scale is too uncertain to tell movers has no speed in the row (as in the run's summary).
    unsure = _world([False] * 4)
    unsure.status.motion.scale_uncertain = True
    assert _score(_step(unsure), None, kernel).speed_mps is None


def test_a_warning_stixel_with_one_pixel_off_the_referee_counts_once():
    idx = np.array([[0, 0, 1], [0, 0, 1], [2, 2, -1]])
    near = np.array([[True, True, True], [True, False, True], [False, False, False]])
    # Stixel 0 warns with one pixel off; stixel 1 warns, all on; stixel 2 is off but does not warn.
    assert warnings_off_referee(idx, np.array([True, True, False]), near) == 1
    assert warnings_off_referee(idx, np.array([False, True, False]), near) == 0


def test_a_clips_row_counts_motion_kinds_speeds_movers_and_warning_frames():
    frames = [
        FrameScore("1", "metric", "road_marks", None, 10.0, False, 0.01, 0, 0),
        FrameScore("2", "metric", "sequence", None, 14.0, False, 0.03, 2, 1),
        FrameScore("3", "standing", None, None, None, False, 0.02, 1, 0),
        FrameScore("4", failed=True),
    ]
    r = summarize(frames)
    assert r["pairs"] == 4 and r["failed"] == 1
    assert r["camera_motion"] == {"metric": 2, "standing": 1, "scale_unknown": 0, "unknown": 0}
    assert r["scale_from"] == {"road_marks": 1, "sequence": 1, "-": 1}
    assert r["standing_share"] == 0.25
    assert r["speed_mps"] == {"median": 12.0, "min": 10.0, "max": 14.0}
    assert r["scale_std_median"] is None
    assert r["false_mover_share"] == {"median": pytest.approx(0.02), "max": pytest.approx(0.03)}
    assert r["ttc_frames"] == 2 and r["ttc_frame_share"] == 0.5 and r["ttc_off_referee_frames"] == 1
    table = markdown({"a": r}).splitlines()
    assert len(table) == 3 and table[2].startswith("| a | 4 (1) | 2/1/0/0 | 25% |")
    # Without a referee, neither movers nor warnings off it are measured.
    bare = summarize([FrameScore("1", "metric", speed_mps=3.0)])
    assert bare["false_mover_share"] is None and bare["ttc_off_referee_frames"] is None


def test_lidar_metrics_clamp_invalid_estimates_to_80_m_over_all_pixels_of_all_frames():
    acc = DepthAccumulator(min_depth=0.001, max_depth=80.0)
    gt = torch.tensor([[10.0, 20.0], [0.0, 40.0]])  # 0: no LiDAR return
    acc.add(torch.tensor([[11.0, float("nan")], [5.0, 40.0]]), gt)  # |d-g|/g: 0.1, 3 (NaN -> 80), -, 0
    acc.add(torch.tensor([[9.0, 1.0], [1.0, 1.0]]), torch.tensor([[10.0, 0.0], [0.0, 0.0]]))  # 0.1
    r = lidar_summary(acc)
    assert r["n"] == 4 and r["rel"] == pytest.approx((0.1 + 3.0 + 0.0 + 0.1) / 4)
    assert r["d1.25"] == pytest.approx(3 / 4)  # 11/10, 40/40 and 10/9 within 1.25; 80/20 not
    empty = lidar_summary(DepthAccumulator(min_depth=0.001, max_depth=80.0))
    assert empty["rel"] is None and empty["n"] == 0


def test_the_lidar_png_beside_the_frames_is_read_in_metres(tmp_path: Path):
    depth = np.zeros((3, 5), np.uint16)
    depth[1, 2] = int(12.5 * 256)
    cv2.imwrite(str(tmp_path / "0000000007.png"), depth)
    step = _step(_world([False] * 4), name="0000000007")
    got = _lidar_depth(step, tmp_path)
    assert got.shape == (3, 5) and float(got[1, 2]) == 12.5 and float(got.sum()) == 12.5
    assert _lidar_depth(_step(_world([False] * 4), name="0000000008"), tmp_path) is None
    step.pair.gt = SimpleNamespace(depth=torch.ones(2, 2))  # the source's own ground truth wins
    assert _lidar_depth(step, tmp_path).shape == (2, 2)


def test_clips_are_found_by_kind_in_the_data_folder(tmp_path: Path):
    city = tmp_path / "city"
    (city / "dad_000001").mkdir(parents=True)
    (city / "dad_000002").mkdir()
    (city / "notes").mkdir()
    (city / "phone.mp4").write_bytes(b"")
    (city / "README.md").write_text("")
    (tmp_path / "dashcam").mkdir()
    (tmp_path / "dashcam" / "highway_solid_white_right.mp4").write_bytes(b"")
    clips = {c.name: c for c in discover_clips(tmp_path)}
    assert list(clips) == ["highway", "dad_000001", "dad_000002", "phone"]  # no traffic drive here
    assert f"data.root={city / 'dad_000001'}" in clips["dad_000001"].overrides
    assert {"data=frames", "data.hfov_deg=90", "data.fps=20", "camera.height=1.3"} <= set(clips["dad_000002"].overrides)
    assert clips["phone"].overrides[:2] == ("data=video", f"data.path={city / 'phone.mp4'}")
    assert not clips["phone"].lidar
    assert Clip("x", ("data.root={data}/a",)).resolved(tmp_path) == [f"data.root={tmp_path}/a"]


def test_kitti_intrinsics_are_read_from_p_rect_02(tmp_path: Path):
    calib = tmp_path / "calib_cam_to_cam.txt"
    calib.write_text("P_rect_00: 1 0 2 0 0 1 3 0 0 0 1 0\n"
                     "P_rect_02: 7.215377e+02 0 6.095593e+02 4.48e+01 0 7.215377e+02 1.72854e+02 2.16e-01 "
                     "0 0 1 2.7e-03\n")
    assert kitti_intrinsics(calib) == pytest.approx((721.5377, 721.5377, 609.5593, 172.854))
