"""Bins of fewer parts than the model's n: no instance where there is no part, one per part
where there are fewer than n (the rules: a centre-vote peak needs votes, a missed part is split
off only where the centre votes put a centre, a wall's top is no part), on shipped models and
simulated bins of fresh seeds."""
import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from conftest import REPO
from inseggan_ros.core.settings import apply, read_params_file
from inseggan_ros.learning.centres import decode, targets
from inseggan_ros.runtime.centres import MIN_PIXELS
from inseggan_ros.runtime.segment import Segmenter
from inseggan_ros.runtime.superpixels import (
    MIN_INSTANCE, WALL_BAND, drop_small, drop_walls, small_frame, split_frame, wall_frame)
from tools.bench_counts import frame_seed, scene_source, scenes, visible_parts

SEED = 31  # the bins below: seeds never used by the cards, the loop or the benchmark


def _perfect(labels: torch.Tensor, n: int) -> torch.Tensor:
    heat, offsets = targets(labels, n)
    return torch.cat([torch.logit(heat.clamp(1e-4, 1 - 1e-4))[:, None], offsets], 1)


def test_a_peak_needs_votes_and_no_peak_means_no_instance():
    lab = torch.zeros(1, 64, 64, dtype=torch.uint8)
    lab[0, 10:30, 10:40] = 1  # a part of 600 pixels
    lab[0, 50:54, 50:60] = 2  # and one of 40
    pred = _perfect(lab, 5)
    fg = lab > 0

    def count(labels):
        return len(labels.unique()) - 1

    assert count(decode(pred, fg, 5)) == count(decode(pred, fg, 5, MIN_PIXELS)) == 2
    one = decode(pred, fg, 5, 100)  # the small part's pixels vote again, for the large one
    assert count(one) == 1 and (one[fg] == one[0, 20, 20]).all()
    # three stray pixels: the net is taught no centre for so few, and the highest point of
    # an empty heatmap is no part (without votes it was: the highest peak always counted)
    stray = torch.zeros(1, 64, 64, dtype=torch.uint8)
    stray[0, 30, 30:33] = 1
    p = _perfect(stray, 5)
    assert count(decode(p, stray > 0, 5)) == 1
    assert count(decode(p, stray > 0, 5, MIN_PIXELS)) == 0
    # votes per frame: more than the whole frame holds leaves no instance
    both = decode(torch.cat([pred, pred]), torch.cat([fg, fg]), 5, torch.tensor([700.0, 100.0]))
    assert not both[0].any() and torch.equal(both[1], one[0])


def _three_blocks():
    h = np.zeros((64, 64))
    h[10:50, 4:24], h[10:50, 24:44], h[10:50, 44:60] = 0.3, 0.6, 0.9
    truth = np.zeros((64, 64), np.uint8)
    truth[10:50, 4:24], truth[10:50, 24:44], truth[10:50, 44:60] = 1, 2, 3
    return h, truth


def test_a_missed_part_is_split_off_only_where_a_centre_may_be():
    h, truth = _three_blocks()
    merged = np.where(truth == 3, 2, truth).astype(np.uint8)
    nowhere = np.zeros((64, 64), bool)
    there = nowhere.copy()
    there[30, 52] = True  # a centre on the third block
    elsewhere = nowhere.copy()
    elsewhere[30, 30] = True  # a centre on the second block only
    np.testing.assert_array_equal(split_frame(merged, h, 3, 800, founding=there)[0], truth)
    for f in (nowhere, elsewhere):
        out, cut = split_frame(merged, h, 3, 800, founding=f)
        np.testing.assert_array_equal(out, merged)
        assert not cut.any()
    # with every id used, a larger piece still replaces the smallest label, centre or not
    stray = merged.copy()
    stray[20:24, 8:12] = 3
    np.testing.assert_array_equal(split_frame(stray, h, 3, 800, founding=nowhere)[0], truth)


def test_a_wall_top_along_the_edge_loses_its_label_a_part_at_the_wall_keeps_it():
    lab = np.zeros((64, 64), np.uint8)
    lab[:, 60:64] = 1  # a band 4 pixels wide along the right edge: a wall's top
    lab[20:40, 44:60] = 2  # a part lying against it, 16 pixels wide
    lab[2:5, 10:40] = 3  # a thin part near the top edge (3 pixels, inside the band) ...
    lab[5:12, 10:40] = 3  # ... that reaches into the bin: 10 pixels thick
    lab[30:33, 20:30] = 4  # a thin sliver inside the bin, away from the edge
    out = wall_frame(lab)
    assert set(np.unique(out)) == {0, 2, 3, 4}
    np.testing.assert_array_equal(out[lab != 1], lab[lab != 1])
    wide = np.zeros((64, 64), np.uint8)
    wide[:, 64 - WALL_BAND - 2:] = 1  # wider than the band: a quarter of it lies inside
    np.testing.assert_array_equal(wall_frame(wide), wide)
    knob = lab.copy()
    knob[30:37, 53:60] = 1  # the band's label reaches in: thicker than a wall's top there
    np.testing.assert_array_equal(wall_frame(knob), np.where(knob == 1, 1, out))
    batch = torch.from_numpy(np.stack([lab, wide]))
    torch.testing.assert_close(drop_walls(batch), torch.from_numpy(np.stack([out, wide])))


def test_an_instance_too_small_to_be_in_view_joins_its_neighbour_or_the_background():
    lab = np.zeros((64, 64), np.uint8)
    lab[10:30, 10:30] = 1
    lab[10:30, 30] = 2  # a rim one pixel wide along part 1: 20 pixels, kept
    lab[30, 10:17] = 3  # a rim of 7 pixels under part 1: too small
    lab[50:52, 50:53] = 4  # 6 pixels alone
    out = small_frame(lab)
    assert MIN_INSTANCE == 8 and set(np.unique(out)) == {0, 1, 2}
    assert (out[30, 10:17] == 1).all() and not out[50:52, 50:53].any()
    np.testing.assert_array_equal(out[lab <= 2], lab[lab <= 2])
    alone = np.zeros((64, 64), np.uint8)
    alone[5, 5:9] = 2
    assert not small_frame(alone).any()
    torch.testing.assert_close(drop_small(torch.from_numpy(np.stack([lab, alone]))),
                               torch.from_numpy(np.stack([out, alone * 0])))


@pytest.fixture(scope="module")
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.mark.parametrize("name", ["cylinder", "wooden_block", "hex_nut_tilted"])
def test_bins_of_no_part_and_one_part_give_no_and_one_instance(name, one_thread):
    """The model's own part, camera and noise (`tools.bench_counts.scene_source`)."""
    seg = Segmenter.from_checkpoint(REPO / "models" / name / "model.pt", device="cpu")
    source = scene_source(REPO / "models" / name)
    for parts in (0, 1):
        seeds = [frame_seed(SEED, parts, i) for i in range(4)]
        for seed, depth, labels in scenes(source, parts, seeds, None):
            out = seg(depth, reconstruction=False)
            got = len(np.unique(out.labels)) - 1
            assert visible_parts(labels, out.roi) == parts
            assert got == parts, (name, parts, seed, got)


QUALITY = read_params_file(REPO / "config" / "quality.yaml")


@pytest.mark.parametrize("name", ["cylinder", "cylinder_tilted"])
def test_an_empty_bin_gives_no_instance_on_every_path(name, one_thread):
    """The model's own settings (realtime.yaml's), quality.yaml's, each with centre votes on
    and off. The cylinder's bin region is fixed, so an empty bin has no foreground; the tilted
    camera's region is found in the frame and holds the top of a wall."""
    seg = Segmenter.from_checkpoint(REPO / "models" / name / "model.pt", device="cpu")
    [(_, depth, labels)] = scenes(scene_source(REPO / "models" / name), 0,
                                  [frame_seed(SEED, 0, 9)], None)
    assert not labels.any()
    paths = {"realtime": seg.inference, "quality": apply(seg.inference, QUALITY)}
    paths.update({f"{k}, centre votes off": replace(v, centre_votes="off")
                  for k, v in list(paths.items())})
    assert paths["realtime"].centre_votes == "on"
    for path, cfg in paths.items():
        out = seg(depth, settings=cfg)
        assert not out.labels.any() and not out.labels64.any(), (name, path)
        assert not out.masks.any() and (out.scores == 0).all(), (name, path)
    if name == "cylinder_tilted":  # the wall's top is foreground: the rule, not an empty input
        assert (seg(depth).x64 > -1).sum() > 20


def test_the_counts_benchmark_prints_its_table_and_writes_json(tmp, capsys, one_thread):
    from tools.bench_counts import main

    out = tmp / "counts.json"
    assert main(["--models", "cylinder", "--counts", "0", "N", "--frames", "1", "--seed",
                 str(SEED), "--json", str(out)]) == 0
    table = capsys.readouterr().out
    assert "count right" in table and table.count("cylinder ") == 2
    rows = json.loads(out.read_text())["rows"]
    assert [(r["parts"], r["frames"]) for r in rows] == [(0, 1), (5, 1)]
    assert rows[0]["miou"] is None and rows[0]["counts"] == {"0": 1}
    assert 0 < rows[1]["miou"] <= 1
    # a model folder beside the names, its bins those of another model's card (--bins-of):
    # the shipped cylinder by its folder on the cylinder's own bins gives the same figures
    assert main(["--models", str(REPO / "models" / "cylinder"), "--bins-of", "cylinder",
                 "--counts", "N", "--frames", "1", "--seed", str(SEED), "--json", str(out)]) == 0
    again = json.loads(out.read_text())["rows"]
    assert again[0]["miou"] == rows[1]["miou"] and again[0]["counts"] == rows[1]["counts"]
    for bad in (["--counts", "two"], ["--models", "teapot"], ["--frames", "0"],
                ["--models", "cylinder", "--bins-of", str(tmp)]):
        with pytest.raises(SystemExit) as e:
            main(bad)
        assert e.value.code == 2
    err = capsys.readouterr().err
    assert "valid: an integer, N or N-k" in err and "valid: bolt" in err
    assert f"--bins-of {tmp}: no models/" in err and "or a model folder" in err
