"""`monostixels eval data=camvid`: score a semantic backend on labelled single images.

No flow, motion or stixels: each image goes through the configured ``semantic`` backend
(:func:`monostixels.inputs.semantic.estimate_semantics`, the same call the pipeline makes), its
argmax is compared with the labels mapped to our classes, and the report carries the ``semantic``
section of docs/conventions.md, section 4.5 (``miou``, ``per_class_iou`` over our classes present in
the dataset) plus the pixel accuracy.
"""
from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from tqdm import tqdm

from monostixels._checks import InputError
from monostixels.data.base import FramePair
from monostixels.data.camvid import CAMVID_CLASSES_PRESENT, CamVidSource
from monostixels.eval.metrics import SemanticAccumulator
from monostixels.core.geometry import Camera
from monostixels.inputs.semantic import estimate_semantics, semantic_params

__all__ = ["evaluate_semantics", "format_semantic_table", "image_pair"]

logger = logging.getLogger(__name__)

#: Nominal camera height (metres) of the wrapper pair: the semantic backends never read it.
_NOMINAL_HEIGHT_M = 1.5


def image_pair(image: torch.Tensor, name: str) -> FramePair:
    """Wrap a single image (3, H, W) RGB [0, 1] as a pair for the semantic backends.

    The backends read only ``pair.image``; the camera is a nominal pinhole (focal = width, marked
    ``meta["nominal_camera"]`` so that ``semantic.focal_px`` is not applied to it) and the previous
    image is the image itself.
    """
    H, W = image.shape[-2:]
    K = torch.tensor([[float(W), 0.0, W / 2], [0.0, float(W), H / 2], [0.0, 0.0, 1.0]])
    return FramePair(image=image, image_prev=image, camera=Camera(K=K, height=_NOMINAL_HEIGHT_M), name=name,
                     meta={"nominal_camera": True})


def evaluate_semantics(cfg: DictConfig, source: CamVidSource, *, progress: bool = True) -> dict[str, Any]:
    """Mean IoU of the ``semantic`` backend of ``cfg`` over the labelled images of ``source``.

    Args:
        cfg: composed config (the ``semantic`` group is used).
        source: a CamVid split.
        progress: show a progress bar over images.

    Returns:
        ``{"dataset", "split", "frames", "semantic": {"miou", "per_class_iou", "pixel_accuracy",
        "classes"}, "seconds_per_frame"}``; the mean runs over our classes present in CamVid.
    """
    backend = semantic_params(cfg.semantic)
    if backend.name in ("none", "gt"):
        raise InputError(
            f"semantic={backend.name}: data=camvid scores a semantic backend; choose fcn8s, "
            "fcn8s_synthetic, onnx or cityscapes19"
        )
    acc = SemanticAccumulator()
    seconds: list[float] = []
    for item in tqdm(source, total=len(source), desc=f"eval camvid {source.split}", disable=not progress, unit="image"):
        image, labels = CamVidSource.to_tensors(*item.load())
        t0 = time.perf_counter()
        scores = estimate_semantics(image_pair(image, item.name), backend)
        seconds.append(time.perf_counter() - t0)
        acc.add(scores.argmax(0), labels)
    if not seconds:
        raise InputError(f"data=camvid: split {source.split!r} yielded no images")
    sem = acc.result(classes=CAMVID_CLASSES_PRESENT)
    cm = acc.confusion
    sem["pixel_accuracy"] = float(cm.diagonal()[: cm.shape[0]].sum()) / max(1, int(cm.sum()))
    sem["classes"] = list(sem["per_class_iou"])
    return {"dataset": "camvid", "split": source.split, "frames": len(seconds), "semantic": sem,
            "seconds_per_frame": float(np.mean(seconds))}


def format_semantic_table(report: dict[str, Any]) -> str:
    """Per-class IoU and the mean as a small text table."""
    sem = report["semantic"]
    lines = [f"CamVid {report['split']} ({report['frames']} images): semantic segmentation",
             f"{'class':<12} {'IoU':>6}"]
    lines += [f"{name:<12} {iou:6.3f}" for name, iou in sem["per_class_iou"].items()]
    lines += [f"{'mean':<12} {sem['miou']:6.3f}", f"{'pixel acc.':<12} {sem['pixel_accuracy']:6.3f}"]
    return "\n".join(lines)
