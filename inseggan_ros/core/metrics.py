"""The InSeGAN paper's instance-segmentation score (mIoU), exactly as the paper defines it.

Per test image: restrict the prediction to ground-truth foreground pixels (predicted labels where
the ground truth is background are ignored); for every ground-truth instance take the best IoU
over the predicted instances (0 when no prediction overlaps it); average over the ground-truth
instances. Over a test set the per-image scores are averaged (`mean_miou`). Label ids need not
agree between prediction and ground truth: the score is invariant to renaming the labels.

An image without any ground-truth instance has no score: `miou` returns NaN for it and
`mean_miou` leaves it out.

The IoUs of all (ground truth, prediction) pairs come from one confusion matrix built with
`np.bincount`, so the cost is linear in the number of pixels with no Python loop over them.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def _check_labels(name: str, a: np.ndarray) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 2:
        raise ValueError(f"{name} must be an (H, W) label image, got shape {a.shape}")
    if a.dtype == bool or not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{name} must have an integer dtype (0 = background, 1..k = instances), "
                         f"got {a.dtype}")
    if a.size and a.min() < 0:
        raise ValueError(f"{name} has negative labels (min {a.min()}); valid: 0 = background, "
                         "1..k = instances")
    return a


def instance_ious(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Each ground-truth instance's best IoU over the predicted instances (0 when none overlaps
    it), in the order of the ground-truth ids: a float64 array, empty when `gt` has no instance.
    Both are (H, W) integer label images, 0 = background; the prediction is restricted to the
    ground-truth foreground, as the paper's mIoU (`miou`, their mean) scores it."""
    pred = _check_labels("pred", pred)
    gt = _check_labels("gt", gt)
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt must have the same shape, got {pred.shape} and {gt.shape}")
    pred = np.where(gt > 0, pred, 0)  # prediction restricted to ground-truth foreground

    # Compact both label sets to 0..K-1 so the confusion matrix stays small whatever the ids.
    g_ids, g_idx = np.unique(gt, return_inverse=True)
    p_ids, p_idx = np.unique(pred, return_inverse=True)
    if not (g_ids > 0).any():
        return np.zeros(0)
    kg, kp = len(g_ids), len(p_ids)
    conf = np.bincount(g_idx.ravel() * kp + p_idx.ravel(), minlength=kg * kp).reshape(kg, kp)

    inter = conf[g_ids > 0][:, p_ids > 0]  # (GT instances, predicted instances) overlaps
    if inter.shape[1] == 0:  # nothing predicted on the GT foreground
        return np.zeros(int((g_ids > 0).sum()))
    g_area = conf[g_ids > 0].sum(axis=1)
    p_area = conf[:, p_ids > 0].sum(axis=0)
    union = g_area[:, None] + p_area[None, :] - inter
    return (inter / union).max(axis=1)  # union >= |g| >= 1, never zero


def miou(pred: np.ndarray, gt: np.ndarray) -> float:
    """The paper's mIoU of one (H, W) predicted label image against the ground truth: the mean
    of `instance_ious`.

    Both are integer label images, 0 = background, 1..k = instances. Returns a float in [0, 1],
    or NaN when `gt` has no instance.
    """
    ious = instance_ious(pred, gt)
    return float(ious.mean()) if ious.size else float("nan")


def miou_batch(preds: Sequence[np.ndarray] | np.ndarray,
               gts: Sequence[np.ndarray] | np.ndarray) -> np.ndarray:
    """Per-image mIoU of paired predictions and ground truths: a float64 array (NaN = no GT)."""
    if len(preds) != len(gts):
        raise ValueError(f"preds and gts must pair up, got {len(preds)} predictions and "
                         f"{len(gts)} ground truths")
    return np.array([miou(p, g) for p, g in zip(preds, gts)], dtype=np.float64)


def mean_miou(scores: Sequence[float] | np.ndarray) -> float:
    """Mean of per-image scores, ignoring NaN (images without instances); NaN if none is left."""
    scores = np.asarray(scores, dtype=np.float64).ravel()
    valid = scores[~np.isnan(scores)]
    return float(valid.mean()) if valid.size else float("nan")
