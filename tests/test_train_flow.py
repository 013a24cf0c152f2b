"""RAFT training (train/flow.py): targets of both directions, augmentation, a short run that learns, resume."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from monostixels.data.synthetic import render_pair
from train.flow import _render_sample, augment, real_pool, sequence_loss

REPO = Path(__file__).resolve().parents[1]
KITTI2015 = REPO.parent / "shared" / "data" / "kitti2015"


def _warp(prev: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    H, W = flow.shape[-2:]
    vv, uu = torch.meshgrid(torch.arange(H).float(), torch.arange(W).float(), indexing="ij")
    grid = torch.stack([(uu + flow[0]) / (W - 1) * 2 - 1, (vv + flow[1]) / (H - 1) * 2 - 1], -1)[None]
    return torch.nn.functional.grid_sample(prev[None], grid, align_corners=True)[0]


def test_both_directions_of_a_render_are_photometrically_consistent():
    fwd, bwd = _render_sample(20 * 100_000 + 3, 0.25, None)
    for cur, prev, flow, valid in (fwd, bwd):
        cur, prev = cur.float() / 255, prev.float() / 255
        err = (_warp(prev, flow.float()) - cur).abs().mean(0)[valid]
        assert valid.float().mean() > 0.3
        assert float(err.median()) < 0.02  # 8-bit images, sub-pixel splatting of the reverse flow
    # The forward target is the renderer's flow, stored as float16 (half a unit of the last place: 8e-3 px at 16 px).
    p = render_pair(20 * 100_000 + 3, scale=0.25)
    assert torch.allclose(fwd[2].float(), p.gt.flow, atol=1e-2)


def test_augmentation_keeps_flow_and_images_consistent():
    sample = _render_sample(20 * 100_000 + 4, 0.35, None)[0]
    gen = torch.Generator().manual_seed(1)
    aug = {"scale_log2": [0.2, 0.4], "colour": 0.0, "asym_prob": 0.0, "eraser_prob": 0.0}
    a, b, f, v = augment(sample, (128, 256), gen, aug)
    assert a.shape == (3, 128, 256) and f.shape == (2, 128, 256) and v.dtype == torch.bool
    err = (_warp(b, f) - a).abs().mean(0)[v]
    assert float(err.median()) < 0.03  # scaled, cropped (maybe flipped): still consistent


def test_real_pool_never_takes_the_lidar_evaluation_drive(tmp_path):
    cfg = OmegaConf.create({"run_dir": str(tmp_path), "crop": [128, 256], "real": {
        "sources": [{"name": "kitti_raw", "root": "../shared/data/kitti_raw_lidar"}], "focal_px": 360.0, "max_fb_px": 0.5}})
    with pytest.raises(ValueError, match="evaluation drive"):
        real_pool(cfg)


@pytest.mark.skipif(not (REPO.parent / "shared" / "data" / "kitti_raw").is_dir(), reason="shared KITTI raw sample absent")
def test_calibration_pairs_are_the_real_sources_at_the_running_scale():
    from train.flow import calibration_pairs

    root = str(REPO.parent / "shared" / "data" / "kitti_raw")
    cfg = OmegaConf.create({"export": {"calibration_per_source": 2, "calibration_scale": 0.5},
                            "real": {"sources": [{"name": "kitti_raw", "root": root, "step": 1}]}})
    pairs = calibration_pairs(cfg)
    from monostixels.build import build_source

    H, W = next(iter(build_source({"name": "kitti_raw", "root": root, "step": 1}))).size
    assert len(pairs) == 2 and all(a.shape == b.shape == (3, round(H / 2), round(W / 2)) for a, b in pairs)
    assert all(0 <= float(a.min()) and float(a.max()) <= 1 and not torch.equal(a, b) for a, b in pairs)
    cfg.real.sources = [{"name": "kitti_raw", "root": "../shared/data/kitti_raw_lidar"}]
    with pytest.raises(ValueError, match="evaluation drive"):
        calibration_pairs(cfg)


def test_sequence_loss_weights_later_updates_more():
    flow = torch.zeros(1, 2, 4, 4)
    valid = torch.ones(1, 4, 4, dtype=torch.bool)
    preds = [torch.ones(1, 2, 4, 4), torch.zeros(1, 2, 4, 4)]
    loss, epe = sequence_loss(preds, flow, valid, gamma=0.8, max_flow=400.0)
    assert float(loss) == pytest.approx(0.8 * 2.0) and epe == 0.0


@pytest.mark.slow
def test_a_short_training_run_lowers_the_loss_and_resumes(tmp_path):
    """A few steps on tiny renders (no real frames): the loss falls and the EPE on one of the scenes falls
    below the initial weights'; a second run resumes from the checkpoint."""
    from monostixels.inputs.raft import build_raft
    from train.flow import validate

    args = [sys.executable, "-m", "train.flow", f"run_dir={tmp_path}", "synthetic.pairs=4", "synthetic.shard=2",
            "synthetic.scale=0.35", "crop=[128,256]", "batch_size=2", "train_updates=3", "val.pairs=1", "val.every=60",
            "val.updates=3", "val.source_seed=20", "ckpt_every=5", "threads=1", "augment.colour=0",
            "augment.eraser_prob=0", "augment.scale_log2=[0,0]", "stages=[{steps: 60, lr: 6e-4, warmup: 2, real_fraction: 0.0}]",
            f"out_weights={tmp_path / 'w.pt'}", f"export.onnx={tmp_path / 'w.onnx'}", "export.updates=2", "max_minutes=null"]
    # The INT8 copy is calibrated on the real frames: one KITTI 2015 pair, small, where the samples are.
    int8 = KITTI2015.is_dir()
    args += ([f"real.sources=[{{name: kitti2015, root: {KITTI2015}, fx: 721.5, fy: 721.5, cx: 609.6, cy: 172.9}}]",
              "export.calibration_per_source=1", "export.calibration_scale=0.3"] if int8 else ["export.int8=false"])
    p = subprocess.run(args, cwd=REPO, capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-3000:]
    ck = torch.load(tmp_path / "ckpt.pt", weights_only=False)
    assert ck["step"] == 60 and len(ck["history"]) == 60
    # The same initial weights (train.flow seeds torch with cfg.seed before building the net) on the
    # validation pair (here a training scene: the run is to learn it) against the trained ones.
    torch.manual_seed(0)
    pairs = torch.load(next((tmp_path / "pool").glob("val_*.pt")), weights_only=True)
    before = validate(build_raft("small"), pairs, 3)
    after = ck["val_history"][-1][1]
    assert after < 0.95 * before
    losses = [h[1] for h in ck["history"]]
    assert sum(losses[-10:]) < 0.9 * sum(losses[:10])  # random crops: noisy, so averaged
    assert (tmp_path / "w.pt").is_file() and (tmp_path / "w.onnx").is_file()
    if int8:
        from monostixels.inputs.raft import OnnxRaft

        assert OnnxRaft(tmp_path / "w_int8.onnx").quantized == "int8"
    # Resume: more steps continue from the checkpoint (no restart from step 0); no second export.
    (tmp_path / "w.onnx").unlink()
    args2 = [a if not a.startswith("stages=") else "stages=[{steps: 64, lr: 6e-4, warmup: 2, real_fraction: 0.0}]" for a in args]
    p = subprocess.run(args2 + ["export.onnx=null"], cwd=REPO, capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-3000:]
    assert "no ONNX export" in p.stdout + p.stderr and not (tmp_path / "w.onnx").exists()
    ck2 = torch.load(tmp_path / "ckpt.pt", weights_only=False)
    assert ck2["step"] == 64 and len(ck2["history"]) == 64 and ck2["history"][:60] == ck["history"]


def test_the_convex_upsampler_alone_trains_on_a_frozen_body(tmp_path):
    """trainable=mask_predictor on a trained body without the head (the shipped RAFT-small's): the head
    starts from scratch and learns (validation EPE below the untrained head's), every other tensor is
    the initial weights' bit for bit, and the weights written load as RAFT-small with the head."""
    from monostixels.inputs.raft import build_raft, load_raft_weights, mask_hidden_of
    from train.flow import validate

    shipped = load_raft_weights(REPO / "models" / "raft_small.pt").state_dict()
    init = {k: v for k, v in shipped.items() if not k.startswith("mask_predictor.")}
    torch.save(init, tmp_path / "init.pt")
    args = [sys.executable, "-m", "train.flow", f"run_dir={tmp_path}", "synthetic.pairs=4", "synthetic.shard=2",
            "synthetic.scale=0.35", "crop=[128,256]", "batch_size=2", "train_updates=3", "val.pairs=1", "val.every=100",
            "val.updates=3", "val.source_seed=20", "ckpt_every=10", "threads=1", "augment.colour=0",
            "augment.eraser_prob=0", "augment.scale_log2=[0,0]", "stages=[{steps: 40, lr: 2e-3, warmup: 2, real_fraction: 0.0}]",
            "mask_hidden=16", "trainable=mask_predictor", f"init_weights={tmp_path / 'init.pt'}",
            f"out_weights={tmp_path / 'w.pt'}", "export.onnx=null", "max_minutes=null"]
    p = subprocess.run(args, cwd=REPO, capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-3000:]
    assert "convex upsampler from scratch" in p.stdout + p.stderr
    ck = torch.load(tmp_path / "ckpt.pt", weights_only=False)
    body = {k: v for k, v in ck["model"].items() if not k.startswith("mask_predictor.")}
    assert body.keys() == init.keys() and all(torch.equal(body[k], init[k].float()) for k in init)
    assert mask_hidden_of(ck["model"]) == 16
    # The untrained head (train.flow seeds torch with cfg.seed before it builds the net) on the same body.
    torch.manual_seed(0)
    untrained = build_raft("small", 16)
    untrained.load_state_dict(init, strict=False)
    pairs = torch.load(next((tmp_path / "pool").glob("val_*.pt")), weights_only=True)
    assert ck["val_history"][-1][1] < 0.95 * validate(untrained, pairs, 3)
    net = load_raft_weights(tmp_path / "w.pt")
    assert net.mask_predictor is not None and mask_hidden_of(net.state_dict()) == 16
    # Initial weights that do not fit the body are refused, not half-loaded.
    torch.save(build_raft("large").state_dict(), tmp_path / "large.pt")
    bad = [a if not a.startswith("init_weights=") else f"init_weights={tmp_path / 'large.pt'}" for a in args]
    p = subprocess.run(bad + [f"run_dir={tmp_path / 'bad'}"], cwd=REPO, capture_output=True, text=True, timeout=900)
    assert p.returncode != 0 and "large.pt" in p.stdout + p.stderr


@pytest.mark.slow
def test_device_chunks_stop_on_time_save_and_resume(tmp_path):
    """train/device_prepare.sh + train/device_chunk.sh, as the accelerator machine runs them, here on the
    CPU (device=cpu; bf16 autocast as on the GPU): each chunk stops after its minutes, its checkpoint
    lands in $OUT, and the next chunk, prepared from it, goes on from its step. Asking for CUDA where
    there is none is a clear error."""
    import os

    env = {**os.environ, "PYTHON": sys.executable, "PYTHONPATH": str(REPO), "OUT": str(tmp_path / "out")}
    root = tmp_path / "root"  # the device machine's checkout: the scripts work in the current directory
    root.mkdir()
    tiny = ["synthetic.pairs=4", "synthetic.shard=2", "synthetic.scale=0.35", "crop=[128,256]", "batch_size=2",
            "train_updates=2", "val.pairs=1", "val.every=100000", "val.updates=2", "val.source_seed=20", "ckpt_every=1000",
            "threads=1", "stages=[{steps: 100000, lr: 2e-4, warmup: 2, real_fraction: 0.0}]"]

    def chunk(*extra: str) -> subprocess.CompletedProcess:
        return subprocess.run(["bash", str(REPO / "train" / "device_chunk.sh"), "0.1", *extra], cwd=root, env=env,
                              capture_output=True, text=True, timeout=600)

    run = tmp_path / "run"  # where this machine keeps the checkpoints that came back
    steps = []
    for _ in range(2):
        p = subprocess.run(["bash", str(REPO / "train" / "device_prepare.sh"), str(run)], cwd=root, env=env,
                           capture_output=True, text=True, timeout=120)
        assert p.returncode == 0, p.stderr
        assert (root / ".device" / "site" / "hydra").is_dir() and (root / ".device" / "site" / "omegaconf").is_dir()
        p = chunk("device=cpu", *tiny)
        log = (tmp_path / "out" / "train.log").read_text()
        assert p.returncode == 0, log[-3000:]
        assert "time limit of 0.1 minutes reached" in log
        ck = torch.load(tmp_path / "out" / "ckpt.pt", weights_only=False)
        assert ck["config"]["amp"] == "bf16" and all(v.dtype != torch.bfloat16 for v in ck["model"].values())
        assert all(torch.isfinite(torch.tensor(h[1])) for h in ck["history"])
        steps.append(ck["step"])
        if len(steps) == 2:
            assert ck["history"][:steps[0]] == first["history"]
        first = ck
        run.mkdir(exist_ok=True)
        (run / "ckpt.pt").write_bytes((tmp_path / "out" / "ckpt.pt").read_bytes())
    assert 0 < steps[0] < steps[1]
    # device=cuda (the script's own) on a machine without CUDA.
    if not torch.cuda.is_available():
        p = chunk(*tiny)
        assert p.returncode != 0 and "torch sees no CUDA device" in (tmp_path / "out" / "train.log").read_text()
