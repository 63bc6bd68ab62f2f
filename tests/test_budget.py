"""The loop's time budget (`learning/budget.py`): the time left split over the stages to come,
the centre votes' iterations fitted to their share at this machine's own step time, the
family's candidates stopped where their share is spent, and what was cut said."""
import json
import math
import time
from pathlib import Path

import pytest
from conftest import REPO

from inseggan_ros.core import checkpoint
from inseggan_ros.learning import budget as budget_mod
from inseggan_ros.learning import family
from inseggan_ros.learning.budget import Budget, centre_iterations
from inseggan_ros.learning.centres import CentreConfig, step_seconds
from inseggan_ros.learning.loop import LoopConfig, _centre_iterations
from inseggan_ros.learning.piles import BagFrames, pile_view
from inseggan_ros.runtime.preprocess import PreprocessConfig

ROD = Path(__file__).resolve().parent / "data" / "wooden_block_unsupervised.pt"  # a block's rod
BAG = REPO / "bags" / "wooden_block_realsense"  # 8 frames of 4 blocks, the rod's camera


def _spent(b: Budget, seconds: float) -> Budget:
    b.start = time.monotonic() - seconds
    return b


def test_the_time_left_is_split_over_the_stages_still_to_come_by_their_weights():
    w = budget_mod.WEIGHTS
    b = _spent(Budget(60.0, ("shape", "family", "simulate", "centres", "export")), 0.0)
    assert b.share("shape") == pytest.approx(3600 * w["shape"], rel=1e-3)
    # ten minutes later, the family gets its weight's part of the 50 minutes left over the
    # stages from it on; a run without a family gives the centres its part
    _spent(b, 600.0)
    rest = w["family"] + w["simulate"] + w["centres"] + w["export"]
    assert b.share("family") == pytest.approx(3000 * w["family"] / rest, rel=1e-3)
    b2 = _spent(Budget(60.0, ("simulate", "centres", "export")), 600.0)
    assert b2.share("centres") == pytest.approx(
        3000 * w["centres"] / (w["centres"] + w["export"]), rel=1e-3)
    assert set(b.record()["shares_minutes"]) == {"shape", "family"}
    # past the deadline every share is 0; the record says the run went over
    _spent(b, 3700.0)
    assert b.share("centres") == 0.0 and b.record()["over"]
    # no budget: nothing bounded, nothing recorded
    free = Budget(0.0)
    assert free.share("family") == math.inf and not free.record()["over"]
    with pytest.raises(ValueError, match="stage 'family' invalid; valid: simulate"):
        Budget(60.0, ("simulate", "centres", "export")).share("family")


@pytest.mark.parametrize("minutes", [-1.0, 2.0, math.nan, math.inf])
def test_a_budget_too_short_or_not_a_number_is_refused_by_name(minutes):
    with pytest.raises(ValueError, match="minutes .* invalid; valid: 0 .* or 5 and more"):
        Budget(minutes)
    with pytest.raises(ValueError, match="minutes .* invalid"):
        LoopConfig(minutes=minutes)


def test_centre_iterations_fit_the_share_between_a_floor_and_what_was_asked():
    assert centre_iterations(3000, math.inf, 0.2) == 3000
    assert centre_iterations(3000, 400.0, 0.2) == int(budget_mod.MARGIN * 400 / 0.2)
    assert centre_iterations(3000, 1e6, 0.2) == 3000
    assert centre_iterations(3000, 1.0, 0.2) == budget_mod.MIN_CENTRE_ITERATIONS
    assert centre_iterations(40, 1.0, 0.2) == 40


def test_the_centre_stage_takes_the_iterations_its_share_holds_and_keeps_them_on_resume(tmp):
    step = step_seconds(CentreConfig())
    assert 0 < step < 60
    cfg = LoopConfig(centre_iterations=3000)
    b = _spent(Budget(10.0, ("centres", "export")), 0.0)
    share = 600 * budget_mod.WEIGHTS["centres"] / (budget_mod.WEIGHTS["centres"]
                                                   + budget_mod.WEIGHTS["export"])
    got = _centre_iterations(cfg, tmp / "centres", b)
    kept = json.loads((tmp / "centres" / "budget.json").read_text())
    # the count is the share over the step time the stage itself measured on this machine (a
    # second timing on a busy machine may differ from it by any factor)
    assert kept["share_s"] == pytest.approx(share, rel=1e-3) and 0 < kept["step_s"] < 60
    assert got == kept["iterations"] == centre_iterations(3000, kept["share_s"], kept["step_s"])
    assert kept["asked"] == 3000
    if got < 3000:
        assert b.cuts == [f"centre votes: {got} of 3000 iterations"]
    # resumed, with any budget or none, the kept count is the schedule
    assert _centre_iterations(cfg, tmp / "centres", Budget(0.0)) == got
    # no budget: what was asked, nothing written
    assert _centre_iterations(cfg, tmp / "free", Budget(0.0)) == 3000
    assert not (tmp / "free").exists()


def test_the_family_makes_its_first_candidate_and_no_more_once_its_share_is_spent(tmp):
    """With no time left, the first candidate is still made and scored on the grid alone (no
    step past its end); the others are listed as not made for the budget."""
    state = checkpoint.load(ROD)
    data = BagFrames(BAG, 4)
    x = data.frames(PreprocessConfig.from_dict(state["preprocess_config"]))[0]["x"]
    cfg = family.FamilyConfig(families=("rod", "taper", "ring"), piles=4, workers=2)
    choice = family.choose(ROD, x, data, None, pile_view(data, state), tmp / "family", cfg,
                           progress=False, seconds=0.0)
    rows = {r["family"]: r for r in choice["rows"]}
    assert choice["kept"] == "rod"
    assert list(rows["rod"]["pile_w1_by_scale"]) == [f"{v:g}" for v in cfg.scales]
    assert rows["taper"] == {"family": "taper", "skipped": family.TIME_SKIP}
    assert rows["ring"] == {"family": "ring", "skipped": family.TIME_SKIP}
