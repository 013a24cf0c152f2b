"""The stream state: work carried from one frame of a sequence to the next (config group ``stream``).

A :class:`StreamState` lives beside the keyframes and tracks of a
:class:`~monostixels.sequence.SequenceRunner` (one object per stream, reset with it) and runs the
steps of the per-pair :class:`~monostixels.pipeline.Pipeline` on every pair (:meth:`StreamState.run_pair`),
which itself keeps nothing. It keeps what the last solved pair computed for its *current* frame, which
becomes the *previous* frame of the next pair:

- per frame (the last few): its 8-bit grey image (the flow backends' input), so that a frame is not
  converted twice, and its semantic scores: with ``stream.semantic_every = k`` the net runs on every
  k-th frame only, and in between a pair takes the scores of its earlier frame carried through the
  flow (each pixel takes the scores of the pixel it came from, ``x + f(x)`` in the previous image);
- of the last pair: its flow, the start of the next pair's flow (``stream.flow_init``: DIS starts its
  coarsest level from it instead of from zero; with a constant velocity the flow at a pixel changes
  little from pair to pair), scaled by the ratio of the two pairs' time intervals; and its camera
  motion, the prediction the ego-motion starts from (``stream.motion_warm_start``, see
  :func:`monostixels.inputs.motion.estimate_mono`'s ``prior``).

With :attr:`StreamState.chain_frames` (set by the sequence layer from ``keyframes.chain_flow`` and
``keyframes.window``) each kept frame also keeps its image and its flows to the frame before it, both
ways; a keyframe pair reaching past the last frame gets them (:class:`Chain`) and its flow is chained
through the frames between (:func:`monostixels.inputs.flow_chain.chained_flow`).

A pair is continued when its earlier frame (``info.frame_prev``) is a kept frame of the same
``info.sequence`` (and image size) and it comes after the last pair; keyframe pairs that reach two
frames back are continued too. Any other pair (independent pairs, the first pair of a clip, a pair
after a failed one) starts cold, exactly as :meth:`Pipeline.run` on its own.

With ``stream.overlap`` the state also overlaps consecutive pairs: the sequence layer reads its source
through :meth:`StreamState.lookahead`, and once a pair's flow and semantics are known (all the next
pair's start from), :meth:`StreamState.start_next` reads the next pair (the next frame, paired as far
back as this one) and computes its flow and semantics in a second thread while this pair's camera
motion is estimated and the pair is solved (the motion, kept by :meth:`StreamState.keep_motion`, is read
by the next pair's own motion estimate only); the pair takes them
(:meth:`StreamState.take_inputs`) if that is the pair asked for next and the state has not changed
since, else computes them itself. The results are the same either way.

Convention (docs/conventions.md, section 2): flow ``x_prev = x + f(x)`` from the current to the
previous image, pixels; camera motion ``X_prev = R X_cur + t`` (metres).
"""
from __future__ import annotations

import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import torch

from monostixels._checks import InputError
from monostixels.data.static_regions import crop_ignored
from monostixels.data.base import FramePair, LiveSource, PreviousFrame, SequentialSource, Source
from monostixels.inputs.motion_track import MotionTrack
from monostixels.pipeline import Carried, Chain, Pipeline, PipelineResult, warp_scores

__all__ = ["StreamParams", "StreamState", "Carried", "Chain", "warp_scores"]

#: Ratio of two pairs' time intervals beyond which the last flow is no start for the next one (a run of
#: dropped frames, a keyframe that reaches back much further): the flow scales with the interval only
#: roughly, and DIS's coarse levels then do better from zero.
_MAX_INTERVAL_RATIO = 2.0
#: Frames whose grey image and scores are kept: a keyframe pair may pair with any of them (the paper's
#: 0.5 m at 5 m/s reaches two frames back at 10 Hz); one reaching further starts cold.
_HISTORY_FRAMES = 4


@dataclass
class StreamParams:
    """What a stream carries from frame to frame: the schema of the config group ``stream``
    (monostixels.config_schema). The defaults carry nothing that changes a result (``stream=cold``).

    Attributes:
        flow_init: start each pair's flow from the last pair's flow (image backends with a DIS stage).
        semantic_every: run the semantic net on every k-th frame of a stream (1 = every frame); the
            frames between take the scores of their pair's earlier frame carried through the flow.
        motion_warm_start: start the monocular ego-motion from the last pair's motion (constant velocity).
        overlap: compute the next pair's flow and semantics in a second thread while this pair's motion is
            estimated and it is solved (sources read from disk; the same results either way).
    """

    flow_init: bool = False
    semantic_every: int = 1
    motion_warm_start: bool = False
    overlap: bool = True

    def __post_init__(self) -> None:
        for key in ("flow_init", "motion_warm_start", "overlap"):
            if not isinstance(getattr(self, key), bool):
                raise InputError(f"stream.{key}: true or false, got {getattr(self, key)!r}")
        k = self.semantic_every
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise InputError(f"stream.semantic_every: a whole number >= 1 (1 = the net on every frame), got {k!r}")


@dataclass
class _Frame:
    """What the stream keeps of a frame that was the current frame of a solved pair."""

    grey: np.ndarray | None          # (H, W) uint8
    semantic: torch.Tensor | None    # (10, H, W)
    semantic_age: int                # frames since the net ran (0 = on this frame)
    image: torch.Tensor | None = None                            # (3, H, W), kept where flows are chained
    step: tuple[np.ndarray, np.ndarray | None] | None = None     # flows to / from the frame before (H, W, 2)
    step_to: Any = None                                          # the frame `step` reaches


@dataclass
class _Pair:
    """What the stream keeps of the last solved pair."""

    frame: Any
    dt: float | None
    flow: np.ndarray | None          # (H, W, 2) float32
    motion: Any


class StreamState:
    """The stream state of one sequence (module docstring).

    Args:
        params: what to carry (:class:`StreamParams`).
    """

    def __init__(self, params: StreamParams | None = None) -> None:
        self.params = params or StreamParams()
        #: Frames a keyframe pair's flow may be chained through (the sequence layer's ``keyframes.window``
        #: where ``keyframes.chain_flow``; 0 = never chained): each kept frame then also keeps its image and
        #: its flows to the frame before.
        self.chain_frames = 0
        self._lock = threading.Lock()
        self._generation = 0
        self._lookahead: _Lookahead | None = None
        self._pool: ThreadPoolExecutor | None = None
        self._ready: Future | None = None
        self.reset()

    def reset(self) -> None:
        """Forget the stream (a new clip, a failed pair); work started ahead is dropped."""
        with self._lock:
            self._generation += 1
            self._key: tuple[Any, tuple[int, int]] | None = None   # (sequence, image size)
            self._frames: dict[Any, _Frame] = {}
            self._last: _Pair | None = None
            self._ready = None
        if self._lookahead is not None:
            self._lookahead.pending = None
        #: Pairs that started from carried work / from scratch since the last reset (logs, tests).
        self.continued = 0
        self.cold = 0
        #: Pairs whose inputs were computed ahead (``stream.overlap``).
        self.ahead = 0

    # ------------------------------------------------------------------ overlap (stream.overlap)
    def lookahead(self, source: Source) -> Source:
        """``source`` as the sequence layer should read it: with ``stream.overlap``, a view that reads the
        next pair ahead (its images, then its flow and semantics, see :meth:`start_next`); a live source
        (frames as they come) or a source of independent pairs as it is."""
        if not self.params.overlap or isinstance(source, LiveSource) or not isinstance(source, SequentialSource):
            self._lookahead = None
            return source
        self._lookahead = _Lookahead(source)
        return self._lookahead

    def start_next(self, inputs: Callable[[FramePair, Carried], Any]) -> None:
        """Start the next pair's ``inputs(pair, carried)`` (the pipeline's flow and semantics) in the
        background: the pair the sequence layer will most likely ask for next (the next frame, paired
        as far back as this one). Called once the state holds what that pair starts from."""
        la = self._lookahead
        if la is None:
            return
        key = la.guess()
        if key is None:
            return
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="monostixels-next-pair")
        generation = self._generation

        def work() -> tuple[FramePair, Any]:
            pair = la.load(key)
            with self._lock:
                carried = self.carried(pair) if generation == self._generation else None
            if carried is None:
                return pair, None
            try:
                return pair, (generation, inputs(pair, carried), None)
            except Exception as err:  # noqa: BLE001 — raised where the pipeline would have raised it
                return pair, (generation, None, err)

        future = self._pool.submit(work)
        la.pending = (key, future)
        self._ready = future

    @property
    def waited_s(self) -> float:
        """Seconds the sequence layer has waited for pairs read ahead and their inputs (``stream.overlap``)."""
        return self._lookahead.waited_s if self._lookahead is not None else 0.0

    def take_inputs(self, pair: FramePair) -> Any:
        """The inputs computed ahead for ``pair`` (the very pair object read ahead, with the state as it is
        now), or None: then the pipeline computes them."""
        future, self._ready = self._ready, None
        if future is None or not future.done() or future.exception() is not None:
            return None  # not this pair's, or its reading failed (the source raised that where it was asked)
        ahead, out = future.result()
        if ahead is not pair or out is None or out[0] != self._generation:
            return None
        if out[2] is not None:
            raise out[2]
        self.ahead += 1
        return out[1]

    # ------------------------------------------------------------------ one pair
    def run_pair(self, pipeline: Pipeline, pair: FramePair, motion_track: MotionTrack | None = None
                 ) -> PipelineResult:
        """Run ``pipeline``'s steps on ``pair``, a pair of this stream: what the last pair of the stream
        computed for this pair's previous frame (grey image, flow, semantic scores, camera motion, as the
        config group ``stream`` says) is carried in, and this pair's is kept; with ``stream.overlap`` the
        next pair's flow and semantics start while this pair's camera motion is estimated and it is
        solved. A pair that does not continue the stream runs as :meth:`Pipeline.run` on its own.

        Args:
            pipeline: the per-pair pipeline.
            pair: the frame pair.
            motion_track: the sequence's prior on the camera's speed
                (:meth:`~monostixels.pipeline.Pipeline.motion_for`), or None.
        """
        pair, sec, start = pipeline.prepare(pair)
        try:
            carried = self.carried(pair)
            ready = self.take_inputs(pair)
            flow, semantic = pipeline.given_inputs(pair, ready if ready is not None else pipeline.inputs(pair, carried),
                                                   sec)
            if ready is not None:
                # Computed ahead, while the last pair was solved: counted in this pair's wall time all the same.
                sec["inputs_ahead"] = sec["inputs"]
                start -= sec["inputs"]
            # What the next pair's inputs start from is known now (this frame's grey image, flow and
            # scores); with stream.overlap its flow and semantics start in the background while this
            # pair's camera motion is estimated and the pair is solved. The motion, which only the
            # next pair's own motion estimate reads, is kept once it is known.
            self.update(pair, grey=flow.grey, flow=flow.flow, semantic=semantic, semantic_fresh=carried.semantic is None,
                        motion=None, carried=carried, flow_result=flow)
            self.start_next(pipeline.inputs)
            motion = pipeline.timed_motion(pair, flow, semantic, carried, motion_track, sec)
            self.keep_motion(pair, None if motion.degenerate else motion)
            res = pipeline.solve_pair(pair, flow, semantic, motion, sec, start)
        except Exception:
            self.drop()  # the next pair starts cold
            raise
        return pipeline.at_full_size(res)

    # ------------------------------------------------------------------ before a pair
    def _continues(self, pair: FramePair) -> bool:
        info = pair.info
        seq, cur, prev = info.sequence, info.frame, info.frame_prev
        return (seq is not None and cur is not None and prev is not None and self._last is not None
                and self._key == (seq, tuple(pair.size)) and prev in self._frames and prev < cur
                and self._last.frame < cur)

    def _chain(self, pair: FramePair) -> Chain | None:
        """The kept flows from the last frame back to ``pair``'s earlier frame, where they reach it."""
        info = pair.info
        seq, cur, prev = info.sequence, info.frame, info.frame_prev
        last = self._last
        if (self.chain_frames < 1 or last is None or seq is None or cur is None or prev is None
                or self._key != (seq, tuple(pair.size)) or not prev < last.frame < cur):
            return None
        frame, steps = last.frame, []
        while frame != prev:
            kept = self._frames.get(frame)
            if kept is None or kept.step is None or kept.step_to is None or kept.step_to < prev:
                return None
            steps.append(kept.step)
            frame = kept.step_to
        top = self._frames[last.frame]
        if top.image is None or len(steps) > self.chain_frames:
            return None
        kept_prev = self._frames.get(prev)
        return Chain(last_image=top.image, last_grey=top.grey, steps=steps,
                     prev_grey=kept_prev.grey if kept_prev is not None else None)

    def carried(self, pair: FramePair) -> Carried:
        """What the stream gives ``pair``: nothing unless its earlier frame was the current frame of a
        kept pair of the same sequence (and image size) and it comes after the last pair; with
        :attr:`chain_frames`, a pair reaching back past the last frame also gets the flows to chain."""
        chain = self._chain(pair)
        if not self._continues(pair):
            return Carried(chain=chain)
        last = self._last
        assert last is not None
        prev = self._frames[pair.info.frame_prev]
        dt = pair.info.dt
        ratio = float(dt) / last.dt if dt and last.dt else 1.0
        p = self.params
        init = None
        if p.flow_init and last.flow is not None and 1.0 / _MAX_INTERVAL_RATIO <= ratio <= _MAX_INTERVAL_RATIO:
            # The flow at a pixel scales with the time between the frames (constant velocity).
            init = last.flow if ratio == 1.0 else last.flow * np.float32(ratio)
        semantic = None
        if p.semantic_every > 1 and prev.semantic is not None and prev.semantic_age + 1 < p.semantic_every:
            semantic = prev.semantic
        motion = last.motion if p.motion_warm_start else None
        return Carried(grey_prev=prev.grey, flow_init=init, semantic=semantic, motion=motion, interval_ratio=ratio,
                       chain=chain)

    # ------------------------------------------------------------------ after a pair
    def update(self, pair: FramePair, *, grey: np.ndarray | None, flow: torch.Tensor | None,
               semantic: torch.Tensor | None, semantic_fresh: bool, motion: Any, carried: Carried,
               flow_result: Any = None) -> None:
        """Keep what ``pair`` computed for its current frame.

        Args:
            pair: the solved pair (``meta`` ``sequence``, ``frame``, ``frame_prev``, ``dt``).
            grey: (H, W) uint8 grey of its current image, or None.
            flow: (2, H, W) its flow. semantic: (10, H, W) its scores, or None.
            semantic_fresh: the net ran on this pair (else its scores were carried).
            motion: its camera-motion estimate, None where it is degenerate or not known yet (then
                :meth:`keep_motion` keeps it once it is).
            carried: what :meth:`carried` gave it.
            flow_result: its :class:`~monostixels.inputs.flow.FlowResult` (with :attr:`chain_frames`: the
                flows between its current frame and the one before, kept for later chains).
        """
        seq, frame = pair.info.sequence, pair.info.frame
        if seq is None or frame is None:
            self.reset()  # an independent pair: nothing to carry
            return
        key = (seq, tuple(pair.size))
        if key != self._key:
            self.reset()
            self._key = key
        with self._lock:  # a pair read ahead in vain may still be reading the state
            self._update(pair, grey, flow, semantic, semantic_fresh, motion, carried, flow_result)

    def keep_motion(self, pair: FramePair, motion: Any) -> None:
        """Keep ``pair``'s camera motion (None where it is degenerate), known after :meth:`update` kept its
        inputs: the start of the next pair's motion estimate (``stream.motion_warm_start``). Nothing
        where ``pair`` is not the last pair kept (an independent pair, a reset)."""
        with self._lock:
            last = self._last
            if (self.params.motion_warm_start and last is not None and self._key is not None
                    and self._key[0] == pair.info.sequence and last.frame == pair.info.frame):
                last.motion = motion

    def _update(self, pair: FramePair, grey: np.ndarray | None, flow: torch.Tensor | None,
                semantic: torch.Tensor | None, semantic_fresh: bool, motion: Any, carried: Carried,
                flow_result: Any) -> None:
        info = pair.info
        frame = info.frame
        last = self._last.frame if self._last is not None else None
        self._generation += 1
        self.continued += int(carried.anything)
        self.cold += int(not carried.anything)
        p = self.params
        prev = self._frames.get(info.frame_prev)
        age = 0 if semantic_fresh or prev is None else prev.semantic_age + 1
        kept = _Frame(grey=grey, semantic=semantic if p.semantic_every > 1 else None, semantic_age=age)
        if self.chain_frames > 0 and flow_result is not None:
            kept.image = pair.image
            kept.step, kept.step_to = _step_of(pair, flow_result, last)
        self._frames[frame] = kept
        for f in sorted(self._frames)[:-max(_HISTORY_FRAMES, self.chain_frames + 1)]:
            del self._frames[f]
        dt = info.dt
        keep_flow = p.flow_init and flow is not None
        self._last = _Pair(frame=frame, dt=float(dt) if dt else None,
                           flow=np.ascontiguousarray(flow.permute(1, 2, 0).numpy()) if keep_flow else None,
                           motion=motion if p.motion_warm_start else None)

    def drop(self) -> None:
        """The pair failed: the next one starts cold."""
        self.reset()


def _hwc(x: torch.Tensor | None) -> np.ndarray | None:
    return None if x is None else np.ascontiguousarray(x.permute(1, 2, 0).numpy(), dtype=np.float32)


def _step_of(pair: FramePair, flow: Any, last: Any) -> tuple[tuple[np.ndarray, np.ndarray | None] | None, Any]:
    """The flows between ``pair``'s current frame and the stream frame before it (``last``), and that frame.

    A chained pair computed them (``flow.step``, to ``last``); a pair of consecutive stream frames has
    them as its own flows (a ground-truth flow none: nothing to chain). Else none."""
    if flow.step is not None:
        return (_hwc(flow.step[0]), _hwc(flow.step[1])), last
    prev = pair.info.frame_prev
    if flow.backend != "gt" and (last is None or prev == last):
        return (_hwc(flow.flow), _hwc(flow.backward)), prev
    return None, None


class _Lookahead:
    """A sequence source whose next pair is read ahead (:meth:`StreamState.lookahead`).

    Everything but the pairs goes to the source. The pair asked for is the one read ahead when its
    index and frames back are the ones guessed (then the very object the background thread computed
    the inputs of), else read as usual.
    """

    def __init__(self, source: SequentialSource) -> None:
        self._source = source
        self._next: tuple[int, int] | None = None
        self.pending: tuple[tuple[int, int], Future] | None = None
        #: Seconds the reader of the pairs spent waiting for pairs read ahead (and their inputs).
        self.waited_s = 0.0

    def __getattr__(self, name: str) -> Any:
        return getattr(self._source, name)

    def __len__(self) -> int:
        return len(self._source)

    def __getitem__(self, index: int) -> FramePair:
        return self._get(index, 1)

    def sequence_key(self, index: int) -> str | None:
        return self._source.sequence_key(index)

    def previous_frames(self, index: int, window: int) -> list[PreviousFrame]:
        return self._source.previous_frames(index, window)

    def pair_back(self, index: int, back: int) -> FramePair:
        return self._get(index, int(back))

    def load(self, key: tuple[int, int]) -> FramePair:
        index, back = key
        pair = self._source[index] if back == 1 else self._source.pair_back(index, back)
        # Cropped here (a bonnet's rows), so that the inputs computed ahead are those of the pair solved.
        return crop_ignored(pair)

    def _get(self, index: int, back: int) -> FramePair:
        pending, self.pending = self.pending, None
        self._next = (index, back)
        if pending is not None and pending[0] == (index, back):
            t0 = time.perf_counter()
            pair = pending[1].result()[0]  # waits for its inputs too: the pipeline needs them next
            self.waited_s += time.perf_counter() - t0
            return pair
        return self.load((index, back))

    def guess(self) -> tuple[int, int] | None:
        """(index, frames back) of the pair most likely asked for next: the next frame of the same clip,
        paired as far back as the last one (keyframes change rarely from frame to frame)."""
        if self._next is None:
            return None
        index, back = self._next
        nxt = index + 1
        if nxt >= len(self._source) or self._source.sequence_key(nxt) != self._source.sequence_key(index):
            return None
        if back > 1 and len(self._source.previous_frames(nxt, back)) < back:
            back = 1
        return nxt, back
