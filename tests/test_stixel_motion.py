"""The eval report's stixel_motion section and the motion section's per-pair extremes."""
from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from monostixels.data.base import FramePair
from monostixels.data.synthetic import SyntheticSource
from monostixels.eval.evaluate import evaluate, frame_interval, moving_stixel_mask
from monostixels.core.geometry import Camera, Motion, intrinsics
from monostixels.eval.metrics import motion_errors
from monostixels.pipeline import load_config
from monostixels.core.stixels import paint_index_map


def test_moving_stixel_mask_by_speed():
    # Two columns of width 2 on a 4 x 4 image: column 0 one stixel moving 0.15 m, column 1 two stixels
    # (bottom static, top moving 0.05 m). At dt = 0.1 s: 1.5 m/s and 0.5 m/s.
    column, top, bot = torch.tensor([0, 1, 1]), torch.tensor([0, 2, 0]), torch.tensor([3, 3, 1])
    st = SimpleNamespace(motion=torch.tensor([[0.15, 0, 0], [0, 0, 0], [0, 0, 0.05]]),
                         index_map=lambda: paint_index_map(column, top, bot, 2, (4, 4)))
    m = moving_stixel_mask(st, 0.1, 1.0)
    assert m[:, :2].all() and not m[:, 2:].any()
    assert moving_stixel_mask(st, 0.1, 0.4)[:2, 2:].all()
    assert not moving_stixel_mask(st, 1.0, 1.0).any()  # the same motion over 1 s is slow


def test_frame_interval_from_meta():
    cam = Camera(K=intrinsics(10.0, 10.0, 2.0, 2.0), height=1.65, ground_normal=torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    img = torch.zeros(3, 4, 4)
    p = FramePair(img, img, cam, meta={"dt": 0.25})
    assert frame_interval(p, 0.1) == 0.25
    p.meta = {"timestamp": "2463-05-15T00:38:58.203752Z", "timestamp_prev": "2463-05-15T00:38:57.415230Z"}
    assert frame_interval(p, 0.1) == pytest.approx(0.788522)
    p.meta = {}
    assert frame_interval(p, 0.1) == 0.1


def test_motion_errors_horizontal_direction():
    gt = Motion(torch.eye(3, dtype=torch.float64), torch.tensor([0.0, 0.19, 1.0], dtype=torch.float64))
    est = Motion(torch.eye(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    e = motion_errors(est, gt)
    assert e["trans_dir_err_deg"] == pytest.approx(10.758, abs=1e-3)  # atan(0.19)
    assert e["trans_dir_err_xz_deg"] == pytest.approx(0.0, abs=1e-9)  # the vertical drift is not counted


def test_report_sections_on_synthetic():
    cfg = load_config(["flow=gt", "semantic=gt", "motion=mono", "data.scale=0.25"])
    r = evaluate(cfg, SyntheticSource(2, seed=0, scale=0.25), dataset="synthetic", progress=False)
    sm = r["stixel_motion"]
    assert set(sm) >= {"moving_share", "static_moving_share", "moving_recall", "speed_mps"}
    assert 0.0 <= sm["static_moving_share"] <= 1.0 and 0.0 <= sm["moving_share"] <= 1.0
    # Oracle inputs: the real movers are found, static pixels are not called moving.
    assert sm["moving_recall"] > 0.5 and sm["static_moving_share"] < 0.05
    mo = r["motion"]
    assert mo["pairs"] == 2 and mo["scale_rel_err_max"] >= mo["scale_rel_err"]
    assert set(mo) >= {"rot_err_deg", "trans_dir_err_deg", "trans_dir_err_xz_deg", "scale_rel_err"}
