"""The label head: slots matched to true instances, the same for any slot order, refused where a
model has none, trained on labelled simulated scenes until it explains held-out ones better,
shipped inside a model."""
import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from conftest import refused, run_cli, zbuffer_settings

from inseggan_ros.core import checkpoint
from inseggan_ros.data.datasets import load_sim_split
from inseggan_ros.learning.label_head import (
    LabelHead, head_labels, miou_of, proposals, slot_targets)
from inseggan_ros.core.paths import resolve_model
from inseggan_ros.runtime.segment import Segmenter
from inseggan_ros.core.settings import InferenceConfig


def test_each_true_instance_takes_the_slot_that_overlaps_it_most():
    labels = np.zeros((1, 6, 6), np.uint8)
    labels[0, :, :3], labels[0, :, 3:] = 2, 1  # slot 1 (label 2) left, slot 0 right
    gt = np.zeros((1, 6, 6), np.uint8)
    gt[0, :, :2], gt[0, :, 2:5] = 7, 9  # instance 7 mostly left, 9 mostly right
    t = slot_targets(labels, gt, n=2)
    assert (t[0][gt[0] == 7] == 1).all() and (t[0][gt[0] == 9] == 0).all()
    assert (t[0][gt[0] == 0] == -1).all()  # background is not scored


def test_the_head_is_the_same_for_any_order_of_the_slots():
    torch.manual_seed(0)
    head = LabelHead(4).eval()
    x = torch.rand(2, 1, 16, 16) * 2 - 1
    renders = torch.rand(2, 3, 16, 16) * 2 - 1
    labels = renders.argmax(1).to(torch.uint8) + 1
    perm = torch.tensor([2, 0, 1])
    relabel = torch.tensor([0, 2, 3, 1], dtype=torch.uint8)  # label k+1 of slot k, permuted
    with torch.no_grad():
        a = head(x, renders, labels)
        b = head(x, renders[:, perm], relabel[labels.long()])
    torch.testing.assert_close(a[:, perm], b)
    fg = torch.ones(2, 16, 16, dtype=torch.bool)
    fg[:, 0] = False
    out = head_labels(head, x, renders, labels, fg)
    assert out.dtype == torch.uint8 and (out[:, 0] == 0).all() and (out[:, 1:] >= 1).all()


def test_label_head_on_needs_a_model_with_a_head(tmp):
    with pytest.raises(ValueError, match="label_head 'maybe' invalid; valid: on, off"):
        InferenceConfig(label_head="maybe")
    state = checkpoint.load(resolve_model("cylinder"))
    state["inference"] = {**state["inference"], "label_head": "on", "centre_votes": "off"}
    state.pop("label_head", None)
    checkpoint.save(tmp / "bad.pt", state)
    with pytest.raises(checkpoint.CheckpointError, match="label head it does not have"):
        Segmenter.from_checkpoint(tmp / "bad.pt", device="cpu")
    seg = Segmenter.from_checkpoint(resolve_model("cylinder"), device="cpu")
    if seg.label_head is None:
        x = np.full((1, 1, 64, 64), -1, np.float32)
        with pytest.raises(ValueError, match="no label head"):
            seg.segment_batch(x, settings=replace(seg.inference, label_head="on",
                                                  centre_votes="off"))


def _held_out_loss(head, args, targets) -> float:
    with torch.no_grad():
        return float(torch.nn.functional.cross_entropy(head(*args[:3]), targets,
                                                       ignore_index=-1))


def test_a_short_training_run_explains_held_out_scenes_better_and_ships_in_the_model(tmp):
    """`inseggan head` on 48 labelled scenes of a part, 100 iterations of 8: on held-out scenes
    its cross-entropy falls well below the untrained head's (which gives the z-buffer's labels)
    and its labels are no worse; the model it writes segments with it."""
    sim = tmp / "sim"
    run_cli("simulate", "--quiet", "--object", "cylinder", "--count", "64", "--split",
            "48,16,0", "--seed", "31", "--workers", "2", "--out", sim, check=True, timeout=600)
    # the shipped cylinder as it labelled before its centre votes: the z-buffer's labels of the
    # best of 8 starting points (realtime.yaml), which the head corrects
    state = checkpoint.load(resolve_model("cylinder"))
    state["inference"] = zbuffer_settings(InferenceConfig.from_dict(state["inference"])).to_dict()
    checkpoint.save(tmp / "cylinder.pt", {k: v for k, v in state.items()
                                          if k not in ("format", "centre_net")})
    out = tmp / "head"
    p = run_cli("head", "--model", tmp / "cylinder.pt", "--sim", sim, "--out", out, "--iterations",
                "100", "--batch", "8", "--quiet", check=True, timeout=600)
    assert "label head in" in p.stdout
    summary = json.loads((out / "summary.json").read_text())
    zbuffer = summary["history"][0]["val_miou_zbuffer"]
    assert summary["history"][0]["val_miou"] == pytest.approx(zbuffer)  # untrained = z-buffer
    seg = Segmenter.from_checkpoint(out / "model.pt", device="cpu")
    assert seg.label_head is not None and seg.inference.label_head == "on"
    torch.manual_seed(0)
    untrained = LabelHead(seg.label_head.width).eval()
    val = load_sim_split(sim, "val", seg.prep_cfg)
    prop = proposals(seg, val["x"], val["fg"])
    args = [torch.from_numpy(a) for a in (val["x"], prop["renders"], prop["labels"], val["fg"])]
    n = prop["renders"].shape[1]
    targets = torch.from_numpy(slot_targets(prop["labels"], val["labels"], n))
    before, after = (_held_out_loss(h, args, targets) for h in (untrained, seg.label_head))
    # measured on 30 held-out cone scenes: 0.57 -> 0.17 (training loss); mIoU unchanged at
    # this size (0.897 -> 0.898); at full size the head adds 0.07 on simulated scenes
    assert after < 0.7 * before, (before, after)
    assert miou_of(head_labels(seg.label_head, *args).numpy(), val["labels"]) > zbuffer - 0.02
    # the segmenter's own path: labels through the model with its head
    out_seg = seg.segment_batch(val["x"][:4], val["fg"][:4])
    assert miou_of(out_seg["labels"].numpy(), val["labels"][:4]) > 0.5


def test_inseggan_head_names_a_data_set_without_scenes(tmp):
    p = refused("head", "--model", "cylinder", "--sim", tmp / "none", "--out", tmp / "o")
    assert p.returncode == 2 and "meta.json" in p.stderr, p.stderr
    p = refused("head", "--model", tmp / "none.pt", "--sim", tmp, "--out", tmp / "o")
    assert p.returncode == 2 and "none.pt" in p.stderr, p.stderr
