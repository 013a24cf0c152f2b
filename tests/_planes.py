"""Exact flow fields of column-wise planar scenes, for solver tests.

Every stixel column holds, bottom to top, ground up to an object's foot, the object (an upright
plane facing the camera, as the stixel model assumes), and sky above. Flow of every pixel is the
exact homography of its plane (static: ``K (R + p t n^T) K^-1``; moving by ``Δ``:
``K (R + p (t - R Δ) n^T) K^-1``), so the true stixels, depths and motions are known.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from monostixels.core.classes import NUM_CLASSES
from monostixels.core.geometry import (
    Camera,
    Motion,
    apply_homography,
    dynamic_homography,
    homography,
    intrinsics,
    object_normals,
    pixel_rays,
    rotation_yaw,
)

H_IMG, W_IMG, WS = 120, 200, 5
# Asymmetric intrinsics so that a transposition or sign slip cannot pass.
K = intrinsics(210.0, 190.0, 97.3, 52.1)
CAM = Camera(K, height=1.65)
MOTION = Motion(rotation_yaw(0.01), torch.tensor([0.03, 0.0, 1.0], dtype=torch.float64))


@dataclass
class Obj:
    """An upright object occupying stixel columns ``c0..c1-1``."""

    c0: int
    c1: int
    dist: float      # horizontal distance (m) = 1 / p
    height: float    # metres above the ground
    cls: int
    delta: tuple[float, float, float] = (0.0, 0.0, 0.0)  # motion prev -> cur (m), on the ground


OBJECTS = [
    Obj(0, 8, 9.0, 6.0, 3),                          # static wall (building)
    Obj(8, 16, 12.0, 1.6, 6, (0.0, 0.0, 0.8)),       # vehicle driving ahead along the axis (epipolar-conformant)
    Obj(16, 24, 14.0, 1.5, 6, (0.6, 0.0, 0.0)),      # crossing vehicle
    Obj(24, 40, 20.0, 8.0, 5),                       # vegetation
]


def build_scene():
    """Flow (2, H, W), covariance (H, W, 2, 2), scores (10, H, W) and the truth per column.

    Returns:
        flow, cov, scores, truth: list per column of dicts ``{"foot_v", "top_v", "obj"}``
        (rows where the object starts and ends; ``foot_v`` = first object row from the bottom).
    """
    dt = torch.float64
    v, u = torch.meshgrid(torch.arange(H_IMG, dtype=dt), torch.arange(W_IMG, dtype=dt), indexing="ij")
    ray = pixel_rays(K, u, v)
    n_g = CAM.ground_normal.double()
    flow = torch.zeros(2, H_IMG, W_IMG, dtype=dt)
    labels = torch.full((H_IMG, W_IMG), 9, dtype=torch.long)
    truth = []
    for obj in OBJECTS:
        for c in range(obj.c0, obj.c1):
            us = slice(c * WS, (c + 1) * WS)
            uc = torch.tensor(c * WS + (WS - 1) / 2, dtype=dt)
            n_o = object_normals(K, n_g, uc)
            # Rows: ground where the ground point is closer than the object's foot, then object
            # up to its top, then sky.
            r = ray[:, us]
            d_ground = CAM.height / (r @ n_g)  # ray parameter to the ground (z = lambda)
            d_obj = obj.dist / (r @ n_o)
            X_obj = r * d_obj[..., None]
            h_above = CAM.height - X_obj @ n_g
            is_ground = (r @ n_g > 0) & (d_ground < d_obj)
            is_obj = ~is_ground & (h_above <= obj.height)
            Hg = homography(K, MOTION.R, MOTION.t, n_g, torch.tensor(1 / CAM.height, dtype=dt))
            delta = torch.tensor(obj.delta, dtype=dt)
            p = torch.tensor(1 / obj.dist, dtype=dt)
            Ho = dynamic_homography(K, MOTION.R, n_o, p * (MOTION.t - MOTION.R @ delta))
            Hs = homography(K, MOTION.R, MOTION.t, n_g, torch.tensor(0.0, dtype=dt))
            for Hm, mask in ((Hg, is_ground), (Ho, is_obj), (Hs, ~is_ground & ~is_obj)):
                up, vp = apply_homography(Hm, u[:, us], v[:, us])
                flow[0, :, us] = torch.where(mask, up - u[:, us], flow[0, :, us])
                flow[1, :, us] = torch.where(mask, vp - v[:, us], flow[1, :, us])
            lab = labels[:, us]
            lab[is_ground] = 0
            lab[is_obj] = obj.cls
            rows_obj = torch.nonzero(is_obj[:, 0])[:, 0]
            truth.append({"column": c, "foot_v": int(rows_obj.max()), "top_v": int(rows_obj.min()), "obj": obj})
    cov = (0.5 ** 2) * torch.eye(2, dtype=dt).expand(H_IMG, W_IMG, 2, 2).clone()
    scores = torch.full((NUM_CLASSES, H_IMG, W_IMG), 0.1 / (NUM_CLASSES - 1), dtype=dt)
    scores.scatter_(0, labels[None], 0.9)
    return flow, cov, scores, truth
