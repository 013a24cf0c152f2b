"""Movers cut off by the image's lower edge stand on the line of their object's visible contacts.

Why: a dynamic stixel's depth is not in its flow but in the scene model (paper, section C): it stands on
the ground stixel below it. A vehicle whose body reaches the image's lower edge has its contact below
the image, and the solver stands it on the bottom row's ground: the farthest it can be. On the KITTI
traffic drive the trucks beside the camera, 2-4 m away, were placed at the bottom row's 5.9 m, and
every stixel stacked on them followed (docs/experiments.md, "Movers cut off by the image's edge").

The same object's contacts are often in view a few columns on: its wheels, the far end of its side.
Outward from a run of cut-off columns, the dynamic stixels of the same class that stand on a ground
stixel are taken while their depth runs on without a jump (a jump is another object); the line through
their contacts on the road plane is the object's side or back (a total least-squares fit, taken where
its RMS distance is small). Each cut-off column's viewing direction meets that line: where it meets it
nearer than the bottom row's ground, the object stands there, and so do the dynamic stixels stacked on
it at its depth (the scene model's rule for a stixel on an object). Farther than the bottom row would
contradict the stixel's reaching the lower edge: left as it is.

Convention: an object stixel lies on ``p n^T X = 1`` with ``n`` its column's horizontal viewing direction
(docs/conventions.md, section 2), so its contact lies ``1 / p`` along that direction on the road plane.
"""
from __future__ import annotations

import dataclasses
import logging

import numpy as np
import torch

from monostixels.core.classes import DYNAMIC_OBJECT, GROUND, STATIC_OBJECT
from monostixels.core.geometry import Motion, ground_basis, object_normals, stixel_motion
from monostixels.core.stixels import StixelWorld

__all__ = ["stand_cut_off"]

logger = logging.getLogger(__name__)

_CUT, _CONTACT = 2, 1


def _bases(stixels: StixelWorld) -> tuple[np.ndarray, np.ndarray, list[list[int]]]:
    """Per column: the index of its lowest object stixel (-1: none), whether that one is a dynamic stixel
    cut off by the lower edge (``_CUT``) or one standing on a ground stixel (``_CONTACT``) (0: neither),
    and the column's stixels bottom to top."""
    H = stixels.image_size[0]
    col = stixels.column.numpy()
    typ = stixels.type.numpy()
    vb = stixels.v_bottom.numpy()
    order = np.lexsort((-vb, col))
    per_col: list[list[int]] = [[] for _ in range(stixels.num_columns)]
    for i in order:
        per_col[col[i]].append(int(i))
    base = np.full(stixels.num_columns, -1)
    kind = np.zeros(stixels.num_columns, dtype=np.int64)
    for c, ids in enumerate(per_col):
        for k, i in enumerate(ids):
            if typ[i] in (STATIC_OBJECT, DYNAMIC_OBJECT):
                base[c] = i
                if typ[i] == DYNAMIC_OBJECT:
                    if k == 0 and vb[i] >= H - 1:
                        kind[c] = _CUT
                    elif k > 0 and typ[ids[k - 1]] == GROUND:
                        kind[c] = _CONTACT
                break
    return base, kind, per_col


def stand_cut_off(stixels: StixelWorld, motion: Motion, contacts: int = 8, max_rms_m: float = 0.25,
                  max_jump: float = 0.15) -> StixelWorld:
    """Dynamic stixels cut off by the image's lower edge, moved to the line of their object's contacts.

    Args:
        stixels: the solver's result (after the mover check). motion: the camera motion (metres), for the
            moved stixels' motion ``Δ`` (``g = p (t - R Δ)`` holds its ``g``, so ``Δ`` follows ``p``).
        contacts: at most this many contact columns on each side of a cut-off run (0: off).
        max_rms_m: the most RMS distance (metres) of the contacts from their line on the road.
        max_jump: the most relative change of depth between neighbouring contacts of one object.

    Returns:
        A new :class:`StixelWorld`, or ``stixels`` where none moves.
    """
    if contacts <= 0 or not bool((stixels.type == DYNAMIC_OBJECT).any()):
        return stixels
    base, kind, per_col = _bases(stixels)
    if not (kind == _CUT).any():
        return stixels
    C, w, W = stixels.num_columns, stixels.column_width, stixels.image_size[1]
    u0 = torch.arange(C, dtype=torch.float64) * w
    uc = (u0 + torch.clamp(u0 + w, max=W) - 1) / 2
    n_g = stixels.ground_normal.double()
    # Each column's horizontal viewing direction on the road plane (right, forward): unit 2-vectors.
    dirs = (object_normals(stixels.K.double(), n_g, uc) @ ground_basis(n_g)).numpy()
    p = stixels.inverse_depth.double().numpy()
    cls = stixels.cls.numpy()
    typ = stixels.type.numpy()
    p_new = p.copy()
    c = 0
    while c < C:
        if kind[c] != _CUT:
            c += 1
            continue
        c1, k_cls = c, cls[base[c]]
        while c1 + 1 < C and kind[c1 + 1] == _CUT and cls[base[c1 + 1]] == k_cls:
            c1 += 1
        near: list[int] = []
        for step, k in ((-1, c - 1), (1, c1 + 1)):
            last, got = None, 0
            while 0 <= k < C and kind[k] in (_CUT, _CONTACT) and cls[base[k]] == k_cls and got < contacts:
                if kind[k] == _CONTACT:
                    d = 1.0 / p[base[k]]
                    if last is not None and abs(d / last - 1.0) > max_jump:
                        break
                    near.append(k)
                    last, got = d, got + 1
                k += step
        if len(near) >= 3:
            pts = np.stack([dirs[k] / p[base[k]] for k in near])
            mu = pts.mean(0)
            _, sv, vh = np.linalg.svd(pts - mu)
            if sv[1] / np.sqrt(len(pts)) <= max_rms_m:
                normal = vh[1]
                for j in range(c, c1 + 1):
                    den = float(dirs[j] @ normal)
                    if abs(den) < 1e-9:
                        continue
                    d = float(mu @ normal) / den
                    i = base[j]
                    if not 0.0 < d < 1.0 / p[i]:
                        continue
                    old, ids = p[i], per_col[j]
                    # The base and the dynamic stixels stacked on it at its depth.
                    for s in ids[ids.index(i):]:
                        if typ[s] != DYNAMIC_OBJECT or p[s] != old:
                            break
                        p_new[s] = 1.0 / d
        c = c1 + 1
    moved = np.nonzero(p_new != p)[0]
    if moved.size == 0:
        return stixels
    idx = torch.from_numpy(moved)
    inv = stixels.inverse_depth.clone()
    inv[idx] = torch.from_numpy(p_new[moved]).to(inv.dtype)
    delta = stixels.motion.clone()
    delta[idx] = stixel_motion(stixels.tau[idx], inv[idx], n_g, motion.R, motion.t).to(delta.dtype)
    logger.debug("%d dynamic stixels cut off by the lower edge stand on their object's contacts", moved.size)
    return dataclasses.replace(stixels, inverse_depth=inv, motion=delta)
