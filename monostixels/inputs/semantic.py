"""Semantic backends: 10-class pixel-wise scores for the stixel energy (config group ``semantic``).

Every backend returns a (10, H, W) float32 tensor of pseudo-probabilities (each pixel sums to 1)
in ``monostixels.core.classes.CLASS_NAMES`` order, or None for ``none``
(docs/conventions.md, sections 4.9 and 5):

- ``gt``: one-hot ground-truth labels, softened: the true class gets ``confidence``, the others
  ``(1 - confidence) / 9``; pixels with ``IGNORE_LABEL`` get the uniform 0.1.
- ``fcn8s``: the FCN-8s shipped in ``models/`` (trained by ``train/semantic.py`` on synthetic
  scenes), run through ONNX Runtime (``runtime: onnx``, default) or torch (``runtime: torch``).
- ``onnx``: any user ONNX model; ``mapping`` sends each of its classes to one of ours (or -1 =
  dropped); the softmax scores of model classes mapped to the same id are summed.
- ``none``: no semantic input.

Preprocessing of the network backends (documented once, shared): the image (3, H, W) RGB [0, 1]
is resized (bilinear, antialiased) either to ``input_size`` (H', W') or by ``scale``; normalised
by ``mean``/``std``; padded bottom/right to a multiple of ``pad_to`` with the mean colour; the
network's output logits are cropped to the unpadded region, upsampled bilinearly to (H, W), and
turned into probabilities by a softmax over the model's channels.

Model paths (:mod:`monostixels._paths`): an absolute path is used as it is; a relative one is
tried against the working directory, then ``models/...`` against the shipped models (installed
with the package, editable or not), then against the repository root.

Settings: one dataclass per backend (:data:`SEMANTIC_SCHEMAS`), the schemas of the group's options
(monostixels.config_schema); a config node or dict is read through them (:func:`semantic_params`).
"""
from __future__ import annotations

import functools
import logging
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Union

import numpy as np
import torch
import torch.nn.functional as F
from omegaconf import MISSING

from monostixels._checks import (InputError, check_finite_fast, check_shape, config_params, choice,
                                 is_unset, option_params)
from monostixels._paths import REPO_ROOT, find_file, path_candidates
from monostixels._threads import onnx_session_options
from monostixels.core.classes import CLASS_NAMES, IGNORE_LABEL, NUM_CLASSES
from monostixels.data.base import FramePair

__all__ = [
    "SEMANTIC_SCHEMAS",
    "GtSemanticConfig",
    "NoSemanticConfig",
    "Fcn8sSemanticConfig",
    "SemanticRuntime",
    "OnnxSemanticConfig",
    "semantic_params",
    "estimate_semantics",
    "fcn8s_scale",
    "gt_scores",
    "resolve_model_path",
    "OnnxSegmenter",
    "TorchSegmenter",
    "map_scores",
    "CITYSCAPES19_CLASSES",
    "CITYSCAPES19_MAPPING",
    "onnx_segmenter",
    "REPO_ROOT",
    "confusion_matrix",
    "iou_from_confusion",
    "quantize_fcn8s_onnx",
]

logger = logging.getLogger(__name__)


@dataclass
class GtSemanticConfig:
    """``semantic=gt``: the data source's labels as one-hot scores, softened.

    Attributes:
        confidence: the score of the true class; the other classes share the remainder.
    """

    name: str = "gt"
    confidence: float = 0.9


@dataclass
class NoSemanticConfig:
    """``semantic=none``: no semantic input (delta_L = 0; types from flow and priors alone).

    Attributes:
        prior_overrides: prior values (:class:`monostixels.core.energy.PriorConfig`) that replace those of the
            ``prior`` group (merged by the Pipeline; the values of ``prior=nosem``). Without semantics the
            2-DOF dynamic-object type fits any flow at least as well as the 1-DOF static types; ``alpha_dyn``
            (cost per pixel row of a dynamic stixel) keeps it for flow the static types cannot explain.
    """

    name: str = "none"
    prior_overrides: Dict[str, float] = field(default_factory=lambda: {"alpha_dyn": 0.25})


#: Where the FCN-8s runs (``semantic.runtime``): ONNX Runtime or PyTorch; OmegaConf refuses any other value.
SemanticRuntime = choice("SemanticRuntime", "onnx torch", __name__)


@dataclass
class Fcn8sSemanticConfig:
    """``semantic=fcn8s``: our FCN-8s (models/MODEL_CARD.md), the real-image net by default;
    ``semantic=fcn8s_synthetic`` is the net of our renders.

    Attributes:
        runtime: ``onnx`` (ONNX Runtime) | ``torch`` (the .pt state dict through PyTorch).
        model: the ONNX file (relative paths: module docstring).
        weights: the .pt file of ``runtime=torch``.
        focal_px: with a calibrated camera (every frame-pair source) the image is resized so that its focal
            length becomes this many pixels: objects then appear at the angular resolution of training
            (:func:`fcn8s_scale`); None = ``scale``.
        scale: resize factor of the image before the net where ``focal_px`` does not apply (images without a
            calibration, CamVid's evaluation); None = full resolution.
    """

    name: str = "fcn8s"
    runtime: SemanticRuntime = SemanticRuntime.onnx
    model: Optional[str] = "models/fcn8s_real.onnx"
    weights: Optional[str] = "models/fcn8s_real.pt"
    focal_px: Optional[float] = 480.0
    scale: Optional[float] = 1.0


@dataclass
class OnnxSemanticConfig:
    """``semantic=onnx``: any segmentation model in ONNX, input (1, 3, h, w) float32 RGB, output (1, C, h', w')
    scores (h'/w' may be a stride of h/w); ``semantic=cityscapes19`` sets it up for Cityscapes models.

    Attributes:
        model: the ONNX file (mandatory).
        input_size: ``[h, w]`` the image is resized to; None = the model's static input size if it declares
            one, else the image resized by ``scale``.
        scale: resize factor where there is no input size; None = full resolution.
        mean, std: normalisation of the RGB [0, 1] image fed to the model, ``(x - mean) / std`` per channel.
        pad_to: pad the (resized) input bottom/right to a multiple of this (e.g. 32 for FCN/VGG models).
        softmax: the model outputs logits (softmax applied here); False: probabilities.
        mapping: one entry per model output channel: our class id (0 road, 1 sidewalk, 2 terrain, 3 building,
            4 pole, 5 vegetation, 6 vehicle, 7 two_wheeler, 8 person, 9 sky) or -1 to drop it; the
            probabilities of channels mapped to the same id are summed. None = the model outputs our 10
            classes in this order.
    """

    name: str = "onnx"
    model: str = MISSING
    input_size: Optional[List[int]] = None
    scale: Optional[float] = None
    mean: List[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    std: List[float] = field(default_factory=lambda: [1.0, 1.0, 1.0])
    pad_to: int = 1
    softmax: bool = True
    mapping: Optional[List[int]] = None


#: The schema of each semantic backend by its ``name`` (``fcn8s_synthetic`` and ``cityscapes19`` are options
#: of ``fcn8s`` and ``onnx`` with other values).
SEMANTIC_SCHEMAS: dict[str, type] = {"gt": GtSemanticConfig, "none": NoSemanticConfig, "fcn8s": Fcn8sSemanticConfig,
                                     "onnx": OnnxSemanticConfig}

#: The settings of any semantic backend.
SemanticConfig = Union[GtSemanticConfig, NoSemanticConfig, Fcn8sSemanticConfig, OnnxSemanticConfig]


def semantic_params(cfg: Any) -> SemanticConfig:
    """The settings of a ``semantic`` config node (or dict) as its backend's dataclass
    (:data:`SEMANTIC_SCHEMAS`); a dataclass given is returned as it is."""
    if not isinstance(cfg, OnnxSemanticConfig) and hasattr(cfg, "get") and cfg.get("name") == "onnx":
        return onnx_params(cfg)  # its model first, with a message of its own
    return option_params(SEMANTIC_SCHEMAS, cfg, "semantic")


def onnx_params(cfg: Any) -> OnnxSemanticConfig:
    """The settings of the ``onnx`` backend (a node, dict or the dataclass), its model required."""
    if not isinstance(cfg, OnnxSemanticConfig) and is_unset(cfg, "model"):
        raise InputError("semantic.model: semantic=onnx needs the path of an ONNX model "
                         "(semantic.model=/path/to/model.onnx)")
    return config_params(OnnxSemanticConfig, cfg, "semantic")

#: Stride the shipped FCN-8s needs its input padded to (five 2x2 pools).
FCN8S_PAD_TO = 32

#: Relative difference allowed between the vertical and horizontal output strides of a model
#: (rounding of odd sizes at stride 8-32 stays well inside it; a transposed output does not).
_STRIDE_TOLERANCE = 0.15

#: The 19 Cityscapes training classes (trainId order, Cordts et al. 2016).
CITYSCAPES19_CLASSES: tuple[str, ...] = (
    "road", "sidewalk", "building", "wall", "fence", "pole", "traffic light", "traffic sign",
    "vegetation", "terrain", "sky", "person", "rider", "car", "truck", "bus", "train",
    "motorcycle", "bicycle",
)
_OURS = {name: i for i, name in enumerate(CLASS_NAMES)}
#: Cityscapes trainId -> our class id (the same list ships as ``conf/semantic/cityscapes19.yaml``).
CITYSCAPES19_MAPPING: tuple[int, ...] = (
    _OURS["road"], _OURS["sidewalk"],
    _OURS["building"], _OURS["building"], _OURS["building"],        # building, wall, fence
    _OURS["pole"], _OURS["pole"], _OURS["pole"],                    # pole, traffic light, sign
    _OURS["vegetation"], _OURS["terrain"], _OURS["sky"],
    _OURS["person"], _OURS["person"],                               # person, rider
    _OURS["vehicle"], _OURS["vehicle"], _OURS["vehicle"], _OURS["vehicle"],  # car..train
    _OURS["two_wheeler"], _OURS["two_wheeler"],                     # motorcycle, bicycle
)


def estimate_semantics(pair: FramePair, cfg: Any, *, threads: int = 0) -> torch.Tensor | None:
    """Semantic class scores of the current image of ``pair``.

    Args:
        pair: the frame pair (only ``pair.image`` and, for ``gt``, ``pair.gt.labels`` are used).
        cfg: the ``semantic`` config node (a dict, or the settings dataclass); ``cfg.name`` in
            ``gt | fcn8s | onnx | none``; keys not given take the defaults of the option of that name.
        threads: ONNX Runtime intra-op threads of the network (0 = the process's, config key
            ``threads``: :func:`monostixels._threads.onnx_session_options`). The scores do not
            depend on it. The pipeline passes 1 when the semantics run beside the flow: a pool of
            ORT threads there takes the cores DeepFlow's strips need.

    Returns:
        (10, H, W) float32 scores summing to 1 per pixel, classes in ``CLASS_NAMES`` order; or
        None for ``none``.
    """
    name = cfg.name if isinstance(cfg, tuple(SEMANTIC_SCHEMAS.values())) else str((cfg or {}).get("name", ""))
    if name not in SEMANTIC_SCHEMAS:
        raise InputError(f"semantic.name: unknown backend {name!r}; expected gt, fcn8s, onnx or none")
    cfg = semantic_params(cfg)
    if name == "none":
        return None
    if name == "gt":
        if pair.gt.labels is None:
            info = pair.info
            source = next((s for s in (info.source, info.dataset) if s is not None), "this data source")
            raise InputError(
                f"semantic=gt: frame {pair.name or '?'} from {source} has no ground-truth labels "
                "(pair.gt.labels is None); use semantic=fcn8s, semantic=onnx or semantic=none"
            )
        return gt_scores(pair.gt.labels, confidence=cfg.confidence,
                         name=f"{pair.name or 'frame'}: gt.labels")
    if name == "fcn8s":
        return _fcn8s_segmenter(cfg, threads)(pair.image, scale=fcn8s_scale(pair, cfg))
    return onnx_segmenter(cfg, threads=threads)(pair.image)


def fcn8s_scale(pair: FramePair, cfg: Any) -> float | None:
    """Resize factor of the image before our FCN-8s: ``focal_px / fx`` or ``scale``.

    With ``semantic.focal_px`` set and a calibrated camera, the image is resized so that its focal
    length becomes ``focal_px`` pixels: the net then sees objects at the angular resolution it was
    trained at, whatever the camera (KITTI fx 721 px and 1242 wide, DDAD fx ~2200 px). A pair
    whose camera is nominal (``pair.info.nominal_camera``: single labelled images such as
    CamVid, which carry no calibration) uses ``semantic.scale``.

    Returns:
        the factor, or None (full resolution).
    """
    cfg = config_params(Fcn8sSemanticConfig, cfg, "semantic")
    focal = cfg.focal_px
    if focal is not None and not pair.info.nominal_camera:
        fx = float(pair.camera.K[0, 0])
        if not (focal > 0 and fx > 0):
            raise InputError(f"semantic.focal_px: needs a positive value and camera fx, got {focal} and {fx}")
        return focal / fx
    return cfg.scale


def gt_scores(labels: torch.Tensor, *, confidence: float = 0.9, name: str = "labels") -> torch.Tensor:
    """Softened one-hot scores from class labels.

    Args:
        labels: (H, W) int class ids 0..9, ``IGNORE_LABEL`` (255) where unknown.
        confidence: probability of the labelled class, in [1/10, 1].
        name: the input's name for error messages.

    Returns:
        (10, H, W) float32: ``confidence`` at the label, ``(1 - confidence) / 9`` elsewhere;
        uniform ``1/10`` at ignored pixels.
    """
    check_shape(labels, ["H", "W"], name)
    if not (1.0 / NUM_CLASSES <= confidence <= 1.0):
        raise InputError(f"semantic.confidence: must lie in [{1 / NUM_CLASSES}, 1], got {confidence}")
    labels = labels.long()
    ignore = labels == IGNORE_LABEL
    bad = ~ignore & ((labels < 0) | (labels >= NUM_CLASSES))
    if bool(bad.any()):
        raise InputError(
            f"{name}: {int(bad.sum())} pixels with ids outside 0..{NUM_CLASSES - 1} and not "
            f"{IGNORE_LABEL} (e.g. {int(labels[bad][0])})"
        )
    other = (1.0 - confidence) / (NUM_CLASSES - 1)
    scores = torch.full((NUM_CLASSES, *labels.shape), other, dtype=torch.float32)
    scores.scatter_(0, labels.clamp(0, NUM_CLASSES - 1)[None], confidence)
    scores[:, ignore] = 1.0 / NUM_CLASSES
    return scores


def resolve_model_path(path: str | Path, what: str = "semantic.model") -> Path:
    """Find a model file: absolute as is; relative to the working directory, the shipped models
    (``models/...``) or the repository root (:func:`monostixels._paths.path_candidates`).

    Args:
        path: the configured path.
        what: the config key, for the error message.

    Returns:
        The existing file's path.
    """
    if path is None or str(path) in ("", "???"):
        raise InputError(f"{what}: a model path is required (e.g. {what}=/path/to/model.onnx)")
    found = find_file(path)
    if found is None:
        looked = ", ".join(map(str, path_candidates(path)))
        raise InputError(f"{what}: model file {path} not found (looked in {looked})")
    return found


def map_scores(probs: torch.Tensor, mapping: Sequence[int] | None, *, model: str = "model") -> torch.Tensor:
    """Sum model-class probabilities into our 10 classes.

    Args:
        probs: (C, H, W) probabilities over the model's C classes.
        mapping: length C, our class id (0..9) per model class or -1 to drop it; None = identity
            (then C must be 10).
        model: the model's name for error messages.

    Returns:
        (10, H, W) float32 summing to 1 per pixel: the kept mass is renormalised; where a pixel's
        whole mass was dropped the scores are uniform (no evidence).
    """
    C = int(probs.shape[0])
    if mapping is None:
        if C != NUM_CLASSES:
            raise InputError(
                f"{model}: outputs {C} channels but no semantic.mapping is configured; a model "
                f"without a mapping must output {NUM_CLASSES} channels ({', '.join(CLASS_NAMES)})"
            )
        return probs.float()
    ids = [int(m) for m in mapping]
    if len(ids) != C:
        raise InputError(
            f"{model}: outputs {C} channels but semantic.mapping has {len(ids)} entries "
            "(one per model class is required)"
        )
    bad = [m for m in ids if not (m == -1 or 0 <= m < NUM_CLASSES)]
    if bad:
        raise InputError(f"semantic.mapping: entries must be -1 or 0..{NUM_CLASSES - 1}, got {bad}")
    keep = torch.tensor([i for i, m in enumerate(ids) if m >= 0], dtype=torch.long)
    target = torch.tensor([m for m in ids if m >= 0], dtype=torch.long)
    out = torch.zeros((NUM_CLASSES, *probs.shape[1:]), dtype=torch.float32)
    out.index_add_(0, target, probs.float()[keep])
    total = out.sum(0, keepdim=True)
    # A pixel whose model classes were all dropped carries no evidence: uniform.
    empty = total <= torch.finfo(torch.float32).tiny
    out = torch.where(empty, torch.full_like(out, 1.0 / NUM_CLASSES), out / total.clamp_min(1e-30))
    return out


def _preprocess(
    image: torch.Tensor,
    *,
    input_size: Sequence[int] | None,
    scale: float | None,
    mean: Sequence[float],
    std: Sequence[float],
    pad_to: int,
) -> tuple[torch.Tensor, tuple[int, int]]:
    """Resize, normalise and pad (see the module docstring).

    Returns:
        ((1, 3, h_pad, w_pad) float32 network input, (h, w) unpadded size).
    """
    check_shape(image, [3, "H", "W"], "image")
    check_finite_fast(image, "image")
    H, W = int(image.shape[-2]), int(image.shape[-1])
    x = image.float()[None]
    if input_size is not None:
        size = (int(input_size[0]), int(input_size[1]))
    elif scale is not None and float(scale) != 1.0:
        size = (max(1, round(H * float(scale))), max(1, round(W * float(scale))))
    else:
        size = (H, W)
    if size != (H, W):
        x = F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)
    m = torch.tensor([float(v) for v in mean]).view(1, 3, 1, 1)
    s = torch.tensor([float(v) for v in std]).view(1, 3, 1, 1)
    x = (x - m) / s
    ph, pw = (-size[0]) % pad_to, (-size[1]) % pad_to
    if ph or pw:
        # Zero after normalisation = the mean colour.
        x = F.pad(x, (0, pw, 0, ph))
    return x.contiguous(), size


def _postprocess(logits: torch.Tensor, size: tuple[int, int], out_hw: tuple[int, int],
                 in_hw: tuple[int, int], model: str) -> torch.Tensor:
    """Check the output (1, C, h, w), crop the padding, upsample to ``out_hw``, softmax.

    Returns:
        (C, H, W) float32 probabilities.
    """
    if logits.ndim != 4 or logits.shape[0] != 1:
        raise InputError(
            f"{model}: expected an output of shape (1, C, h, w), got {tuple(logits.shape)}"
        )
    h, w = int(logits.shape[-2]), int(logits.shape[-1])
    if h < 1 or w < 1:
        raise InputError(f"{model}: empty output of shape {tuple(logits.shape)}")
    # The output may be at a lower resolution (a stride) than the network input, but both sides
    # must shrink by the same factor; otherwise the scores cannot be placed on the image.
    sh, sw = in_hw[0] / h, in_hw[1] / w
    if abs(sh - sw) > _STRIDE_TOLERANCE * max(sh, sw):
        raise InputError(
            f"{model}: output of shape {tuple(logits.shape)} does not fit the input of size "
            f"{in_hw} (H, W): strides {sh:.2f} vs {sw:.2f}"
        )
    # Crop what belongs to the unpadded input.
    ch, cw = max(1, round(size[0] / sh)), max(1, round(size[1] / sw))
    logits = logits[..., :ch, :cw].float()
    check_finite_fast(logits, f"{model}: output")
    logits = F.interpolate(logits, size=out_hw, mode="bilinear", align_corners=False)
    return torch.softmax(logits[0], dim=0)


class OnnxSegmenter:
    """A segmentation model run through ONNX Runtime.

    Args:
        path: the ``.onnx`` file (input (1, 3, h, w) float32, output (1, C, h', w') scores).
        input_size: (h, w) the image is resized to; None = the model's static input size if it
            declares one, else the image is resized by ``scale``.
        scale: resize factor used when ``input_size`` is None (None or 1 = full resolution).
        mean: per-channel mean subtracted from the RGB [0, 1] image.
        std: per-channel std the image is divided by.
        mapping: model class -> our class id (or -1), None = identity (C must be 10).
        pad_to: pad the network input to a multiple of this (32 for FCN-8s; 1 = none).
        softmax: the model outputs logits (True) or probabilities already (False).
        threads: ONNX Runtime intra-op threads (0 = the process's, config key ``threads``).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        input_size: Sequence[int] | None = None,
        scale: float | None = None,
        mean: Sequence[float] = (0.0, 0.0, 0.0),
        std: Sequence[float] = (1.0, 1.0, 1.0),
        mapping: Sequence[int] | None = None,
        pad_to: int = 1,
        softmax: bool = True,
        threads: int = 0,
    ) -> None:
        import onnxruntime as ort  # local: only the network backends need it

        self.path = Path(path)
        options = onnx_session_options(max(0, int(threads)))
        try:
            self.session = ort.InferenceSession(str(self.path), options, providers=["CPUExecutionProvider"])
        except Exception as err:  # onnxruntime raises its own exception types
            raise InputError(f"ONNX model {self.path}: cannot be loaded ({err})") from err
        inputs = self.session.get_inputs()
        if len(inputs) != 1:
            raise InputError(f"ONNX model {self.path}: expected one input, found {len(inputs)}")
        self.input_name = inputs[0].name
        shape = list(inputs[0].shape)
        if len(shape) != 4 or (isinstance(shape[1], int) and shape[1] != 3):
            raise InputError(
                f"ONNX model {self.path}: expected an input of shape (1, 3, h, w), it declares {shape}"
            )
        static = all(isinstance(d, int) and d > 0 for d in shape[2:])
        if input_size is None and static:
            input_size = (int(shape[2]), int(shape[3]))
        self.input_size = None if input_size is None else (int(input_size[0]), int(input_size[1]))
        if len(mean) != 3 or len(std) != 3:
            raise InputError(f"semantic.mean/std: need 3 values (RGB), got {list(mean)} / {list(std)}")
        self.scale, self.mean, self.std = scale, tuple(mean), tuple(std)
        self.mapping = None if mapping is None else [int(m) for m in mapping]
        self.pad_to = max(1, int(pad_to))
        self.softmax = softmax

    def logits(self, image: torch.Tensor, scale: float | None = None) -> tuple[torch.Tensor, tuple[int, int], tuple[int, int]]:
        """Raw network output for ``image`` (3, H, W): ((1, C, h, w), unpadded size, input size).

        ``scale`` replaces the configured resize factor for this call (None = the configured one).
        """
        x, size = _preprocess(image, input_size=self.input_size, scale=self.scale if scale is None else scale,
                              mean=self.mean, std=self.std, pad_to=self.pad_to)
        try:
            out = self.session.run(None, {self.input_name: x.numpy()})[0]
        except Exception as err:
            raise InputError(
                f"ONNX model {self.path}: inference failed on an input of shape {tuple(x.shape)} ({err})"
            ) from err
        return torch.from_numpy(np.asarray(out, dtype=np.float32)), size, (int(x.shape[-2]), int(x.shape[-1]))

    def __call__(self, image: torch.Tensor, scale: float | None = None) -> torch.Tensor:
        """(10, H, W) float32 class probabilities of ``image`` (3, H, W) RGB [0, 1]; ``scale`` as in
        :meth:`logits`."""
        out, size, in_hw = self.logits(image, scale)
        name = f"ONNX model {self.path}"
        if out.ndim == 4 and self.mapping is not None and out.shape[1] != len(self.mapping):
            hint = ""
            if out.shape[1] == len(self.mapping) + 1:
                # E.g. a Cityscapes model with a 20th "background" channel (semantic=cityscapes19).
                hint = (f"; to drop the model's last channel, append -1 to the mapping "
                        f"(semantic.mapping=[{','.join(map(str, self.mapping))},-1])")
            raise InputError(
                f"{name}: outputs {out.shape[1]} channels but semantic.mapping has "
                f"{len(self.mapping)} entries (one per model class is required){hint}"
            )
        if out.ndim == 4 and self.mapping is None and out.shape[1] != NUM_CLASSES:
            raise InputError(
                f"{name}: outputs {out.shape[1]} channels, expected {NUM_CLASSES} "
                f"({', '.join(CLASS_NAMES)}); configure semantic.mapping for other class sets"
            )
        if not self.softmax:
            out = out.clamp_min(1e-12).log()
        probs = _postprocess(out, size, tuple(image.shape[-2:]), in_hw, name)
        return map_scores(probs, self.mapping, model=name)


class TorchSegmenter:
    """The FCN-8s run in torch from a ``.pt`` file written by ``save_fcn8s``.

    Args:
        path: the ``.pt`` file.
        scale: resize factor of the image before the network (the training scale).
    """

    def __init__(self, path: str | Path, *, scale: float | None = None) -> None:
        from monostixels.inputs.fcn8s import load_fcn8s

        self.path = Path(path)
        self.model, self.meta = load_fcn8s(self.path)
        self.scale = scale

    @torch.no_grad()
    def __call__(self, image: torch.Tensor, scale: float | None = None) -> torch.Tensor:
        """(10, H, W) float32 class probabilities of ``image`` (3, H, W) RGB [0, 1]; ``scale``
        replaces the configured resize factor for this call (None = the configured one)."""
        # Normalisation is inside the model: feed RGB [0, 1].
        x, size = _preprocess(image, input_size=None, scale=self.scale if scale is None else scale, mean=(0, 0, 0),
                              std=(1, 1, 1), pad_to=FCN8S_PAD_TO)
        out = self.model.forward_aligned(x)
        name = f"FCN-8s {self.path}"
        if out.shape[1] != NUM_CLASSES:
            raise InputError(f"{name}: outputs {out.shape[1]} channels, expected {NUM_CLASSES}")
        return _postprocess(out, size, tuple(image.shape[-2:]), tuple(x.shape[-2:]), name)


def _fcn8s_segmenter(cfg: Fcn8sSemanticConfig, threads: int = 0) -> OnnxSegmenter | TorchSegmenter:
    runtime, scale = cfg.runtime, cfg.scale
    if runtime == "onnx":
        path = resolve_model_path(cfg.model, "semantic.model")
        path = Path(_int8_checked(str(path), path.stat().st_mtime_ns))
        return _cached_onnx(str(path), path.stat().st_mtime_ns, None, scale,
                            (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), None, FCN8S_PAD_TO, True, int(threads))
    # runtime=torch (the schema admits no other: SemanticRuntime)
    path = resolve_model_path(cfg.weights, "semantic.weights")
    return _cached_torch(str(path), path.stat().st_mtime_ns, scale)


def onnx_segmenter(cfg: Any, *, threads: int = 0) -> OnnxSegmenter:
    """The ``onnx`` backend's segmenter for a ``semantic`` config node (``model``, ``input_size``,
    ``scale``, ``mean``, ``std``, ``mapping``, ``pad_to``, ``softmax``); one cached session per
    model file and settings (``threads``: ONNX Runtime intra-op threads, 0 = the process's). Also the
    teacher of ``train.semantic``'s distillation."""
    cfg = onnx_params(cfg)
    path = resolve_model_path(cfg.model, "semantic.model")
    size, mapping = cfg.input_size, cfg.mapping
    return _cached_onnx(
        str(path), path.stat().st_mtime_ns,
        None if size is None else tuple(size),
        cfg.scale, tuple(cfg.mean), tuple(cfg.std),
        None if mapping is None else tuple(mapping),
        cfg.pad_to, cfg.softmax, int(threads),
    )


@functools.lru_cache(maxsize=4)
def _int8_checked(path: str, mtime: int) -> str:
    """The FCN-8s file to run for ``path``: ``path`` itself, unless it is an INT8 copy whose weights can
    saturate (:func:`monostixels.inputs.quantize.can_saturate`) and this CPU has no VNNI; then the float
    file it was made from (its ``int8_from``, beside it), with one warning. An INT8 file's CPU path is
    logged (``summary.json`` ``platform`` records it too)."""
    import onnx
    import onnxruntime

    from monostixels._cpu import cpu_info, int8_path
    from monostixels.inputs.quantize import can_saturate

    meta = {p.key: p.value for p in onnx.load(path).metadata_props}
    if meta.get("quantized") != "int8":
        return path
    route = int8_path()
    logger.info("semantic: INT8 net %s, ONNX Runtime %s on %s: its %s path", path, onnxruntime.__version__,
                cpu_info()["model"], route)
    if route != "no_vnni" or not can_saturate(path):
        return path
    src = Path(path).with_name(meta.get("int8_from", "")) if meta.get("int8_from") else None
    if src is None or not src.is_file():
        logger.warning("semantic: %s has 8-bit weights, which can saturate on this CPU (no VNNI), and no float "
                       "file beside it; its labels may differ from the float net's", path)
        return path
    logger.warning("semantic: %s has 8-bit weights, which can saturate on this CPU (no VNNI): running the float "
                   "net %s instead", path, src)
    return str(src)


def quantize_fcn8s_onnx(src: str | os.PathLike, dst: str | os.PathLike, images: Iterable[torch.Tensor],
                        scale: float = 1.0, *, reduce_range: bool = True) -> Path:
    """An INT8 copy of an FCN-8s ONNX file (:func:`monostixels.inputs.fcn8s.export_onnx`: input ``image``
    (1, 3, h, w) RGB in [0, 1], ImageNet normalisation inside the graph).

    Args:
        src: the float file (e.g. ``models/fcn8s_real.onnx``).
        dst: the INT8 file to write.
        images: calibration images (3, H, W) RGB in [0, 1]; each is resized by ``scale`` and padded to a
            multiple of 32, as ``semantic=fcn8s`` feeds the net.
        scale: resize factor of the calibration images.
        reduce_range: weights in 7 bits (:func:`~monostixels.inputs.quantize.quantize_convolutions`); False:
            8 bits, which can saturate.

    Returns:
        ``dst``, with the float file's metadata, ``quantized: int8`` and ``int8_from`` (the float file's name).

    Weights in 7 bits (:func:`~monostixels.inputs.quantize.quantize_convolutions`' ``reduce_range``). The first
    convolution (the image's 3 channels) stays float32: so the net is faster (its INT8 form quantizes the image
    first, for a 3-channel product) and keeps the float net's labels on 0.993 of KITTI 000000_10's
    pixels against 0.987 with all 18 in INT8 (docs/experiments.md, "Every x86 CPU").
    """
    import onnx

    from monostixels.inputs.quantize import quantize_convolutions

    src = Path(src)
    if not src.is_file():
        raise InputError(f"quantize: no ONNX file at {src}")
    proto = onnx.load(str(src))
    if [i.name for i in proto.graph.input] != ["image"]:
        raise InputError(f"quantize: {src} is not an FCN-8s export (one input named 'image'), "
                         f"it has inputs {[i.name for i in proto.graph.input]}")
    meta = {p.key: p.value for p in proto.metadata_props}

    def feeds() -> Iterable[dict[str, np.ndarray]]:
        for image in images:
            # The graph normalises itself: mean 0, std 1 here, as OnnxSegmenter calls it for our nets.
            x, _ = _preprocess(image, input_size=None, scale=scale, mean=(0.0, 0.0, 0.0),
                               std=(1.0, 1.0, 1.0), pad_to=32)
            yield {"image": x.numpy()}

    def reads_the_image(shape: tuple[int, ...]) -> bool:
        return shape[1] == 3

    return quantize_convolutions(proto, dst, feeds(), {**meta, "int8_from": src.name},
                                 reduce_range=reduce_range, keep_float=reads_the_image)


# Sessions are expensive to create; one per (file, modification time, settings, threads).
@functools.lru_cache(maxsize=4)
def _cached_onnx(path: str, mtime: int, input_size, scale, mean, std, mapping, pad_to,
                 softmax: bool = True, threads: int = 0) -> OnnxSegmenter:
    return OnnxSegmenter(path, input_size=input_size, scale=scale, mean=mean, std=std,
                         mapping=mapping, pad_to=pad_to, softmax=softmax, threads=threads)


@functools.lru_cache(maxsize=2)
def _cached_torch(path: str, mtime: int, scale) -> TorchSegmenter:
    return TorchSegmenter(path, scale=scale)


def confusion_matrix(pred: torch.Tensor, labels: torch.Tensor, num_classes: int = NUM_CLASSES) -> torch.Tensor:
    """Confusion counts of predicted vs true class ids.

    Args:
        pred: (...) int predicted class ids 0..num_classes-1.
        labels: (...) int true ids, ``IGNORE_LABEL`` where unknown (not counted).

    Returns:
        (num_classes, num_classes) int64, rows = true class, columns = predicted class.
    """
    valid = labels != IGNORE_LABEL
    idx = labels[valid].long() * num_classes + pred[valid].long()
    return torch.bincount(idx, minlength=num_classes * num_classes).view(num_classes, num_classes)


def iou_from_confusion(conf: torch.Tensor) -> tuple[float, dict[str, float]]:
    """Mean and per-class intersection over union from a confusion matrix.

    Args:
        conf: (10, 10) counts, rows = true class.

    Returns:
        ``(miou, {class name: iou})``; classes absent from both the ground truth and the prediction
        (union 0) are left out of the mean and reported as NaN.
    """
    conf = conf.double()
    tp = conf.diag()
    union = conf.sum(0) + conf.sum(1) - tp
    iou = torch.where(union > 0, tp / union.clamp_min(1), torch.full_like(tp, float("nan")))
    present = union > 0
    miou = float(iou[present].mean()) if bool(present.any()) else float("nan")
    return miou, {name: float(iou[i]) for i, name in enumerate(CLASS_NAMES)}
