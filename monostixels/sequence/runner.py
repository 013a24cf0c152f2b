"""Video as the unit: keyframes, the stream state carried from frame to frame, tracks and time-to-collision.

:class:`SequenceRunner` runs a :class:`~monostixels.pipeline.Pipeline` over a data source frame by frame.
For a source of sequences (drives, videos, folders of frames, synthetic clips: the sources implement
``sequence_key``, ``previous_frames`` and ``pair_back``, see :class:`monostixels.data._lazy_source.LazySource`):

1. **Keyframes** (paper: "keyframes with a minimum driven distance of 0.5 m"). The current frame is
   paired with the most recent earlier frame, at most ``keyframes.window`` frames back, whose driven
   distance is at least ``keyframes.min_distance_m``. The distance is the ground truth's where the
   motion comes from it (``motion=gt|file``), else the stream's speed estimate (the last pairs' ``|t|``
   over their time) times the time between the frames. Where no frame in the window is far enough:
   the oldest one (the most baseline there is; a standing camera: the movers' chained flow measured
   over the longest interval), or the previous frame where a standing camera's flow is not chained
   (``keyframes.chain_flow=false``: a flow straight across the pair loses large displacements).
   ``keyframes.min_distance_m = 0`` always pairs with the previous frame. A pair reaching past the
   previous frame takes its flow chained through the frames between (``keyframes.chain_flow``; the
   stream keeps each frame's flows to the frame before it: :func:`monostixels.inputs.flow_chain.chained_flow`).
   Only solved frames are partners: a frame whose pair failed has no pose to chain through.
2. **A standing camera.** A pair without baseline is solved as before (degenerate: depths from the
   scene model), but the movers still are found and measured from the flow: their depth from the
   ground contact, their motion from ``t̃``. Static stixels whose track was measured with a baseline
   keep the track's depth (``status.counts.carried_stixels``).
3. **Tracks** (:mod:`monostixels.sequence.tracking`): every object stixel gets a ``track_id``, a filtered depth
   and a world velocity (m/s, world = the sequence's first camera); with ``temporal.enabled=false``
   velocities come from the pair alone and no depth is filtered.
4. **Time to collision** per object stixel (``ttc_s``), and the frame's pose (camera to world).

Everything carried from frame to frame lives here: the kept frames and their poses, the speed the
keyframes read, the stream's reused work (:class:`~monostixels.sequence.stream.StreamState`), the monocular
scale's speed prior (:class:`~monostixels.inputs.motion_track.MotionTrack`, handed to each pair's camera
motion) and the tracks. The pipeline itself keeps nothing between pairs: the stream runs its steps on each
pair (:meth:`~monostixels.sequence.stream.StreamState.run_pair`).

Independent pairs (KITTI 2015, synthetic pairs) pass through with single-pair velocities and TTC.

Convention: camera motion ``X_prev = R X_cur + t``; a pose is camera-to-world, ``X_w = R_wc X_c + o``.
"""
from __future__ import annotations

import dataclasses
import gc
import logging
import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Iterator, Sequence

import torch

from monostixels._checks import InputError
from monostixels._threads import threads, torch_threads
from monostixels.core.classes import CLASS_TYPE, DYNAMIC_OBJECT, STATIC_OBJECT
from monostixels.data._lazy_source import PairSkipped
from monostixels.data.base import FramePair, KeyframeParams, LiveSource, PreviousFrame, SequentialSource, Source
from monostixels.core.geometry import Motion
from monostixels.inputs.motion import NO_METRIC_MOTION
from monostixels.inputs.motion_track import MonoMotionConfig, MotionTrack, motion_params
from monostixels.pipeline import MotionEstimationError, Pipeline, PipelineResult, PipelineSettings
from monostixels.core.stixels import StixelWorld
from monostixels.sequence.stream import StreamParams, StreamState
from monostixels.sequence.tracked import TrackedFrame
from monostixels.sequence.tracking import Tracks, TrackParams, stixel_points
from monostixels.sequence.ttc import TtcParams, confirmed, critical, object_wide, time_to_collision

__all__ = ["KeyframeParams", "SequenceSettings", "SequenceStep", "SequenceRunner", "choose_keyframe", "motion_matrix", "motion_track_for"]

logger = logging.getLogger(__name__)


def choose_keyframe(candidates: Sequence[PreviousFrame], params: KeyframeParams, speed_mps: float | None,
                    use_gt_motion: bool, standing_m: float) -> tuple[int, float | None]:
    """Frames back (>= 1) of the earlier frame to pair with, and its estimated driven distance (m, None = unknown).

    Args:
        candidates: earlier frames, nearest first (``back`` 1, 2, ...).
        params: keyframe settings.
        speed_mps: the stream's speed estimate (m/s), None before the first pair.
        use_gt_motion: measure the distance with the candidates' ground-truth motion where they have it.
        standing_m: below this distance the camera counts as standing (``solver.min_translation``).
    """
    if not candidates:
        raise InputError("keyframes: the current frame has no earlier frame to pair with")

    def distance(c: PreviousFrame) -> float | None:
        if use_gt_motion and c.motion is not None:
            return c.motion.translation_norm
        if speed_mps is not None and math.isfinite(c.dt):
            return speed_mps * c.dt
        return None

    dist = [distance(c) for c in candidates]
    if params.min_distance_m == 0 or dist[0] is None:
        return candidates[0].back, dist[0]
    for c, d in zip(candidates, dist):
        if d is not None and d >= params.min_distance_m:
            return c.back, d
    known = [(c, d) for c, d in zip(candidates, dist) if d is not None]
    c_far, d_far = known[-1]
    if d_far > standing_m:
        return c_far.back, d_far
    if params.chain_flow:
        # Standing: no baseline to gain, but a mover's flow grows with the interval while a chained
        # flow's error grows slower (each frame's flow refined on the pair), so its motion is measured
        # over the longest interval allowed. A flow straight across the pair loses large displacements:
        # the previous frame then.
        recent = [(c, d) for c, d in zip(candidates, dist) if math.isfinite(c.dt) and c.dt <= params.standing_max_s]
        if recent:
            return recent[-1][0].back, recent[-1][1]
    return candidates[0].back, dist[0]


def motion_track_for(motion: Any) -> MotionTrack | None:
    """The monocular scale's constant-velocity prior over the pairs of a sequence (``motion.sequence_prior``
    with ``motion=mono``), else None: what the sequence layer keeps from pair to pair. ``motion``: the
    ``motion`` group's settings (its config node or dataclass)."""
    motion = motion_params(motion)
    if isinstance(motion, MonoMotionConfig) and motion.sequence_prior:
        return MotionTrack(motion)
    return None


def motion_matrix(motion: Motion) -> torch.Tensor:
    """The (4, 4) transform from the current to the earlier camera: ``[R t; 0 1]`` (``X_prev = R X_cur + t``)."""
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = motion.R.double()
    T[:3, 3] = motion.t.double()
    return T


@dataclass
class SequenceStep:
    """One processed frame: the source index, the pair solved, and the result (None: motion failed).

    ``tracked``: what the sequence layer adds to the pair's stixels (tracks, velocities, TTC, pose); the
    result's ``stixels`` is :meth:`TrackedFrame.world` of it, as ``stixels.json`` writes it.
    """

    index: int
    pair: FramePair
    result: PipelineResult | None
    error: str | None = None
    tracked: TrackedFrame | None = None


@dataclass
class _Frame:
    """What the stream keeps of a processed frame."""

    name: str
    time: float
    pose: torch.Tensor           # (4, 4) camera-to-world


@dataclass(frozen=True)
class SequenceSettings:
    """What a :class:`SequenceRunner` reads of the composed config, each group parsed once by the builder
    (:func:`monostixels.build.sequence_settings`): the pipeline's settings and the groups of the sequence layer."""

    pipeline: PipelineSettings
    keyframes: KeyframeParams
    temporal: TrackParams
    ttc: TtcParams
    stream: StreamParams


class SequenceRunner:
    """Frames of a data source through the pipeline, with keyframes, tracks and TTC (module docstring).

    Args:
        settings: the settings parsed once (:class:`SequenceSettings`: groups keyframes, temporal, ttc, stream
            beside the pipeline's; :func:`monostixels.build.sequence_settings`, or :func:`monostixels.build.build_runner`
            for the runner of a config).
        pipeline: the per-pair pipeline (built from the settings when None).
    """

    def __init__(self, settings: SequenceSettings, pipeline: Pipeline | None = None) -> None:
        if not isinstance(settings, SequenceSettings):
            raise TypeError(f"SequenceRunner: expected SequenceSettings, got {type(settings).__name__}; "
                            "from a config: monostixels.build.build_runner(cfg, purpose)")
        self.settings = settings
        self.pipeline = pipeline if pipeline is not None else Pipeline(settings.pipeline)
        self.keyframes = settings.keyframes
        self.track_params = settings.temporal
        self.ttc = settings.ttc
        motion = settings.pipeline.motion
        self.use_gt_distance = motion.name in ("gt", "file")
        self.standing_m = float(self.pipeline.solver_cfg.min_translation)
        self.default_dt = settings.pipeline.eval.frame_interval_s
        # Work carried from frame to frame (config group stream; monostixels.sequence.stream).
        self.stream = StreamState(settings.stream)
        self.stream.chain_frames = self.keyframes.window if self.keyframes.chain_flow else 0
        # The speed prior of the monocular scale: it restarts by itself where pairs do not continue a
        # sequence in time order (monostixels.inputs.motion_track), so a new clip needs no reset here.
        self.motion_track = motion_track_for(motion)
        self.reset()

    def reset(self) -> None:
        """Forget the stream (a new clip)."""
        self.key: str | None = None
        self.frames: OrderedDict[int, _Frame] = OrderedDict()  # frame number -> kept state
        self.tracks = Tracks(self.track_params)
        self.speed: float | None = None
        self.count = 0
        self.stream.reset()

    # ------------------------------------------------------------------ driving a source
    def run(self, source: Source, progress: Any = None) -> Iterator[SequenceStep]:
        """Process every pair of ``source`` in order; yields one :class:`SequenceStep` per pair."""
        sequential = isinstance(source, SequentialSource)
        read = self.stream.lookahead(source)  # stream.overlap: the next pair read (and its inputs started) ahead
        if read is source:
            yield from self._run(source, sequential, progress)
            return
        # Overlapped, this thread and the next pair's flow keep the cores busy: torch one thread less.
        with torch_threads(threads() - 1):
            yield from self._run(read, sequential, progress)

    def _run(self, source: Any, sequential: bool, progress: Any) -> Iterator[SequenceStep]:
        # A live source (a camera: monostixels.data.live_video.LiveVideoSource) has no length: it yields its
        # pairs' indices as frames arrive.
        for i in (source.indices() if isinstance(source, LiveSource) else range(len(source))):
            key = source.sequence_key(i) if sequential else None
            try:
                if key is None:
                    self.reset()
                    pair = source[i]
                    step = self._solve(i, pair, None, None)
                else:
                    if key != self.key:
                        self.reset()
                        self.key = key
                    cands = self._solved(source.previous_frames(i, self.keyframes.window), key)
                    back, driven = choose_keyframe(cands, self.keyframes, self.speed, self.use_gt_distance,
                                                   self.standing_m)
                    pair = source.pair_back(i, back) if back != 1 else source[i]
                    # Paired across unreadable frames, the pair reaches further back than chosen.
                    if pair.info.back is None:
                        pair.meta["back"] = back  # the pair tells how far back it reaches (FrameInfo.back)
                    back = int(pair.info.back)
                    step = self._solve(i, pair, back, driven)
            except PairSkipped:
                # Its frames could not be read: the source warned and lists them (skipped_frames).
                if progress is not None:
                    progress.update(1)
                continue
            if progress is not None:
                progress.update(1)
            _freeze_startup_objects()
            yield step

    def _solved(self, candidates: list[PreviousFrame], key: Any) -> list[PreviousFrame]:
        """The earlier frames a pair may reach: those solved (their pose is known), nearest first.

        A frame whose pair failed (its camera motion could not be estimated) has no pose to chain a later
        pair's pose through. Where every earlier frame of the window failed, the sequence starts again at
        this pair (tracks and stream forgotten), paired with the frame before.
        """
        if not self.frames:
            return candidates
        solved = {f.name for f in self.frames.values()}
        usable = [c for c in candidates if c.name in solved]
        if usable or not candidates:
            return usable
        logger.warning("no solved frame in the last %d: the sequence starts again", self.keyframes.window)
        self.reset()
        self.key = key
        return candidates[:1]

    # ------------------------------------------------------------------ one frame
    def _solve(self, index: int, pair: FramePair, back: int | None, driven: float | None) -> SequenceStep:
        try:
            res = self.stream.run_pair(self.pipeline, pair, self.motion_track)
        except MotionEstimationError as err:
            self.reset() if back is None else None
            return SequenceStep(index, pair, None, str(err))
        pair = res.pair  # the frame pair at its full size (a stream reading ahead may have cut a bonnet off)
        dt = float(pair.info.dt or (self.default_dt * (back or 1)))
        sequence = back is not None
        if res.motion.kind in NO_METRIC_MOTION:
            # The camera's motion is not known: no pose to chain, nothing to track, no time to collision.
            return self._step(index, pair, res, self._unknown(res, pair, back, dt))
        if sequence and not res.motion.degenerate:
            self.speed = res.motion.motion.translation_norm / max(dt, 1e-9)
        elif sequence and res.motion.degenerate:
            self.speed = 0.0
        return self._step(index, pair, res, self._finish(res, pair, back, driven, dt, sequence))

    @staticmethod
    def _step(index: int, pair: FramePair, res: PipelineResult, tracked: TrackedFrame) -> SequenceStep:
        """The step of a solved pair: its result's stixels a new world with the sequence's fields."""
        res.stixels = tracked.world()
        res.pose = tracked.pose
        return SequenceStep(index, pair, res, tracked=tracked)

    def _unknown(self, res: PipelineResult, pair: FramePair, back: int | None, dt: float) -> TrackedFrame:
        """Outputs of a pair whose camera motion is unknown (``scale_unknown`` / ``unknown``).

        Its stixels are already static (the pipeline); here they get no track, no velocity, no time to
        collision and no pose (``pose`` stays None). The frame is not kept as a later pair's partner, so the
        pose chain goes on through the frames whose motion is known; the keyframe speed is left as it was.
        """
        self.count += 1
        return TrackedFrame.untracked(res.stixels, _pair_info(pair, back, dt, None, None))

    def _finish(self, res: PipelineResult, pair: FramePair, back: int | None, driven: float | None, dt: float,
                sequence: bool) -> TrackedFrame:
        st = res.stixels
        # Frames are known by the source's frame numbers (raw frame, video frame, clip frame), so that a
        # keyframe pair finds its earlier frame whatever the source skipped.
        info = pair.info
        frame_no = int(info.frame if info.frame is not None else self.count)
        self.count += 1
        T_prev_cur = motion_matrix(res.motion.motion)
        prev = None
        if sequence and info.frame_prev is not None:
            prev = self.frames.get(int(info.frame_prev))
        if prev is None and sequence and info.frame_prev is not None and not self.frames:
            # The sequence's first pair: its earlier frame is the world (a later keyframe pair may pair
            # with that frame too, and must see it at the same pose).
            prev = _Frame(str(info.name_prev or ""), 0.0, torch.eye(4, dtype=torch.float64))
            self.frames[int(info.frame_prev)] = prev
        if prev is not None:
            pose = prev.pose @ T_prev_cur
            time = prev.time + dt
        else:
            pose = torch.eye(4, dtype=torch.float64)
            time = 0.0 if not self.frames else next(reversed(self.frames.values())).time + dt
        tracking = sequence and self.track_params.enabled
        # The camera's velocity over the pair, current axes: it moved by R^T t (X_prev = R X_cur + t).
        v_cam = (res.motion.motion.R.double().T @ res.motion.motion.t.double()) / max(dt, 1e-9)
        if tracking:
            # The flow from this frame to the last one (the stream frame before it): a chained keyframe
            # pair's first step, or a consecutive pair's own flow; the association follows stixels through it.
            last_no = next(reversed(self.frames)) if self.frames else None
            flow_last = None
            if res.flow.step is not None:
                flow_last = res.flow.step[0]
            elif last_no is not None and pair.info.frame_prev == last_no:
                flow_last = res.flow.flow
            out = self.tracks.update(
                st, frame=frame_no, time=time, pose=pose, dt_pair=dt,
                degenerate=bool(res.motion.degenerate or st.status.motion.degenerate), camera_velocity=v_cam,
                motion=res.motion.motion, flow_to_last=flow_last, flow_reaches=last_no)
            track_id, velocity = out["track_id"], out["velocity"]
            st = _with_filtered_depth(st, out["point_cam"])
            if bool(out["carried"].any()):
                st.status.counts.carried_stixels = int(out["carried"].sum())
                st.status.motion.add_reason("static depths carried from the tracks of earlier frames with a baseline")
        else:
            N = len(st)
            track_id = torch.full((N,), -1, dtype=torch.long)
            dyn = st.type == DYNAMIC_OBJECT
            velocity = torch.where(dyn[:, None], st.motion.double() @ pose[:3, :3].T / max(dt, 1e-9),
                                   torch.zeros(N, 3, dtype=torch.float64))
        # Time to collision: the tracks' filtered closing rate, or this pair's depth over its relative
        # velocity (the same monocular scale in both, so it cancels); current camera axes.
        X_cam, _, _ = stixel_points(st)
        X_ok = torch.nan_to_num(X_cam, nan=-1.0)
        R_wc = pose[:3, :3]
        v_rel = velocity @ R_wc - v_cam[None]
        obj = (st.type == STATIC_OBJECT) | (st.type == DYNAMIC_OBJECT)
        ttc = out["ttc"] if tracking else time_to_collision(X_ok, v_rel)
        ttc = torch.where(obj, ttc, torch.full((len(st),), math.inf, dtype=torch.float64))
        # A warning only on a class that can move (a vehicle, a two-wheeler, a person: parked or moving), with a
        # tracked closing that holds in both the filtered rate and the filtered velocity, and never where the
        # camera motion's length is uncertain: with a wrong length the static world closes at the wrong speed
        # (docs/conventions.md, section 4.4).
        movable = torch.tensor(CLASS_TYPE)[st.cls.long()] == DYNAMIC_OBJECT
        ttc_both = torch.maximum(ttc, time_to_collision(X_ok, v_rel)) if tracking else ttc
        warn = obj & movable & critical(X_ok, v_rel, ttc_both, self.ttc)
        warn = object_wide(confirmed(warn, out["age"] if tracking else None, self.ttc), st)
        if st.status.motion.scale_uncertain:
            warn = torch.zeros_like(warn)
        if sequence:
            self.frames[frame_no] = _Frame(pair.name, time, pose)
            while len(self.frames) > self.keyframes.window + 1:
                self.frames.popitem(last=False)
        return TrackedFrame(stixels=st, track_id=track_id, velocity=velocity, ttc_s=ttc, ttc_warning=warn, pose=pose,
                            pair_info=_pair_info(pair, back, dt, res.motion.motion.translation_norm, driven))


_frozen = False


def _freeze_startup_objects() -> None:
    """Move every object alive after the first solved pair (libraries, configs, loaded models) out of the
    garbage collector's reach, once per process: they live for the whole run, and each full collection
    would otherwise walk all of them again (a pause of about 0.1 s on a 2-core machine, one in the first
    20 frames of a KITTI drive: a spike in the step time)."""
    global _frozen
    if not _frozen:
        _frozen = True
        gc.collect()
        gc.freeze()


def _pair_info(pair: FramePair, back: int | None, dt: float, driven_m: float | None,
               keyframe_m: float | None) -> dict[str, Any]:
    """``TrackedFrame.pair_info`` of a solved pair: its frames, how far back, seconds and metres driven (None
    where the camera motion is unknown) and the keyframe distance it was chosen by."""
    return {"current": pair.name, "previous": pair.info.name_prev or "",
            "frames_back": int(back) if back is not None else 1, "dt_s": dt,
            "driven_m": driven_m, "keyframe_distance_m": keyframe_m}


def _with_filtered_depth(st: StixelWorld, point_cam: torch.Tensor) -> StixelWorld:
    """The stixels with each tracked stixel's inverse depth through its filtered point (N, 3), current camera."""
    ok = torch.isfinite(point_cam).all(1)
    if not bool(ok.any()):
        return st
    d = (torch.nan_to_num(point_cam) * st.normals()).sum(-1)
    p = torch.where(ok & (d > 1e-3), 1.0 / d.clamp_min(1e-3), st.inverse_depth.double())
    return dataclasses.replace(st, inverse_depth=p.to(st.inverse_depth.dtype), status=st.status.copy())
