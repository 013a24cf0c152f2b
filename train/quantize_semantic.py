"""Write the INT8 copy of our real-image FCN-8s (``semantic=fcn8s_int8``, the net of ``preset=fast``).

Static quantization of the convolutions (:func:`monostixels.inputs.semantic.quantize_fcn8s_onnx`),
calibrated on every 12th CamVid train image (``conf/quantize_semantic.yaml``). About half the float
net's time on a CPU with 8-bit dot products; its accuracy beside the float net: models/MODEL_CARD.md.

Run from the repository root::

    python -m train.quantize_semantic                                          # models/fcn8s_real_int8.onnx
    python -m train.quantize_semantic src=runs/x/export.onnx dst=runs/x/export_int8.onnx
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import hydra
import torch
from omegaconf import DictConfig

from monostixels._checks import InputError, one_line_errors
from monostixels.inputs.semantic import quantize_fcn8s_onnx

logger = logging.getLogger(__name__)


def calibration_images(root: str | Path, split: str, every: int) -> list[torch.Tensor]:
    """Every ``every``-th image (sorted by name) of ``<root>/<split>/`` as (3, H, W) RGB in [0, 1]."""
    folder = Path(root) / split
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise InputError(f"calibration.every: an integer >= 1, got {every!r}")
    paths = sorted(p for p in folder.glob("*") if p.suffix.lower() in {".jpg", ".jpeg", ".png"})[::every]
    if not paths:
        raise InputError(f"calibration: no images in {folder}")
    images = []
    for p in paths:
        bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if bgr is None:
            raise InputError(f"calibration: cannot read {p}")
        images.append(torch.from_numpy(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)).permute(2, 0, 1).float() / 255.0)
    return images


def run(cfg: DictConfig) -> dict[str, object]:
    """Quantize ``cfg.src`` to ``cfg.dst``; returns what was written."""
    c = cfg.calibration
    images = calibration_images(str(c.root), str(c.split), c.every)
    dst = quantize_fcn8s_onnx(str(cfg.src), str(cfg.dst), images, scale=float(c.scale))
    return {"dst": str(dst), "calibration_images": len(images), "mb": round(dst.stat().st_size / 1e6, 2)}


@hydra.main(config_path="../conf", config_name="quantize_semantic", version_base=None)
@one_line_errors("train.quantize_semantic")
def main(cfg: DictConfig) -> None:
    """Hydra entry point (``python -m train.quantize_semantic key=value ...``)."""
    print(json.dumps(run(cfg), indent=1))


if __name__ == "__main__":
    main()
