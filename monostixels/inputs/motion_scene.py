"""The metric scale from the scene model: static objects stand on the ground.

A second source of the length of ``t`` beside the road's own motion (:mod:`monostixels.inputs.motion`,
step 4). Where a static object (building, pole, vegetation) meets the ground (road, sidewalk, terrain) in an
image column, the ray through that contact row meets the ground plane at the camera height (less a kerb where
the ground there is sidewalk or terrain: the road is the lowest surface): the object's depth ``z_c``. The flow of the object's pixels just above the contact, with the rotation and the unit
translation ``t̂`` known, gives ``ρ = s / z`` (the translation's length over the depth, 1/m x m): so
``s = z_c ρ``, one sample per column. With the right scale the static world's flow depths agree with its
contacts; with a wrong one every static object seems to move. The samples' weighted median in log space is the
estimate, their spread its uncertainty (the standard error of the median, with a floor for the model itself:
a contact row a pixel off, an object that does not face the camera).

It needs nothing of the road's texture: it holds where the asphalt's flow fails at speed, and where cars hide
the road ahead but not the kerbs and house fronts beside it.

Convention: ``X_prev = R X_cur + t``, flow ``x_prev = x + f`` (docs/conventions.md, section 2).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from monostixels.core.classes import CLASS_NAMES, CLASS_TYPE, GROUND, STATIC_OBJECT
from monostixels.core.geometry import Motion
from monostixels.inputs.motion_base import MotionEstimate, MotionKind, ScaleFrom

__all__ = ["GRADE_STD", "SceneScale", "scene_scale", "with_scene_scale"]

#: Grid rows of ground below and of a static object above a contact (on the flow grid of the estimator).
_RUN = 2
#: Object pixels above the contact whose flow is read (grid rows).
_ABOVE = 3
#: Least translational parallax (pixels) of a sample: below it the flow's noise is the sample.
_MIN_PARALLAX_PX = 0.5
#: The model's own error (std of log s) of one column's sample: a contact a pixel or two off at 20 m,
#: an object side not facing the camera.
_MODEL_STD = 0.15
#: Fewest columns for an estimate.
_MIN_COLUMNS = 8
#: The road's change of grade (radians, one standard deviation) between the car and the contacts: the tilt
#: of the ground they stand on against the plane of travel that even an exact direction of travel leaves.
#: On KITTI drive 0023 the scene model's length agrees with the GPS/IMU within 1-2 % at contacts 5-6 camera
#: heights away: at most about 0.2 deg there. The direction's own scatter over a sequence comes on top of it
#: (:class:`~monostixels.inputs.motion_track.MotionTrack`). Every column shares the tilt: it does not
#: average out over the columns.
GRADE_STD = math.radians(0.25)


@dataclass
class SceneScale:
    """The scene model's length of ``t``: ``scale`` (m), ``std`` (std of ``log scale``), ``columns`` (samples),
    ``reach``: its contacts' distance in camera heights (their weighted median of ``z_c / h``)."""

    scale: float
    std: float
    columns: int
    reach: float = 0.0


def _unit_inverse_depth(K: np.ndarray, R: np.ndarray, t_unit: np.ndarray, p_cur: np.ndarray,
                        p_prev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``ρ = s / z`` (N,) of static pixels from their flow, and the translational parallax (N,) pixels of a unit ρ.

    ``x_prev ~ K (R a + ρ t̂)`` with ``a = K^-1 x``: ``ρ (c - x' c_3) = x' b_3 - b`` (two equations, ``b = K R a``,
    ``c = K t̂``), solved by least squares. ``p_cur``, ``p_prev``: (N, 2) pixels.
    """
    a = np.c_[p_cur, np.ones(len(p_cur))] @ np.linalg.inv(K).T
    b = a @ (K @ R).T
    c = K @ t_unit
    g = c[None, :2] - p_prev * c[2]  # (N, 2)
    r = p_prev * b[:, 2:3] - b[:, :2]
    den = np.maximum(np.einsum("ij,ij->i", g, g), 1e-30)
    rho = np.einsum("ij,ij->i", g, r) / den
    # d x' / d ρ at ρ: the pixels the flow moves per unit of ρ (its noise maps through it).
    return rho, np.sqrt(den) / np.maximum(np.abs(b[:, 2] + rho * c[2]), 1e-9)


def scene_scale(K: np.ndarray, R: np.ndarray, t_unit: np.ndarray, n_g: np.ndarray, height: float,
                labels: np.ndarray, us: np.ndarray, vs: np.ndarray, flow: np.ndarray, ok: np.ndarray,
                step: int, kerb: float = 0.15, tilt_std: float = GRADE_STD) -> SceneScale | None:
    """The length of ``t_unit`` from static objects' ground contacts (module docstring).

    Args:
        K: (3, 3) intrinsics. R: (3, 3) rotation, t_unit: (3,) unit translation (``X_prev = R X + t``).
        n_g: (3,) unit ground normal (current camera, pointing down); height: camera height (m).
        labels: (Hg, Wg) class ids on the estimator's grid; us, vs: (Hg * Wg,) its pixels, row-major.
        flow: (Hg * Wg, 2) flow (current -> previous, pixels) there; ok: (Hg * Wg,) usable vectors.
        step: the grid's stride (pixels).
        kerb: how far sidewalks and verges (terrain) lie above the road (m): an object standing on them meets a
            ground ``height - kerb`` below the camera (left out, every such contact reads ``kerb / height`` too
            far: 9 % at KITTI's 1.65 m, as the renderer's and drive 0023's house fronts showed).
        tilt_std: the ground's tilt against ``n_g`` that cannot be ruled out (radians, :data:`GRADE_STD`).

    Returns:
        A :class:`SceneScale`, or None with fewer than ``_MIN_COLUMNS`` columns of contacts.
    """
    Hg, Wg = labels.shape
    ctype = np.asarray(CLASS_TYPE)[labels]
    ground, static = ctype == GROUND, ctype == STATIC_OBJECT
    okg = ok.reshape(Hg, Wg)
    # A contact below grid row j: rows j+1..j+_RUN ground, rows j-_RUN+1..j static and usable; per column the
    # lowest one (the first obstacle from the bottom).
    cand = np.ones((Hg, Wg), dtype=bool)
    for k in range(1, _RUN + 1):
        cand[: Hg - k] &= ground[k:]
        cand[Hg - k:] = False
    for k in range(_RUN):
        cand[k:] &= static[: Hg - k] & okg[: Hg - k]
        cand[:k] = False
    has = cand.any(0)
    if has.sum() < _MIN_COLUMNS:
        return None
    cols = np.nonzero(has)[0]
    rows = Hg - 1 - np.argmax(cand[::-1, cols], axis=0)  # the lowest contact of each column
    # The contact row lies between the object's lowest grid row and the ground's below it.
    u_c = us.reshape(Hg, Wg)[rows, cols].astype(np.float64)
    v_c = vs.reshape(Hg, Wg)[rows, cols] + step / 2.0
    ray = np.c_[u_c, v_c, np.ones(len(u_c))] @ np.linalg.inv(K).T
    down = ray @ n_g
    front = down > 1e-6
    below = labels[np.minimum(rows + 1, Hg - 1), cols]
    h_c = np.where(below == CLASS_NAMES.index("road"), height, height - kerb)
    z_c = np.where(front, h_c / np.where(front, down, 1.0), np.nan)  # ray parameter = depth (ray z = 1)
    # The object's pixels above the contact: their ρ, and the column's median.
    samples, weights = [], []
    for k in range(_ABOVE):
        r = rows - k
        inside = (r >= 0) & front
        r = np.clip(r, 0, Hg - 1)
        idx = r * Wg + cols
        use = inside & static[r, cols] & okg[r, cols]
        p_cur = np.c_[us[idx], vs[idx]].astype(np.float64)
        rho, slope = _unit_inverse_depth(K, R, t_unit, p_cur, p_cur + flow[idx])
        par = np.abs(rho) * slope
        use &= (rho > 0) & (par >= _MIN_PARALLAX_PX)
        samples.append(np.where(use, rho, np.nan))
        weights.append(np.where(use, par, np.nan))
    samples, weights = np.stack(samples), np.stack(weights)
    good = np.isfinite(samples).any(0) & np.isfinite(z_c)
    if good.sum() < _MIN_COLUMNS:
        return None
    rho_col = np.nanmedian(samples[:, good], axis=0)
    par_col = np.nanmedian(weights[:, good], axis=0)
    log_s = np.log(z_c[good] * rho_col)
    # Weighted by the parallax (the flow's error in ρ falls with it); the standard error of the median from
    # the samples' spread (MAD), and the model's error of each column, over the effective number of columns.
    w = par_col**2
    med = _weighted_median(log_s, w)
    mad = float(np.median(np.abs(log_s - med))) * 1.4826
    n_eff = float(w.sum() ** 2 / np.sum(w**2))
    # A ground tilted by δ against n_g moves a contact's depth by about δ z_c / h in log: the same δ in every
    # column, so it adds to the standard error whole, at the contacts' distance (their weighted median).
    reach = _weighted_median(z_c[good] / h_c[good], w)
    std = math.sqrt(1.5708 * (mad**2 + _MODEL_STD**2) / n_eff + (tilt_std * reach) ** 2)
    return SceneScale(float(math.exp(med)), std, int(good.sum()), reach)


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The value (N,) at which the ``weights`` (N,) sorted by value first reach half their sum."""
    order = np.argsort(values)
    cw = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cw, 0.5 * cw[-1])])


def with_scene_scale(est: MotionEstimate, scene: SceneScale | None, t_unit: np.ndarray, params: Any) -> MotionEstimate:
    """``est`` with the scene model's length of its translation (:mod:`~monostixels.inputs.motion_scene`) as evidence.

    A road's length gets the measurement error ``scale_meas_std``; where the scene model contradicts it (their
    log lengths differ by more than ``scale_gate`` standard deviations of the difference), the pair's
    uncertainty is that difference: one of the two is wrong, and nothing tells which. A pair whose road gave
    no length (``scale_unknown``) takes the scene model's where its uncertainty is within ``max_scale_std``.
    The settings are the ``motion=mono`` group's (:class:`~monostixels.inputs.motion_track.MonoMotionConfig`).
    """
    meas = float(getattr(params, "scale_meas_std", 0.04))
    gate = float(getattr(params, "scale_gate", 2.0))
    bound = float(getattr(params, "max_scale_std", 0.15))
    if scene is None:
        return est if est.kind != MotionKind.METRIC else dataclasses.replace(est, scale_std=meas)
    note = f"scene model: {scene.scale:.3f} m (std {scene.std:.2f}, {scene.columns} contacts at {scene.reach:.0f} camera heights)"
    if est.kind == MotionKind.METRIC:
        delta = math.log(float(est.motion.t.norm()) / scene.scale)
        std = meas
        if abs(delta) > gate * math.hypot(meas, scene.std):
            std = abs(delta)
            note += f", {delta * 100:+.0f} % from the road's: uncertain"
        return dataclasses.replace(est, reason=f"{est.reason}; {note}", scale_std=std)
    if est.kind == MotionKind.SCALE_UNKNOWN and scene.std <= bound:
        motion = Motion(est.unit_motion.R, torch.from_numpy(np.ascontiguousarray(t_unit * scene.scale)))
        return dataclasses.replace(est, motion=motion, kind=MotionKind.METRIC, unit_motion=None,
                                   scale_from=ScaleFrom.SCENE, scale_std=scene.std, scene_reach=scene.reach,
                                   reason=f"{est.reason}; {note}: the length taken from it")
    return dataclasses.replace(est, reason=f"{est.reason}; {note}")
