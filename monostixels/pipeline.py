"""The one call a user makes: a frame pair and its camera in, stixels (and the SfM baseline) out.

Data flows one way: images -> inputs (flow, semantics, camera motion) -> per-column costs ->
DP -> stixels -> depth / evaluation / pictures.

Example (the builder, :mod:`monostixels.build`, parses the config into the pipeline's settings):
    >>> from monostixels.build import Purpose, build_pipeline
    >>> from monostixels.pipeline import load_config
    >>> cfg = load_config(["flow=gt", "semantic=gt", "motion=gt"])
    >>> from monostixels.data.synthetic import render_pair
    >>> result = build_pipeline(cfg, Purpose.EVAL).run(render_pair(0, scale=0.25))
    >>> result.stixels.depth_map().shape
    torch.Size([94, 310])
"""
from __future__ import annotations

import dataclasses
import logging
import time
from concurrent.futures import wait
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import torch

from monostixels._checks import InputError, check_frame_size, config_params
from monostixels._config import load_config
from monostixels._pools import helper_pool
from monostixels._threads import ensure_threads, set_opencv_threads, threads
from monostixels.post.boundaries import refine_object_tops
from monostixels.data.base import FramePair
from monostixels.core.energy import PriorConfig, load_config_group
from monostixels.post.sfm import triangulate
from monostixels.core.geometry import Camera, Motion
from monostixels.inputs.flow import FlowResult, estimate_flow
from monostixels.inputs.flow_chain import chained_flow
from monostixels.inputs.motion import (NO_METRIC_MOTION, MotionEstimate, MotionKind, ScaleFrom, estimate_motion,
                                      implied_height)
from monostixels.inputs.motion_track import MonoMotionConfig, MotionTrack
from monostixels.inputs.semantic import estimate_semantics
from monostixels.post.cut_off import stand_cut_off
from monostixels.post.movers import MoverCheckParams, check_movers, settle_receding, static_only
from monostixels.core.solver import SolverConfig, solve
from monostixels.data.static_regions import crop_ignored
from monostixels.core.stixels import StixelWorld
from monostixels.core.status import StreamFrames

__all__ = ["EvalConfig", "MotionEstimationError", "PipelineResult", "Carried", "Chain", "PipelineSettings", "Pipeline",
           "warp_scores", "load_config"]

logger = logging.getLogger(__name__)


class MotionEstimationError(InputError):
    """The camera motion of a frame pair could not be estimated from its images (``motion=mono``)."""


@dataclass
class EvalConfig:
    """The evaluation's settings (docs/conventions.md, section 4.5), which the product path reads too (the SfM
    baseline's guard, the frame interval of sources without times, the depth colour maps of every command's
    pictures): the schema of the config group ``eval`` (monostixels.config_schema).

    Attributes:
        max_depth: ground-truth cap (metres): pixels with ground truth beyond it are not evaluated, and
            estimates are clamped to it (an invalid estimate is set to it). 80 m is the usual KITTI practice
            (Eigen et al. 2014; Godard et al. 2017); KITTI 2015's Velodyne ground truth rarely reaches beyond.
        min_depth: lower clamp of estimates (metres), the usual KITTI practice (Eigen/Godard evaluation code):
            it only keeps ``y*/y`` finite. A larger value (1 m) would silently improve a method that outputs
            absurdly close depths, and no ground-truth pixel is closer than a few metres.
        sfm_min_parallax_rad: rays of the structure-from-motion baseline (:mod:`monostixels.post.sfm`) whose
            parallax angle is below this (radians) carry no depth (+inf); a numerical guard far below any
            measurable parallax (1 px at KITTI's 721 px focal length is 1.4e-3 rad).
        colormap_min_depth, colormap_max_depth: the depth colour maps (pictures only, not metrics) span inverse
            depth between these (metres), red (close) to dark blue (far).
        moving_speed_mps: the report's ``stixel_motion``: a stixel counts as moving when its estimated world
            motion over the frame interval exceeds this speed (m/s; a walking pedestrian's is ~1.4 m/s, a
            static object's motion mis-estimated by 10 cm at 10 Hz stays below).
        frame_interval_s: seconds between the frames of a pair for sources whose pairs carry no time
            (``meta["dt"]``): KITTI's 10 Hz.
    """

    max_depth: float = 80.0
    min_depth: float = 0.001
    sfm_min_parallax_rad: float = 1.0e-6
    colormap_min_depth: float = 3.0
    colormap_max_depth: float = 80.0
    moving_speed_mps: float = 1.0
    frame_interval_s: float = 0.1


@dataclass
class PipelineResult:
    """Everything the pipeline computed for one frame pair.

    Attributes:
        pair: the input. flow: flow (2, H, W) and covariance (H, W, 2, 2). semantic: (10, H, W)
        scores or None. motion: the camera motion used (``X_prev = R X_cur + t``) and how it was
        obtained. stixels: the result. sfm_depth: (H, W) depth of the triangulation baseline
        (metres; invalid = negative or inf), None from a pipeline made with ``sfm=False``.
        seconds: wall time of each stage (flow and semantic may overlap; ``inputs`` both together) and of
            the pair (``wall``); ``inputs_ahead``: the inputs' time where a stream computed them while
            the last pair was solved (``stream.overlap``; part of ``wall`` all the same).
        pose: (4, 4) camera-to-world of the current frame on sequences (world = the first camera;
        :mod:`monostixels.sequence`), else None.
    """

    pair: FramePair
    flow: FlowResult
    semantic: torch.Tensor | None
    motion: MotionEstimate
    stixels: StixelWorld
    sfm_depth: torch.Tensor | None
    seconds: dict[str, float] = field(default_factory=dict)
    pose: torch.Tensor | None = None

    @property
    def total_seconds(self) -> float:
        """Wall time of the mono-stixel pipeline (inputs + solver), without the SfM baseline."""
        if "wall" in self.seconds:
            return self.seconds["wall"] - self.seconds.get("sfm", 0.0)
        return sum(v for k, v in self.seconds.items() if k != "sfm")


@dataclass
class Carried:
    """What a pair is given from the earlier frames of its stream (:mod:`monostixels.sequence.stream`; fields
    None where nothing is carried).

    Attributes:
        grey_prev: (H, W) uint8 grey of the pair's previous image.
        flow_init: (H, W, 2) float32 start of the flow, pixels (current -> previous).
        semantic: (10, H, W) scores of the pair's previous frame, to carry through the flow; None = run the net.
        motion: the last pair's camera-motion estimate (:class:`~monostixels.inputs.motion.MotionEstimate`).
        interval_ratio: this pair's time interval over the last pair's (1 where unknown).
    """

    grey_prev: np.ndarray | None = None
    flow_init: np.ndarray | None = None
    semantic: torch.Tensor | None = None
    motion: Any = None
    interval_ratio: float = 1.0
    chain: "Chain | None" = None

    @property
    def anything(self) -> bool:
        """Whether anything is carried (else the pair runs exactly as on its own)."""
        return any(x is not None for x in (self.grey_prev, self.flow_init, self.semantic, self.motion, self.chain))


@dataclass
class Chain:
    """What a keyframe pair's flow is chained through (:func:`monostixels.inputs.flow_chain.chained_flow`).

    Attributes:
        last_image: (3, H, W) image of the stream's last frame ``L`` (between the pair's two frames).
        last_grey: (H, W) uint8 grey of it, or None.
        prev_grey: (H, W) uint8 grey of the pair's earlier frame where the stream kept it, or None.
        steps: the kept flows from ``L`` back to the pair's earlier frame, newest first: (flow from a frame
            to the frame before it, flow back or None), (H, W, 2) float32 pixels.
    """

    last_image: torch.Tensor
    last_grey: np.ndarray | None
    steps: list[tuple[np.ndarray, np.ndarray | None]]
    prev_grey: np.ndarray | None = None


@dataclass(frozen=True)
class PipelineSettings:
    """What a :class:`Pipeline` reads of the composed config, each group parsed once into its schema's dataclass
    (monostixels.config_schema) by the builder (:func:`monostixels.build.pipeline_settings`), which hands them down.

    Attributes:
        flow, semantic, motion: the input groups' settings (the dataclass of the chosen option).
        eval: the ``eval`` group (the SfM baseline's guard, the frame interval, the colour maps).
        prior: the ``prior`` group with the semantic option's ``prior_overrides`` applied.
        solver, movers: the ``solver`` and ``movers`` groups.
        threads: the thread budget (``threads``: ``auto`` or a count).
    """

    flow: Any
    semantic: Any
    motion: Any
    eval: EvalConfig
    prior: PriorConfig
    solver: SolverConfig
    movers: MoverCheckParams
    threads: Any = "auto"


class Pipeline:
    """Frame pair -> stixels, configured by the settings of the Hydra config's groups (flow, semantic, motion,
    prior, solver, movers, eval): :func:`monostixels.build.build_pipeline` builds one from a config.

    Args:
        settings: the settings parsed once (:class:`PipelineSettings`; :func:`monostixels.build.pipeline_settings`).
        allow_motion_failure: see :meth:`motion_for`.
        sfm: also triangulate the SfM baseline (``eval``, ``demo``); ``run`` does not read it.
        report_height: with a metric motion from elsewhere (``motion=gt`` / ``file``), also estimate the camera
            height the road implies (:func:`~monostixels.inputs.motion.implied_height`), in
            ``status.motion.camera_height_fit_m`` (``monostixels run``).
        overlap: estimate the semantics in a second thread while the flow is computed (they are
            independent; OpenCV's flow and ONNX Runtime release the GIL, and DeepFlow runs on one
            core). Results are the same either way; ``seconds`` then holds each stage's own wall
            time, which overlap, and ``seconds["wall"]`` the pair's.
    """

    def __init__(self, settings: PipelineSettings, *, allow_motion_failure: bool = False, sfm: bool = True,
                 overlap: bool = True, report_height: bool = False) -> None:
        if not isinstance(settings, PipelineSettings):
            raise TypeError(f"Pipeline: expected PipelineSettings, got {type(settings).__name__}; "
                            "from a config: monostixels.build.build_pipeline(cfg, purpose)")
        self.settings = settings
        self.report_height = report_height
        # The monocular estimator's own settings, for the camera height the road implies beside a given motion.
        self._mono_cfg = config_params(MonoMotionConfig, load_config_group("motion", "mono"), "motion") \
            if report_height else None
        self.sfm = sfm
        self.overlap = overlap
        # The config's thread budget, unless the command line (or a library user) already set one.
        ensure_threads(settings.threads)
        # Overlapped, the flow runs in its own thread beside the semantic net (and the last pair's solve),
        # which keep a core busy: OpenCV's pool gets the rest (monostixels._threads.set_opencv_threads).
        set_opencv_threads(max(1, threads() - 1) if overlap else None)
        self.flow_cfg = settings.flow
        self.semantic_cfg = settings.semantic
        self.motion_cfg = settings.motion
        self.eval_cfg = settings.eval
        self.prior = settings.prior.params()
        self.allow_motion_failure = allow_motion_failure
        self.solver_cfg = settings.solver
        self.mover_check = settings.movers

    def motion_for(self, pair: FramePair, flow: FlowResult, semantic: torch.Tensor | None,
                   prior: MotionEstimate | None = None, interval_ratio: float = 1.0,
                   track: MotionTrack | None = None) -> MotionEstimate:
        """Camera motion of the pair from the ``motion`` config group.

        ``prior``: the last pair's estimate of a stream (``stream.motion_warm_start``) and the ratio of
        this pair's time interval to its (``interval_ratio``): the start of the monocular estimate
        (:func:`monostixels.inputs.motion.estimate_mono`). ``track``: the sequence's constant-velocity
        prior on the monocular scale (:func:`motion_track_for`, owned by the sequence layer), updated
        with this pair; None: the pair's own estimate.

        A degenerate estimate (standing still, pure rotation) keeps its rotation (identity if
        none) with zero translation: the solver then flags the frame and takes depths from the
        scene model (docs/conventions.md, section 7). An estimate that fails outright raises
        :class:`MotionEstimationError`, unless the pipeline was made with
        ``allow_motion_failure=True`` (``monostixels run``): then the frame is treated as degenerate,
        flagged, with a warning.
        """
        warm = {} if prior is None else {"prior": prior, "interval_ratio": interval_ratio}
        est = estimate_motion(pair, flow, self.motion_cfg, semantic, **warm)
        if track is not None:
            est = track.update(pair, est)
        if est.motion is None:
            if not est.degenerate and not self.allow_motion_failure:
                raise MotionEstimationError(f"{pair.name}: camera motion could not be estimated ({est.reason})")
            # `monostixels run`: still produce output, flagged, from the scene model only; the frame's one
            # warning (its flags' reason, which holds est.reason) is logged where it is solved.
            # Solved like a standing camera (depths from the scene model), but its kind stays what it is:
            # without a metric motion no flow vector may be called object motion.
            est = MotionEstimate(
                motion=Motion(torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)),
                degenerate=True, reason=est.reason, inlier_ratio=est.inlier_ratio,
                kind=est.kind if est.kind in NO_METRIC_MOTION else MotionKind.UNKNOWN, unit_motion=est.unit_motion,
            )
        return est

    def scale_uncertain(self, motion: MotionEstimate) -> bool:
        """Whether a metric motion's length is too uncertain to tell movers and warn of collisions:
        its ``scale_std`` above ``motion.max_scale_std`` (docs/conventions.md, section 4.4)."""
        bound = getattr(self.motion_cfg, "max_scale_std", None)
        return (motion.kind == MotionKind.METRIC and motion.scale_std is not None and bound is not None
                and motion.scale_std > bound)

    def camera_for(self, pair: FramePair, motion: MotionEstimate) -> Camera:
        """The camera the solver uses: ``pair.camera``, with the road normal fitted by the ego-motion
        estimator when ``motion.use_ground_normal`` is true and the estimator fitted one.

        A real camera is not mounted exactly level and roads tilt by a few degrees; a level ground
        model then turns the road ahead into object fragments.
        """
        use = getattr(self.motion_cfg, "use_ground_normal", False)
        if not use or motion.ground_normal is None or motion.degenerate:
            return pair.camera
        n = motion.ground_normal.to(pair.camera.ground_normal.dtype)
        return dataclasses.replace(pair.camera, ground_normal=n)

    def run(self, pair: FramePair, motion_track: MotionTrack | None = None) -> PipelineResult:
        """Run every stage on one frame pair, on its own: nothing carried in from earlier frames.

        A sequence's stream (:meth:`monostixels.sequence.stream.StreamState.run_pair`) runs the same steps
        (:meth:`prepare`, :meth:`inputs`, :meth:`given_inputs`, :meth:`timed_motion`, :meth:`solve_pair`,
        :meth:`at_full_size`) with what the last pair of the stream computed.

        Args:
            pair: the frame pair.
            motion_track: the sequence's prior on the camera's speed (see :meth:`motion_for`), or None.
        """
        pair, sec, start = self.prepare(pair)
        carried = Carried()
        flow, semantic = self.given_inputs(pair, self.inputs(pair, carried), sec)
        motion = self.timed_motion(pair, flow, semantic, carried, motion_track, sec)
        return self.at_full_size(self.solve_pair(pair, flow, semantic, motion, sec, start))

    def prepare(self, pair: FramePair) -> tuple[FramePair, dict[str, float], float]:
        """The pair as the stages see it (rows of an ignored region at the bottom cut off), an empty table
        of each stage's seconds and the pair's start time."""
        # Before any stage: OpenCV's flow kills the process on frames below MIN_FRAME_SIZE.
        check_frame_size(*pair.size, pair.name or "frame")
        sec: dict[str, float] = {}
        start = time.perf_counter()
        return crop_ignored(pair), sec, start  # a stream reading ahead has cropped it already

    def given_inputs(self, pair: FramePair, inputs: tuple[FlowResult, torch.Tensor | None, dict[str, float]],
                     sec: dict[str, float]) -> tuple[FlowResult, torch.Tensor | None]:
        """The flow and scores of :meth:`inputs` (their seconds added to ``sec``), ignored pixels made
        uninformative."""
        flow, semantic, input_sec = inputs
        sec.update(input_sec)
        ignore = pair.info.ignore_pixels
        if ignore is not None:
            flow, semantic = _without(ignore, flow, semantic)
        return flow, semantic

    def timed_motion(self, pair: FramePair, flow: FlowResult, semantic: torch.Tensor | None, carried: Carried,
                     motion_track: MotionTrack | None, sec: dict[str, float]) -> MotionEstimate:
        """:meth:`motion_for` started from what is carried in, its seconds in ``sec["motion"]``."""
        t0 = time.perf_counter()
        motion = self.motion_for(pair, flow, semantic, carried.motion, carried.interval_ratio, motion_track)
        sec["motion"] = time.perf_counter() - t0
        return motion

    def at_full_size(self, res: PipelineResult) -> PipelineResult:
        """``res`` of a pair whose bottom rows were cut off (:meth:`prepare`) at the frame's size."""
        pair = res.pair
        full = pair.info.full_pair
        full = pair if full is None else full
        if pair is not full:
            # The outputs keep the frame's size: the rows cut off get no stixel (no depth).
            res.pair = full
            res.stixels.image_size = full.size
            res.flow, res.semantic = _padded(res.flow, res.semantic, full.size[0])
            res.stixels.status.counts.ignored_pixels = int(full.info.ignore_mask.sum())
        return res

    def inputs(self, pair: FramePair, carried: Carried) -> tuple[FlowResult, torch.Tensor | None, dict[str, float]]:
        """The pair's flow and semantic scores (``carried``: what a stream gives it) and each one's wall time.

        With ``overlap`` the semantic net runs in a second thread beside the flow; scores carried by the
        stream (``stream.semantic_every``) follow the flow instead. A keyframe pair given the kept flows of
        the frames between (``carried.chain``) takes its flow chained through them.
        """
        check_frame_size(*pair.size, pair.name or "frame")
        sec: dict[str, float] = {}
        # Beside an image flow backend, one ONNX Runtime thread: its default pool (one spinning
        # thread per core) took the cores of DeepFlow's strips. Same scores either way; the
        # ground-truth flow is quick, and the semantics are then the longer of the two.
        ort_threads = 1 if self.overlap and self.flow_cfg.name != "gt" else 0

        def semantics() -> tuple[torch.Tensor | None, float]:
            t = time.perf_counter()
            return estimate_semantics(pair, self.semantic_cfg, threads=ort_threads), time.perf_counter() - t

        fresh = carried.semantic is None
        t_in = time.perf_counter()
        future = helper_pool("semantics").submit(semantics) if self.overlap and fresh else None
        try:
            t0 = time.perf_counter()
            if carried.chain is not None and self.flow_cfg.name != "gt":
                # A keyframe pair reaching past the last frame: its flow chained through the frames between.
                ch = carried.chain
                flow = chained_flow(pair, self.flow_cfg, ch.last_image, ch.steps, last_grey=ch.last_grey,
                                    prev_grey=ch.prev_grey)
            else:
                kept = {k: v for k, v in (("init", carried.flow_init), ("grey_prev", carried.grey_prev)) if v is not None}
                flow = estimate_flow(pair, self.flow_cfg, **kept)
            sec["flow"] = time.perf_counter() - t0
            if future is not None:
                semantic, sec["semantic"] = future.result()
            elif fresh:
                semantic, sec["semantic"] = semantics()
            else:
                t0 = time.perf_counter()
                semantic = warp_scores(carried.semantic, flow.flow)
                sec["semantic"] = time.perf_counter() - t0
        finally:
            if future is not None:
                wait([future])  # the semantic thread is done before this pair goes on (or fails)
        sec["inputs"] = time.perf_counter() - t_in
        return flow, semantic, sec

    def solve_pair(self, pair: FramePair, flow: FlowResult, semantic: torch.Tensor | None, motion: MotionEstimate,
                   sec: dict[str, float], start: float) -> PipelineResult:
        """The stixels of a pair from its inputs and camera motion: the solver, then the post-processing
        (movers, object tops), the flags and the SfM baseline; ``sec["wall"]`` counts from ``start``."""
        t0 = time.perf_counter()
        with torch.inference_mode():
            stixels = solve(flow.flow, flow.cov, semantic, self.camera_for(pair, motion), motion.motion, self.prior,
                            self.solver_cfg)
        sec["solver"] = time.perf_counter() - t0
        uncertain = self.scale_uncertain(motion)
        if self.mover_check.enabled and not motion.degenerate:
            # Dynamic stixels that an object standing still explains become static (monostixels.post.movers);
            # with an uncertain length, every one whose flow fits the epipolar geometry.
            t0 = time.perf_counter()
            stixels = check_movers(stixels, flow.flow, motion.motion, params=self.mover_check, scale_known=not uncertain)
            # Static objects whose flow puts them behind the camera pull away: their depth is the scene model's.
            stixels = settle_receding(stixels, flow.flow, motion.motion, float(pair.camera.height))
            sec["movers"] = time.perf_counter() - t0
        if self.mover_check.cut_off_contacts > 0 and not motion.degenerate and motion.motion is not None:
            # Movers whose contact is below the image stand on their object's visible contacts (monostixels.post.cut_off).
            stixels = stand_cut_off(stixels, motion.motion, self.mover_check.cut_off_contacts,
                                    self.mover_check.cut_off_max_rms_m, self.mover_check.cut_off_max_jump)
        if self.solver_cfg.top_refine_rows and semantic is not None:
            # Moving objects' tops from cell edges to pixel rows (monostixels.post.boundaries).
            t0 = time.perf_counter()
            stixels = refine_object_tops(stixels, semantic, self.solver_cfg.top_refine_rows,
                                         self.solver_cfg.top_refine_depth_ratio, float(self.prior.alpha_L),
                                         self.solver_cfg.top_refine_objects)
            sec["tops"] = time.perf_counter() - t0
        if self.report_height and motion.scale_from == ScaleFrom.GIVEN and not motion.degenerate:
            # A metric motion from elsewhere (gt / file): the camera height the road implies beside the setting.
            h_fit = implied_height(pair, flow, self._mono_cfg, semantic, motion.motion)
            if h_fit is not None:
                stixels.status.motion.camera_height_fit_m = round(h_fit, 3)
        if motion.kind in NO_METRIC_MOTION:
            # The camera's motion is not known: the flow cannot tell an object's motion from the camera's.
            stixels = static_only(stixels)
        # The camera motion's status (stixels.json writes it as its flags, docs/conventions.md).
        status = stixels.status.motion
        status.kind = motion.kind
        status.scale_from = motion.scale_from
        if motion.scale_std is not None and motion.kind == MotionKind.METRIC:
            status.scale_std = round(float(motion.scale_std), 4)
            status.scale_uncertain = uncertain
        if motion.degenerate:
            status.degenerate = True
        if status.degenerate:
            status.add_reason(str(motion.reason), first=True)
            logger.warning("%s: %s", pair.name, status.reason)
        info = pair.info
        if info.capture_time_s is not None:
            # A live source (monostixels.data.live_video.LiveVideoSource): which frames this pair is made of.
            stixels.status.stream = StreamFrames(
                frame=info.frame, capture_time_s=info.capture_time_s, previous_frame=info.frame_prev,
                previous_capture_time_s=info.capture_time_prev_s, dropped_before=info.dropped_before,
                realtime=info.realtime)
        sfm = None
        if self.sfm:
            t0 = time.perf_counter()
            sfm = triangulate(flow.flow, pair.camera.K, motion.motion,
                              min_parallax_rad=self.eval_cfg.sfm_min_parallax_rad).depth
            sec["sfm"] = time.perf_counter() - t0
        sec["wall"] = time.perf_counter() - start
        logger.debug("%s: %d stixels, seconds %s", pair.name, len(stixels), sec)
        return PipelineResult(pair=pair, flow=flow, semantic=semantic, motion=motion, stixels=stixels,
                              sfm_depth=sfm, seconds=sec)


def warp_scores(scores: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Scores of the previous image carried to the current one through the flow.

    Each current pixel ``x`` takes the scores at ``x + f(x)`` in the previous image (bilinear; the
    border replicated where the flow leaves the image). Bilinear weights are a convex combination, so
    scores that sum to 1 per pixel still do (to float rounding, ~1e-6).

    Args:
        scores: (C, H, W) float32 class scores of the previous image.
        flow: (2, H, W) current -> previous, pixels.

    Returns:
        (C, H, W) float32 scores of the current image.
    """
    C, H, W = scores.shape
    if tuple(flow.shape) != (2, H, W):
        raise InputError(f"warp_scores: flow of shape {tuple(flow.shape)} for scores of shape {tuple(scores.shape)}")
    f = flow.float().numpy()
    mx = f[0] + np.arange(W, dtype=np.float32)[None, :]
    my = f[1] + np.arange(H, dtype=np.float32)[:, None]
    src = np.ascontiguousarray(scores.float().numpy())
    out = np.empty_like(src)
    # One plane at a time: no interleaving of the channels (OpenCV remaps at most 4 at once).
    for c in range(C):
        cv2.remap(src[c], mx, my, cv2.INTER_LINEAR, dst=out[c], borderMode=cv2.BORDER_REPLICATE)
    return torch.from_numpy(out)


#: Flow variance (pixels^2) given to ignored pixels: far past any motion or solver gate, so they weigh nothing.
_IGNORED_FLOW_VAR = 1.0e6


def _without(ignore: torch.Tensor, flow: FlowResult, semantic: torch.Tensor | None
             ) -> tuple[FlowResult, torch.Tensor | None]:
    """The inputs with ``ignore`` (H, W) pixels made uninformative: the flow's variance beyond every gate
    (the solver and the ego-motion weigh them by it) and the class scores flat."""
    m = ignore.bool()
    cov = flow.cov.clone()
    cov[m] = torch.eye(2, dtype=cov.dtype) * _IGNORED_FLOW_VAR
    flow = dataclasses.replace(flow, cov=cov)
    if semantic is not None:
        semantic = semantic.clone()
        semantic[:, m] = 1.0 / semantic.shape[0]
    return flow, semantic


def _padded(flow: FlowResult, semantic: torch.Tensor | None, rows: int) -> tuple[FlowResult, torch.Tensor | None]:
    """A cropped pair's inputs back at the frame's ``rows``: zero flow of no weight and flat scores below the cut."""

    def pad(x: torch.Tensor | None, value: float) -> torch.Tensor | None:
        if x is None:
            return None
        extra = list(x.shape)
        extra[-2] = rows - x.shape[-2]
        return torch.cat([x, torch.full(extra, value, dtype=x.dtype)], dim=-2)

    cov = flow.cov
    cov_pad = torch.eye(2, dtype=cov.dtype).expand(rows - cov.shape[0], cov.shape[1], 2, 2) * _IGNORED_FLOW_VAR
    step = flow.step
    if step is not None:
        step = (pad(step[0], 0.0), pad(step[1], 0.0))
    flow = dataclasses.replace(flow, flow=pad(flow.flow, 0.0), cov=torch.cat([cov, cov_pad], 0),
                               backward=pad(flow.backward, 0.0), step=step, grey=None)
    if semantic is not None:
        semantic = pad(semantic, 1.0 / semantic.shape[0])
    return flow, semantic
