"""The paper's mIoU (`core.metrics`) on label images whose answers are worked out by hand,
and against a slow, obviously-correct loop implementation on random label images."""
import math

import numpy as np
import pytest

from inseggan_ros.core.metrics import mean_miou, miou, miou_batch


def reference_miou(pred: np.ndarray, gt: np.ndarray) -> float:
    """The definition, literally: loops over instances, boolean masks, no tricks."""
    gt_ids = sorted(set(gt.ravel().tolist()) - {0})
    if not gt_ids:
        return float("nan")
    restricted = np.where(gt > 0, pred, 0)
    pred_ids = sorted(set(restricted.ravel().tolist()) - {0})
    scores = []
    for g in gt_ids:
        g_mask = gt == g
        best = 0.0
        for p in pred_ids:
            p_mask = restricted == p
            best = max(best, (g_mask & p_mask).sum() / (g_mask | p_mask).sum())
        scores.append(best)
    return sum(scores) / len(scores)


# Three GT instances: A = 1 (4 px), B = 2 (4 px), C = 3 (2 px); 6 background pixels.
GT = np.array([[1, 1, 2, 2],
               [1, 1, 2, 2],
               [0, 0, 3, 3],
               [0, 0, 0, 0]], np.uint8)


def test_perfect_prediction_with_permuted_ids_scores_one():
    pred = np.choose(GT, [0, 7, 3, 200]).astype(np.uint8)  # 1 -> 7, 2 -> 3, 3 -> 200
    assert miou(pred, GT) == 1.0
    assert miou(GT, GT) == 1.0


def test_merging_two_equal_instances_scores_half_each():
    gt = np.array([[1, 1, 2, 2],
                   [1, 1, 2, 2]], np.uint8)
    pred = np.ones_like(gt)  # one predicted instance over both
    # A: |A n P| = 4, |A u P| = 8 -> 0.5; B likewise -> mean (0.5 + 0.5) / 2 = 0.5
    assert miou(pred, gt) == 0.5


def test_merge_plus_exact_instance():
    pred = np.array([[5, 5, 5, 5],
                     [5, 5, 5, 5],
                     [0, 0, 9, 9],
                     [0, 0, 0, 0]], np.uint8)
    # A: 4/8 = 0.5, B: 4/8 = 0.5, C: 2/2 = 1 -> (0.5 + 0.5 + 1) / 3 = 2/3
    assert miou(pred, GT) == pytest.approx(2 / 3)


def test_partial_overlap_takes_best_prediction():
    pred = np.array([[1, 1, 1, 2],
                     [1, 2, 2, 2],
                     [0, 0, 2, 0],
                     [0, 0, 0, 0]], np.uint8)
    # pred 1 = {(0,0),(0,1),(0,2),(1,0)}, pred 2 = {(0,3),(1,1),(1,2),(1,3),(2,2)}
    # A = {(0,0),(0,1),(1,0),(1,1)}: with 1: |n| = 3, |u| = 4 + 4 - 3 = 5 -> 3/5;
    #                               with 2: |n| = 1, |u| = 4 + 5 - 1 = 8 -> 1/8; best 3/5
    # B = {(0,2),(0,3),(1,2),(1,3)}: with 1: |n| = 1, |u| = 7 -> 1/7;
    #                               with 2: |n| = 3, |u| = 4 + 5 - 3 = 6 -> 1/2; best 1/2
    # C = {(2,2),(2,3)}:            with 2: |n| = 1, |u| = 2 + 5 - 1 = 6 -> 1/6; best 1/6
    # mean (3/5 + 1/2 + 1/6) / 3 = (18 + 15 + 5) / 90 = 38/90 = 19/45
    assert miou(pred, GT) == pytest.approx(19 / 45)


def test_prediction_outside_gt_foreground_is_ignored():
    pred = np.array([[1, 1, 2, 2],
                     [1, 1, 2, 2],
                     [1, 4, 3, 3],  # label 1 spills into background, label 4 lives only there
                     [4, 4, 4, 3]], np.uint8)
    assert miou(pred, GT) == 1.0


def test_gt_instance_without_prediction_scores_zero():
    pred = np.where(GT == 1, 1, 0).astype(np.uint8)
    pred[3, 0] = 2  # a prediction on background only: ignored, does not rescue B or C
    # A: 1, B: 0, C: 0 -> 1/3
    assert miou(pred, GT) == pytest.approx(1 / 3)
    assert miou(np.zeros_like(GT), GT) == 0.0


def test_empty_gt_is_nan_and_mean_ignores_it():
    empty = np.zeros((4, 4), np.uint8)
    assert math.isnan(miou(GT, empty))
    scores = miou_batch([GT, GT, np.ones_like(GT)], [GT, empty, GT])
    assert scores.dtype == np.float64 and scores.shape == (3,)
    assert scores[0] == 1.0 and math.isnan(scores[1])
    # all foreground as one instance: A 4/10, B 4/10, C 2/10 -> (0.4 + 0.4 + 0.2) / 3 = 1/3
    assert scores[2] == pytest.approx(1 / 3)
    assert mean_miou(scores) == pytest.approx((1 + 1 / 3) / 2)
    assert math.isnan(mean_miou([float("nan")]))
    assert math.isnan(mean_miou([]))


def test_matches_loop_reference_on_random_label_images():
    rng = np.random.default_rng(0)
    for trial in range(60):
        h, w = rng.integers(1, 24, size=2)
        k_gt, k_pred = rng.integers(0, 7), rng.integers(0, 9)
        dtype = [np.uint8, np.uint16, np.int32, np.int64][trial % 4]
        gt = rng.integers(0, k_gt + 1, size=(h, w)).astype(dtype)
        pred = rng.integers(0, k_pred + 1, size=(h, w)).astype(dtype)
        if trial % 3 == 0:  # sparse, non-consecutive ids
            pred = (pred * 37 % 251).astype(dtype)
        expected = reference_miou(pred, gt)
        got = miou(pred, gt)
        if math.isnan(expected):
            assert math.isnan(got)
        else:
            assert got == pytest.approx(expected, abs=1e-12), (trial, gt, pred)


def test_bad_input_is_rejected_with_a_clear_message():
    with pytest.raises(ValueError, match="same shape"):
        miou(np.zeros((4, 5), np.uint8), GT)
    with pytest.raises(ValueError, match="integer dtype"):
        miou(GT.astype(np.float32), GT)
    with pytest.raises(ValueError, match="negative labels"):
        miou(GT.astype(np.int8) - 1, GT)
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        miou(GT[None], GT[None])
    with pytest.raises(ValueError, match="pair up"):
        miou_batch([GT, GT], [GT])
