"""Segmentation API and evaluation CLI on a real (tiny) trained model."""
import json

import numpy as np
import pytest
import torch
from conftest import BAGS, refused, run_cli

from inseggan_ros.io import bags
from inseggan_ros.core.checkpoint import CheckpointError
from inseggan_ros.runtime.segment import (
    Segmenter, calibrate_tau, instance_scores, labels_from_renders)
from inseggan_ros.runtime.smoothing import SmoothConfig, smooth_full, smooth_labels


def test_zbuffer_labels_and_scores_by_hand():
    r = torch.full((1, 2, 4, 4), -1.0)
    r[0, 0, :2, :] = 0.5  # instance 1 covers the top half
    r[0, 1, 1:3, :] = 0.8  # instance 2 covers rows 1-2, nearer the camera
    labels = labels_from_renders(r, tau=0.0)[0]
    expected = torch.tensor([[1] * 4, [2] * 4, [2] * 4, [0] * 4], dtype=torch.uint8)
    assert torch.equal(labels, expected)
    fg = torch.ones(1, 4, 4, dtype=torch.bool)
    fg[0, 0, 0] = False
    assert labels_from_renders(r, 0.0, fg)[0, 0, 0] == 0  # only input foreground is labelled
    scores = instance_scores(r, labels[None], 0.0)[0]
    assert scores.tolist() == [0.5, 1.0]  # half of instance 1 is hidden by instance 2


def test_tau_calibration_with_and_without_labels():
    r = torch.full((2, 1, 8, 8), -1.0)
    r[:, 0, 2:6, 2:6] = 0.2
    fg = torch.zeros(2, 8, 8, dtype=torch.bool)
    fg[:, 2:6, 2:6] = True
    tau, scores = calibrate_tau(r, fg)  # the rendered foreground must match the input's
    assert -1 < tau <= 0.2 and scores[tau] == pytest.approx(1.0)
    gt = fg.numpy().astype(np.uint8)
    tau, scores = calibrate_tau(r, fg, gt)
    assert scores[tau] == pytest.approx(1.0)


def _two_blocks(edge_col: int, label_col: int):
    """A 32 x 32 frame: a low block (height -0.2) left of `edge_col` and a high one (0.6) right
    of it, on rows 8..23; labels split at `label_col` instead (a misplaced boundary)."""
    x = torch.full((1, 1, 32, 32), -1.0)
    x[0, 0, 8:24, 6:edge_col] = -0.2
    x[0, 0, 8:24, edge_col:26] = 0.6
    labels = torch.zeros(1, 32, 32, dtype=torch.uint8)
    labels[0, 8:24, 6:label_col] = 1
    labels[0, 8:24, label_col:26] = 2
    return x, labels


def test_label_smoothing_moves_a_boundary_onto_the_height_edge():
    x, labels = _two_blocks(edge_col=16, label_col=19)  # 3 columns of the high block labelled 1
    out = smooth_labels(labels, x, n=3)
    _, want = _two_blocks(edge_col=16, label_col=16)
    torch.testing.assert_close(out, want, rtol=0, atol=0)
    torch.testing.assert_close(smooth_labels(labels, x, 3, SmoothConfig(iters=0)), labels)


def test_label_smoothing_leaves_a_boundary_without_a_height_edge_in_place():
    x, labels = _two_blocks(edge_col=26, label_col=16)  # one flat block, two labels
    out = smooth_labels(labels, x, n=2)
    moved = (out != labels).sum().item()
    assert moved <= 16, moved  # at most a column's worth of pixels changes hands
    assert set(out[labels > 0].unique().tolist()) == {1, 2}
    assert (out[labels == 0] == 0).all()  # background stays background


@pytest.mark.parametrize("side", [128, 400])  # 2 pixels per model pixel; 6, worked 3x coarser
def test_full_resolution_smoothing_puts_blocky_boundaries_on_the_height_edge(side):
    """Two objects meet along a diagonal height edge; labels upsampled from a coarse grid
    follow it in steps. smooth_full moves most of the wrongly labelled pixels to the right
    instance, and changes nothing else."""
    depth = np.full((side, side), 0.5, np.float32)  # floor 0.5 m
    lo, hi = side // 8, side - side // 8
    r, c = np.mgrid[:side, :side]
    inside = (r >= lo) & (r < hi) & (c >= lo) & (c < hi)
    right = c > r + side // 10  # the true edge: a diagonal
    depth[inside & ~right], depth[inside & right] = 0.49, 0.47  # 10 mm and 30 mm high
    cell = side // 16  # a coarse grid: 4 model pixels a cell
    coarse = (c // cell * cell + cell // 2) > (r // cell * cell + cell // 2) + side // 10
    labels = np.where(inside, np.where(coarse, 2, 1), 0).astype(np.uint8)
    truth = np.where(inside, np.where(right, 2, 1), 0)
    out = smooth_full(labels, depth, 0.5, 0.05, 2, SmoothConfig(), 64, (0, 0, side, side))
    before, after = (labels != truth).sum(), (out != truth).sum()
    assert before > 0 and after < 0.5 * before, (before, after)
    assert ((out > 0) == (labels > 0)).all()  # background and foreground unchanged
    np.testing.assert_array_equal(
        smooth_full(labels, depth, 0.5, 0.05, 2, SmoothConfig(iters=0), 64, (0, 0, side, side)),
        labels)


def test_label_smoothing_settings_are_validated():
    for kwargs, message in [({"iters": -1}, "smooth_iters -1 invalid; valid: >= 0"),
                            ({"radius": 0}, "smooth_radius 0 invalid; valid: >= 1"),
                            ({"sigma_height": 0.0}, "smooth_sigma_height 0.0 invalid; valid: > 0")]:
        with pytest.raises(ValueError, match=message):
            SmoothConfig(**kwargs)


def test_segmenter_on_a_full_resolution_frame(tiny_model):
    seg = Segmenter.from_checkpoint(tiny_model / "run" / "best.pt", device="cpu")
    frame = bags.read_all(BAGS / "cylinder_sim", limit=1)[0]
    depth = frame.metres()
    out = seg(depth)
    n = seg.model_cfg.n_instances
    assert out.labels.shape == depth.shape and out.labels.dtype == np.uint8
    assert out.labels.max() <= n
    assert out.masks.shape == (n, *depth.shape)
    np.testing.assert_array_equal(out.masks.any(0), out.labels > 0)
    assert out.reconstruction.shape == depth.shape
    assert out.scores.shape == (n,) and ((0 <= out.scores) & (out.scores <= 1)).all()
    # labels only where the input has objects (above the floor by min_height)
    heights = depth.max() - depth
    assert not (out.labels[heights < 0.001] > 0).any()
    again = seg(depth)
    np.testing.assert_array_equal(again.labels, out.labels)  # deterministic


def test_eval_cli_writes_table_json_and_png(tiny_model, tmp):
    p = run_cli("eval", "--model", tiny_model / "run" / "best.pt", "--data",
                tiny_model / "data", "--frames", "10", "--out", tmp / "ev", "--quiet",
                check=True, timeout=600)
    assert "| kmeans |" in p.stdout and "| inseggan |" in p.stdout
    r = json.loads((tmp / "ev" / "results.json").read_text())
    assert r["frames"] == 10
    assert set(r["methods"]) == {"inseggan", "kmeans", "spectral", "grabcut_kmeans", "felzenszwalb"}
    for m in r["methods"].values():
        assert 0 <= m["miou_all"] <= 1 and m["ms_per_frame"] > 0
    assert (tmp / "ev" / "qualitative.png").read_bytes()[:4] == b"\x89PNG"
    p = run_cli("eval", "--model", tiny_model / "run" / "best.pt", "--data",
                tiny_model / "data", "--frames", "4", "--out", tmp / "ev2", "--quiet",
                "--methods", "kmeans", "--refine-steps", "3", "--refine-hypotheses", "2",
                "--smooth-iters", "5", check=True, timeout=600)
    r = json.loads((tmp / "ev2" / "results.json").read_text())
    assert (r["refine_steps"], r["refine_hypotheses"], r["smooth_iters"]) == (3, 2, 5)
    assert "3 refinement steps" in p.stdout and "5 smoothing iterations" in p.stdout
    p = refused("eval", "--model", tiny_model / "run" / "best.pt", "--data",
                tiny_model / "data", "--frames", "4", "--out", tmp / "ev3",
                "--refine-hypotheses", "0")
    assert p.returncode != 0 and "hypotheses 0 invalid; valid: >= 1" in p.stderr
    p = refused("eval", "--model", tiny_model / "run" / "best.pt", "--data",
                tiny_model / "data", "--frames", "4", "--out", tmp / "ev5", "--smooth-iters", "-1")
    assert p.returncode == 2 and "smooth_iters -1 invalid; valid: >= 0" in p.stderr


def test_bad_model_files_give_one_clear_error(tmp):
    (tmp / "junk.pt").write_bytes(b"not a checkpoint")
    for path, message in [(tmp / "none.pt", "no such model file"),
                          (tmp / "junk.pt", "not a readable checkpoint")]:
        with pytest.raises(CheckpointError, match=message):
            Segmenter.from_checkpoint(path)
        p = refused("eval", "--model", path, "--data", tmp, "--out", tmp / "x")
        assert p.returncode == 2 and message in p.stderr and "Traceback" not in p.stderr
    torch.save({"format": "something-else"}, tmp / "other.pt")
    with pytest.raises(CheckpointError, match="not an inseggan checkpoint"):
        Segmenter.from_checkpoint(tmp / "other.pt")


def test_a_model_is_named_by_shipped_name_folder_or_file(tmp):
    """`--model` and the node's model_path: a shipped name, a model folder (its model.pt, as
    `export` and `loop` write them) or a checkpoint file; a folder without one is no model."""
    from inseggan_ros.core.paths import resolve_model

    shipped = resolve_model("cylinder")
    assert shipped.name == "model.pt" and shipped.parent.name == "cylinder"
    assert resolve_model(str(shipped.parent)) == shipped
    assert resolve_model(str(shipped)) == shipped
    (tmp / "empty").mkdir()
    with pytest.raises(CheckpointError, match="no such model file"):
        Segmenter.from_checkpoint(resolve_model(str(tmp / "empty")))


def test_two_hard_subsets_are_reported():
    """The paper's hard subset (K-Means < 0.6) and the second one (Felzenszwalb < 0.8), each
    averaged over its own frames, and the table shows both."""
    from inseggan_ros.evaluation import evaluate

    results = {"inseggan": {"scores": np.array([0.9, 0.5, 0.7]), "seconds": 0.3},
               "kmeans": {"scores": np.array([0.5, 0.7, 0.55]), "seconds": 0.1},
               "felzenszwalb": {"scores": np.array([0.9, 0.6, 0.85]), "seconds": 0.1}}
    s = evaluate.summarise(results, 3)
    assert (s["hard_frames"], s["hard_felzenszwalb_frames"]) == (2, 1)
    assert s["methods"]["inseggan"]["miou_hard"] == pytest.approx(0.8)  # frames 0 and 2
    assert s["methods"]["inseggan"]["miou_hard_felzenszwalb"] == pytest.approx(0.5)  # frame 1
    table = evaluate.format_table(s)
    assert "Felzenszwalb < 0.8 (1 frames)" in table
    assert "| inseggan | 0.700 | 0.800 | 0.500 |" in table
    del results["felzenszwalb"]
    assert "Felzenszwalb" not in evaluate.format_table(evaluate.summarise(results, 3))
