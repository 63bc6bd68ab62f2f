"""The superpixel vote's scale chosen on labelled frames (`vote_scale.py`: the loop's own
simulated piles; here the cylinder's labelled sample bag)."""
from dataclasses import replace

import numpy as np
import pytest

from inseggan_ros.evaluation import vote_scale
from inseggan_ros.core.metrics import mean_miou, miou_batch


def test_each_scale_is_scored_as_the_segmenter_votes_and_the_best_is_kept(cylinder_bag):
    seg, frames = cylinder_bag
    assert seg.inference.superpixel_scale == 50  # the model's own: always scored too
    choice = vote_scale.choose(seg, frames, scales=(20, 400, 1600))
    rows = {r["scale"]: r["miou"] for r in choice["rows"]}
    assert sorted(rows) == [20, 50, 400, 1600] and choice["frames"] == len(frames["x"])
    for scale in (20, 1600):  # the model's labels computed once, voted at each scale: the
        # same labels as the whole pipeline at that scale
        labels = seg.segment_batch(frames["x"], frames["fg"], settings=replace(
            seg.inference, superpixel_scale=scale))["labels"].numpy()
        assert rows[scale] == pytest.approx(mean_miou(miou_batch(labels, frames["labels"])))
    # superpixels as coarse as 1600 cover touching parts together: scored lowest there
    assert rows[1600] < rows[400] - 0.02, rows
    assert rows[choice["scale"]] >= max(rows.values()) - choice["tolerance"], choice
    if choice["scale"] != 50:
        assert rows[choice["scale"]] > rows[50] + vote_scale.TOLERANCE, choice
    assert "labelled simulated piles" in vote_scale.describe(choice)
    # a gain within the tolerance leaves the settings' own scale
    assert vote_scale.choose(seg, frames, scales=(400,), tolerance=1.0)["scale"] == 50


def test_nothing_is_chosen_with_the_vote_off_and_bad_scales_are_named(cylinder_bag):
    seg, frames = cylinder_bag
    own = seg.inference
    try:
        seg.inference = replace(own, superpixel_scale=0)
        off = vote_scale.choose(seg, frames)
        assert off["scale"] == 0 and off["rows"] == [] and "off" in vote_scale.describe(off)
    finally:
        seg.inference = own
    with pytest.raises(ValueError, match="vote scales .* integers >= 1"):
        vote_scale.choose(seg, frames, scales=(50, 0))
    empty = {k: v[:0] for k, v in frames.items() if isinstance(v, np.ndarray)}
    with pytest.raises(ValueError, match="no labelled piles"):
        vote_scale.choose(seg, empty)


def test_the_loop_takes_its_scales_from_its_config_and_refuses_bad_ones():
    from inseggan_ros.learning.loop import LoopConfig

    assert LoopConfig().vote_scales == vote_scale.SCALES
    assert LoopConfig(vote_scales=()).vote_scales == ()  # the export settings' own scale
    for bad in ((50, 0), (50.5,)):
        with pytest.raises(ValueError, match="vote_scales .* integers >= 1, or none"):
            LoopConfig(vote_scales=bad)
