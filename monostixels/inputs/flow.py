"""Optical flow (config group ``flow``): one interface, covariance from one place.

Backends (``cfg.name``):

- ``gt``: the data source's ground-truth flow (``pair.gt.flow``), covariance ``sigma^2 I``;
  pixels without ground truth get flow 0 and the covariance ceiling ``sigma_max^2 I``.
- ``deepflow``, ``dis``, ``raft``: the image backends (:mod:`monostixels.inputs.flow_backends`, with the
  refinement); the resampling to and from ``cfg.scale``: :mod:`monostixels.inputs.flow_resample`; the
  chained flow of a keyframe pair: :mod:`monostixels.inputs.flow_chain`.

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
import time
from concurrent.futures import wait
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import torch

from monostixels._pools import helper_pool
from monostixels._checks import InputError, check_finite, check_finite_fast, check_image_pair, check_same_size, check_shape
from monostixels.data.base import FramePair
from monostixels.inputs.confidence import ConfidenceParams, fb_consistency_error, flow_covariance
from monostixels.inputs.flow_backends import BACKENDS, gray_u8, raft_both_ways, refine_flow, refine_passes, run_backend
from monostixels.inputs.flow_config import ImageFlowConfig, flow_name, flow_params
from monostixels.inputs.flow_resample import downscale, flow_scale, scaled_size, upsample_cov, upsample_flow


__all__ = [
    "FLOW_BACKENDS",
    "KITTI_OUTLIER_PX",
    "KITTI_OUTLIER_REL",
    "FlowResult",
    "estimate_flow",
    "compute_flow",
    "confidence_params",
    "flow_metrics",
]


logger = logging.getLogger(__name__)


FLOW_BACKENDS = ("gt", "deepflow", "dis", "raft")


#: KITTI 2015 flow outlier rule: end-point error above 3 px *and* above 5 % of the true flow length.
KITTI_OUTLIER_PX = 3.0


KITTI_OUTLIER_REL = 0.05


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


#: Backends that run on the 8-bit grey images (:func:`gray_u8`).
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
    if name not in BACKENDS:
        raise InputError(f"flow.name: image-based backend must be one of {tuple(BACKENDS)}, got {name!r}")
    cfg = image_params(cfg)
    check_image_pair(image_cur, image_prev)
    return flow_of_checked_images(image_cur, image_prev, cfg)[0]


def image_params(cfg: Any) -> ImageFlowConfig:
    """The settings of an image backend, their values checked before any image is touched."""
    cfg = flow_params(cfg)
    flow_scale(cfg)
    refine_passes(cfg)
    return cfg


def _uses_grey(cfg: ImageFlowConfig) -> bool:
    """Whether the flow of ``cfg`` reads the full-size grey images (the refinement, or a grey backend at
    full size)."""
    full_size = cfg.scale == 1.0 or cfg.name in _OWN_SCALE
    return cfg.refine or (full_size and cfg.name in _GREY_BACKENDS)


def flow_of_checked_images(image_cur: torch.Tensor, image_prev: torch.Tensor, cfg: ImageFlowConfig, init: np.ndarray | None = None,
                            grey_prev: np.ndarray | None = None, grey_cur: np.ndarray | None = None
                            ) -> tuple[torch.Tensor, np.ndarray | None]:
    """:func:`compute_flow` on images that passed :func:`monostixels._checks.check_image_pair`, backend name known.

    ``init``: (H, W, 2) start of the flow (full-size pixels), or None; ``grey_prev``, ``grey_cur``: the
    :func:`gray_u8` of ``image_prev`` / ``image_cur`` where the caller has them. Returns the flow and
    the full-size grey of ``image_cur`` where one was made or given (else None).
    """
    name, scale, refine = cfg.name, cfg.scale, cfg.refine
    full_size = scale == 1.0 or name in _OWN_SCALE
    # The full-size grey images once, for the backend and the refinement alike.
    grey = None
    if _uses_grey(cfg):
        grey = (grey_cur if grey_cur is not None else gray_u8(image_cur.float()),
                grey_prev if grey_prev is not None else gray_u8(image_prev.float()))
    if full_size:
        flow = run_backend(name, image_cur, image_prev, cfg, grey, init)
    else:
        H, W = image_cur.shape[-2:]
        size = scaled_size(H, W, scale)
        small_init = None
        if init is not None:  # to the grid and pixels of the downscaled images
            small_init = cv2.resize(init, (size[1], size[0]), interpolation=cv2.INTER_AREA) * np.float32(
                [size[1] / W, size[0] / H])
        flow = upsample_flow(run_backend(name, downscale(image_cur, size), downscale(image_prev, size), cfg,
                                       None, small_init), (H, W))
    if refine:
        flow = refine_flow(grey, flow, refine_passes(cfg))
        check_finite_fast(flow, f"flow from backend {name} after flow.refine")
    return flow, (grey[0] if grey is not None else None)


def both_ways(pair: FramePair, cfg: ImageFlowConfig, init: np.ndarray | None = None, grey_prev: np.ndarray | None = None
               ) -> tuple[torch.Tensor, torch.Tensor, np.ndarray | None]:
    """An image backend's flows current -> previous and previous -> current (images checked), and the
    current grey image where one was made (else None)."""
    if cfg.name == "raft":
        flow, back, grey = raft_both_ways(pair.image, pair.image_prev, cfg, grey_prev)  # RAFT starts from zero
    else:
        # Both greys once, for the two directions (each is the other's previous image).
        g_cur = g_prev = None
        if _uses_grey(cfg):
            g_cur = gray_u8(pair.image.float())
            g_prev = grey_prev if grey_prev is not None else gray_u8(pair.image_prev.float())
        # The two directions in two threads: the OpenCV backends release the GIL and DeepFlow's
        # variational stage (bands=1) and the refinement use about one core each. The backward
        # flow starts from zero: the carried flow is a forward one.
        back_job = helper_pool("flow-backward").submit(flow_of_checked_images, pair.image_prev, pair.image, cfg,
                                                       None, g_cur, g_prev)
        flow, grey = flow_of_checked_images(pair.image, pair.image_prev, cfg, init, g_prev, g_cur)
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
        flow, back, grey = both_ways(pair, cfg, init, grey_prev)
        return flow, _covariance(pair.image, cfg, params, fb_consistency_error(flow, back)), grey, back
    cov = helper_pool("covariance").submit(_covariance, pair.image, cfg, params, None)
    try:
        flow, grey = flow_of_checked_images(pair.image, pair.image_prev, cfg, init, grey_prev)
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
    size = scaled_size(H, W, scale)
    s = math.sqrt((size[0] / H) * (size[1] / W))
    grid_params = dataclasses.replace(params, sigma=params.sigma * s, sigma_min=params.sigma_min * s,
                                      sigma_max=params.sigma_max * s)
    fb_grid = None
    if fb_err is not None:  # nearest sampling keeps inf (unchecked); pixels -> grid pixels
        fb_grid = torch.from_numpy(cv2.resize(fb_err.numpy(), (size[1], size[0]), interpolation=cv2.INTER_NEAREST)) * s
    cov = flow_covariance(downscale(image, size), grid_params, fb_error=fb_grid)
    return upsample_cov(cov, (H, W))


def _gt_flow(pair: FramePair, params: ConfidenceParams) -> tuple[torch.Tensor, torch.Tensor]:
    source = pair.info.source if pair.info.source is not None else pair.name or "this data source"
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
    cfg = flow_params(cfg) if name == "gt" else image_params(cfg)
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
