"""Centre votes: targets that decode to the labels they came from, a short training run that must
segment held-out piles better than the untrained network, the model it ships, and the settings
and stages that refuse what cannot work."""
import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from conftest import refused, run_cli
from inseggan_ros.core import checkpoint
from inseggan_ros.core import settings
from inseggan_ros.learning.centres import (
    OFFSET_UNIT, CentreConfig, CentreNet, centre_labels, decode, fit, match_to_renders, miou_of,
    piles_part, targets)
from inseggan_ros.data.datasets import load_sim_split
from inseggan_ros.learning.loop import LoopConfig
from inseggan_ros.core.paths import resolve_model
from inseggan_ros.runtime.segment import Segmenter
from inseggan_ros.core.settings import InferenceConfig


def _blocks() -> torch.Tensor:
    """Two frames of separate rectangles, labelled 1.. (a part per rectangle)."""
    lab = torch.zeros(2, 64, 64, dtype=torch.uint8)
    lab[0, 5:15, 5:40] = 1
    lab[0, 20:50, 10:18] = 2
    lab[0, 30:40, 30:60] = 3
    lab[1, 10:30, 10:30] = 2
    lab[1, 40:60, 40:52] = 1
    return lab


def _perfect_prediction(labels: torch.Tensor, n: int) -> torch.Tensor:
    heat, offsets = targets(labels, n)
    logit = torch.logit(heat.clamp(1e-4, 1 - 1e-4))
    return torch.cat([logit[:, None], offsets], 1)


def test_the_targets_decode_to_the_labels_they_came_from():
    labels = _blocks()
    heat, offsets = targets(labels, 5)
    assert (heat.amax((1, 2)) > 0.9).all()  # 1 where a centre falls on a pixel
    # every part's pixels point at one place: their mean
    ys, xs = np.nonzero(labels[0].numpy() == 2)
    vy = ys + offsets[0, 0].numpy()[ys, xs] * OFFSET_UNIT
    vx = xs + offsets[0, 1].numpy()[ys, xs] * OFFSET_UNIT
    assert np.allclose(vy, ys.mean(), atol=1e-4) and np.allclose(vx, xs.mean(), atol=1e-4)
    decoded = decode(_perfect_prediction(labels, 5), labels > 0, 5)
    assert miou_of(decoded.numpy(), labels.numpy()) == pytest.approx(1.0)
    # a frame of one part gives one instance, not n
    one = torch.zeros(1, 64, 64, dtype=torch.uint8)
    one[0, 20:30, 10:50] = 1
    assert decode(_perfect_prediction(one, 5), one > 0, 5).unique().tolist() == [0, 1]
    # a part with a hole (a nut lying flat): its centre is in the hole, off the foreground,
    # and it is still found
    ring = torch.zeros(1, 64, 64, dtype=torch.uint8)
    ring[0, 10:30, 10:30] = 1
    ring[0, 15:25, 15:25] = 0
    ring[0, 40:50, 35:60] = 2
    decoded = decode(_perfect_prediction(ring, 5), ring > 0, 5)
    assert miou_of(decoded.numpy(), ring.numpy()) == pytest.approx(1.0)


def test_instances_take_the_id_of_the_render_they_overlap_most():
    labels = _blocks()
    zbuffer = labels.clone()
    zbuffer[0][labels[0] == 1], zbuffer[0][labels[0] == 3] = 3, 1  # renders in another order
    zbuffer[0, 5:15, 30:40] = 2  # and a little off
    matched = match_to_renders(labels, zbuffer, 5)
    assert (matched[0][labels[0] == 1] == 3).all() and (matched[0][labels[0] == 3] == 1).all()
    assert (matched[1] == labels[1]).all()
    assert (matched == 0).equal(labels == 0)


def test_settings_and_loop_refuse_what_cannot_work(tmp):
    with pytest.raises(ValueError, match="centre_votes 'yes' invalid; valid: on, off"):
        InferenceConfig(centre_votes="yes")
    with pytest.raises(ValueError, match="at most one on"):
        InferenceConfig(centre_votes="on", label_head="on")
    with pytest.raises(ValueError, match="centre_iterations -1 invalid"):
        LoopConfig(centre_iterations=-1)
    with pytest.raises(ValueError, match="centre_iterations 3 invalid; valid: 0 .* or >= 4"):
        LoopConfig(centre_iterations=3)
    with pytest.raises(ValueError, match="at most one above 0"):
        LoopConfig(centre_iterations=10, head_iterations=10)
    with pytest.raises(ValueError, match="lr 0 invalid; valid: in"):
        CentreConfig(lr=0)
    with pytest.raises(ValueError, match="batch 0 invalid; valid: >= 1"):
        CentreConfig(batch=0)
    with pytest.raises(ValueError, match="iterations 2 invalid; valid: >= 4"):
        CentreConfig(iterations=2)
    state = checkpoint.load("models/cylinder/model.pt")  # shipped with centre votes, on
    assert state["inference"]["centre_votes"] == "on"
    checkpoint.save(tmp / "m.pt", {k: v for k, v in state.items()
                                   if k not in ("format", "centre_net")})
    with pytest.raises(checkpoint.CheckpointError, match="centre-vote network it does not have"):
        Segmenter.from_checkpoint(tmp / "m.pt")
    checkpoint.save(tmp / "none.pt", {**{k: v for k, v in state.items()
                                         if k not in ("format", "centre_net")},
                                      "inference": {**state["inference"], "centre_votes": "off"}})
    seg = Segmenter.from_checkpoint(tmp / "none.pt", device="cpu")  # a model without the net
    with pytest.raises(ValueError, match="no centre-vote network"):
        seg.check(replace(seg.inference, centre_votes="on"))
    x = np.full((1, 1, 64, 64), -1.0, np.float32)
    with pytest.raises(ValueError, match="no centre-vote network"):
        seg.segment_batch(x, settings=replace(seg.inference, centre_votes="on"))
    # a teacher's centre votes: only over the model's own labels, and only where it has them
    with pytest.raises(ValueError, match="no centre-vote network to label with"):
        fit(tmp / "none.pt", tmp, tmp / "out", self_labels=True, teacher_votes=True)
    with pytest.raises(ValueError, match="without self-labels.*valid: with --self-labels"):
        fit("models/cylinder/model.pt", tmp, tmp / "out", teacher_votes=True)
    # the teacher's settings: only over the model's own labels, and only a readable file
    with pytest.raises(ValueError, match="teacher's settings .* without self-labels"):
        fit("models/cylinder/model.pt", tmp, tmp / "out", teacher_settings="quality")
    with pytest.raises(ValueError, match="nothing.yaml: not a readable parameters file"):
        fit("models/cylinder/model.pt", tmp, tmp / "out", self_labels=True,
            teacher_settings=str(tmp / "nothing.yaml"))


def test_a_short_training_run_segments_held_out_piles_better_and_ships_in_the_model(tmp):
    """`inseggan centres` on 48 labelled piles, 150 iterations of 8: the held-out piles' mIoU
    rises well above the untrained network's; the model it writes segments with it (ids of the
    renders, no vote), its card line says so, and started again it resumes, trains no more and
    refuses other settings in the same folder."""
    sim = tmp / "sim"
    run_cli("simulate", "--quiet", "--object", "cylinder", "--count", "64", "--split",
            "48,16,0", "--seed", "31", "--workers", "2", "--out", sim, check=True, timeout=600)
    out = tmp / "centres"
    args = ("centres", "--model", "cylinder", "--sim", sim, "--out", out, "--iterations", "150",
            "--batch", "8", "--width", "8", "--threads", "1", "--quiet")
    p = run_cli(*args, check=True, timeout=600)
    assert "centre votes in" in p.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert (out / "curves.png").stat().st_size > 0
    seg = Segmenter.from_checkpoint(out / "model.pt", device="cpu")
    assert seg.centre_net is not None and seg.inference.centre_votes == "on"
    assert (checkpoint.load(out / "model.pt")["centre_net"]["piles_part"]
            == "the simulator's cylinder (the true part)")
    val = load_sim_split(sim, "val", seg.prep_cfg)
    n = seg.model_cfg.n_instances
    torch.manual_seed(0)
    untrained = miou_of(centre_labels(CentreNet(8).eval(), val["x"], val["fg"], n).numpy(),
                        val["labels"])
    trained = miou_of(centre_labels(seg.centre_net, val["x"], val["fg"], n).numpy(),
                      val["labels"])
    assert summary["best_val_miou"] == pytest.approx(trained)
    # measured: 0.40 -> 0.85 (0.84 in AVX2 mode) at this size; at full size (3,000 piles,
    # 3,000 iterations of 32) 0.96 on the cylinder's piles
    assert trained > untrained + 0.15, (untrained, trained)
    # the segmenter's path: the net's instances, each with the id of the render it overlaps most
    settings = replace(seg.inference, encoder_precision="float32")
    got = seg.segment_batch(val["x"], val["fg"], settings=settings)
    zbuffer = seg.segment_batch(val["x"], val["fg"], settings=replace(settings,
                                                                      centre_votes="off"))
    assert not torch.equal(got["labels"], zbuffer["labels"])
    assert miou_of(got["labels"].numpy(), val["labels"]) > trained - 0.05
    raw = replace(settings, smooth=replace(settings.smooth, iters=0))
    before = seg.model_labels(val["x"], val["fg"], settings=replace(raw, centre_votes="off"))
    mine = centre_labels(seg.centre_net, val["x"], val["fg"], n)
    assert torch.equal(seg.model_labels(val["x"], val["fg"], settings=raw)["labels"],
                       match_to_renders(mine, before["labels"], n))
    # a finished run started again trains nothing more; other settings are refused
    mtime = (out / "net.pt").stat().st_mtime_ns
    run_cli(*args, check=True, timeout=600)
    assert (out / "net.pt").stat().st_mtime_ns == mtime
    p = refused("centres", "--model", "cylinder", "--sim", sim, "--out", out, "--iterations",
                "150", "--batch", "4", "--width", "8", "--threads", "1", "--quiet")
    assert p.returncode != 0 and "made with other settings" in p.stderr, p.stderr
    p = refused("centres", "--model", "cylinder", "--sim", sim, "--out", tmp / "bag_cut",
                "--self-labels", "--as-bag", "--quiet")
    assert p.returncode != 0 and "valid: one of them" in p.stderr, p.stderr


def test_self_labels_teach_the_net_the_models_own_labels_of_the_users_frames(tmp):
    """`inseggan centres --self-labels`: the data set's training frames, labelled by the model
    itself (centre votes off; no true label read), teach the net; the last --held-out frames
    choose the iteration. The labels it cached are the model's own, not the true ones; the net
    learns them; the card says where it was taught; too few frames are refused by name."""
    from inseggan_ros.evaluation.modelcard import _centres_line, centres_record

    data = tmp / "data"
    run_cli("simulate", "--quiet", "--object", "cylinder", "--count", "56", "--split",
            "56,0,0", "--seed", "37", "--workers", "2", "--out", data, check=True, timeout=600)
    out = tmp / "self"
    p = run_cli("centres", "--model", "cylinder", "--sim", data, "--self-labels", "--held-out",
                "8", "--out", out, "--iterations", "150", "--batch", "8", "--width", "8",
                "--threads", "1", "--quiet", check=True, timeout=600)
    assert "held-out self-labelled frames" in p.stdout
    seg = Segmenter.from_checkpoint(out / "model.pt", device="cpu")
    train = load_sim_split(data, "train", seg.prep_cfg)
    with np.load(out / "self_labels.npz") as saved:
        assert saved["done"].all()
        cached = saved["labels"]
    assert cached.shape == train["labels"].shape
    own = seg.segment_batch(train["x"], train["fg"], settings=replace(
        seg.inference, centre_votes="off", encoder_precision="float32"))["labels"].numpy()
    to_own, to_truth = miou_of(cached, own), miou_of(cached, train["labels"])
    assert to_own > 0.98 and to_truth < to_own - 0.02, (to_own, to_truth)
    # the net learns them: on the 8 held-out frames, far above an untrained net
    n = seg.model_cfg.n_instances
    x, fg = train["x"][-8:], train["fg"][-8:]
    torch.manual_seed(0)
    untrained = miou_of(centre_labels(CentreNet(8).eval(), x, fg, n).numpy(), cached[-8:])
    trained = miou_of(centre_labels(seg.centre_net, x, fg, n).numpy(), cached[-8:])
    assert trained > untrained + 0.15, (untrained, trained)
    record = centres_record(checkpoint.load(out / "model.pt"))
    assert record["teacher"] == "self-labels" and record["train_frames"] == 48
    card = {"centre_votes": record, "inference": {"centre_votes": "on"}}
    assert "labelled by this model itself" in _centres_line(card)[0]
    # the teacher's settings (--teacher-settings): the labels are those the model gives with them
    run_cli("centres", "--model", "cylinder", "--sim", data, "--self-labels", "--held-out", "8",
            "--teacher-settings", "fastest", "--out", tmp / "fastest", "--iterations", "4",
            "--batch", "8", "--width", "8", "--threads", "1", "--quiet", check=True, timeout=600)
    with np.load(tmp / "fastest" / "self_labels.npz") as saved:
        cached = saved["labels"]
    fastest = settings.apply_file(seg.inference, "fastest", seg.stored_settings)
    theirs = seg.segment_batch(train["x"], train["fg"], settings=replace(
        fastest, centre_votes="off", encoder_precision="float32"))["labels"].numpy()
    assert miou_of(cached, theirs) > 0.98
    record = centres_record(checkpoint.load(tmp / "fastest" / "model.pt"))
    card = {"centre_votes": record, "inference": {"centre_votes": "on"}}
    assert "with the settings of `fastest`" in _centres_line(card)[0]
    p = refused("centres", "--model", "cylinder", "--sim", data, "--self-labels", "--held-out",
                "56", "--out", tmp / "few", "--iterations", "10", "--quiet")
    assert p.returncode != 0 and "training frames" in p.stderr and "held out" in p.stderr


def test_self_labels_from_a_recording_label_all_its_frames(tmp):
    """`--self-labels` with a recording (a bag) instead of a data set: all its frames, cut as
    the model cuts a bag's, labelled by the model itself; the last --held-out choose. With
    --teacher-centre-votes the labels are the model's as it ships (its centre votes on), not
    its z-buffer's. A folder that is neither a data set nor a bag is refused by name."""
    from inseggan_ros.data.datasets import load_bag
    from inseggan_ros.evaluation.modelcard import _centres_line, centres_record

    bag = tmp / "bag"
    run_cli("simulate-bag", "--quiet", "--object", "cylinder", "--count", "16", "--seed", "5",
            "--out", bag, check=True, timeout=600)
    out = tmp / "self"
    run_cli("centres", "--model", "cylinder", "--sim", bag, "--self-labels", "--held-out", "4",
            "--out", out, "--iterations", "20", "--batch", "4", "--width", "8", "--threads", "1",
            "--quiet", check=True, timeout=600)
    seg = Segmenter.from_checkpoint(out / "model.pt", device="cpu")
    frames = load_bag(bag, seg.prep_cfg)
    with np.load(out / "self_labels.npz") as saved:
        assert saved["done"].all() and len(saved["labels"]) == 16
        cached = saved["labels"]
    own = seg.segment_batch(frames["x"], frames["fg"], settings=replace(
        seg.inference, centre_votes="off", encoder_precision="float32"))["labels"].numpy()
    assert miou_of(cached, own) > 0.98
    record = centres_record(checkpoint.load(out / "model.pt"))
    assert record["teacher"] == "self-labels" and record["train_frames"] == 12
    # the model as it ships labels (its own centre votes on): a second round's teacher
    out2 = tmp / "self_votes"
    run_cli("centres", "--model", "cylinder", "--sim", bag, "--self-labels",
            "--teacher-centre-votes", "--held-out", "4", "--out", out2, "--iterations", "4",
            "--batch", "4", "--width", "8", "--threads", "1", "--quiet", check=True, timeout=600)
    with np.load(out2 / "self_labels.npz") as saved:
        votes = saved["labels"]
    shipped = Segmenter.from_checkpoint(resolve_model("cylinder"), device="cpu")
    assert shipped.inference.centre_votes == "on"
    theirs = shipped.segment_batch(frames["x"], frames["fg"], settings=replace(
        shipped.inference, encoder_precision="float32"))["labels"].numpy()
    assert miou_of(votes, theirs) > 0.98
    assert miou_of(votes, own) < miou_of(votes, theirs) - 0.01  # not the z-buffer's
    record = centres_record(checkpoint.load(out2 / "model.pt"))
    assert record["teacher"] == "self-labels with its centre votes"
    card = {"centre_votes": record, "inference": {"centre_votes": "on"}}
    assert "with its centre votes on" in _centres_line(card)[0]
    (tmp / "empty").mkdir()
    p = refused("centres", "--model", "cylinder", "--sim", tmp / "empty", "--self-labels",
                "--out", tmp / "none", "--iterations", "10", "--quiet")
    assert p.returncode != 0 and str(tmp / "empty") in p.stderr, p.stderr
    assert "meta.json" in p.stderr and "recording" in p.stderr, p.stderr


@pytest.mark.parametrize("model, words", [
    ("models/wooden_block_tilted", "fitted by reconstruction as 1 convex piece of 4 walls (best "
                                   "of 1500 iterations, at 1000)"),
    ("models/cylinder_tilted", "the learned rod of"),
    ("cylinder", "the simulator's cylinder (the true part)")])
def test_the_card_names_what_the_piles_are_of_for_every_shipped_kind_of_record(tmp, model, words):
    """The piles' part as the card says it, read from their meta.json: a shipped model's
    template (the block's shape-fit record is of an earlier format) or a library part."""
    from inseggan_ros.sim.dataset import FORMAT

    (tmp / "sim").mkdir()
    (tmp / "sim" / "meta.json").write_text(json.dumps(
        {"format": FORMAT, "scene": {"object": model}}))
    assert words in piles_part(tmp / "sim")
