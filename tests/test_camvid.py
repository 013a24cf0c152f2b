"""CamVid: loader and label mapping, semantic-only evaluation, the real-image net, a user's
Cityscapes model with a background channel, and training on a CamVid-layout folder."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from monostixels._checks import InputError
from monostixels.core.classes import CLASS_NAMES, IGNORE_LABEL, NUM_CLASSES
from monostixels.data.camvid import (
    CAMVID_CLASSES,
    CAMVID_CLASSES_PRESENT,
    CAMVID_TO_OURS,
    CAMVID_VOID,
    CamVidSource,
    map_camvid_labels,
    read_camvid_split,
)
from monostixels.data.base import FramePair
from monostixels.eval.semantic import evaluate_semantics, image_pair
from monostixels.core.geometry import Camera
from monostixels.inputs.semantic import CITYSCAPES19_MAPPING, estimate_semantics, fcn8s_scale
from monostixels.pipeline import load_config
from tests.test_semantic import _load_train_module

ort = pytest.importorskip("onnxruntime")

REPO = Path(__file__).resolve().parents[1]
CONF = REPO / "conf"
SHARED = REPO.parent / "shared"
CAMVID = SHARED / "data" / "camvid"
CITYSCAPES_KITTI = SHARED / "models" / "espnetv2_cityscapes_384x1248.onnx"
KITTI_FRAME = SHARED / "data" / "kitti_raw" / "2011_09_30" / "2011_09_30_drive_0028_sync" / "image_02" / "data" / "0000001110.jpg"
REAL_ONNX = REPO / "models" / "fcn8s_real.onnx"
REAL_PT = REPO / "models" / "fcn8s_real.pt"
IDS = {n: i for i, n in enumerate(CLASS_NAMES)}


def test_label_mapping_by_name() -> None:
    # Every CamVid class by name, including the merges the module documents.
    expected = {"sky": "sky", "building": "building", "pole": "pole", "road": "road", "pavement": "sidewalk",
                "tree": "vegetation", "sign_symbol": "pole", "fence": "building", "car": "vehicle",
                "pedestrian": "person", "bicyclist": "two_wheeler"}
    assert [CLASS_NAMES[CAMVID_TO_OURS[i]] for i in range(len(CAMVID_CLASSES))] == \
        [expected[n] for n in CAMVID_CLASSES]
    assert IDS["terrain"] not in CAMVID_CLASSES_PRESENT and len(CAMVID_CLASSES_PRESENT) == 9
    raw = np.array([[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, CAMVID_VOID]], dtype=np.uint8)
    out = map_camvid_labels(raw)
    assert out.dtype == np.uint8
    assert out.tolist() == [[IDS["sky"], IDS["building"], IDS["pole"], IDS["road"]],
                            [IDS["sidewalk"], IDS["vegetation"], IDS["pole"], IDS["building"]],
                            [IDS["vehicle"], IDS["person"], IDS["two_wheeler"], IGNORE_LABEL]]


def test_label_values_outside_mapping_fail() -> None:
    with pytest.raises(InputError, match=r"lab\.png.*outside.*e\.g\. 12"):
        map_camvid_labels(np.array([[0, 12], [3, 11]], dtype=np.uint8), name="lab.png")
    with pytest.raises(InputError, match="single-channel"):
        map_camvid_labels(np.zeros((4, 4, 3), dtype=np.uint8), name="rgb.png")
    with pytest.raises(InputError, match="outside"):
        map_camvid_labels(np.array([[-1, 0]], dtype=np.int16))


# --- a CamVid-layout folder written by the tests --------------------------------------------------

#: CamVid value -> grey level of the image: the test segmenter reads the class back from it.
def _grey(camvid_value: int) -> int:
    return 20 * CAMVID_TO_OURS[camvid_value] + 10 if camvid_value < CAMVID_VOID else 0


def _write_camvid(root: Path, n: int = 3, size: tuple[int, int] = (48, 64), seed: int = 0) -> list[np.ndarray]:
    """Write train/val/test splits of ``n`` images each; image grey level encodes our class."""
    rng = np.random.default_rng(seed)
    labels_all = []
    for split in ("train", "val", "test"):
        (root / split).mkdir(parents=True)
        (root / f"{split}annot").mkdir()
        lines = []
        for i in range(n):
            lab = rng.integers(0, CAMVID_VOID + 1, size=(size[0] // 8, size[1] // 8)).repeat(8, 0).repeat(8, 1)
            lab = lab.astype(np.uint8)
            img = np.vectorize(_grey)(lab).astype(np.uint8)
            cv2.imwrite(str(root / split / f"f{i:03d}.png"), np.repeat(img[..., None], 3, axis=2))
            cv2.imwrite(str(root / f"{split}annot" / f"f{i:03d}.png"), lab)
            # The SegNet lists carry their authors' absolute paths: only the last two parts count.
            lines.append(f"/SegNet/CamVid/{split}/f{i:03d}.png /SegNet/CamVid/{split}annot/f{i:03d}.png")
            if split == "test":
                labels_all.append(lab)
        (root / f"{split}.txt").write_text("\n".join(lines) + "\n")
    return labels_all


def test_read_split_and_load(tmp_path: Path) -> None:
    labels = _write_camvid(tmp_path, n=2)
    items = read_camvid_split(tmp_path, "test")
    assert [it.name for it in items] == ["f000", "f001"]
    img, lab = items[1].load()
    assert img.shape == (48, 64, 3) and lab.shape == (48, 64)
    np.testing.assert_array_equal(lab, map_camvid_labels(labels[1]))
    src = CamVidSource(tmp_path, split="test", frames=1)
    assert len(src) == 1
    image, lab_t = CamVidSource.to_tensors(*src[0].load())
    assert image.shape == (3, 48, 64) and lab_t.dtype == torch.int64


def test_bad_camvid_input_fails_clearly(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="does not exist"):
        read_camvid_split(tmp_path / "absent", "test")
    _write_camvid(tmp_path, n=2)
    with pytest.raises(InputError, match="split must be one of"):
        read_camvid_split(tmp_path, "testing")
    # A label image of another size than its image.
    cv2.imwrite(str(tmp_path / "testannot" / "f000.png"), np.zeros((40, 64), np.uint8))
    with pytest.raises(InputError, match=r"testannot/f000\.png: size 64x40 differs from its image"):
        read_camvid_split(tmp_path, "test")[0].load()
    # Label values outside 0..11 (e.g. a colour-index label image of another dataset).
    cv2.imwrite(str(tmp_path / "testannot" / "f001.png"), np.full((48, 64), 30, np.uint8))
    with pytest.raises(InputError, match=r"testannot/f001\.png.*outside"):
        read_camvid_split(tmp_path, "test")[1].load()
    # A listed file that is missing.
    (tmp_path / "val" / "f001.png").unlink()
    with pytest.raises(InputError, match=r"val\.txt:2: file .*f001\.png not found"):
        read_camvid_split(tmp_path, "val")


def _export_grey_decoder(path: Path, *, wrong_class: int | None = None) -> None:
    """An ONNX 'segmenter' that reads our class id from the grey level (1x1 conv, 10 logits).

    logit_k = s (2 k x - k^2) with x = (grey - 10) / 20 peaks at k = x: linear in the image.
    ``wrong_class``: that class's logit is lowered so it is never predicted.
    """
    s = 40.0
    k = torch.arange(NUM_CLASSES, dtype=torch.float32)
    conv = torch.nn.Conv2d(3, NUM_CLASSES, 1)
    with torch.no_grad():
        conv.weight.zero_()
        # x = (255 * r - 10) / 20 with r the red channel in [0, 1].
        conv.weight[:, 0, 0, 0] = s * 2 * k * 255 / 20
        conv.bias.copy_(s * (-2 * k * 10 / 20 - k ** 2))
        if wrong_class is not None:
            conv.bias[wrong_class] -= 1e6
    axes = {0: "b", 2: "h", 3: "w"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(conv, (torch.rand(1, 3, 16, 16),), str(path), dynamo=False, input_names=["x"],
                          output_names=["y"], dynamic_axes={"x": axes, "y": axes})


def test_semantic_eval_against_hand_counted_iou(tmp_path: Path) -> None:
    labels = _write_camvid(tmp_path / "camvid", n=3)
    model = tmp_path / "decoder.onnx"
    _export_grey_decoder(model)
    cfg = load_config(["data=camvid", f"data.root={tmp_path / 'camvid'}", "semantic=onnx", f"semantic.model={model}"])
    report = evaluate_semantics(cfg, CamVidSource(cfg.data.root, split="test"), progress=False)
    # A perfect segmenter: IoU 1 for every present class.
    assert report["frames"] == 3 and report["semantic"]["miou"] == pytest.approx(1.0)
    assert report["semantic"]["pixel_accuracy"] == pytest.approx(1.0)
    assert set(report["semantic"]["per_class_iou"]) == {CLASS_NAMES[c] for c in CAMVID_CLASSES_PRESENT}

    # Never predicting 'person': its pixels go to the neighbouring class id (person 8 -> 7 or 9).
    _export_grey_decoder(model, wrong_class=IDS["person"])
    report = evaluate_semantics(cfg, CamVidSource(cfg.data.root, split="test"), progress=False)
    ours = np.concatenate([map_camvid_labels(l).ravel() for l in labels])
    ours = ours[ours != IGNORE_LABEL]
    n_person = int((ours == IDS["person"]).sum())
    assert n_person > 0
    # The grey level of a person (170) lies between two_wheeler (150) and sky (190): the decoder's
    # parabola ties there, and the argmax takes the lower id, two_wheeler.
    n_tw = int((ours == IDS["two_wheeler"]).sum())
    iou = report["semantic"]["per_class_iou"]
    assert iou["person"] == 0.0
    assert iou["two_wheeler"] == pytest.approx(n_tw / (n_tw + n_person))
    present = [c for c in CAMVID_CLASSES_PRESENT if (ours == c).any()]
    expected = (len(present) - 2 + n_tw / (n_tw + n_person)) / len(present)
    assert report["semantic"]["miou"] == pytest.approx(expected)
    assert report["semantic"]["pixel_accuracy"] == pytest.approx(1 - n_person / len(ours))


def test_eval_camvid_cli_writes_semantic_section(tmp_path: Path) -> None:
    _write_camvid(tmp_path / "camvid", n=2)
    model = tmp_path / "decoder.onnx"
    _export_grey_decoder(model)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    args = ["eval", "data=camvid", f"data.root={tmp_path / 'camvid'}", "data.split=val", "semantic=onnx",
            f"semantic.model={model}", "out=o.json"]
    p = subprocess.run([sys.executable, "-m", "monostixels.cli", *args], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    report = json.loads((tmp_path / "o.json").read_text())
    assert report["dataset"] == "camvid" and report["split"] == "val" and report["frames"] == 2
    assert report["semantic"]["miou"] == pytest.approx(1.0) and "per_class_iou" in report["semantic"]
    assert "mean" in p.stdout
    # Stixels need frame pairs: `run` refuses CamVid with a clear error.
    p = subprocess.run([sys.executable, "-m", "monostixels.cli", "run", "data=camvid",
                        f"data.root={tmp_path / 'camvid'}", "semantic=none"],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert p.returncode != 0 and "single images" in p.stderr


# --- a user's Cityscapes model with a background channel (the shared ESPNetv2) --------------------

#: The 19-class mapping plus -1 for the model's 20th ("background") channel.
CITYSCAPES20_MAPPING = list(CITYSCAPES19_MAPPING) + [-1]


def _cityscapes_cfg(**extra):
    return OmegaConf.merge(load_config(["semantic=cityscapes19"]).semantic, {"model": str(CITYSCAPES_KITTI)}, extra)


@pytest.mark.skipif(not CITYSCAPES_KITTI.is_file(), reason=f"{CITYSCAPES_KITTI} absent (a user's model; "
                    "the shared folder is not shipped)")
@pytest.mark.skipif(not KITTI_FRAME.is_file(), reason=f"{KITTI_FRAME} absent (shared sample data)")
def test_cityscapes_model_with_background_channel() -> None:
    bgr = cv2.imread(str(KITTI_FRAME))
    image = torch.from_numpy(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)).permute(2, 0, 1).float() / 255
    pair = image_pair(image, "kitti")
    # 19 entries for a 20-channel model: a clear error that says how to drop the channel.
    with pytest.raises(InputError, match=r"20 channels.*19 entries.*-1"):
        estimate_semantics(pair, _cityscapes_cfg())
    scores = estimate_semantics(pair, _cityscapes_cfg(mapping=CITYSCAPES20_MAPPING))
    # The model's fixed 384x1248 input: the image is resized to it and the scores back (370x1226).
    assert scores.shape == (NUM_CLASSES, 370, 1226)
    torch.testing.assert_close(scores.sum(0), torch.ones(370, 1226), atol=1e-4, rtol=0)
    pred = scores.argmax(0)
    # KITTI frame 1110: sky above the street's vanishing point,
    # trees at the top left, road at the bottom centre.
    assert float((pred[:30, 560:620] == IDS["sky"]).float().mean()) > 0.8
    assert float((pred[:80, 150:350] == IDS["vegetation"]).float().mean()) > 0.8
    assert float((pred[330:, 400:800] == IDS["road"]).float().mean()) > 0.8


# --- the shipped real-image net -----------------------------------------------------------------


@pytest.mark.skipif(not REAL_ONNX.is_file() or not REAL_PT.is_file(), reason="models/fcn8s_real.* not present "
                    "(train with `python -m train.semantic`)")
def test_shipped_real_net_onnx_matches_torch() -> None:
    cfg = load_config(["semantic=fcn8s"]).semantic
    assert cfg.model == "models/fcn8s_real.onnx"
    g = torch.Generator().manual_seed(0)
    # A smooth random image of a size that is no multiple of 32 (padding and crop included).
    image = torch.nn.functional.interpolate(torch.rand(1, 3, 12, 16, generator=g), size=(150, 230),
                                            mode="bilinear", align_corners=False)[0]
    p_onnx = estimate_semantics(image_pair(image, "x"), cfg)
    p_torch = estimate_semantics(image_pair(image, "x"), OmegaConf.merge(cfg, {"runtime": "torch"}))
    assert p_onnx.shape == (NUM_CLASSES, 150, 230)
    assert float(p_onnx.max(0).values.std()) > 1e-3  # not a constant output
    # Both files hold float16 weights, but the ONNX graph's are rounded again after batch norm was
    # folded into the convolutions: probabilities agree to ~4e-4, argmax nearly everywhere.
    torch.testing.assert_close(p_onnx, p_torch, atol=1e-3, rtol=0)
    assert float((p_onnx.argmax(0) == p_torch.argmax(0)).float().mean()) > 0.999


@pytest.mark.skipif(not REAL_ONNX.is_file(), reason="models/fcn8s_real.onnx not present")
@pytest.mark.skipif(not CAMVID.is_dir(), reason=f"{CAMVID} absent (shared sample data)")
def test_shipped_real_net_segments_camvid_val() -> None:
    # CamVid val (model selection split, never trained on): every 10th image.
    cfg = load_config(["data=camvid", f"data.root={CAMVID}", "semantic=fcn8s"])
    report = evaluate_semantics(cfg, CamVidSource(CAMVID, split="val", step=10), progress=False)
    assert report["frames"] == 11
    iou = report["semantic"]["per_class_iou"]
    assert report["semantic"]["miou"] > 0.5, iou
    assert min(iou["road"], iou["sky"], iou["building"], iou["vehicle"]) > 0.6, iou


# --- training on a CamVid-layout folder -----------------------------------------------------------


def test_training_on_camvid_layout_exports_parity_models(tmp_path: Path) -> None:
    from hydra import compose, initialize_config_dir

    mod = _load_train_module()
    _write_camvid(tmp_path / "camvid", n=4, size=(64, 96))
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="train_semantic", overrides=[
            "model.width_mult=0.0625", "model.fc_channels=16", "model.init_from=null",
            f"data.camvid_root={tmp_path / 'camvid'}", "data.synthetic_per_epoch=0", "data.real_scale=1.0",
            f"data.cache={tmp_path / 'cache'}", "augment.crop=[64,64]", "train.epochs=2", "train.batch_size=2",
            "train.time_limit_s=null", "train.val_every=1", "train.keep_epochs=[1]", f"run_dir={tmp_path / 'run'}",
            # The shipped recipe: the best checkpoint interpolated with an early one.
            f"export.interpolate_from={tmp_path / 'run' / 'epoch_1.pt'}", "export.interpolate_alpha=0.5",
            f"export.onnx={tmp_path / 'm.onnx'}", f"export.pt={tmp_path / 'm.pt'}", "export.sample_size=[64,96]",
        ])
    result = mod.run(cfg)
    assert [h["epoch"] for h in result["history"]] == [1, 2]
    assert all(0.0 <= h["val_miou"] <= 1.0 for h in result["history"])
    assert "CamVid val" in result["val"]
    # The exported weights are the midpoint of the best and the epoch-1 checkpoints.
    best = torch.load(tmp_path / "run" / "best.pt", weights_only=True)["state_dict"]
    early = torch.load(tmp_path / "run" / "epoch_1.pt", weights_only=True)["state_dict"]
    shipped = torch.load(tmp_path / "m.pt", weights_only=True)["state_dict"]
    k = "fc6.weight"
    torch.testing.assert_close(shipped[k].float(), (0.5 * (best[k] + early[k])).half().float())
    assert result["epoch"].endswith("epoch 1 (x0.5)")
    # float16 weights in both files: the ONNX file is about half of the float32 export, and the two
    # runtimes agree.
    n_params = sum(p.numel() for p in mod.fcn8s_vgg16(width_mult=0.0625, batch_norm=True, fc_kernel=3,
                                                      fc_channels=16).parameters())
    assert (tmp_path / "m.onnx").stat().st_size < 0.65 * 4 * n_params
    image = torch.rand(3, 50, 70)
    base = {"name": "fcn8s", "model": str(tmp_path / "m.onnx"), "weights": str(tmp_path / "m.pt"), "scale": 1.0}
    p_onnx = estimate_semantics(image_pair(image, "x"), OmegaConf.create({**base, "runtime": "onnx"}))
    p_torch = estimate_semantics(image_pair(image, "x"), OmegaConf.create({**base, "runtime": "torch"}))
    torch.testing.assert_close(p_onnx, p_torch, atol=1e-4, rtol=0)
    # CamVid test is never read by training.
    with pytest.raises(ValueError, match="never reads"):
        mod._real_set(cfg, "test", None)


@pytest.mark.parametrize("command, model", [("run", "models/fcn8s_real_int8.onnx"), ("demo", "models/fcn8s_synthetic.onnx")])
def test_command_default_semantic_nets(tmp_path: Path, command: str, model: str) -> None:
    """`run` (a user's frames) defaults to the real-image net (its INT8 copy, `preset=fast`'s), `demo`
    (our renders) to the synthetic one."""
    p = subprocess.run([sys.executable, "-m", "monostixels.cli", command, "--cfg", "job"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    semantic = OmegaConf.create(p.stdout).semantic
    if (REPO / model).is_file():
        assert semantic.name == "fcn8s" and semantic.model == model
    else:  # a checkout without the model falls back, and says so
        assert semantic.name == ("none" if command == "run" else "gt") and "not found" in p.stderr


def test_shipped_models_fit_the_size_budget() -> None:
    # All shipped models together stay under 27 MB (the repository carries them): 25 MB until the
    # semantic net's 2 MB INT8 copy (preset=fast's) came in beside its float file.
    total = sum(f.stat().st_size for f in (REPO / "models").iterdir() if f.suffix in (".onnx", ".pt"))
    assert total <= 27_000_000, total


def test_fcn8s_scale_from_focal_length() -> None:
    cfg = OmegaConf.create({"name": "fcn8s", "focal_px": 360.0, "scale": 0.75})
    image = torch.rand(3, 20, 30)
    K = torch.tensor([[720.0, 0.0, 14.0], [0.0, 700.0, 9.0], [0.0, 0.0, 1.0]])
    calibrated = FramePair(image=image, image_prev=image, camera=Camera(K=K))
    assert fcn8s_scale(calibrated, cfg) == pytest.approx(0.5)  # focal_px / fx, not fy
    # Single images without a calibration (CamVid) use `scale`.
    assert fcn8s_scale(image_pair(image, "camvid"), cfg) == pytest.approx(0.75)
    assert fcn8s_scale(calibrated, OmegaConf.create({"scale": None, "focal_px": None})) is None
    with pytest.raises(InputError, match="semantic.focal_px"):
        fcn8s_scale(calibrated, OmegaConf.merge(cfg, {"focal_px": -1.0}))
