"""Depth / semantic / bottoms metrics against hand-computed values, and the report tables."""
from __future__ import annotations

import math

import pytest
import torch

from monostixels._checks import InputError
from monostixels.core.classes import CLASS_NAMES
from monostixels.eval.metrics import (
    DepthAccumulator,
    SemanticAccumulator,
    bottoms_metrics,
    dense_compactness,
    depth_metrics,
    semantic_metrics,
    stixel_compactness,
)
from monostixels.eval.report import format_table, markdown_table

MAX_D = 80.0
MIN_D = 1e-3


def test_depth_metrics_hand_computed_with_invalid_estimate():
    # gt: 0 = no ground truth, 100 > max_depth: not evaluated -> 4 pixels (10, 20, 40, 5).
    gt = torch.tensor([[10.0, 20.0, 0.0], [40.0, 100.0, 5.0]])
    # 10.5: ratio 1.05; 20: exact; -3 (behind the camera): set to max_depth 80, ratio 2;
    # 4 vs 5: ratio exactly 1.25, which is NOT < 1.25.
    pred = torch.tensor([[10.5, 20.0, 7.0], [-3.0, 50.0, 4.0]])
    m = depth_metrics(pred, gt, min_depth=MIN_D, max_depth=MAX_D)
    assert m["n"] == 4
    assert m["rel"] == pytest.approx((0.05 + 0.0 + 1.0 + 0.2) / 4)
    assert m["rmse"] == pytest.approx(math.sqrt((0.25 + 0.0 + 1600.0 + 1.0) / 4))
    assert m["d1.1"] == pytest.approx(2 / 4)
    assert m["d1.25"] == pytest.approx(2 / 4)
    assert m["d1.25^2"] == pytest.approx(3 / 4)
    assert m["d1.25^3"] == pytest.approx(3 / 4)


def test_depth_metrics_clamps_every_kind_of_invalid_estimate_to_max_depth():
    gt = torch.full((1, 5), 40.0)
    pred = torch.tensor([[float("nan"), float("inf"), 0.0, -5.0, 1000.0]])
    m = depth_metrics(pred, gt, min_depth=MIN_D, max_depth=MAX_D)
    # All five count (nothing dropped), all become 80 m: rel = 1, rmse = 40, ratio 2.
    assert m["n"] == 5
    assert m["rel"] == pytest.approx(1.0)
    assert m["rmse"] == pytest.approx(40.0)
    assert m["d1.25^3"] == 0.0


def test_depth_metrics_min_clamp_and_mask():
    gt = torch.tensor([[2.0, 10.0], [10.0, 10.0]])
    pred = torch.tensor([[0.5, 10.0], [5.0, 30.0]])
    mask = torch.tensor([[True, True], [False, False]])
    m = depth_metrics(pred, gt, mask, min_depth=1.0, max_depth=MAX_D)
    # 0.5 -> clamped to 1.0: rel 0.5, err 1; second pixel exact. Masked-out pixels do not count.
    assert m["n"] == 2
    assert m["rel"] == pytest.approx(0.25)
    assert m["rmse"] == pytest.approx(math.sqrt(0.5))
    assert m["d1.1"] == pytest.approx(0.5)


def test_depth_metrics_empty_is_nan_and_bad_input_raises():
    m = depth_metrics(torch.ones(2, 2), torch.zeros(2, 2), min_depth=MIN_D, max_depth=MAX_D)
    assert m["n"] == 0 and math.isnan(m["rel"])
    with pytest.raises(InputError, match="pred and gt"):
        depth_metrics(torch.ones(2, 3), torch.ones(3, 2), min_depth=MIN_D, max_depth=MAX_D)
    with pytest.raises(InputError, match="min_depth"):
        depth_metrics(torch.ones(2, 2), torch.ones(2, 2), min_depth=5.0, max_depth=1.0)


def test_accumulator_equals_metrics_on_concatenation():
    g = torch.Generator().manual_seed(0)
    frames = []
    for w in (7, 4, 9):
        gt = torch.rand(5, w, generator=g) * 100.0
        gt[torch.rand(5, w, generator=g) < 0.3] = 0.0
        pred = gt * (0.6 + 0.8 * torch.rand(5, w, generator=g))
        pred[torch.rand(5, w, generator=g) < 0.1] = -1.0
        mask = torch.rand(5, w, generator=g) < 0.7
        frames.append((pred, gt, mask))
    acc = DepthAccumulator(min_depth=MIN_D, max_depth=MAX_D)
    for p, t, k in frames:
        acc.add(p, t, k)
    cat = [torch.cat(x, dim=1) for x in zip(*frames)]
    ref = depth_metrics(*cat, min_depth=MIN_D, max_depth=MAX_D)
    res = acc.result()
    assert res["n"] == ref["n"] > 0
    for k in ("rel", "rmse", "d1.1", "d1.25", "d1.25^2", "d1.25^3"):
        assert res[k] == pytest.approx(ref[k], rel=1e-12)
    # ... and it is not the mean of per-frame means (frames differ in size).
    per_frame = [depth_metrics(p, t, k, min_depth=MIN_D, max_depth=MAX_D)["rel"] for p, t, k in frames]
    assert abs(sum(per_frame) / 3 - res["rel"]) > 1e-6


def test_compactness():
    assert stixel_compactness([100, 200]) == pytest.approx(450.0)  # 3 x mean stixels
    assert dense_compactness([375 * 1242, 375 * 1242]) == pytest.approx(465750.0)  # paper: 465 k


def test_semantic_metrics_hand_computed():
    gt = torch.tensor([[0, 0, 1], [1, 255, 2]])
    pred = torch.tensor([[0, 1, 1], [1, 0, 9]])
    m = semantic_metrics(pred, gt)
    iou = m["per_class_iou"]
    assert iou["road"] == pytest.approx(1 / 2)  # TP 1, FN 1
    assert iou["sidewalk"] == pytest.approx(2 / 3)  # TP 2, FP 1
    assert iou["terrain"] == 0.0  # FN 1
    assert iou["sky"] == 0.0  # FP 1 (the ignored pixel's prediction 0 is not a FP of road)
    assert math.isnan(iou["building"])  # absent from both: skipped in the mean
    assert m["miou"] == pytest.approx((1 / 2 + 2 / 3 + 0 + 0) / 4)
    assert list(iou) == list(CLASS_NAMES)


def test_semantic_accumulator_and_void_predictions():
    acc = SemanticAccumulator()
    acc.add(torch.tensor([[0, 255]]), torch.tensor([[0, 0]]))  # prediction 255 = miss of road
    acc.add(torch.tensor([[0]]), torch.tensor([[0]]))
    assert acc.result()["per_class_iou"]["road"] == pytest.approx(2 / 3)
    with pytest.raises(InputError, match="gt_labels"):
        acc.add(torch.tensor([[0]]), torch.tensor([[12]]))


def test_bottoms_metrics_hand_computed():
    m = bottoms_metrics([100.0, 103.0, float("nan"), 120.0], [100.0, 110.0, 50.0, 108.0])
    assert m["n"] == 4 and m["missing"] == 1
    assert m["mae_px"] == pytest.approx((0 + 7 + 12) / 3)
    assert m["within_5px"] == pytest.approx(1 / 4)
    assert m["within_10px"] == pytest.approx(2 / 4)


def _paper_report() -> dict:
    def M(rel, rmse, a, b, c, d, n):
        return {"rel": rel, "rmse": rmse, "d1.1": a, "d1.25": b, "d1.25^2": c, "d1.25^3": d, "n": n}

    return {
        "dataset": "kitti2015",
        "frames": 171,
        "methods": {
            "monostixels": {
                "overall": M(0.1230, 6.29, 0.7061, 0.8895, 0.9583, 0.9773, 1000),
                "static": M(0.1122, 6.31, 0.7603, 0.9042, 0.9595, 0.9773, 900),
                "moving": M(0.1940, 6.16, 0.3469, 0.7920, 0.9504, 0.9772, 100),
                "compactness": 5690.0,
                "seconds_per_frame": 0.5,
            },
            "sfm": {
                "overall": M(0.3557, 11.29, 0.6659, 0.7698, 0.8290, 0.8744, 1000),
                "static": M(0.1708, 7.93, 0.7618, 0.8757, 0.9319, 0.9565, 900),
                "moving": M(1.5807, 23.56, 0.0316, 0.0694, 0.1475, 0.3310, 100),
                "compactness": 465000.0,
            },
        },
        "semantic": {"miou": 0.5, "per_class_iou": {"road": 0.9, "sky": float("nan")}},
        "bottoms": {"mae_px": 3.25, "within_5px": 0.8, "within_10px": 0.9, "n": 40},
    }


def test_format_table_has_paper_numbers_in_the_right_columns():
    text = format_table(_paper_report())
    lines = text.splitlines()
    header = next(l for l in lines if "Metric" in l)
    assert header.index("SfM baseline") < header.index("Mono-Stixels")
    assert "465.00 k" in text and "5.69 k" in text
    i_moving = next(i for i, l in enumerate(lines) if l.startswith("Moving"))
    assert lines[i_moving].split()[-2:] == ["158.07", "19.40"]
    rmse_moving = lines[i_moving + 1].split()
    assert rmse_moving[-2:] == ["23.56", "6.16"]
    i_overall = next(i for i, l in enumerate(lines) if l.startswith("Overall"))
    assert lines[i_overall].split()[-2:] == ["35.57", "12.30"]
    assert lines[i_overall + 5].split()[-2:] == ["87.44", "97.73"]  # d<1.25^3
    assert "mIoU" in text and "50.00" in text
    sky = next(l for l in lines if "IoU sky" in l)
    assert sky.split()[-1] == "-"  # NaN class shown as '-'
    assert next(l for l in lines if "within 5 px" in l).split()[-1] == "80.00"


def test_markdown_table_rows():
    md = markdown_table(_paper_report())
    assert "| Split | Metric | SfM baseline | Mono-Stixels |" in md
    assert "| Static | Rel. error [%] | 17.08 | 11.22 |" in md
    assert "|  | Seconds per frame | - | 0.500 |" in md
