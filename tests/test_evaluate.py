"""evaluate(): report contents, and frames whose camera motion cannot be estimated."""
from __future__ import annotations

import math

import torch

from monostixels.data.synthetic import SyntheticSource
from monostixels.eval.evaluate import evaluate, predicted_bottoms
from monostixels.inputs.motion import MotionEstimate
from monostixels.pipeline import load_config


def test_failed_motion_frame_counts_with_invalid_estimates(monkeypatch):
    import monostixels.pipeline as pl

    def fail(pair, flow, cfg, semantic=None):
        return MotionEstimate(motion=None, degenerate=False, reason="no ground visible", inlier_ratio=0.0)

    monkeypatch.setattr(pl, "estimate_motion", fail)
    cfg = load_config(["flow=gt", "semantic=gt", "motion=mono", "data.scale=0.2"])
    src = SyntheticSource(1, seed=0, scale=0.2)
    r = evaluate(cfg, src, dataset="synthetic", progress=False)
    pair = src[0]
    gt = pair.gt.depth
    m = (gt > 0) & (gt <= cfg.eval.max_depth)
    # Every ground-truth pixel counts, estimated as max_depth (invalid -> clamped).
    want_rel = float(((cfg.eval.max_depth - gt[m]) / gt[m]).mean())
    assert r["failed_frames"] == [pair.name] and r["frames"] == 1
    for meth in ("monostixels", "sfm"):
        assert r["methods"][meth]["overall"]["n"] == int(m.sum())
        assert math.isclose(r["methods"][meth]["overall"]["rel"], want_rel, rel_tol=1e-5)
    assert r["methods"]["monostixels"]["compactness"] == 0


def test_predicted_bottoms_take_the_lowest_object_stixel():
    from types import SimpleNamespace

    st = SimpleNamespace(column_width=5, num_columns=3,
                         column=torch.tensor([0, 0, 0, 1, 1, 2]), type=torch.tensor([0, 1, 2, 0, 3, 0]),
                         v_bottom=torch.tensor([99, 60, 40, 99, 50, 99]))
    out = predicted_bottoms(st, torch.tensor([2.0, 7.0, 12.0]))
    assert out[0] == 60 and math.isnan(float(out[1])) and math.isnan(float(out[2]))
