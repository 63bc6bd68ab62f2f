"""A learned rod sized from the user's unlabelled frames (`sizing`, `inseggan loop
--size-by-thickness --size-rounds N`): the parts' thickness read off the frames, the rod resized
to it, and the template's scale chosen by how well it explains the frames."""
import json

import pytest
import torch
from conftest import refused, run_cli

from inseggan_ros.core import checkpoint
from inseggan_ros.learning import sizing
from inseggan_ros.data.datasets import load_sim_split
from inseggan_ros.learning.loop import (
    AUTO_SIZE_ROUNDS, LoopConfig, resume_plan, run, size_plan, size_stage)
from inseggan_ros.core.paths import resolve_model
from inseggan_ros.runtime.segment import Segmenter
from inseggan_ros.sim.learned import model_camera, template_scale
from inseggan_ros.runtime.model import build_models

CYLINDER = resolve_model("cylinder")  # the shipped model
DIAMETER = 0.024  # the simulator's cylinder: 24 mm x 40 mm


@pytest.fixture(scope="module")
def cylinders(tmp_path_factory):
    """40 simulated bins of five cylinders: 12 training, 20 validation and 8 test scenes, the
    shipped cylinder model's camera and bin."""
    root = tmp_path_factory.mktemp("sizing") / "cylinders"
    run_cli("simulate", "--quiet", "--object", "cylinder", "--count", "40", "--split",
            "0.3,0.5,0.2", "--seed", "5", "--out", root, check=True, timeout=600)
    return root


def test_the_parts_thickness_is_read_off_unlabelled_frames(cylinders):
    seg = Segmenter.from_checkpoint(CYLINDER, device="cpu")
    frames = load_sim_split(cylinders, "train", seg.prep_cfg)
    thickness = sizing.frame_thickness(frames["x"], frames["fg"], seg.prep_cfg.max_height)
    # lying on the floor, a cylinder's top is its diameter high (the frames' heights carry
    # the camera's quantisation and a tilt of some parts over others)
    assert 0.9 * DIAMETER < thickness < 1.15 * DIAMETER, thickness
    empty = frames["fg"][:3] & False
    with pytest.raises(ValueError, match="too few to measure"):
        sizing.frame_thickness(frames["x"][:3] * 0 - 1, empty, seg.prep_cfg.max_height)


def test_a_rod_resized_to_a_thickness_rests_on_the_floor_at_that_height():
    state = checkpoint.load(CYLINDER)
    G = build_models(state, CYLINDER)[1]
    metres = template_scale(state, G, model_camera(CYLINDER, state))
    before = sizing.rod_dimensions_mm(G, metres)
    s = sizing.size_to_thickness(state, G, float(metres[2]), 0.020)
    G2 = build_models(state, CYLINDER)[1]
    after = sizing.rod_dimensions_mm(G2, metres)
    assert after[2] == pytest.approx(20.0, rel=1e-4)  # its thickest sphere 20 mm high
    assert after[0] / after[1] == pytest.approx(before[0] / before[1], rel=1e-4)  # same shape
    assert after[2] == pytest.approx(before[2] * s, rel=1e-4)
    with torch.no_grad():  # the axis at that sphere's radius: it touches the floor
        assert float(G2.lift) == pytest.approx(float(G2.spheres()[1].max()), rel=1e-4)
    # the radii alone, the centres' span kept: a bolt's rod that came out thick
    state = checkpoint.load(CYLINDER)
    with torch.no_grad():
        centres = G.spheres()[0]
    span = float(centres[-1, 0] - centres[0, 0])
    s_thin = sizing.size_to_thickness(state, G, float(metres[2]), 0.010, keep_length=True)
    G3 = build_models(state, CYLINDER)[1]
    thin = sizing.rod_dimensions_mm(G3, metres)
    assert thin[2] == pytest.approx(10.0, rel=1e-4)
    assert s_thin == pytest.approx(10.0 / before[2], rel=1e-4)
    with torch.no_grad():
        c3, r3 = G3.spheres()
        assert float(c3[-1, 0] - c3[0, 0]) == pytest.approx(span, rel=1e-4)  # not clamped
        assert float(G3.lift) == pytest.approx(float(r3.max()), rel=1e-4)
    assert state["model_config"]["spheres"] == G3.cfg.spheres >= G.cfg.spheres
    assert thin[0] > after[0] * 10.0 / 20.0  # longer than the rod scaled alike would be
    with pytest.raises(ValueError, match="does nothing"):
        LoopConfig(size_by_thickness="off", size_keep_length=True)
    convex = checkpoint.load(resolve_model("wooden_block"))
    with pytest.raises(ValueError, match="only a rod of spheres"):
        sizing.scaled(build_models(convex)[1], 1.1)


def test_a_rod_made_longer_and_thinner_keeps_its_profile_on_more_spheres():
    G = build_models(checkpoint.load(resolve_model("bolt")), "bolt")[1]  # 12 spheres
    with torch.no_grad():
        centres, radii = G.spheres()
        span = float(centres[-1, 0] - centres[0, 0])
        same, got = sizing.reshaped(G, 1.0, 1.0, G.cfg.spheres)  # the same rod, rebuilt
        assert torch.allclose(same.spheres()[1], radii, rtol=1e-4)
        assert got == pytest.approx(span, rel=1e-4)
        pose = torch.tensor([[[0.3, -0.2, 0.5, 0.1, -0.1, 0.3]]])  # axis-angle, translation
        assert torch.allclose(same.render_poses(pose), G.render_poses(pose), atol=1e-4)
        # twice the span at 0.6 of the radii, on 24 spheres: the clamp on the span (the
        # spheres must overlap) does not bind, and the radii fall along the rod as they did
        thin, got = sizing.reshaped(G, 2.0, 0.6, 24)
        c2, r2 = thin.spheres()
        assert len(r2) == 24 and thin.cfg.spheres == 24
        assert got == pytest.approx(2 * span, rel=1e-4)
        assert float(c2[-1, 0] - c2[0, 0]) == pytest.approx(2 * span, rel=1e-4)
        assert float(r2[0]) == pytest.approx(0.6 * float(radii[0]), rel=1e-3)
        assert float(r2[-1]) == pytest.approx(0.6 * float(radii[-1]), rel=1e-3)
        assert float(thin.lift) == pytest.approx(0.6 * float(G.lift), rel=1e-4)
        # on the bolt's own 12 spheres the same request is held short: they must overlap
        short, got = sizing.reshaped(G, 2.0, 0.6, 12)
        assert got < 2 * span
        assert got <= 0.95 * 11 * float(short.spheres()[1].min()) * (1 + 1e-5)
    with pytest.raises(ValueError, match="invalid; valid: > 0"):
        sizing.reshaped(G, 0.0, 1.0)


def test_the_scale_that_explains_the_frames_best_undoes_a_shrunk_template(cylinders):
    """The shipped cylinder model keeps its own size; with its rod shrunk to 0.75 of it, the
    frames choose a larger scale. No label is read."""
    seg = Segmenter.from_checkpoint(CYLINDER, device="cpu")
    frames = load_sim_split(cylinders, "val", seg.prep_cfg)
    calib = {k: frames[k][:12] for k in ("x", "fg")}
    held = {k: frames[k][12:] for k in ("x", "fg")}
    own, rows = sizing.choose_scale(seg, calib, held, scales=(0.8, 1.0, 1.3))
    assert [r["scale"] for r in rows] == [0.8, 1.0, 1.3] and own == 1.0, rows
    tau, G = seg.tau, seg.G
    seg.G = sizing.scaled(G, 0.75)
    chosen, rows = sizing.choose_scale(seg, calib, held, scales=(1.0, 1.3))
    assert chosen == 1.3, rows
    assert seg.tau == tau  # the segmenter is left as it was
    with pytest.raises(ValueError, match="scales"):
        sizing.choose_scale(seg, calib, held, scales=(0.0, 1.0))


def test_the_loop_sizes_the_rod_then_chooses_its_scale_and_resumes(cylinders, tmp):
    """`inseggan loop --size-by-thickness --size-rounds 1` on the shipped cylinder's rod made
    too small: resized to the frames' thickness first, then a scale chosen; where it is not 1,
    the piles and the encoder again at that scale, and the shipped template is that one.
    Started again, nothing is redone."""
    start = tmp / "small.pt"
    state = checkpoint.load(CYLINDER)
    sizing.scale_state(state, 0.6)
    checkpoint.save(start, state)
    out = tmp / "loop"
    args = ["loop", "--model", start, "--data", cylinders, "--out", out, "--scenes", "12",
            "--val-scenes", "4", "--iterations", "6", "--centre-iterations", "0",
            "--size-by-thickness", "--size-rounds", "1", "--quiet"]
    p = run_cli(*args, check=True, timeout=900)
    assert "rod sized to the frames' thickness" in p.stdout, p.stdout
    summary = json.loads((out / "summary.json").read_text())
    size = summary["size"]
    assert 0.9 * DIAMETER * 1000 < size["thickness_mm"] < 1.15 * DIAMETER * 1000
    assert size["dimensions_mm_after"][2] == pytest.approx(size["thickness_mm"], rel=1e-3)
    assert size["dimensions_mm_before"][2] < 0.8 * size["thickness_mm"]  # it was too small
    (chosen,) = summary["size_rounds"]
    assert [r["scale"] for r in chosen["rows"]] == list(sizing.SCALES)
    sized = checkpoint.load(out / "size" / "model.pt")["generator"]
    shipped = checkpoint.load(out / "model" / "model.pt")["generator"]
    if chosen["scale"] != 1.0:
        assert list(summary["seconds"]) == ["size", "simulate", "encoder", "scale1",
                                            "simulate1", "encoder1", "export"]
        want = float(sized["log_radius"]) + float(torch.tensor(chosen["scale"]).log())
        assert (out / "size_round1" / "encoder" / "summary.json").is_file()
    else:
        assert list(summary["seconds"]) == ["size", "simulate", "encoder", "scale1", "export"]
        want = float(sized["log_radius"])
        assert not (out / "size_round1" / "sim").exists()
    assert float(shipped["log_radius"]) == pytest.approx(want, abs=1e-5)
    stamps = {f: f.stat().st_mtime_ns for f in (out / "size" / "model.pt", out / "encoder" /
              "last.pt", out / "size_round1" / "scale.json")}
    run_cli(*args, check=True, timeout=600)
    assert {f: f.stat().st_mtime_ns for f in stamps} == stamps
    p = refused("loop", "--model", start, "--data", cylinders, "--out", tmp / "o",
                "--size-rounds", "-1")
    assert p.returncode == 2 and "size_rounds -1 invalid" in p.stderr, p.stderr
    p = refused("loop", "--model", resolve_model("wooden_block"), "--data", cylinders, "--out",
                tmp / "o", "--size-by-thickness")  # a convex template: refused before any stage
    assert p.returncode == 2 and "size a rod of spheres" in p.stderr, p.stderr
    assert not (tmp / "o").exists()


def test_by_default_only_a_rod_the_loop_learns_is_sized_and_a_flat_parts_is_left_as_is(
        cylinders, tmp):
    """The defaults (`--size-by-thickness auto`, `--size-rounds` unset): a rod the loop learns
    itself is sized to the thickness if it is elongated and gets AUTO_SIZE_ROUNDS rounds; a
    given model is left alone; asking for sizing of a convex template is refused. The stage
    itself leaves the shipped hex nut's rod (about as long as wide: a nut lies flat, so its
    thickness is not its width) as it is, and resizes the shipped cylinder's."""
    auto = LoopConfig()
    assert size_plan(auto, True, "spheres") == ("if_elongated", AUTO_SIZE_ROUNDS)
    assert size_plan(auto, False, "spheres") == ("off", 0)
    assert size_plan(auto, True, "convex") == ("off", 0)
    assert size_plan(LoopConfig(size_by_thickness="on", size_rounds=1), False,
                     "spheres") == ("on", 1)
    assert size_plan(LoopConfig(size_by_thickness="off", size_rounds=0), True,
                     "spheres") == ("off", 0)
    with pytest.raises(ValueError, match="size a rod of spheres"):
        size_plan(LoopConfig(size_rounds=1), True, "convex")
    keep = LoopConfig(size_keep_length=True)  # the rule it changes must be on
    assert size_plan(keep, True, "spheres") == ("if_elongated", AUTO_SIZE_ROUNDS)
    assert size_plan(LoopConfig(size_by_thickness="on", size_keep_length=True), False,
                     "spheres") == ("on", 0)
    for learns, renderer in ((False, "spheres"), (True, "convex")):
        with pytest.raises(ValueError, match="--size-keep-length changes the thickness rule"):
            size_plan(keep, learns, renderer)
    with pytest.raises(ValueError, match="size_by_thickness 'yes' invalid"):
        LoopConfig(size_by_thickness="yes")

    nut = resolve_model("hex_nut")
    assert size_stage(nut, cylinders, tmp / "nut", auto, only_elongated=True) == nut
    left = json.loads((tmp / "nut" / "size.json").read_text())
    assert "not elongated" in left["left_as_is"] and not (tmp / "nut" / "model.pt").exists()
    assert size_stage(nut, cylinders, tmp / "nut", auto, only_elongated=True) == nut  # resumed
    sized = size_stage(CYLINDER, cylinders, tmp / "cyl", auto, only_elongated=True)
    assert sized == tmp / "cyl" / "model.pt"
    done = json.loads((tmp / "cyl" / "size.json").read_text())
    assert sizing.elongated(done["dimensions_mm_before"])
    assert done["dimensions_mm_after"][2] == pytest.approx(done["thickness_mm"], rel=1e-3)


def test_a_folder_whose_piles_were_made_unsized_is_not_sized_under_them(cylinders, tmp):
    """A loop folder holding piles (or an encoder) but no size/size.json was started without the
    size stage: resumed, the default plan drops the stage (the run goes on as started), and
    the stage asked for is refused before anything runs, naming the way out."""
    fresh, old, sized = tmp / "fresh", tmp / "old", tmp / "sized"
    (old / "sim").mkdir(parents=True)
    (old / "sim" / "meta.json").write_text("{}")
    (sized / "encoder").mkdir(parents=True)
    (sized / "size").mkdir()
    (sized / "size" / "size.json").write_text("{}")
    assert resume_plan("if_elongated", fresh) == "if_elongated"
    assert resume_plan("if_elongated", sized) == "if_elongated"
    assert resume_plan("if_elongated", old) == "off"
    assert resume_plan("off", old) == "off"
    with pytest.raises(ValueError, match="made without the size stage.*--size-by-thickness off"):
        resume_plan("on", old)
    with pytest.raises(ValueError, match="made without the size stage"):
        run(CYLINDER, cylinders, old, LoopConfig(size_by_thickness="on"), progress=False)
    assert sorted(p.name for p in old.iterdir()) == ["sim"]  # nothing written
