"""The flow backends of images (``flow.name``: deepflow, dis, raft) and the variational refinement at full size.

- ``deepflow``: DeepFlow (Weinzaepfel et al. 2013), the paper's choice: OpenCV contrib's
  variational DeepFlow, guided by dense patch matches for large displacements
  (``cfg.matches: dis|none``, see :func:`_deepflow`).
- ``dis``: OpenCV DIS flow (Kroeger et al. 2016), fast; ``cfg.preset`` ultrafast|fast|medium.
- ``raft``: torchvision RAFT (small/large) with weights from a local file (``cfg.weights``),
  run in torch or through ONNX Runtime (``cfg.runtime: torch|onnx``, file ``cfg.onnx``; ``auto``: ONNX
  Runtime on a CPU, the INT8 copy beside the weights where ``cfg.precision: int8``).

Each returns the flow from the *current* to the *previous* image (:mod:`monostixels.inputs.flow`);
OpenCV backends are called as ``calc(current, previous)``.
"""
from __future__ import annotations

import logging
import threading
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
import torch

from monostixels._pools import helper_pool
from monostixels._checks import InputError, check_finite_fast
from monostixels._paths import find_file
from monostixels.inputs.flow_config import DeepFlowConfig, DisFlowConfig, ImageFlowConfig, RaftFlowConfig, flow_params
from monostixels.inputs.flow_resample import (MIN_SCALED_SIDE, at_scale, downscale, flow_scale, remap, scaled_size,
                                              upsample_flow)
from monostixels.core.grey import to_gray_u8

__all__ = ["BACKENDS", "gray_u8", "raft_both_ways", "refine_flow", "refine_passes", "resolve_path", "run_backend"]


logger = logging.getLogger(__name__)


_DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


def resolve_path(path: str | Path) -> Path:
    """A file path from the config (:func:`monostixels._paths.find_file`: absolute, relative to the
    working directory, a shipped model ``models/...``, the repository root); as given if none exists."""
    found = find_file(path)
    return found if found is not None else Path(path).expanduser()


def gray_u8(image: torch.Tensor) -> np.ndarray:
    """(3, H, W) float32 RGB in [0, 1] -> (H, W) uint8 grey (OpenCV flow backends work on 8-bit grey)."""
    # Quantised in numpy rather than with torch ops (the same values): no thread hand-offs beside the
    # other threads of the flow stage.
    x = np.clip(image.detach().numpy(), 0.0, 1.0)
    return to_gray_u8((x * 255.0 + 0.5).astype(np.uint8))


#: Overlap (px of the grid DeepFlow runs on) on each side of a seam between bands; blended linearly.
_BAND_MARGIN = 24


def _bands(cfg: DeepFlowConfig) -> int:
    raw = cfg.bands
    if isinstance(raw, bool) or not isinstance(raw, int) or raw < 1:
        raise InputError(f"flow.bands: must be a whole number >= 1, got {raw!r}")
    return raw


def _in_bands(calc: Callable[[np.ndarray, np.ndarray], np.ndarray], a: np.ndarray, b: np.ndarray,
              bands: int) -> np.ndarray:
    """``calc(a, b)`` on ``bands`` vertical strips side by side, one thread each (OpenCV releases the
    GIL; DeepFlow itself runs on one core). Neighbouring strips overlap by ``2 * _BAND_MARGIN``
    columns, blended linearly, so no seam shows; a strip sees its own image part only, which the
    DIS warp before it makes harmless (the residual flow left to solve is short-range)."""
    if bands == 1:
        return calc(a, b)
    h, w = a.shape
    m = _BAND_MARGIN
    cuts = [round(k * w / bands) for k in range(bands + 1)]
    if min(c1 - c0 for c0, c1 in zip(cuts[:-1], cuts[1:])) < 2 * m + MIN_SCALED_SIDE:
        raise InputError(f"flow.bands: {bands} strips of a {w} px wide grid are too narrow "
                         f"(each needs >= {2 * m + MIN_SCALED_SIDE} px); lower flow.bands")
    spans = [(max(c0 - m, 0), min(c1 + m, w)) for c0, c1 in zip(cuts[:-1], cuts[1:])]
    pool = helper_pool("flow-bands", bands)
    parts = list(pool.map(lambda sp: calc(np.ascontiguousarray(a[:, sp[0]:sp[1]]),
                                          np.ascontiguousarray(b[:, sp[0]:sp[1]])), spans))
    out = np.zeros((h, w, 2), np.float32)
    weight = np.zeros((1, w, 1), np.float32)
    for (s0, s1), part in zip(spans, parts):
        # Weights 1 inside the strip's own columns, ramping to 0 across each overlap with a
        # neighbour (the two ramps of an overlap add up to 1).
        cols = np.arange(s0, s1, dtype=np.float32)
        left = (cols - s0 + 0.5) / (2 * m) if s0 > 0 else np.ones_like(cols)
        right = (s1 - 0.5 - cols) / (2 * m) if s1 < w else np.ones_like(cols)
        wgt = np.clip(np.minimum(left, right), 0.0, 1.0)
        out[:, s0:s1] += wgt[None, :, None] * part
        weight[:, s0:s1] += wgt[None, :, None]
    return out / weight


def _deepflow(cur: torch.Tensor, prev: torch.Tensor, cfg: DeepFlowConfig,
              grey: tuple[np.ndarray, np.ndarray] | None = None, init: np.ndarray | None = None) -> torch.Tensor:
    """DeepFlow current -> previous.

    DeepFlow is a variational energy plus a matching term fed by DeepMatching, which is what lets
    it follow large displacements. OpenCV's ``createOptFlow_DeepFlow`` is the variational part
    only: it is accurate on small displacements and fails on large ones (the near road). With
    ``matches: dis`` (default) dense patch matches from DIS stand in for
    DeepMatching: the previous image is warped by them and DeepFlow's energy then solves for the
    residual, composed as ``f(x) = r(x) + f0(x + r(x))``. ``matches: none`` is OpenCV's DeepFlow
    as is. ``cfg.scale < 1``: the matches stay at full resolution, the residual (or, without
    matches, the whole DeepFlow) is solved on the downscaled images. ``cfg.bands > 1``: that
    variational solve runs on as many overlapping vertical strips in parallel threads. ``grey``:
    the images' :func:`gray_u8`, when the caller has them; ``init``: (H, W, 2) start of the DIS
    matches (:func:`_dis_calc`).
    """
    if not hasattr(cv2, "optflow"):
        raise InputError(f"flow=deepflow: this OpenCV ({cv2.__version__}) has no cv2.optflow; DeepFlow is in "
                         "opencv-contrib-python-headless (install it instead of the plain OpenCV wheel)")
    a, b = grey if grey is not None else (gray_u8(cur), gray_u8(prev))
    scale = flow_scale(cfg)
    bands = _bands(cfg)

    def variational(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return _in_bands(lambda p, q: cv2.optflow.createOptFlow_DeepFlow().calc(p, q, None), x, y, bands)

    matches = cfg.matches
    if matches == "none":
        f = at_scale(variational, a, b, scale)
    elif matches == "dis":
        f0 = _dis_calc(_DIS_PRESETS[cfg.matches_preset], a, b, init)
        r = np.ascontiguousarray(at_scale(variational, a, remap(b, f0), scale))
        f = r + remap(f0, r)
    else:
        raise InputError(f"flow.matches: must be 'dis' or 'none', got {matches!r}")
    return torch.from_numpy(np.ascontiguousarray(f.transpose(2, 0, 1))).float()


def refine_flow(grey: tuple[np.ndarray, np.ndarray], flow: torch.Tensor, passes: int = 1) -> torch.Tensor:
    """Full-resolution variational refinement of ``flow`` (2, H, W) on the (current, previous) grey
    images (:func:`gray_u8`), ``passes`` times (OpenCV ``VariationalRefinement`` with its defaults:
    the energy and iterations DIS uses at each of its levels).

    One call linearises the data term once, around the flow it starts from (the previous image
    warped by it); a far start leaves it short of the energy's minimum. Each further pass warps
    again by the refined flow, as the levels of a pyramid would (docs/experiments.md "Flow").
    """
    f = np.ascontiguousarray(flow.permute(1, 2, 0).numpy(), dtype=np.float32)
    refinement = _refinement()
    for _ in range(passes):
        refinement.calc(grey[0], grey[1], f)
    return torch.from_numpy(np.ascontiguousarray(f.transpose(2, 0, 1)))


_KEPT = threading.local()


def _refinement() -> Any:
    """This thread's OpenCV ``VariationalRefinement``, made once and kept.

    A new one allocates its full-size buffers at its first call (~25 ms of a ~85 ms refinement of a
    KITTI frame on one core); a kept one reuses them. The results are bit-identical (each call starts
    from the flow and images it is given; tests/test_flow.py). One per thread: the two directions and
    the strips refine in threads of their own. DIS objects are not kept: one given a start keeps some
    of it for its later calls (their flow then differs).
    """
    obj = getattr(_KEPT, "refinement", None)
    if obj is None:
        obj = _KEPT.refinement = cv2.VariationalRefinement_create()
    return obj


def refine_passes(cfg: ImageFlowConfig) -> int:
    """``cfg.refine_passes``: how many times :func:`refine_flow` runs where ``refine`` is on."""
    val = cfg.refine_passes
    if isinstance(val, bool) or not isinstance(val, int) or val < 1:
        raise InputError(f"flow.refine_passes: must be an integer >= 1, got {val!r}")
    return val


#: Smallest side (pixels) of the images DIS is run on: below it OpenCV's DIS crashes the process
#: (measured: 12 px segfaults, 16 px runs unless the image is very wide, which raises a cv2.error).
_DIS_MIN_SIDE = 16


def _dis_calc(preset: int, a: np.ndarray, b: np.ndarray, init: np.ndarray | None) -> np.ndarray:
    """DIS flow (H, W, 2) of grey images ``a`` -> ``b``; ``init`` (H, W, 2) float32 pixels: its start.

    OpenCV's DIS takes a given flow as the start of its coarsest level (downscaled) instead of zero;
    every level still runs, so the result is DIS's, seeded (a stream's previous flow: the matches of
    large displacements then come from it rather than from the coarsest patches alone).
    """
    if min(a.shape[:2]) < _DIS_MIN_SIDE:
        # OpenCV's DIS segfaults on such images (12 x 40 px) instead of raising.
        raise InputError(f"flow: DIS cannot run on {a.shape[1]}x{a.shape[0]} px grey images (at flow.scale); "
                         f"it needs a side of at least {_DIS_MIN_SIDE} px")
    algo = cv2.DISOpticalFlow_create(preset)
    if init is not None and init.shape != (*a.shape, 2):
        raise InputError(f"flow init: shape {init.shape} for {a.shape[1]}x{a.shape[0]} images, expected (H, W, 2)")
    try:
        return algo.calc(a, b, None if init is None else np.array(init, dtype=np.float32, order="C"))
    except cv2.error as e:
        # A wide, low image leaves DIS's pyramid no level (16 x 1000 px); OpenCV asserts in its resize.
        raise InputError(f"flow: DIS cannot run on {a.shape[1]}x{a.shape[0]} px grey images (at flow.scale): "
                         f"{str(e).strip().splitlines()[-1]}") from None


def _dis(cur: torch.Tensor, prev: torch.Tensor, cfg: DisFlowConfig,
         grey: tuple[np.ndarray, np.ndarray] | None = None, init: np.ndarray | None = None) -> torch.Tensor:
    a, b = grey if grey is not None else (gray_u8(cur), gray_u8(prev))
    f = _dis_calc(_DIS_PRESETS[cfg.preset], a, b, init)
    return torch.from_numpy(np.ascontiguousarray(f.transpose(2, 0, 1))).float()


@lru_cache(maxsize=4)
def _saturates_here(path: str) -> bool:
    """Whether the INT8 file ``path`` has 8-bit weights (pairwise 16-bit sums can saturate) and this CPU has
    no VNNI (:mod:`monostixels.inputs.quantize`): ``flow.precision=int8`` then runs the float graph, warned once."""
    from monostixels._cpu import int8_path
    from monostixels.inputs.quantize import can_saturate

    if int8_path() != "no_vnni" or not can_saturate(path):
        return False
    logger.warning("flow: %s has 8-bit weights, which can saturate on this CPU (no VNNI): running the float "
                   "graph beside it instead", path)
    return True


def _raft_net(cfg: Any) -> Any:
    """The RAFT runner of ``cfg`` (``cfg.runtime`` auto | torch | onnx), loaded once per file."""
    from monostixels.inputs.raft import cached_onnx_raft, cached_torch_raft  # torchvision import is slow

    cfg: RaftFlowConfig = flow_params(cfg)  # type: ignore[assignment]
    runtime = cfg.runtime
    if runtime == "auto":
        # On a CPU the exported graph runs faster in ONNX Runtime than the network in torch
        # (docs/results.md "Flow"). The export of the weights is the .onnx file beside them (as
        # train.flow writes both): other weights without one run in torch, and so does any on a GPU.
        # flow.precision=int8 takes the INT8 copy beside them (<name>_int8.onnx) where there is one:
        # its convolutions, most of the time, run faster on a CPU at a small cost in accuracy
        # (docs/experiments.md "Flow"), except where its 8-bit weights can saturate (a CPU without VNNI).
        weights, precision = cfg.weights, cfg.precision
        if weights is not None and not torch.cuda.is_available():
            w = resolve_path(weights)
            int8 = [w.with_name(w.stem + "_int8.onnx")] if precision == "int8" else []
            names = [n for n in int8 if n.is_file() and not _saturates_here(str(n))] + [w.with_suffix(".onnx")]
            for beside in (n for n in names if n.is_file()):
                net = cached_onnx_raft(beside, cfg.threads)
                # Its updates are fixed at export: another flow.iters runs in torch.
                if net.num_flow_updates == cfg.iters:
                    return net
        runtime = "torch"
    if runtime == "torch":
        if cfg.weights is None:
            raise InputError("flow.weights: the raft backend needs a weights file (flow.weights=PATH)")
        return cached_torch_raft(resolve_path(cfg.weights), cfg.size, cfg.iters)
    # runtime=onnx (the schema admits no other: flow_config.RaftRuntime)
    if cfg.onnx is None:
        raise InputError("flow.onnx: the raft backend with runtime=onnx needs an ONNX file (flow.onnx=PATH)")
    return cached_onnx_raft(resolve_path(cfg.onnx), cfg.threads)


def _raft(cur: torch.Tensor, prev: torch.Tensor, cfg: RaftFlowConfig,
          grey: tuple[np.ndarray, np.ndarray] | None = None, init: np.ndarray | None = None) -> torch.Tensor:
    """RAFT current -> previous (``cfg.runtime`` torch | onnx); it reads the RGB images, not ``grey``,
    and starts from zero (``init`` is not used)."""
    return _raft_net(cfg)(cur, prev)


def raft_both_ways(image_cur: torch.Tensor, image_prev: torch.Tensor, cfg: RaftFlowConfig, grey_prev: np.ndarray | None = None
                    ) -> tuple[torch.Tensor, torch.Tensor, np.ndarray | None]:
    """RAFT's flows current -> previous and previous -> current as one batch, at ``cfg.scale`` and refined
    as :func:`compute_flow` does each (the forward-backward check without twice the network's time).
    Returns both flows and, where the refinement made it, the full-size grey of ``image_cur`` (as
    :func:`flow_of_checked_images`; ``grey_prev`` is the caller's grey of ``image_prev``, or None)."""
    net = _raft_net(cfg)
    scale = flow_scale(cfg)
    H, W = image_cur.shape[-2:]
    if scale == 1.0:
        fwd, bwd = net.both_ways(image_cur.float(), image_prev.float())
    else:
        size = scaled_size(H, W, scale)
        fwd, bwd = net.both_ways(downscale(image_cur, size), downscale(image_prev, size))
        fwd, bwd = upsample_flow(fwd, (H, W)), upsample_flow(bwd, (H, W))
    for f in (fwd, bwd):
        check_finite_fast(f, "flow from backend raft")
    if not cfg.refine:
        return fwd, bwd, None
    g_cur = gray_u8(image_cur.float())
    g_prev = grey_prev if grey_prev is not None else gray_u8(image_prev.float())
    passes = refine_passes(cfg)
    # The two directions in two threads: OpenCV's refinement leaves most of a second core idle (and
    # releases the GIL); on two cores this halves its time.
    back = helper_pool("refine-backward").submit(refine_flow, (g_prev, g_cur), bwd, passes)
    fwd, bwd = refine_flow((g_cur, g_prev), fwd, passes), back.result()
    for f in (fwd, bwd):
        check_finite_fast(f, "flow from backend raft after flow.refine")
    return fwd, bwd, g_cur


#: Image backends: (current, previous, cfg, grey images or None, start flow or None) -> flow (2, H, W).
BACKENDS: dict[str, Callable[..., torch.Tensor]] = {
    "deepflow": _deepflow,
    "dis": _dis,
    "raft": _raft,
}


def run_backend(name: str, image_cur: torch.Tensor, image_prev: torch.Tensor, cfg: ImageFlowConfig,
             grey: tuple[np.ndarray, np.ndarray] | None = None, init: np.ndarray | None = None) -> torch.Tensor:
    """The backend's flow on the images as given (no resampling); ``grey``: their :func:`gray_u8`;
    ``init``: (H, W, 2) start of the flow at their size, or None."""
    flow = BACKENDS[name](image_cur.float(), image_prev.float(), cfg, grey, init)
    check_finite_fast(flow, f"flow from backend {name}")
    return flow
