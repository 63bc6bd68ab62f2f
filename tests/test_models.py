"""Every shipped model: its card agrees with its checkpoint, and it segments shipped sample frames.

The quality check compares InSeGAN with K-Means on the frames of the model's sample bag. The card
records both scores, measured at export; the test measures them again (they must agree to within
what another CPU's arithmetic changes, CPU_TOLERANCE), and where the card records InSeGAN clearly
below K-Means, the comparison is expected to fail (strict xfail: should a retrained model beat
K-Means, the test fails until the card and README say so).
"""
import functools
import json
from dataclasses import replace
from pathlib import Path

import pytest
from conftest import BAGS, REPO, refused, run_cli

from inseggan_ros.core import checkpoint
from inseggan_ros.data import datasets as data
from inseggan_ros.evaluation import evaluate
from inseggan_ros.core.metrics import mean_miou
from inseggan_ros.evaluation.modelcard import card_markdown, full_resolution_scores, markdown
from inseggan_ros.runtime.segment import Segmenter

MODELS = sorted(p.parent for p in (REPO / "models").glob("*/card.json"))


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """As the cards were measured (and as the node runs by default): one torch thread. The
    refinement picks among starting points by fitting loss, and another thread count's
    rounding can tip a pick (the cylinder bag: 0.851 with one thread, 0.861 with two)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def below_kmeans(card: dict, full_resolution: bool = False) -> bool:
    """What the card records for the model's sample bag: InSeGAN not above K-Means (at 64 x 64,
    or at the bag's full resolution, as the segmenter node outputs)."""
    b = card["sample_bag_scores"]
    if full_resolution:
        b = b["full_resolution"]
    return b["inseggan"] <= b["kmeans"]


def test_the_three_issue_models_and_the_node_default_are_shipped():
    from inseggan_ros.ros.segmenter import DEFAULT_MODEL

    names = {p.name for p in MODELS}
    assert {"cylinder", "hex_nut", "wooden_block"} <= names, names
    assert DEFAULT_MODEL in names


@pytest.mark.parametrize("folder", MODELS, ids=[p.name for p in MODELS])
def test_card_matches_checkpoint(folder):
    card = json.loads((folder / "card.json").read_text())
    path = folder / "model.pt"
    assert path.stat().st_size <= 20 * 2**20, "at most 20 MB per model"
    state = checkpoint.load(path)
    assert "discriminator" not in state and "optimizers" not in state  # inference weights only
    assert card["model_config"] == state["model_config"]
    assert card["n_instances"] == state["model_config"]["n_instances"]
    assert card["tau"] == pytest.approx(state["tau"])
    inference = state["inference"]  # the setting names of today, or of before 2026-11-23
    assert card["refine_steps"] == inference["refine_steps"]
    assert card["hypotheses"] == inference.get("refine_hypotheses", inference.get("hypotheses"))
    assert card["smooth_iters"] == inference["smooth"]["iters"]
    assert card["precision"] == state["precision"]
    assert card["iterations"] == state["iteration"]
    seg = Segmenter.from_checkpoint(path, device="cpu")
    cfg = seg.inference
    assert seg.tau == pytest.approx(card["tau"]) and cfg.refine_steps == card["refine_steps"]
    assert cfg.refine_hypotheses == card["hypotheses"] and cfg.smooth.iters == card["smooth_iters"]
    assert cfg.refine_keep == card.get("keep", 0)
    readme = (folder / "README.md").read_text()
    assert readme == markdown(card), "README.md is the card as the export writes it"
    assert f"{card['tau']:.3f}" in readme and (folder / "qualitative.png").is_file()


def load_as_measured(folder: Path):
    """The shipped model with its card's encoder and centre-net precisions (what `auto`
    resolved to where the card was measured), so that a CPU without native bfloat16 measures
    the same arithmetic."""
    card = json.loads((folder / "card.json").read_text())
    seg = Segmenter.from_checkpoint(folder / "model.pt", device="cpu")
    seg.inference = replace(seg.inference,
                            encoder_precision=card.get("encoder_precision",
                                                       seg.inference.encoder_precision),
                            centre_precision=card.get("centre_precision",
                                                      seg.inference.centre_precision))
    return seg


@functools.lru_cache(maxsize=None)
def sample_bag_scores(folder: Path) -> tuple[float, float, int]:
    """(InSeGAN mIoU, K-Means mIoU, frames) on the model's shipped sample bag, at 64 x 64."""
    card = json.loads((folder / "card.json").read_text())
    seg = load_as_measured(folder)
    frames = data.load_bag(BAGS / card["sample_bag"], seg.prep_cfg)
    assert frames["labels"] is not None and len(frames["x"]) >= 6
    results = evaluate.run_methods(frames, seg.model_cfg.n_instances, seg, ["kmeans"],
                                   progress=False)
    ours, km = mean_miou(results["inseggan"]["scores"]), mean_miou(results["kmeans"]["scores"])
    print(f"{folder.name}: InSeGAN {ours:.3f} vs K-Means {km:.3f} on {len(frames['x'])} frames")
    return ours, km, len(frames["x"])


# How far a card's scores move with the CPU's arithmetic, measured: the cylinder bag at full
# resolution scores 0.868 with a bfloat16 encoder on AVX512-BF16 (where the card was made) and
# 0.850 in float32, in emulated bfloat16 on AVX2, and in bfloat16 on AMX: the pose picked among
# the starting points can tip. The cards' figures hold to this; comparisons with K-Means are
# made on the same frames in the same run.
CPU_TOLERANCE = 0.03


@pytest.mark.parametrize("folder", MODELS, ids=[p.name for p in MODELS])
def test_segments_its_sample_bag_as_its_card_says(folder):
    card = json.loads((folder / "card.json").read_text())
    ours, km, count = sample_bag_scores(folder)
    recorded = card["sample_bag_scores"]
    assert count == recorded["frames"]
    assert ours == pytest.approx(recorded["inseggan"], abs=CPU_TOLERANCE)
    assert km == pytest.approx(recorded["kmeans"], abs=CPU_TOLERANCE)
    assert ours - km == pytest.approx(recorded["inseggan"] - recorded["kmeans"],
                                      abs=CPU_TOLERANCE)
    assert ours > 0.3, "well above labelling everything as one object (about 0.2)"
    full = full_resolution_scores(load_as_measured(folder), BAGS / card["sample_bag"])
    assert full == pytest.approx(recorded["full_resolution"], abs=CPU_TOLERANCE)


@pytest.mark.parametrize("folder", MODELS, ids=[p.name for p in MODELS])
def test_segments_its_sample_bag_better_than_kmeans(folder, request):
    """Where the card records InSeGAN clearly above or below K-Means on its sample bag, the
    same holds here (below: a strict expected failure, so that a retrained model that beats
    K-Means fails the test until its card says so). A card margin within CPU_TOLERANCE is a tie
    that another CPU's rounding may flip; the card test above covers it."""
    card = json.loads((folder / "card.json").read_text())
    b = card["sample_bag_scores"]
    margin = b["inseggan"] - b["kmeans"]
    if abs(margin) <= CPU_TOLERANCE:
        pytest.skip(f"{folder.name}: the card records a tie with K-Means on "
                    f"{card['sample_bag']} ({b['inseggan']:.3f} vs {b['kmeans']:.3f})")
    if margin < 0:
        request.applymarker(pytest.mark.xfail(strict=True, reason=(
            f"{folder.name}: its card records mIoU {b['inseggan']:.3f} vs K-Means "
            f"{b['kmeans']:.3f} on the sample bag {card['sample_bag']}")))
    ours, km, _ = sample_bag_scores(folder)
    assert ours > km


def test_card_shape_adds_the_learned_template_against_the_true_part(tmp):
    """`inseggan card-shape` on a copy of a shipped model: the card gains the template's IoU
    with the true part and both sets of dimensions, README.md is that card, shape.png is
    drawn, and the weights are untouched; a part with no true shape is refused."""
    import shutil

    folder = shutil.copytree(REPO / "models" / "cylinder", tmp / "cylinder")
    weights = (folder / "model.pt").read_bytes()
    p = run_cli("card-shape", folder, "--voxels", "8", check=True, timeout=600)
    assert "volumetric IoU" in p.stdout
    card = json.loads((folder / "card.json").read_text())
    f = card["shape"]
    assert f["object"] == "cylinder" and 0 < f["iou"] <= 1
    assert f["dims_true_mm"] == pytest.approx([40, 24, 24], abs=1.5)
    assert len(f["dims_template_mm"]) == 3 and min(f["dims_template_mm"]) > 0
    assert (folder / "README.md").read_text() == card_markdown(card)
    assert (folder / "shape.png").stat().st_size > 0
    assert (folder / "model.pt").read_bytes() == weights
    p = refused("card-shape", folder, "--object", "teapot")
    assert p.returncode == 2 and "not a part of the simulator's library" in p.stderr, p.stderr


def test_card_run_records_another_training_run_on_the_cards_test_split(tmp, tiny_model):
    """`inseggan card-run` on a copy of a shipped model: the run (from its checkpoint) and its
    scores (from `inseggan eval`'s results.json) become a row of the card, README.md is that
    card, the weights are untouched, the same label replaces its row, and scores of another
    split or of fewer frames are refused."""
    import shutil

    folder = shutil.copytree(REPO / "models" / "cone", tmp / "cone")
    weights = (folder / "model.pt").read_bytes()
    card = json.loads((folder / "card.json").read_text())
    results = {"frames": card["test"]["frames"], "data": f"{card['data']['root']} (test)",
               "refine_steps": 0, "refine_hypotheses": 1, "smooth_iters": 0,
               "methods": {"inseggan": {"miou_all": 0.5, "miou_hard": 0.25,
                                        "miou_hard_felzenszwalb": 0.4, "ms_per_frame": 3.0}}}
    (tmp / "results.json").write_text(json.dumps(results))
    ckpt = tiny_model / "run" / "best.pt"
    args = ("card-run", folder, "--checkpoint", ckpt, "--eval", tmp / "results.json",
            "--hardware", "a test CPU")
    before = len(card.get("training_runs", []))
    run_cli(*args, "--label", "tiny", check=True)
    results["methods"]["inseggan"]["miou_all"] = 0.6
    (tmp / "results.json").write_text(json.dumps(results))
    run_cli(*args, "--label", "tiny", check=True)
    card = json.loads((folder / "card.json").read_text())
    assert len(card["training_runs"]) == before + 1
    row = card["training_runs"][-1]
    state = checkpoint.load(ckpt)
    assert row["miou_all"] == 0.6 and row["iterations"] == state["iteration"]
    assert row["nf"] == state["train_config"]["model"]["nf"] == 8
    readme = (folder / "README.md").read_text()
    assert readme == card_markdown(card) and "| tiny | a test CPU |" in readme
    assert (folder / "model.pt").read_bytes() == weights
    # a checkpoint with a centre-vote net: its iterations and minutes join the row's
    run_cli("card-run", folder, "--checkpoint", folder / "model.pt", "--eval",
            tmp / "results.json", "--hardware", "a test CPU", "--label", "votes", check=True)
    row = json.loads((folder / "card.json").read_text())["training_runs"][-1]
    net = checkpoint.load(folder / "model.pt")["centre_net"]["summary"]
    assert row["centre_iterations"] == net["config"]["iterations"] > 0
    assert f"+ {net['config']['iterations']} (centre votes)" in (folder / "README.md").read_text()
    for bad, why in ((dict(data=f"{card['data']['root']} (val)"), "the card's test split"),
                     (dict(frames=card["test"]["frames"] - 1), "score the run on all of them")):
        (tmp / "results.json").write_text(json.dumps({**results, **bad}))
        p = refused(*args, "--label", "bad")
        assert p.returncode == 2 and why in p.stderr, p.stderr


def test_quality_settings_segment_the_default_models_bag_better_than_kmeans():
    """config/quality.yaml (the node's --params-file for quality; that it sets the node's
    parameters: test_segmenter.py) on the default model's sample bag, every frame at the bag's
    own resolution as the node outputs them, against K-Means on the same frames."""
    from inseggan_ros.core import settings
    from inseggan_ros.ros.segmenter import DEFAULT_MODEL

    folder = REPO / "models" / DEFAULT_MODEL
    card = json.loads((folder / "card.json").read_text())
    seg = load_as_measured(folder)
    params = settings.read_params_file(REPO / "config" / "quality.yaml")
    seg.inference = settings.apply(seg.inference, {**params, "encoder_precision": None})
    assert seg.inference.refine_steps == params["refine_steps"] > 0
    full = full_resolution_scores(seg, BAGS / card["sample_bag"])
    print(f"quality settings at full resolution: {full}")
    assert full["inseggan"] > full["kmeans"], full


def test_card_settings_ships_other_settings_and_measures_the_card_anew(tmp):
    """`inseggan card-settings` on a copy of a shipped model: the model stores the new settings
    with its weights and tau unchanged, the card's test table is measured again on the card's
    test split (here a small one of the same seed) with them, README.md is that card, the shape
    drawing and training runs stay; a data set of another seed is refused by name."""
    import shutil

    import torch

    folder = shutil.copytree(REPO / "models" / "cone", tmp / "cone")
    before = checkpoint.load(folder / "model.pt")
    old_card = json.loads((folder / "card.json").read_text())
    for seed, out in ((1, tmp / "cone_data"), (2, tmp / "other")):
        run_cli("simulate", "--object", "cone", "--count", "8", "--split", "0,1,1", "--seed",
                seed, "--workers", "1", "--quiet", "--out", out, check=True)
    run_cli("card-settings", folder, "--data", tmp / "cone_data", "--profile", "realtime",
            "--superpixel-scale", "0", "--split-scale", "0", "--smooth-iters", "3", check=True,
            timeout=600)
    state = checkpoint.load(folder / "model.pt")
    assert state["inference"]["superpixel_scale"] == 0 and state["inference"]["split_scale"] == 0
    assert state["inference"]["smooth"]["iters"] == 3 and state["tau"] == before["tau"]
    for key in ("generator", "encoder"):
        for name, value in before[key].items():
            assert torch.equal(state[key][name], value), name
    card = json.loads((folder / "card.json").read_text())
    assert card["inference"] == state["inference"] and card["smooth_iters"] == 3
    assert card["test"]["frames"] == 4 and card["also"] == {}
    assert set(card["test"]["methods"]) == {"inseggan", "kmeans", "spectral", "grabcut_kmeans",
                                            "felzenszwalb"}
    assert card["shape"] == old_card["shape"] and (folder / "shape.png").is_file()
    assert card.get("training_runs") == old_card.get("training_runs")
    assert (folder / "README.md").read_text() == card_markdown(card)
    p = refused("card-settings", folder, "--data", tmp / "other", "--profile", "realtime")
    assert p.returncode == 2 and "valid: the card's data set (seed 1, cone)" in p.stderr, p.stderr
