"""Distillation of the real-image net (train/semantic.py): teacher pseudo-labels on unlabelled frames."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from monostixels._checks import InputError
from monostixels.core.classes import CLASS_NAMES, IGNORE_LABEL, NUM_CLASSES
from tests.test_camvid import CONF, SHARED, _write_camvid
from tests.test_semantic import _load_train_module

pytest.importorskip("onnxruntime")

IDS = {n: i for i, n in enumerate(CLASS_NAMES)}
KITTI2015 = SHARED / "data" / "kitti2015" / "training" / "image_2"
TEACHER_KITTI = SHARED / "models" / "espnetv2_cityscapes_384x1248.onnx"


def _split_teacher(image: torch.Tensor) -> torch.Tensor:
    """Road (p 0.9) in the left half, sky (p 0.6, unsure) in the right half."""
    _, h, w = image.shape
    probs = torch.full((NUM_CLASSES, h, w), 0.1 / (NUM_CLASSES - 1))
    probs[:, :, : w // 2] = 0.1 / (NUM_CLASSES - 1)
    probs[IDS["road"], :, : w // 2] = 0.9
    probs[:, :, w // 2:] = 0.4 / (NUM_CLASSES - 1)
    probs[IDS["sky"], :, w // 2:] = 0.6
    return probs


def _write_image(path: Path, h: int, w: int, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    cv2.imwrite(str(path), rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
    return path


def test_pseudo_labels_keep_confident_pixels_at_the_target_focal_length(tmp_path: Path) -> None:
    mod = _load_train_module()
    frame = mod.DistillFrame(_write_image(tmp_path / "a.png", 40, 80), 200.0, _split_teacher)
    data = mod.PseudoLabelled([frame], focal_px=100.0, confidence=0.7, repeat=3)
    assert len(data) == 3
    image, labels = data.load(2)
    # fx 200 -> 100 px: half size.
    assert image.shape == (20, 40, 3) and labels.shape == (20, 40)
    assert (labels[:, :18] == IDS["road"]).all()
    # Sky at p 0.6 < 0.7 teaches nothing.
    assert (labels[:, 22:] == IGNORE_LABEL).all()
    img_t, lab_t = data[1]
    assert img_t.shape == (3, 20, 40) and lab_t.dtype == torch.int64


def test_distillation_bad_input_fails_clearly(tmp_path: Path) -> None:
    mod = _load_train_module()
    good = mod.DistillFrame(_write_image(tmp_path / "a.png", 8, 8), 100.0, _split_teacher)
    with pytest.raises(InputError, match="no frames"):
        mod.PseudoLabelled([], focal_px=100.0, confidence=0.5)
    with pytest.raises(InputError, match="confidence"):
        mod.PseudoLabelled([good], focal_px=100.0, confidence=1.5)
    with pytest.raises(InputError, match="focal length fx"):
        mod.PseudoLabelled([mod.DistillFrame(good.path, 0.0, _split_teacher)], focal_px=100.0, confidence=0.5)
    (tmp_path / "broken.png").write_bytes(b"not an image")
    bad = mod.PseudoLabelled([mod.DistillFrame(tmp_path / "broken.png", 100.0, _split_teacher)],
                             focal_px=100.0, confidence=0.5)
    with pytest.raises(InputError, match="broken.png"):
        bad.load(0)
    wrong = mod.PseudoLabelled([mod.DistillFrame(good.path, 100.0, lambda im: torch.ones(3, 8, 8))],
                               focal_px=100.0, confidence=0.5)
    with pytest.raises(InputError, match="teacher scores"):
        wrong.load(0)
    cfg = {"teacher": {"mean": [0, 0, 0], "std": [1, 1, 1]},
           "sets": [{"glob": str(tmp_path / "nothing" / "*.png"), "fx": 100.0, "model": "m.onnx"}]}
    with pytest.raises(InputError, match=r"sets\[0\]\.glob: no file matches"):
        mod.distill_frames(cfg)


def test_training_with_distillation_draws_pseudo_labelled_frames(tmp_path: Path) -> None:
    """One epoch = CamVid train + `distill.per_epoch` frames labelled by an ONNX teacher."""
    from hydra import compose, initialize_config_dir

    mod = _load_train_module()
    _write_camvid(tmp_path / "camvid", n=4, size=(64, 96))
    # A tiny FCN-8s exported to ONNX plays the teacher (10 outputs: identity mapping).
    teacher = mod.fcn8s_vgg16(num_classes=NUM_CLASSES, width_mult=0.0625, batch_norm=True, fc_kernel=3, fc_channels=16)
    mod.export_onnx(teacher.eval(), tmp_path / "teacher.onnx", sample_size=(64, 96))
    (tmp_path / "frames").mkdir()
    for k in range(3):
        _write_image(tmp_path / "frames" / f"{k}.png", 48, 96, seed=k)
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="train_semantic_distill", overrides=[
            "model.width_mult=0.0625", "model.fc_channels=16", "model.init_from=null",
            f"data.camvid_root={tmp_path / 'camvid'}", "data.synthetic_per_epoch=0",
            f"data.cache={tmp_path / 'cache'}", "augment.crop=[64,64]", "train.epochs=1", "train.batch_size=2",
            "train.time_limit_s=null", "train.val_every=1", f"run_dir={tmp_path / 'run'}",
            "data.distill.per_epoch=4", "data.distill.repeat=2", "data.distill.focal_px=100", "data.distill.confidence=0.0",
            "data.distill.teacher.mean=[0,0,0]", "data.distill.teacher.std=[1,1,1]", "data.distill.teacher.mapping=null",
            "data.distill.teacher.pad_to=32",
            f"data.distill.sets=[{{glob: '{tmp_path / 'frames' / '*.png'}', fx: 100.0, "
            f"model: '{tmp_path / 'teacher.onnx'}', input_size: null}}]",
            "export.enabled=false",
        ])
    frames = mod.distill_frames(cfg.data.distill)
    assert [f.path.name for f in frames] == ["0.png", "1.png", "2.png"]
    result = mod.run(cfg)
    # 4 CamVid train images + 4 pseudo-labelled draws, batch 2: 4 steps (CamVid alone: 2).
    assert result["history"][0]["steps"] == 4
    assert 0.0 <= result["history"][0]["val_miou"] <= 1.0


@pytest.mark.skipif(not TEACHER_KITTI.is_file(), reason=f"{TEACHER_KITTI} absent (a user's model, shared)")
@pytest.mark.skipif(not KITTI2015.is_dir(), reason=f"{KITTI2015} absent (shared sample data)")
def test_shipped_distillation_config_labels_kitti_road() -> None:
    """The stage-2 config's teacher (20 outputs, background dropped) labels the road ahead as road."""
    mod = _load_train_module()
    cfg = OmegaConf.load(CONF / "train_semantic_distill.yaml").data.distill
    kitti = OmegaConf.create({**OmegaConf.to_container(cfg), "sets": [
        {**OmegaConf.to_container(cfg.sets[0]), "glob": str(KITTI2015 / "000000_10.png"), "model": str(TEACHER_KITTI)}]})
    frames = mod.distill_frames(kitti)
    data = mod.PseudoLabelled(frames, focal_px=float(cfg.focal_px), confidence=float(cfg.confidence))
    image, labels = data.load(0)
    # 1242 x 375 at fx 721.5, resized to the configured focal length.
    assert abs(image.shape[1] - 1242 * float(cfg.focal_px) / 721.5377) <= 1
    bottom = labels[-20:, image.shape[1] // 3: 2 * image.shape[1] // 3]
    assert (bottom == IDS["road"]).mean() > 0.8
    assert (labels == IGNORE_LABEL).mean() < 0.3


# --- Soft-target distillation (train/teacher_labels.py cache + data.soft in train/semantic.py) ---


def _teacher_module():
    import train.teacher_labels as tl

    return tl


def test_distill_loss_matches_hand_computed_cross_entropy_and_kl() -> None:
    """Two pixels: one with a hard label and soft targets, one with soft targets only; weights != 1."""
    mod = _load_train_module()
    torch.manual_seed(0)
    logits = torch.randn(1, NUM_CLASSES, 1, 2, dtype=torch.float64)
    p = torch.rand(1, NUM_CLASSES, 1, 2, dtype=torch.float64)
    p = p / p.sum(1, keepdim=True)
    labels = torch.tensor([[[3, IGNORE_LABEL]]])
    w = torch.linspace(0.5, 2.0, NUM_CLASSES, dtype=torch.float64)
    a = 0.3
    loss = mod.distill_loss(logits, labels, p, weight=w, soft_weight_labelled=a)
    # By hand, from the definitions.
    logq = torch.log_softmax(logits[0, :, 0], dim=0)  # (C, 2)
    pp = p[0, :, 0]
    kl = [float((pp[:, k] * (pp[:, k].log() - logq[:, k])).sum()) for k in range(2)]
    wp = [float((pp[:, k] * w).sum()) for k in range(2)]
    num = float(w[3]) * -float(logq[3, 0]) + a * wp[0] * kl[0] + wp[1] * kl[1]
    den = float(w[3]) + a * wp[0] + wp[1]
    assert float(loss) == pytest.approx(num / den, rel=1e-9)
    # Temperature T: T^2 KL between the tempered distributions.
    T = 2.0
    lossT = mod.distill_loss(logits[..., 1:], labels[..., 1:], p[..., 1:], temperature=T)
    pT = torch.softmax(pp[:, 1].log() / T, 0)
    qT = torch.log_softmax(logits[0, :, 0, 1] / T, 0)
    assert float(lossT) == pytest.approx(T * T * float((pT * (pT.log() - qT)).sum()), rel=1e-9)
    # Pixels without soft targets (all zero) and without labels contribute nothing.
    zero = torch.zeros_like(p)
    only_ce = mod.distill_loss(logits, labels, zero, weight=w)
    assert float(only_ce) == pytest.approx(-float(logq[3, 0]), rel=1e-9)


def test_soft_labels_round_trip_through_the_cache(tmp_path: Path) -> None:
    tl = _teacher_module()
    g = torch.Generator().manual_seed(1)
    probs = torch.softmax(3 * torch.randn(NUM_CLASSES, 7, 9, generator=g), 0)
    tl.save_entry(tmp_path / "a" / "x.npz", probs)
    back = tl.load_entry(tmp_path / "a" / "x.npz")
    assert back.shape == probs.shape
    # Each value is off by <= 1/510 before renormalisation; the sum by <= C/510.
    e, s = 1 / 510, NUM_CLASSES / 510
    assert float((back - probs).abs().max()) <= (e + s) / (1 - s)
    assert torch.allclose(back.sum(0), torch.ones(7, 9), atol=1e-5)
    assert torch.equal(back.argmax(0)[probs.max(0).values > 0.6], probs.argmax(0)[probs.max(0).values > 0.6])


def test_teacher_mapping_sums_probabilities_and_drops_background() -> None:
    tl = _teacher_module()
    logits = torch.zeros(4, 1, 1)
    logits[3] = 100.0  # the background takes no mass even when it wins
    out = tl.map_probabilities(logits, [IDS["road"], IDS["road"], IDS["sky"], -1])
    assert out.shape == (NUM_CLASSES, 1, 1)
    assert float(out[IDS["road"]]) == pytest.approx(2 / 3) and float(out[IDS["sky"]]) == pytest.approx(1 / 3)
    assert float(out.sum()) == pytest.approx(1.0)
    with pytest.raises(InputError, match="mapping"):
        tl.map_probabilities(logits, [0, 1])


def test_zoom_windows_lie_in_the_frame_and_letterbox_keeps_the_aspect() -> None:
    tl = _teacher_module()
    # KITTI-like 370 x 1226 into 384 x 1248: full scale ~1.018; zoom 2 -> ~181 x 602 windows.
    wins = tl.view_windows(370, 1226, (384, 1248), {"name": "zoom2", "zoom": 2.0, "columns": 2, "center_row": 0.3})
    assert [n for n, _ in wins] == ["zoom2_0", "zoom2_1"]
    s = min(384 / 370, 1248 / 1226)
    for _, (x0, y0, x1, y1) in wins:
        assert 0 <= x0 < x1 <= 1226 and 0 <= y0 < y1 <= 370
        assert abs((y1 - y0) - 384 / (2 * s)) <= 1 and abs((x1 - x0) - 1248 / (2 * s)) <= 1
    assert wins[0][1][0] == 0 and wins[1][1][2] == 1226
    # Centred on row 0.3 x 370 = 111 unless clipped at the top.
    y0, y1 = wins[0][1][1], wins[0][1][3]
    assert y0 == max(0, round(111 - (y1 - y0) / 2))
    assert tl.view_windows(50, 80, (64, 64), {"name": "full"}) == [("full", (0, 0, 80, 50))]
    img = np.full((50, 80, 3), 200, np.uint8)
    x, (h, w) = tl.letterbox(img, (64, 96))
    # 50 x 80 at min(64/50, 96/80) = 1.2 -> 60 x 96; rows below are padding.
    assert (h, w) == (60, 96) and x.shape == (64, 96, 3)
    assert np.allclose(x[:60], 200 / 255) and (x[60:] == 0).all()


def _write_manifest(tmp_path: Path, entries: list[tuple[str, int]], size: tuple[int, int] = (40, 64)) -> Path:
    tl = _teacher_module()
    img = _write_image(tmp_path / "img.png", *size)
    lines = []
    for k, (src, frame) in enumerate(entries):
        probs = torch.zeros(NUM_CLASSES, size[0] // 2, size[1] // 2)
        probs[IDS["road"], size[0] // 4:] = 1.0
        probs[IDS["sky"], : size[0] // 4] = 1.0
        npz = tmp_path / "cache" / f"{k}.npz"
        tl.save_entry(npz, probs)
        lines.append(tl.SoftEntry(f"{src}/{frame}/full", src, frame, "full", str(img), (0, 0, size[1], size[0]),
                                  100.0, str(npz)).to_json())
    lines.append('{"id": "torn')  # an interrupted write is skipped
    (tmp_path / "manifest.jsonl").write_text("\n".join(lines) + "\n")
    return tmp_path / "manifest.jsonl"


def test_holdout_frames_never_reach_the_training_list(tmp_path: Path) -> None:
    mod = _load_train_module()
    entries = [("kitti_0028", f) for f in range(1110, 1115)] + [("dashcam", f) for f in range(0, 12)] + [("camvid_val", 0)]
    manifest = _write_manifest(tmp_path, entries)
    cfg = {"manifest": str(manifest), "weights": {"kitti_0028": 1.0, "dashcam": 1.0, "camvid_val": 0.0},
           "holdout": [{"source": "kitti_0028"}, {"source": "dashcam", "frames": [6, 1000]}]}
    train, out = mod.soft_entries(cfg)
    assert {(e.source, e.frame) for e in train} == {("dashcam", f) for f in range(6)}
    assert {(e.source, e.frame) for e in out} == {("kitti_0028", f) for f in range(1110, 1115)} | \
        {("dashcam", f) for f in range(6, 12)}
    # Draws by source weight: a zero-weight source is never drawn, the share follows the weights.
    g = torch.Generator().manual_seed(0)
    both, _ = mod.soft_entries({**cfg, "holdout": [], "weights": {"kitti_0028": 3.0, "dashcam": 1.0}})
    picks = mod.soft_draw(both, {"kitti_0028": 3.0, "dashcam": 1.0}, 0.0, 4000, g)
    share = np.mean([both[j].source == "kitti_0028" for j in picks])
    assert 0.72 < share < 0.78


def test_void_below_removes_the_teacher_from_the_bottom_rows_of_its_source_only(tmp_path: Path) -> None:
    """``void_below`` zeroes the teacher's probabilities at and below its row of the frame (a window
    keeps the frame's rows), for the sources it names; other sources and the labels are untouched."""
    mod = _load_train_module()
    manifest = _write_manifest(tmp_path, [("dashcam", 0), ("kitti_0028", 1110)], size=(40, 64))
    entries, _ = mod.soft_entries({"manifest": str(manifest), "weights": {"dashcam": 1.0, "kitti_0028": 1.0}})
    tl = _teacher_module()
    # A window of the lower half of the frame (rows 20-39): the limit at 0.75 is its row 10.
    e = entries[0]
    window = tl.SoftEntry(e.id + "_low", e.source, e.frame, "low", e.image, (0, 20, 64, 40), e.fx, e.probs)
    data = mod.SoftLabelled([*entries, window], focal_px=100.0, void_below={"dashcam": 0.75})
    _, _, full = data.load(0)
    mass = full.sum(0)
    assert full.shape[1] == 40
    assert torch.all(mass[30:] == 0) and torch.all(mass[:30] > 0.99)
    _, _, other = data.load(1)
    assert torch.all(other.sum(0) > 0.99)
    _, _, low = data.load(2)
    assert torch.all(low.sum(0)[10:] == 0) and torch.all(low.sum(0)[:10] > 0)
    with pytest.raises(InputError, match="void_below.dashcam"):
        mod.SoftLabelled(entries, focal_px=100.0, void_below={"dashcam": 1.5})


def test_soft_targets_follow_the_augmented_geometry(tmp_path: Path) -> None:
    """Soft one-hot targets made from the labels stay aligned with them through scale, rotation,
    vertical shift, crop and flip; padded areas carry neither labels nor teacher mass."""
    mod = _load_train_module()
    h, w = 60, 90
    lab = torch.zeros(h, w, dtype=torch.int64)
    lab[:, 30:] = IDS["building"]
    lab[40:, :] = IDS["road"]
    lab[10:20, 60:70] = IDS["person"]
    soft = F_one_hot(lab)
    image = torch.rand(3, h, w)
    aug = {"scale_jitter": [0.5, 2.0], "rotate_deg": 8.0, "vshift": 0.3, "crop": [48, 64], "hflip": 0.5,
           "brightness": 0.3, "contrast": 0.3, "saturation": 0.3, "channel_gain": 0.1, "gamma": [0.7, 1.4],
           "blur_prob": 0.5, "blur_sigma": [0.3, 1.0], "jpeg_prob": 0.5, "jpeg_quality": [30, 90],
           "noise_std": [0.0, 0.03]}
    for seed in range(12):
        g = torch.Generator().manual_seed(seed)
        im, lb, sf = mod.augment_soft(image, lab, soft, g, aug)
        assert im.shape == (3, 48, 64) and lb.shape == (48, 64) and sf.shape == (NUM_CLASSES, 48, 64)
        assert 0 <= float(im.min()) and float(im.max()) <= 1
        sure = (sf.max(0).values > 0.99) & (lb != IGNORE_LABEL)
        assert (sf.argmax(0)[sure] == lb[sure]).float().mean() > 0.99
        # Where the labels are padding (ignore), the teacher has (almost) no mass.
        pad = lb == IGNORE_LABEL
        if pad.any():
            assert float(sf.sum(0)[pad].mean()) < 0.2


def F_one_hot(lab: torch.Tensor) -> torch.Tensor:
    """(H, W) ids -> (10, H, W) float one-hot."""
    return torch.nn.functional.one_hot(lab, NUM_CLASSES).permute(2, 0, 1).float()


def test_teacher_cache_and_soft_training_end_to_end(tmp_path: Path) -> None:
    """The cache over two image sources (one with a zoom view) is resumable; one epoch of data.soft
    training draws only non-held-out windows."""
    from hydra import compose, initialize_config_dir

    mod, tl = _load_train_module(), _teacher_module()
    _write_camvid(tmp_path / "camvid", n=4, size=(64, 96))
    teacher = mod.fcn8s_vgg16(num_classes=NUM_CLASSES, width_mult=0.0625, batch_norm=True, fc_kernel=3, fc_channels=16)
    mod.export_onnx(teacher.eval(), tmp_path / "teacher.onnx", sample_size=(64, 96))
    for src in ("a", "b"):
        (tmp_path / src).mkdir()
        for k in range(3):
            _write_image(tmp_path / src / f"{k:04d}.png", 48, 96, seed=k)
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        tcfg = compose(config_name="teacher_labels", overrides=[
            f"out={tmp_path / 'cache'}", "teacher.mean=[0,0,0]", "teacher.std=[1,1,1]",
            f"teacher.mapping={list(range(NUM_CLASSES))}",
            f"sources=[{{name: a, kind: images, glob: '{tmp_path / 'a' / '*.png'}', fx: 100.0, model: '{tmp_path / 'teacher.onnx'}', input_size: [64, 96], views: [full, zoom2]}},"
            f"{{name: b, kind: images, glob: '{tmp_path / 'b' / '*.png'}', fx: 100.0, model: '{tmp_path / 'teacher.onnx'}', input_size: [64, 96]}}]",
        ])
    first = tl.run(OmegaConf.merge(tcfg, {"limit": 4}))
    assert first["new"] == 4
    rest = tl.run(tcfg)
    # a: 3 full + 3 x 2 zoom windows; b: 3 full. The resumed run adds only the missing ones.
    assert rest["total"] == 12 and rest["new"] == 8
    entries = tl.read_manifest(tmp_path / "cache" / "manifest.jsonl")
    assert len(entries) == 12
    e = next(x for x in entries if x.view == "zoom2_1")
    p = tl.load_entry(e.probs)
    # The window is letterboxed into 64 x 96 at 2x the full view's scale; stored at half that.
    x0, y0, x1, y1 = e.box
    s = 2 * min(64 / 48, 96 / 96)
    assert abs(p.shape[1] - (y1 - y0) * s / 2) <= 1 and abs(p.shape[2] - (x1 - x0) * s / 2) <= 1
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="train_semantic_soft", overrides=[
            "model.width_mult=0.0625", "model.fc_channels=16", "model.init_from=null",
            f"data.camvid_root={tmp_path / 'camvid'}", f"data.cache={tmp_path / 'synth'}",
            "augment.crop=[32,64]", "train.epochs=2", "train.batch_size=2", "train.time_limit_s=null",
            "train.val_every=1", f"run_dir={tmp_path / 'run'}", "export.sample_size=[64,96]",
            f"data.soft.manifest={tmp_path / 'cache' / 'manifest.jsonl'}", "data.soft.per_epoch=6",
            "data.soft.default_weight=1.0", "data.soft.focal_px=100", "data.soft.weight_sample=4",
            "data.soft.holdout=[{source: b, frames: [1, 3]}]",
        ])
    train, out = mod.soft_entries(cfg.data.soft)
    assert len(train) == 10 and {(x.source, x.frame) for x in out} == {("b", 1), ("b", 2)}
    result = mod.run(cfg)
    assert result["history"][0]["steps"] == 3
    assert np.isfinite(result["history"][0]["loss"]) and 0.0 <= result["history"][0]["val_miou"] <= 1.0
    # The export (run_dir/export.*) records the soft-label data and the holdout in its metadata.
    _, meta = mod.load_fcn8s(result["pt"])
    assert "soft labels" in meta["data"] and "'source': 'b'" in meta["data"]
    assert Path(result["onnx"]).is_file() and 0.0 <= result["val_miou_onnx"] <= 1.0
    # export.checkpoint=final (the config's): the exported weights are those at the end of the
    # schedule (epoch 2, the resume state's), whichever epoch had the best validation mIoU.
    assert result["epoch"] == 2 and len(result["history"]) == 2
    exported, _ = mod.load_fcn8s(result["pt"])
    last = torch.load(tmp_path / "run" / "last.pt", map_location="cpu", weights_only=True)["model"]
    for k, v in exported.state_dict().items():
        if v.is_floating_point():
            torch.testing.assert_close(v, last[k].half().float() if cfg.export.half_pt else last[k], rtol=0, atol=0)
    with pytest.raises(InputError, match="export.checkpoint"):
        mod.run(OmegaConf.merge(cfg, {"export": {"checkpoint": "latest"}, "resume": True}))


def test_augment_at_scale_one_is_an_exact_crop_and_flip() -> None:
    """Without rotation and at scale 1 the warp is a plain crop (bilinear at pixel centres is exact)."""
    mod = _load_train_module()
    g0 = torch.Generator().manual_seed(3)
    image = torch.rand(3, 30, 50, generator=g0)
    labels = torch.randint(0, NUM_CLASSES, (30, 50), generator=g0)
    soft = F_one_hot(labels) * 0.5 + 0.05
    aug = {"scale_jitter": [1.0, 1.0], "crop": [20, 24], "hflip": 0.5, "brightness": 0.0, "contrast": 0.0,
           "saturation": 0.0, "channel_gain": 0.0, "gamma": [1.0, 1.0], "blur_prob": 0.0, "blur_sigma": [1, 1],
           "noise_std": [0.0, 0.0]}
    found = set()
    for seed in range(10):
        _, lb, sf = mod.augment_soft(image, labels, soft, torch.Generator().manual_seed(seed), aug)
        im, lb2 = mod.augment(image, labels, torch.Generator().manual_seed(seed), aug)
        assert torch.equal(lb, lb2)
        hits = [(y, x, f) for y in range(11) for x in range(27) for f in (False, True)
                if torch.equal((labels.flip(-1) if f else labels)[y:y + 20, x:x + 24] if not f else
                               labels[y:y + 20, x:x + 24].flip(-1), lb)]
        assert hits, f"seed {seed}: not a crop"
        y, x, f = hits[0]
        ref = image[:, y:y + 20, x:x + 24]
        ref = ref.flip(-1) if f else ref
        assert torch.allclose(im, ref, atol=1e-5)
        sref = soft[:, y:y + 20, x:x + 24]
        assert torch.allclose(sf, sref.flip(-1) if f else sref, atol=1e-5)
        found.add(f)
    assert found == {False, True}


def test_loso_teacher_agreement_of_the_teacher_itself_is_one(tmp_path: Path) -> None:
    """benchmarks.distill_loso: a student that is the teacher (same weights, the window at the
    teacher's scale) agrees with the cache on (nearly) every pixel; a different net does not."""
    from hydra import compose, initialize_config_dir

    from benchmarks.distill_loso import teacher_agreement

    mod, tl = _load_train_module(), _teacher_module()
    torch.manual_seed(0)
    net = mod.fcn8s_vgg16(num_classes=NUM_CLASSES, width_mult=0.0625, batch_norm=True, fc_kernel=3, fc_channels=16).eval()
    arch = {"num_classes": NUM_CLASSES, "width_mult": 0.0625, "batch_norm": True, "fc_kernel": 3, "fc_channels": 16}
    mod.export_onnx(net, tmp_path / "teacher.onnx", sample_size=(64, 96))
    mod.save_fcn8s(net, tmp_path / "same.pt", arch=arch)
    (tmp_path / "a").mkdir()
    for k in range(2):
        _write_image(tmp_path / "a" / f"{k:04d}.png", 64, 96, seed=k)
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        tcfg = compose(config_name="teacher_labels", overrides=[
            f"out={tmp_path / 'cache'}", "teacher.mean=[0,0,0]", "teacher.std=[1,1,1]", "downsample=1",
            f"teacher.mapping={list(range(NUM_CLASSES))}",
            f"sources=[{{name: a, kind: images, glob: '{tmp_path / 'a' / '*.png'}', fx: 50.0, "
            f"model: '{tmp_path / 'teacher.onnx'}', input_size: [64, 96]}}]",
        ])
    tl.run(tcfg)
    entries = tl.read_manifest(tmp_path / "cache" / "manifest.jsonl")
    same = teacher_agreement(tmp_path / "same.pt", entries, focal_px=50.0)
    assert set(same) == {"a"} and same["a"]["entries"] == 2
    assert same["a"]["agreement"] > 0.98
    # Another net: the same one with the scores of a class the teacher rarely picks raised.
    rare = int(torch.bincount(tl.load_entry(entries[0].probs).argmax(0).flatten(), minlength=NUM_CLASSES).argmin())
    with torch.no_grad():
        for prm in net.parameters():
            if prm.shape == (NUM_CLASSES,):
                prm[rare] += 20.0
    mod.save_fcn8s(net, tmp_path / "other.pt", arch=arch)
    diff = teacher_agreement(tmp_path / "other.pt", entries, focal_px=50.0)
    assert diff["a"]["agreement"] < 0.5 < same["a"]["agreement"]


def test_loso_teacher_agreement_leaves_out_the_void_rows(tmp_path: Path, monkeypatch) -> None:
    """benchmarks.distill_loso compares nothing below ``void_below`` of the frame (the rows training gives
    the teacher no say in): a student that disagrees there only agrees fully once they are left out."""
    import monostixels.inputs.semantic as semantic_mod
    from benchmarks.distill_loso import teacher_agreement

    class SkyEverywhere:
        def __init__(self, weights: object) -> None:
            pass

        def __call__(self, rgb: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
            probs = torch.zeros(NUM_CLASSES, *rgb.shape[-2:])
            probs[IDS["sky"]] = 1.0
            return probs

    monkeypatch.setattr(semantic_mod, "TorchSegmenter", SkyEverywhere)
    # The cached teacher: sky over the top half of each 40x64 frame, road below.
    manifest = _write_manifest(tmp_path, [("dashcam", 0), ("dashcam", 1)])
    entries = _teacher_module().read_manifest(manifest)
    whole = teacher_agreement("unused.pt", entries, focal_px=100.0)
    assert whole["dashcam"]["agreement"] == pytest.approx(0.5)
    top = teacher_agreement("unused.pt", entries, focal_px=100.0, void_below={"dashcam": 0.5})
    assert top["dashcam"]["agreement"] == pytest.approx(1.0) and top["dashcam"]["entries"] == 2
    other = teacher_agreement("unused.pt", entries, focal_px=100.0, void_below={"kitti_0028": 0.5})
    assert other["dashcam"]["agreement"] == pytest.approx(0.5)


@pytest.mark.parametrize("module, override, named", [
    ("train.semantic", "data.soft.manifest={tmp}/nowhere/manifest.jsonl", "nowhere/manifest.jsonl"),
    ("train.teacher_labels", "sources=[{{name: x, kind: images, glob: '{tmp}/none/*.png', fx: 500.0, model: m.onnx}}]", "none/"),
    ("train.quantize_semantic", "calibration.root={tmp}/no_camvid", "no_camvid/train"),
    ("train.flow", "crop=[100,200]", "crop: both sides must be multiples"),
    ("train.priors", "data.frames=many", "data.frames: expected an integer, got 'many'"),
])
def test_training_entry_points_end_a_bad_input_with_one_line_naming_it(tmp_path: Path, module: str, override: str,
                                                                       named: str) -> None:
    import subprocess
    import sys

    args = [sys.executable, "-m", module, override.format(tmp=tmp_path), f"hydra.run.dir={tmp_path / 'hydra'}"]
    if module == "train.semantic":
        args[3:3] = ["--config-name", "train_semantic_soft"]
    else:  # where each would write, were the input good
        args.append({"train.teacher_labels": f"out={tmp_path / 'cache'}", "train.quantize_semantic": f"dst={tmp_path / 'q.onnx'}",
                     "train.flow": f"run_dir={tmp_path / 'flow'}", "train.priors": f"out={tmp_path / 'priors.yaml'}"}[module])
    p = subprocess.run(args, cwd=CONF.parent, capture_output=True, text=True, timeout=300)
    assert p.returncode == 1
    err = [line for line in p.stderr.splitlines() if line.strip() and "WARNING" not in line]
    assert len(err) == 1 and err[0].startswith(f"{module}: error: ") and named in err[0], p.stderr[-2000:]
    assert "Traceback" not in p.stderr
