"""The classical baselines (`evaluation.baselines`) on synthetic height images of discs: the
label-image contract every baseline promises, determinism, accuracy where the task is easy,
edge cases and input errors."""
import inspect
import time

import numpy as np
import pytest

from inseggan_ros.evaluation.baselines import BASELINES, kmeans
from inseggan_ros.core.metrics import miou

SIZE = 64


def disc_scene(centres, radii, tops, size=SIZE):
    """Heights and GT labels of discs seen from above: each a shallow dome (top height at the
    centre, 10 % lower at the rim); where discs overlap the higher one is seen."""
    yy, xx = np.mgrid[:size, :size]
    heights = np.zeros((size, size), np.float32)
    labels = np.zeros((size, size), np.uint8)
    for i, ((cy, cx), r, top) in enumerate(zip(centres, radii, tops), start=1):
        d2 = ((yy - cy) ** 2 + (xx - cx) ** 2) / r ** 2
        h = top * (1 - 0.1 * d2)
        seen = (d2 <= 1) & (h > heights)
        heights[seen] = h[seen]
        labels[seen] = i
    return heights, labels


def with_specks(heights, labels, fraction=0.02, seed=0):
    """The scene with sensor-noise specks: random background pixels marked foreground."""
    specks = (np.random.default_rng(seed).random(labels.shape) < fraction) & (labels == 0)
    return np.where(specks, np.float32(0.05), heights), labels, (labels > 0) | specks


# n well-separated discs of different heights
SEPARATED = disc_scene([(12, 12), (12, 50), (50, 12), (50, 50), (31, 31)], [8] * 5,
                       [1.0, 1.5, 2.0, 2.5, 3.0])
# two overlapping discs: the right one (height 2) lies over the left one (height 1)
TOUCHING = disc_scene([(32, 20), (32, 42)], [12, 12], [1.0, 2.0])


def seven_pieces():
    """More separate pieces than instances (objects seen in parts, say): 7 equal discs on a
    ring, n = 5, heights with a little noise. Before the spectral baseline linked the pieces,
    its eigen-solver took ~4 s on this."""
    angles = np.linspace(0, 2 * np.pi, 7, endpoint=False)
    heights, labels = disc_scene([(32 + 22 * np.sin(a), 32 + 22 * np.cos(a)) for a in angles],
                                 [5] * 7, [1.0] * 7)
    noise = np.random.default_rng(0).normal(0, 0.01, heights.shape).astype(np.float32)
    return np.where(labels > 0, heights + noise, 0).astype(np.float32), labels


SEVEN_PIECES = seven_pieces()
# name -> (heights, GT labels, foreground mask, n)
SCENES = {
    "separated": (*SEPARATED, SEPARATED[1] > 0, 5),
    "touching": (*TOUCHING, TOUCHING[1] > 0, 2),
    "seven_pieces": (*SEVEN_PIECES, SEVEN_PIECES[1] > 0, 5),
    "separated_with_specks": (*with_specks(*SEPARATED), 5),
}


@pytest.mark.parametrize("scene", SCENES)
@pytest.mark.parametrize("name", BASELINES)
def test_label_image_contract_and_determinism(name, scene):
    heights, _, fg, n = SCENES[scene]
    labels = BASELINES[name](heights, fg, n, seed=3)
    assert labels.shape == heights.shape and labels.dtype == np.uint8
    assert (labels[~fg] == 0).all(), "labels outside the foreground"
    assert (labels[fg] > 0).all(), "unlabelled foreground pixels"
    assert set(np.unique(labels[fg]).tolist()) == set(range(1, n + 1))
    again = BASELINES[name](heights.copy(), fg.copy(), n, seed=3)
    np.testing.assert_array_equal(labels, again)


@pytest.mark.parametrize("name", BASELINES)
def test_separated_discs_are_recovered(name):
    heights, gt, fg, n = SCENES["separated"]
    assert miou(BASELINES[name](heights, fg, n), gt) > 0.9


def test_kmeans_recovers_separated_discs_for_any_seed():
    heights, gt, fg, n = SCENES["separated"]
    for seed in range(3):
        assert miou(kmeans(heights, fg, n, seed=seed), gt) > 0.9


@pytest.mark.parametrize("name", ["kmeans", "spectral"])
def test_more_pieces_than_instances_are_grouped(name):
    heights, gt, fg, n = SCENES["seven_pieces"]
    # 7 pieces in 5 labels: at best 3 alone (IoU 1) and 2 merged pairs (IoU 1/2 each):
    # (3 * 1 + 4 * 0.5) / 7 = 5/7 = 0.714
    assert miou(BASELINES[name](heights, fg, n), gt) > 0.65


@pytest.mark.parametrize("name", ["spectral", "felzenszwalb"])
def test_specks_do_not_take_instances(name):
    heights, gt, fg, n = SCENES["separated_with_specks"]
    assert miou(BASELINES[name](heights, fg, n), gt) > 0.9


@pytest.mark.parametrize("name", ["spectral", "felzenszwalb"])
def test_height_step_splits_touching_discs(name):
    heights, gt, fg, n = SCENES["touching"]
    assert miou(BASELINES[name](heights, fg, n), gt) > 0.9


@pytest.mark.parametrize("name", BASELINES)
def test_empty_and_tiny_foreground(name):
    fn = BASELINES[name]
    heights = np.random.default_rng(0).random((SIZE, SIZE)).astype(np.float32)
    empty = np.zeros((SIZE, SIZE), bool)
    out = fn(heights, empty, 5)
    assert out.dtype == np.uint8 and out.shape == (SIZE, SIZE) and not out.any()
    tiny = empty.copy()
    tiny[5, 5:8] = True  # 3 pixels, 5 instances asked for: one label each
    out = fn(heights, tiny, 5)
    assert sorted(out[tiny].tolist()) == [1, 2, 3] and not out[~tiny].any()


@pytest.mark.parametrize("name", BASELINES)
def test_odd_but_valid_input(name):
    fn = BASELINES[name]
    heights, gt, fg, n = SCENES["separated"]
    flat = fn(np.ones_like(heights), fg, n)  # no height information at all
    assert set(np.unique(flat[fg]).tolist()) == set(range(1, n + 1))
    lost = heights.copy()
    lost[~fg] = np.nan  # no reading off the objects is fine
    assert set(np.unique(fn(lost, fg, n)[fg]).tolist()) == set(range(1, n + 1))
    one = fn(heights, fg, 1)
    assert (one[fg] == 1).all() and not one[~fg].any()


@pytest.mark.parametrize("name", BASELINES)
def test_bad_input_is_rejected_with_a_clear_message(name):
    fn = BASELINES[name]
    heights, gt, fg, n = SCENES["separated"]
    with pytest.raises(ValueError, match="shape of heights"):
        fn(heights, fg[:, :32], n)
    with pytest.raises(ValueError, match=r"n must be an integer in 1\.\.255"):
        fn(heights, fg, 0)
    with pytest.raises(ValueError, match=r"n must be an integer in 1\.\.255"):
        fn(heights, fg, 256)
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        fn(heights[None], fg[None], n)
    bad = heights.copy()
    bad[gt == 1] = np.nan
    with pytest.raises(ValueError, match="finite"):
        fn(bad, fg, n)
    with pytest.raises(ValueError, match="seed"):
        fn(heights, fg, n, seed=-1)


def test_registry_has_the_four_baselines_with_one_signature():
    assert list(BASELINES) == ["kmeans", "spectral", "grabcut_kmeans", "felzenszwalb"]
    for fn in BASELINES.values():
        assert list(inspect.signature(fn).parameters) == ["heights", "fg", "n", "seed"]


@pytest.mark.parametrize("scene", SCENES)
@pytest.mark.parametrize("name", BASELINES)
def test_fast_enough_for_run_time(name, scene):
    heights, _, fg, n = SCENES[scene]
    fn = BASELINES[name]
    best = min(_timed(fn, heights, fg, n) for _ in range(2))
    assert best < 0.5, f"{name} took {best:.3f} s for a 64 x 64 frame"


def _timed(fn, *args) -> float:
    start = time.perf_counter()
    fn(*args)
    return time.perf_counter() - start
