"""The model's labels voted within depth superpixels (`superpixels.py`, `superpixel_scale`), and
the parts it missed split off along coarse depth segments (`split_scale`)."""
from dataclasses import replace

import numpy as np
import torch
from conftest import BAGS

from inseggan_ros.io import bags
from inseggan_ros.evaluation import evaluate
from inseggan_ros.core.metrics import mean_miou, miou_batch
from inseggan_ros.runtime.segment import Segmenter
from inseggan_ros.runtime.superpixels import (
    depth_superpixels, frame_segments, split_frame, split_labels, vote_frame, vote_labels)


def two_blocks():
    """Heights of two blocks that touch (column 30), at different heights, on a 64 x 64 floor;
    their true labels."""
    h = np.zeros((64, 64))
    h[10:50, 10:30], h[10:50, 30:54] = 0.3, 0.6
    truth = np.zeros((64, 64), np.uint8)
    truth[10:50, 10:30], truth[10:50, 30:54] = 1, 2
    return h, truth


def test_votes_move_a_misplaced_boundary_onto_the_height_edge():
    h, truth = two_blocks()
    shifted = truth.copy()  # a render a few pixels off: the boundary at column 27
    shifted[10:50, 27:30] = 2
    voted = vote_frame(shifted, h, 2, 50)
    # 120 pixels wrong before; after, at most the one-pixel strip along the edge, which the
    # superpixels' slight blur makes a superpixel of its own (its votes are the render's)
    assert (shifted != truth).sum() == 120 and (voted != truth).sum() <= 40
    assert (voted[10:50, 10:29] == 1).all() and (voted[10:50, 30:54] == 2).all()
    assert (voted[truth == 0] == 0).all(), "background stays background"
    np.testing.assert_array_equal(vote_frame(shifted, h, 2, 0), shifted)  # scale 0: off
    empty = np.zeros((64, 64), np.uint8)
    np.testing.assert_array_equal(vote_frame(empty, h, 2, 50), empty)


def test_every_superpixel_takes_one_label_and_every_part_pixel_keeps_one():
    rng = np.random.default_rng(0)
    h, truth = two_blocks()
    h = h + rng.normal(0, 0.01, h.shape) * (truth > 0)
    noisy = np.where(truth > 0, rng.integers(1, 4, truth.shape), 0).astype(np.uint8)
    voted = vote_frame(noisy, h, 3, 50)
    seg = depth_superpixels(h, noisy > 0, scale=50, sigma=0.3, min_size=20)
    assert ((voted > 0) == (noisy > 0)).all()
    for s in np.unique(seg[noisy > 0]):
        assert len(np.unique(voted[(seg == s) & (noisy > 0)])) == 1
        counts = np.bincount(noisy[(seg == s) & (noisy > 0)], minlength=4)
        assert counts[voted[(seg == s) & (noisy > 0)][0]] == counts.max()  # the most frequent


def test_the_segmenter_votes_its_labels_after_smoothing(cylinder_bag):
    seg, frames = cylinder_bag
    x = frames["x"][:4]
    plain = replace(seg.inference, superpixel_scale=0, split_scale=0)
    voted = seg.segment_batch(x, settings=replace(plain, superpixel_scale=50))["labels"]
    before = seg.segment_batch(x, settings=plain)["labels"]
    expect = vote_labels(before, torch.as_tensor(x), seg.model_cfg.n_instances, 50)
    torch.testing.assert_close(voted, expect)
    assert (voted != before).any()


def test_voting_raises_the_mIoU_on_the_cylinder_sample_bag(cylinder_bag):
    """The same frames, the same run, with and without the vote (measured where it was
    made: 0.863 -> 0.900 on the 16 frames)."""
    seg, frames = cylinder_bag
    scores = {}
    for scale in (0, 50):
        seg.inference = replace(seg.inference, superpixel_scale=scale, split_scale=0)
        r = evaluate.run_methods(frames, seg.model_cfg.n_instances, seg, [], progress=False)
        scores[scale] = mean_miou(miou_batch(r["inseggan"]["labels"], frames["labels"]))
    assert scores[50] > scores[0] + 0.01, scores


def three_blocks():
    """Heights of three blocks side by side at different heights, touching; their labels."""
    h = np.zeros((64, 64))
    h[10:50, 4:24], h[10:50, 24:44], h[10:50, 44:60] = 0.3, 0.6, 0.9
    truth = np.zeros((64, 64), np.uint8)
    truth[10:50, 4:24], truth[10:50, 24:44], truth[10:50, 44:60] = 1, 2, 3
    return h, truth


def test_a_label_over_two_parts_gives_the_part_missed_an_unused_id():
    h, truth = three_blocks()
    merged = np.where(truth == 3, 2, truth).astype(np.uint8)  # two renders on block 1, none on 3
    out, cut = split_frame(merged, h, 3, 800)
    np.testing.assert_array_equal(out, truth)
    assert cut.tolist() == [False, False, True]
    np.testing.assert_array_equal(split_frame(merged, h, 3, 0)[0], merged)  # scale 0: off
    # with only two ids there is none to give: nothing changes
    two, cut2 = split_frame(merged, h, 2, 800)
    np.testing.assert_array_equal(two, merged)
    assert not cut2.any()


def test_a_larger_missed_part_replaces_the_smallest_label():
    h, truth = three_blocks()
    merged = np.where(truth == 3, 2, truth).astype(np.uint8)
    merged[20:24, 8:12] = 3  # a stray label of 16 pixels inside block 1: all three ids are used
    out, cut = split_frame(merged, h, 3, 800)
    np.testing.assert_array_equal(out, truth)  # the stray pixels went to their nearest label, 1
    assert cut.tolist() == [False, False, True]
    # a second piece no larger than the smallest label stays where it is
    stray = truth.copy()
    stray[10:50, 44:48] = 2  # label 2 spills onto block 3 (160 pixels); label 3 keeps 480
    kept, cut3 = split_frame(stray, h, 3, 800)
    np.testing.assert_array_equal(kept, stray)
    assert not cut3.any()


def test_the_segmenter_splits_after_the_vote_and_scores_cut_pieces_zero(cylinder_bag):
    seg, frames = cylinder_bag
    x = frames["x"]
    n = seg.model_cfg.n_instances
    voted = replace(seg.inference, superpixel_scale=50, split_scale=0)
    out = seg.segment_batch(x, settings=replace(voted, split_scale=800))
    before = seg.segment_batch(x, settings=voted)["labels"]
    expect, cut = split_labels(before, torch.as_tensor(x), n, 800)
    torch.testing.assert_close(out["labels"], expect)
    assert cut.any(), "the sample bag has frames where the model missed a part"
    assert (out["scores"][cut] == 0).all() and (out["scores"][~cut] > 0).any()


def test_segments_made_beforehand_give_the_same_labels_and_are_used_only_where_they_fit():
    h, truth = three_blocks()
    lab = truth.copy()
    lab[lab == 3] = 2  # the third part missed: the split has something to do
    fg = lab > 0
    pre = frame_segments(h, fg, (50, 800))
    assert set(pre.by_scale) == {50, 800}
    np.testing.assert_array_equal(vote_frame(lab, h, 3, 50, pre), vote_frame(lab, h, 3, 50))
    for a, b in zip(split_frame(lab, h, 3, 800, pre), split_frame(lab, h, 3, 800)):
        np.testing.assert_array_equal(a, b)
    # segments made for a smaller foreground, or at other scales, are not used
    other = frame_segments(h, fg & (np.arange(64) < 40)[None], (50, 800))
    assert other.get(fg, 50) is None and pre.get(fg, 60) is None
    np.testing.assert_array_equal(vote_frame(lab, h, 3, 50, other), vote_frame(lab, h, 3, 50))
    # one segment over the whole foreground: the split has no edge to cut along
    whole = replace(pre, by_scale={**pre.by_scale, 800: fg.astype(np.int64)})
    assert np.array_equal(split_frame(lab, h, 3, 800, whole)[0], lab)
    assert not np.array_equal(split_frame(lab, h, 3, 800)[0], lab)


def test_the_superpixel_thread_gives_the_node_path_the_same_labels(cylinder_bag):
    """`Segmenter(superpixel_thread=True)` on full frames of the sample bag, in and out of
    turn with the one-thread path: identical labels and scores."""
    seg, _ = cylinder_bag
    frames = [f.metres() for f in bags.read_frames(BAGS / "cylinder_sim", limit=4)]
    cfg = replace(seg.inference, superpixel_scale=50, split_scale=800)
    threaded = Segmenter(seg.G, seg.E, seg.model_cfg, seg.prep_cfg, seg.tau,
                         inference=cfg, superpixel_thread=True)
    for f in frames:
        a, b = seg(f, reconstruction=False, settings=cfg), threaded(f, reconstruction=False)
        np.testing.assert_array_equal(a.labels, b.labels)
        np.testing.assert_array_equal(a.scores, b.scores)
    assert threaded._pool is not None, "the thread made the segments"


def test_the_second_thread_gives_centre_votes_the_same_labels(cylinder_bag):
    """With centre votes on, the net runs in the second thread beside the encoder: the same
    labels and scores as one thread, for the net in float32 and in bfloat16 (native or not)."""
    seg, _ = cylinder_bag
    frames = [f.metres() for f in bags.read_frames(BAGS / "cylinder_sim", limit=3)]
    for precision in ("float32", "bfloat16"):
        cfg = replace(seg.inference, centre_votes="on", split_scale=800,
                      encoder_precision=precision)
        one, two = (Segmenter(seg.G, seg.E, seg.model_cfg, seg.prep_cfg, seg.tau, inference=cfg,
                              superpixel_thread=t, centre_net=seg.centre_net)
                    for t in (False, True))
        for f in frames:
            a, b = one(f, reconstruction=False), two(f, reconstruction=False)
            np.testing.assert_array_equal(a.labels, b.labels)
            np.testing.assert_array_equal(a.scores, b.scores)
        assert one._pool is None and two._pool is not None
