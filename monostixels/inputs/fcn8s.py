"""FCN-8s on a VGG-16 backbone (Long, Shelhamer, Darrell, CVPR 2015), with a width multiplier.

The paper's semantic input (Mono-Stixels, section "Semantic segmentation") is an FCN-8s: a VGG-16
whose fully connected layers are turned into convolutions (``fc6``/``fc7``), with class scores
predicted at three strides (pool3 = 1/8, pool4 = 1/16, fc7 = 1/32) and fused coarse-to-fine by 2x
upsampling and addition, then upsampled 8x to the input resolution.

Differences from the Caffe original, and why:

- ``width_mult`` scales every channel count (VGG conv layers and fc6/fc7), so that the network
  trains on a small CPU; at ``width_mult=1.0`` the backbone has exactly torchvision's VGG-16 layout.
- ``fc_kernel``: fc6 is a ``7 x 7`` convolution in the original (the 7 x 7 pool5 window of the
  ImageNet classifier); width-reduced variants may use a smaller kernel (3) to save compute.
- "Same" padding in fc6 instead of the original's 100-pixel input padding and crop offsets: any
  input whose sides are multiples of 32 maps exactly onto strides 8/16/32; other sizes are padded
  up to the next multiple of 32 (zeros after normalisation, i.e. the ImageNet-mean colour) and the
  scores are cropped back. ``forward`` does that for any (H, W).
- ``batch_norm=True`` builds the VGG-16-BN layout (torchvision ``vgg16_bn``); it is what makes
  training from scratch on synthetic images converge in minutes. ONNX export folds it away.
- The input is an RGB image in [0, 1]; ImageNet mean/std normalisation is part of the module
  (buffers ``mean``/``std``), so the exported ONNX model takes the image as it is.

State-dict compatibility: ``model.backbone`` is an ``nn.Sequential`` indexed exactly like
torchvision's ``vgg16().features`` (conv layers at 0, 2, 5, 7, 10, ...; ``vgg16_bn`` layout when
``batch_norm=True``), so ``model.backbone.load_state_dict(tv_vgg16.features.state_dict())`` works at
``width_mult=1.0``; :func:`load_vgg16_backbone` loads such weights from a file the user has (it
never downloads).
"""
from __future__ import annotations

import logging
import math
import warnings
from pathlib import Path
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from monostixels._checks import InputError, check_shape
from monostixels.core.classes import NUM_CLASSES

__all__ = ["FCN8s", "fcn8s_vgg16", "vgg16_features", "load_vgg16_backbone", "VGG16_CFG", "OUTPUT_STRIDE",
           "export_onnx", "save_fcn8s", "load_fcn8s", "load_fcn8s_state", "SKIP_POOL2_KEYS", "ONNX_INPUT",
           "ONNX_OUTPUT"]

logger = logging.getLogger(__name__)

#: VGG-16 "configuration D" (Simonyan & Zisserman 2015, Table 1): conv channels, "M" = 2x2 max-pool.
VGG16_CFG: tuple[int | str, ...] = (
    64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M",
)
#: Channels of the fully connected layers fc6/fc7 of VGG-16 (as convolutions in FCN).
VGG16_FC_CHANNELS = 4096
#: Kernel of fc6 in the original FCN (the 7 x 7 pool5 window of the ImageNet classifier).
VGG16_FC6_KERNEL = 7
#: Total stride of the backbone (five 2x2 pools): inputs are padded to a multiple of this.
OUTPUT_STRIDE = 32
#: ImageNet RGB mean and std (torchvision's VGG weights expect inputs normalised by these).
IMAGENET_MEAN: tuple[float, float, float] = (0.485, 0.456, 0.406)
IMAGENET_STD: tuple[float, float, float] = (0.229, 0.224, 0.225)
#: Names of the input and output of exported ONNX models.
ONNX_INPUT = "image"
ONNX_OUTPUT = "scores"
#: ONNX opset of the export (supported by onnxruntime >= 1.17).
ONNX_OPSET = 17
#: Smallest channel count of a width-reduced layer (keeps tiny test networks well defined).
MIN_CHANNELS = 4
#: The tensors ``skip_pool2`` adds to an FCN-8s (it drops one: ``upscore8.weight``, the 8x upsampler).
SKIP_POOL2_KEYS = ("score_pool2.weight", "score_pool2.bias", "upscore_pool3.weight", "upscore4.weight")


def _scaled(channels: int, width_mult: float) -> int:
    return max(MIN_CHANNELS, int(round(channels * width_mult)))


def vgg16_features(*, width_mult: float = 1.0, batch_norm: bool = False) -> nn.Sequential:
    """The VGG-16 convolutional trunk, indexed like torchvision's ``vgg16().features``.

    Args:
        width_mult: multiplier on every channel count (1.0 = VGG-16).
        batch_norm: the ``vgg16_bn`` layout (conv, BN, ReLU) instead of (conv, ReLU).

    Returns:
        ``nn.Sequential`` mapping (B, 3, H, W) normalised RGB to (B, C5, H/32, W/32).
    """
    layers: list[nn.Module] = []
    in_ch = 3
    for v in VGG16_CFG:
        if v == "M":
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
            continue
        out_ch = _scaled(int(v), width_mult)
        layers.append(nn.Conv2d(in_ch, out_ch, kernel_size=3, padding=1))
        if batch_norm:
            layers.append(nn.BatchNorm2d(out_ch))
        layers.append(nn.ReLU(inplace=True))
        in_ch = out_ch
    return nn.Sequential(*layers)


def _bilinear_kernel(channels: int, kernel_size: int) -> torch.Tensor:
    """Weights (C, C, k, k) of a per-channel bilinear upsampling transposed convolution."""
    factor = (kernel_size + 1) // 2
    centre = factor - 1 if kernel_size % 2 == 1 else factor - 0.5
    og = torch.arange(kernel_size, dtype=torch.float32)
    filt1d = 1 - (og - centre).abs() / factor
    filt = filt1d[:, None] * filt1d[None, :]
    weight = torch.zeros(channels, channels, kernel_size, kernel_size)
    weight[range(channels), range(channels)] = filt
    return weight


def _upsampler(channels: int, factor: int, *, learned: bool) -> nn.ConvTranspose2d:
    """Transposed conv that upsamples exactly by ``factor`` (kernel 2f, stride f, padding f/2),
    initialised to bilinear interpolation; frozen unless ``learned``."""
    up = nn.ConvTranspose2d(
        channels, channels, kernel_size=2 * factor, stride=factor, padding=factor // 2, bias=False
    )
    with torch.no_grad():
        up.weight.copy_(_bilinear_kernel(channels, 2 * factor))
    up.weight.requires_grad_(learned)
    return up


class FCN8s(nn.Module):
    """FCN-8s: class scores from pool3, pool4 and fc7 of a VGG trunk, fused coarse to fine.

    Args:
        backbone: a VGG trunk (see :func:`vgg16_features`) with five ``MaxPool2d`` layers.
        num_classes: number of output channels (10 = ``monostixels.core.classes.CLASS_NAMES``).
        fc_channels: channels of fc6 and fc7.
        fc_kernel: kernel of fc6 (odd; "same" padding).
        dropout: dropout probability after fc6 and fc7 (training only).
        learned_upsampling: train the 2x upsamplers (bilinear init); the final 8x is fixed bilinear
            as in the original.
        skip_pool2: a fourth skip, from pool2 (stride 4): the fused stride-8 scores are upsampled 2x
            (learned as the others), pool2's scores added, and the final upsampling is 4x. A thin
            pole spans a few pixels, under one stride-8 cell; its scores zero-initialised, the net
            starts as the FCN-8s it extends (:data:`SKIP_POOL2_KEYS`).
        mean: RGB mean subtracted from the [0, 1] input.
        std: RGB std the input is divided by.

    Shape:
        input (B, 3, H, W) RGB in [0, 1]; output (B, num_classes, H, W) raw scores (logits).
    """

    def __init__(
        self,
        *,
        backbone: nn.Sequential,
        num_classes: int = NUM_CLASSES,
        fc_channels: int = VGG16_FC_CHANNELS,
        fc_kernel: int = VGG16_FC6_KERNEL,
        dropout: float = 0.5,
        learned_upsampling: bool = True,
        skip_pool2: bool = False,
        mean: Sequence[float] = IMAGENET_MEAN,
        std: Sequence[float] = IMAGENET_STD,
    ) -> None:
        super().__init__()
        if fc_kernel % 2 != 1:
            raise InputError(f"fc_kernel: must be odd for 'same' padding, got {fc_kernel}")
        pools = [i for i, m in enumerate(backbone) if isinstance(m, nn.MaxPool2d)]
        if len(pools) != 5:
            raise InputError(f"backbone: expected 5 MaxPool2d layers (VGG), found {len(pools)}")
        # Outputs of pool3 (stride 8) and pool4 (stride 16) feed the skip score layers (and pool2,
        # stride 4, with skip_pool2).
        self._taps = (pools[2], pools[3])
        self._pool2 = pools[1] if skip_pool2 else None
        convs = [m for m in backbone if isinstance(m, nn.Conv2d)]
        ch_pool3 = _out_channels_before(backbone, pools[2])
        ch_pool4 = _out_channels_before(backbone, pools[3])
        ch_pool5 = convs[-1].out_channels
        self.num_classes = num_classes
        self.register_buffer("mean", torch.tensor(mean, dtype=torch.float32).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(std, dtype=torch.float32).view(1, 3, 1, 1))
        self.backbone = backbone
        self.fc6 = nn.Conv2d(ch_pool5, fc_channels, kernel_size=fc_kernel, padding=fc_kernel // 2)
        self.fc7 = nn.Conv2d(fc_channels, fc_channels, kernel_size=1)
        self.drop = nn.Dropout2d(p=dropout)
        self.score_fr = nn.Conv2d(fc_channels, num_classes, kernel_size=1)
        self.score_pool4 = nn.Conv2d(ch_pool4, num_classes, kernel_size=1)
        self.score_pool3 = nn.Conv2d(ch_pool3, num_classes, kernel_size=1)
        self.upscore2 = _upsampler(num_classes, 2, learned=learned_upsampling)
        self.upscore_pool4 = _upsampler(num_classes, 2, learned=learned_upsampling)
        self.skip_pool2 = bool(skip_pool2)
        if self.skip_pool2:
            self.score_pool2 = nn.Conv2d(_out_channels_before(backbone, pools[1]), num_classes, kernel_size=1)
            self.upscore_pool3 = _upsampler(num_classes, 2, learned=learned_upsampling)
            self.upscore4 = _upsampler(num_classes, 4, learned=False)
        else:
            self.upscore8 = _upsampler(num_classes, 8, learned=False)
        self._init_head()

    def _init_head(self) -> None:
        for m in (self.fc6, self.fc7):
            nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            nn.init.zeros_(m.bias)
        # Score layers start at zero, as in the FCN paper (section 4.3, "zero-initialised").
        for m in (self.score_fr, self.score_pool4, self.score_pool3) + ((self.score_pool2,) if self.skip_pool2 else ()):
            nn.init.zeros_(m.weight)
            nn.init.zeros_(m.bias)

    def forward_aligned(self, x: torch.Tensor) -> torch.Tensor:
        """Scores for an input whose sides are multiples of 32 (no padding; the ONNX graph).

        Args:
            x: (B, 3, H, W) RGB in [0, 1], H and W multiples of :data:`OUTPUT_STRIDE`.

        Returns:
            (B, num_classes, H, W) logits.
        """
        h = (x - self.mean) / self.std
        pool2 = pool3 = pool4 = h
        for i, layer in enumerate(self.backbone):
            h = layer(h)
            if i == self._taps[0]:
                pool3 = h
            elif i == self._taps[1]:
                pool4 = h
            elif i == self._pool2:
                pool2 = h
        h = self.drop(F.relu(self.fc6(h), inplace=True))
        h = self.drop(F.relu(self.fc7(h), inplace=True))
        s = self.upscore2(self.score_fr(h))                       # B x C x H/16 x W/16
        s = self.upscore_pool4(s + self.score_pool4(pool4))      # B x C x H/8 x W/8
        if self.skip_pool2:
            s = self.upscore_pool3(s + self.score_pool3(pool3))  # B x C x H/4 x W/4
            return self.upscore4(s + self.score_pool2(pool2))    # B x C x H x W
        return self.upscore8(s + self.score_pool3(pool3))        # B x C x H x W

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Scores for any input size: pads to a multiple of 32 (bottom/right), crops back.

        Args:
            x: (B, 3, H, W) RGB in [0, 1].

        Returns:
            (B, num_classes, H, W) logits.
        """
        check_shape(x, [None, 3, None, None], "FCN8s input")
        H, W = int(x.shape[-2]), int(x.shape[-1])
        ph = (-H) % OUTPUT_STRIDE
        pw = (-W) % OUTPUT_STRIDE
        if ph or pw:
            # Pad with the mean colour, i.e. zeros after normalisation.
            x = F.pad(x - self.mean, (0, pw, 0, ph)) + self.mean
        return self.forward_aligned(x)[..., :H, :W]


def _out_channels_before(backbone: nn.Sequential, index: int) -> int:
    convs = [m for m in list(backbone)[:index] if isinstance(m, nn.Conv2d)]
    return convs[-1].out_channels


def fcn8s_vgg16(
    *,
    num_classes: int = NUM_CLASSES,
    width_mult: float = 1.0,
    batch_norm: bool = False,
    fc_kernel: int = VGG16_FC6_KERNEL,
    fc_channels: int | None = None,
    dropout: float = 0.5,
    learned_upsampling: bool = True,
    skip_pool2: bool = False,
) -> FCN8s:
    """FCN-8s on VGG-16 (``width_mult=1.0``: the paper's network, fc6 7 x 7 with 4096 channels).

    Args:
        num_classes: output channels.
        width_mult: multiplier on all channel counts (e.g. 0.25 for CPU training).
        batch_norm: VGG-16-BN trunk (torchvision ``vgg16_bn`` layout).
        fc_kernel: fc6 kernel (7 in the paper; 3 is a cheaper choice for reduced widths).
        fc_channels: channels of fc6/fc7; None = 4096 x ``width_mult``.
        dropout: dropout after fc6/fc7.
        learned_upsampling: learn the two 2x upsamplers.
        skip_pool2: add the stride-4 skip from pool2 (see :class:`FCN8s`).

    Returns:
        An :class:`FCN8s` mapping (B, 3, H, W) RGB [0, 1] to (B, num_classes, H, W) logits.
    """
    if not width_mult > 0 or not math.isfinite(width_mult):
        raise InputError(f"width_mult: must be a positive number, got {width_mult}")
    backbone = vgg16_features(width_mult=width_mult, batch_norm=batch_norm)
    return FCN8s(
        backbone=backbone,
        num_classes=num_classes,
        fc_channels=_scaled(VGG16_FC_CHANNELS, width_mult) if fc_channels is None else int(fc_channels),
        fc_kernel=fc_kernel,
        dropout=dropout,
        learned_upsampling=learned_upsampling,
        skip_pool2=skip_pool2,
    )


def load_vgg16_backbone(model: FCN8s, path: str | Path, *, strict: bool = True) -> list[str]:
    """Initialise ``model.backbone`` (and fc6/fc7 where shapes allow) from VGG-16 weights on disk.

    Accepts a file saved with ``torch.save`` holding either the state dict of a torchvision
    ``vgg16``/``vgg16_bn`` (keys ``features.N.*``, ``classifier.N.*``) or of its ``features``
    module alone (keys ``N.*``). Never downloads anything. When the classifier is present and the
    model has the paper's head (width 1.0, ``fc_kernel=7``), ``classifier.0``/``classifier.3`` are
    reshaped into the convolutions fc6 (4096 x 512 x 7 x 7) and fc7 (4096 x 4096 x 1 x 1), as in
    the FCN paper.

    Args:
        model: the network to initialise (in place).
        path: the weights file.
        strict: fail when a backbone tensor is missing or has another shape.

    Returns:
        Names of the tensors of ``model`` that were loaded.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"VGG-16 weights file {path}: not found (weights are never downloaded)")
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict):
        raise InputError(f"VGG-16 weights file {path}: expected a state dict, got {type(state).__name__}")
    if any(k.startswith("features.") for k in state):
        features = {k[len("features."):]: v for k, v in state.items() if k.startswith("features.")}
    else:
        features = dict(state)
    own = model.backbone.state_dict()
    mismatched = [
        f"{k}: file {tuple(features[k].shape)} vs model {tuple(v.shape)}"
        for k, v in own.items() if k in features and features[k].shape != v.shape
    ]
    missing = [k for k in own if k not in features]
    if strict and (mismatched or missing):
        raise InputError(
            f"VGG-16 weights file {path}: does not fit the backbone (width_mult must be 1.0 and the "
            f"batch_norm setting must match); missing {missing[:4]}, mismatched {mismatched[:4]}"
        )
    usable = {k: features[k] for k in own if k in features and features[k].shape == own[k].shape}
    model.backbone.load_state_dict(usable, strict=False)
    loaded = [f"backbone.{k}" for k in usable]
    fc = {"fc6": "classifier.0", "fc7": "classifier.3"}
    for name, src in fc.items():
        w, b = state.get(f"{src}.weight"), state.get(f"{src}.bias")
        conv: nn.Conv2d = getattr(model, name)
        if w is None or b is None or w.numel() != conv.weight.numel() or b.shape != conv.bias.shape:
            continue
        with torch.no_grad():
            conv.weight.copy_(w.reshape(conv.weight.shape))
            conv.bias.copy_(b)
        loaded += [f"{name}.weight", f"{name}.bias"]
    logger.info("loaded %d VGG-16 tensors from %s", len(loaded), path)
    return loaded


class _Aligned(nn.Module):
    """Export wrapper: the graph is :meth:`FCN8s.forward_aligned` (no data-dependent padding)."""

    def __init__(self, model: FCN8s) -> None:
        super().__init__()
        self.model = model

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model.forward_aligned(x)


def export_onnx(
    model: FCN8s,
    path: str | Path,
    *,
    sample_size: tuple[int, int] = (192, 640),
    metadata: dict[str, str] | None = None,
    half_weights: bool = False,
) -> Path:
    """Export ``model`` (in eval mode) to ONNX with dynamic batch, height and width.

    The graph is :meth:`FCN8s.forward_aligned`: input ``image`` (B, 3, H, W) RGB in [0, 1] with H
    and W multiples of 32 (the caller pads; :mod:`monostixels.inputs.semantic` does), output
    ``scores`` (B, num_classes, H, W) logits. Batch norm is folded into the convolutions.

    Args:
        model: the network.
        path: where to write the ``.onnx`` file.
        sample_size: (H, W) of the tracing input, multiples of 32.
        metadata: key/value strings stored in the model's ``metadata_props``.
        half_weights: store the large weight tensors as float16, each followed by a ``Cast`` to
            float32 (ONNX Runtime folds the casts when it loads the model): half the file size,
            and the network computes in float32 with float16-rounded weights.

    Returns:
        The written path.
    """
    import onnx  # local import: only needed for export

    if sample_size[0] % OUTPUT_STRIDE or sample_size[1] % OUTPUT_STRIDE:
        raise InputError(f"sample_size: must be multiples of {OUTPUT_STRIDE}, got {sample_size}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    was_training = model.training
    model.eval()
    x = torch.rand(1, 3, *sample_size)
    axes = {0: "batch", 2: "height", 3: "width"}
    with warnings.catch_warnings():
        # The TorchScript exporter is deprecated in favour of torch.export + onnxscript, which is
        # not a dependency; the TorchScript path handles our static graph exactly.
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(
            _Aligned(model), (x,), str(path), dynamo=False, opset_version=ONNX_OPSET,
            input_names=[ONNX_INPUT], output_names=[ONNX_OUTPUT],
            dynamic_axes={ONNX_INPUT: axes, ONNX_OUTPUT: axes},
        )
    model.train(was_training)
    if metadata or half_weights:
        proto = onnx.load(str(path))
        if half_weights:
            store_half_weights(proto)
        for key, value in (metadata or {}).items():
            entry = proto.metadata_props.add()
            entry.key, entry.value = str(key), str(value)
        onnx.checker.check_model(proto)
        onnx.save(proto, str(path))
    logger.info("exported %s", path)
    return path


#: Weight tensors with at least this many values are stored as float16 by ``half_weights``.
_HALF_MIN_SIZE = 1024


def store_half_weights(proto) -> None:
    """Replace each large float32 initializer of an ONNX ``ModelProto`` by a float16 one and a Cast back
    to float32 (ONNX Runtime folds the casts at load): half the file, float16-rounded weights."""
    from onnx import TensorProto, helper, numpy_helper

    graph = proto.graph
    casts = []
    for init in graph.initializer:
        if init.data_type != TensorProto.FLOAT:
            continue
        arr = numpy_helper.to_array(init)
        if arr.size < _HALF_MIN_SIZE:
            continue
        name = init.name
        init.CopyFrom(numpy_helper.from_array(arr.astype("float16"), name=f"{name}__fp16"))
        casts.append(helper.make_node("Cast", [f"{name}__fp16"], [name], to=TensorProto.FLOAT,
                                      name=f"{name}__cast"))
    # Casts first: every consumer comes after its producer (ONNX graphs are topologically sorted).
    nodes = casts + list(graph.node)
    del graph.node[:]
    graph.node.extend(nodes)


def save_fcn8s(model: FCN8s, path: str | Path, *, arch: dict, meta: dict | None = None,
               half: bool = False) -> Path:
    """Save a model file ``{"arch": builder kwargs, "state_dict": ..., "meta": ...}``.

    Args:
        model: the network.
        path: output ``.pt`` path.
        arch: the keyword arguments of :func:`fcn8s_vgg16` that rebuild the architecture.
        meta: anything worth keeping (training command, mIoU, scale).
        half: store floating tensors as float16 (half the size; loaded back as float32).

    Returns:
        The written path.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: (v.half() if half and v.is_floating_point() else v) for k, v in model.state_dict().items()}
    torch.save({"arch": dict(arch), "state_dict": state, "meta": dict(meta or {})}, path)
    return path


def load_fcn8s_state(model: FCN8s, state: dict[str, torch.Tensor]) -> list[str]:
    """Load ``state`` into ``model``; an FCN-8s's state into a ``skip_pool2`` model is allowed.

    That one start keeps the new layers as initialised (pool2's scores zero, the 2x upsampler bilinear)
    and drops the FCN-8s's fixed 8x upsampler: the fine-tuning of an FCN-8s into the stride-4 net.

    Returns:
        The names of ``model``'s tensors left at their initial values (empty for a full match).

    Raises:
        RuntimeError: any other mismatch (as ``load_state_dict``).
    """
    state = {k: v.float() if v.is_floating_point() else v for k, v in state.items()}
    own = model.state_dict()
    if model.skip_pool2 and not any(k in state for k in SKIP_POOL2_KEYS) and "upscore8.weight" in state:
        state = {k: v for k, v in state.items() if k != "upscore8.weight"}
        model.load_state_dict({**state, **{k: own[k] for k in SKIP_POOL2_KEYS}})
        return list(SKIP_POOL2_KEYS)
    model.load_state_dict(state)
    return []


def load_fcn8s(path: str | Path) -> tuple[FCN8s, dict]:
    """Load a file written by :func:`save_fcn8s` (or a training checkpoint) in eval mode.

    Args:
        path: the ``.pt`` file.

    Returns:
        ``(model, meta)``.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"FCN-8s weights file {path}: not found")
    blob = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(blob, dict) or "arch" not in blob or "state_dict" not in blob:
        raise InputError(f"FCN-8s weights file {path}: expected a dict with 'arch' and 'state_dict'")
    model = fcn8s_vgg16(**blob["arch"])
    load_fcn8s_state(model, blob["state_dict"])
    return model.eval(), dict(blob.get("meta", {}))
