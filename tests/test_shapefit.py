"""`inseggan shape-fit`: a convex template fitted by reconstruction to a box part's unlabelled
frames, from a rod model, moves towards the true part; the result is a model the rest of the
product takes; a finished run is not redone and a different one is not resumed into it."""
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import refused, run_cli

from inseggan_ros.core import checkpoint
from inseggan_ros.runtime.model import ConvexGenerator
from inseggan_ros.runtime.segment import Segmenter
from inseggan_ros.learning.shapefit import (
    ShapeFitConfig, convex_from_rod, fit_shape, hold_out, rod_box, rod_discs)
from inseggan_ros.runtime.model import build_models

# the wooden block's rod model as the GAN left it (no label of any kind): test_loop's
MODEL = Path(__file__).resolve().parent / "data" / "wooden_block_unsupervised.pt"


def test_the_convex_start_is_the_rods_bounding_box_with_its_encoder():
    state = checkpoint.load(MODEL)
    _, rod, E = build_models(state, MODEL)
    new, G, E2 = convex_from_rod(state, ShapeFitConfig())
    assert isinstance(G, ConvexGenerator) and new["model_config"]["renderer"] == "convex"
    c, r = (t.detach() for t in rod.spheres())
    a, b, h = rod_box(rod)
    assert a == pytest.approx(float((c[:, 0].abs() + r).max())) and b == h == float(r.max())
    x, real = G.corners()  # the box's corners: +-a, +-b, and 0..2h in z
    x = x[real]
    np.testing.assert_allclose(x.amax(0).tolist(), [a, b, 2 * h], atol=1e-5)
    np.testing.assert_allclose(x.amin(0).tolist(), [-a, -b, 0], atol=1e-5)
    z = torch.randn(2, 3, rod.cfg.latent_dim)
    # the same poses for the same codes: every instance starts where the rod put it
    torch.testing.assert_close(G.pose(z.reshape(6, -1)), rod.pose(z.reshape(6, -1)))
    for k, v in E.state_dict().items():
        torch.testing.assert_close(v, E2.state_dict()[k])


def _stepped_rod(head: float = 0.2, shaft: float = 0.1):
    """A rod of 12 spheres: the first three `head` wide, the rest `shaft` (a bolt's profile)."""
    from inseggan_ros.runtime.model import ModelConfig, SphereGenerator

    rod = SphereGenerator(ModelConfig(renderer="spheres", composite="zbuffer", spheres=12,
                                      radius_profile="free"))
    with torch.no_grad():  # radii = e^log_radius (0.5 + 0.5 sigmoid(shape))
        rod.log_radius.fill_(np.log(head))
        rod.radius_shape.copy_(torch.tensor([9.0] * 3 + [0.0] * 9))  # 1.0 x, then 0.75 x
        rod.length.fill_(1.0)
    return rod


def test_discs_follow_a_rods_step_and_make_one_body_of_those_sizes():
    """A rod with a head: two discs cut near the head's end, the head's the wider; built as a
    convex template, each piece spans its segment along the axis with walls at its radius,
    and the whole is one connected body."""
    from inseggan_ros.runtime.model import CONVEX_MIN_EXTENT, ModelConfig
    from inseggan_ros.evaluation.shape import components, template_pieces

    rod = _stepped_rod()
    c, r = (t.detach() for t in rod.spheres())
    discs = rod_discs(rod, 2, 8)
    assert len(discs) == 2
    (a0, a1, ra), (b0, b1, rb) = discs
    assert ra > 1.2 * rb  # the head, then the shaft (the widening order: the head first)
    ends = sorted([a0, a1, b0, b1])
    assert ends[0] == pytest.approx(float((c[:, 0] - r).min()), abs=0.01)
    assert ends[-1] == pytest.approx(float((c[:, 0] + r).max()), abs=0.01)
    step = float(c[2, 0] + r[2])  # where the third (last wide) sphere ends
    cut = a1 if a0 < b0 else a0
    assert abs(cut - step) < 0.1
    G = ConvexGenerator(ModelConfig(renderer="convex", composite="zbuffer", pieces=2, walls=8,
                                    floor_contact=True))
    G.init_discs(discs, 0.0)
    x, real = (t.detach() for t in G.corners())
    for k, (x0, x1, rad) in enumerate(discs):
        xk = x[k][real[k]]  # an octagon about x with walls facing +-y and +-z: those at rad
        assert float(xk[:, 1].abs().max()) == pytest.approx(rad, rel=1e-3)
        assert float(xk[:, 2].abs().max()) == pytest.approx(rad, rel=1e-3)
        lo, hi = float(xk[:, 0].min()), float(xk[:, 0].max())
        if k == 0:  # the first disc spans its segment
            assert (lo, hi) == (pytest.approx(x0, abs=1e-4), pytest.approx(x1, abs=1e-4))
        else:  # the next one its segment and back to the previous one's centre (connected)
            prev = (discs[k - 1][0] + discs[k - 1][1]) / 2
            end, reached = (x1, hi) if x0 > prev else (x0, lo)  # its end away from the previous
            assert reached == pytest.approx(end, abs=1e-4)
            assert min(lo, hi) <= prev + 1e-4 and max(lo, hi) >= prev - 1e-4
    assert components(template_pieces(G)) == 1
    with pytest.raises(ValueError, match="segments"):
        G.init_discs([(0.0, CONVEX_MIN_EXTENT, 0.1), (0.1, 0.3, 0.1)], 0.0)
    with pytest.raises(ValueError, match="pieces"):
        rod_discs(rod, 200, 8)


def test_a_tapered_disc_is_a_frustum_of_its_radii_and_the_rest_is_refused():
    """`taper` (a cone, a stopper): one disc whose walls lean in along the axis, its apothem r
    at x0 and taper x r at x1, the caps where the disc ends (its corners the frustum's), one
    body; a taper of two discs, a wall steeper than a tilt can lean, a point thinner than a
    piece's least extent, and a taper of a box or a ring are refused by name."""
    import math

    from inseggan_ros.runtime.model import CONVEX_MIN_EXTENT, ModelConfig, taper_slope
    from inseggan_ros.evaluation.shape import components, occupancy, template_pieces

    G = ConvexGenerator(ModelConfig(renderer="convex", composite="zbuffer", pieces=1, walls=8,
                                    floor_contact=True))
    x0, x1, r, taper = -0.4, 0.4, 0.3, 0.2
    G.init_discs([(x0, x1, r)], 0.0, taper)
    x, real = (t.detach() for t in G.corners())
    x = x[0][real[0]]
    assert len(x) == 16  # two octagons, one at each end
    for end, rad in ((x0, r), (x1, taper * r)):
        ring = x[(x[:, 0] - end).abs() < 1e-4]
        assert len(ring) == 8  # the octagon's corners at its apothem / cos(pi / 8)
        np.testing.assert_allclose(ring[:, 1:].norm(dim=1), rad / math.cos(math.pi / 8),
                                   rtol=1e-4)
    assert components(template_pieces(G)) == 1
    # inside at the wide end's rim, outside at the narrow end's: the walls lean
    inside = occupancy(template_pieces(G), np.array([[x0 + 0.01, 0.0, 0.9 * r],
                                                     [x1 - 0.01, 0.0, 0.9 * r],
                                                     [x1 - 0.01, 0.0, 0.9 * taper * r]]))
    assert list(inside) == [True, False, True]
    assert taper_slope((x0, x1, r), taper) == pytest.approx(r * (1 - taper) / (x1 - x0))
    with pytest.raises(ValueError, match="one piece"):
        ConvexGenerator(ModelConfig(renderer="convex", composite="zbuffer", pieces=2, walls=8)
                        ).init_discs([(-0.4, 0.0, 0.3), (0.0, 0.4, 0.1)], 0.0, taper)
    with pytest.raises(ValueError, match="leaning"):  # a short, wide disc to a point
        G.init_discs([(-0.1, 0.1, 0.3)], 0.0, 0.2)
    with pytest.raises(ValueError, match="narrow end"):
        G.init_discs([(x0, x1, r)], 0.0, CONVEX_MIN_EXTENT / r / 2)
    with pytest.raises(ValueError, match="taper"):
        ShapeFitConfig(taper=0.5)  # a box
    with pytest.raises(ValueError, match="taper"):
        ShapeFitConfig(start="discs", pieces=1, walls=12, hole=0.5, taper=0.5)  # a ring
    with pytest.raises(ValueError, match="taper"):
        ShapeFitConfig(start="discs", pieces=1, taper=0.0)


def test_a_flange_between_two_shafts_is_built_as_thin_as_its_disc():
    """Three discs, the middle the widest (a pin's flange): built in the order along the axis,
    the flange reaches back to the first shaft's centre at its own width (4 times as long as
    its disc); `piece_order` builds it first, so each shaft reaches back into a piece no
    narrower and the body is the discs themselves, still one piece."""
    from inseggan_ros.runtime.model import CONVEX_MIN_EXTENT, ModelConfig
    from inseggan_ros.evaluation.shape import components, template_pieces
    from inseggan_ros.learning.shapefit import piece_order, spill

    discs = [(-0.4, -0.05, 0.1), (-0.05, 0.05, 0.23), (0.05, 0.4, 0.1)]
    order = piece_order(discs)
    assert order[0] == discs[1] and sorted(order) == sorted(discs)
    assert spill(order) == pytest.approx(0.0, abs=1e-12)
    assert spill(discs) == pytest.approx(0.175 * (0.23 ** 2 - 0.1 ** 2))  # half a shaft
    bolt = [(-0.4, -0.2, 0.2), (-0.2, 0.4, 0.1)]
    assert piece_order(bolt) == bolt and piece_order(bolt[::-1]) == bolt  # the head first

    def flange_span(segments):
        G = ConvexGenerator(ModelConfig(renderer="convex", composite="zbuffer", pieces=3,
                                        walls=8, floor_contact=True))
        G.init_discs(segments, 0.0)
        assert components(template_pieces(G)) == 1
        x, real = (t.detach() for t in G.corners())
        k = segments.index(discs[1])
        xk = x[k][real[k]]
        return float(xk[:, 0].min()), float(xk[:, 0].max())

    lo, hi = flange_span(discs)
    # back to the first shaft's centre (and the ball about it): 0.1 + 0.175 + the ball
    assert (lo, hi) == (pytest.approx(-0.225 - CONVEX_MIN_EXTENT, abs=2e-3),
                        pytest.approx(0.05, abs=1e-4))
    assert flange_span(order) == (pytest.approx(-0.05, abs=1e-4), pytest.approx(0.05, abs=1e-4))


def test_a_disc_start_renders_as_its_rod_did_for_the_rods_poses():
    """`shape-fit --start discs`: the convex template from the rod model's profile, about the
    rod's axis, so that the rod's encoder and pose decoder place it where they placed the rod:
    the same codes give renders that cover nearly the same pixels."""
    state = checkpoint.load(MODEL)
    _, rod, _ = build_models(state, MODEL)
    _, G, _ = convex_from_rod(state, ShapeFitConfig(pieces=2, walls=8, start="discs"))
    z = torch.randn(4, 3, rod.cfg.latent_dim, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        a = rod.render_instances(z) > -1 + 1e-3
        b = G.render_instances(z) > -1 + 1e-3
    iou = float((a & b).sum()) / float((a | b).sum())
    assert iou > 0.7  # measured 0.81 (the discs have flat ends where the rod is round)
    with pytest.raises(ValueError, match="start"):
        ShapeFitConfig(start="sphere")


def test_shape_fit_with_no_iterations_writes_the_discs_a_simulator_drops(tmp):
    """`shape-fit --start discs --iterations 0`: the discs of the rod's profile, measured on
    the frames and against the true part, not fitted; a model `simulate --object` piles up."""
    user = tmp / "user"
    run_cli("simulate", "--quiet", "--object", "bolt", "--instances", "4", "--count", "12",
            "--split", "8,4,0", "--seed", "5", "--camera", "realsense_d435", "--noise",
            "realsense", "--workers", "1", "--out", user, check=True, timeout=300)  # MODEL's view
    out = tmp / "discs"
    p = run_cli("shape-fit", "--model", MODEL, "--data", user, "--out", out, "--start", "discs",
                "--pieces", "2", "--walls", "8", "--iterations", "0", "--frames", "8", "--quiet",
                check=True, timeout=300)
    assert "IoU with the true part" in p.stdout, p.stdout + p.stderr
    # the search's grid, refused without it
    for flag in ("--pile-stretches", "--pile-holes", "--fine-piles"):
        bad = refused("shape-fit", "--model", MODEL, "--data", user, "--out", tmp / "bad",
                      "--start", "discs", "--iterations", "0", flag, "1", "--quiet")
        assert bad.returncode != 0 and "valid: with --match-piles" in bad.stderr, bad.stderr
        assert not (tmp / "bad").exists()
    s = json.loads((out / "summary.json").read_text())
    assert s["iterations"] == 0 and s["model"] == str(out / "best.pt")
    assert s["best"]["iteration"] == 0 and s["best"]["recon_l1"] > 0
    _, G, _ = build_models(checkpoint.load(out / "best.pt"))
    _, start, _ = convex_from_rod(checkpoint.load(MODEL),
                                  ShapeFitConfig(pieces=2, walls=8, start="discs"))
    for a, b in zip(G.halfspaces(), start.halfspaces()):
        torch.testing.assert_close(a, b)
    piles = tmp / "piles"
    run_cli("simulate", "--quiet", "--object", out / "best.pt", "--count", "2", "--split",
            "2,0,0", "--seed", "5", "--workers", "1", "--out", piles, check=True, timeout=300)
    from inseggan_ros.data.datasets import load_sim_split

    assert int(load_sim_split(piles, "train")["labels"].max()) >= 1
    from inseggan_ros.learning.centres import piles_part

    # what a centre-vote net taught on them records (its card names the piles' part)
    assert piles_part(piles) == ("the learned rod's profile as 2 flat-ended discs, not fitted, "
                                 f"from `{out / 'best.pt'}`")
    assert piles_part(user) == "the simulator's bolt (the true part)"
    with pytest.raises(ValueError, match="iterations"):
        ShapeFitConfig(iterations=-1)


def test_a_ring_of_six_sectors_is_one_hexagonal_nut_with_its_hole_open():
    """`ConvexGenerator.init_ring`: six convex sectors make the hexagonal ring of that
    thickness, apothem and hole (volumetric IoU on a voxel grid), one connected body; a
    wall too thin for a sector to hold its neighbour's centre is refused, as is a hole on a
    template that is not one disc of 12 walls."""
    from inseggan_ros.evaluation import shape
    from inseggan_ros.runtime.model import ModelConfig

    G = ConvexGenerator(ModelConfig(renderer="convex", composite="zbuffer", pieces=6,
                                    walls=12, floor_contact=True))
    x0, x1, r, hole = -0.1, 0.14, 0.25, 0.6
    G.init_ring((x0, x1, r), hole)
    pieces = shape.template_pieces(G)
    assert shape.components(pieces) == 1
    g = np.linspace(-0.4, 0.4, 121)
    p = np.stack([v.ravel() for v in np.meshgrid(g, g, g, indexing="ij")], 1)
    ang = np.arange(6) * np.pi / 3  # the flats' normals about the x axis
    flats = (p @ np.stack([np.zeros(6), np.sin(ang), -np.cos(ang)])).max(1)
    true = (p[:, 0] >= x0) & (p[:, 0] <= x1) & (flats <= r) & (flats >= hole * r)
    got = shape.occupancy(pieces, p)
    assert (got & true).sum() / (got | true).sum() > 0.97  # measured 0.99
    assert not got[flats < 0.9 * hole * r].any()  # the hole open
    with pytest.raises(ValueError, match="wall"):
        G.init_ring((x0, x1, r), 0.8)  # a wall of 0.05, thinner than 2.2 x 0.03
    with pytest.raises(ValueError, match="ring"):
        ConvexGenerator(ModelConfig(renderer="convex", composite="zbuffer", pieces=2,
                                    walls=12)).init_ring((x0, x1, r), hole)
    with pytest.raises(ValueError, match="walls 12"):
        ShapeFitConfig(pieces=1, walls=8, start="discs", hole=0.5)
    ShapeFitConfig(pieces=1, walls=12, start="discs", hole=0.5)


def test_a_short_recording_still_holds_frames_out_to_keep_the_best_fit_by():
    """A recording's frames are one sequence: `frames` to fit, the next `val_frames` to measure
    the fit on; a recording shorter than both (320 frames of a 400-frame bag, the default 1000
    + 100) keeps its last fifth for validation instead of validating on nothing."""
    frames = np.arange(2000)
    train, val = hold_out(frames, ShapeFitConfig())
    assert (len(train), len(val), val[0]) == (1000, 100, 1000)
    train, val = hold_out(frames[:320], ShapeFitConfig())
    assert (len(train), len(val)) == (256, 64) and val[0] == 256 and val[-1] == 319
    train, val = hold_out(frames[:320], ShapeFitConfig(frames=100, val_frames=30))
    assert (len(train), len(val), val[0]) == (100, 30, 100)
    train, val = hold_out(frames[:4], ShapeFitConfig())
    assert (len(train), len(val)) == (4, 0)  # too few to spare one: fitted on all, kept last


def test_only_a_rod_model_is_a_starting_point():
    from inseggan_ros.runtime.model import ModelConfig

    convex, _, _ = convex_from_rod(checkpoint.load(MODEL), ShapeFitConfig())
    G = ConvexGenerator(ModelConfig.from_dict(convex["model_config"]))
    with pytest.raises(ValueError, match="starts from a rod model"):
        convex_from_rod({**convex, "generator": G.state_dict()}, ShapeFitConfig())


def test_a_short_fit_moves_the_box_towards_the_true_block_and_is_not_redone(tmp):
    user = tmp / "user"
    run_cli("simulate", "--quiet", "--object", "wooden_block", "--instances", "4", "--count", "40",
            "--split", "32,8,0", "--seed", "31", "--camera", "realsense_d435", "--noise",
            "realsense", "--workers", "2", "--out", user, check=True, timeout=600)
    out = tmp / "fit"
    args = ["shape-fit", "--model", MODEL, "--data", user, "--out", out, "--iterations", "100",
            "--eval-every", "50", "--frames", "32", "--quiet"]
    p = run_cli(*args, check=True, timeout=900)
    assert "shape fitted" in p.stdout, p.stdout + p.stderr
    s = json.loads((out / "summary.json").read_text())
    first, kept = s["first"], s["best"]  # the start, and the evaluation kept (best.pt)
    msg = f"{first} -> {kept}"
    # measured: IoU 0.39 -> 0.52, the length 78 -> 69 mm, validation L1 0.53 -> 0.30
    assert s["model"] == str(out / "best.pt") and kept["iteration"] > 0, msg
    assert kept["shape_iou"] > first["shape_iou"] + 0.05, msg
    assert abs(max(kept["dims_mm"]) - 50) < abs(max(first["dims_mm"]) - 50) - 2, msg
    assert kept["recon_l1"] < 0.8 * first["recon_l1"], msg
    assert (out / "curves.png").is_file()
    # a model the product takes: it loads, and segments a frame
    seg = Segmenter.from_checkpoint(out / "best.pt", device="cpu")
    assert isinstance(seg.G, ConvexGenerator)
    from inseggan_ros.data.datasets import load_sim_split

    frame = load_sim_split(user, "val", limit=1)
    with torch.no_grad():
        labels = seg.segment_batch(frame["x"], frame["fg"])["labels"]
    assert labels.shape == (1, 64, 64) and int(labels.max()) >= 1
    # started again: nothing is redone; with other settings: refused, named
    stamp = (out / "last.pt").stat().st_mtime_ns
    run_cli(*args, check=True, timeout=600)
    assert (out / "last.pt").stat().st_mtime_ns == stamp
    (out / "summary.json").unlink()
    with pytest.raises(ValueError, match="same model and config to resume"):
        fit_shape(MODEL, frame["x"], out, ShapeFitConfig(iterations=7), progress=False)


def test_a_killed_fit_resumes_where_it_stopped_and_ends_as_an_unbroken_one(tmp):
    """Killed after its first checkpoint (here: the report raising at the second evaluation),
    a fit started again continues from last.pt and ends with the very weights of a run that
    was never stopped (the optimiser's state and the batch draws are restored too)."""
    _, rod, _ = build_models(checkpoint.load(MODEL), MODEL)
    with torch.no_grad():  # frames the rod itself draws: something to reconstruct
        z = torch.randn(12, rod.cfg.n_instances, rod.cfg.latent_dim,
                        generator=torch.Generator().manual_seed(0))
        x = rod.zbuffer(rod.render_instances(z)).numpy()  # (12, 1, 64, 64)
    cfg = ShapeFitConfig(iterations=6, eval_every=3, batch_size=4, frames=12)
    fit_shape(MODEL, x, tmp / "whole", cfg, val_x=x[:4], progress=False)

    class Killed(Exception):
        pass

    calls = []

    def dies_at_the_second_evaluation(G):
        calls.append(1)
        if len(calls) == 3:  # iteration 0, 3, then 6: killed before the save at 6
            raise Killed
        return {"iou": 0.0, "dims_template_mm": [0, 0, 0], "dims_true_mm": [0, 0, 0]}

    with pytest.raises(Killed):
        fit_shape(MODEL, x, tmp / "killed", cfg, val_x=x[:4], progress=False,
                  report=dies_at_the_second_evaluation)
    assert checkpoint.load(tmp / "killed" / "last.pt")["shape_fit"]["iteration"] == 3
    fit_shape(MODEL, x, tmp / "killed", cfg, val_x=x[:4], progress=False)
    a = checkpoint.load(tmp / "whole" / "last.pt")
    b = checkpoint.load(tmp / "killed" / "last.pt")
    assert b["shape_fit"]["iteration"] == 6
    for key in ("generator", "encoder"):
        for name, v in a[key].items():
            torch.testing.assert_close(v, b[key][name], rtol=0, atol=0)


def test_a_convex_model_refuses_refinement_by_name_and_runs_without():
    """The shipped wooden_block model is a convex template (shape-fit, then the loop): a pose
    fit is the rod's, so refine_steps > 0 is refused with what is valid (the segmenter node
    rejects the parameter with this message), and its own settings run."""
    from dataclasses import replace

    from conftest import REPO

    seg = Segmenter.from_checkpoint(REPO / "models" / "wooden_block" / "model.pt", device="cpu")
    assert isinstance(seg.G, ConvexGenerator) and seg.inference.refine_steps == 0
    seg.check(seg.inference)
    with pytest.raises(ValueError, match="refine_steps 5: .*convex.*valid: 0"):
        seg.check(replace(seg.inference, refine_steps=5))
