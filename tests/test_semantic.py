"""Tests of the FCN-8s network, the semantic backends, ONNX export and the training loop."""
from __future__ import annotations

import importlib.util
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf

from monostixels._checks import InputError
from monostixels.core.classes import CLASS_NAMES, IGNORE_LABEL, NUM_CLASSES
from monostixels.data.base import FramePair, GroundTruth
from monostixels.core.geometry import Camera
from monostixels.inputs.fcn8s import (
    OUTPUT_STRIDE,
    export_onnx,
    fcn8s_vgg16,
    load_vgg16_backbone,
    save_fcn8s,
)
from monostixels.inputs.semantic import (
    CITYSCAPES19_MAPPING,
    REPO_ROOT,
    confusion_matrix,
    estimate_semantics,
    gt_scores,
    iou_from_confusion,
    map_scores,
)
from monostixels.pipeline import load_config

ort = pytest.importorskip("onnxruntime")

REPO = Path(__file__).resolve().parents[1]
CONF = REPO / "conf"
SHIPPED_ONNX = REPO / "models" / "fcn8s_synthetic.onnx"
SHIPPED_PT = REPO / "models" / "fcn8s_synthetic.pt"
TINY = 0.0625  # width multiplier of the test networks (4..32 channels)


def _pair(image: torch.Tensor, labels: torch.Tensor | None = None, name: str = "test") -> FramePair:
    H, W = image.shape[-2:]
    K = torch.tensor([[700.0, 0.0, W / 2 + 3], [0.0, 690.0, H / 2 - 2], [0.0, 0.0, 1.0]])
    return FramePair(image=image, image_prev=image.clone(), camera=Camera(K=K),
                     gt=GroundTruth(labels=labels), name=name, meta={"source": "unit-test source"})


def _randomise(model: torch.nn.Module, seed: int = 0) -> torch.nn.Module:
    """Random weights everywhere (score layers start at zero) and non-trivial BN statistics."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            p.copy_(torch.randn(p.shape, generator=g) * (0.3 if p.ndim > 1 else 0.1))
        for name, b in model.named_buffers():
            if name.endswith("running_mean"):
                b.copy_(torch.randn(b.shape, generator=g) * 0.1)
            elif name.endswith("running_var"):
                b.copy_(torch.rand(b.shape, generator=g) + 0.5)
    return model.eval()


def _load_train_module():
    # train/ is a script package at the repository root (not installed): load it by path.
    spec = importlib.util.spec_from_file_location("train_semantic_under_test", REPO / "train" / "semantic.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


# --- network -------------------------------------------------------------------------------


@pytest.mark.parametrize("batch_norm", [False, True])
def test_backbone_state_dict_matches_torchvision(batch_norm: bool) -> None:
    from monostixels._torchvision import torchvision

    if batch_norm:
        # vgg16_bn().features is make_layers(cfgs["D"], batch_norm=True); building only the trunk
        # skips the 120M-parameter classifier.
        tv_features = torchvision.models.vgg.make_layers(torchvision.models.vgg.cfgs["D"], batch_norm=True)
    else:
        tv_features = torchvision.models.vgg16(weights=None).features
    ref = tv_features.state_dict()
    # fc_channels small: only the backbone is compared (keeps the test light).
    model = fcn8s_vgg16(width_mult=1.0, batch_norm=batch_norm, fc_channels=8)
    own = model.backbone.state_dict()
    assert list(own) == list(ref)
    assert all(own[k].shape == ref[k].shape for k in ref)
    if not batch_norm:
        # Conv layers at torchvision's indices.
        assert [k for k in own if k.endswith(".weight")][:3] == ["0.weight", "2.weight", "5.weight"]
    model.backbone.load_state_dict(ref)  # strict: names and shapes fit
    assert torch.equal(model.backbone[0].weight, tv_features[0].weight)


def test_load_vgg16_backbone_from_file_reshapes_classifier(tmp_path: Path) -> None:
    # A torchvision-style full VGG state dict (features.*, classifier.*) at reduced width, with
    # classifier shapes that match fc6 (k=7) / fc7 after reshaping.
    donor = _randomise(fcn8s_vgg16(width_mult=TINY, fc_kernel=7, fc_channels=16), seed=1)
    c5 = donor.backbone[28].out_channels
    state = {f"features.{k}": v for k, v in donor.backbone.state_dict().items()}
    state["classifier.0.weight"] = torch.randn(16, c5 * 7 * 7)
    state["classifier.0.bias"] = torch.randn(16)
    state["classifier.3.weight"] = torch.randn(16, 16)
    state["classifier.3.bias"] = torch.randn(16)
    path = tmp_path / "vgg16.pth"
    torch.save(state, path)
    model = fcn8s_vgg16(width_mult=TINY, fc_kernel=7, fc_channels=16)
    loaded = load_vgg16_backbone(model, path)
    assert "fc6.weight" in loaded and "backbone.0.weight" in loaded
    assert torch.equal(model.backbone[26].weight, donor.backbone[26].weight)
    # classifier.0 flattens (C5, 7, 7) in C order: element (o, c, y, x) = row o, column c*49 + y*7 + x.
    assert model.fc6.weight[3, 2, 4, 5] == state["classifier.0.weight"][3, 2 * 49 + 4 * 7 + 5]
    assert torch.equal(model.fc7.weight[:, :, 0, 0], state["classifier.3.weight"])
    wrong = fcn8s_vgg16(width_mult=TINY, batch_norm=True)
    with pytest.raises(InputError, match="vgg16.pth"):
        load_vgg16_backbone(wrong, path)
    with pytest.raises(InputError, match="not found"):
        load_vgg16_backbone(model, tmp_path / "absent.pth")


@pytest.mark.parametrize("size", [(37, 61), (64, 96), (5, 3)])
def test_output_shape_any_size(size: tuple[int, int]) -> None:
    model = _randomise(fcn8s_vgg16(width_mult=TINY, batch_norm=True, fc_kernel=3))
    x = torch.rand(2, 3, *size)
    with torch.no_grad():
        y = model(x)
    assert y.shape == (2, NUM_CLASSES, *size)
    # Padding is with the mean colour, bottom/right, and the crop is the top-left block.
    ph, pw = (-size[0]) % OUTPUT_STRIDE, (-size[1]) % OUTPUT_STRIDE
    padded = F.pad(x - model.mean, (0, pw, 0, ph)) + model.mean
    with torch.no_grad():
        ref = model.forward_aligned(padded)[..., : size[0], : size[1]]
    torch.testing.assert_close(y, ref)


def test_upsamplers_are_exact_and_bilinear() -> None:
    model = fcn8s_vgg16(width_mult=TINY)
    # A linear ramp is reproduced exactly by bilinear interpolation away from the border.
    ramp = torch.arange(6.0).view(1, 1, 1, 6).expand(1, NUM_CLASSES, 4, 6).contiguous()
    up = model.upscore8(ramp)
    assert up.shape == (1, NUM_CLASSES, 32, 48)
    # Output pixel u (centre u + 0.5) lies at input coordinate (u + 0.5) / 8 - 0.5.
    u = torch.arange(8, 40)
    expected = (u + 0.5) / 8 - 0.5
    torch.testing.assert_close(up[0, 3, 12, 8:40], expected.float(), atol=1e-5, rtol=0)
    assert not model.upscore8.weight.requires_grad and model.upscore2.weight.requires_grad


# --- ONNX export ---------------------------------------------------------------------------


def test_onnx_matches_torch(tmp_path: Path) -> None:
    model = _randomise(fcn8s_vgg16(width_mult=TINY, batch_norm=True, fc_kernel=3))
    path = export_onnx(model, tmp_path / "m.onnx", sample_size=(64, 96), metadata={"k": "v"})
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    for size in [(64, 96), (96, 160)]:  # dynamic H, W
        x = torch.rand(1, 3, *size)
        with torch.no_grad():
            ref = model.forward_aligned(x).numpy()
        out = sess.run(None, {"image": x.numpy()})[0]
        assert out.shape == ref.shape
        assert np.abs(ref).max() > 1e-2  # the comparison is not between zeros
        np.testing.assert_allclose(out, ref, atol=1e-4, rtol=1e-4)
    assert sess.get_modelmeta().custom_metadata_map["k"] == "v"

    # The two runtimes of the `fcn8s` backend agree on a non-multiple-of-32 image.
    pt = save_fcn8s(model, tmp_path / "m.pt", arch={"width_mult": TINY, "batch_norm": True, "fc_kernel": 3})
    image = torch.rand(3, 45, 70)
    base = {"name": "fcn8s", "model": str(path), "weights": str(pt), "scale": 1.0, "focal_px": None}
    p_onnx = estimate_semantics(_pair(image), OmegaConf.create({**base, "runtime": "onnx"}))
    p_torch = estimate_semantics(_pair(image), OmegaConf.create({**base, "runtime": "torch"}))
    assert p_onnx.shape == (NUM_CLASSES, 45, 70)
    torch.testing.assert_close(p_onnx, p_torch, atol=1e-4, rtol=0)
    torch.testing.assert_close(p_onnx.sum(0), torch.ones(45, 70), atol=1e-5, rtol=0)


# --- backends ------------------------------------------------------------------------------


def test_gt_scores_softened_and_sum_to_one() -> None:
    labels = torch.tensor([[0, 9, IGNORE_LABEL], [4, 7, 2]])
    s = gt_scores(labels, confidence=0.82)
    assert s.shape == (NUM_CLASSES, 2, 3) and s.dtype == torch.float32
    torch.testing.assert_close(s.sum(0), torch.ones(2, 3))
    assert float(s[9, 0, 1]) == pytest.approx(0.82)
    assert float(s[0, 0, 1]) == pytest.approx(0.18 / 9)
    torch.testing.assert_close(s[:, 0, 2], torch.full((NUM_CLASSES,), 0.1))
    assert torch.equal(s.argmax(0)[1], torch.tensor([4, 7, 2]))

    cfg = load_config(["semantic=gt"]).semantic
    out = estimate_semantics(_pair(torch.rand(3, 2, 3), labels), cfg)
    assert float(out[0, 0, 0]) == pytest.approx(float(cfg.confidence))
    with pytest.raises(InputError, match="unit-test source"):
        estimate_semantics(_pair(torch.rand(3, 2, 3), None), cfg)
    with pytest.raises(InputError, match="outside"):
        gt_scores(torch.tensor([[3, 12]]))
    assert estimate_semantics(_pair(torch.rand(3, 2, 3)), OmegaConf.create({"name": "none"})) is None


def _export_const_model(path: Path, channels: int, *, out_transposed: bool = False) -> torch.Tensor:
    """An ONNX model with ``channels`` outputs whose logits are a fixed vector at every pixel."""
    logits = torch.linspace(-1.0, 2.0, channels) * torch.tensor([(-1.0) ** i for i in range(channels)])

    class Const(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.conv = torch.nn.Conv2d(3, channels, 1)
            torch.nn.init.zeros_(self.conv.weight)
            with torch.no_grad():
                self.conv.bias.copy_(logits)

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            y = self.conv(F.avg_pool2d(x, 4))  # output at stride 4, like a real segmentation net
            return y.transpose(-1, -2) if out_transposed else y

    axes = {0: "b", 2: "h", 3: "w"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # legacy (TorchScript) exporter
        torch.onnx.export(Const(), (torch.rand(1, 3, 32, 64),), str(path), dynamo=False, input_names=["x"],
                          output_names=["y"], dynamic_axes={"x": axes, "y": axes})
    return logits


def test_cityscapes_mapping_sums_probabilities(tmp_path: Path) -> None:
    path = tmp_path / "cityscapes_fake.onnx"
    logits = _export_const_model(path, 19)
    cfg = OmegaConf.merge(load_config(["semantic=cityscapes19"]).semantic, {"model": str(path)})
    assert list(cfg.mapping) == list(CITYSCAPES19_MAPPING)
    out = estimate_semantics(_pair(torch.rand(3, 50, 70)), cfg)
    assert out.shape == (NUM_CLASSES, 50, 70)
    p = torch.softmax(logits, 0)
    ids = {n: i for i, n in enumerate(CLASS_NAMES)}
    # building = building + wall + fence; vehicle = car + truck + bus + train; etc.
    expected = torch.zeros(NUM_CLASSES)
    for cs_id, ours in enumerate(CITYSCAPES19_MAPPING):
        expected[ours] += p[cs_id]
    assert float(expected[ids["building"]]) == pytest.approx(float(p[2] + p[3] + p[4]))
    torch.testing.assert_close(out[:, 25, 35], expected, atol=1e-5, rtol=0)
    torch.testing.assert_close(out.sum(0), torch.ones(50, 70), atol=1e-5, rtol=0)

    # Dropped classes (-1): the remaining mass is renormalised.
    mapping = [-1] * 19
    mapping[0], mapping[10] = ids["road"], ids["sky"]
    out = estimate_semantics(_pair(torch.rand(3, 40, 40)), OmegaConf.merge(cfg, {"mapping": mapping}))
    assert float(out[ids["road"], 5, 5]) == pytest.approx(float(p[0] / (p[0] + p[10])), abs=1e-5)


def test_user_onnx_wrong_channels_or_shape_fails(tmp_path: Path) -> None:
    path = tmp_path / "seven.onnx"
    _export_const_model(path, 7)
    base = load_config(["semantic=onnx"]).semantic
    image = torch.rand(3, 40, 60)
    with pytest.raises(InputError, match=r"seven\.onnx.*7 channels.*expected 10"):
        estimate_semantics(_pair(image), OmegaConf.merge(base, {"model": str(path)}))
    with pytest.raises(InputError, match=r"seven\.onnx.*7 channels.*19 entries"):
        estimate_semantics(_pair(image), OmegaConf.merge(base, {"model": str(path), "mapping": list(CITYSCAPES19_MAPPING)}))
    with pytest.raises(InputError, match="semantic.model"):
        estimate_semantics(_pair(image), base)
    with pytest.raises(InputError, match="not found"):
        estimate_semantics(_pair(image), OmegaConf.merge(base, {"model": str(tmp_path / "nope.onnx")}))
    bad = tmp_path / "transposed.onnx"
    _export_const_model(bad, 10, out_transposed=True)
    with pytest.raises(InputError, match=r"transposed\.onnx.*does not fit"):
        estimate_semantics(_pair(torch.rand(3, 40, 96)), OmegaConf.merge(base, {"model": str(bad)}))


def test_map_scores_identity_needs_ten_channels() -> None:
    probs = torch.softmax(torch.randn(10, 3, 4), 0)
    torch.testing.assert_close(map_scores(probs, None), probs)
    with pytest.raises(InputError, match="entries must be"):
        map_scores(probs, [0, 1, 2, 3, 4, 5, 6, 7, 8, 12])


def test_iou_from_confusion() -> None:
    pred = torch.tensor([0, 0, 1, 1, 9, 3])
    labels = torch.tensor([0, 1, 1, 1, 9, IGNORE_LABEL])
    miou, per = iou_from_confusion(confusion_matrix(pred, labels))
    # road: tp 1, union 2; sidewalk: tp 2, union 3; sky: 1/1; others absent (NaN, not averaged).
    assert per["road"] == pytest.approx(0.5) and per["sidewalk"] == pytest.approx(2 / 3)
    assert np.isnan(per["building"])
    assert miou == pytest.approx((0.5 + 2 / 3 + 1.0) / 3)


def test_model_path_resolves_against_repo_root(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from monostixels.inputs.semantic import resolve_model_path

    assert REPO_ROOT == REPO  # editable install: the package lives in the checkout
    monkeypatch.chdir(tmp_path)
    target = REPO / "conf" / "semantic" / "fcn8s.yaml"  # any file tracked in the repo
    assert resolve_model_path("conf/semantic/fcn8s.yaml") == target.resolve()


# --- training ------------------------------------------------------------------------------


def _toy_batch(n: int, size: tuple[int, int], seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Images of class-coloured blocks with noise, and their labels."""
    g = torch.Generator().manual_seed(seed)
    H, W = size
    labels = torch.randint(0, NUM_CLASSES, (n, H // 16, W // 16), generator=g)
    labels = labels.repeat_interleave(16, 1).repeat_interleave(16, 2)
    colours = torch.rand(NUM_CLASSES, 3, generator=g)
    images = colours[labels].permute(0, 3, 1, 2) + 0.05 * torch.randn(n, 3, H, W, generator=g)
    return images.clamp(0, 1), labels


def test_few_training_steps_lower_the_loss() -> None:
    mod = _load_train_module()
    torch.manual_seed(0)
    model, _ = mod.build_model({"width_mult": TINY, "batch_norm": True, "fc_kernel": 3,
                                "fc_channels": 32, "dropout": 0.0})
    batch = _toy_batch(4, (64, 64), seed=3)
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=1e-2)
    losses = mod.train_steps(model, [batch] * 25, opt)
    assert len(losses) == 25
    assert losses[0] == pytest.approx(np.log(NUM_CLASSES), rel=0.05)  # zero-initialised scores
    assert np.mean(losses[-3:]) < 0.7 * losses[0]


def test_fine_tuning_starts_from_saved_weights(tmp_path: Path) -> None:
    mod = _load_train_module()
    from monostixels._checks import InputError
    from monostixels.inputs.fcn8s import save_fcn8s

    cfg = {"width_mult": TINY, "batch_norm": True, "fc_kernel": 3, "fc_channels": 32, "dropout": 0.0}
    torch.manual_seed(1)
    src, arch = mod.build_model(cfg)
    with torch.no_grad():
        for p in src.parameters():
            p.add_(torch.randn_like(p))
    path = save_fcn8s(src, tmp_path / "src.pt", arch=arch)
    torch.manual_seed(2)
    model, _ = mod.build_model({**cfg, "init_from": str(path)})
    for (k, a), b in zip(src.state_dict().items(), model.state_dict().values()):
        assert torch.equal(a, b), k
    with pytest.raises(InputError, match="model.init_from"):
        mod.build_model({**cfg, "fc_channels": 16, "init_from": str(path)})


def test_the_stride4_skip_runs_exports_and_starts_from_an_fcn8s(tmp_path: Path) -> None:
    mod = _load_train_module()
    from monostixels.inputs.fcn8s import SKIP_POOL2_KEYS, _bilinear_kernel, load_fcn8s

    cfg = {"width_mult": TINY, "batch_norm": True, "fc_kernel": 3, "fc_channels": 32, "dropout": 0.0}
    torch.manual_seed(1)
    src, arch = mod.build_model(cfg)
    _randomise(src)
    with torch.no_grad():  # the upsamplers back to bilinear: the comparison below is of the skip alone
        for up, f in ((src.upscore2, 2), (src.upscore_pool4, 2), (src.upscore8, 8)):
            up.weight.copy_(_bilinear_kernel(NUM_CLASSES, 2 * f))
    path = save_fcn8s(src, tmp_path / "fcn8s.pt", arch=arch)
    model, arch4 = mod.build_model({**cfg, "skip_pool2": True, "init_from": str(path)})
    assert arch4 == {**arch, "skip_pool2": True}
    own = model.state_dict()
    for k, v in src.state_dict().items():
        if k != "upscore8.weight":
            assert torch.equal(own[k], v), k
    assert set(own) - set(src.state_dict()) == set(SKIP_POOL2_KEYS)
    # Started from the FCN-8s (pool2's scores zero): the same scores but for a 2x-then-4x bilinear
    # upsampling in place of one 8x; the classes agree nearly everywhere.
    x = torch.rand(1, 3, 96, 128)
    with torch.no_grad():
        a, b = src.eval()(x), model.eval()(x)
    assert (a.argmax(1) == b.argmax(1)).float().mean() > 0.95
    assert float(model.score_pool2.weight.detach().abs().max()) == 0.0
    # A file of the stride-4 net loads as one, and exports with the torch and ONNX graphs agreeing.
    _randomise(model, seed=3)
    pt = save_fcn8s(model, tmp_path / "s4.pt", arch=arch4)
    back, _ = load_fcn8s(pt)
    assert back.skip_pool2 and all(torch.equal(back.state_dict()[k], v) for k, v in model.state_dict().items())
    onnx_path = export_onnx(model.eval(), tmp_path / "s4.onnx", sample_size=(64, 96))
    sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    with torch.no_grad():
        ref = model.forward_aligned(x).numpy()
    out = sess.run(None, {"image": x.numpy()})[0]
    assert np.abs(ref).max() > 1e-2
    np.testing.assert_allclose(out, ref, atol=1e-4, rtol=1e-4)
    # Another FCN-8s architecture does not fit.
    with pytest.raises(InputError, match="model.init_from"):
        mod.build_model({**cfg, "fc_channels": 16, "skip_pool2": True, "init_from": str(path)})


def test_the_stride4_skip_draws_thin_poles_the_stride8_net_cannot() -> None:
    # Vertical 3 px lines on a plain background, 4 px apart at their nearest: a stride-8 score map
    # blurs them into their background, the stride-4 skip separates them. The same steps for both.
    mod = _load_train_module()
    rng = np.random.default_rng(0)
    images, labels = [], []
    for _ in range(6):
        img = torch.full((3, 64, 64), 0.3)
        lab = torch.zeros(64, 64, dtype=torch.long)
        for u in rng.choice(np.arange(2, 60, 7), size=4, replace=False):
            img[:, :, u:u + 3] = 0.9
            lab[:, u:u + 3] = 1
        images.append(img)
        labels.append(lab)
    batch = (torch.stack(images), torch.stack(labels))
    iou = {}
    for skip in (False, True):
        torch.manual_seed(0)
        model, _ = mod.build_model({"width_mult": TINY, "batch_norm": True, "fc_kernel": 3, "fc_channels": 32,
                                    "dropout": 0.0, "skip_pool2": skip})
        opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=1e-2)
        mod.train_steps(model, [batch] * 60, opt)
        with torch.no_grad():
            pred = model.eval()(batch[0]).argmax(1)
        inter = ((pred == 1) & (batch[1] == 1)).sum().item()
        union = ((pred == 1) | (batch[1] == 1)).sum().item()
        iou[skip] = inter / max(union, 1)
    assert iou[True] > 0.4 and iou[True] > 2 * iou[False], iou


def test_augment_keeps_labels_valid_and_crops() -> None:
    mod = _load_train_module()
    aug = OmegaConf.load(CONF / "train_semantic_synthetic.yaml").augment
    image, labels = _toy_batch(1, (96, 160), seed=5)
    g = torch.Generator().manual_seed(0)
    img, lab = mod.augment(image[0], labels[0], g, OmegaConf.merge(aug, {"crop": [64, 128]}))
    assert img.shape == (3, 64, 128) and lab.shape == (64, 128)
    assert float(img.min()) >= 0 and float(img.max()) <= 1
    vals = set(lab.unique().tolist())
    assert vals <= set(range(NUM_CLASSES)) | {IGNORE_LABEL} and len(vals - {IGNORE_LABEL}) > 1


# --- the shipped model ---------------------------------------------------------------------


def test_shipped_model_segments_validation_renders() -> None:
    if not SHIPPED_ONNX.is_file():
        pytest.skip(f"{SHIPPED_ONNX} not present (train with `python -m train.semantic`)")
    synthetic = pytest.importorskip("monostixels.data.synthetic", reason="synthetic renderer not present")
    cfg = load_config(["semantic=fcn8s_synthetic"]).semantic
    conf = torch.zeros(NUM_CLASSES, NUM_CLASSES, dtype=torch.int64)
    for frame in (0, 1):
        # Validation source seed 9 (never used in training), rendered at the training scale 0.5.
        pair = synthetic.render_pair(9 * 100_000 + frame, scale=0.5)
        scores = estimate_semantics(pair, OmegaConf.merge(cfg, {"scale": 1.0}))
        assert scores.shape == (NUM_CLASSES, *pair.size)
        conf += confusion_matrix(scores.argmax(0), pair.gt.labels)
        if SHIPPED_PT.is_file():
            torch_scores = estimate_semantics(pair, OmegaConf.merge(cfg, {"scale": 1.0, "runtime": "torch"}))
            assert float((torch_scores.argmax(0) == scores.argmax(0)).float().mean()) > 0.999
    miou, per_class = iou_from_confusion(conf)
    assert miou >= 0.6, per_class


def test_init_from_a_missing_file_names_the_option_and_the_file(tmp_path) -> None:
    mod = _load_train_module()
    cfg = {"width_mult": TINY, "batch_norm": True, "fc_kernel": 3, "fc_channels": 16, "dropout": 0.0}
    with pytest.raises(InputError, match=r"model.init_from: .*nowhere\.pt: not found"):
        mod.build_model({**cfg, "init_from": str(tmp_path / "nowhere.pt")})
