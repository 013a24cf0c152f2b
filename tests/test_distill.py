"""Distillation of the real-image net (train/semantic.py): teacher pseudo-labels on unlabelled frames."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from monostixels._checks import InputError
from monostixels.classes import CLASS_NAMES, IGNORE_LABEL, NUM_CLASSES
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
