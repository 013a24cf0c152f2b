"""The camera motion over a sequence: a constant-velocity prior on the metric scale and the road normal.

:class:`MotionTrack` is step 5 of :mod:`monostixels.inputs.motion`'s method: the speed ``|t| / dt``
filtered in log space (a 1-D Kalman filter), a pair's outlier scale replaced by the prediction, a
pair of known direction and unknown length given the recent speed, and the road normal filtered on
the unit sphere. The sequence layer (:mod:`monostixels.sequence`, through the pipeline) owns one per
sequence; its parameters are :class:`MotionTrackParams` (keys of the ``motion`` config group).
"""
from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import Any, Union

import torch

from monostixels._checks import InputError, is_unset, option_params
from monostixels.data.base import FramePair
from monostixels.core.geometry import Motion
from monostixels.inputs.motion_base import (FileMotionConfig, GtMotionConfig, MonoParams, MotionEstimate, MotionKind,
                                            ScaleFrom)

__all__ = ["MOTION_SCHEMAS", "MonoMotionConfig", "MotionTrack", "MotionTrackParams", "motion_params"]

logger = logging.getLogger(__name__)

#: Pairs over which the direction of travel's scatter is measured (:meth:`MotionTrack.direction_scatter`).
ELEVATION_WINDOW = 8
#: The direction of travel's scatter (radians) assumed before a sequence has shown its own: between a
#: calibrated car camera's (KITTI drive 0023: 0.07 deg from pair to pair) and a phone's behind a windscreen
#: (Kochi, Singapore: about 3 deg); the clips' numbers are in docs/experiments.md.
DIRECTION_PRIOR_STD = math.radians(1.0)


@dataclass
class MotionTrackParams:
    """Constant-velocity prior of :class:`MotionTrack` (keys of the ``motion`` config group).

    Attributes:
        sequence_prior: filter the metric scale over consecutive pairs (``mono`` only).
        speed_process_std: relative change of speed per second allowed by the model (1/s, std):
            0.3 = 30 %/s, i.e. 2.7 m/s^2 at 9 m/s (braking or accelerating firmly), 3 % per KITTI frame.
        scale_meas_std: relative error (std) of one pair's monocular scale.
        scale_gate: a pair's scale farther than this many innovation standard deviations from the
            prediction is an outlier and replaced by the prediction. The next pair's scale, again an
            outlier but within this many standard deviations of the first one, restarts the track at it
            (then the track, not the pairs, is wrong: a first pair far off would hold every later pair out).
        normal_process_std_deg: how fast the road normal may turn in the camera (degrees per
            square-root second: a random walk; pitching on bumps, a change of slope).
        normal_meas_std_deg: error (std, degrees) of one pair's fitted road normal.
        normal_gate_deg: a fit farther than this from the prediction (degrees, beyond its innovation
            std) is an outlier and the prediction stands. 0 = no normal filter.
        scale_hold_s: a pair whose translation direction is known but not its length
            (``scale_unknown``) takes the filtered speed of the pairs before it, for at most this many
            seconds after the last pair with a measured scale (a car's speed changes slowly); later, or
            without such pairs, it stays ``scale_unknown``. 0 = never. Its uncertainty grows meanwhile
            (``scale_std``), and past ``max_scale_std`` it moves nothing and warns of nothing.
        max_scale_std: the bound on the scale's relative uncertainty (the std of ``log |t|``) above which
            the camera motion's length is not trusted to tell movers: a flow that fits the epipolar
            geometry does not make a stixel a mover, and no time-to-collision warning is raised
            (:mod:`monostixels.post.movers`, :mod:`monostixels.sequence.runner`). 0.15: the mover check
            calls a static object moving from a 30 % depth discrepancy (``movers.min_depth_discrepancy``),
            twice this.
    """

    sequence_prior: bool = True
    speed_process_std: float = 0.3
    scale_meas_std: float = 0.04
    scale_gate: float = 2.0
    normal_process_std_deg: float = 0.3
    normal_meas_std_deg: float = 0.5
    normal_gate_deg: float = 3.0
    scale_hold_s: float = 2.0
    max_scale_std: float = 0.15


@dataclass
class MonoMotionConfig(MonoParams, MotionTrackParams):
    """Schema of the option ``mono`` of the config group ``motion`` (monostixels.config_schema): the
    estimator's settings (:class:`~monostixels.inputs.motion.MonoParams`), the sequence prior's
    (:class:`MotionTrackParams`) and:

    Attributes:
        name: the backend (``mono``).
        use_ground_normal: solve with the road normal fitted for the scale instead of
            ``camera.ground_normal`` (a real camera is not mounted exactly level and roads tilt by a few degrees).
    """

    name: str = "mono"
    use_ground_normal: bool = True


#: The schema of each option of the config group ``motion`` by its ``name`` (monostixels.config_schema).
MOTION_SCHEMAS: dict[str, type] = {"gt": GtMotionConfig, "file": FileMotionConfig, "mono": MonoMotionConfig}

#: The settings of any camera-motion backend.
MotionConfig = Union[GtMotionConfig, FileMotionConfig, MonoMotionConfig]


def motion_params(cfg: Any) -> MotionConfig:
    """The settings of a ``motion`` config node (or dict) as its backend's dataclass (:data:`MOTION_SCHEMAS`);
    a dataclass given is returned as it is."""
    if not isinstance(cfg, FileMotionConfig) and hasattr(cfg, "get") and cfg.get("name") == "file" \
            and is_unset(cfg, "path"):
        raise InputError("motion.path: motion=file needs a poses file (motion.path=PATH)")
    return option_params(MOTION_SCHEMAS, cfg, "motion")


class MotionTrack:
    """Steadies the metric scale and the road normal of monocular ego-motion over a sequence.

    Scale: the state is the log speed ``log(|t| / dt)`` (dt seconds between the frames,
    ``info.dt``; 1 per pair when unknown) with its variance. Per pair: predict (constant velocity,
    variance grows by ``(speed_process_std dt)^2``), gate the new measurement, update. Only the
    length of ``t`` changes (direction and rotation are the pair's own: with a driving camera's parallax
    they are already steady).

    Road normal (the plane the ground stixels lie on, ``ground_normal``): the filtered normal of the
    pair's earlier frame, turned into the current camera (``n_cur = R^T n_prev``), is the prediction
    (variance grows by ``normal_process_std_deg^2 dt``); the pair's fit updates it (isotropic, in
    radians on the unit sphere). One fit's error moves far ground by ``z / h`` times the angle (0.3
    degrees: 6 % at 20 m), so the filter steadies the ground's depth from frame to frame.

    Pairs continue the track when they come from the same ``info.sequence`` in time order: this
    pair's current frame after the last one, its earlier frame not after it (a keyframe pair may reach
    back several frames); anything else (another sequence, a jump, a degenerate or failed pair)
    restarts the track.

    Args:
        params: the prior's parameters.
    """

    def __init__(self, params: MotionTrackParams | None = None) -> None:
        self.params = params or MotionTrackParams()
        self._key: tuple | None = None
        self._x = 0.0  # log speed
        self._var = math.inf
        self._rejected: float | None = None  # log speed of the last pair, where it contradicted the track
        self._confirmed = False  # two pairs' measured scales agreed since the track (re)started
        self._normals: dict[Any, tuple[torch.Tensor, float]] = {}  # frame -> (filtered normal, variance rad^2)
        self._held_s = 0.0  # seconds since the last pair with a measured scale
        # The direction of travel's elevation over the ground (radians) of the sequence's recent pairs: its
        # scatter is how far one pair's plane of travel may be tilted. Kept through the speed's restarts.
        self._elevations: list[float] = []
        self._elev_seq: Any = None

    def reset(self) -> None:
        self._key, self._x, self._var = None, 0.0, math.inf
        self._rejected = None
        self._confirmed = False
        self._normals = {}
        self._held_s = 0.0

    def update(self, pair: FramePair, est: MotionEstimate) -> MotionEstimate:
        """The estimate of ``pair`` with its scale and road normal filtered by the sequence so far (and the
        state advanced); its ``scale_std`` is the relative uncertainty of the length it reports."""
        prm = self.params
        info = pair.info
        seq, cur, prev = info.sequence, info.frame, info.frame_prev
        est = self._scene_at_its_distance(pair, est)
        consecutive = (seq is not None and cur is not None and prev is not None and self._key is not None
                       and self._key[0] == seq and prev <= self._key[1] < cur and math.isfinite(self._var))
        dt = float(info.dt or 1.0)
        if est.kind == MotionKind.SCALE_UNKNOWN and est.unit_motion is not None and consecutive and self._confirmed:
            # Only a confirmed track lends its speed: one pair's length, never corroborated, may be the
            # error (a highway's first pair said 4 m/s at 27 m/s, and was held over 16 pairs).
            if self._held_s + dt <= prm.scale_hold_s:
                return self._hold(est, cur, prev, dt)
        if est.motion is None or est.degenerate or seq is None or cur is None:
            self.reset()
            return est
        norm = float(est.motion.t.norm())
        if norm <= 0:
            self.reset()
            return est
        est = self._filter_normal(est, cur, prev if consecutive else None, dt)
        self._held_s = 0.0
        z = math.log(norm / dt)
        # The pair's own uncertainty where it has one (the road and the scene model disagreeing: larger).
        r = max(prm.scale_meas_std, est.scale_std or 0.0) ** 2
        self._key = (seq, cur)
        if not consecutive:
            self._x, self._var, self._rejected, self._confirmed = z, r, None, False
            return dataclasses.replace(est, scale_std=math.sqrt(r))
        x_pred = self._x
        p_pred = self._var + (prm.speed_process_std * dt) ** 2
        innov = z - x_pred
        s = p_pred + r
        last, self._rejected = self._rejected, None
        if abs(innov) > prm.scale_gate * math.sqrt(s):
            # The pair contradicts the track. Its uncertainty is the disagreement: the frames say two things,
            # and until a later pair tells which, its movers and warnings fail safe (max_scale_std).
            std = abs(innov)
            if not self._confirmed or (last is not None and abs(z - last) <= prm.scale_gate * math.sqrt(
                    2 * r + (prm.speed_process_std * dt) ** 2)):
                # A track of one pair has no more support than this pair; two contradicting pairs that agree
                # with each other: the track was off, not the pairs. The track restarts at this pair, and
                # this pair's own length stands (no value the current frame contradicts is held).
                self._x, self._var, self._confirmed = z, r, False
                note = (f"sequence prior: scale {norm:.3f} m is {innov * 100:+.0f} % from the constant-velocity "
                        f"prediction of an {'unconfirmed' if last is None else 'outvoted'} track: the speed restarts "
                        f"at it (uncertain: {std:.2f})")
            else:
                # One pair against a confirmed track: the prediction stands (its variance grows), marked uncertain.
                self._x, self._var, self._rejected = x_pred, p_pred, z
                note = (f"sequence prior: scale {norm:.3f} m is {innov * 100:+.0f} % from the constant-velocity "
                        f"prediction, replaced by {math.exp(x_pred) * dt:.3f} m (uncertain: {std:.2f})")
                # The length is the sequence's now, not the pair's own measurement.
                est = dataclasses.replace(est, scale_from=ScaleFrom.SEQUENCE)
        else:
            k = p_pred / s
            self._x, self._var = x_pred + k * innov, (1 - k) * p_pred
            self._confirmed = True
            std = math.sqrt(self._var)
            note = f"sequence prior: scale {norm:.3f} -> {math.exp(self._x) * dt:.3f} m"
        t_new = est.motion.t * (math.exp(self._x) * dt / norm)
        logger.debug("%s: %s", pair.name, note)
        return dataclasses.replace(est, motion=Motion(est.motion.R, t_new), reason=f"{est.reason}; {note}",
                                   scale_std=std)

    def direction_scatter(self) -> float:
        """How far (radians, one standard deviation) one pair's direction of travel scatters in elevation: the
        RMS change between the last :data:`ELEVATION_WINDOW` pairs over sqrt(2), or :data:`DIRECTION_PRIOR_STD`
        before there are three of them."""
        e = self._elevations
        if len(e) < 3:
            return DIRECTION_PRIOR_STD
        d = [b - a for a, b in zip(e, e[1:])]
        return math.sqrt(sum(x * x for x in d) / (2 * len(d)))

    def _scene_at_its_distance(self, pair: FramePair, est: MotionEstimate) -> MotionEstimate:
        """Records the pair's direction of travel, and gives a length from the scene model the uncertainty of
        the plane of travel's tilt at its contacts' distance (``scene_reach``). Past ``max_scale_std`` the
        pair's length is unknown (``scale_unknown``): a sequence's held speed, or none, takes its place."""
        moving = est.motion if est.motion is not None and not est.degenerate else est.unit_motion
        n = pair.camera.ground_normal
        if moving is not None and n is not None and float(moving.t.norm()) > 0:
            seq = pair.info.sequence
            if seq != self._elev_seq or seq is None:
                self._elevations, self._elev_seq = [], seq
            t = moving.t.double()
            elev = math.asin(max(-1.0, min(1.0, float(t @ n.double()) / float(t.norm()))))
            self._elevations = [*self._elevations, elev][-ELEVATION_WINDOW:]
        if est.scale_from != ScaleFrom.SCENE or est.scene_reach is None or est.motion is None:
            return est
        scatter = self.direction_scatter()
        std = math.hypot(est.scale_std or 0.0, scatter * est.scene_reach)
        note = (f"the scene model's length at {est.scene_reach:.0f} camera heights, the direction of travel "
                f"scattering {math.degrees(scatter):.2f} deg: uncertain by {std:.2f}")
        if std <= self.params.max_scale_std:
            return dataclasses.replace(est, scale_std=std, reason=f"{est.reason}; {note}")
        R, t = est.motion.R, est.motion.t
        return dataclasses.replace(est, motion=None, kind=MotionKind.SCALE_UNKNOWN, unit_motion=Motion(R, t / t.norm()),
                                   scale_from=None, scale_std=None, scene_reach=None,
                                   reason=f"{est.reason}; {note} (> {self.params.max_scale_std}): no metric length")

    def _hold(self, est: MotionEstimate, cur: Any, prev: Any, dt: float) -> MotionEstimate:
        """A ``scale_unknown`` pair made metric by the filtered speed (predicted, not updated: its variance
        grows, and so does the ``scale_std`` reported) and, where the earlier frame has one, the filtered
        road normal turned into this camera."""
        prm = self.params
        self._var += (prm.speed_process_std * dt) ** 2
        self._held_s += dt
        self._key = (self._key[0], cur)
        self._rejected = None
        R, t_unit = est.unit_motion.R, est.unit_motion.t
        length = math.exp(self._x) * dt
        normal = None
        old = self._normals.get(prev)
        if old is not None:
            n = R.double().T @ old[0]
            normal = n / n.norm()
            var = old[1] + math.radians(prm.normal_process_std_deg) ** 2 * dt
            self._normals = {f: v for f, v in self._normals.items() if f >= prev} | {cur: (normal, var)}
        note = (f"scale from the sequence: {length:.3f} m ({math.exp(self._x):.1f} m/s, "
                f"{self._held_s:.2f} s since the last measured scale)")
        logger.debug("%s", note)
        return dataclasses.replace(est, motion=Motion(R, t_unit / t_unit.norm() * length), kind=MotionKind.METRIC,
                                   scale_from=ScaleFrom.SEQUENCE, ground_normal=normal, reason=f"{est.reason}; {note}",
                                   scale_std=math.sqrt(self._var))

    def _filter_normal(self, est: MotionEstimate, cur: Any, prev: Any, dt: float) -> MotionEstimate:
        """``est`` with its road normal fused with the one of frame ``prev`` (None: restart)."""
        prm = self.params
        n_m = est.ground_normal
        if n_m is None or prm.normal_gate_deg <= 0:
            return est
        n_m = n_m.double() / n_m.double().norm()
        r = math.radians(prm.normal_meas_std_deg) ** 2
        old = self._normals.get(prev) if prev is not None else None
        if old is None:
            self._normals = {cur: (n_m, r)}
            return est
        n_prev, var = old
        n_pred = est.motion.R.double().T @ n_prev  # a direction in the earlier camera, seen from the current one
        var_pred = var + math.radians(prm.normal_process_std_deg) ** 2 * dt
        innov = math.acos(max(-1.0, min(1.0, float(n_pred @ n_m))))
        if innov > math.radians(prm.normal_gate_deg) + 3.0 * math.sqrt(var_pred + r):
            n_new, var_new = n_pred, var_pred
        else:
            k = var_pred / (var_pred + r)
            n_new = n_pred + k * (n_m - n_pred)
            n_new, var_new = n_new / n_new.norm(), (1.0 - k) * var_pred
        # Kept: the frames from this pair's earlier frame on. A keyframe pair reaching back past them (pairs
        # (3, 1), (4, 2), ...) starts the normal again at its own fit, which matches its own scale (the two
        # trade off in the photometric search); a filtered normal would not match it (docs/experiments.md,
        # "Ego-motion").
        self._normals = {f: v for f, v in self._normals.items() if f >= prev} | {cur: (n_new, var_new)}
        return dataclasses.replace(est, ground_normal=n_new.to(est.ground_normal.dtype))
