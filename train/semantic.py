"""Train the FCN-8s semantic nets, validate per epoch, export to ONNX.

Two configurations (any key can be overridden on the command line):

- ``conf/train_semantic.yaml`` (default): the real-image net ``models/fcn8s_real.*``
  (``semantic=fcn8s``): CamVid train (real labels mapped to our classes by
  :mod:`monostixels.data.camvid`) mixed with ``data.synthetic_per_epoch`` synthetic renders per
  epoch, fine-tuned from the synthetic net; model selection on CamVid val (mIoU over our classes
  present in CamVid). CamVid test is never read here.
- ``conf/train_semantic_synthetic.yaml``: the synthetic net ``models/fcn8s_synthetic.*``
  (``semantic=fcn8s_synthetic``), renders only.

Run from the repository root::

    nice -n 10 python -m train.semantic                       # train + validate + export
    nice -n 10 python -m train.semantic resume=true           # continue from <run_dir>/last.pt
    python -m train.semantic train.epochs=0 resume=true       # evaluate + export the best checkpoint
    nice -n 10 python -m train.semantic --config-name train_semantic_synthetic

Synthetic data: frames of the built-in synthetic benchmark (``monostixels.data.synthetic.render_pair``),
scene seed = source seed x 100_000 + frame. Training uses source seeds >= 10 with domain
randomisation: the renderer's appearance randomisation (textures, colours, lighting, via
``appearance_seed``) on a fraction of the frames, plus photometric augmentation here (brightness,
contrast, saturation, colour cast, gamma, blur, noise) and geometric augmentation (scale jitter,
random crops, horizontal flips), so the net learns the classes, not a lookup of our textures.
Validation: ``val_frames`` frames of source seed 9 (never trained on), default appearance, mIoU
per epoch. Evaluation seeds 0-2 are never touched.

Outputs (``run_dir``): ``last.pt`` (resume state), ``best.pt`` (best validation mIoU), ``final.pt``
(the weights at the end of the schedule; ``export.checkpoint`` picks which of the two is exported),
``history.json`` (loss and mIoU per epoch), ``result.json`` (final validation of the exported ONNX
model through ``monostixels.inputs.semantic``, per-class IoU, the exact command).
"""
from __future__ import annotations

import glob
import json
import logging
import math
import os
import shlex
import sys
import time
from pathlib import Path
from typing import Any, Callable, NamedTuple, Sequence

import cv2
import hydra
import numpy as np
import torch
import torch.nn.functional as F
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import ConcatDataset, DataLoader, Dataset, SubsetRandomSampler
from tqdm import tqdm

from monostixels._checks import InputError, one_line_errors
from monostixels.core.classes import CLASS_NAMES, IGNORE_LABEL, NUM_CLASSES
from monostixels.data.camvid import CAMVID_CLASSES_PRESENT, CamVidItem, CamVidSource, read_camvid_split
from monostixels.eval.metrics import SemanticAccumulator
from monostixels.eval.semantic import image_pair
from monostixels.inputs.fcn8s import (FCN8s, export_onnx, fcn8s_vgg16, load_fcn8s, load_fcn8s_state, load_vgg16_backbone,
                                      save_fcn8s)
from monostixels.inputs.semantic import estimate_semantics, onnx_segmenter

__all__ = [
    "SEED_STRIDE",
    "scene_seed",
    "SyntheticSegmentation",
    "RealSegmentation",
    "DistillFrame",
    "PseudoLabelled",
    "distill_frames",
    "augment",
    "build_model",
    "train_steps",
    "Schedule",
    "evaluate",
    "interpolate_weights",
    "main",
]

logger = logging.getLogger("train.semantic")

#: Scene seed of frame i of source seed s is s * SEED_STRIDE + i (monostixels.data.synthetic).
SEED_STRIDE = 100_000
#: Name of the Hydra config (conf/train_semantic.yaml).
CONFIG_NAME = "train_semantic"


def scene_seed(source_seed: int, frame: int) -> int:
    """Scene seed of ``frame`` of the synthetic source with seed ``source_seed``."""
    return int(source_seed) * SEED_STRIDE + int(frame)


def _default_render(seed: int, scale: float, appearance_seed: int | None) -> tuple[np.ndarray, np.ndarray]:
    from monostixels.data.synthetic import render_pair  # written alongside; imported when needed

    pair = render_pair(seed, scale=scale, appearance_seed=appearance_seed)
    if pair.gt.labels is None:
        raise RuntimeError(f"render_pair({seed}) returned no labels")
    img = (pair.image.clamp(0, 1).permute(1, 2, 0).numpy() * 255.0 + 0.5).astype(np.uint8)
    return img, pair.gt.labels.numpy().astype(np.uint8)


class _LabelledImages(Dataset):
    """Shared ``__getitem__`` of the datasets below: ``load(i)`` as tensors, then ``transform``."""

    transform: Callable[[torch.Tensor, torch.Tensor, int], tuple[torch.Tensor, torch.Tensor]] | None = None

    def load(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        image, labels = CamVidSource.to_tensors(*self.load(i))
        if self.transform is not None:
            image, labels = self.transform(image, labels, i)
        return image, labels


class SyntheticSegmentation(_LabelledImages):
    """(image, labels) of synthetic frames, cached as PNG files; missing ones are rendered.

    Args:
        items: (scene seed, appearance seed or None) per sample.
        cache: cache folder (created).
        scale: render scale.
        transform: optional ``(image, labels, index) -> (image, labels)`` (augmentation).
        render: ``(seed, scale, appearance_seed) -> (uint8 (H, W, 3) RGB, uint8 (H, W) labels)``.

    Returns per item:
        image (3, H, W) float32 RGB [0, 1], labels (H, W) int64 (``IGNORE_LABEL`` = unknown).
    """

    def __init__(
        self,
        items: list[tuple[int, int | None]],
        *,
        cache: str | Path,
        scale: float,
        transform: Callable[[torch.Tensor, torch.Tensor, int], tuple[torch.Tensor, torch.Tensor]] | None = None,
        render: Callable[[int, float, int | None], tuple[np.ndarray, np.ndarray]] = _default_render,
    ) -> None:
        self.items = list(items)
        self.cache = Path(cache) / f"scale{scale:g}"
        self.cache.mkdir(parents=True, exist_ok=True)
        self.scale = float(scale)
        self.transform = transform
        self.render = render

    def __len__(self) -> int:
        return len(self.items)

    def _paths(self, i: int) -> tuple[Path, Path]:
        seed, app = self.items[i]
        stem = f"{seed}_{'default' if app is None else app}"
        return self.cache / f"{stem}.png", self.cache / f"{stem}_labels.png"

    def load(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """uint8 (H, W, 3) RGB and uint8 (H, W) labels of item ``i`` (rendered if not cached)."""
        img_path, lab_path = self._paths(i)
        if img_path.is_file() and lab_path.is_file():
            bgr = cv2.imread(str(img_path), cv2.IMREAD_COLOR)
            lab = cv2.imread(str(lab_path), cv2.IMREAD_UNCHANGED)
            if bgr is not None and lab is not None:
                return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), lab
        seed, app = self.items[i]
        img, lab = self.render(seed, self.scale, app)
        # Write then rename, so a reader never sees half a file (loader workers run in parallel).
        for path, arr in ((img_path, cv2.cvtColor(img, cv2.COLOR_RGB2BGR)), (lab_path, lab)):
            tmp = path.with_name(f".{path.stem}.{os.getpid()}.png")
            cv2.imwrite(str(tmp), arr)
            tmp.replace(path)
        return img, lab


class RealSegmentation(_LabelledImages):
    """(image, labels) of labelled real images (CamVid), held in memory (367 images: ~190 MB).

    Args:
        items: the labelled images (:func:`monostixels.data.camvid.read_camvid_split`).
        scale: resize factor applied once at loading (1 = the images' own size).
        transform: optional ``(image, labels, index) -> (image, labels)`` (augmentation).

    Returns per item:
        image (3, H, W) float32 RGB [0, 1], labels (H, W) int64 our class ids (``IGNORE_LABEL`` = void).
    """

    def __init__(self, items: list[CamVidItem], *, scale: float = 1.0,
                 transform: Callable[[torch.Tensor, torch.Tensor, int], tuple[torch.Tensor, torch.Tensor]] | None = None) -> None:
        self.items, self.scale, self.transform = list(items), float(scale), transform
        self._data: list[tuple[np.ndarray, np.ndarray] | None] = [None] * len(self.items)

    def __len__(self) -> int:
        return len(self.items)

    def load(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """uint8 (H, W, 3) RGB and uint8 (H, W) labels of item ``i`` (read once, then cached)."""
        if self._data[i] is None:
            img, lab = self.items[i].load()
            if self.scale != 1.0:
                h, w = round(img.shape[0] * self.scale), round(img.shape[1] * self.scale)
                img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
                lab = cv2.resize(lab, (w, h), interpolation=cv2.INTER_NEAREST)
            self._data[i] = (img, lab)
        return self._data[i]  # type: ignore[return-value]


class DistillFrame(NamedTuple):
    """One unlabelled real frame for distillation.

    Attributes:
        path: the image file (any format OpenCV reads).
        fx: the camera's focal length in pixels (the image is resized so that it becomes
            ``focal_px`` of :class:`PseudoLabelled`, the resolution the backend runs at).
        teacher: ``(3, H, W) RGB [0, 1] -> (10, H, W)`` class probabilities in our classes.
    """

    path: Path
    fx: float
    teacher: Callable[[torch.Tensor], torch.Tensor]


class PseudoLabelled(_LabelledImages):
    """Unlabelled real frames with a teacher's labels (knowledge distillation, hard pseudo-labels).

    A pixel gets the teacher's most likely class where its probability is at least
    ``confidence`` and ``IGNORE_LABEL`` elsewhere (uncertain boundaries teach nothing). The teacher
    sees the full image; image and labels are then resized to the focal length ``focal_px`` that
    the ``fcn8s`` backend gives a calibrated camera at inference (``semantic.focal_px``).
    Pseudo-labels are computed once per frame and kept in memory.

    Args:
        frames: the frames (:func:`distill_frames`).
        focal_px: focal length (pixels) the frames are resized to.
        confidence: smallest teacher probability that makes a label, in [0, 1).
        repeat: the dataset lists every frame this many times (distinct augmentations of few frames).
        transform: optional ``(image, labels, index) -> (image, labels)`` (augmentation).

    Returns per item:
        image (3, H, W) float32 RGB [0, 1], labels (H, W) int64 (``IGNORE_LABEL`` = unsure).
    """

    def __init__(self, frames: list[DistillFrame], *, focal_px: float, confidence: float, repeat: int = 1,
                 transform: Callable[[torch.Tensor, torch.Tensor, int], tuple[torch.Tensor, torch.Tensor]] | None = None) -> None:
        if not frames:
            raise InputError("data.distill: no frames to distil on")
        if not focal_px > 0:
            raise InputError(f"data.distill.focal_px: must be positive, got {focal_px}")
        if not 0 <= confidence < 1:
            raise InputError(f"data.distill.confidence: must be in [0, 1), got {confidence}")
        if int(repeat) < 1:
            raise InputError(f"data.distill.repeat: must be >= 1, got {repeat}")
        for f in frames:
            if not f.fx > 0:
                raise InputError(f"data.distill: frame {f.path}: focal length fx must be positive, got {f.fx}")
        self.frames, self.focal_px, self.confidence = list(frames), float(focal_px), float(confidence)
        self.repeat, self.transform = int(repeat), transform
        self._data: list[tuple[np.ndarray, np.ndarray] | None] = [None] * len(self.frames)

    def __len__(self) -> int:
        return len(self.frames) * self.repeat

    def load(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """uint8 (H, W, 3) RGB and uint8 (H, W) pseudo-labels of item ``i`` at ``focal_px``."""
        j = i % len(self.frames)
        if self._data[j] is None:
            f = self.frames[j]
            bgr = cv2.imread(str(f.path), cv2.IMREAD_COLOR)
            if bgr is None:
                raise InputError(f"data.distill: cannot read image {f.path}")
            rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            probs = f.teacher(torch.from_numpy(rgb).permute(2, 0, 1).float() / 255.0)
            if probs.shape != (NUM_CLASSES, *rgb.shape[:2]):
                raise InputError(f"data.distill: teacher scores of {f.path} have shape {tuple(probs.shape)}, "
                                 f"expected ({NUM_CLASSES}, {rgb.shape[0]}, {rgb.shape[1]})")
            conf, lab = probs.max(0)
            lab[conf < self.confidence] = IGNORE_LABEL
            lab_np = lab.numpy().astype(np.uint8)
            s = self.focal_px / f.fx
            h, w = max(8, round(rgb.shape[0] * s)), max(8, round(rgb.shape[1] * s))
            rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
            lab_np = cv2.resize(lab_np, (w, h), interpolation=cv2.INTER_NEAREST)
            self._data[j] = (rgb, lab_np)
        return self._data[j]  # type: ignore[return-value]


def distill_frames(dcfg: DictConfig | dict) -> list[DistillFrame]:
    """The frames of the ``data.distill`` config, each with its teacher (ONNX Runtime).

    ``dcfg.sets``: a list of ``{glob, fx, model, input_size}``: image files (a glob pattern,
    sorted), their focal length in pixels, and the teacher ONNX model with its input size;
    ``dcfg.teacher``: the shared teacher settings (``mean``, ``std``, ``mapping`` to our classes,
    -1 drops a channel such as a background class, ``pad_to``), as in ``conf/semantic/onnx.yaml``.
    A pattern that matches no file is an error (nothing is silently left out).
    """
    teacher = OmegaConf.to_container(dcfg["teacher"], resolve=True) if isinstance(dcfg["teacher"], DictConfig) \
        else dict(dcfg["teacher"])
    frames: list[DistillFrame] = []
    for k, entry in enumerate(dcfg["sets"]):
        pattern = str(entry["glob"])
        paths = sorted(glob.glob(pattern))
        if not paths:
            raise InputError(f"data.distill.sets[{k}].glob: no file matches {pattern!r}")
        # The `onnx` semantic backend itself (one cached session per model file and settings).
        segment = onnx_segmenter(OmegaConf.create(
            {**teacher, "name": "onnx", "model": str(entry["model"]), "input_size": entry.get("input_size")}))
        frames += [DistillFrame(Path(p), float(entry["fx"]), segment) for p in paths]
    return frames


def void_rows(box: Sequence[int], frame_height: int, rows: int, fraction: float) -> torch.Tensor:
    """Mask (rows,) of the rows of a window ``box = (x0, y0, x1, y1)`` of a frame, sampled at ``rows`` rows,
    whose centre lies at or below ``fraction`` of the frame's height (``data.soft.void_below``)."""
    y0, y1 = box[1], box[3]
    centre = y0 + (torch.arange(rows, dtype=torch.float64) + 0.5) * ((y1 - y0) / rows)
    return centre >= fraction * frame_height


def held_out(source: str, frame: int, holdout: list | None) -> bool:
    """Whether ``(source, frame)`` is excluded by ``holdout``.

    ``holdout``: a list of ``{source: name}`` (the whole source) or ``{source: name, frames: [lo, hi]}``
    (frames ``lo <= frame < hi``), e.g. ``[{source: kitti_0028}]``, ``[{source: dashcam, frames: [110, 221]}]``.
    """
    for h in holdout or ():
        if str(h["source"]) != source:
            continue
        fr = h.get("frames")
        if fr is None or int(fr[0]) <= int(frame) < int(fr[1]):
            return True
    return False


class SoftLabelled(Dataset):
    """Frames with the teacher's cached soft labels (``python -m train.teacher_labels``) and, where
    they exist (CamVid), the ground-truth labels.

    Each entry is a window of a frame (``SoftEntry.box``); image, labels and probabilities are
    resized so that the camera's focal length becomes ``focal_px`` (the resolution the backend runs
    at). Nothing is kept in memory (~1500 entries would take ~3 GB); an entry costs ~20 ms to read.

    Args:
        entries: the manifest entries to train on (holdouts already removed).
        focal_px: focal length (pixels) every window is resized to.
        transform: optional ``(image, labels, soft, index) -> (image, labels, soft)`` (augmentation).
        void_below: per source name, the fraction of the frame height (0-1) below which the teacher
            gives no target (its probabilities are zeroed there: no teacher term). The Cityscapes
            teacher never learned the rows its training images fill with the ego vehicle's bonnet,
            and on a camera without one it labels the near road there as a vehicle.

    Returns per item:
        image (3, H, W) float32 RGB [0, 1], labels (H, W) int64 (``IGNORE_LABEL`` where none),
        soft (10, H, W) float32 teacher probabilities.
    """

    def __init__(self, entries: list, *, focal_px: float,
                 transform: Callable[[torch.Tensor, torch.Tensor, torch.Tensor, int], tuple] | None = None,
                 void_below: dict[str, float] | None = None) -> None:
        if not entries:
            raise InputError("data.soft: no teacher-labelled entries to train on (all held out, or an empty manifest)")
        if not focal_px > 0:
            raise InputError(f"data.soft.focal_px: must be positive, got {focal_px}")
        void = {str(k): float(v) for k, v in (void_below or {}).items()}
        for name, frac in void.items():
            if not 0.0 < frac <= 1.0:
                raise InputError(f"data.soft.void_below.{name}: a fraction of the frame height in (0, 1], got {frac}")
        self.entries, self.focal_px, self.transform, self.void_below = list(entries), float(focal_px), transform, void

    def __len__(self) -> int:
        return len(self.entries)

    def load(self, i: int) -> tuple[np.ndarray, np.ndarray, torch.Tensor]:
        """uint8 (H, W, 3) RGB, uint8 (H, W) labels and (10, H, W) float32 probabilities of entry ``i``."""
        from train.teacher_labels import load_entry

        e = self.entries[i]
        bgr = cv2.imread(e.image, cv2.IMREAD_COLOR)
        if bgr is None:
            raise InputError(f"data.soft: cannot read image {e.image}")
        x0, y0, x1, y1 = e.box
        rgb = cv2.cvtColor(bgr[y0:y1, x0:x1], cv2.COLOR_BGR2RGB)
        if e.labels is not None:
            from monostixels.data.camvid import map_camvid_labels

            raw = cv2.imread(e.labels, cv2.IMREAD_UNCHANGED)
            if raw is None:
                raise InputError(f"data.soft: cannot read labels {e.labels}")
            lab = map_camvid_labels(raw, name=e.labels)[y0:y1, x0:x1]
        else:
            lab = np.full(rgb.shape[:2], IGNORE_LABEL, np.uint8)
        s = self.focal_px / e.fx
        h, w = max(8, round(rgb.shape[0] * s)), max(8, round(rgb.shape[1] * s))
        if (h, w) != rgb.shape[:2]:
            rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
            lab = cv2.resize(lab, (w, h), interpolation=cv2.INTER_NEAREST)
        soft = F.interpolate(load_entry(e.probs)[None], size=(h, w), mode="bilinear", align_corners=False)[0]
        if e.source in self.void_below:
            soft[:, void_rows(e.box, bgr.shape[0], h, self.void_below[e.source])] = 0.0
        return rgb, lab, soft

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        rgb, lab, soft = self.load(i)
        image, labels = CamVidSource.to_tensors(rgb, lab)
        if self.transform is not None:
            image, labels, soft = self.transform(image, labels, soft, i)
        return image, labels, soft


class _NoSoft(Dataset):
    """A dataset of (image, labels) as (image, labels, zero soft targets), for batches mixed with
    :class:`SoftLabelled` (zero probabilities = no teacher term)."""

    def __init__(self, data: Dataset) -> None:
        self.data = data

    def __len__(self) -> int:
        return len(self.data)  # type: ignore[arg-type]

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        image, labels = self.data[i]
        return image, labels, torch.zeros((NUM_CLASSES, *labels.shape), dtype=torch.float32)


def soft_entries(scfg: DictConfig | dict) -> tuple[list, list]:
    """``(train, held out)`` entries of the manifest ``scfg.manifest``.

    Train: entries of the sources with a positive weight in ``scfg.weights`` (a source missing from
    it gets ``scfg.default_weight``), views in ``scfg.views`` (null = all), minus ``scfg.holdout``.
    """
    from train.teacher_labels import read_manifest

    entries = read_manifest(scfg["manifest"])
    weights = dict(scfg.get("weights") or {})
    default = float(scfg.get("default_weight", 1.0))
    views = scfg.get("views")
    holdout = list(scfg.get("holdout") or [])
    train, out = [], []
    for e in entries:
        if held_out(e.source, e.frame, holdout):
            out.append(e)
        elif float(weights.get(e.source, default)) > 0 and (views is None or e.view.split("_")[0] in views):
            train.append(e)
    return train, out


def soft_draw(entries: list, weights: dict, default: float, n: int, g: torch.Generator) -> list[int]:
    """``n`` entry indices drawn with replacement, each source's share proportional to its weight.

    Within a source all entries are equally likely (a 221-frame clip does not outweigh 2 frames of
    another camera unless its weight says so).
    """
    per_source: dict[str, int] = {}
    for e in entries:
        per_source[e.source] = per_source.get(e.source, 0) + 1
    p = torch.tensor([float(weights.get(e.source, default)) / per_source[e.source] for e in entries], dtype=torch.float64)
    if not len(p) or float(p.sum()) <= 0 or n <= 0:
        return []
    return torch.multinomial(p, n, replacement=True, generator=g).tolist()


def distill_loss(logits: torch.Tensor, labels: torch.Tensor, soft: torch.Tensor, *,
                 weight: torch.Tensor | None = None, temperature: float = 1.0,
                 soft_weight_labelled: float = 1.0) -> torch.Tensor:
    """Class-weighted mean over supervised pixels of hard cross-entropy and soft-target KL.

    Per pixel with a hard label y: ``w[y] * -log q_y``; per pixel with soft targets p (sum 1;
    all zero = none): ``a * w_p * T^2 * KL(p_T || q_T)`` with ``p_T = softmax(log p / T)``,
    ``q_T = softmax(z / T)``, ``w_p = sum_c p_c w[c]`` (class balancing follows the teacher) and
    ``a = soft_weight_labelled`` where the pixel also has a hard label (else 1). The loss is the
    sum of both terms over the batch divided by the sum of their weights (``w[y]``, ``a w_p``).

    Args:
        logits: (B, C, H, W) student scores.
        labels: (B, H, W) int64, ``IGNORE_LABEL`` where none.
        soft: (B, C, H, W) teacher probabilities.
        weight: (C,) class weights (None = 1).
        temperature: T (1 = the teacher's own probabilities).
        soft_weight_labelled: weight a of the teacher where a ground-truth label exists.
    """
    C = logits.shape[1]
    w = torch.ones(C, dtype=logits.dtype) if weight is None else weight.to(logits.dtype)
    logq = F.log_softmax(logits, dim=1)
    has_label = labels != IGNORE_LABEL
    y = torch.where(has_label, labels, torch.zeros_like(labels))
    wh = w[y] * has_label
    hard = -(logq.gather(1, y[:, None])[:, 0] * wh).sum()
    mass = soft.sum(1)
    has_soft = mass > 0.5
    p = soft / mass.clamp_min(1e-6)[:, None]
    T = float(temperature)
    if T != 1.0:
        pT = torch.softmax(p.clamp_min(1e-8).log() / T, dim=1)
        logqT = F.log_softmax(logits / T, dim=1)
    else:
        pT, logqT = p, logq
    kl = (pT * (pT.clamp_min(1e-8).log() - logqT)).sum(1) * T * T
    ws = (p * w.view(1, C, 1, 1)).sum(1) * has_soft
    ws = ws * torch.where(has_label, torch.full_like(ws, float(soft_weight_labelled)), torch.ones_like(ws))
    total = wh.sum() + ws.sum()
    return (hard + (kl * ws).sum()) / total.clamp_min(1e-6)


def _uniform(g: torch.Generator, lo: float, hi: float) -> float:
    return lo + (hi - lo) * float(torch.rand((), generator=g))


def augment(image: torch.Tensor, labels: torch.Tensor, g: torch.Generator, aug: DictConfig | dict) -> tuple[torch.Tensor, torch.Tensor]:
    """Geometric and photometric augmentation of one training sample.

    Args:
        image: (3, H, W) RGB [0, 1].
        labels: (H, W) int64 class ids.
        g: random generator.
        aug: the ``augment`` config (see conf/train_semantic.yaml; ``rotate_deg``, ``vshift``,
            ``jpeg_prob`` are optional and off when absent).

    Returns:
        (3, h, w) augmented image and (h, w) labels, (h, w) = ``aug.crop``; padded areas are
        ``IGNORE_LABEL``.
    """
    image, labels, _ = _geometric(image, labels, None, g, aug)
    return _photometric(image, g, aug), labels


def augment_soft(image: torch.Tensor, labels: torch.Tensor, soft: torch.Tensor, g: torch.Generator,
                 aug: DictConfig | dict) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`augment` with soft targets that follow the image's geometry.

    Args:
        image: (3, H, W) RGB [0, 1].
        labels: (H, W) int64 hard labels (``IGNORE_LABEL`` where none).
        soft: (C, H, W) teacher probabilities (all zero where there is no teacher).

    Returns:
        (3, h, w) image, (h, w) labels, (C, h, w) soft targets (bilinear; zero in padded areas).
    """
    image, labels, soft = _geometric(image, labels, soft, g, aug)
    return _photometric(image, g, aug), labels, soft  # type: ignore[return-value]


def _geometric(image: torch.Tensor, labels: torch.Tensor, soft: torch.Tensor | None, g: torch.Generator,
               aug: DictConfig | dict) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Scale jitter, small rotation, vertical shift, random crop, flip (see :func:`augment_soft`).

    Convention: the source is scaled by ``s`` (about its top-left corner, pixel centres at
    ``+0.5``), placed on a canvas ``vshift x crop height`` taller at the top and the bottom (and
    padded right / below to the crop size), the crop window is chosen on that canvas and rotated
    about its own centre. Only the source region the crop needs is resampled (one ``grid_sample``
    into the crop), so large soft-target maps cost no more than the crop.
    """
    s = _uniform(g, *aug["scale_jitter"])
    H, W = image.shape[-2:]
    Hs, Ws = max(8, round(H * s)), max(8, round(W * s))
    rot = float(aug.get("rotate_deg", 0.0) or 0.0)
    # A camera rolled by a few degrees (a dashcam mounted askew).
    angle = math.radians(_uniform(g, -rot, rot)) if rot > 0 else 0.0
    ch, cw = int(aug["crop"][0]), int(aug["crop"][1])
    vshift = float(aug.get("vshift", 0.0) or 0.0)
    # Pad above and below so that the crop may put the horizon up to `vshift` x crop height higher
    # or lower than the source camera's pitch allows (other mounts, other pitches).
    pad = round(vshift * ch) if vshift > 0 else 0
    canvas_h, canvas_w = max(ch, Hs + 2 * pad), max(cw, Ws)
    y0 = int(torch.randint(0, canvas_h - ch + 1, (), generator=g))
    x0 = int(torch.randint(0, canvas_w - cw + 1, (), generator=g))
    flip = float(torch.rand((), generator=g)) < aug["hflip"]
    # Output pixel (i, j) -> scaled-image index (ys, xs): rotate about the crop centre.
    v, u = torch.meshgrid(torch.arange(ch, dtype=torch.float32) + 0.5 - ch / 2,
                          torch.arange(cw, dtype=torch.float32) + 0.5 - cw / 2, indexing="ij")
    c, sn = math.cos(angle), math.sin(angle)
    xs = x0 + cw / 2 + c * u - sn * v - 0.5
    ys = y0 + ch / 2 + sn * u + c * v - pad - 0.5
    # Source continuous coordinates (pixel edges at integers).
    X, Y = (xs + 0.5) * (W / Ws), (ys + 0.5) * (H / Hs)
    valid = (X >= 0) & (X <= W) & (Y >= 0) & (Y <= H)
    # The source region the crop needs (+2 px for the bilinear footprint).
    sx0 = int(max(0, math.floor(float(X.min())) - 2)); sx1 = int(min(W, math.ceil(float(X.max())) + 2))
    sy0 = int(max(0, math.floor(float(Y.min())) - 2)); sy1 = int(min(H, math.ceil(float(Y.max())) + 2))
    if sx1 <= sx0 or sy1 <= sy0:
        sx0, sx1, sy0, sy1 = 0, W, 0, H  # crop entirely in padding
    img_r, lab_r = image[:, sy0:sy1, sx0:sx1], labels[sy0:sy1, sx0:sx1]
    soft_r = None if soft is None else soft[:, sy0:sy1, sx0:sx1]
    rh, rw = sy1 - sy0, sx1 - sx0
    if s < 1:
        # Downscaling: low-pass the region first (antialias), then sample it near 1:1.
        rh, rw = max(2, round(rh * s)), max(2, round(rw * s))
        img_r = F.interpolate(img_r[None], size=(rh, rw), mode="bilinear", align_corners=False, antialias=True)[0]
        lab_r = F.interpolate(lab_r[None, None].float(), size=(rh, rw), mode="nearest")[0, 0].long()
        if soft_r is not None:
            soft_r = F.interpolate(soft_r[None], size=(rh, rw), mode="bilinear", align_corners=False, antialias=True)[0]
    fx, fy = rw / (sx1 - sx0), rh / (sy1 - sy0)
    # grid_sample (align_corners=False): -1 / +1 are the outer edges of the region.
    gx = (X - sx0) * fx / rw * 2 - 1
    gy = (Y - sy0) * fy / rh * 2 - 1
    grid = torch.stack([gx, gy], -1)[None]
    if flip:
        grid, valid = grid.flip(2), valid.flip(1)
    out = F.grid_sample(img_r[None], grid, mode="bilinear", padding_mode="border", align_corners=False)[0]
    out = torch.where(valid, out, torch.full_like(out, 0.5))
    lab = F.grid_sample(lab_r[None, None].float(), grid, mode="nearest", padding_mode="border", align_corners=False)[0, 0].long()
    lab = torch.where(valid, lab, torch.full_like(lab, IGNORE_LABEL))
    if soft_r is not None:
        soft_r = F.grid_sample(soft_r[None], grid, mode="bilinear", padding_mode="border", align_corners=False)[0] * valid
    return out.contiguous(), lab.contiguous(), None if soft_r is None else soft_r.contiguous()


def _photometric(image: torch.Tensor, g: torch.Generator, aug: DictConfig | dict) -> torch.Tensor:
    """Brightness, contrast, saturation, colour cast, gamma, blur, JPEG, noise of (3, H, W)."""
    image = image * (1 + _uniform(g, -aug["brightness"], aug["brightness"]))
    mean = image.mean()
    image = (image - mean) * (1 + _uniform(g, -aug["contrast"], aug["contrast"])) + mean
    grey = image.mean(0, keepdim=True)
    image = (image - grey) * (1 + _uniform(g, -aug["saturation"], aug["saturation"])) + grey
    gains = 1 + (torch.rand(3, 1, 1, generator=g) * 2 - 1) * aug["channel_gain"]
    image = (image * gains).clamp(0, 1)
    image = image ** _uniform(g, *aug["gamma"])
    if float(torch.rand((), generator=g)) < aug["blur_prob"]:
        sigma = _uniform(g, *aug["blur_sigma"])
        image = _gaussian_blur(image, sigma)
    jpeg = float(aug.get("jpeg_prob", 0.0) or 0.0)
    if jpeg > 0 and float(torch.rand((), generator=g)) < jpeg:
        # Compression blocks and ringing of dashcam video and re-encoded frames.
        image = _jpeg(image, int(round(_uniform(g, *aug["jpeg_quality"]))))
    noise = _uniform(g, *aug["noise_std"])
    image = image + noise * torch.randn(image.shape, generator=g)
    return image.clamp(0, 1).contiguous()


def _jpeg(image: torch.Tensor, quality: int) -> torch.Tensor:
    """(3, H, W) RGB [0, 1] through a JPEG encode/decode at ``quality`` (OpenCV)."""
    u8 = (image.clamp(0, 1).permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(u8, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        return image
    rgb = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    return torch.from_numpy(rgb).permute(2, 0, 1).float() / 255.0


def _gaussian_blur(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of (3, H, W) with std ``sigma`` pixels (kernel +-3 sigma)."""
    r = max(1, int(math.ceil(3 * sigma)))
    x = torch.arange(-r, r + 1, dtype=image.dtype)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    img = F.pad(image[:, None], (r, r, r, r), mode="replicate")
    img = F.conv2d(img, k.view(1, 1, 1, -1))
    img = F.conv2d(img, k.view(1, 1, -1, 1))
    return img[:, 0]


class _Augment:
    """Picklable transform for loader workers: a generator per (epoch seed, item)."""

    def __init__(self, aug: dict, seed: int) -> None:
        self.aug, self.seed, self.epoch = aug, seed, 0

    def __call__(self, image: torch.Tensor, labels: torch.Tensor, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch * 100_003 + i)
        return augment(image, labels, g, self.aug)


class _AugmentSoft(_Augment):
    """:class:`_Augment` for :class:`SoftLabelled` items (image, labels, soft targets)."""

    def __call__(self, image: torch.Tensor, labels: torch.Tensor, soft: torch.Tensor,  # type: ignore[override]
                 i: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        # Offset the item seed: soft entries and the other sets share indices 0.. .
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch * 100_003 + 50_000_017 + i)
        return augment_soft(image, labels, soft, g, self.aug)


def build_model(mcfg: DictConfig | dict) -> tuple[FCN8s, dict]:
    """The network of the ``model`` config and the builder kwargs that rebuild it."""
    arch = {
        "num_classes": NUM_CLASSES,
        "width_mult": float(mcfg["width_mult"]),
        "batch_norm": bool(mcfg["batch_norm"]),
        "fc_kernel": int(mcfg["fc_kernel"]),
        "fc_channels": None if mcfg.get("fc_channels") is None else int(mcfg["fc_channels"]),
        "dropout": float(mcfg["dropout"]),
    }
    if mcfg.get("skip_pool2"):  # only where set: the arch of the FCN-8s files stays as it was
        arch["skip_pool2"] = True
    model = fcn8s_vgg16(**arch)
    if mcfg.get("vgg16_weights"):
        load_vgg16_backbone(model, mcfg["vgg16_weights"])
    if mcfg.get("init_from"):
        # Fine-tuning starts a fresh schedule from earlier weights (``resume`` continues a run).
        try:
            init, _ = load_fcn8s(mcfg["init_from"])
        except InputError as exc:
            raise InputError(f"model.init_from: {exc} (the training config's comment says where those weights "
                             "come from)") from None
        try:
            fresh = load_fcn8s_state(model, init.state_dict())
            if fresh:
                logger.info("model.init_from: an FCN-8s; the stride-4 skip starts at its initial values (%s)",
                            ", ".join(fresh))
        except RuntimeError as exc:
            raise InputError(f"model.init_from {mcfg['init_from']}: does not fit the model config {arch}: {exc}") from None
    return model, arch


def class_weights(labels: list[torch.Tensor], power: float, max_weight: float | None = None) -> torch.Tensor:
    """(10,) loss weights ``(1 / frequency) ** power`` normalised to mean 1 over present classes.

    Args:
        labels: label maps (H, W) int64.
        power: 0 = uniform; 0.5 = inverse square root (softens the rarity of poles, persons).
        max_weight: cap on a weight after normalisation (None = no cap): a class that is rare only
            because few frames of its source are mixed in (terrain, synthetic only) should not be
            over-predicted on the main data.
    """
    counts = torch.zeros(NUM_CLASSES, dtype=torch.float64)
    for lab in labels:
        valid = lab[lab != IGNORE_LABEL]
        counts += torch.bincount(valid, minlength=NUM_CLASSES).double()[:NUM_CLASSES]
    freq = counts / counts.sum().clamp_min(1)
    w = torch.where(freq > 0, freq.clamp_min(1e-6) ** -power, torch.zeros_like(freq))
    present = freq > 0
    w = w / w[present].mean()
    if max_weight is not None:
        w = w.clamp(max=float(max_weight))
    return w.float()


def train_steps(
    model: FCN8s,
    batches,
    optimizer: torch.optim.Optimizer,
    *,
    schedule: "Schedule | None" = None,
    weight: torch.Tensor | None = None,
    progress: tqdm | None = None,
    soft_loss: dict | None = None,
) -> list[float]:
    """Run one optimisation step per batch; returns the losses.

    Batches of ``(image, labels)``: cross-entropy, ignore 255. Batches of ``(image, labels, soft)``:
    :func:`distill_loss` with the keyword arguments ``soft_loss`` (``temperature``,
    ``soft_weight_labelled``). With a ``schedule``, the learning rate is set from it before each
    step and the loop stops when the schedule is done.
    """
    model.train()
    losses: list[float] = []
    for batch in batches:
        image, labels = batch[0], batch[1]
        if schedule is not None:
            if schedule.done():
                break
            for group in optimizer.param_groups:
                group["lr"] = schedule.lr()
        logits = model(image)
        if len(batch) == 3:
            loss = distill_loss(logits, labels, batch[2], weight=weight, **(soft_loss or {}))
        else:
            loss = F.cross_entropy(logits, labels, weight=weight, ignore_index=IGNORE_LABEL)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if schedule is not None:
            schedule.step += 1
        losses.append(float(loss.detach()))
        if progress is not None:
            progress.update(1)
            progress.set_postfix(loss=f"{losses[-1]:.3f}", lr=f"{optimizer.param_groups[0]['lr']:.1e}")
    return losses


class Schedule:
    """One-cycle learning rate (linear warm-up, cosine decay) over steps or wall time.

    Progress is ``max(step / total_steps, seconds / time_limit_s)``: with a time limit, the whole
    schedule (warm-up and annealing) fits into it even when the shared CPU is slower than
    planned, and training ends when progress reaches 1.

    Args:
        max_lr: peak learning rate.
        total_steps: optimisation steps of the full schedule.
        time_limit_s: wall-time budget in seconds (None = steps only).
        warmup: fraction of the schedule spent warming up from ``max_lr / 10``.
        final_div: the last learning rate is ``max_lr / final_div``.
    """

    def __init__(self, max_lr: float, total_steps: int, *, time_limit_s: float | None = None,
                 warmup: float = 0.1, final_div: float = 100.0) -> None:
        self.max_lr, self.total_steps, self.time_limit_s = max_lr, max(1, total_steps), time_limit_s
        self.warmup, self.final_div = warmup, final_div
        self.step = 0
        self.seconds_before = 0.0  # wall time of earlier (resumed) runs
        self._t0 = time.monotonic()

    def seconds(self) -> float:
        return self.seconds_before + time.monotonic() - self._t0

    def progress(self) -> float:
        p = self.step / self.total_steps
        if self.time_limit_s:
            p = max(p, self.seconds() / float(self.time_limit_s))
        return min(1.0, p)

    def done(self) -> bool:
        return self.progress() >= 1.0

    def lr(self) -> float:
        p = self.progress()
        lo = self.max_lr / 10
        if p < self.warmup:
            return lo + (self.max_lr - lo) * p / self.warmup
        q = (p - self.warmup) / max(1e-9, 1 - self.warmup)
        end = self.max_lr / self.final_div
        return end + 0.5 * (self.max_lr - end) * (1 + math.cos(math.pi * q))

    def state_dict(self) -> dict[str, float]:
        return {"step": self.step, "seconds": self.seconds()}

    def load_state_dict(self, state: dict[str, float]) -> None:
        self.step = int(state["step"])
        self.seconds_before = float(state["seconds"])
        self._t0 = time.monotonic()


@torch.no_grad()
def evaluate(predict: Callable[[torch.Tensor], torch.Tensor], data: Dataset, desc: str = "val",
             classes: tuple[int, ...] | None = None) -> tuple[float, dict[str, float]]:
    """mIoU of ``predict`` ((3, H, W) -> (H, W) class ids) over ``data``.

    Args:
        classes: class ids the mean runs over and that are reported (None = every class present
            in labels or predictions); the metric of ``monostixels eval``.

    Returns:
        ``(miou, per-class IoU)`` from the confusion matrix accumulated over all frames.
    """
    acc = SemanticAccumulator()
    for i in tqdm(range(len(data)), desc=desc, leave=False):
        image, labels = data[i]
        acc.add(predict(image), labels)
    res = acc.result(classes=classes)
    return res["miou"], res["per_class_iou"]


def _torch_predict(model: FCN8s) -> Callable[[torch.Tensor], torch.Tensor]:
    def predict(image: torch.Tensor) -> torch.Tensor:
        model.eval()
        return model(image[None])[0].argmax(0)
    return predict


def _items(cfg: DictConfig) -> tuple[list[tuple[int, int | None]], list[tuple[int, int | None]]]:
    d = cfg.data
    train: list[tuple[int, int | None]] = []
    for s in d.train_source_seeds:
        if int(s) == int(d.val_source_seed) or int(s) < 10:
            raise InputError(f"data.train_source_seeds: {s} is reserved (validation {d.val_source_seed}, evaluation < 10)")
        for i in range(int(d.frames_per_seed)):
            seed = scene_seed(int(s), i)
            # Every other frame with a randomised appearance (textures, colours, lighting).
            app = None if d.appearance_offset is None or i % 2 == 0 else int(d.appearance_offset) + seed
            train.append((seed, app))
    val = [(scene_seed(int(d.val_source_seed), i), None) for i in range(int(d.val_frames))]
    return train, val


def _real_set(cfg: DictConfig, split: str, transform: Callable | None) -> RealSegmentation | None:
    """CamVid ``split`` (train or val) as a dataset, or None when ``data.camvid_root`` is null."""
    root = cfg.data.get("camvid_root")
    if root is None:
        return None
    if split == "test":
        raise InputError("CamVid test is for the final report only; training never reads it")
    return RealSegmentation(read_camvid_split(root, split), scale=float(cfg.data.get("real_scale", 1.0)),
                            transform=transform)


def _distill_set(cfg: DictConfig, transform: Callable | None) -> PseudoLabelled | None:
    """The pseudo-labelled frames of ``data.distill`` (None when absent or disabled)."""
    d = cfg.data.get("distill")
    if d is None or not d.get("enabled", False):
        return None
    # Teacher labels are made lazily, on a frame's first draw: an export-only run (train.epochs=0)
    # never pays for them.
    data = PseudoLabelled(distill_frames(d), focal_px=float(d.focal_px), confidence=float(d.confidence),
                          repeat=int(d.get("repeat", 1)), transform=transform)
    logger.info("distillation: %d frames (x%d), %d drawn per epoch", len(data.frames), data.repeat, int(d.per_epoch))
    return data


def _val_set(cfg: DictConfig, val_items: list) -> tuple[Dataset, tuple[int, ...] | None]:
    """The validation set of ``data.val`` and the classes its mean IoU runs over."""
    which = str(cfg.data.get("val", "synthetic"))
    if which == "camvid":
        return _real_set(cfg, "val", None), CAMVID_CLASSES_PRESENT  # type: ignore[return-value]
    if which == "synthetic":
        return SyntheticSegmentation(val_items, cache=cfg.data.cache, scale=float(cfg.data.scale)), None
    raise InputError(f"data.val: expected synthetic or camvid, got {which!r}")


def _command() -> str:
    return "nice -n 10 python -m train.semantic " + " ".join(shlex.quote(a) for a in sys.argv[1:])


def prerender(cfg: DictConfig) -> None:
    """Fill the cache (synthetic validation frames first, then training frames) without training."""
    train_items, val_items = _items(cfg)
    sets = []
    if str(cfg.data.get("val", "synthetic")) == "synthetic":
        sets += [SyntheticSegmentation(val_items, cache=cfg.data.cache, scale=float(cfg.data.scale)),
                 SyntheticSegmentation(val_items, cache=cfg.data.cache, scale=float(cfg.data.final_eval_scale))]
    sets.append(SyntheticSegmentation(train_items, cache=cfg.data.cache, scale=float(cfg.data.scale)))
    for data in sets:
        for i in tqdm(range(len(data)), desc=f"render {data.cache.name}", mininterval=10):
            data.load(i)


def run(cfg: DictConfig) -> dict[str, Any]:
    """Train (or resume), validate per epoch, export the best or final model, evaluate the export."""
    torch.set_num_threads(int(cfg.train.threads))
    torch.manual_seed(int(cfg.train.seed))
    if cfg.export.enabled:
        _export_checkpoint(cfg)  # a typo fails now, not after hours of training
    if cfg.get("prerender_only", False):
        prerender(cfg)
        return {"command": _command(), "prerendered": True}
    run_dir = Path(cfg.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    train_items, val_items = _items(cfg)
    aug = OmegaConf.to_container(cfg.augment, resolve=True)
    transform = _Augment(aug, int(cfg.train.seed))
    synth_set = SyntheticSegmentation(train_items, cache=cfg.data.cache, scale=float(cfg.data.scale), transform=transform)
    real_set = _real_set(cfg, "train", transform) if cfg.data.get("real_train", True) else None
    val_set, val_classes = _val_set(cfg, val_items)
    distill_set = _distill_set(cfg, transform)
    scfg = cfg.data.get("soft")
    use_soft = scfg is not None and bool(scfg.get("enabled", False))
    soft_transform = _AugmentSoft(aug, int(cfg.train.seed))
    # One epoch: every real image once plus `synthetic_per_epoch` synthetic frames,
    # `distill.per_epoch` pseudo-labelled frames and `soft.per_epoch` teacher-labelled windows drawn anew.
    fixed = [d for d in (real_set, synth_set, distill_set) if d is not None]
    if use_soft:
        fixed = [_NoSoft(d) for d in fixed]
    n_real = 0 if real_set is None else len(real_set)
    n_synth = cfg.data.get("synthetic_per_epoch")
    n_synth = len(synth_set) if n_synth is None else min(int(n_synth), len(synth_set))
    n_distill = 0 if distill_set is None else min(int(cfg.data.distill.per_epoch), len(distill_set))
    n_soft = int(scfg.per_epoch) if use_soft else 0
    soft_loss = None
    if use_soft:
        soft_loss = {"temperature": float(scfg.loss.temperature),
                     "soft_weight_labelled": float(scfg.loss.soft_weight_labelled)}
        soft_train, soft_out = soft_entries(scfg)
        void_below = dict(scfg.get("void_below") or {})
        logger.info("soft labels: %d training entries, %d held out (%s)", len(soft_train), len(soft_out),
                    OmegaConf.to_container(scfg.holdout) if scfg.get("holdout") else "none")
    model, arch = build_model(cfg.model)
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(params, lr=float(cfg.train.lr), weight_decay=float(cfg.train.weight_decay))
    bs = int(cfg.train.batch_size)
    steps_per_epoch = max(1, (n_real + n_synth + n_distill + n_soft) // bs)
    epochs = int(cfg.train.epochs)
    total = max(1, epochs * steps_per_epoch)
    schedule = Schedule(float(cfg.train.lr), total, time_limit_s=cfg.train.time_limit_s)
    state: dict[str, Any] = {"epoch": 0, "best_miou": -1.0, "history": [], "weight": None}
    last = run_dir / "last.pt"
    if cfg.resume and last.is_file():
        ck = torch.load(last, map_location="cpu", weights_only=False)
        model.load_state_dict(ck["model"])
        optimizer.load_state_dict(ck["optimizer"])
        schedule.load_state_dict(ck["schedule"])
        state.update({k: ck[k] for k in ("epoch", "best_miou", "history", "weight")})
        logger.info("resumed from %s at epoch %d (best mIoU %.4f)", last, state["epoch"], state["best_miou"])

    if state["weight"] is None:
        power = float(cfg.train.class_weight_power)
        plain = SyntheticSegmentation(train_items[:: max(1, len(train_items) // 40)], cache=cfg.data.cache,
                                      scale=float(cfg.data.scale))
        n_plain = n_synth // 4 if (real_set is not None or use_soft) else 40
        sample = [plain[j][1] for j in range(min(n_plain, len(plain)))]
        if real_set is not None:
            sample += [torch.from_numpy(real_set.load(j)[1].astype(np.int64)) for j in range(n_real)]
        if use_soft:
            # The teacher's most likely class on a sample of the drawn windows stands for the
            # class frequencies of the soft-labelled data.
            g0 = torch.Generator().manual_seed(int(cfg.train.seed))
            picks = soft_draw(soft_train, dict(scfg.get("weights") or {}), float(scfg.get("default_weight", 1.0)),
                              int(scfg.get("weight_sample", 64)), g0)
            probe = SoftLabelled(soft_train, focal_px=float(scfg.focal_px), void_below=void_below)
            for j in tqdm(picks, desc="class frequencies", mininterval=10):
                _, lab, soft = probe.load(j)
                lab_t = torch.from_numpy(lab.astype(np.int64))
                teacher = torch.where(soft.sum(0) > 0.5, soft.argmax(0), torch.full_like(lab_t, IGNORE_LABEL))
                sample.append(torch.where(lab_t != IGNORE_LABEL, lab_t, teacher))
        w = class_weights(sample, power, cfg.train.get("class_weight_max"))
        # Thin classes (pole, person, two_wheeler) weigh more than their frequency alone gives.
        for name, boost in (cfg.train.get("class_boost") or {}).items():
            w[CLASS_NAMES.index(str(name))] *= float(boost)
        state["weight"] = w.tolist()
    weight = torch.tensor(state["weight"], dtype=torch.float32)
    logger.info("class weights %s", dict(zip(CLASS_NAMES, [round(w, 3) for w in state["weight"]])))

    for epoch in range(int(state["epoch"]), epochs):
        if schedule.done():
            break
        transform.epoch = epoch
        g = torch.Generator().manual_seed(int(cfg.train.seed) + epoch)
        synth_pick = (torch.randperm(len(synth_set), generator=g)[:n_synth] + n_real).tolist()
        distill_pick = [] if distill_set is None else (
            torch.randperm(len(distill_set), generator=g)[:n_distill] + n_real + len(synth_set)).tolist()
        parts: list[Dataset] = list(fixed)
        soft_pick: list[int] = []
        if use_soft:
            # Re-read the manifest each epoch: the teacher may still be labelling in the background.
            soft_train, _ = soft_entries(scfg)
            soft_set = SoftLabelled(soft_train, focal_px=float(scfg.focal_px), transform=soft_transform,
                                    void_below=void_below)
            soft_transform.epoch = epoch
            offset = sum(len(d) for d in fixed)  # type: ignore[arg-type]
            soft_pick = [offset + j for j in soft_draw(soft_train, dict(scfg.get("weights") or {}),
                                                       float(scfg.get("default_weight", 1.0)), n_soft, g)]
            parts.append(soft_set)
        loader = DataLoader(
            ConcatDataset(parts), batch_size=bs, drop_last=True, num_workers=int(cfg.data.workers),
            sampler=SubsetRandomSampler(list(range(n_real)) + synth_pick + distill_pick + soft_pick, generator=g),
            persistent_workers=False,
        )
        t0 = time.monotonic()
        with tqdm(total=steps_per_epoch, desc=f"epoch {epoch + 1}/{epochs}", mininterval=10) as bar:
            losses = train_steps(model, loader, optimizer, schedule=schedule, weight=weight, progress=bar,
                                 soft_loss=soft_loss)
        complete = len(losses) == steps_per_epoch or schedule.done()
        every = int(cfg.train.get("val_every", 1))
        if (epoch + 1) % every and epoch + 1 < epochs and not schedule.done():
            # Validation costs ~a tenth of an epoch on 2 cores: every `val_every` epochs, and at the end.
            miou, per_class = float("nan"), {}
        else:
            miou, per_class = evaluate(_torch_predict(model), val_set, classes=val_classes)
        entry = {"epoch": epoch + 1, "loss": float(np.mean(losses)) if losses else float("nan"),
                 "val_miou": miou, "val_per_class_iou": per_class, "seconds": time.monotonic() - t0,
                 "steps": len(losses), "step": schedule.step, "wall_s": schedule.seconds()}
        state["history"].append(entry)
        logger.info("epoch %d: loss %.4f, val mIoU %.4f (%s), %.0f s", epoch + 1, entry["loss"], miou,
                    ", ".join(f"{k} {v:.2f}" for k, v in per_class.items()), entry["seconds"])
        snapshot = {"arch": arch, "state_dict": model.state_dict(), "epoch": epoch + 1, "val_miou": miou}
        if math.isfinite(miou) and miou > state["best_miou"]:
            state["best_miou"] = miou
            torch.save(snapshot, run_dir / "best.pt")
        if epoch + 1 in set(cfg.train.get("keep_epochs") or ()):
            torch.save(snapshot, run_dir / f"epoch_{epoch + 1}.pt")
        if schedule.done() or epoch + 1 >= epochs:
            # The end of the schedule: on cameras never trained on it generalises better than the
            # CamVid-val best (held-out runs, docs/results.md), so export.checkpoint can pick it.
            torch.save(snapshot, run_dir / "final.pt")
        if complete:
            state["epoch"] = epoch + 1
        tmp = run_dir / "last.pt.tmp"
        torch.save({"model": model.state_dict(), "optimizer": optimizer.state_dict(),
                    "schedule": schedule.state_dict(), **{k: state[k] for k in ("epoch", "best_miou", "history", "weight")}}, tmp)
        tmp.replace(last)
        (run_dir / "history.json").write_text(json.dumps(state["history"], indent=1))
        if schedule.done():
            logger.info("schedule done after %d steps, %.0f s", schedule.step, schedule.seconds())
            break

    result: dict[str, Any] = {"best_val_miou_torch": state["best_miou"], "history": state["history"]}
    if cfg.export.enabled and (run_dir / f"{_export_checkpoint(cfg)}.pt").is_file():
        result.update(_export_and_evaluate(cfg, run_dir, val_items))
    result["command"] = _command()
    (run_dir / "result.json").write_text(json.dumps(result, indent=1))
    return result


def interpolate_weights(final: dict[str, torch.Tensor], early: dict[str, torch.Tensor], alpha: float) -> dict[str, torch.Tensor]:
    """``alpha * final + (1 - alpha) * early`` for every floating tensor (BN statistics included).

    Weight-space interpolation between an early and the final checkpoint of one fine-tuning run
    (Wortsman et al., "Robust fine-tuning of zero-shot models", CVPR 2022): the late epochs fit
    CamVid's camera and town more closely, the interpolated net keeps more of the earlier, more
    general solution (measured: KITTI bottoms within 10 px 0.84 -> 0.91 for a CamVid val mIoU
    0.683 -> 0.677 at alpha 0.7; models/MODEL_CARD.md).
    """
    if set(final) != set(early):
        raise InputError("export.interpolate_from: the checkpoint's tensors differ from the trained model's")
    return {k: (alpha * v.float() + (1 - alpha) * early[k].float()).to(v.dtype) if v.is_floating_point() else v
            for k, v in final.items()}


def _export_checkpoint(cfg: DictConfig) -> str:
    """``export.checkpoint``, checked: ``best`` or ``final``."""
    which = str(cfg.export.get("checkpoint", "best"))
    if which not in ("best", "final"):
        raise InputError(f"export.checkpoint: {which!r} is neither 'best' (the best validation mIoU) nor 'final' "
                         "(the end of the schedule)")
    return which


def _export_and_evaluate(cfg: DictConfig, run_dir: Path, val_items: list) -> dict[str, Any]:
    best = torch.load(run_dir / f"{_export_checkpoint(cfg)}.pt", map_location="cpu", weights_only=True)
    model = fcn8s_vgg16(**best["arch"])
    state = best["state_dict"]
    early_path = cfg.export.get("interpolate_from")
    if early_path:
        early = torch.load(early_path, map_location="cpu", weights_only=True)
        # The early net as the run started from it (an FCN-8s into the stride-4 net: its new layers
        # at their initial values), tensor for tensor beside the trained one.
        start = fcn8s_vgg16(**best["arch"])
        try:
            load_fcn8s_state(start, early["state_dict"])
        except RuntimeError:
            raise InputError("export.interpolate_from: the checkpoint's tensors differ from the trained model's") from None
        state = interpolate_weights(state, start.state_dict(), float(cfg.export.interpolate_alpha))
        best = {**best, "epoch": f"{best['epoch']} (x{float(cfg.export.interpolate_alpha):g}) + epoch "
                                 f"{early.get('epoch', Path(early_path).name)} (x{1 - float(cfg.export.interpolate_alpha):g})"}
    model.load_state_dict(state)
    model.eval()
    half_pt, half_onnx = bool(cfg.export.half_pt), bool(cfg.export.get("half_onnx", False))
    real = cfg.data.get("camvid_root") is not None
    data = f"synthetic source seeds {list(cfg.data.train_source_seeds)} x {cfg.data.frames_per_seed} frames"
    if real:
        data = (f"CamVid train (SegNet split, 367 images) + {cfg.data.synthetic_per_epoch} of {data} per epoch; "
                "CamVid terms CC BY-NC 4.0 (non-commercial)")
    d = cfg.data.get("distill")
    if d is not None and d.get("enabled", False):
        data += (f"; + {d.per_epoch} per epoch of unlabelled frames ({', '.join(str(e.glob) for e in d.sets)}) "
                 f"with pseudo-labels of the teacher {sorted({str(e.model) for e in d.sets})} "
                 "(a Cityscapes-trained model: Cityscapes terms, non-commercial)")
    sc = cfg.data.get("soft")
    if sc is not None and sc.get("enabled", False):
        data = (f"soft labels of the Cityscapes teacher (Cityscapes terms, non-commercial) from {sc.manifest}, "
                f"{sc.per_epoch} windows per epoch by source weight {dict(sc.weights)}, held out "
                f"{OmegaConf.to_container(sc.holdout)}; CamVid labels where present (CC BY-NC 4.0, non-commercial)")
    meta = {
        "classes": ",".join(CLASS_NAMES),
        "input": "RGB float32 [0,1], (B,3,H,W), H and W multiples of 32; normalisation inside",
        "scale": f"{float(cfg.data.real_scale if real else cfg.data.scale):g}",
        "arch": json.dumps(best["arch"]),
        "epoch": str(best["epoch"]),
        "val_miou_torch": f"{best['val_miou']:.4f}",
        "command": _command(),
        "data": data,
    }
    if half_pt or half_onnx:
        # Round the weights once, so that the ONNX file and the .pt hold the same numbers.
        model.load_state_dict({k: v.half().float() if v.is_floating_point() else v
                               for k, v in model.state_dict().items()})
    onnx_path = export_onnx(model, cfg.export.onnx, sample_size=tuple(cfg.export.sample_size), metadata=meta,
                            half_weights=half_onnx)
    pt_path = save_fcn8s(model, cfg.export.pt, arch=best["arch"], meta=meta, half=half_pt)
    # Final check of the shipped file through the backend the pipeline calls.
    if real:
        # CamVid val at its own size (not the training set's pre-scaled copy), the backend
        # resizing by the training scale, as `eval data=camvid` does.
        val_set = RealSegmentation(read_camvid_split(cfg.data.camvid_root, "val"), scale=1.0)
        classes = CAMVID_CLASSES_PRESENT
        backend_scale = float(cfg.data.real_scale)
        where = f"CamVid val (101 images) at 360x480, backend scale {backend_scale:g}"
    else:
        # Validation frames rendered at `final_eval_scale` (1.0 = full KITTI size), the backend
        # resizing them to the training scale and upsampling the scores back.
        eval_scale = float(cfg.data.final_eval_scale)
        backend_scale = float(cfg.data.scale) / eval_scale
        val_set, classes = SyntheticSegmentation(val_items, cache=cfg.data.cache, scale=eval_scale), None
        where = (f"source seed {cfg.data.val_source_seed}, frames 0..{int(cfg.data.val_frames) - 1}, "
                 f"rendered at scale {eval_scale:g}, default appearance, backend scale {backend_scale:g}")
    sem_cfg = OmegaConf.create({"name": "fcn8s", "runtime": "onnx", "model": str(Path(onnx_path).resolve()),
                                "scale": backend_scale})

    def predict(image: torch.Tensor) -> torch.Tensor:
        return estimate_semantics(image_pair(image, "val"), sem_cfg).argmax(0)

    miou, per_class = evaluate(predict, val_set, desc="val (onnx)", classes=classes)
    logger.info("exported %s (%.1f MB) and %s; ONNX val mIoU %.4f", onnx_path,
                Path(onnx_path).stat().st_size / 1e6, pt_path, miou)
    return {"onnx": str(onnx_path), "pt": str(pt_path), "epoch": best["epoch"],
            "val_miou_onnx": miou, "val_per_class_iou_onnx": per_class, "val": where}


@hydra.main(config_path="../conf", config_name=CONFIG_NAME, version_base=None)
@one_line_errors("train.semantic")
def main(cfg: DictConfig) -> None:
    """Hydra entry point (``python -m train.semantic key=value ...``)."""
    result = run(cfg)
    print(json.dumps({k: v for k, v in result.items() if k != "history"}, indent=1))


if __name__ == "__main__":
    main()
