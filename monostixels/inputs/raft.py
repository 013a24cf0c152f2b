"""RAFT optical flow (torchvision architecture): builders, weight loading, padding, ONNX.

The network is torchvision's RAFT (Teed & Deng, ECCV 2020), ``small`` or ``large``, always
built with ``weights=None`` — this module never downloads anything. Weights come from a local
file: a checkpoint of our own training (``train/flow.py``; a dict with a ``"model"`` state dict)
or a plain state dict a user saved from ``torchvision.models.optical_flow.raft_*``.

Convention: :class:`RaftFlow` takes the *current* image as ``image1`` and the *previous* image
as ``image2``; RAFT's output maps a pixel of ``image1`` into ``image2`` so the result is the flow
current -> previous, ``x_prev = x + f`` (docs/conventions.md, section 2).

Input sizes: RAFT needs H and W divisible by 8; its 4-level correlation pyramid at 1/8
resolution needs at least 16 cells per side, so inputs are padded (edge replication) to
multiples of 8 and at least 128 pixels, and the flow is cropped back.

ONNX: :func:`export_onnx` exports :class:`RaftFlow` with a free batch and size (``torch.export``);
:class:`OnnxRaft` runs it with ONNX Runtime, both directions of a pair as one batch of two. A graph
of one fixed size (the legacy tracer, ``dynamic=False``) still works: smaller images are padded up
to it, a larger one is an :class:`InputError` naming the file and the size. :func:`quantize_onnx` writes an
INT8 copy of a float graph (its convolutions), which ``flow.runtime=auto`` prefers on a CPU.
"""
from __future__ import annotations

import logging
import os
import warnings
from collections.abc import Iterable
from functools import lru_cache
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from monostixels._checks import InputError, check_image_pair
from monostixels._threads import onnx_session_options
from monostixels._torchvision import torchvision

__all__ = [
    "RAFT_SIZES",
    "RAFT_MULTIPLE",
    "RAFT_MIN_SIZE",
    "ONNX_OPSET",
    "ONNX_MAX_SIZE",
    "GatherCorrBlock",
    "build_raft",
    "mask_hidden_of",
    "load_raft_weights",
    "RaftFlow",
    "convex_upsample",
    "padded_size",
    "pad_images",
    "export_onnx",
    "compact_names",
    "quantize_onnx",
    "TorchRaft",
    "OnnxRaft",
    "cached_torch_raft",
    "cached_onnx_raft",
]

logger = logging.getLogger(__name__)

_coords_grid = torchvision.models.optical_flow._utils.make_coords_grid
_upsample_flow = torchvision.models.optical_flow._utils.upsample_flow

#: The two torchvision RAFT configurations.
RAFT_SIZES = ("small", "large")
#: RAFT works at 1/8 resolution: H and W must be multiples of 8.
RAFT_MULTIPLE = 8
#: Smallest side (pixels): 1/8 resolution and 3 pooling levels of the correlation pyramid leave 2 cells.
RAFT_MIN_SIZE = 128
#: ONNX opset of the fixed-size export (the any-size export through torch.export takes at least 18).
ONNX_OPSET = 17


class GatherCorrBlock(torchvision.models.optical_flow.raft.CorrBlock):
    """torchvision's correlation block with the pyramid lookup done by gathers instead of ``grid_sample``.

    The same values (bilinear, zero outside the volume, the window's first axis the x offset as in
    torchvision): a window of ``2r + 1`` taps around a centroid shares one fractional offset, so the
    ``(2r + 2)^2`` integer cells under it are gathered once and blended with four weights. ONNX Runtime
    spends most of RAFT-small's time in ``GridSample`` and the arithmetic on its normalised grid
    (one batch item per pixel, a 7x7 grid each); the gathers take a fraction of it.
    """

    def index_pyramid(self, centroids_coords: torch.Tensor) -> torch.Tensor:
        r = self.radius
        side = 2 * r + 1
        B, _, h, w = centroids_coords.shape
        c = centroids_coords.permute(0, 2, 3, 1).reshape(B * h * w, 2)
        offsets = torch.arange(-r, r + 2, device=c.device, dtype=c.dtype)  # 2r + 2 cells per axis
        features = []
        for volume in self.corr_pyramid:
            n, _, H, W = volume.shape
            x0, y0 = torch.floor(c[:, :1]), torch.floor(c[:, 1:])
            fx, fy = (c[:, :1] - x0)[:, :, None], (c[:, 1:] - y0)[:, :, None]
            xs, ys = x0 + offsets, y0 + offsets  # (n, 2r + 2)
            inside = (((xs >= 0) & (xs <= W - 1))[:, :, None] & ((ys >= 0) & (ys <= H - 1))[:, None, :])
            idx = ys.clamp(0, H - 1).long()[:, None, :] * W + xs.clamp(0, W - 1).long()[:, :, None]
            cells = torch.gather(volume.reshape(n, H * W), 1, idx.reshape(n, -1)).reshape(n, side + 1, side + 1)
            cells = cells * inside.to(cells.dtype)
            win = ((1 - fx) * (1 - fy) * cells[:, :-1, :-1] + fx * (1 - fy) * cells[:, 1:, :-1]
                   + (1 - fx) * fy * cells[:, :-1, 1:] + fx * fy * cells[:, 1:, 1:])
            features.append(win.reshape(B, h, w, side * side))
            c = c / 2
        return torch.cat(features, dim=-1).permute(0, 3, 1, 2).contiguous()


def _with_gather_lookup(model: nn.Module) -> nn.Module:
    """``model`` with :class:`GatherCorrBlock` in place of its correlation block (no weights in it)."""
    old = model.corr_block
    model.corr_block = GatherCorrBlock(num_levels=old.num_levels, radius=old.radius)
    return model


def build_raft(size: str = "small", mask_hidden: int = 0) -> nn.Module:
    """A torchvision RAFT network with random weights (``weights=None``: no download).

    Args:
        size: ``small`` or ``large``.
        mask_hidden: RAFT-small only: > 0 adds RAFT's convex upsampler (the mask predictor, this many
            hidden channels) in place of torchvision's bilinear upsampling of the 1/8-resolution flow,
            which smears motion boundaries over 8 pixels of the input. RAFT-large always has it.
    """
    if size not in RAFT_SIZES:
        raise InputError(f"flow.size: RAFT size must be one of {RAFT_SIZES}, got {size!r}")
    if size == "large":
        return _with_gather_lookup(torchvision.models.optical_flow.raft_large(weights=None, progress=False))
    extra = {}
    if mask_hidden > 0:
        from torchvision.models.optical_flow.raft import MaskPredictor

        # in_channels: RAFT-small's recurrent hidden state (96 channels).
        extra["mask_predictor"] = MaskPredictor(in_channels=96, hidden_size=int(mask_hidden))
    return _with_gather_lookup(torchvision.models.optical_flow.raft_small(weights=None, progress=False, **extra))


def mask_hidden_of(state: dict[str, torch.Tensor]) -> int:
    """Hidden channels of the convex upsampler in a RAFT state dict (0: none, bilinear upsampling)."""
    w = state.get("mask_predictor.convrelu.0.weight")
    return int(w.shape[0]) if w is not None else 0


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
    # The file says whether RAFT-small has the convex upsampler (its mask predictor's weights).
    model = build_raft(size, mask_hidden_of(state) if size == "small" else 0)
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
        # torchvision's RAFT.forward, with the flow upsampled only after the last update: it upsamples
        # after every update (for the training loss over all of them), which in torch at inference is
        # a mask prediction and a full-size convex combination wasted per update.
        raft = self.raft
        # torchvision RAFT expects images normalised to [-1, 1].
        a, b = 2.0 * image_cur - 1.0, 2.0 * image_prev - 1.0
        fmap_a, fmap_b = torch.chunk(raft.feature_encoder(torch.cat([a, b], dim=0)), chunks=2, dim=0)
        raft.corr_block.build_pyramid(fmap_a, fmap_b)
        context_out = raft.context_encoder(a)
        hidden_size = raft.update_block.hidden_state_size
        hidden, context = torch.split(context_out, [hidden_size, context_out.shape[1] - hidden_size], dim=1)
        hidden, context = torch.tanh(hidden), F.relu(context)
        B, _, h, w = fmap_a.shape
        coords0 = _coords_grid(B, h, w).to(fmap_a.device)
        coords1 = coords0.clone()
        for _ in range(self.num_flow_updates):
            corr = raft.corr_block.index_pyramid(centroids_coords=coords1)
            hidden, delta = raft.update_block(hidden, context, corr, coords1 - coords0)
            coords1 = coords1 + delta
        if raft.mask_predictor is None:
            return _upsample_flow(coords1 - coords0)
        return convex_upsample(coords1 - coords0, raft.mask_predictor(hidden))


def convex_upsample(flow: torch.Tensor, up_mask: torch.Tensor, factor: int = 8) -> torch.Tensor:
    """RAFT's convex upsampling: each full-size vector a softmax-weighted mean of the 3x3 coarse vectors
    around its cell, times ``factor`` (torchvision's ``upsample_flow`` with a mask, to float rounding).

    The softmax is written out (max, exp, sums): ONNX Runtime's ``Softmax`` over the 9 weights, an inner
    axis of a 7-d tensor, transposes it to the last axis and back, several times the time of the whole
    upsampling written this way.

    Args:
        flow: (B, 2, h, w) coarse flow, pixels of the coarse grid. up_mask: (B, 9 * factor^2, h, w) logits.

    Returns:
        (B, 2, factor h, factor w) flow, pixels.
    """
    B, C, h, w = flow.shape
    m = up_mask.view(B, 1, 9, factor, factor, h, w)
    e = torch.exp(m - m.amax(dim=2, keepdim=True))
    around = F.unfold(factor * flow, kernel_size=3, padding=1).view(B, C, 9, 1, 1, h, w)
    up = (e * around).sum(dim=2) / e.sum(dim=2)
    return up.permute(0, 1, 4, 2, 5, 3).reshape(B, C, factor * h, factor * w)


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
    """RAFT inference in torch on (3, H, W) images; pads and crops (on CUDA when a GPU is present)."""

    def __init__(self, module: RaftFlow, device: str = "auto") -> None:
        # On a machine with a GPU torch runs there (the fast path); everything else stays on the CPU.
        self.device = torch.device("cuda" if device == "auto" and torch.cuda.is_available() else
                                   ("cpu" if device == "auto" else device))
        self.module = module.eval().to(self.device)

    def __call__(self, image_cur: torch.Tensor, image_prev: torch.Tensor) -> torch.Tensor:
        """Flow (2, H, W) current -> previous, pixels."""
        check_image_pair(image_cur, image_prev)
        (a, b), (H, W) = pad_images(image_cur[None].float(), image_prev[None].float())
        with torch.inference_mode():
            flow = self.module(a.to(self.device), b.to(self.device)).cpu()
        return flow[0, :, :H, :W].contiguous()

    def both_ways(self, image_cur: torch.Tensor, image_prev: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Flows (2, H, W) current -> previous and previous -> current, as one batch of two."""
        check_image_pair(image_cur, image_prev)
        (a, b), (H, W) = pad_images(image_cur[None].float(), image_prev[None].float())
        with torch.inference_mode():
            flow = self.module(torch.cat([a, b]).to(self.device), torch.cat([b, a]).to(self.device)).cpu()
        return flow[0, :, :H, :W].contiguous(), flow[1, :, :H, :W].contiguous()


#: Largest padded input side (pixels) an exported ONNX graph accepts (its dynamic dimensions' bound).
ONNX_MAX_SIZE = 4096


def export_onnx(module: RaftFlow, path: str | os.PathLike, height: int = RAFT_MIN_SIZE, width: int = RAFT_MIN_SIZE,
                opset: int = ONNX_OPSET, dynamic: bool = True, half_weights: bool = False) -> Path:
    """Export :class:`RaftFlow` to ONNX.

    The graph has inputs ``image_cur``, ``image_prev`` (B, 3, Hp, Wp) in [0, 1] and the output ``flow``
    (B, 2, Hp, Wp). With ``dynamic`` (default; ``torch.export`` through onnxscript) the size is free:
    any ``Hp, Wp`` that are multiples of 8 from :data:`RAFT_MIN_SIZE` to :data:`ONNX_MAX_SIZE`
    (``height``, ``width`` only size the example input), and ``B = 2``: a pair both ways, the
    forward-backward check in one run (a free batch does not export; one batch of two takes less time
    than two runs of one). Without it the legacy tracer fixes ``(Hp, Wp) = padded_size(height,
    width)`` and ``B = 1``. ``half_weights`` stores the weights as float16 (each cast back to float32
    in the graph): half the file, the same flow as weights loaded from a float16 state dict. The
    exporter's per-node debugging metadata is dropped.
    """
    Hp, Wp = padded_size(height, width)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    gen = torch.Generator().manual_seed(0)
    a = torch.rand(1, 3, Hp, Wp, generator=gen)
    b = torch.rand(1, 3, Hp, Wp, generator=gen)
    module = module.eval()
    # The exporters warn about every shape check in RAFT's forward; they are satisfied by construction.
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if dynamic:
            lo, hi = RAFT_MIN_SIZE // RAFT_MULTIPLE, ONNX_MAX_SIZE // RAFT_MULTIPLE
            h8, w8 = torch.export.Dim("h8", min=lo, max=hi), torch.export.Dim("w8", min=lo, max=hi)
            dims = {2: RAFT_MULTIPLE * h8, 3: RAFT_MULTIPLE * w8}
            a2, b2 = torch.cat([a, b]), torch.cat([b, a])
            torch.onnx.export(module, (a2, b2), str(path), input_names=["image_cur", "image_prev"],
                              output_names=["flow"], opset_version=max(opset, 18), dynamo=True,
                              dynamic_shapes={"image_cur": dims, "image_prev": dims}, external_data=False)
        else:
            torch.onnx.export(module, (a, b), str(path), input_names=["image_cur", "image_prev"],
                              output_names=["flow"], opset_version=opset, dynamo=False, do_constant_folding=True)
    import onnx

    proto = onnx.load(str(path))
    # The exporter's debugging record on every node (stack traces, module scopes) is most of a dynamic
    # graph's bytes and nothing ONNX Runtime reads.
    for node in proto.graph.node:
        node.doc_string = ""
        del node.metadata_props[:]
    compact_names(proto)
    if half_weights:
        from monostixels.inputs.fcn8s import store_half_weights

        store_half_weights(proto)
    # The recurrent updates are fixed in the graph: recorded, so that a runner can tell.
    entry = proto.metadata_props.add()
    entry.key, entry.value = "num_flow_updates", str(module.num_flow_updates)
    onnx.save(proto, str(path))
    logger.info("exported RAFT (%d flow updates, %s) to %s", module.num_flow_updates,
                "any size" if dynamic else f"{Hp}x{Wp}", path)
    return path


def compact_names(proto: Any) -> None:
    """Short names for an ONNX ``ModelProto``'s internal tensors (its inputs and outputs keep theirs), no node
    names, no intermediate shape records: the same graph in fewer bytes (the 12 unrolled updates repeat
    long module paths thousands of times)."""
    keep = {v.name for v in proto.graph.input} | {v.name for v in proto.graph.output}
    names: dict[str, str] = {}

    def short(name: str) -> str:
        if not name or name in keep:
            return name
        return names.setdefault(name, f"t{len(names):x}")

    for node in proto.graph.node:
        node.name = ""
        node.input[:] = [short(n) for n in node.input]
        node.output[:] = [short(n) for n in node.output]
    for init in proto.graph.initializer:
        init.name = short(init.name)
    del proto.graph.value_info[:]


def quantize_onnx(src: str | os.PathLike, dst: str | os.PathLike,
                  pairs: Iterable[tuple[torch.Tensor, torch.Tensor]]) -> Path:
    """An INT8 copy of an :func:`export_onnx` graph of batch two: its convolutions quantized, the rest float.

    :func:`monostixels.inputs.quantize.quantize_convolutions`, activation ranges seen on ``pairs``: the
    convolutions are most of RAFT's time, while the correlation lookup and the flow arithmetic keep
    float32 (a flow is pixel coordinates, not an activation of bounded range).

    Args:
        src: a dynamic (any-size) float graph of batch two, as :func:`export_onnx` writes.
        dst: the INT8 file to write.
        pairs: calibration pairs ``(image_cur, image_prev)`` (3, H, W) in [0, 1], at the scale the
            graph will run at; each is fed both ways, as :class:`OnnxRaft` runs a pair.

    Returns:
        ``dst``, with ``num_flow_updates`` and ``quantized: int8`` in its metadata.
    """
    import numpy as np
    import onnx

    from monostixels.inputs.quantize import quantize_convolutions

    src, dst = Path(src), Path(dst)
    proto = onnx.load(str(src))
    if proto.graph.input[0].type.tensor_type.shape.dim[0].dim_value != 2:
        raise InputError(f"quantize_onnx: {str(src)!r} is not a both-ways graph (batch 2) of export_onnx")
    meta = {p.key: p.value for p in proto.metadata_props}

    def feeds() -> Iterable[dict[str, np.ndarray]]:
        for cur, prev in pairs:
            (a, b), _ = pad_images(cur[None].float(), prev[None].float())
            yield {"image_cur": torch.cat([a, b]).numpy(), "image_prev": torch.cat([b, a]).numpy()}

    # 8-bit weights, as the shipped copy was made: they can saturate on a CPU without VNNI
    # (monostixels/inputs/quantize.py; models/MODEL_CARD.md says what that costs the flow).
    quantize_convolutions(proto, dst, feeds(), meta, reduce_range=False)
    out = onnx.load(str(dst))
    compact_names(out)
    onnx.save(out, str(dst))
    return dst


class OnnxRaft:
    """RAFT inference through ONNX Runtime (CPU) on (3, H, W) images; same output as :class:`TorchRaft`.

    Args:
        path: an ONNX file written by :func:`export_onnx`: of any size (dynamic), or of one size, to which
            smaller images are padded (a larger one is an :class:`InputError` naming the file).
        threads: ONNX Runtime's intra-op threads (0 = the process's, config key ``threads``:
            :func:`monostixels._threads.onnx_session_options`).
    """

    def __init__(self, path: str | os.PathLike, threads: int = 0) -> None:
        import onnxruntime as ort  # imported here: only the `onnx` runtime needs it

        p = Path(path)
        if not p.is_file():
            raise InputError(f"flow.onnx: RAFT ONNX file not found: {str(p)!r} (export one with `python -m train.flow export_only=true`)")
        opts = onnx_session_options(threads)
        opts.log_severity_level = 3
        try:
            self.session = ort.InferenceSession(str(p), sess_options=opts, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types for bad files.
            raise InputError(f"flow.onnx: cannot load RAFT ONNX file {str(p)!r}: {exc}") from exc
        shape = self.session.get_inputs()[0].shape
        self.path = p
        # A dynamic graph names its dimensions (strings); a fixed one has numbers.
        self.size = None if not all(isinstance(d, int) for d in shape[2:]) else (int(shape[2]), int(shape[3]))
        self.batch = int(shape[0]) if isinstance(shape[0], int) else 1
        meta = self.session.get_modelmeta().custom_metadata_map
        #: Recurrent updates fixed in the graph (None: a file exported before they were recorded).
        self.num_flow_updates = int(meta["num_flow_updates"]) if "num_flow_updates" in meta else None
        #: "int8" for a :func:`quantize_onnx` copy, else None (float).
        self.quantized = meta.get("quantized")

    def _run(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        out = self.session.run(["flow"], {"image_cur": a.numpy(), "image_prev": b.numpy()})[0]
        return torch.from_numpy(out)

    def _pad(self, *images: torch.Tensor) -> tuple[list[torch.Tensor], tuple[int, int]]:
        H, W = images[0].shape[-2:]
        Hp, Wp = padded_size(H, W)
        if self.size is not None and (Hp > self.size[0] or Wp > self.size[1]):
            raise InputError(
                f"flow.onnx: {str(self.path)!r} was exported for {self.size[0]}x{self.size[1]} inputs, the images are "
                f"{H}x{W} (padded {Hp}x{Wp}); export it for any size with `python -m train.flow export_only=true`"
            )
        # A fixed-size graph: smaller images are padded up to it (edge replication, as for torch); the flow
        # then differs slightly from the torch path, which pads only to a multiple of 8.
        return pad_images(*(im[None].float() for im in images), size=self.size)

    def __call__(self, image_cur: torch.Tensor, image_prev: torch.Tensor) -> torch.Tensor:
        """Flow (2, H, W) current -> previous, pixels."""
        check_image_pair(image_cur, image_prev)
        if self.batch == 2:
            return self.both_ways(image_cur, image_prev)[0]
        (a, b), (H, W) = self._pad(image_cur, image_prev)
        return self._run(a, b)[0, :, :H, :W].contiguous()

    def both_ways(self, image_cur: torch.Tensor, image_prev: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Flows (2, H, W) current -> previous and previous -> current, in one batched run where the graph allows."""
        check_image_pair(image_cur, image_prev)
        (a, b), (H, W) = self._pad(image_cur, image_prev)
        if self.batch == 2:
            out = self._run(torch.cat([a, b]), torch.cat([b, a]))
            return out[0, :, :H, :W].contiguous(), out[1, :, :H, :W].contiguous()
        return self._run(a, b)[0, :, :H, :W].contiguous(), self._run(b, a)[0, :, :H, :W].contiguous()


def _file_key(path: str | os.PathLike) -> tuple[str, float]:
    p = Path(path)
    return str(p.resolve()), (p.stat().st_mtime if p.is_file() else -1.0)


@lru_cache(maxsize=4)
def _torch_raft(key: tuple[str, float], size: str, num_flow_updates: int) -> TorchRaft:
    return TorchRaft(RaftFlow(load_raft_weights(key[0], size), num_flow_updates))


@lru_cache(maxsize=4)
def _onnx_raft(key: tuple[str, float], threads: int = 0) -> OnnxRaft:
    return OnnxRaft(key[0], threads)


def cached_torch_raft(path: str | os.PathLike, size: str, num_flow_updates: int) -> TorchRaft:
    """A :class:`TorchRaft` for a weights file, loaded once per (file, modification time)."""
    if not Path(path).is_file():
        load_raft_weights(path, size)  # raises the InputError naming the file
    return _torch_raft(_file_key(path), size, int(num_flow_updates))


def cached_onnx_raft(path: str | os.PathLike, threads: int = 0) -> OnnxRaft:
    """An :class:`OnnxRaft` for an ONNX file, loaded once per (file, modification time, threads)."""
    if not Path(path).is_file():
        OnnxRaft(path)  # raises the InputError naming the file
    return _onnx_raft(_file_key(path), int(threads))
