"""Optical flow backends (config group ``flow``): one interface, covariance from one place.

Backends (``cfg.name``):

- ``gt``: the data source's ground-truth flow (``pair.gt.flow``), covariance ``sigma^2 I``;
  pixels without ground truth get flow 0 and the covariance ceiling ``sigma_max^2 I``.
- ``deepflow``: DeepFlow (Weinzaepfel et al. 2013), the paper's choice: OpenCV contrib's
  variational DeepFlow, guided by dense patch matches for large displacements
  (``cfg.matches: dis|none``, see :func:`_deepflow`).
- ``dis``: OpenCV DIS flow (Kroeger et al. 2016), fast; ``cfg.preset`` ultrafast|fast|medium.
- ``raft``: torchvision RAFT (small/large) with weights from a local file (``cfg.weights``),
  run in torch or through ONNX Runtime (``cfg.runtime: torch|onnx``, file ``cfg.onnx``; ``auto``: ONNX
  Runtime on a CPU, the INT8 copy beside the weights where ``cfg.precision: int8``).

Settings: one dataclass per backend (:mod:`monostixels.inputs.flow_config`), the schemas of the group's
options; a config node or dict is read through them.

Convention: every backend returns the flow from the *current* to the *previous* image,
``x_prev = x + f(x)`` (docs/conventions.md, section 2), in pixels; OpenCV backends are called as
``calc(current, previous)``. The covariance comes from
:func:`monostixels.inputs.confidence.flow_covariance` (``cfg.confidence``), optionally with
forward-backward consistency (``cfg.fb_consistency: true`` runs the backend both ways).

Resolution (``cfg.scale``, image backends) and refinement (``cfg.refine``): the dense estimate
may run on the images downscaled by ``scale`` in (0, 1] (area averaging); its flow is upsampled
bilinearly to the input size and its vectors multiplied by the size ratio. DeepFlow guided by DIS
matches keeps the matches at full resolution (cheap, and what follows large displacements) and
runs only its variational stage, the expensive part, at ``scale``. ``refine: true`` then polishes
the full-size flow with a variational refinement at full resolution (OpenCV's
``VariationalRefinement``, the energy DIS uses; ``refine_passes`` times, each warping again by the
last pass's flow), which restores the sub-pixel accuracy the
downscaled stage gives away. The covariance is computed on the grid of the last stage: the
full-size image after a refinement or at ``scale = 1``, else the downscaled image (its
``window_sigma`` in pixels of that grid, ``sigma``/``sigma_min``/``sigma_max`` in full-size
pixels), mapped to full-size pixels^2. Measured choices: docs/experiments.md, "Pipeline speed".
"""
from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from concurrent.futures import wait
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Sequence

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from monostixels._pools import helper_pool
from monostixels._checks import InputError, check_finite, check_finite_fast, check_image_pair, check_same_size, check_shape
from monostixels._paths import find_file
from monostixels.data.base import FramePair
from monostixels.inputs.confidence import ConfidenceParams, fb_consistency_error, flow_covariance
from monostixels.inputs.flow_config import (DeepFlowConfig, DisFlowConfig, ImageFlowConfig, RaftFlowConfig, flow_name,
                                            flow_params)
from monostixels.core.grey import to_gray_u8

__all__ = [
    "FLOW_BACKENDS",
    "KITTI_OUTLIER_PX",
    "KITTI_OUTLIER_REL",
    "FlowResult",
    "estimate_flow",
    "chained_flow",
    "compose_flows",
    "compute_flow",
    "confidence_params",
    "flow_scale",
    "resolve_path",
    "flow_metrics",
]

logger = logging.getLogger(__name__)

FLOW_BACKENDS = ("gt", "deepflow", "dis", "raft")
#: KITTI 2015 flow outlier rule: end-point error above 3 px *and* above 5 % of the true flow length.
KITTI_OUTLIER_PX = 3.0
KITTI_OUTLIER_REL = 0.05

_DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


@dataclass
class FlowResult:
    """Flow of a frame pair with its per-pixel covariance.

    Attributes:
        flow: (2, H, W) float32, current -> previous, pixels (``x_prev = x + flow``).
        cov: (H, W, 2, 2) float32 covariance of the flow, pixels^2 (positive definite).
        seconds: wall time of the estimate (flow and covariance), seconds.
        backend: the backend name (``cfg.name``).
        grey: (H, W) uint8 grey of the current image where the backend made one (OpenCV backends at
            full size), else None: a stream keeps it for the pair whose previous image it becomes.
    """

    flow: torch.Tensor
    cov: torch.Tensor
    seconds: float
    backend: str
    grey: np.ndarray | None = None
    #: (2, H, W) flow previous -> current, where the forward-backward check computed it.
    backward: torch.Tensor | None = None
    #: A chained keyframe pair (:func:`chained_flow`): the flows (forward, backward or None) between the
    #: current frame and the stream's last frame, which the stream keeps for the next chains.
    step: tuple[torch.Tensor, torch.Tensor | None] | None = None
    #: Frames the flow was chained through (1 = computed on the pair directly).
    chained: int = 1


def confidence_params(cfg: Any) -> ConfidenceParams:
    """The :class:`ConfidenceParams` of a ``flow`` config node, dict or settings dataclass
    (:mod:`monostixels.inputs.flow_config`)."""
    p = flow_params(cfg)
    return ConfidenceParams(
        method=p.confidence, sigma=p.sigma, noise=p.noise, window_sigma=p.window_sigma,
        sigma_min=min(ConfidenceParams.sigma_min, p.sigma) if p.sigma_min is None else p.sigma_min,
        sigma_max=p.sigma_max, fb_weight=getattr(p, "fb_weight", ConfidenceParams.fb_weight),
    )


def flow_scale(cfg: Any) -> float:
    """``cfg.scale`` (1 for ``gt``): the factor the images are downscaled by before an image backend runs.

    Raises:
        InputError: not a number in (0, 1].
    """
    scale = getattr(flow_params(cfg), "scale", 1.0)
    if not (math.isfinite(scale) and 0.0 < scale <= 1.0):
        raise InputError(f"flow.scale: must be in (0, 1] (1 = full resolution), got {scale}")
    return scale


#: Smallest image side (px) an image backend is run at (DIS patches are 8 px, its pyramid needs more).
_MIN_SCALED_SIDE = 16


def _scaled_size(H: int, W: int, scale: float) -> tuple[int, int]:
    """(h, w) of an (H, W) image downscaled by ``scale``; an error if a side falls below 16 px."""
    h, w = max(1, round(H * scale)), max(1, round(W * scale))
    if min(h, w) < _MIN_SCALED_SIDE:
        raise InputError(f"flow.scale: {scale} turns the {W}x{H} images into {w}x{h}; "
                         f"each side must stay >= {_MIN_SCALED_SIDE} px (raise flow.scale)")
    return h, w


def _downscale(image: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """(C, H, W) float image resampled to ``size`` = (h, w) by area averaging (OpenCV INTER_AREA)."""
    h, w = size
    arr = np.ascontiguousarray(image.float().permute(1, 2, 0).numpy())
    small = cv2.resize(arr, (w, h), interpolation=cv2.INTER_AREA)
    if small.ndim == 2:
        small = small[..., None]
    return torch.from_numpy(np.ascontiguousarray(small.transpose(2, 0, 1)))


def _upsample_flow(flow: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Flow (2, h, w) in pixels of its grid -> (2, H, W) in pixels of the ``size`` = (H, W) grid.

    Convention: pixel centres map as ``u_full = (u + 0.5) W / w - 0.5`` (``align_corners=False``),
    so a displacement of ``du`` grid pixels is ``du W / w`` full-size pixels (and ``dv H / h``).
    """
    H, W = size
    h, w = flow.shape[-2:]
    up = F.interpolate(flow[None].float(), size=(H, W), mode="bilinear", align_corners=False)[0]
    return up * torch.tensor([W / w, H / h], dtype=torch.float32).view(2, 1, 1)


def _upsample_cov(cov: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Covariance (h, w, 2, 2) in grid pixels^2 -> (H, W, 2, 2) in full-size pixels^2: ``D C D``
    with ``D = diag(W / w, H / h)``, interpolated bilinearly (a convex combination of symmetric
    positive definite matrices stays positive definite, within the same eigenvalue bounds)."""
    H, W = size
    h, w = cov.shape[:2]
    d = torch.tensor([W / w, H / h], dtype=torch.float32)
    scaled = cov.float() * (d[:, None] * d[None, :])
    flat = scaled.reshape(h, w, 4).permute(2, 0, 1)[None]  # 1 x 4 x h x w
    up = F.interpolate(flat, size=(H, W), mode="bilinear", align_corners=False)[0]
    return up.permute(1, 2, 0).reshape(H, W, 2, 2).contiguous()


def resolve_path(path: str | Path) -> Path:
    """A file path from the config (:func:`monostixels._paths.find_file`: absolute, relative to the
    working directory, a shipped model ``models/...``, the repository root); as given if none exists."""
    found = find_file(path)
    return found if found is not None else Path(path).expanduser()


def _gray_u8(image: torch.Tensor) -> np.ndarray:
    """(3, H, W) float32 RGB in [0, 1] -> (H, W) uint8 grey (OpenCV flow backends work on 8-bit grey)."""
    # Quantised in numpy rather than with torch ops (the same values): no thread hand-offs beside the
    # other threads of the flow stage.
    x = np.clip(image.detach().numpy(), 0.0, 1.0)
    return to_gray_u8((x * 255.0 + 0.5).astype(np.uint8))


@lru_cache(maxsize=4)
def _pixel_grid(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates ``(u, v)`` (h, w) float32 of an (h, w) grid, read-only (shared between calls)."""
    xx, yy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    xx.flags.writeable = yy.flags.writeable = False
    return xx, yy


def _remap(img: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """``img`` sampled at ``x + flow(x)`` (bilinear, border replicated); flow (H, W, 2) pixels."""
    xx, yy = _pixel_grid(*flow.shape[:2])
    return cv2.remap(img, xx + flow[..., 0], yy + flow[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _at_scale(calc: Callable[[np.ndarray, np.ndarray], np.ndarray], a: np.ndarray, b: np.ndarray,
              scale: float) -> np.ndarray:
    """``calc(a, b)`` (an (h, w, 2) flow of two grey images) run at ``scale``, returned at full size, full-size pixels."""
    if scale == 1.0:
        return calc(a, b)
    H, W = a.shape
    h, w = _scaled_size(H, W, scale)
    small = calc(cv2.resize(a, (w, h), interpolation=cv2.INTER_AREA), cv2.resize(b, (w, h), interpolation=cv2.INTER_AREA))
    return _upsample_flow(torch.from_numpy(np.ascontiguousarray(small.transpose(2, 0, 1))), (H, W)).permute(1, 2, 0).numpy()


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
    if min(c1 - c0 for c0, c1 in zip(cuts[:-1], cuts[1:])) < 2 * m + _MIN_SCALED_SIDE:
        raise InputError(f"flow.bands: {bands} strips of a {w} px wide grid are too narrow "
                         f"(each needs >= {2 * m + _MIN_SCALED_SIDE} px); lower flow.bands")
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
    the images' :func:`_gray_u8`, when the caller has them; ``init``: (H, W, 2) start of the DIS
    matches (:func:`_dis_calc`).
    """
    if not hasattr(cv2, "optflow"):
        raise InputError(f"flow=deepflow: this OpenCV ({cv2.__version__}) has no cv2.optflow; DeepFlow is in "
                         "opencv-contrib-python-headless (install it instead of the plain OpenCV wheel)")
    a, b = grey if grey is not None else (_gray_u8(cur), _gray_u8(prev))
    scale = flow_scale(cfg)
    bands = _bands(cfg)

    def variational(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return _in_bands(lambda p, q: cv2.optflow.createOptFlow_DeepFlow().calc(p, q, None), x, y, bands)

    matches = cfg.matches
    if matches == "none":
        f = _at_scale(variational, a, b, scale)
    elif matches == "dis":
        f0 = _dis_calc(_DIS_PRESETS[cfg.matches_preset], a, b, init)
        r = np.ascontiguousarray(_at_scale(variational, a, _remap(b, f0), scale))
        f = r + _remap(f0, r)
    else:
        raise InputError(f"flow.matches: must be 'dis' or 'none', got {matches!r}")
    return torch.from_numpy(np.ascontiguousarray(f.transpose(2, 0, 1))).float()


def _refine(grey: tuple[np.ndarray, np.ndarray], flow: torch.Tensor, passes: int = 1) -> torch.Tensor:
    """Full-resolution variational refinement of ``flow`` (2, H, W) on the (current, previous) grey
    images (:func:`_gray_u8`), ``passes`` times (OpenCV ``VariationalRefinement`` with its defaults:
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
    a, b = grey if grey is not None else (_gray_u8(cur), _gray_u8(prev))
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


def _raft_both_ways(image_cur: torch.Tensor, image_prev: torch.Tensor, cfg: RaftFlowConfig, grey_prev: np.ndarray | None = None
                    ) -> tuple[torch.Tensor, torch.Tensor, np.ndarray | None]:
    """RAFT's flows current -> previous and previous -> current as one batch, at ``cfg.scale`` and refined
    as :func:`compute_flow` does each (the forward-backward check without twice the network's time).
    Returns both flows and, where the refinement made it, the full-size grey of ``image_cur`` (as
    :func:`_flow_of_checked_images`; ``grey_prev`` is the caller's grey of ``image_prev``, or None)."""
    net = _raft_net(cfg)
    scale = flow_scale(cfg)
    H, W = image_cur.shape[-2:]
    if scale == 1.0:
        fwd, bwd = net.both_ways(image_cur.float(), image_prev.float())
    else:
        size = _scaled_size(H, W, scale)
        fwd, bwd = net.both_ways(_downscale(image_cur, size), _downscale(image_prev, size))
        fwd, bwd = _upsample_flow(fwd, (H, W)), _upsample_flow(bwd, (H, W))
    for f in (fwd, bwd):
        check_finite_fast(f, "flow from backend raft")
    if not cfg.refine:
        return fwd, bwd, None
    g_cur = _gray_u8(image_cur.float())
    g_prev = grey_prev if grey_prev is not None else _gray_u8(image_prev.float())
    passes = _refine_passes(cfg)
    # The two directions in two threads: OpenCV's refinement leaves most of a second core idle (and
    # releases the GIL); on two cores this halves its time.
    back = helper_pool("refine-backward").submit(_refine, (g_prev, g_cur), bwd, passes)
    fwd, bwd = _refine((g_cur, g_prev), fwd, passes), back.result()
    for f in (fwd, bwd):
        check_finite_fast(f, "flow from backend raft after flow.refine")
    return fwd, bwd, g_cur


#: Image backends: (current, previous, cfg, grey images or None, start flow or None) -> flow (2, H, W).
_BACKENDS: dict[str, Callable[..., torch.Tensor]] = {
    "deepflow": _deepflow,
    "dis": _dis,
    "raft": _raft,
}


def _backend(name: str, image_cur: torch.Tensor, image_prev: torch.Tensor, cfg: ImageFlowConfig,
             grey: tuple[np.ndarray, np.ndarray] | None = None, init: np.ndarray | None = None) -> torch.Tensor:
    """The backend's flow on the images as given (no resampling); ``grey``: their :func:`_gray_u8`;
    ``init``: (H, W, 2) start of the flow at their size, or None."""
    flow = _BACKENDS[name](image_cur.float(), image_prev.float(), cfg, grey, init)
    check_finite_fast(flow, f"flow from backend {name}")
    return flow


#: Backends that run on the 8-bit grey images (:func:`_gray_u8`).
_GREY_BACKENDS = frozenset({"deepflow", "dis"})


#: Backends that apply ``cfg.scale`` themselves (DeepFlow keeps its matches at full resolution).
_OWN_SCALE = frozenset({"deepflow"})


def compute_flow(image_cur: torch.Tensor, image_prev: torch.Tensor, cfg: Any) -> torch.Tensor:
    """Flow (2, H, W) float32 from ``image_cur`` to ``image_prev`` ((3, H, W) RGB in [0, 1]) with
    the image backend ``cfg.name`` (deepflow | dis | raft), no covariance.

    With ``cfg.scale < 1`` the backend runs on the downscaled images and the flow is upsampled to
    (H, W), in full-size pixels; ``cfg.refine`` then refines it at full size (module docstring).
    """
    name = flow_name(cfg)
    if name not in _BACKENDS:
        raise InputError(f"flow.name: image-based backend must be one of {tuple(_BACKENDS)}, got {name!r}")
    cfg = _image_params(cfg)
    check_image_pair(image_cur, image_prev)
    return _flow_of_checked_images(image_cur, image_prev, cfg)[0]


def _image_params(cfg: Any) -> ImageFlowConfig:
    """The settings of an image backend, their values checked before any image is touched."""
    cfg = flow_params(cfg)
    flow_scale(cfg)
    _refine_passes(cfg)
    return cfg


def _uses_grey(cfg: ImageFlowConfig) -> bool:
    """Whether the flow of ``cfg`` reads the full-size grey images (the refinement, or a grey backend at
    full size)."""
    full_size = cfg.scale == 1.0 or cfg.name in _OWN_SCALE
    return cfg.refine or (full_size and cfg.name in _GREY_BACKENDS)


def _flow_of_checked_images(image_cur: torch.Tensor, image_prev: torch.Tensor, cfg: ImageFlowConfig, init: np.ndarray | None = None,
                            grey_prev: np.ndarray | None = None, grey_cur: np.ndarray | None = None
                            ) -> tuple[torch.Tensor, np.ndarray | None]:
    """:func:`compute_flow` on images that passed :func:`monostixels._checks.check_image_pair`, backend name known.

    ``init``: (H, W, 2) start of the flow (full-size pixels), or None; ``grey_prev``, ``grey_cur``: the
    :func:`_gray_u8` of ``image_prev`` / ``image_cur`` where the caller has them. Returns the flow and
    the full-size grey of ``image_cur`` where one was made or given (else None).
    """
    name, scale, refine = cfg.name, cfg.scale, cfg.refine
    full_size = scale == 1.0 or name in _OWN_SCALE
    # The full-size grey images once, for the backend and the refinement alike.
    grey = None
    if _uses_grey(cfg):
        grey = (grey_cur if grey_cur is not None else _gray_u8(image_cur.float()),
                grey_prev if grey_prev is not None else _gray_u8(image_prev.float()))
    if full_size:
        flow = _backend(name, image_cur, image_prev, cfg, grey, init)
    else:
        H, W = image_cur.shape[-2:]
        size = _scaled_size(H, W, scale)
        small_init = None
        if init is not None:  # to the grid and pixels of the downscaled images
            small_init = cv2.resize(init, (size[1], size[0]), interpolation=cv2.INTER_AREA) * np.float32(
                [size[1] / W, size[0] / H])
        flow = _upsample_flow(_backend(name, _downscale(image_cur, size), _downscale(image_prev, size), cfg,
                                       None, small_init), (H, W))
    if refine:
        flow = _refine(grey, flow, _refine_passes(cfg))
        check_finite_fast(flow, f"flow from backend {name} after flow.refine")
    return flow, (grey[0] if grey is not None else None)


def _refine_passes(cfg: ImageFlowConfig) -> int:
    """``cfg.refine_passes``: how many times :func:`_refine` runs where ``refine`` is on."""
    val = cfg.refine_passes
    if isinstance(val, bool) or not isinstance(val, int) or val < 1:
        raise InputError(f"flow.refine_passes: must be an integer >= 1, got {val!r}")
    return val


def _both_ways(pair: FramePair, cfg: ImageFlowConfig, init: np.ndarray | None = None, grey_prev: np.ndarray | None = None
               ) -> tuple[torch.Tensor, torch.Tensor, np.ndarray | None]:
    """An image backend's flows current -> previous and previous -> current (images checked), and the
    current grey image where one was made (else None)."""
    if cfg.name == "raft":
        flow, back, grey = _raft_both_ways(pair.image, pair.image_prev, cfg, grey_prev)  # RAFT starts from zero
    else:
        # Both greys once, for the two directions (each is the other's previous image).
        g_cur = g_prev = None
        if _uses_grey(cfg):
            g_cur = _gray_u8(pair.image.float())
            g_prev = grey_prev if grey_prev is not None else _gray_u8(pair.image_prev.float())
        # The two directions in two threads: the OpenCV backends release the GIL and DeepFlow's
        # variational stage (bands=1) and the refinement use about one core each. The backward
        # flow starts from zero: the carried flow is a forward one.
        back_job = helper_pool("flow-backward").submit(_flow_of_checked_images, pair.image_prev, pair.image, cfg,
                                                       None, g_cur, g_prev)
        flow, grey = _flow_of_checked_images(pair.image, pair.image_prev, cfg, init, g_prev, g_cur)
        back, _ = back_job.result()
    return flow, back, grey


def _image_flow(pair: FramePair, cfg: ImageFlowConfig, params: ConfidenceParams, init: np.ndarray | None = None,
                grey_prev: np.ndarray | None = None
                ) -> tuple[torch.Tensor, torch.Tensor, np.ndarray | None, torch.Tensor | None]:
    """Flow, covariance, current grey image (or None) and backward flow (where the forward-backward check
    computed one, else None) of an image backend; the covariance on the grid of the last stage (module
    docstring). ``init``, ``grey_prev``: see :func:`estimate_flow`.

    Without the forward-backward check the covariance depends on the image only: it is computed
    in a second thread while the backend runs (the same numbers; a core DeepFlow leaves idle).
    """
    check_image_pair(pair.image, pair.image_prev)
    if init is not None:
        check_shape(torch.from_numpy(init), [*pair.size, 2], "flow init (H, W, 2)")
    if grey_prev is not None and grey_prev.shape != tuple(pair.size):
        raise InputError(f"flow: grey_prev of shape {grey_prev.shape} for images of size {tuple(pair.size)}")
    if cfg.fb_consistency:
        flow, back, grey = _both_ways(pair, cfg, init, grey_prev)
        return flow, _covariance(pair.image, cfg, params, fb_consistency_error(flow, back)), grey, back
    cov = helper_pool("covariance").submit(_covariance, pair.image, cfg, params, None)
    try:
        flow, grey = _flow_of_checked_images(pair.image, pair.image_prev, cfg, init, grey_prev)
    finally:
        wait([cov])  # the covariance's thread is done before this pair goes on (or fails)
    return flow, cov.result(), grey, None


def _covariance(image: torch.Tensor, cfg: ImageFlowConfig, params: ConfidenceParams, fb_err: torch.Tensor | None) -> torch.Tensor:
    """The flow covariance (H, W, 2, 2) of :func:`_image_flow`: full-size, or on the grid of a
    downscaled backend without refinement (floor and ceiling converted from full-size to grid
    pixels; the structure tensor of the downscaled image, whose finest texture no longer pins the flow)."""
    scale = cfg.scale
    if scale == 1.0 or cfg.refine:
        return flow_covariance(image, params, fb_error=fb_err)
    H, W = image.shape[-2:]
    size = _scaled_size(H, W, scale)
    s = math.sqrt((size[0] / H) * (size[1] / W))
    grid_params = dataclasses.replace(params, sigma=params.sigma * s, sigma_min=params.sigma_min * s,
                                      sigma_max=params.sigma_max * s)
    fb_grid = None
    if fb_err is not None:  # nearest sampling keeps inf (unchecked); pixels -> grid pixels
        fb_grid = torch.from_numpy(cv2.resize(fb_err.numpy(), (size[1], size[0]), interpolation=cv2.INTER_NEAREST)) * s
    cov = flow_covariance(_downscale(image, size), grid_params, fb_error=fb_grid)
    return _upsample_cov(cov, (H, W))


def _gt_flow(pair: FramePair, params: ConfidenceParams) -> tuple[torch.Tensor, torch.Tensor]:
    source = pair.meta.get("source", pair.name or "this data source")
    flow = pair.gt.flow
    if flow is None:
        raise InputError(f"flow=gt: {source} has no ground-truth flow (pair.gt.flow is None); choose flow=deepflow|dis|raft")
    check_shape(flow, [2, "H", "W"], f"{source}: gt.flow")
    check_same_size(flow, pair.image, "gt.flow", "image")
    # The oracle is the true motion field wherever the source knows it (a renderer knows it at
    # occluded pixels too); ``gt.flow_valid`` (visible in both frames) is for scoring flow, not
    # for hiding motion. Pixels without a value (NaN, e.g. KITTI gaps) get flow 0 with the
    # covariance ceiling, so they carry no information.
    known = torch.isfinite(flow).all(0)
    if not bool(known.any()):
        raise InputError(f"flow=gt: {source}: gt.flow has no finite value")
    flow = torch.where(known[None], flow.float(), torch.zeros((), dtype=torch.float32))
    cov = flow_covariance(pair.image, params)
    ceiling = (params.sigma_max**2) * torch.eye(2)
    cov = torch.where(known[..., None, None], cov, ceiling)
    return flow, cov


def estimate_flow(pair: FramePair, cfg: Any, *, init: np.ndarray | None = None,
                  grey_prev: np.ndarray | None = None) -> FlowResult:
    """Flow current -> previous and its covariance for a frame pair.

    Args:
        pair: the frame pair (images (3, H, W) RGB in [0, 1]).
        cfg: the ``flow`` config group node (or a dict, or the settings dataclass): ``name`` in
            gt|deepflow|dis|raft and that backend's settings (:mod:`monostixels.inputs.flow_config`: the
            covariance, the resolution the backend runs at and the refinement at full size, the backend's own);
            keys not given take the defaults of the option named after the backend (``flow=deepflow``...).
        init: (H, W, 2) float32 start of the flow (pixels, current -> previous), e.g. a stream's last
            flow (:mod:`monostixels.sequence.stream`); taken by the backends with a DIS stage (``dis``, and
            ``deepflow``'s DIS matches), ignored by ``raft`` and ``gt``. None = start from zero.
        grey_prev: (H, W) uint8 grey of ``pair.image_prev`` (``FlowResult.grey`` of the pair it was the
            current image of), or None: converted here. The same values either way.

    Returns:
        A :class:`FlowResult`: flow (2, H, W) pixels, covariance (H, W, 2, 2) pixels^2.

    Raises:
        InputError: unknown backend, missing ground truth / weights, bad image shapes, NaN flow,
            ``scale`` outside (0, 1].
    """
    name = flow_name(cfg)
    if name not in FLOW_BACKENDS:
        raise InputError(f"flow.name: unknown flow backend {name!r}, expected one of {FLOW_BACKENDS}")
    cfg = flow_params(cfg) if name == "gt" else _image_params(cfg)
    params = confidence_params(cfg)
    t0 = time.perf_counter()
    grey = back = None
    if name == "gt":
        flow, cov = _gt_flow(pair, params)
    else:
        flow, cov, grey, back = _image_flow(pair, cfg, params, init, grey_prev)
    seconds = time.perf_counter() - t0
    logger.debug("flow %s on %s: %.2f s", name, pair.name, seconds)
    return FlowResult(flow=flow.contiguous(), cov=cov.contiguous(), seconds=seconds, backend=name, grey=grey,
                      backward=back)


def compose_flows(first: np.ndarray, then: np.ndarray) -> np.ndarray:
    """The flow of two flows one after the other: ``x -> x + a(x)`` (``first``), then ``y -> y + b(y)``
    (``then``), i.e. ``a(x) + b(x + a(x))`` (bilinear, border replicated); (H, W, 2) float32 pixels."""
    return first + _remap(then, first)


def chained_flow(pair: FramePair, cfg: Any, last_image: torch.Tensor, steps: Sequence[tuple[np.ndarray, np.ndarray | None]],
                 *, last_grey: np.ndarray | None = None, prev_grey: np.ndarray | None = None) -> FlowResult:
    """Flow of a keyframe pair reaching several frames back, chained through the frames between.

    The paper pairs frames a driven distance apart (0.5 m). Over two or more frame intervals the
    displacements double or more, and a variational flow gets the near road and the movers wrong more
    often than it gets them twice as large. So the flow is composed: the flow from the current frame to
    the stream's last frame ``L`` (computed here, both ways where ``cfg.fb_consistency``), then the kept flows
    ``L -> ... -> k`` of the frames between; the sum is refined on the pair's own images (``refine_passes``
    passes, at least one: the composition blurs and accumulates the frames' errors; the pair's images
    have the last word), and its covariance comes from the chained forward-backward check at full size.

    Args:
        pair: the keyframe pair (current frame ``t``, earlier frame ``k``); images (3, H, W) RGB in [0, 1].
        cfg: the ``flow`` group (an image backend).
        last_image: (3, H, W) image of the stream's last frame ``L`` (``k < L < t``).
        steps: the kept flows of the frames from ``L`` back to ``k``, newest first: ``steps[i]`` = (flow
            from frame ``i`` to the frame before it, flow back or None), (H, W, 2) float32 pixels.
        last_grey: (H, W) uint8 grey of ``last_image``, or None.
        prev_grey: (H, W) uint8 grey of ``pair.image_prev`` (kept by the stream), or None: converted here.

    Returns:
        The pair's :class:`FlowResult` (``chained`` frames, ``step`` = this frame's flows to ``L``).
    """
    name = flow_name(cfg)
    if name not in _BACKENDS:
        raise InputError(f"flow.name: chained keyframe flow needs an image backend {tuple(_BACKENDS)}, got {name!r}")
    cfg = _image_params(cfg)
    if not steps:
        raise InputError("chained flow: no kept flows between the stream's last frame and the pair's earlier frame")
    t0 = time.perf_counter()
    params = confidence_params(cfg)
    fb = cfg.fb_consistency
    check_image_pair(pair.image, pair.image_prev)
    check_image_pair(pair.image, last_image)
    step_pair = dataclasses.replace(pair, image_prev=last_image)
    if fb:
        f_tl, b_tl, grey = _both_ways(step_pair, cfg, None, last_grey)
    else:
        (f_tl, grey), b_tl = _flow_of_checked_images(pair.image, last_image, cfg, None, last_grey), None
    fwd = f_tl.permute(1, 2, 0).numpy()
    for f, _ in steps:
        fwd = compose_flows(fwd, f)
    bwd = None
    if fb:
        if any(b is None for _, b in steps) or b_tl is None:
            raise InputError("chained flow: flow.fb_consistency needs the kept backward flows of the frames between")
        bwd = steps[-1][1]
        for _, b in reversed(steps[:-1]):
            bwd = compose_flows(bwd, b)
        bwd = compose_flows(bwd, np.ascontiguousarray(b_tl.permute(1, 2, 0).numpy()))
    g_cur = grey if grey is not None else _gray_u8(pair.image.float())
    g_prev = prev_grey if prev_grey is not None else _gray_u8(pair.image_prev.float())
    passes = _refine_passes(cfg)

    def chw(x: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1)))

    back_job = helper_pool("refine-backward").submit(_refine, (g_prev, g_cur), chw(bwd), passes) \
        if bwd is not None else None
    flow = _refine((g_cur, g_prev), chw(fwd), passes)
    back = back_job.result() if back_job is not None else None
    check_finite_fast(flow, f"chained flow from backend {name}")
    cov = flow_covariance(pair.image, params, fb_error=fb_consistency_error(flow, back) if back is not None else None)
    seconds = time.perf_counter() - t0
    logger.debug("flow %s on %s chained through %d frames: %.2f s", name, pair.name, len(steps) + 1, seconds)
    return FlowResult(flow=flow.contiguous(), cov=cov.contiguous(), seconds=seconds, backend=name, grey=g_cur,
                      backward=back, step=(f_tl, b_tl), chained=len(steps) + 1)


def flow_metrics(flow: torch.Tensor, gt_flow: torch.Tensor, valid: torch.Tensor | None = None) -> dict[str, float]:
    """End-point error and KITTI Fl-all of a flow against ground truth.

    Args:
        flow: (2, H, W) estimated flow, pixels.
        gt_flow: (2, H, W) ground-truth flow, pixels (same direction convention).
        valid: (H, W) bool pixels with ground truth (default: where ``gt_flow`` is finite).

    Returns:
        ``{"epe": mean end-point error (px), "fl_all": fraction of valid pixels whose error is
        > 3 px and > 5 % of the true flow length}``; NaN for both when no pixel is valid.
    """
    check_shape(flow, [2, "H", "W"], "flow")
    check_shape(gt_flow, [2, "H", "W"], "gt_flow")
    check_same_size(flow, gt_flow, "flow", "gt_flow")
    ok = torch.isfinite(gt_flow).all(0)
    if valid is not None:
        check_shape(valid, list(flow.shape[-2:]), "valid")
        ok = ok & valid.bool()
    check_finite(flow[:, ok], "flow (at valid pixels)")
    if not bool(ok.any()):
        return {"epe": math.nan, "fl_all": math.nan}
    err = (flow[:, ok].double() - gt_flow[:, ok].double()).norm(dim=0)
    mag = gt_flow[:, ok].double().norm(dim=0)
    outlier = (err > KITTI_OUTLIER_PX) & (err > KITTI_OUTLIER_REL * mag)
    return {"epe": float(err.mean()), "fl_all": float(outlier.double().mean())}
