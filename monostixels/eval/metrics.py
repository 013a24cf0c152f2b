"""Evaluation metrics: depth (Eigen et al.), compactness, semantic IoU, stixel bottoms, camera motion.

Depth metrics follow the paper's "Metric and Baseline" section (Eigen et al., NIPS 2014):
``rel = mean |y - y*| / y*``, ``rmse = sqrt(mean (y - y*)^2)`` and the threshold accuracies
``% of pixels with max(y / y*, y* / y) < thr`` for ``thr`` in 1.1, 1.25, 1.25^2, 1.25^3.

Convention (docs/conventions.md, section 4.5): *every* pixel with ground truth counts for *every*
method. An estimate that is not a valid depth (NaN, inf, zero or negative — e.g. a triangulation
behind the camera, a sky stixel, a pixel without an estimate) is set to ``max_depth``; finite
positive estimates are clamped into ``[min_depth, max_depth]``. Nothing is dropped, so methods are
compared on identical pixel sets.

Overall numbers over a data set are computed over all pixels of all frames (the accumulators
sum per-pixel terms), not as a mean of per-frame means. The settings of the evaluation: the config group
``eval`` (:class:`monostixels.pipeline.EvalConfig`).
"""
from __future__ import annotations

import logging
import math
from typing import Sequence

import numpy as np
import torch

from monostixels._checks import InputError, check_shape
from monostixels.core.classes import CLASS_NAMES, IGNORE_LABEL, NUM_CLASSES
from monostixels.core.geometry import Motion, angle_deg

__all__ = [
    "DEPTH_THRESHOLDS",
    "VALUES_PER_STIXEL",
    "BOTTOM_TOLERANCES_PX",
    "depth_metrics",
    "DepthAccumulator",
    "stixel_compactness",
    "dense_compactness",
    "semantic_metrics",
    "SemanticAccumulator",
    "bottoms_metrics",
    "motion_errors",
]

logger = logging.getLogger(__name__)

#: Threshold accuracies reported in the paper's Table II: key -> threshold on max(y/y*, y*/y).
DEPTH_THRESHOLDS: dict[str, float] = {"d1.1": 1.1, "d1.25": 1.25, "d1.25^2": 1.25**2, "d1.25^3": 1.25**3}
#: Values needed per mono-stixel (segmentation, type, inverse depth; paper "Metric and Baseline").
VALUES_PER_STIXEL = 3
#: Tolerances (pixels) of the stixel-bottom accuracy, reported as ``within_<tol>px``.
BOTTOM_TOLERANCES_PX: tuple[int, ...] = (5, 10)


def _validate_depth_inputs(
    pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None, min_depth: float, max_depth: float
) -> None:
    check_shape(pred, ["H", "W"], "pred (depth estimate)")
    check_shape(gt, ["H", "W"], "gt (ground-truth depth)")
    if pred.shape != gt.shape:
        raise InputError(f"pred and gt differ in size: {tuple(pred.shape)} vs {tuple(gt.shape)} (H, W)")
    if mask is not None:
        check_shape(mask, ["H", "W"], "mask")
        if mask.shape != gt.shape:
            raise InputError(f"mask and gt differ in size: {tuple(mask.shape)} vs {tuple(gt.shape)} (H, W)")
        if mask.dtype != torch.bool:
            raise InputError(f"mask: expected a bool tensor, got {mask.dtype}")
    if not (math.isfinite(min_depth) and math.isfinite(max_depth) and 0 < min_depth < max_depth):
        raise InputError(f"min_depth/max_depth: need 0 < min_depth < max_depth, got {min_depth}, {max_depth}")


def _depth_terms(
    pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None, min_depth: float, max_depth: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Estimates and ground truth (float64, 1-D) at the evaluated pixels, estimates clamped."""
    _validate_depth_inputs(pred, gt, mask, min_depth, max_depth)
    g = gt.detach().double()
    sel = torch.isfinite(g) & (g > 0) & (g <= max_depth)
    if mask is not None:
        sel &= mask
    y_star = g[sel]
    y = pred.detach().double()[sel]
    # An invalid estimate is not dropped: it is set to the far end of the evaluation range.
    invalid = ~torch.isfinite(y) | (y <= 0)
    y = torch.where(invalid, torch.full_like(y, max_depth), y.clamp(min_depth, max_depth))
    return y, y_star


class DepthAccumulator:
    """Sums the per-pixel depth-error terms over frames.

    ``result()`` gives the metrics over all pixels of all frames added so far, exactly what
    :func:`depth_metrics` gives on the concatenation of the frames.

    Args:
        min_depth: lower clamp of estimates (metres).
        max_depth: ground-truth cap and upper clamp of estimates (metres); invalid estimates
            are set to it.
    """

    def __init__(self, *, min_depth: float, max_depth: float) -> None:
        if not (math.isfinite(min_depth) and math.isfinite(max_depth) and 0 < min_depth < max_depth):
            raise InputError(f"min_depth/max_depth: need 0 < min_depth < max_depth, got {min_depth}, {max_depth}")
        self.min_depth = float(min_depth)
        self.max_depth = float(max_depth)
        self.n = 0
        self.sum_rel = 0.0
        self.sum_sq = 0.0
        self.hits = {k: 0 for k in DEPTH_THRESHOLDS}

    def add(self, pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> None:
        """Add one frame.

        Args:
            pred: (H, W) estimated depth z, metres (any value; invalid ones are clamped).
            gt: (H, W) ground-truth depth z, metres; 0 = no ground truth.
            mask: (H, W) bool, optional restriction (e.g. the moving-object mask).
        """
        y, y_star = _depth_terms(pred, gt, mask, self.min_depth, self.max_depth)
        self.n += int(y.numel())
        self.sum_rel += float(((y - y_star).abs() / y_star).sum())
        self.sum_sq += float(((y - y_star) ** 2).sum())
        ratio = torch.maximum(y / y_star, y_star / y)
        for k, thr in DEPTH_THRESHOLDS.items():
            self.hits[k] += int((ratio < thr).sum())

    def result(self) -> dict[str, float | int]:
        """``{"rel", "rmse", "d1.1", "d1.25", "d1.25^2", "d1.25^3", "n"}``.

        Fractions in 0..1, rmse in metres, ``n`` = ground-truth pixels counted. With ``n = 0``
        every metric is NaN (nothing to evaluate, e.g. no moving pixels in the data).
        """
        if self.n == 0:
            out: dict[str, float | int] = {"rel": math.nan, "rmse": math.nan}
            out.update({k: math.nan for k in DEPTH_THRESHOLDS})
            out["n"] = 0
            return out
        out = {"rel": self.sum_rel / self.n, "rmse": math.sqrt(self.sum_sq / self.n)}
        out.update({k: self.hits[k] / self.n for k in DEPTH_THRESHOLDS})
        out["n"] = self.n
        return out


def depth_metrics(
    pred: torch.Tensor,
    gt: torch.Tensor,
    mask: torch.Tensor | None = None,
    *,
    min_depth: float,
    max_depth: float,
) -> dict[str, float | int]:
    """Depth metrics of one frame (paper Table II).

    Ground-truth pixels: ``0 < gt <= max_depth`` (and ``mask``). At each of them the estimate
    counts: NaN / inf / ``<= 0`` estimates become ``max_depth``, others are clamped into
    ``[min_depth, max_depth]``.

    Args:
        pred: (H, W) estimated depth z in the current camera, metres.
        gt: (H, W) ground-truth depth z, metres; 0 = no ground truth.
        mask: (H, W) bool or None: evaluate only these pixels (static / moving split).
        min_depth: lower clamp of estimates, metres.
        max_depth: ground-truth cap and upper clamp of estimates, metres.

    Returns:
        ``{"rel", "rmse", "d1.1", "d1.25", "d1.25^2", "d1.25^3", "n"}``: fractions 0..1, rmse in
        metres, ``n`` the number of ground-truth pixels counted (metrics NaN when ``n = 0``).
    """
    acc = DepthAccumulator(min_depth=min_depth, max_depth=max_depth)
    acc.add(pred, gt, mask)
    return acc.result()


def stixel_compactness(stixels_per_frame: Sequence[int]) -> float:
    """Compactness of a stixel representation: ``3 x`` the mean number of stixels per frame.

    Paper: three values per mono-stixel (segmentation, type, inverse depth).
    """
    if len(stixels_per_frame) == 0:
        return math.nan
    return VALUES_PER_STIXEL * float(np.mean(np.asarray(stixels_per_frame, dtype=np.float64)))


def dense_compactness(pixels_per_frame: Sequence[int]) -> float:
    """Compactness of a dense depth map: the mean number of pixels per frame (paper)."""
    if len(pixels_per_frame) == 0:
        return math.nan
    return float(np.mean(np.asarray(pixels_per_frame, dtype=np.float64)))


class SemanticAccumulator:
    """Confusion matrix of pixel labels over frames, for the mean IoU.

    Rows are ground-truth classes 0..9, columns predicted classes 0..9 plus one "void" column
    for predictions outside 0..9 (they count as a miss of the ground-truth class). Pixels whose
    ground truth is ``IGNORE_LABEL`` (255) are not scored at all.
    """

    def __init__(self, num_classes: int = NUM_CLASSES) -> None:
        self.num_classes = num_classes
        self.confusion = torch.zeros(num_classes, num_classes + 1, dtype=torch.int64)

    def add(self, pred_labels: torch.Tensor, gt_labels: torch.Tensor) -> None:
        """Add one frame: ``pred_labels`` and ``gt_labels`` (H, W) integer class ids."""
        check_shape(pred_labels, ["H", "W"], "pred_labels")
        check_shape(gt_labels, ["H", "W"], "gt_labels")
        if pred_labels.shape != gt_labels.shape:
            raise InputError(
                f"pred_labels and gt_labels differ in size: {tuple(pred_labels.shape)} vs {tuple(gt_labels.shape)}"
            )
        if pred_labels.is_floating_point() or gt_labels.is_floating_point():
            raise InputError("pred_labels / gt_labels: expected integer class ids, got floating point")
        C = self.num_classes
        g = gt_labels.reshape(-1).long()
        p = pred_labels.reshape(-1).long()
        keep = g != IGNORE_LABEL
        bad_gt = keep & ((g < 0) | (g >= C))
        if bool(bad_gt.any()):
            raise InputError(f"gt_labels: values outside 0..{C - 1} and {IGNORE_LABEL}: {torch.unique(g[bad_gt]).tolist()}")
        g, p = g[keep], p[keep]
        p = torch.where((p >= 0) & (p < C), p, torch.full_like(p, C))  # void column
        self.confusion += torch.bincount(g * (C + 1) + p, minlength=C * (C + 1)).reshape(C, C + 1)

    def result(self, class_names: Sequence[str] = CLASS_NAMES, classes: Sequence[int] | None = None) -> dict:
        """``{"miou": float, "per_class_iou": {name: iou}}``.

        ``IoU_c = TP / (TP + FP + FN)``. A class absent from both the ground truth and the
        prediction (``TP + FP + FN = 0``) has no IoU: it is NaN in ``per_class_iou`` and skipped
        in the mean (it would otherwise count as 0 or 1 depending on convention). With
        ``classes`` (ids), the mean runs over those only (e.g. the classes a dataset labels) and
        ``per_class_iou`` lists only them.
        """
        cm = self.confusion.double()
        C = self.num_classes
        tp = cm.diagonal()[:C]
        fn = cm.sum(1) - tp  # includes the void column
        fp = cm[:, :C].sum(0) - tp
        union = tp + fp + fn
        iou = torch.where(union > 0, tp / union.clamp_min(1), torch.full_like(tp, math.nan))
        present = union > 0
        keep = range(C) if classes is None else sorted(int(c) for c in classes)
        if classes is not None:
            chosen = torch.zeros_like(present)
            chosen[list(keep)] = True
            present = present & chosen
        miou = float(iou[present].mean()) if bool(present.any()) else math.nan
        return {"miou": miou, "per_class_iou": {class_names[i]: float(iou[i]) for i in keep}}


def semantic_metrics(pred_labels: torch.Tensor, gt_labels: torch.Tensor) -> dict:
    """Mean IoU of one label map (H, W) against ground truth (H, W); 255 = ignore.

    Returns:
        ``{"miou": float, "per_class_iou": {"road": float, ...}}``; classes absent from both
        ground truth and prediction are NaN and skipped in the mean.
    """
    acc = SemanticAccumulator()
    acc.add(pred_labels, gt_labels)
    return acc.result()


def bottoms_metrics(pred_rows: Sequence[float] | np.ndarray | torch.Tensor,
                    gt_rows: Sequence[float] | np.ndarray | torch.Tensor) -> dict[str, float | int]:
    """Accuracy of stixel bottoms: per labelled column, predicted vs labelled row (pixels).

    Args:
        pred_rows: (N,) predicted bottom row of the lowest object stixel per labelled column;
            NaN where the method has no object stixel in that column.
        gt_rows: (N,) labelled row where the first obstacle meets the ground.

    Returns:
        ``{"mae_px", "within_5px", "within_10px", "n", "missing"}``: ``within_<tol>px`` is the
        fraction of labelled columns with ``|pred - gt| <= tol`` pixels; ``n`` = labelled columns;
        a column without prediction (``missing``) counts as outside both tolerances (the
        fractions are over all ``n``) but cannot enter the mean absolute error, which is over
        the ``n - missing`` predicted columns.
    """
    pred = np.asarray(pred_rows.detach().cpu() if isinstance(pred_rows, torch.Tensor) else pred_rows, dtype=np.float64).reshape(-1)
    gt = np.asarray(gt_rows.detach().cpu() if isinstance(gt_rows, torch.Tensor) else gt_rows, dtype=np.float64).reshape(-1)
    if pred.shape != gt.shape:
        raise InputError(f"pred_rows and gt_rows differ in length: {pred.size} vs {gt.size}")
    if not np.isfinite(gt).all():
        raise InputError("gt_rows: non-finite labelled rows")
    n = int(gt.size)
    have = np.isfinite(pred)
    err = np.abs(pred[have] - gt[have])
    out: dict[str, float | int] = {"mae_px": float(err.mean()) if err.size else math.nan}
    for tol in BOTTOM_TOLERANCES_PX:
        out[f"within_{tol}px"] = float((err <= tol).sum() / n) if n else math.nan
    out["n"] = n
    out["missing"] = int(n - have.sum())
    return out


def motion_errors(est: Motion, gt: Motion) -> dict[str, float]:
    """Errors of an estimated camera motion against ground truth.

    Returns:
        ``rot_err_deg``: angle of ``R_est R_gt^T`` (degrees); ``trans_dir_err_deg``: angle between
        the translations (degrees; NaN if either is zero); ``trans_dir_err_xz_deg``: the same for
        their horizontal parts ``(t_x, t_z)`` (camera x right, z forward; for ground truth whose
        vertical component drifts, e.g. the poses of KITTI odometry sequence 08); ``scale_rel_err``:
        ``|‖t‖/‖t_gt‖ - 1|`` (NaN if ``t_gt = 0``).
    """
    Rd = est.R.double() @ gt.R.double().T
    # ||R - I||_F = 2 sqrt(2) sin(theta / 2): accurate for small angles, unlike acos of the trace.
    s = float(torch.linalg.norm(Rd - torch.eye(3, dtype=Rd.dtype))) / (2.0 * math.sqrt(2.0))
    rot = math.degrees(2.0 * math.asin(min(1.0, s)))
    te, tg = est.t.double(), gt.t.double()
    ne, ng = float(te.norm()), float(tg.norm())
    tdir = angle_deg(te, tg)
    tdir_xz = angle_deg(te[[0, 2]], tg[[0, 2]])
    scale = abs(ne / ng - 1.0) if ng > 0 else math.nan
    return {"rot_err_deg": rot, "trans_dir_err_deg": tdir, "trans_dir_err_xz_deg": tdir_xz, "scale_rel_err": scale}
