"""The template family chosen by the user's frames (`learning/family.py`): each family made from
the learned rod, piled at several scales in the user's bin, scored against the frames without
a label; the scaled templates exact; the choice resumable."""
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import REPO

from inseggan_ros.core import checkpoint
from inseggan_ros.learning import family
from inseggan_ros.learning.piles import BagFrames, pile_view
from inseggan_ros.learning.family import FAMILIES
from inseggan_ros.learning import shapefit
from inseggan_ros.learning.shapefit import ShapeFitConfig, convex_from_rod, flat_top, rod_box
from inseggan_ros.runtime.model import build_models
from inseggan_ros.runtime.preprocess import PreprocessConfig
from inseggan_ros.sim.learned import template_pieces_units

ROD = Path(__file__).resolve().parent / "data" / "wooden_block_unsupervised.pt"  # a block's rod
BAG = REPO / "bags" / "wooden_block_realsense"  # 8 frames of 4 blocks, the rod's camera


def _extent(file: Path) -> np.ndarray:
    state = checkpoint.load(file)
    pts = np.concatenate(template_pieces_units(build_models(state, file)[1]))
    return pts.max(0) - pts.min(0)


def test_config_refuses_what_it_cannot_do():
    for kw, said in (({"families": ("rod", "cube")}, "families"),
                     ({"families": ()}, "families"),
                     ({"families": ("box", "box")}, "each once"),
                     ({"scales": (1.0, 0.5)}, "scales"),
                     ({"scales": (0.0, 1.0)}, "scales"),
                     ({"piles": 0}, "piles"),
                     ({"extend": -1}, "extend"),
                     ({"refine": -1}, "refine"),
                     ({"leaders": -2}, "leaders"),
                     ({"frames": 50, "val_frames": 50}, "val_frames")):
        with pytest.raises(ValueError, match=said):
            family.FamilyConfig(**kw)


def test_the_scale_search_steps_past_the_grid_only_while_its_best_is_at_an_end():
    seen = []

    def distance_to(best):
        def measure(v):
            seen.append(v)
            return abs(v - best)
        return measure

    cfg = family.FamilyConfig()
    w1 = family.scale_search(distance_to(1.5), cfg)  # beyond the top: 1.18, 1.38, 1.63
    assert list(w1)[:4] == [0.55, 0.7, 0.85, 1.0]
    assert list(w1)[4:] == pytest.approx([1 / 0.85, 1 / 0.85 ** 2, 1 / 0.85 ** 3], abs=1e-3)
    assert min(w1, key=w1.get) == list(w1)[5]  # 1.38 brackets 1.5: no step past 1.63
    w1 = family.scale_search(distance_to(0.8), cfg)  # inside the grid: nothing more
    assert list(w1) == [0.55, 0.7, 0.85, 1.0]
    w1 = family.scale_search(distance_to(0.01), cfg)  # below it, at most `extend` steps
    assert len(w1) == 4 + cfg.extend and min(w1) < 0.55 * 0.786 ** 2
    seen.clear()
    w1 = family.scale_search(distance_to(9.0), family.FamilyConfig(extend=0))
    assert list(w1) == seen == [0.55, 0.7, 0.85, 1.0]


def test_the_refinement_halves_the_step_about_the_best_each_round():
    """A V-shaped distance whose minimum (1.3) lies between grid points: each round measures
    the geometric middles between the best and its two neighbours, so the best found moves
    to within the last step of the minimum; no time left, nothing is measured."""
    seen = []

    def measure(v):
        seen.append(v)
        return abs(np.log(v / 1.3))

    w1 = {v: measure(v) for v in (1.0, 1.1765, 1.3842, 1.6286)}
    seen.clear()
    one = family.refine_scale(measure, w1, 1)
    assert seen == pytest.approx([(1.1765 * 1.3842) ** 0.5, (1.3842 * 1.6286) ** 0.5], abs=1e-4)
    two = family.refine_scale(measure, w1, 2)
    assert set(one) < set(two) and len(two) == len(w1) + 4
    best = min(two, key=two.get)
    assert abs(np.log(best / 1.3)) < abs(np.log(min(w1, key=w1.get) / 1.3)) / 2
    assert abs(np.log(best / 1.3)) <= np.log(1.3842 / 1.1765) / 4 + 1e-6
    seen.clear()
    assert family.refine_scale(measure, w1, 2, more=lambda: False) == w1 and not seen


def test_the_score_sums_each_measure_over_the_best_and_the_edges_only_when_asked():
    rows = [{"pile_w1": 0.02, "edge_w1": 0.4, "recon_l1": 0.3},
            {"pile_w1": 0.04, "edge_w1": 0.1, "recon_l1": 0.3}]
    assert family.combined(rows) == pytest.approx([2.0, 3.0])
    assert family.combined(rows, edges=True) == pytest.approx([6.0, 4.0])


def test_a_scaled_template_is_the_same_shape_that_many_times_as_large(tmp):
    """A rod and a convex template (a box, two boxes) scaled by `scaled_model`: every extent x s,
    the rest of the model (its encoder, its poses) as it was; scale 1 is the file itself."""
    state = checkpoint.load(ROD)
    for pieces in (1, 2):
        new, G, E = convex_from_rod(state, ShapeFitConfig(pieces=pieces), ROD)
        box = checkpoint.save(tmp / f"box{pieces}.pt", {
            **new, "generator": G.state_dict(), "encoder": E.state_dict()})
        for file in (ROD, box):
            assert family.scaled_model(file, 1.0, tmp / "same.pt") == Path(file)
            half = family.scaled_model(file, 0.5, tmp / f"half_{pieces}_{Path(file).stem}.pt")
            np.testing.assert_allclose(_extent(half), 0.5 * _extent(file), rtol=2e-3, atol=2e-3)
            a, b = checkpoint.load(file), checkpoint.load(half)
            assert all(torch.equal(v, b["encoder"][k]) for k, v in a["encoder"].items())
            assert all(torch.equal(v, b["generator"][k]) for k, v in a["generator"].items()
                       if k.startswith("pose."))


def test_bars_scaled_across_keep_their_height(tmp):
    """The bars' height is the frames' (`shapefit.flat_top`), so the scale search sizes their
    outline only: `scaled_model(flat=True)` scales x and y, keeps z; refused on a rod and on
    tilted pieces, naming what is valid."""
    state = checkpoint.load(ROD)
    new, G, E = convex_from_rod(state, ShapeFitConfig(pieces=3, walls=4, start="u"), ROD)
    u = checkpoint.save(tmp / "u.pt", {**new, "generator": G.state_dict(),
                                       "encoder": E.state_dict()})
    assert set(family.FLAT) == {"bar", "tee", "ell", "u"}
    wide = family.scaled_model(u, 1.5, tmp / "wide.pt", flat=True)
    np.testing.assert_allclose(_extent(wide), _extent(u) * [1.5, 1.5, 1.0], rtol=2e-3,
                               atol=2e-3)
    whole = family.scaled_model(u, 1.5, tmp / "whole.pt")
    np.testing.assert_allclose(_extent(whole), _extent(u) * 1.5, rtol=2e-3, atol=2e-3)
    with pytest.raises(ValueError, match="a rod is scaled whole; valid: flat with a convex"):
        family.scaled_model(ROD, 1.5, tmp / "rod.pt", flat=True)
    tilted = checkpoint.load(u)
    tilted["generator"]["tilt"][0, 2, 0] = 0.3
    tilted = checkpoint.save(tmp / "tilted.pt", tilted)
    with pytest.raises(ValueError, match="its pieces are tilted; valid: flat with upright"):
        family.scaled_model(tilted, 1.5, tmp / "t.pt", flat=True)


def test_a_block_s_frames_choose_a_box_over_the_rod_and_the_taper_and_resume(tmp):
    """On a recording of blocks, from the block's learned rod (round-ended, as tall as it is
    wide), the fitted box's piles look most like the frames: it is kept, at one of the grid's
    scales; every candidate's scores are recorded; asked again, nothing is made again."""
    state = checkpoint.load(ROD)
    data = BagFrames(BAG, 4)
    x = data.frames(PreprocessConfig.from_dict(state["preprocess_config"]))[0]["x"]
    cfg = family.FamilyConfig(families=("rod", "box", "taper"), piles=12, fit_iterations=60,
                              workers=2)
    out = tmp / "family"
    choice = family.choose(ROD, x, data, None, pile_view(data, state), out, cfg, progress=False)
    assert choice["kept"] == "box", choice["rows"]
    rows = {r["family"]: r for r in choice["rows"]}
    assert set(rows) == {"rod", "box", "taper"}
    for r in rows.values():
        assert {f"{v:g}" for v in cfg.scales} <= set(r["pile_w1_by_scale"])  # and any steps
        assert len(r["pile_w1_by_scale"]) <= len(cfg.scales) + cfg.extend  # past its ends
        assert r["pile_w1"] == pytest.approx(min(r["pile_w1_by_scale"].values()), abs=1e-5)
        assert r["score"] >= 2 - 1e-6
    assert rows["box"]["score"] == min(r["score"] for r in rows.values())
    assert not any("refined" in r for r in rows.values())  # no refinement by default
    assert choice["part"] == rows["box"]["part"] and Path(choice["part"]).is_file()
    assert checkpoint.load(choice["model"])["model_config"]["renderer"] == "convex"
    assert (out / "family.png").is_file() and (out / "views.png").is_file()
    stamp = (out / "family.json").stat().st_mtime_ns
    again = family.choose(ROD, x, data, None, pile_view(data, state), out, cfg, progress=False)
    assert again == json.loads((out / "family.json").read_text()) == choice
    assert (out / "family.json").stat().st_mtime_ns == stamp


def _inside(G, x: float, y: float) -> bool:
    """Whether the template holds the point (x, y) halfway up its pieces."""
    n, d = (t.detach() for t in G.halfspaces())
    p = torch.tensor([x, y, float(G.centre[0, 2].detach())])
    return bool(((n @ p) <= d).all(-1).any())


@pytest.mark.parametrize("kind", ["tee", "ell", "u"])
def test_bars_start_joined_as_a_t_an_l_or_a_u_from_the_rod_s_box(kind):
    """Copies of one box fitted to T-pieces' frames stayed one slab, so bars start joined: a
    bar 2a long across the top, and as long down from its middle (T), its end (L) or both its
    ends (U: three pieces, whose centres are not in one point), each as wide as the rod's
    radius, the outline centred on the origin."""
    state = checkpoint.load(ROD)
    rod = build_models(state, ROD)[1]
    a, b, _ = rod_box(rod)
    w = b / 2
    _, G, _ = convex_from_rod(state, ShapeFitConfig(pieces=3 if kind == "u" else 2, walls=4,
                                                    start=kind))
    top, bottom = a - w, -a + w / 2  # the top bar's middle; near the down bars' ends
    assert _inside(G, -0.9 * a, top) and _inside(G, 0.9 * a, top)  # the bar across
    assert not _inside(G, 0.0, top + 2 * w)  # nothing above it
    stems = {"tee": [0.0], "ell": [a - w], "u": [-a + w, a - w]}[kind]
    for stem in stems:
        assert _inside(G, stem, bottom) and _inside(G, stem, 0.0)  # each bar down, whole
    for x in (-0.9 * a, 0.0, 0.9 * a):
        if all(abs(x - stem) > 2 * w for stem in stems):
            assert not _inside(G, x, bottom), (kind, x)
    assert FAMILIES[kind].start == kind and kind not in family.FITTED  # the model keeps the rod
    with pytest.raises(ValueError, match="start tee is 2 bars; valid: pieces 2 and walls 4"):
        ShapeFitConfig(pieces=1, start="tee")
    with pytest.raises(ValueError, match="start u is 3 bars; valid: pieces 3 and walls 4"):
        ShapeFitConfig(pieces=2, start="u")


def test_a_lone_bar_is_as_long_as_the_rod_and_half_as_wide_or_as_asked():
    """The bar family: one bar 2a long (the rod's length) and b wide (half the rod's
    footprint, a 2:1 block from a round blob), centred on the origin; twice as wide, square at
    most as long; the model keeps the rod (not fitted) and its outline is what is scaled."""
    state = checkpoint.load(ROD)
    a, b, _ = rod_box(build_models(state, ROD)[1])
    _, G, _ = convex_from_rod(state, ShapeFitConfig(pieces=1, walls=4, start="bar"))
    w = b / 2
    assert _inside(G, -0.95 * a, 0.0) and _inside(G, 0.95 * a, 0.0)
    assert _inside(G, 0.0, -0.9 * w) and _inside(G, 0.0, 0.9 * w)
    assert not _inside(G, 1.1 * a, 0.0) and not _inside(G, 0.0, 1.2 * w)
    assert not _inside(G, 0.0, -1.2 * w)
    _, G, _ = convex_from_rod(state, ShapeFitConfig(pieces=1, walls=4, start="bar",
                                                    bar_width=2.0))
    half = max(a, b)  # as wide as the rod: square where the rod is as long as it is wide
    assert _inside(G, 0.0, 0.9 * b) and not _inside(G, 0.0, 1.1 * b)
    assert _inside(G, 0.95 * half, 0.0) and not _inside(G, 1.1 * half, 0.0)
    assert FAMILIES["bar"].start == "bar" and "bar" in family.FLAT
    assert "bar" not in family.FITTED
    with pytest.raises(ValueError, match="start bar is 1 bar; valid: pieces 1 and walls 4"):
        ShapeFitConfig(pieces=2, walls=4, start="bar")


def test_flat_parts_height_is_the_lowest_mode_of_the_frames_heights():
    """Parts lying flat at one height (0.3 model units), others leaning higher (spread to 1.5):
    the bars are as thick as the flat ones, not the lower quartile's; where the heights only
    fall from the threshold up (no mode seen) or there are too few, None."""
    rng = np.random.default_rng(0)
    state = checkpoint.load(ROD)
    gain = build_models(state, ROD)[1].cfg.height_gain
    x = np.full((40, 1, 32, 32), -1.0, np.float32)
    fg = rng.random(x.shape) < 0.5
    flat = 0.3 + rng.normal(0, 0.02, x.shape)
    leaning = rng.uniform(0.35, 1.5, x.shape)
    h = np.where(rng.random(x.shape) < 0.2, flat, leaning)
    x[fg] = (h[fg] - 1).astype(np.float32)
    top = flat_top(x, gain)
    assert top == pytest.approx(0.3 / gain, abs=shapefit.FLAT_BIN / gain)
    assert np.quantile(h[fg], 0.25) > 0.3 + 2 * shapefit.FLAT_BIN  # what rod_box would take
    falling = np.full((40, 1, 32, 32), -1.0, np.float32)
    falling[fg] = (0.24 + rng.exponential(0.3, x.shape)[fg] - 1).astype(np.float32)
    assert flat_top(falling, gain) is None
    assert flat_top(x[:, :, :2, :2][:1], gain) is None
    _, G, _ = convex_from_rod(state, ShapeFitConfig(pieces=3, walls=4, start="u"), x=x)
    heights = np.concatenate(template_pieces_units(G))[:, 2]
    assert np.ptp(heights) == pytest.approx(top, rel=0.02)


def test_bars_as_wide_as_asked():
    """`bar_width` scales the bars' width (times the rod's radius), not their length; refused,
    naming what is valid, outside (0, 2] or on a start that is not bars."""
    state = checkpoint.load(ROD)
    a, b, _ = rod_box(build_models(state, ROD)[1])
    w = b / 2
    _, G, _ = convex_from_rod(state, ShapeFitConfig(pieces=3, walls=4, start="u",
                                                    bar_width=0.5))
    bottom = -a + w / 2
    assert _inside(G, -a + w / 4, bottom) and _inside(G, a - w / 4, bottom)  # the legs
    assert not _inside(G, -a + 1.5 * w, bottom)  # inside a leg as wide as the rod's radius
    assert _inside(G, -0.9 * a, a - w / 2) and _inside(G, 0.9 * a, a - w / 2)  # as long
    assert not _inside(G, 0.0, a - w / 2 - w)
    for bad in (0.0, 2.5):
        with pytest.raises(ValueError, match=r"bar_width .* invalid; valid: in \(0, 2\]"):
            ShapeFitConfig(pieces=3, walls=4, start="u", bar_width=bad)
    with pytest.raises(ValueError, match="sizes bars; valid: with a start of bar, tee, ell, u"):
        ShapeFitConfig(start="box", bar_width=0.5)


def test_the_width_search_steps_towards_the_nearer_width_while_it_is_at_an_end():
    """From the width the bars start at (1, distance 2): one step thinner, then on in the
    direction that was nearer, at most `steps` widths; none with no time left."""
    seen = []

    def towards(best):
        def measure(v):
            seen.append(v)
            return 2 + abs(np.log(v / best)) - abs(np.log(1 / best))
        return measure

    d = family.width_search(towards(0.45), 2)
    assert list(d) == pytest.approx([0.49, 0.7, 1.0]) and min(d, key=d.get) == 0.49
    d = family.width_search(towards(1.9), 3)  # wider, up to MAX_BAR_WIDTH (2) and no further
    assert list(d) == pytest.approx([0.7, 1.0, 1 / 0.7], abs=1e-4)
    d = family.width_search(towards(0.8), 5)  # bracketed by 0.49 and 1: no further step
    assert list(d) == pytest.approx([0.49, 0.7, 1.0])
    seen.clear()
    assert family.width_search(towards(0.5), 2, more=lambda: False) == {1.0: 2.0} and not seen
    assert family.width_search(towards(0.5), 0) == {1.0: 2.0}


def test_pieces_joined_in_a_chain_need_each_centre_in_the_next_piece():
    """Per-piece joints: accepted where each lies in its own box and the next one's (a U's
    corners), refused, naming what is valid, where a piece would not hold the previous
    centre."""
    state = checkpoint.load(ROD)
    _, G, _ = convex_from_rod(state, ShapeFitConfig(pieces=3, walls=4, start="u"))
    legs = [(-0.5, -0.3, -0.5, 0.5, 0.1), (-0.5, 0.5, 0.3, 0.5, 0.1), (0.3, 0.5, -0.5, 0.5, 0.1)]
    G.init_boxes(legs, [(-0.4, 0.4), (0.4, 0.4), (0.4, 0.4)])
    assert _inside(G, -0.4, -0.45) and _inside(G, 0.4, -0.45) and not _inside(G, 0.0, -0.2)
    with pytest.raises(ValueError, match="per box a point inside it and the next box"):
        G.init_boxes(legs, [(-0.4, -0.4), (0.0, 0.4), (0.4, -0.4)])
    with pytest.raises(ValueError, match="one \\(x, y\\) or 3 of them"):
        G.init_boxes(legs, [(0.4, 0.4)] * 2)


def test_a_scale_at_which_the_bin_cannot_hold_n_parts_is_no_candidate_s_end(tmp):
    """A candidate whose template, at a scale of the grid, is too large for the user's bin to
    hold n of it (the simulator's PileError) gets no distance there, not a failed loop: it is
    kept at a scale that piles, or, where none does, skipped with the simulator's reason."""
    state = checkpoint.load(ROD)
    data = BagFrames(BAG, 4)
    x = data.frames(PreprocessConfig.from_dict(state["preprocess_config"]))[0]["x"]
    cfg = family.FamilyConfig(families=("rod", "taper"), piles=6, scales=(1.0, 4.0), extend=0,
                              widths=0, workers=2)
    choice = family.choose(ROD, x, data, None, pile_view(data, state), tmp / "a", cfg,
                           progress=False)
    for row in choice["rows"]:
        assert row["scale"] == 1.0 and row["pile_w1_by_scale"]["4"] is None, row
        assert row["edge_w1_by_scale"]["4"] is None and row["pile_w1"] > 0
    too_large = family.FamilyConfig(families=("rod",), piles=6, scales=(4.0,), extend=0,
                                    workers=2)
    with pytest.raises(ValueError, match=r"no template family could be made .* rod: not "
                                         r"piled: at no scale .* at x4: .*fell out of the"):
        family.choose(ROD, x, data, None, pile_view(data, state), tmp / "b", too_large,
                      progress=False)
