"""Import torchvision on a CPU-only torch.

Why this exists: torchvision 0.28.0 is the release that pairs with torch 2.13.0, but its wheel
is a CUDA build; on the CPU torch its C++ extension does not load, so the custom operators
``torchvision::nms`` and ``torchvision::qnms`` are never defined, and ``import torchvision``
fails when ``_meta_registrations`` registers fake kernels for them. We define the two operator
schemas (no kernels) before the import. We only use pure-Python parts of torchvision (model
architectures: RAFT, VGG-16); its C++ ops and ``torchvision.io`` stay unavailable — read and
write images with OpenCV. Import torchvision only through this module.
"""
from __future__ import annotations

import torch

__all__ = ["torchvision"]

_SCHEMAS = {
    "nms": "nms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor",
    "qnms": "qnms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor",
}

# Kept at module level: the schemas live as long as this Library object.
_LIB: torch.library.Library | None = None


def _define_missing_ops() -> None:
    global _LIB
    missing = [name for name in _SCHEMAS if not _op_exists(name)]
    if not missing:
        return
    _LIB = torch.library.Library("torchvision", "FRAGMENT")
    for name in missing:
        _LIB.define(_SCHEMAS[name])


def _op_exists(name: str) -> bool:
    try:
        torch._C._dispatch_find_schema_or_throw(f"torchvision::{name}", "")
        return True
    except RuntimeError:
        return False


_define_missing_ops()

import torchvision  # noqa: E402  (must follow the op definitions above)
