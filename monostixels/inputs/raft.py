"""RAFT optical flow (torchvision architecture): builders, weight loading, padding, ONNX.

The network is torchvision's RAFT (Teed & Deng, ECCV 2020), ``small`` or ``large``, always
built with ``weights=None`` — this module never downloads anything. Weights come from a local
file: a checkpoint of our own training (``train/flow.py``; a dict with a ``"model"`` state dict)
or a plain state dict a user saved from ``torchvision.models.optical_flow.raft_*``.

Convention: :class:`RaftFlow` takes the *current* image as ``image1`` and the *previous* image
as ``image2``; RAFT's output maps a pixel of ``image1`` into ``image2`` so the result is the flow
current -> previous, ``x_prev = x + f`` (SPEC section 2).

Input sizes: RAFT needs H and W divisible by 8; its 4-level correlation pyramid at 1/8
resolution needs at least 16 cells per side, so inputs are padded (edge replication) to
multiples of 8 and at least 128 pixels, and the flow is cropped back.

ONNX: :func:`export_onnx` traces :class:`RaftFlow` for one padded input size (the traced
coordinate grid fixes it); :class:`OnnxRaft` runs such a file with ONNX Runtime: smaller images
are padded up to the exported size, a larger one is an :class:`InputError` naming the file and
the size (and the command that exports a file for it).
"""
from __future__ import annotations

import logging
import os
import warnings
from functools import lru_cache
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from monostixels._checks import InputError, check_image_pair
from monostixels._torchvision import torchvision

__all__ = [
    "RAFT_SIZES",
    "RAFT_MULTIPLE",
    "RAFT_MIN_SIZE",
    "ONNX_OPSET",
    "build_raft",
    "load_raft_weights",
    "RaftFlow",
    "padded_size",
    "pad_images",
    "export_onnx",
    "TorchRaft",
    "OnnxRaft",
    "cached_torch_raft",
    "cached_onnx_raft",
]

logger = logging.getLogger(__name__)

#: The two torchvision RAFT configurations.
RAFT_SIZES = ("small", "large")
#: RAFT works at 1/8 resolution: H and W must be multiples of 8.
RAFT_MULTIPLE = 8
#: Smallest side (pixels): 1/8 resolution and 3 pooling levels of the correlation pyramid leave 2 cells.
RAFT_MIN_SIZE = 128
#: grid_sample (correlation lookup) needs ONNX opset 16.
ONNX_OPSET = 17


def build_raft(size: str = "small") -> nn.Module:
    """A torchvision RAFT network with random weights (``weights=None``: no download).

    Args:
        size: ``small`` or ``large``.
    """
    if size not in RAFT_SIZES:
        raise InputError(f"flow.size: RAFT size must be one of {RAFT_SIZES}, got {size!r}")
    builder = torchvision.models.optical_flow.raft_small if size == "small" else torchvision.models.optical_flow.raft_large
    return builder(weights=None, progress=False)


def load_raft_weights(path: str | os.PathLike, size: str = "small") -> nn.Module:
    """RAFT of ``size`` with the weights of a local file, in eval mode.

    Args:
        path: a ``.pt``/``.pth`` file holding a state dict, or a checkpoint dict with the state
            dict under ``"model"`` (our ``train/flow.py`` checkpoints).
        size: ``small`` or ``large``; must match the file.

    Raises:
        InputError: the file is missing, unreadable, or does not fit the architecture.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(
            f"flow.weights: RAFT weights file not found: {str(p)!r} (train one with `python -m train.flow`, "
            "or point flow.weights at a state dict of torchvision RAFT)"
        )
    try:
        obj = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for a corrupt file; report them all as one.
        raise InputError(f"flow.weights: cannot read RAFT weights {str(p)!r}: {exc}") from exc
    state = obj.get("model", obj) if isinstance(obj, dict) else None
    if not isinstance(state, dict):
        raise InputError(f"flow.weights: {str(p)!r} holds no state dict (got {type(obj).__name__})")
    model = build_raft(size)
    try:
        model.load_state_dict(state)
    except RuntimeError as exc:
        raise InputError(f"flow.weights: {str(p)!r} does not fit RAFT-{size}: {str(exc).splitlines()[0]}") from exc
    return model.eval()


class RaftFlow(nn.Module):
    """RAFT with our input/output conventions (the module that is exported to ONNX).

    Args:
        raft: a torchvision RAFT network.
        num_flow_updates: recurrent refinement steps at inference.

    Forward:
        image_cur, image_prev: (B, 3, H, W) float RGB in [0, 1], H and W multiples of 8.
        Returns the final flow (B, 2, H, W), current -> previous, pixels.
    """

    def __init__(self, raft: nn.Module, num_flow_updates: int = 12) -> None:
        super().__init__()
        self.raft = raft
        self.num_flow_updates = int(num_flow_updates)

    def forward(self, image_cur: torch.Tensor, image_prev: torch.Tensor) -> torch.Tensor:
        # torchvision RAFT expects images normalised to [-1, 1].
        return self.raft(2.0 * image_cur - 1.0, 2.0 * image_prev - 1.0, num_flow_updates=self.num_flow_updates)[-1]


def padded_size(height: int, width: int) -> tuple[int, int]:
    """Input size (H, W) RAFT runs at for an image of ``height`` x ``width`` pixels."""
    def up(n: int) -> int:
        return max(RAFT_MIN_SIZE, -(-n // RAFT_MULTIPLE) * RAFT_MULTIPLE)
    return up(height), up(width)


def pad_images(*images: torch.Tensor, size: tuple[int, int] | None = None) -> tuple[list[torch.Tensor], tuple[int, int]]:
    """Pad images (B, 3, H, W) at the bottom/right by edge replication to ``size`` (default :func:`padded_size`).

    Returns:
        The padded images and the original (H, W) to crop the flow back to.
    """
    H, W = images[0].shape[-2:]
    Hp, Wp = size if size is not None else padded_size(H, W)
    if Hp < H or Wp < W:
        raise InputError(f"RAFT input: image {H}x{W} is larger than the network input {Hp}x{Wp}")
    out = [F.pad(im, (0, Wp - W, 0, Hp - H), mode="replicate") if (Hp, Wp) != (H, W) else im for im in images]
    return out, (H, W)


class TorchRaft:
    """RAFT inference in torch on (3, H, W) images; pads and crops."""

    def __init__(self, module: RaftFlow) -> None:
        self.module = module.eval()

    def __call__(self, image_cur: torch.Tensor, image_prev: torch.Tensor) -> torch.Tensor:
        """Flow (2, H, W) current -> previous, pixels."""
        check_image_pair(image_cur, image_prev)
        (a, b), (H, W) = pad_images(image_cur[None].float(), image_prev[None].float())
        with torch.inference_mode():
            flow = self.module(a, b)
        return flow[0, :, :H, :W].contiguous()


def export_onnx(module: RaftFlow, path: str | os.PathLike, height: int, width: int, opset: int = ONNX_OPSET) -> Path:
    """Export :class:`RaftFlow` to ONNX for images of ``height`` x ``width`` (padded size used).

    The traced graph has inputs ``image_cur``, ``image_prev`` (1, 3, Hp, Wp) in [0, 1] and the
    output ``flow`` (1, 2, Hp, Wp); ``(Hp, Wp) = padded_size(height, width)`` is stored in the
    graph, so :class:`OnnxRaft` knows which images the file accepts.
    """
    Hp, Wp = padded_size(height, width)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    gen = torch.Generator().manual_seed(0)
    a = torch.rand(1, 3, Hp, Wp, generator=gen)
    b = torch.rand(1, 3, Hp, Wp, generator=gen)
    module = module.eval()
    # The tracer warns about every shape check in RAFT's forward; the size is fixed on purpose.
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            module, (a, b), str(path), input_names=["image_cur", "image_prev"], output_names=["flow"],
            opset_version=opset, dynamo=False, do_constant_folding=True,
        )
    logger.info("exported RAFT (%d flow updates) at %dx%d to %s", module.num_flow_updates, Hp, Wp, path)
    return path


class OnnxRaft:
    """RAFT inference through ONNX Runtime (CPU) on (3, H, W) images; same output as :class:`TorchRaft`.

    Args:
        path: an ONNX file written by :func:`export_onnx`.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        import onnxruntime as ort  # imported here: only the `onnx` runtime needs it

        p = Path(path)
        if not p.is_file():
            raise InputError(f"flow.onnx: RAFT ONNX file not found: {str(p)!r} (export one with `python -m train.flow export_only=true`)")
        opts = ort.SessionOptions()
        opts.log_severity_level = 3
        try:
            self.session = ort.InferenceSession(str(p), sess_options=opts, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types for bad files.
            raise InputError(f"flow.onnx: cannot load RAFT ONNX file {str(p)!r}: {exc}") from exc
        shape = self.session.get_inputs()[0].shape
        self.path = p
        self.size = (int(shape[2]), int(shape[3]))

    def __call__(self, image_cur: torch.Tensor, image_prev: torch.Tensor) -> torch.Tensor:
        """Flow (2, H, W) current -> previous, pixels."""
        check_image_pair(image_cur, image_prev)
        H, W = image_cur.shape[-2:]
        Hp, Wp = padded_size(H, W)
        if Hp > self.size[0] or Wp > self.size[1]:
            raise InputError(
                f"flow.onnx: {str(self.path)!r} was exported for {self.size[0]}x{self.size[1]} inputs, the images are "
                f"{H}x{W} (padded {Hp}x{Wp}); export it for this size with "
                f"`python -m train.flow export_only=true export.height={H} export.width={W} export.onnx=OUT.onnx`"
            )
        # Smaller images are padded up to the exported size (edge replication, as for torch); the
        # flow then differs slightly from the torch path, which pads only to a multiple of 8.
        (a, b), _ = pad_images(image_cur[None].float(), image_prev[None].float(), size=self.size)
        out = self.session.run(["flow"], {"image_cur": a.numpy(), "image_prev": b.numpy()})[0]
        return torch.from_numpy(out[0, :, :H, :W]).contiguous()


def _file_key(path: str | os.PathLike) -> tuple[str, float]:
    p = Path(path)
    return str(p.resolve()), (p.stat().st_mtime if p.is_file() else -1.0)


@lru_cache(maxsize=4)
def _torch_raft(key: tuple[str, float], size: str, num_flow_updates: int) -> TorchRaft:
    return TorchRaft(RaftFlow(load_raft_weights(key[0], size), num_flow_updates))


@lru_cache(maxsize=4)
def _onnx_raft(key: tuple[str, float]) -> OnnxRaft:
    return OnnxRaft(key[0])


def cached_torch_raft(path: str | os.PathLike, size: str, num_flow_updates: int) -> TorchRaft:
    """A :class:`TorchRaft` for a weights file, loaded once per (file, modification time)."""
    if not Path(path).is_file():
        load_raft_weights(path, size)  # raises the InputError naming the file
    return _torch_raft(_file_key(path), size, int(num_flow_updates))


def cached_onnx_raft(path: str | os.PathLike) -> OnnxRaft:
    """An :class:`OnnxRaft` for an ONNX file, loaded once per (file, modification time)."""
    if not Path(path).is_file():
        OnnxRaft(path)  # raises the InputError naming the file
    return _onnx_raft(_file_key(path))
