"""The runtime under the segmenter node's robot-cell features (no ROS): picks computed on the
labelled parts' boxes, moved into a target frame, each instance's fit and the bin check against
a model card, and the networks as traced graphs."""
import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from conftest import BAGS, REPO

from inseggan_ros.io import bags
from inseggan_ros.runtime import bin_check, picks
from inseggan_ros.runtime.picks import PickConfig, compute_picks
from inseggan_ros.runtime.segment import Segmenter

K = np.array([[400.0, 0, 49.5], [0, 400.0, 39.5], [0, 0, 1]])  # a 100 x 80 image


def _boxes_scene():
    depth = np.full((80, 100), 0.5)  # floor
    labels = np.zeros(depth.shape, np.uint8)
    yy, xx = np.mgrid[:80, :100]
    bump = 0.47 - 0.0004 * ((yy - 40) ** 2 + (xx - 30) ** 2) ** 0.5  # a curved part ...
    part = (np.abs(yy - 40) < 15) & (np.abs(xx - 30) < 18)
    depth[part], labels[part] = bump[part], 1
    depth[30:50, 40:75], labels[30:50, 40:75] = 0.45, 2  # ... and one lying across its edge
    depth[8:20, 82:96], labels[8:20, 82:96] = 0.46, 3
    depth[10, 85] = np.nan  # no reading
    return depth, labels


def test_picks_do_not_depend_on_where_the_parts_lie_in_the_frame():
    """The same parts with a margin round them (K's principal point moved with them): the same
    picks to the last bit; and without the areas, the same picks less their area."""
    depth, labels = _boxes_scene()
    got = compute_picks(depth, labels, K, occluded=[0.2, 0.0, 0.5])
    big_d, big_l = np.zeros((200, 300)), np.zeros((200, 300), np.uint8)
    big_d[70:150, 130:230], big_l[70:150, 130:230] = depth, labels
    big_d[5, 5], big_l[190, 290] = 0.4, 0  # a reading without a label far off
    K2 = K.copy()
    K2[0, 2], K2[1, 2] = K[0, 2] + 130, K[1, 2] + 70
    moved = compute_picks(big_d, big_l, K2, occluded=[0.2, 0.0, 0.5])
    plain = compute_picks(depth, labels, K, occluded=[0.2, 0.0, 0.5],
                          cfg=PickConfig(areas=False))
    assert [p.instance for p in got] == [2, 3, 1] and not got[2].free
    for a, b, c in zip(got, moved, plain):
        for field in ("instance", "area", "rise", "free", "top_depth", "pixels", "occluded"):
            assert getattr(a, field) == getattr(b, field), field
        np.testing.assert_array_equal(a.position, b.position)
        np.testing.assert_array_equal(a.normal, b.normal)
        np.testing.assert_array_equal(a.position, c.position)
        np.testing.assert_array_equal(a.normal, c.normal)
        assert np.isnan(c.area) and a.area > 0 and c.rise == a.rise


def test_picks_moved_to_a_target_frame():
    from scipy.spatial.transform import Rotation

    depth, labels = _boxes_scene()
    cam = compute_picks(depth, labels, K)
    t, q = picks.check_transform([0.3, -0.2, 1.1], [0.1, 0.7, -0.2, 0.6775])  # norm 0.9995
    assert abs(np.linalg.norm(q) - 1) < 1e-12
    R = Rotation.from_quat(q)
    for a, b in zip(cam, picks.transform_picks(cam, t, q)):
        np.testing.assert_allclose(b.position, R.apply(a.position) + t, atol=1e-12)
        np.testing.assert_allclose(b.normal, R.apply(a.normal), atol=1e-12)
        pose = Rotation.from_quat(b.orientation())
        assert (pose.inv() * R * Rotation.from_quat(a.orientation())).magnitude() < 1e-9
        np.testing.assert_allclose(pose.as_matrix()[:, 2], b.normal, atol=1e-9)
        assert (b.top_depth, b.rise, b.free) == (a.top_depth, a.rise, a.free)
    for bad, match in (([0, 0, 0, 0], "norm is 0.000000"), ([0, 0, 0.9, 0.5], "norm is 1.029"),
                       ([0, 0, 1], "four finite numbers"), ([np.nan, 0, 0, 1], "four finite")):
        with pytest.raises(ValueError, match=match):
            picks.check_transform([0, 0, 0], bad)
    with pytest.raises(ValueError, match=r"target_translation \[1, 2\] invalid"):
        picks.check_transform([1, 2], [0, 0, 0, 1])


def test_instance_fit_counts_what_the_input_explains():
    x = np.full((8, 8), -1.0, np.float32)
    x[2:6, 2:6] = 0.0  # a part, height 0 (in the model's units)
    fg = x > -1
    renders = np.full((3, 8, 8), -1.0, np.float32)
    renders[0, 2:6, 2:6] = 0.0  # exactly the part
    renders[1, 2:6, 2:8] = 0.0  # half of it over the floor: 16 of 24 pixels explained
    renders[2, 2:6, 2:6] = 0.5  # above what the camera sees
    fit = bin_check.instance_fit(renders, x, fg, tau=-0.5, max_height=0.05)
    np.testing.assert_allclose(fit, [1.0, 16 / 24, 0.0])
    labels = np.zeros((8, 8), np.uint8)
    labels[2:6, 2:4], labels[2:6, 4:6] = 1, 2
    fit = bin_check.instance_fit(renders, x, fg, -0.5, 0.05, labels, scores=[1.0, 0.0, 0.0])
    np.testing.assert_allclose(fit, [1.0, 0.0, 0.0])  # instance 2: a split piece, no render


def test_bin_check_against_a_card(tmp_path):
    card = json.loads((REPO / "models" / "cylinder_tilted" / "card.json").read_text())
    ref, source = bin_check.card_reference(REPO / "models" / "cylinder_tilted" / "model.pt")
    assert source == "cylinder_tilted/card.json measures"
    assert ref == {k: card["measures"][k] for k in bin_check.REFERENCE_KEYS}
    none, why = bin_check.card_reference(REPO / "models" / "cylinder" / "model.pt")
    assert none is None and why.startswith("no reference: the model card has no label-free")
    assert bin_check.card_reference(tmp_path / "best.pt")[1] == \
        "no reference: no card.json beside best.pt"
    check = bin_check.BinCheck(ref, source, 5, window=3)
    assert check.verdict().message == "no frame yet"
    like = {"recon_l1": ref["recon_l1"], "recon_l1_foreground": 0.4, "coverage": ref["coverage"],
            "spill": ref["spill"] + 0.05, "visible": np.array([5])}
    check.add({**like, "coverage": 0.0})
    v = check.verdict()  # one frame: too few to judge on
    assert v.level == "ok" and v.message == "collecting frames (1 of the 3 it judges on)", v
    for _ in range(3):
        check.add(like)
    assert check.verdict().level == "ok"
    for _ in range(2):  # two of three frames spill: the median does
        check.add({**like, "spill": ref["spill"] + 0.2})
    v = check.verdict()
    assert v.level == "warn" and v.message.startswith("the bin does not look like the model's "
                                                      "part (spill ")
    check.add({**like, "recon_l1_foreground": None, "coverage": None, "spill": 1.0})
    v = check.verdict()
    assert v.level == "warn" and v.message.startswith("bin empty")
    assert v.values["frames_in_window"] == "3", "an empty frame is not in the window"
    unchecked = bin_check.BinCheck(None, why, 5)
    unchecked.add(like)
    assert unchecked.verdict().message.startswith("not checked (no reference")


def test_traced_networks_give_the_same_labels():
    """The node's path (the second thread, the networks traced) against one thread, eager:
    identical labels, scores and reconstructions, the encoder in float32 and bfloat16; the
    networks did run as TorchScript graphs."""
    torch.set_num_threads(1)
    eager = Segmenter.from_checkpoint(REPO / "models" / "cylinder" / "model.pt", device="cpu")
    frames = [f.metres() for f in bags.read_frames(BAGS / "cylinder_sim", limit=3)]
    for precision in ("float32", "bfloat16"):
        cfg = replace(eager.inference, encoder_precision=precision)
        node = Segmenter(eager.G, eager.E, eager.model_cfg, eager.prep_cfg, eager.tau,
                         inference=cfg, superpixel_thread=True, centre_net=eager.centre_net,
                         traced=True)
        for f in frames:
            a, b = eager(f, settings=cfg), node(f)
            np.testing.assert_array_equal(a.labels, b.labels)
            np.testing.assert_array_equal(a.scores, b.scores)
            np.testing.assert_array_equal(a.reconstruction, b.reconstruction)
        graphs = [g for k, t in node._cast.items() if "traced" in k for g in t._graphs.values()]
        assert len(graphs) == 2 and all(isinstance(g, torch.jit.ScriptModule) for g in graphs)
