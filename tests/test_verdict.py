"""A loop's label-free verdict (`evaluation.verdict`): every shipped recording-made model
passes it, and a card with the figures of a model that explains nothing fails it by name."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

from inseggan_ros.evaluation import verdict

MODELS = Path(__file__).resolve().parents[1] / "models"
TILTED = sorted(p.parent.name for p in MODELS.glob("*_tilted/card.json"))


@pytest.mark.parametrize("name", TILTED)
def test_the_shipped_recording_made_models_pass(name):
    card = json.loads((MODELS / name / "card.json").read_text())
    assert verdict.verdict(card) == {"ok": True, "problems": []}


def test_a_model_that_explains_nothing_fails_with_its_figures():
    card = json.loads((MODELS / TILTED[0] / "card.json").read_text())
    bad = copy.deepcopy(card)
    bad["measures"]["coverage"] = 0.055
    bad["centre_votes"]["best_val_miou"] = 0.268
    v = verdict.verdict(bad)
    assert not v["ok"]
    assert len(v["problems"]) == 2
    assert "coverage 0.055" in v["problems"][0] and "centre votes mIoU 0.268" in v["problems"][1]


def test_a_card_without_figures_has_nothing_to_judge():
    assert verdict.verdict({}) == {"ok": True, "problems": []}


def test_labels_that_leave_the_frames_edges_far_more_than_the_piles_fail_by_name():
    """The over-centre-votes check (`vote_scale.over_centres`) found the template is not the
    part's shape: the verdict says so with both shares and the vote's scale."""
    card = json.loads((MODELS / TILTED[0] / "card.json").read_text())
    card["vote_scale"] = {"setting": "centre_superpixel_scale", "scale": 120, "mismatch": True,
                          "off_edge": {"piles": 0.015, "frames": 0.092}}
    v = verdict.verdict(card)
    assert not v["ok"] and len(v["problems"]) == 1
    assert "0.092" in v["problems"][0] and "0.015" in v["problems"][0]
    assert "scale 120" in v["problems"][0]
    card["vote_scale"]["mismatch"] = False
    assert verdict.verdict(card)["ok"]
