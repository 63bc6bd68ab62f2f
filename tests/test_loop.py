"""`inseggan loop`: a model's learned shape simulated, its encoder (and a label head) fitted to
those labelled piles, the result shipped with a card from the user's frames; resumable stage by
stage."""
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import REPO, refused, run_cli

from inseggan_ros.core import checkpoint
from inseggan_ros.evaluation import vote_scale
from inseggan_ros.learning.family import DEFAULT_FAMILIES, FLAT, FamilyConfig
from inseggan_ros.learning import losses
from inseggan_ros.data.datasets import load_bag, load_sim_split
from inseggan_ros.learning.loop import AUTO_SIZE_ROUNDS, VOTE_SCALES
from inseggan_ros.runtime.preprocess import PreprocessConfig
from inseggan_ros.sim.learned import model_camera, template_scale
from inseggan_ros.core.metrics import mean_miou, miou_batch
from inseggan_ros.evaluation.modelcard import markdown
from inseggan_ros.runtime.segment import labels_from_renders
from inseggan_ros.runtime.model import build_models

# a box part's model as training left it, without labels: the wooden_block model shipped before
# its encoder went through the loop (every shipped model has now been through it, so none of them
# is an unsupervised starting point)
MODEL = Path(__file__).resolve().parent / "data" / "wooden_block_unsupervised.pt"
CAMERA = ("--camera", "realsense_d435", "--noise", "realsense")  # the model's


def _scores(path, data) -> tuple[float, float]:
    """The encoder's own poses (one start, no smoothing) on labelled frames -> (the label loss
    the loop trains on, mIoU at the model's tau)."""
    state = checkpoint.load(path)
    _, G, E = build_models(state, path)
    x = torch.from_numpy(data["x"])
    with torch.no_grad():
        z = E.eval()(x)
        pose = G.pose(z.reshape(-1, z.shape[-1])).reshape(len(x), z.shape[1], 6)
        renders = G.render_poses(pose)
        loss = losses.label_loss(renders, torch.from_numpy(data["labels"].astype(np.int64)), x)
        labels = labels_from_renders(renders, float(state["tau"]), torch.from_numpy(data["fg"]))
    return float(loss), float(mean_miou(miou_batch(labels.numpy(), data["labels"])))


def test_a_tiny_loop_explains_held_out_scenes_of_its_shape_better_than_its_starting_point(tmp):
    user = tmp / "user"  # the user's frames: their val and test splits make the card
    run_cli("simulate", "--quiet", "--object", "wooden_block", "--instances", "4", "--count", "48",
            "--split", "8,20,20", "--seed", "21", *CAMERA,
            "--workers", "2", "--out", user, check=True, timeout=600)
    out = tmp / "loop"
    args = ["loop", "--model", MODEL, "--data", user, "--out", out, "--scenes", "96",
            "--val-scenes", "16", "--iterations", "150", "--centre-iterations", "0", "--workers",
            "2", "--quiet"]
    p = run_cli(*args, check=True, timeout=900)
    assert "loop done" in p.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["seconds"]) == {"simulate", "encoder", "export"}
    card = json.loads((out / "model" / "card.json").read_text())
    assert card["label_free"] and card["labelled"]["frames"] == 20  # the user's test frames
    assert (out / "model" / "model.pt").is_file() and (out / "model" / "qualitative.png").is_file()
    # the run's resolved configuration (every option), written beside it and stored on its
    # card with the code's commit; given back with --recipe, it resolves to the same
    recipe = yaml.safe_load((out / "recipe.yaml").read_text())
    assert recipe["command"] == "loop" and recipe["model"] == str(MODEL)
    assert (recipe["scenes"], recipe["val_scenes"], recipe["lr"]) == (96, 16, 3e-4)
    assert card["recipe"] == {k: v for k, v in recipe.items() if k not in ("command", "commit")}
    assert card["commit"] == recipe["commit"] != ""
    again = run_cli("loop", "--recipe", out / "recipe.yaml", "--print-recipe", check=True)
    again = yaml.safe_load(again.stdout)  # resolved by the code now, whose commit is its own
    assert {**again, "commit": recipe["commit"]} == recipe
    # the vote's scale chosen on the piles' validation split: every default scale scored, and
    # the one chosen is what the model ships and its card names
    vote = summary["vote_scale"]
    assert vote == card["vote_scale"] and vote["frames"] == 16
    assert {r["scale"] for r in vote["rows"]} == set(VOTE_SCALES) | {vote["default"]}
    assert checkpoint.load(out / "model" / "model.pt")["inference"]["superpixel_scale"] \
        == vote["scale"] == card["inference"]["superpixel_scale"]
    assert f"**Vote:** scale {vote['scale']}, chosen on 16 labelled simulated piles" in \
        (out / "model" / "README.md").read_text()
    assert f"superpixel vote: scale {vote['scale']}, chosen on 16" in p.stdout
    # held-out scenes of the learned shape, from a seed the loop did not use
    held = tmp / "held"
    run_cli("simulate", "--quiet", "--object", MODEL, "--instances", "4", "--count", "40",
            "--split", "0,0,40", *CAMERA,
            "--seed", "99", "--workers", "2", "--out", held, check=True, timeout=600)
    data = load_sim_split(held, "test")
    before, after = _scores(MODEL, data), _scores(out / "encoder" / "last.pt", data)
    msg = "held-out scenes of the learned shape, label loss / mIoU: {:.3f} / {:.3f} -> " \
          "{:.3f} / {:.3f}".format(*before, *after)
    # the instances explained better (measured: 0.89 -> 0.84); at this size (96 scenes, 150
    # iterations) the mIoU does not reliably rise (0.459 -> 0.450-0.467 over learning rates,
    # docs/experiments.md), so it is held only to not falling apart (lr 3e-3 diverged to 0.26)
    assert after[0] < 0.97 * before[0], msg
    assert after[1] > before[1] - 0.05, msg
    assert np.isfinite(summary["tau"])  # started again, nothing is redone: the test below
    # run again with --self-frames, the finished stages are kept and only the self-fit is added
    encoder_time = (out / "encoder" / "last.pt").stat().st_mtime_ns
    p = run_cli(*args, "--self-frames", "8", "--self-iterations", "10", check=True, timeout=900)
    again = json.loads((out / "summary.json").read_text())
    assert set(again["seconds"]) == {"simulate", "encoder", "self", "export"}, again
    assert (out / "encoder" / "last.pt").stat().st_mtime_ns == encoder_time
    card = json.loads((out / "model" / "card.json").read_text())
    assert card["distillation"]["self_fit"]["frames"] == 8  # and the loop's step before it
    assert card["distillation"]["previous"]["config"]["labels"] == "simulated"
    assert checkpoint.load(out / "self" / "last.pt")["distill"]["iteration"] == 10
    # and again with centre votes, taught on the user's 8 training frames labelled by the model
    # itself (1 held out; taught on the piles: the default loop's test below)
    p = run_cli(*args, "--self-frames", "8", "--self-iterations", "10", "--centre-iterations",
                "20", "--centre-teacher", "self-labels", check=True, timeout=900)
    again = json.loads((out / "summary.json").read_text())
    assert list(again["seconds"]) == ["simulate", "encoder", "self", "centres", "export"], again
    shipped = checkpoint.load(out / "model" / "model.pt")
    assert shipped["centre_net"]["teacher"] == "self-labels"
    assert shipped["centre_net"]["sim"] == str(user)
    assert shipped["inference"]["centre_votes"] == "on"
    assert shipped["centre_net"]["summary"]["train_frames"] == 7
    with np.load(out / "centres_self" / "self_labels.npz") as saved:
        assert saved["done"].all() and len(saved["labels"]) == 8
    assert "labelled by this model itself" in (out / "model" / "README.md").read_text()
    # and with centre votes taught on piles pasted from the parts seen whole in those frames:
    # the vote's scale then chosen on the net's own validation piles
    run_cli(*args, "--self-frames", "8", "--self-iterations", "10", "--centre-iterations",
            "20", "--centre-teacher", "pasted", check=True, timeout=900)
    shipped = checkpoint.load(out / "model" / "model.pt")
    assert shipped["centre_net"]["teacher"] == "pasted piles"
    assert (out / "centres_pasted" / "net.pt").is_file()
    assert shipped["centre_net"]["piles_part"].endswith("parts seen whole in the user's frames")
    card = json.loads((out / "model" / "card.json").read_text())
    assert card["vote_scale"]["taught"] and card["vote_scale"]["frames"] == 16  # --val-scenes
    assert "piles pasted from the" in (out / "model" / "README.md").read_text()
    # without a model the loop's first stage learns the shape from the data set's training
    # frames (here for 2 iterations; from a bag, the test below)
    from inseggan_ros.learning.loop import learn_shape
    from inseggan_ros.learning.train import get_config

    cfg = get_config("cpu_spheres", max_iterations=2, eval_every=2, checkpoint_every=2)
    state = checkpoint.load(learn_shape(user, tmp / "shape", cfg, progress=False))
    assert checkpoint.load(tmp / "shape" / "last.pt")["iteration"] == 2
    assert state["model_config"]["n_instances"] == 4
    assert state["data"]["train_frames"] == 8 and state["data"]["val_frames"] == 20


def test_loop_refuses_a_missing_model_and_frames_of_another_camera(tmp):
    p = refused("loop", "--model", tmp / "nothing.pt", "--data", tmp, "--out", tmp / "o")
    assert p.returncode == 2 and "no model there" in p.stderr
    run_cli("simulate", "--quiet", "--count", "2", "--split", "0,1,1", "--out", tmp / "other",
            check=True, timeout=300)  # the default 224 x 224 camera
    p = refused("loop", "--model", MODEL, "--data", tmp / "other", "--out", tmp / "o")
    assert p.returncode == 2 and "not cut as the model's were roi" in p.stderr, p.stderr
    assert not (tmp / "o" / "sim").exists()
    p = refused("loop", "--model", MODEL, "--data", tmp / "other", "--out", tmp / "o",
                "--vote-scales", "50,0")
    assert p.returncode == 2 and "'50,0' is not scales like 50,160,250" in p.stderr, p.stderr


def test_one_command_from_a_bag_learns_the_shape_then_ships_a_model(tmp):
    """From a recording (depth, CameraInfo; a tilted camera): without --model the loop trains
    the shape on the bag's frames first (stage `shape`), simulates piles of it through the
    camera estimated from the bag, cut as the bag's frames are, goes on with a label head
    (stage `head`) and ships a model whose card comes from the bag's last frames; started
    again, nothing is redone."""
    bag = tmp / "user_bag"
    run_cli("simulate-bag", "--quiet", "--object", "wooden_block", "--instances", "4", "--count",
            "30", "--tilt", "3", "--seed", "22", *CAMERA, "--out", bag, check=True, timeout=600)
    out = tmp / "loop"
    args = ["loop", "--bag", bag, "--instances", "4", "--noise", "realsense", "--labels-topic",
            "/camera/depth/instance_labels", "--out", out, "--train-iterations", "4",
            "--eval-every", "2", "--scenes", "16", "--val-scenes", "4", "--iterations", "10",
            "--head-iterations", "5", "--centre-iterations", "0", "--min-instances", "0",
            "--quiet"]
    p = run_cli(*args, check=True, timeout=900)
    assert "loop done" in p.stdout and "shape" in p.stdout
    summary = json.loads((out / "summary.json").read_text())
    # by default a rod the loop learns itself is sized (tests/test_sizing.py): to the
    # thickness where it came out elongated, then up to two scale rounds
    assert summary["sizing"] == {"by_thickness": "if_elongated", "rounds": AUTO_SIZE_ROUNDS}
    thick = [] if summary["size"].get("left_as_is") else ["size"]
    scales = [r["scale"] for r in summary["size_rounds"]]
    rounds = [f"{stage}{k}" for k, s in enumerate(scales, 1)
              for stage in (["scale"] if s == 1 else ["scale", "simulate", "encoder"])]
    assert list(summary["seconds"]) == ["shape", *thick, "simulate", "encoder", *rounds,
                                        "head", "export"]
    assert len(scales) == AUTO_SIZE_ROUNDS or scales[-1] == 1.0, scales
    assert summary["data"]["kind"] == "bag" and summary["data"]["instances"] == 4
    shape = json.loads((out / "shape" / "summary.json").read_text())
    assert shape["iterations"] == 4
    # validated without the labels topic (the card's only): by reconstruction, no mIoU
    log = [json.loads(line) for line in (out / "shape" / "log.jsonl").read_text().splitlines()]
    val = [r for r in log if r["kind"] == "val"]
    assert val and all("miou" not in r and "recon_l1" in r for r in val), val
    # the bag's last 20 % (6 frames) are the card's only: the shape learned from the other 24
    learned = checkpoint.load(out / "shape" / "best.pt")
    assert learned["data"]["source"] == "bag" and learned["data"]["train_frames"] == 24
    # the template in metres: the bin is found in every frame, so its scale is that of the
    # bag's median region and floor, seen by the bag's camera (not a guess from max_height)
    view, cam = learned["data"]["view"], model_camera(out / "shape" / "best.pt", learned)
    assert cam is not None and cam.fx == pytest.approx(426.0) and abs(cam.tilt - 3) < 0.5
    x0, _, x1, _ = view["roi"]
    want = (x1 - x0) * view["floor_depth"] / cam.fx / 2  # at the floor; the template's middle
    scale = template_scale(learned, build_models(learned)[1], cam)  # is nearer
    assert 0.8 * want < scale[0] <= want, (scale, want)
    card = json.loads((out / "model" / "card.json").read_text())
    assert card["label_free"] and card["source"]["kind"] == "bag"
    assert card["labelled"]["frames"] == 6  # from the labels topic, for the card only
    assert card["vote_scale"]["frames"] == 4  # chosen on the last piles' validation split
    # the piles: the bag's camera (its tilt found), cut as the bag's frames are (the bin found
    # in every frame), so that their bin lands where the bag's does
    sim_meta = json.loads((out / "sim" / "meta.json").read_text())
    sim_camera = sim_meta["scene"]["camera"]
    assert sim_camera["width"] == 848 and abs(sim_camera["tilt"] - 3) < 0.5, sim_camera
    # --min-instances 0: each pile holds 0..4 parts, its own count (a bin a robot empties)
    counts = {int(k) for split in ("train", "val") for k in sim_meta["instance_counts"][split]}
    assert sim_meta["scene"]["min_instances"] == 0 and len(counts) > 1 and counts <= set(
        range(5)), sim_meta["instance_counts"]
    prep = PreprocessConfig.from_dict(learned["preprocess_config"])
    assert prep.roi is None
    piles = load_sim_split(out / "sim", "train", prep, limit=8, as_given=True)
    frames = load_bag(bag, prep, limit=8)
    assert np.abs(np.median(piles["roi"], 0) - np.median(frames["roi"], 0)).max() <= 3
    # the shipped model carries the template the shape stage learned, at the bag's n, sized
    # as the stages said: its spheres as many times as large
    shipped = checkpoint.load(out / "model" / "model.pt")
    assert learned["model_config"]["n_instances"] == 4
    shape_keys = [k for k in learned["generator"] if not k.startswith("pose.")]  # the rod
    assert "log_radius" in shape_keys
    scale = math.prod(scales) * (summary["size"]["scale"] if thick else 1.0)
    for key in shape_keys:
        want = learned["generator"][key].float()
        if key == "log_radius":
            want = want + math.log(scale)
        elif key == "length":
            want = want * scale
        elif key == "lift" and scale != 1:
            continue  # set to rest on the floor when sized, then scaled
        assert torch.allclose(want, shipped["generator"][key].float(), atol=1e-3), key
    # with its label head (its training: tests/test_label_head.py), switched on, at its tau
    assert shipped["label_head"]["width"] == 8 and shipped["inference"]["label_head"] == "on"
    assert shipped["tau"] == shipped["label_head"]["tau"]
    # started again after a complete run: every stage's result is there, nothing is redone
    kept = (out / "shape" / "last.pt", out / "sim" / "meta.json", out / "encoder" / "last.pt",
            out / "head" / "model.pt", out / "size" / "size.json",
            out / "size_round1" / "scale.json")
    stamps = {p: p.stat().st_mtime_ns for p in kept}
    run_cli(*args, check=True, timeout=600)
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    p = refused("loop", "--model", out / "shape" / "best.pt", "--bag", bag, "--instances", "4",
                "--out", tmp / "o", "--train-minutes", "5")
    assert p.returncode == 2 and "without --model only" in p.stderr, p.stderr
    p = refused("loop", "--bag", bag, "--out", tmp / "o")
    assert p.returncode == 2 and "--bag needs --instances" in p.stderr, p.stderr
    assert not (tmp / "o").exists()


def test_the_loop_piles_a_nut_with_its_hole_where_the_grid_asks_for_one(tmp):
    """`loop --match-piles --match-pieces 1 --match-walls 12 --pile-holes`: the nut's rod cut
    into one disc, built as a hexagonal nut of six ring sectors with the hole the search
    kept; the piles, and the centre votes the model ships with, are of that nut."""
    rod = REPO / "models" / "hex_nut" / "model.pt"
    out = tmp / "loop"
    p = run_cli("loop", "--model", rod, "--bag", REPO / "bags" / "hex_nut_sim_32fc1",
                "--instances", "5", "--out", out, "--match-piles", "--match-pieces", "1",
                "--match-walls", "12", "--pile-lengths", "0.4,0.8", "--pile-radii", "1,1.1",
                "--pile-holes", "0.6", "--coarse-piles", "2", "--fine-piles", "0", "--scenes",
                "12", "--val-scenes", "4", "--iterations", "0", "--centre-iterations", "8",
                "--workers", "2", "--quiet", check=True, timeout=900)
    assert "a nut with a hole x0.6 as wide" in p.stdout, p.stdout
    part = checkpoint.load(out / "match" / "best.pt")
    assert (part["model_config"]["pieces"], part["model_config"]["walls"]) == (6, 12)
    assert part["shape_fit"]["config"]["hole"] == 0.6
    net = checkpoint.load(out / "model" / "model.pt")["centre_net"]
    assert "a hexagonal nut with a hole 0.6" in net["piles_part"], net["piles_part"]
    # a recording's card names no part: the true shape to measure against must be given
    bad = refused("card-shape", out / "model")
    assert bad.returncode == 2 and "names no part" in bad.stderr, bad.stderr
    # given, both shapes are measured at the size the recording's estimated camera gives: the
    # data set's camera, from which the shipped nut's card measured its own rod
    run_cli("card-shape", out / "model", "--object", "hex_nut", "--voxels", "8",
            "--piles-template", out / "match" / "best.pt", check=True, timeout=600)
    card = json.loads((out / "model" / "card.json").read_text())
    shipped = json.loads((REPO / "models" / "hex_nut" / "card.json").read_text())["shape"]
    for f in (card["shape"], card["piles_shape"]):
        assert f["object"] == "hex_nut" and 0 < f["iou"] <= 1
        assert f["dims_true_mm"] == shipped["dims_true_mm"]
        assert f["metres_per_unit"] == pytest.approx(shipped["metres_per_unit"], rel=0.05)
    assert card["piles_shape"]["template"] == str(out / "match" / "best.pt")
    readme = (out / "model" / "README.md").read_text()
    assert readme == markdown(card) and "piles_shape.png" in readme


def test_the_loop_piles_a_disc_template_matched_to_the_frames_and_keeps_the_rod(tmp):
    """`loop --match-piles` (stage `match`, the tilted bolts' recipe in one command): the rod
    is cut into discs whose head is sized by how their piles look against the recording's
    frames (`pilematch`, tests/test_pilematch.py), the piles are of that part, and with
    `--iterations 0` the rod model keeps its own encoder while its centre votes learn from the
    piles; the model shipped is the rod with the votes. Started again, nothing is redone."""
    rod = REPO / "models" / "bolt" / "model.pt"  # a rod of spheres with a rounded head
    out = tmp / "loop"
    args = ["loop", "--model", rod, "--bag", REPO / "bags" / "bolt_sim", "--instances", "5",
            "--out", out, "--match-piles", "--pile-lengths", "0.5,1", "--pile-radii", "1,1.2",
            "--coarse-piles", "3", "--fine-piles", "0", "--scenes", "12", "--val-scenes", "4",
            "--iterations", "0", "--centre-iterations", "8", "--workers", "2", "--quiet"]
    p = run_cli(*args, check=True, timeout=900)
    assert "no encoder stage" in p.stdout and "matched by 4 variants" in p.stdout, p.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert list(summary["seconds"]) == ["match", "simulate", "centres", "export"]
    assert summary["encoder"] is None and summary["sizing"] == {"by_thickness": "off",
                                                                "rounds": 0}
    match = json.loads((out / "match" / "search" / "summary.json").read_text())
    assert summary["match"]["best"] == match["best"] and len(match["coarse"]) == 4
    assert match["config"]["piles"] == 3 and match["config"]["workers"] == 2
    part = out / "match" / "best.pt"
    meta = json.loads((out / "sim" / "meta.json").read_text())
    assert meta["scene"]["object"] == str(part)  # the piles are of the matched discs
    discs = checkpoint.load(part)["model_config"]
    assert discs["renderer"] == "convex" and discs["pieces"] == 2
    # the model shipped is the rod, its generator and encoder untouched, with the piles' votes
    shipped, given = checkpoint.load(out / "model" / "model.pt"), checkpoint.load(rod)
    assert shipped["model_config"]["renderer"] == "spheres"
    for part_of in ("generator", "encoder"):
        assert all(torch.equal(v, shipped[part_of][k]) for k, v in given[part_of].items())
    net = shipped["centre_net"]  # the loop's own, taught on the matched part's piles
    assert shipped["inference"]["centre_votes"] == "on" and net["sim"] == str(out / "sim")
    assert net["width"] == 16 and "widest sized by simulated piles" in net["piles_part"]
    assert json.loads((out / "model" / "card.json").read_text())["source"]["kind"] == "bag"
    kept = (part, out / "match" / "search" / "variants.jsonl", out / "sim" / "meta.json",
            out / "centres" / "model.pt")
    stamps = {f: f.stat().st_mtime_ns for f in kept}
    run_cli(*args, check=True, timeout=600)
    assert {f: f.stat().st_mtime_ns for f in stamps} == stamps
    # refused before any stage: sizing a matched part, a part that is not a rod, the grid or
    # the discs' shape without --match-piles, no encoder stage with nothing after it
    base = ["loop", "--bag", REPO / "bags" / "bolt_sim", "--instances", "5", "--quiet"]
    for extra, said in (
            (["--model", rod, "--match-piles", "--size-rounds", "1"], "sizes the part itself"),
            (["--model", REPO / "models" / "wooden_block", "--match-piles"],
             "cuts a rod of spheres"),
            (["--model", rod, "--pile-lengths", "0.5,1"], "valid: with --match-piles"),
            (["--model", rod, "--match-pieces", "3"], "valid: with --match-piles"),
            (["--model", rod, "--iterations", "0", "--centre-iterations", "0"],
             "no encoder stage) with centre_iterations"),
            (["--model", rod, "--match-piles", "--match-walls", "6"], "walls 6 invalid"),
            (["--model", rod, "--match-piles", "--pile-tapers", "0.3,1"],
             "frustum of one disc"),  # the default two discs
            (["--model", rod, "--pile-tapers", "0.3,1"], "--pile-tapers")):
        bad = refused(*base, *extra, "--out", tmp / "bad")
        assert bad.returncode == 2 and said in bad.stderr, (extra, bad.stderr)
        assert not (tmp / "bad").exists()


def test_the_loop_fits_a_convex_template_from_the_rod_and_piles_and_ships_it(tmp):
    """`loop --convex-pieces 1` (stage `convex`, the tilted blocks' recipe in one command): the
    rod becomes a box fitted to the recording's frames by reconstruction (`shapefit`,
    tests/test_shapefit.py), the piles are of that box, and the model shipped is the box model
    with the piles' centre votes; no size stage runs on it. Started again, nothing is redone."""
    out = tmp / "loop"
    args = ["loop", "--model", MODEL, "--bag", REPO / "bags" / "wooden_block_realsense",
            "--instances", "4", "--noise", "realsense", "--out", out, "--convex-pieces", "1",
            "--convex-iterations", "6", "--scenes", "12", "--val-scenes", "4", "--iterations",
            "0", "--centre-iterations", "8", "--workers", "2", "--quiet"]
    p = run_cli(*args, check=True, timeout=900)
    assert "no encoder stage" in p.stdout, p.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert list(summary["seconds"]) == ["convex", "simulate", "centres", "export"]
    assert summary["sizing"] == {"by_thickness": "off", "rounds": 0}
    box = out / "convex" / "best.pt"
    fit = json.loads((out / "convex" / "summary.json").read_text())
    assert fit["config"]["pieces"] == 1 and fit["config"]["iterations"] == 6
    meta = json.loads((out / "sim" / "meta.json").read_text())
    assert meta["scene"]["object"] == str(box)  # the piles are of the fitted box
    shipped = checkpoint.load(out / "model" / "model.pt")
    fitted, rod = checkpoint.load(box), checkpoint.load(MODEL)
    assert rod["model_config"]["renderer"] == "spheres"
    assert shipped["model_config"]["renderer"] == "convex"
    assert (shipped["model_config"]["pieces"], shipped["model_config"]["walls"]) == (1, 4)
    for part_of in ("generator", "encoder"):  # the fit's own, not the rod's
        assert all(torch.equal(v, shipped[part_of][k]) for k, v in fitted[part_of].items())
    assert shipped["inference"]["centre_votes"] == "on"
    assert shipped["centre_net"]["sim"] == str(out / "sim")
    # the fit's account ships, its optimiser's state (twice the model's size) does not
    assert "optimizer" not in shipped["shape_fit"] and shipped["shape_fit"]["iterations"] == 6
    card = json.loads((out / "model" / "card.json").read_text())
    assert card["shape_fit"]["kept"] == fitted["shape_fit"]["iteration"]
    kept = (box, out / "sim" / "meta.json", out / "centres" / "model.pt")
    stamps = {f: f.stat().st_mtime_ns for f in kept}
    run_cli(*args, check=True, timeout=600)
    assert {f: f.stat().st_mtime_ns for f in stamps} == stamps
    # refused before any stage: a template that is not a rod, both pile templates at once,
    # the box's walls without --convex-pieces, no pieces
    base = ["loop", "--bag", REPO / "bags" / "wooden_block_realsense", "--instances", "4",
            "--iterations", "0", "--centre-iterations", "8", "--quiet"]
    for extra, said in (
            (["--model", REPO / "models" / "wooden_block", "--convex-pieces", "1"],
             "fits a convex template from a rod"),
            (["--model", MODEL, "--convex-pieces", "1", "--match-piles"],
             "valid: at most one"),
            (["--model", MODEL, "--convex-walls", "6"], "valid: with --convex-pieces"),
            (["--model", MODEL, "--convex-pieces", "-1"], "pieces -1 invalid")):
        bad = refused(*base, *extra, "--out", tmp / "bad")
        assert bad.returncode == 2 and said in bad.stderr, (extra, bad.stderr)
        assert not (tmp / "bad").exists()


def test_the_default_loop_chooses_the_template_family_then_piles_it_once(tmp):
    """The default loop (no encoder stage, no template named): the scale rounds run before any
    pile (they read the model, never the piles), then every template family is made from the
    rod, piled and scored against the recording's frames (`family.choose`), and the piles of
    the kept one are simulated once; the card lists every candidate and the one kept. Started
    again, nothing is redone; --families rod is the rod's own piles, as before the choice."""
    out = tmp / "loop"
    args = ["loop", "--model", MODEL, "--bag", REPO / "bags" / "wooden_block_realsense",
            "--instances", "4", "--out", out, "--scenes", "12", "--val-scenes", "4",
            "--centre-iterations", "8", "--minutes", "30", "--size-rounds", "1",
            "--family-piles", "6",
            "--family-iterations", "4", "--workers", "2", "--quiet"]
    p = run_cli(*args, check=True, timeout=900)
    summary = json.loads((out / "summary.json").read_text())
    assert list(summary["seconds"]) == ["scale1", "family", "simulate", "centres", "export"]
    card = json.loads((out / "model" / "card.json").read_text())
    # the time budget: the family and the centre votes had their shares; the card says so
    assert card["budget"] == summary["budget"] and card["budget"]["minutes"] == 30
    assert set(card["budget"]["shares_minutes"]) == {"family", "centres"}
    assert "time budget 30 min" in p.stdout
    fam = card["template_family"]
    assert fam == summary["template_family"]
    assert [r["family"] for r in fam["candidates"]] == \
        ["rod", "box", "bars", "tee", "ell", "u", "discs", "ring", "taper"]
    scored = [r for r in fam["candidates"] if "skipped" not in r]
    assert {"rod", "box", "bars"} <= {r["family"] for r in scored}
    for r in scored:
        assert r["pile_w1"] > 0 and r["recon_l1"] > 0 and r["seconds"] > 0
        # the grid's four scales, and steps past an end where the share holds them; a bars
        # candidate made thinner or wider: the three scales about its area's, and such steps
        assert ("width" in r) == (r["family"] in ("bar", "tee", "ell", "u"))
        n = 3 if r.get("width", 1) != 1 else 4
        # the bars' best scale refined before their width search (two scales a round, where
        # the time holds them); the width the search kept says so where it is the first
        flat = 2 * FamilyConfig.flat_refine if r["family"] in FLAT else 0
        assert n <= len(r["pile_w1_by_scale"]) <= n + FamilyConfig.extend + flat
        if r["family"] not in FLAT:
            assert "refined" not in r  # no refinement by default
        elif r["width"] == 1:
            assert r.get("refined", 0) == FamilyConfig.flat_refine
        assert r["score"] >= 2 - 1e-6  # each measure over its best: 1 + 1 at least
    kept = min(scored, key=lambda r: r["score"])
    assert fam["kept"] == kept["family"] and f"template family: {kept['family']}" in p.stdout
    assert (out / "family" / "family.png").is_file() and (out / "family" / "views.png").is_file()
    assert (out / "model" / "template_family.png").read_bytes() == \
        (out / "family" / "views.png").read_bytes()  # the card's three views of each candidate
    readme = (out / "model" / "README.md").read_text()
    assert f"**Template family:** {kept['family']} kept" in readme and "Verdict" in readme
    assert "**Time budget:** 30 min" in readme
    # the piles: simulated once, of the kept template (the fitted convex one becomes the model;
    # discs, a ring or a taper are the piles' part and the model stays the rod)
    # at the scale whose piles looked most like the frames
    choice = json.loads((out / "family" / "family.json").read_text())
    by_scale = kept["pile_w1_by_scale"]
    assert f"{choice['scale']:g}" in by_scale and choice["scale"] == kept["scale"]
    assert kept["pile_w1"] == pytest.approx(min(by_scale.values()), abs=1e-5)
    moved = kept["family"] != "rod" or kept["scale"] != 1.0
    sim = out / "family" / "sim" if moved else out / "sim"
    if not moved and summary["size_rounds"][0]["scale"] != 1:
        sim = out / "size_round1" / "sim"
    meta = json.loads((sim / "meta.json").read_text())
    assert meta["scene"]["object"] == (choice["part"] if moved else choice["model"])
    assert not (out / "size_round1" / "sim").exists() or not moved
    shipped = checkpoint.load(out / "model" / "model.pt")
    want = "convex" if kept["family"] in ("box", "bars") else "spheres"
    assert shipped["model_config"]["renderer"] == want
    # the centre votes, taught on those piles and shipped on; the vote over them run only where
    # the user's frames' labels leave their height edges far more than the piles'
    # (`vote_scale.over_centres`; their training: test_centres.py)
    assert shipped["centre_net"]["width"] == 16 and shipped["inference"]["centre_votes"] == "on"
    assert shipped["centre_net"]["sim"] == str(sim)
    vote = summary["vote_scale"]
    assert vote["setting"] == "centre_superpixel_scale" and set(vote["off_edge"]) == {
        "piles", "frames"} and vote["user_frames"] > 0, vote
    assert shipped["inference"]["centre_superpixel_scale"] == vote["scale"]
    assert vote["scale"] == 0 or vote["mismatch"]
    assert f"superpixel vote: {vote_scale.describe(vote)}" in p.stdout
    assert "instances from the centre votes" in readme
    recipe = yaml.safe_load((out / "recipe.yaml").read_text())
    assert recipe["families"] == list(DEFAULT_FAMILIES)
    done = (out / "family" / "family.json", sim / "meta.json")
    stamps = {f: f.stat().st_mtime_ns for f in done}
    run_cli(*args, check=True, timeout=600)
    assert {f: f.stat().st_mtime_ns for f in stamps} == stamps
    # --families rod: no choice; a family beside a named template is refused
    p = run_cli(*args[:-9], "--families", "rod", "--out", tmp / "rod", "--print-recipe",
                check=True)
    assert "families: [rod]" in p.stdout
    bad = refused(*args[:5], "--out", tmp / "bad", "--families", "box,ring", "--convex-pieces",
                  "1")
    assert bad.returncode == 2 and "--families chooses the template" in bad.stderr, bad.stderr
    bad = refused(*args[:5], "--out", tmp / "bad", "--families", "rod,cube")
    assert bad.returncode == 2 and "'rod,cube' invalid" in bad.stderr, bad.stderr
    assert not (tmp / "bad").exists()
