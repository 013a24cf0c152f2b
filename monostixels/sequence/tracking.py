"""Stixel tracks: association, a Kalman filter per track, velocities and time-to-collision.

A track follows one stixel (ground or object) from frame to frame, after the stixel literature
(Pfeiffer & Franke 2011). An object track's state is the stixel's position and velocity on the
ground plane of the world (the first camera of the sequence, docs/conventions.md, section 2:
x right, y down, z forward): ``x = (X, Z, V_X, V_Z)`` metres and m/s, a constant-velocity model
driven by white acceleration. A ground track filters the distance of its plane (the camera's height
above the road under it).

Per frame, for the pair (current ``t``, earlier ``k``):

1. **Association.** Every track's point, predicted by its own velocity and seen from the current
   camera through the chained camera motion, lands in a stixel of frame ``t``: the track is a
   candidate there. Where the flow to the last frame is known, so are the tracks of the last frame's
   stixels that a stixel's pixels land in through it (``overlap_min_share`` of them at least). A
   stixel continues a candidate of its kind whose prediction passes the chi-square gate on position
   and velocity (several: the nearest). A mover's stixel linked through the flow to its track whose
   one-pair velocity alone fails continues it on its position (once, ``coast_min_age``). Stixels
   without a track start one.
2. **Measurement.** Position: the stixel's plane at its column centre and middle row, in the world
   (along-ray standard deviation ``depth_std_rel`` of the distance, across the ray half a column).
   Velocity: a dynamic stixel's metric motion over the pair's interval, the median over its object
   (adjacent dynamic stixels at a similar depth) and, for a tracked one, recomputed at the track's
   depth (the flow fixes ``g = p (t - R Δ)``, not ``Δ``); a static stixel is a measurement of zero
   velocity: the solver found a static plane to explain its flow.
3. **Output.** The filtered point, moved along the stixel's own ray, gives its depth (the plane
   through it, same normal); the filtered velocity its world velocity.

Time to collision: each track filters the closing rate ``-v_rel,z / Z`` (a scalar filter with a chi-square
gate on each pair's rate); the time to collision and the warnings: :mod:`monostixels.sequence.ttc`.

Everything is vectorised over stixels and tracks (no Python loop over either).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

from monostixels._checks import InputError
from monostixels.core.classes import DYNAMIC_OBJECT, GROUND, STATIC_OBJECT
from monostixels.core.geometry import Motion, pixel_rays, stixel_motion
from monostixels.core.stixels import StixelWorld, neighbours, segment_lower_median


__all__ = ["TrackParams", "TrackState", "Tracks", "stixel_points"]


#: Chi-square quantile of 4 degrees of freedom at 99.9 %: the association gate on position and velocity.
_CHI2_4DOF_999 = 18.47


#: The same of 2 degrees of freedom: the gate on position alone.
_CHI2_2DOF_999 = 13.82


@dataclass
class TrackParams:
    """Settings of the stixel tracks: the schema of the config group ``temporal`` (monostixels.config_schema).

    Attributes:
        enabled: track (False: every frame on its own; velocities and TTC from the pair alone).
        accel_std_mps2: white-acceleration noise of the constant-velocity model (m/s^2).
        depth_std_rel: along-ray standard deviation of a stixel's distance, relative (mono-stixels'
            mean relative depth error on real streets).
        depth_std_min_m: its floor (metres).
        velocity_std_mps, velocity_std_rel: standard deviation of a dynamic stixel's velocity from one pair.
        static_velocity_std_mps: standard deviation of the zero velocity a static stixel stands for.
        max_age_frames: a track not seen for more frames than this is dropped.
        group_depth_ratio: dynamic stixels of one object (adjacent columns, overlapping rows, depths
            within this relative difference) share the median of their motions as the velocity
            measurement; 0 = every stixel on its own.
        eta_std_rel, eta_std_abs: error (std) of one pair's closing rate ``-v_rel,z / Z``: relative, and
            absolute (1/s), for a pair ``eta_interval_s`` apart.
        eta_interval_s: the pair interval (seconds) ``eta_std_*`` hold for; a pair ``dt`` apart has
            ``eta_interval_s / dt`` times that error (its rate is a displacement over ``dt``).
        eta_gate: chi-square bound (1 degree of freedom) on a pair's closing rate against its track's
            prediction: a rate beyond it leaves the prediction standing, a second one in a row restarts the
            track's rate at the measurement; 0 = no gate.
        eta_process_std: random walk of the closing rate beyond constant relative velocity (1/s per
            square-root second: braking, turning).
        ground_height_std_rel: error (std) of one pair's road height under a ground stixel, relative to
            the camera height (the flow fits each ground stixel's plane).
        ground_height_process_std: random walk of the road height along a track (metres per
            square-root second: slopes, kerbs passing under the column).
        overlap_min_share: where the flow to the last tracked frame is given, a stixel may also continue
            the track of any last-frame stixel of its kind that at least this share of its pixels map
            into through the flow; 0 = off (the tracks' predicted points alone).
        coast_min_age: a dynamic stixel linked through the flow to a mover's track that has continued at
            least this many frames, whose velocity fails the gate where its position passes, continues
            the track on its position alone (the track's velocity stands, once; a second such frame in a
            row starts a new track); 0 = off.
    """

    enabled: bool = True
    accel_std_mps2: float = 2.0
    depth_std_rel: float = 0.08
    depth_std_min_m: float = 0.2
    velocity_std_mps: float = 0.3
    velocity_std_rel: float = 0.05
    static_velocity_std_mps: float = 0.3
    max_age_frames: int = 5
    group_depth_ratio: float = 0.25
    eta_std_rel: float = 0.05
    eta_std_abs: float = 0.01
    eta_process_std: float = 0.05
    eta_interval_s: float = 0.2
    eta_gate: float = 3.84
    ground_height_std_rel: float = 0.03
    ground_height_process_std: float = 0.1
    overlap_min_share: float = 0.3
    coast_min_age: int = 2

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "enabled":
                if not isinstance(v, bool):
                    raise InputError(f"temporal.enabled: true or false, got {v!r}")
                continue
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)):
                raise InputError(f"temporal.{f.name}: a finite number, got {v!r}")
        for k in ("accel_std_mps2", "depth_std_rel", "depth_std_min_m", "velocity_std_mps", "static_velocity_std_mps",
                  "eta_std_abs", "eta_process_std", "eta_interval_s", "ground_height_std_rel", "ground_height_process_std"):
            if getattr(self, k) <= 0:
                raise InputError(f"temporal.{k}: must be > 0, got {getattr(self, k)}")
        for k in ("velocity_std_rel", "eta_std_rel", "eta_gate", "overlap_min_share"):
            if getattr(self, k) < 0:
                raise InputError(f"temporal.{k}: must be >= 0, got {getattr(self, k)}")
        if not (isinstance(self.coast_min_age, int) and self.coast_min_age >= 0):
            raise InputError(f"temporal.coast_min_age: an integer >= 0 (0 = off), got {self.coast_min_age!r}")
        if not (isinstance(self.max_age_frames, int) and self.max_age_frames >= 1):
            raise InputError(f"temporal.max_age_frames: an integer >= 1, got {self.max_age_frames!r}")
        if self.overlap_min_share > 1:
            raise InputError(f"temporal.overlap_min_share: a share in [0, 1], got {self.overlap_min_share}")
        if self.group_depth_ratio < 0:
            raise InputError(f"temporal.group_depth_ratio: must be >= 0 (0 = off), got {self.group_depth_ratio}")


def object_groups(world: StixelWorld, depth_ratio: float) -> torch.Tensor:
    """Objects (N,) int64: the label of the group of each dynamic stixel (-1 for the others).

    A group is a connected set of dynamic stixels in adjacent columns whose rows overlap and whose
    depths differ by at most ``depth_ratio`` (relative): the stixels of one mover, not a car and the
    car behind it.
    """
    N = len(world)
    label = torch.full((N,), -1, dtype=torch.long)
    dyn = torch.nonzero(world.type == DYNAMIC_OBJECT).squeeze(1)
    if dyn.numel() == 0:
        return label
    col, top, bot = world.column[dyn], world.v_top[dyn], world.v_bottom[dyn]
    d = world.depth.double()[dyn]
    a, b = torch.meshgrid(torch.arange(dyn.numel()), torch.arange(dyn.numel()), indexing="ij")
    # Each pair once (a's column left of b's): the labels spread along an edge both ways.
    edge = (neighbours(col, top, bot) & (col[b] > col[a])
            & ((d[a] / d[b] - 1).abs() <= depth_ratio) & ((d[b] / d[a] - 1).abs() <= depth_ratio))
    ea, eb = a[edge], b[edge]
    lab = torch.arange(dyn.numel())
    while ea.numel():  # min-label propagation until every edge joins equal labels
        m = torch.minimum(lab[ea], lab[eb])
        new = lab.scatter_reduce(0, ea, m, reduce="amin").scatter_reduce(0, eb, m, reduce="amin")
        new = new[new]  # pointer jumping
        if torch.equal(new, lab):
            break
        lab = new
    label[dyn] = lab
    return label


def _group_median(values: torch.Tensor, label: torch.Tensor) -> torch.Tensor:
    """Per row of ``values`` (N, k) the component-wise lower median over the rows of its group (label >= 0)."""
    out = values.clone()
    rows = torch.nonzero(label >= 0).squeeze(1)
    if rows.numel() == 0:
        return out
    lab = label[rows]
    order = torch.argsort(lab, stable=True)
    lab_s, rows_s = lab[order], rows[order]
    _, counts = torch.unique_consecutive(lab_s, return_counts=True)
    seg = torch.repeat_interleave(torch.arange(counts.numel()), counts)
    for k in range(values.shape[1]):
        out[rows_s, k] = torch.repeat_interleave(segment_lower_median(values[rows_s, k], seg, counts), counts)
    return out


def stixel_points(world: StixelWorld) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A point of every stixel: its plane at the column centre and middle row, in camera coordinates.

    Returns:
        X (N, 3) metres (sky: NaN), the column centre ``u`` (N,) and the row ``v`` (N,) pixels.
    """
    K = world.K.double()
    W = world.image_size[1]
    u0 = world.column.double() * world.column_width
    u = (u0 + torch.clamp(u0 + world.column_width, max=W) - 1) / 2
    v = (world.v_top + world.v_bottom).double() / 2
    ray = pixel_rays(K, u, v)
    n = world.normals()
    p = world.inverse_depth.double()
    X = ray / (p * (ray * n).sum(-1))[:, None]
    return torch.where((p > 0)[:, None], X, torch.full_like(X, math.nan)), u, v


@dataclass
class TrackState:
    """The tracks' state: one row per track (``T`` rows) in every field.

    ``x`` (T, 4) X, Z, V_X, V_Z (world, m and m/s) and ``P`` (T, 4, 4) its covariance; ``ids`` (T,); ``time``
    (T,) seconds and ``last_frame`` (T,) frame number of the last update; ``measured`` (T,) position measured
    with a baseline; ``y`` (T,) world height of the tracked point (m); ``kind`` (T,) 0 object, 1 ground; ``gy``
    (T,) a ground track's plane distance (m) and ``gy_var`` its variance; ``eta`` (T,) closing rate -v_rel,z / Z
    (1/s), ``eta_var`` its variance and ``eta_rejected`` the last pair's rate failed the gate; ``stixel`` (T,)
    the track's stixel in the frame of its last update; ``age`` (T,) frames continued; ``dynamic`` (T,) its
    last stixel was dynamic; ``coasted`` (T,) its last update was on the position alone.
    """

    x: torch.Tensor
    P: torch.Tensor
    ids: torch.Tensor
    time: torch.Tensor
    last_frame: torch.Tensor
    measured: torch.Tensor
    y: torch.Tensor
    kind: torch.Tensor
    gy: torch.Tensor
    gy_var: torch.Tensor
    eta: torch.Tensor
    eta_var: torch.Tensor
    eta_rejected: torch.Tensor
    stixel: torch.Tensor
    age: torch.Tensor
    dynamic: torch.Tensor
    coasted: torch.Tensor

    @staticmethod
    def empty() -> "TrackState":
        """No track: every field with zero rows, in its dtype and row shape."""
        f64, i64, b = torch.float64, torch.long, torch.bool
        dtypes = {"x": (f64, (4,)), "P": (f64, (4, 4)), "ids": (i64, ()), "time": (f64, ()), "last_frame": (i64, ()),
                  "measured": (b, ()), "y": (f64, ()), "kind": (i64, ()), "gy": (f64, ()), "gy_var": (f64, ()),
                  "eta": (f64, ()), "eta_var": (f64, ()), "eta_rejected": (b, ()), "stixel": (i64, ()),
                  "age": (i64, ()), "dynamic": (b, ()), "coasted": (b, ())}
        return TrackState(**{k: torch.zeros((0, *shape), dtype=dt) for k, (dt, shape) in dtypes.items()})

    def __len__(self) -> int:
        return self.ids.numel()

    def take(self, rows: torch.Tensor) -> "TrackState":
        """The tracks ``rows`` (a (T,) bool mask or indices), every field alike."""
        return TrackState(**{f.name: getattr(self, f.name)[rows] for f in fields(self)})

    def extend(self, new: "TrackState") -> "TrackState":
        """These tracks followed by ``new``'s."""
        return TrackState(**{f.name: torch.cat([getattr(self, f.name), getattr(new, f.name)]) for f in fields(self)})


class Tracks:
    """The tracks of one sequence (see the module docstring).

    Args:
        params: track settings.
    """

    def __init__(self, params: TrackParams) -> None:
        self.params = params
        self.state = TrackState.empty()
        self.next_id = 0
        self.prev_frame: int | None = None                   # the frame of the last update
        self.prev_index: torch.Tensor | None = None          # (H, W) its stixel index map (-1: none)

    def __len__(self) -> int:
        """Live tracks."""
        return len(self.state)

    # ------------------------------------------------------------------ model
    def _predict(self, rows: torch.Tensor, time: float) -> tuple[torch.Tensor, torch.Tensor]:
        """State (n, 4) and covariance (n, 4, 4) of tracks ``rows`` predicted to ``time`` (seconds)."""
        dt = (time - self.state.time[rows]).clamp_min(0.0)
        n = rows.numel()
        F = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
        F[:, 0, 2] = dt
        F[:, 1, 3] = dt
        q = self.params.accel_std_mps2 ** 2
        Q = torch.zeros(n, 4, 4, dtype=torch.float64)
        for a, b in ((0, 2), (1, 3)):
            Q[:, a, a] = q * dt**4 / 4
            Q[:, a, b] = Q[:, b, a] = q * dt**3 / 2
            Q[:, b, b] = q * dt**2
        x = (F @ self.state.x[rows, :, None])[..., 0]
        P = F @ self.state.P[rows] @ F.transpose(1, 2) + Q
        return x, P

    def _measurement(self, pos: torch.Tensor, vel: torch.Tensor, dyn: torch.Tensor, cam: torch.Tensor,
                     lateral_std: torch.Tensor) -> torch.Tensor:
        """Covariance (n, 4, 4) of a measurement of a stixel at ``pos`` (n, 2) moving at ``vel`` (n, 2) (world x, z)."""
        prm = self.params
        rel = pos - cam[None]
        dist = rel.norm(dim=1).clamp_min(1e-6)
        along = torch.clamp(prm.depth_std_rel * dist, min=prm.depth_std_min_m)
        d = rel / dist[:, None]
        e = torch.stack([-d[:, 1], d[:, 0]], 1)
        Rp = along[:, None, None] ** 2 * d[:, :, None] * d[:, None, :] + lateral_std[:, None, None] ** 2 * e[:, :, None] * e[:, None, :]
        sv = torch.where(dyn, prm.velocity_std_mps + prm.velocity_std_rel * vel.norm(dim=1),
                         torch.full_like(dist, prm.static_velocity_std_mps))
        R = torch.zeros(pos.shape[0], 4, 4, dtype=torch.float64)
        R[:, :2, :2] = Rp
        R[:, 2, 2] = R[:, 3, 3] = sv**2
        return R

    # ------------------------------------------------------------------ one frame
    def update(self, world: StixelWorld, *, frame: int, time: float, pose: torch.Tensor, dt_pair: float,
               degenerate: bool, camera_velocity: torch.Tensor | None = None,
               motion: Motion | None = None, flow_to_last: torch.Tensor | None = None,
               flow_reaches: int | None = None) -> dict[str, torch.Tensor]:
        """Associate, filter and report the tracks of one frame.

        Args:
            world: the frame's stixels (``motion`` (N, 3): ``Δ`` of dynamic stixels over the pair, current axes).
            frame: the frame's number in its sequence. time: its time (seconds).
            pose: (4, 4) camera-to-world of the frame.
            dt_pair: seconds between the pair's frames.
            degenerate: the pair had no baseline: static depths are the scene model's, not a measurement.
            camera_velocity: (3,) the camera's velocity over the pair in its current axes (m/s), for the
                closing rates; None = standing.
            motion: the pair's camera motion (``X_prev = R X_cur + t``): tracked movers' motions are then
                recomputed at their tracks' depths; None = the solver's.
            flow_to_last: (2, H, W) flow from this frame to frame ``flow_reaches`` (pixels, ``x_there = x +
                flow``); where that is the last updated frame, its stixels seen through the flow are
                candidates of the association too (``overlap_min_share``). None: the predicted points alone.

        Returns:
            ``track_id`` (N,) int64 (-1: sky), ``position`` (N, 3) filtered world position (NaN where
            untracked), ``point_cam`` (N, 3) the filtered point on the stixel's ray in the current camera, ``velocity`` (N, 3) world m/s, ``carried`` (N,) bool: a static stixel of a frame
            without baseline whose depth comes from its track, ``ttc`` (N,) seconds from the filtered
            closing rate (inf: not closing; ground and sky inf).
        """
        prm = self.params
        N = len(world)
        dtype = torch.float64
        Rwc, o = pose[:3, :3].to(dtype), pose[:3, 3].to(dtype)
        X_cam, u, v = stixel_points(world)
        X_w = X_cam @ Rwc.T + o
        # Ground stixels are tracked too (static; their plane's height comes from the flow, and so does
        # its frame-to-frame noise); objects continue object tracks, ground ground tracks.
        obj = ((world.type == STATIC_OBJECT) | (world.type == DYNAMIC_OBJECT) | (world.type == GROUND)) \
            & torch.isfinite(X_w).all(1)
        kind = (world.type == GROUND).long()
        dyn = world.type == DYNAMIC_OBJECT
        vel_meas = torch.where(dyn[:, None], world.motion.to(dtype) @ Rwc.T / max(dt_pair, 1e-6),
                               torch.zeros(N, 3, dtype=dtype))
        # Closing rate eta = -v_rel,z / Z (1/s) of this pair alone: depth and speeds share the monocular
        # scale, so their ratio does not (TTC = 1 / eta is scale-free; the paper's "time to contact").
        # Each stixel's own motion over its own depth: the object's median velocity below would divide
        # one stixel's scale error by another's depth.
        v_cam = torch.zeros(3, dtype=dtype) if camera_velocity is None else camera_velocity.to(dtype)
        eta_meas = -(vel_meas @ Rwc - v_cam[None])[:, 2] / X_cam[:, 2].clamp_min(1e-3)
        if prm.group_depth_ratio > 0:
            # One mover's stixels share its motion: the median over the object is the measurement of each
            # (one stixel's motion is one column's flow, the object's median is steadier).
            vel_meas = _group_median(vel_meas, object_groups(world, prm.group_depth_ratio))
        fx = float(world.K[0, 0])
        lateral_std = X_cam[:, 2].abs() * (world.column_width / fx) / 2 + 0.05

        # --- association: the tracks' predicted points, seen from this camera
        parent = torch.full((N,), -1, dtype=torch.long)  # row of the track a stixel continues
        position_only = torch.zeros(N, dtype=torch.bool)  # continues it on its position alone
        index = world.index_map()
        if self.state.ids.numel() and bool(obj.any()):
            overlap = None
            if (flow_to_last is not None and flow_reaches is not None and flow_reaches == self.prev_frame
                    and prm.overlap_min_share > 0):
                overlap = self._overlap(world, index, obj, kind, flow_to_last)
            parent, position_only = self._associate(world, index, obj, kind, time, Rwc, o, X_w, lateral_std, dyn,
                                                    vel_meas, degenerate, overlap)
        keeps_id = parent >= 0
        rows_all = torch.nonzero(obj).squeeze(1)
        out_id = torch.full((N,), -1, dtype=torch.long)
        out_pos = torch.full((N, 3), math.nan, dtype=dtype)
        out_vel = torch.zeros(N, 3, dtype=dtype)
        carried = torch.zeros(N, dtype=torch.bool)
        if rows_all.numel() == 0:
            self._drop_old(frame)
            self.prev_frame, self.prev_index = frame, index
            return {"track_id": out_id, "position": out_pos, "velocity": out_vel, "carried": carried,
                    "age": torch.zeros(N, dtype=torch.long)}

        n = rows_all.numel()
        pos = X_w[rows_all][:, [0, 2]]
        z = torch.cat([pos, vel_meas[rows_all][:, [0, 2]]], 1)
        c = parent[rows_all]
        keeps = keeps_id[rows_all]
        has = c >= 0
        x_pred = z.clone()  # a new track starts at its measurement
        P_pred = torch.zeros(n, 4, 4, dtype=dtype)
        prior_measured = torch.zeros(n, dtype=torch.bool)
        if bool(has.any()):
            x_pred[has], P_pred[has] = self._predict(c[has], time)
            prior_measured[has] = self.state.measured[c[has]]
            if motion is not None and bool((has & dyn[rows_all]).any()):
                # A mover's flow fixes g = p (t - R Δ), not Δ: with its track's depth instead of this
                # pair's ground contact, Δ = R^T (t - g / p) loses most of the contact's error.
                vel_meas = self._velocity_at_track_depth(world, rows_all, has, x_pred, X_cam, Rwc, o, motion,
                                                         dt_pair, vel_meas)
                z[:, 2:] = vel_meas[rows_all][:, [0, 2]]
        # Noise scaled by the prediction, not by the measurement: a measurement-scaled noise would give
        # the too-far and too-fast readings less weight and bias the filter low.
        Rm = self._measurement(x_pred[:, :2], x_pred[:, 2:], dyn[rows_all], o[[0, 2]], lateral_std[rows_all])
        P_pred[~has] = Rm[~has]
        coast = position_only[rows_all] & has
        Rm[coast, 2, 2] = Rm[coast, 3, 3] = 1e12  # the velocity measured is not used: the track's stands
        keeps &= has
        # Without a baseline a static stixel's depth is the scene model's: where its track was measured
        # with a baseline before, the track's prediction stands (carried into the output).
        hold = has & prior_measured & ~dyn[rows_all] if degenerate else torch.zeros_like(has)
        x_new, P_new = x_pred.clone(), P_pred.clone()
        upd = has & ~hold
        if bool(upd.any()):
            Kg = P_pred[upd] @ torch.linalg.inv(P_pred[upd] + Rm[upd])
            x_new[upd] = x_pred[upd] + (Kg @ (z[upd] - x_pred[upd])[:, :, None])[..., 0]
            P_new[upd] = (torch.eye(4, dtype=dtype) - Kg) @ P_pred[upd]
        carried[rows_all[hold]] = True
        # Ground: what is filtered is the stixel plane's distance d = 1/p, the camera's height above the
        # road under it (a scalar, static; it does not change as the camera turns, and is the same
        # wherever on a flat road the stixel's middle row falls as the stixel changes from frame to frame).
        ground = kind[rows_all] == 1
        d_m = 1.0 / world.inverse_depth.double()[rows_all].clamp_min(1e-6)
        r_d = (prm.ground_height_std_rel * d_m) ** 2
        gy, gy_var = d_m.clone(), r_d.clone()
        gh = has & ground
        if bool(gh.any()):
            rows_g = c[gh]
            v_pred = self.state.gy_var[rows_g] + prm.ground_height_process_std ** 2 * (time - self.state.time[rows_g]).clamp_min(0.0)
            k = torch.where(hold[gh], torch.zeros_like(v_pred), v_pred / (v_pred + r_d[gh]))
            gy[gh] = self.state.gy[rows_g] + k * (d_m[gh] - self.state.gy[rows_g])
            gy_var[gh] = (1.0 - k) * v_pred
        x_new[ground], P_new[ground] = z[ground], Rm[ground]

        ids = torch.empty(n, dtype=torch.long)
        ids[keeps] = self.state.ids[c[keeps]]
        n_new = int((~keeps).sum())
        ids[~keeps] = torch.arange(self.next_id, self.next_id + n_new)
        self.next_id += n_new
        measured_now = prior_measured | dyn[rows_all] | (not degenerate)
        eta_new, eta_var_new, eta_rej_new = self._filter_eta(c, has, eta_meas[rows_all], time,
                                                             degenerate & ~dyn[rows_all], dt_pair)

        # Replace the continued tracks, append the new ones (splits included), drop the stale.
        keep = torch.ones(self.state.ids.numel(), dtype=torch.bool)
        keep[c[keeps]] = False
        age_new = torch.zeros(n, dtype=torch.long)
        age_new[keeps] = self.state.age[c[keeps]] + 1
        self.state = self.state.take(keep).extend(TrackState(
            x=x_new, P=P_new, ids=ids, time=torch.full((n,), float(time), dtype=dtype),
            last_frame=torch.full((n,), int(frame), dtype=torch.long), measured=measured_now, y=X_w[rows_all][:, 1],
            kind=kind[rows_all], gy=gy, gy_var=gy_var, eta=eta_new, eta_var=eta_var_new, eta_rejected=eta_rej_new,
            stixel=rows_all, age=age_new, dynamic=dyn[rows_all], coasted=coast))
        self._drop_old(frame)
        self.prev_frame, self.prev_index = frame, index

        out_id[rows_all] = ids
        # The filtered point on the stixel's own ray (it stays in its column): the ray's scale whose
        # horizontal position is nearest the filtered one.
        r_w = X_cam[rows_all] @ Rwc.T
        a = r_w[:, [0, 2]]
        b = x_new[:, :2] - o[[0, 2]]
        lam = (a * b).sum(1) / (a * a).sum(1).clamp_min(1e-12)
        # Ground: where the ray meets the plane at the filtered distance (the measured point is on d_m).
        lam = torch.where(ground, gy / d_m, lam)
        out_cam = torch.full((N, 3), math.nan, dtype=dtype)
        out_cam[rows_all] = lam[:, None] * X_cam[rows_all]
        y = X_w[rows_all][:, 1]
        out_pos[rows_all] = torch.stack([x_new[:, 0], y, x_new[:, 1]], 1)
        out_vel[rows_all] = torch.stack([x_new[:, 2], torch.zeros_like(y), x_new[:, 3]], 1)
        out_ttc = torch.full((N,), math.inf, dtype=dtype)
        out_ttc[rows_all] = torch.where(eta_new > 1e-6, 1.0 / eta_new.clamp_min(1e-6), torch.full_like(eta_new, math.inf))
        out_age = torch.zeros(N, dtype=torch.long)
        out_age[rows_all] = age_new
        return {"track_id": out_id, "position": out_pos, "velocity": out_vel, "carried": carried, "ttc": out_ttc,
                "point_cam": out_cam, "age": out_age}

    def _velocity_at_track_depth(self, world: StixelWorld, rows_all: torch.Tensor, has: torch.Tensor,
                                 x_pred: torch.Tensor, X_cam: torch.Tensor, Rwc: torch.Tensor, o: torch.Tensor,
                                 motion: Motion, dt_pair: float, vel_meas: torch.Tensor) -> torch.Tensor:
        """World velocities (N, 3) with each tracked dynamic stixel's motion recomputed at its predicted depth
        (the object's median again where grouping is on)."""
        dyn = world.type == DYNAMIC_OBJECT
        sel = has & dyn[rows_all]
        rows = rows_all[sel]
        r_w = X_cam[rows] @ Rwc.T
        a, b = r_w[:, [0, 2]], x_pred[sel, :2] - o[[0, 2]]
        lam = ((a * b).sum(1) / (a * a).sum(1).clamp_min(1e-12)).clamp(0.5, 2.0)  # at most a factor 2 off
        n = world.normals()[rows]
        p_track = 1.0 / ((lam[:, None] * X_cam[rows]) * n).sum(1).clamp_min(1e-3)
        delta = stixel_motion(world.tau[rows], p_track, world.ground_normal, motion.R, motion.t)
        out = vel_meas.clone()
        out[rows] = delta @ Rwc.T / max(dt_pair, 1e-6)
        if self.params.group_depth_ratio > 0:
            out = _group_median(torch.where(dyn[:, None], out, torch.zeros_like(out)),
                                object_groups(world, self.params.group_depth_ratio))
        return out

    def _filter_eta(self, parent: torch.Tensor, has: torch.Tensor, eta_meas: torch.Tensor, time: float,
                    hold: torch.Tensor, dt_pair: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Filtered closing rates (n,) 1/s, their variances and whether the measurement was rejected, of the
        stixels continuing tracks ``parent`` (``has``) or starting new ones (at their measurement).

        At constant relative velocity ``d eta / dt = eta^2``: the prediction is ``eta / (1 - eta dt)``
        (its variance scaled by the square of that map's slope), plus a random walk of
        ``eta_process_std`` per square-root second. ``hold``: no measurement (a static stixel without
        baseline), the prediction stands. ``dt_pair``: seconds between the pair's frames.
        """
        prm = self.params
        # One pair's rate is a displacement over its interval: the flow's error spread over a longer
        # interval gives a smaller error in the rate.
        scale = prm.eta_interval_s / max(dt_pair, 1e-3)
        r = ((prm.eta_std_rel * eta_meas.abs() + prm.eta_std_abs) * scale) ** 2
        eta, var = eta_meas.clone(), r.clone()
        rejected = torch.zeros_like(has)
        if bool(has.any()):
            rows = parent[has]
            dt = (time - self.state.time[rows]).clamp_min(0.0)
            e0 = self.state.eta[rows]
            den = (1.0 - e0 * dt).clamp_min(0.2)  # past the predicted contact: no faster than 5x
            e_pred = e0 / den
            v_pred = self.state.eta_var[rows] / den**4 + prm.eta_process_std**2 * dt
            # Noise from the prediction's size (a measurement-scaled noise would favour small rates).
            r_h = ((prm.eta_std_rel * e_pred.abs() + prm.eta_std_abs) * scale) ** 2
            k = v_pred / (v_pred + r_h)
            eta[has] = e_pred + k * (eta_meas[has] - e_pred)
            var[has] = (1.0 - k) * v_pred
            if prm.eta_gate > 0:
                # A rate the prediction cannot explain is a lost flow (a near mover's large displacement, its
                # contact below the image): the prediction stands once; twice in a row, the track's rate is
                # what is wrong and restarts at the measurement (the start's own values above).
                out = (eta_meas[has] - e_pred) ** 2 > prm.eta_gate * (v_pred + r_h)
                coast = out & ~self.state.eta_rejected[rows]
                eta[has] = torch.where(coast, e_pred, torch.where(out, eta_meas[has], eta[has]))
                var[has] = torch.where(coast, v_pred, torch.where(out, r[has], var[has]))
                rejected[has] = coast
            hold_h = hold[has]
            eta[has] = torch.where(hold_h, e_pred, eta[has])
            var[has] = torch.where(hold_h, v_pred, var[has])
            rejected[has] &= ~hold_h
        return eta, var, rejected

    def _drop_old(self, frame: int) -> None:
        keep = (frame - self.state.last_frame) <= self.params.max_age_frames
        if not bool(keep.all()):
            self.state = self.state.take(keep)

    def _overlap(self, world: StixelWorld, index: torch.Tensor, obj: torch.Tensor, kind: torch.Tensor,
                 flow: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Candidate pairs (track rows (n,), stixels (n,)) from the flow to the last updated frame.

        ``index``: (H, W) this frame's stixel index map. Every second pixel of every second row of a
        stixel of this frame is followed through ``flow`` (2, H, W) into the last frame; the track of the
        last-frame stixel it lands in (of the same kind) is a candidate where at least
        ``overlap_min_share`` of the stixel's followed pixels land in it.
        A track's single predicted point misses a stixel whose rows and columns change as a mover nears
        or turns; its pixels, seen through the flow, do not.
        """
        if self.prev_index is None or tuple(self.prev_index.shape) != tuple(world.image_size) \
                or tuple(flow.shape[-2:]) != tuple(world.image_size):
            return None
        H, W = world.image_size
        last = torch.nonzero(self.state.last_frame == self.prev_frame).squeeze(1)
        n_prev = int(self.prev_index.max()) + 1
        if last.numel() == 0 or n_prev <= 0:
            return None
        row_of = torch.full((n_prev,), -1, dtype=torch.long)
        ok_rows = self.state.stixel[last] < n_prev
        row_of[self.state.stixel[last[ok_rows]]] = last[ok_rows]
        # Every second pixel of every second row, row-major: strided views instead of gathers.
        vv, uu = torch.meshgrid(torch.arange(0, H, 2), torch.arange(0, W, 2), indexing="ij")
        vv, uu = vv.reshape(-1), uu.reshape(-1)
        s_idx = index[::2, ::2].reshape(-1)
        f = flow[:, ::2, ::2].reshape(2, -1).double()
        u2 = (uu + f[0]).round()
        v2 = (vv + f[1]).round()
        valid = (s_idx >= 0) & torch.isfinite(u2) & torch.isfinite(v2)
        valid &= (u2 >= 0) & (u2 < W) & (v2 >= 0) & (v2 < H)
        s_idx = s_idx.clamp_min(0)
        valid &= obj[s_idx]
        total = torch.bincount(s_idx[valid], minlength=len(world))
        j = torch.full_like(s_idx, -1)
        j[valid] = self.prev_index[v2[valid].long(), u2[valid].long()]
        r = torch.where(j >= 0, row_of[j.clamp_min(0)], torch.full_like(j, -1))
        hit = valid & (r >= 0) & (self.state.kind[r.clamp_min(0)] == kind[s_idx])
        if not bool(hit.any()):
            return None
        T = self.state.ids.numel()
        key, count = torch.unique(s_idx[hit] * T + r[hit], return_counts=True)
        s_u, r_u = key // T, key % T
        keep = count.double() >= self.params.overlap_min_share * total[s_u].double()
        return r_u[keep], s_u[keep]

    def _associate(self, world: StixelWorld, index: torch.Tensor, obj: torch.Tensor, kind: torch.Tensor, time: float,
                   Rwc: torch.Tensor, o: torch.Tensor,
                   X_w: torch.Tensor, lateral_std: torch.Tensor, dyn: torch.Tensor, vel_meas: torch.Tensor,
                   degenerate: bool, overlap: tuple[torch.Tensor, torch.Tensor] | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor]:
        """Row (N,) of the track each stixel continues (-1: none), and whether (N,) on its position alone.

        Every track's point, predicted to ``time`` (its own velocity) and projected into this camera
        (the pose chain of the camera motion), lands in a stixel: that track is a candidate of the stixel.
        ``overlap`` (track rows, stixels): more candidates, the last frame's stixels seen through the flow
        (:meth:`_overlap`). A candidate continues in its stixel if the stixel is of its kind and the
        prediction passes the chi-square gate on position and velocity. Several candidates passing in one
        stixel: the nearest (Mahalanobis) continues there. Without a baseline (``degenerate``) a static
        stixel's depth is the scene model's and is not gated. A dynamic stixel left without a track whose
        flow links it to a mover's track (``coast_min_age``) whose position alone passes its gate
        continues that track on its position alone.
        """
        H, W = world.image_size
        xp, Pp = self._predict(torch.arange(self.state.ids.numel()), time)
        Xw = torch.stack([xp[:, 0], self.state.y, xp[:, 1]], 1)
        Xc = (Xw - o) @ Rwc
        K = world.K.double()
        z = Xc[:, 2]
        front = z > 0.1
        zs = torch.where(front, z, torch.ones_like(z))
        u = (K[0, 0] * Xc[:, 0] / zs + K[0, 2]).round()
        v = (K[1, 1] * Xc[:, 1] / zs + K[1, 2]).round()
        inside = front & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        s_of = torch.full((self.state.ids.numel(),), -1, dtype=torch.long)
        s_of[inside] = index[v[inside].long(), u[inside].long()]
        cand = torch.nonzero((s_of >= 0)).squeeze(1)
        parent = torch.full((len(world),), -1, dtype=torch.long)
        position_only = torch.zeros(len(world), dtype=torch.bool)
        sc = s_of[cand]
        linked = torch.zeros(cand.numel(), dtype=torch.bool)  # a candidate through the flow
        if overlap is not None:
            cand, sc = torch.cat([cand, overlap[0]]), torch.cat([sc, overlap[1]])
            linked = torch.cat([linked, torch.ones(overlap[0].numel(), dtype=torch.bool)])
        if cand.numel() == 0:
            return parent, position_only
        ok = obj[sc] & (kind[sc] == self.state.kind[cand])
        cand, sc, linked = cand[ok], sc[ok], linked[ok]
        if cand.numel() == 0:
            return parent, position_only
        pos = X_w[sc][:, [0, 2]]
        Rm = self._measurement(xp[cand, :2], xp[cand, 2:], dyn[sc], o[[0, 2]], lateral_std[sc])
        # Gate on position and velocity: a mover's stixel does not continue the track of the wall behind it.
        S = Pp[cand] + Rm
        r = torch.cat([pos, vel_meas[sc][:, [0, 2]]], 1) - xp[cand]
        d2 = (r[:, None, :] @ torch.linalg.solve(S, r[:, :, None]))[:, 0, 0]
        gate = d2 < _CHI2_4DOF_999
        if degenerate:
            gate |= ~dyn[sc]
        gate |= kind[sc] == 1  # a ground track's point follows its stixel's middle row: no position gate
        parent = self._nearest(len(world), cand[gate], sc[gate], d2[gate])
        m = self.params.coast_min_age
        if m > 0:
            # A near mover's one-pair velocity can be far off (its contact below the image, its flow lost)
            # while its pixels, through the flow, land in its own track: a track that has continued m frames
            # outweighs that one pair's velocity, once (the closing rate's gate does the same).
            alt = linked & dyn[sc] & (parent[sc] < 0) & self.state.dynamic[cand] & (self.state.age[cand] >= m) \
                & ~self.state.coasted[cand]
            if bool(alt.any()):
                ra, Sa = r[alt, :2], S[alt, :2, :2]
                d2p = (ra[:, None, :] @ torch.linalg.solve(Sa, ra[:, :, None]))[:, 0, 0]
                g2 = d2p < _CHI2_2DOF_999
                second = self._nearest(len(world), cand[alt][g2], sc[alt][g2], d2p[g2])
                position_only = second >= 0
                parent = torch.where(position_only, second, parent)
        return parent, position_only

    def _nearest(self, n: int, cand: torch.Tensor, sc: torch.Tensor, d2: torch.Tensor) -> torch.Tensor:
        """Row (n,) of the candidate track ``cand`` with the smallest ``d2`` in each stixel ``sc`` (-1: none;
        ties: the older track, lower row)."""
        parent = torch.full((n,), -1, dtype=torch.long)
        if cand.numel() == 0:
            return parent
        best = torch.full((n,), math.inf, dtype=torch.float64).scatter_reduce(0, sc, d2, reduce="amin")
        win = d2 == best[sc]
        first = torch.full((n,), self.state.ids.numel(), dtype=torch.long).scatter_reduce(
            0, sc[win], cand[win], reduce="amin")
        hit = first < self.state.ids.numel()
        parent[hit] = first[hit]
        return parent
