"""The superpixel vote's scale chosen on labelled frames (`vote_scale.py`: the loop's own
simulated piles; here the cylinder's labelled sample bag)."""
from dataclasses import replace

import numpy as np
import pytest

from conftest import BAGS, REPO
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


def test_off_edge_is_the_share_of_label_boundaries_away_from_height_edges():
    """Two flat squares at two heights: labelled each its own, every boundary is on the height
    edge (0); one square labelled in two halves, the boundary inside it is off every edge."""
    x = np.full((1, 1, 32, 32), -1.0, np.float32)
    fg = np.zeros((1, 32, 32), bool)
    x[0, 0, 4:20, 4:14], x[0, 0, 4:20, 14:24] = -0.5, 0.0  # touching, 0.5 apart
    fg[0, 4:20, 4:24] = True
    own = np.zeros((1, 32, 32), np.uint8)
    own[0, 4:20, 4:14], own[0, 4:20, 14:24] = 1, 2
    assert vote_scale.off_edge(x, fg, own) == 0.0
    halves = own.copy()
    halves[0, 4:20, 14:19] = 1  # the second square cut in its middle
    assert vote_scale.off_edge(x, fg, halves) == pytest.approx(1.0)
    assert np.isnan(vote_scale.off_edge(x, fg, np.where(fg, 1, 0)))  # one label: no boundary


def test_over_centre_votes_the_vote_runs_only_where_the_frames_labels_leave_their_edges():
    """The shipped cylinder's centre votes on its labelled sample frames as the piles: on the
    same frames the labels leave the edges as on the piles, and the vote stays off; on the
    frames zoomed twice (parts twice the size the net knows, cut by its votes) they leave
    them far more often, and the vote runs at the largest scale that costs the piles at
    most VOTE_COST."""
    import torch
    import torch.nn.functional as F

    from inseggan_ros.data import datasets as data
    from inseggan_ros.runtime.segment import Segmenter

    torch.set_num_threads(1)
    seg = Segmenter.from_checkpoint(REPO / "models" / "cylinder" / "model.pt", device="cpu")
    assert seg.inference.centre_votes == "on" and seg.inference.vote_scale == 0
    piles = data.load_bag(BAGS / "cylinder_sim", seg.prep_cfg)
    same = vote_scale.choose(seg, piles, frames=piles)
    assert same["setting"] == "centre_superpixel_scale" and not same["mismatch"]
    assert same["scale"] == 0 and same["off_edge"]["frames"] == same["off_edge"]["piles"]
    assert "off over centre votes" in vote_scale.describe(same)
    x = F.interpolate(torch.as_tensor(piles["x"])[:, :, 16:48, 16:48], scale_factor=2).numpy()
    zoomed = vote_scale.choose(seg, piles, frames={"x": x, "fg": x[:, 0] > -1 + 1e-4})
    share = zoomed["off_edge"]
    ratio, gap = vote_scale.MISMATCH
    assert zoomed["mismatch"] and share["frames"] >= max(ratio * share["piles"],
                                                         share["piles"] + gap), zoomed
    fits = [r["scale"] for r in zoomed["rows"] if r["gain"] >= -vote_scale.VOTE_COST]
    assert zoomed["scale"] == max(fits) and sorted(r["scale"] for r in zoomed["rows"]) == \
        sorted(vote_scale.SCALES)
    assert f"over centre votes at scale {zoomed['scale']}" in vote_scale.describe(zoomed)
    voted = replace(seg.inference, centre_superpixel_scale=zoomed["scale"])
    assert voted.vote_scale == zoomed["scale"]  # the segmenter then votes at it
    # without the user's frames there is nothing to compare: the vote stays off
    assert vote_scale.choose(seg, piles)["scale"] == 0
    with pytest.raises(ValueError, match="centre_superpixel_scale -1 invalid; valid: >= 0"):
        replace(seg.inference, centre_superpixel_scale=-1)


def test_over_centre_votes_taught_on_the_piles_the_scale_is_the_best_by_its_gain_there():
    """Piles the centre votes were taught on (`piles["taught"]`, pasted from the user's frames)
    compare no frames: each scale is scored on them as the segmenter votes, 0 (off) among
    them, and the best kept only where it beats off by more than the tolerance."""
    import torch

    from inseggan_ros.data import datasets as data
    from inseggan_ros.runtime.segment import Segmenter

    torch.set_num_threads(1)
    seg = Segmenter.from_checkpoint(REPO / "models" / "cylinder" / "model.pt", device="cpu")
    piles = {**data.load_bag(BAGS / "cylinder_sim", seg.prep_cfg), "taught": True}
    choice = vote_scale.choose(seg, piles, scales=(50, 1600))
    rows = {r["scale"]: r["miou"] for r in choice["rows"]}
    assert choice["taught"] and sorted(rows) == [0, 50, 1600] and "off_edge" not in choice
    for scale in (0, 1600):
        labels = seg.segment_batch(piles["x"], piles["fg"], settings=replace(
            seg.inference, centre_superpixel_scale=scale))["labels"].numpy()
        assert rows[scale] == pytest.approx(mean_miou(miou_batch(labels, piles["labels"])))
    assert rows[1600] < rows[0] - 0.02, rows  # coarse superpixels join touching parts
    assert choice["scale"] in (0, 50) and "pasted from the user's frames" in \
        vote_scale.describe(choice)
    if choice["scale"] == 50:
        assert rows[50] > rows[0] + vote_scale.TOLERANCE
    assert vote_scale.choose(seg, piles, scales=(50,), tolerance=1.0)["scale"] == 0
