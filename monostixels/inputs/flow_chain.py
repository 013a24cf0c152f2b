"""Chained flow of a keyframe pair (``keyframes.chain_flow``): the flow to the stream's last frame composed
with the kept flows of the frames between, refined on the pair's own images."""
from __future__ import annotations

import dataclasses
import logging
import time
from typing import Any, Sequence

import numpy as np
import torch

from monostixels._pools import helper_pool
from monostixels._checks import InputError, check_finite_fast, check_image_pair
from monostixels.data.base import FramePair
from monostixels.inputs.confidence import fb_consistency_error, flow_covariance
from monostixels.inputs.flow import FlowResult, both_ways, confidence_params, flow_of_checked_images, image_params
from monostixels.inputs.flow_backends import BACKENDS, gray_u8, refine_flow, refine_passes
from monostixels.inputs.flow_config import flow_name
from monostixels.inputs.flow_resample import remap

__all__ = ["chained_flow", "compose_flows"]


logger = logging.getLogger(__name__)


def compose_flows(first: np.ndarray, then: np.ndarray) -> np.ndarray:
    """The flow of two flows one after the other: ``x -> x + a(x)`` (``first``), then ``y -> y + b(y)``
    (``then``), i.e. ``a(x) + b(x + a(x))`` (bilinear, border replicated); (H, W, 2) float32 pixels."""
    return first + remap(then, first)


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
    if name not in BACKENDS:
        raise InputError(f"flow.name: chained keyframe flow needs an image backend {tuple(BACKENDS)}, got {name!r}")
    cfg = image_params(cfg)
    if not steps:
        raise InputError("chained flow: no kept flows between the stream's last frame and the pair's earlier frame")
    t0 = time.perf_counter()
    params = confidence_params(cfg)
    fb = cfg.fb_consistency
    check_image_pair(pair.image, pair.image_prev)
    check_image_pair(pair.image, last_image)
    step_pair = dataclasses.replace(pair, image_prev=last_image)
    if fb:
        f_tl, b_tl, grey = both_ways(step_pair, cfg, None, last_grey)
    else:
        (f_tl, grey), b_tl = flow_of_checked_images(pair.image, last_image, cfg, None, last_grey), None
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
    g_cur = grey if grey is not None else gray_u8(pair.image.float())
    g_prev = prev_grey if prev_grey is not None else gray_u8(pair.image_prev.float())
    passes = refine_passes(cfg)

    def chw(x: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1)))

    back_job = helper_pool("refine-backward").submit(refine_flow, (g_prev, g_cur), chw(bwd), passes) \
        if bwd is not None else None
    flow = refine_flow((g_cur, g_prev), chw(fwd), passes)
    back = back_job.result() if back_job is not None else None
    check_finite_fast(flow, f"chained flow from backend {name}")
    cov = flow_covariance(pair.image, params, fb_error=fb_consistency_error(flow, back) if back is not None else None)
    seconds = time.perf_counter() - t0
    logger.debug("flow %s on %s chained through %d frames: %.2f s", name, pair.name, len(steps) + 1, seconds)
    return FlowResult(flow=flow.contiguous(), cov=cov.contiguous(), seconds=seconds, backend=name, grey=g_cur,
                      backward=back, step=(f_tl, b_tl), chained=len(steps) + 1)
