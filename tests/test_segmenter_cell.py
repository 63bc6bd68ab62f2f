"""What a robot cell needs from the segmenter, over real DDS between real processes: its
lifecycle driven through ~/change_state, ~/enable and ~/segment_next, picks in the robot's frame
with their confidence, and the bin check against the model card (a wrong part, an empty bin)."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import BAGS, set_params

from inseggan_ros.io import bags
from test_bin_replay import stop
from test_segmenter import start_segmenter

pytestmark = pytest.mark.serial  # nodes over real DDS: run alone (setup.cfg)

HERE = Path(__file__).parent


def frames_file(tmp, name: str, depth: list, K) -> Path:
    path = tmp / f"{name}.npz"
    np.savez(path, depth=np.stack(depth).astype(np.uint16), K=np.asarray(K, float))
    return path


def bag_frames(tmp, bag: str, count: int = 4) -> Path:
    frames = bags.read_all(BAGS / bag)[:count]
    return frames_file(tmp, bag, [f.depth for f in frames], frames[0].camera_info.K)


def drive(tmp, ns: str, steps: list, timeout: float = 240) -> dict:
    """Run cell_probe.py with `steps` against the segmenter in `ns` -> what it wrote."""
    (tmp / "steps.json").write_text(json.dumps(steps))
    out = tmp / "cell.json"
    proc = subprocess.Popen([sys.executable, str(HERE / "cell_probe.py"), str(out), ns,
                             str(tmp / "steps.json")], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "probe ready"
    rc = proc.wait(timeout=timeout)
    got = json.loads(out.read_text())
    assert rc == 0, json.dumps(got["steps"], indent=1)[-3000:]
    return got


def results(got) -> list:
    return [s["result"] for s in got["steps"]]


def test_lifecycle_is_driven_from_another_process(tmp):
    """With autostart false: unconfigured with no model; configure loads it (inactive: no work);
    activate subscribes; deactivate stops the work; cleanup unloads; configure + activate
    again serve as before."""
    frames = bag_frames(tmp, "cylinder_sim")
    seg = start_segmenter("/cell_lc", "autostart:=false", "diagnostics_period:=0.2")
    try:
        got = drive(tmp, "/cell_lc", [
            ["state"], ["segment_next"], ["publish", str(frames), 5.0], ["idle", 2.0],
            ["transition", "configure"], ["state"], ["segment_next"], ["idle", 2.0],
            ["transition", "activate"], ["state"], ["labels", 3, 60.0],
            ["transition", "deactivate"], ["state"], ["idle", 1.0], ["idle", 2.0],
            ["transition", "cleanup"], ["state"], ["idle", 0.5],
            ["transition", "configure"], ["transition", "activate"], ["labels", 2, 60.0],
        ])
    finally:
        assert stop(seg) == 0
    err = seg.stderr.read()
    assert "Traceback" not in err, err
    r, steps = results(got), got["steps"]
    assert r[0] == "unconfigured"
    assert r[1][0] is False and r[1][1].startswith("no model loaded (lifecycle state "
                                                   "unconfigured)"), r[1]
    assert steps[3]["labels"] == [], "no labels before configure"
    assert r[4] is True and r[5] == "inactive"
    assert r[6] == [False, "not subscribed (lifecycle state inactive): activate the node first"]
    assert steps[7]["labels"] == [], "no labels while inactive"
    assert r[8] is True and r[9] == "active" and r[10] is True
    assert r[11] is True and r[12] == "inactive"
    assert steps[14]["labels"] == [], "no labels after deactivate"
    assert r[15] is True and r[16] == "unconfigured"
    assert r[18] is True and r[19] is True and r[20] is True
    assert err.count("]: model ") == 2, err  # loaded at each configure


def test_a_failed_configure_leaves_the_node_unconfigured_and_says_why(tmp):
    seg = start_segmenter("/cell_badcfg", "autostart:=false", "model_path:=no_such_model",
                          "diagnostics_period:=0.2")
    try:
        got = drive(tmp, "/cell_badcfg", [["transition", "configure"], ["state"],
                                          ["idle", 1.0]])
        assert seg.poll() is None, "the node keeps running"
    finally:
        assert stop(seg) == 0
    err = seg.stderr.read()
    assert results(got)[:2] == [False, "unconfigured"]
    assert "configure failed: model_path 'no_such_model': no such model file" in err, err
    d = got["diagnostics"]["segmenter: instance segmentation"]
    assert d["_level"] == 2 and d["_message"].startswith("configure failed: model_path"), d


def test_enable_pauses_and_segment_next_segments_one_frame_while_paused(tmp):
    """Paused, no frame is segmented; ~/segment_next segments the next frame that arrives after
    the call (one label image, stamped after the call), publishes its picks and answers with
    the counts; streaming resumes with ~/enable true."""
    frames = bag_frames(tmp, "cylinder_sim")
    seg = start_segmenter("/cell_en", "diagnostics_period:=0.2")
    try:
        got = drive(tmp, "/cell_en", [
            ["publish", str(frames), 5.0], ["labels", 2, 60.0],
            ["enable", False], ["idle", 1.0], ["idle", 2.0],
            ["segment_next"], ["idle", 1.0], ["idle", 1.0],
            ["enable", True], ["labels", 2, 30.0],
        ])
    finally:
        assert stop(seg) == 0
    err = seg.stderr.read()
    assert "Traceback" not in err, err
    r, steps = results(got), got["steps"]
    assert r[2][0] is True and r[2][1].startswith("paused")
    assert steps[4]["labels"] == [], "paused: nothing segmented"
    ok, message = r[5]
    assert ok, message
    triggered = steps[5]["labels"] + steps[6]["labels"]
    assert len(triggered) == 1, triggered
    assert triggered[0] > steps[5]["t0_ns"], "a frame that arrived after the call"
    assert steps[7]["labels"] == [], "still paused"
    n_inst = dict((s, n) for s, n in got["labels"])[triggered[0]]
    n_picks = [n for s, _, n in got["picks"] if s == triggered[0]]
    assert message == f"instances {n_inst}, picks {n_picks[0]}", (message, n_inst, n_picks)
    assert n_inst >= 3 and n_picks[0] >= 1
    assert r[8][0] is True and r[9] is True, "streaming again"


def _empty_bin_frames(count: int = 3):
    """cylinder_sim frames with every part replaced by the bin floor: walls, an empty floor."""
    out = []
    for f in bags.read_all(BAGS / "cylinder_sim")[:count]:
        depth = f.depth.copy()
        x0, y0, x1, y1 = 58, 57, 167, 166  # the bin floor
        floor = depth[y0:y1, x0:x1][f.labels[y0:y1, x0:x1] == 0]
        depth[f.labels > 0] = np.median(floor)
        out.append(depth)
    return out, f.camera_info.K


def test_an_empty_bin_gives_no_instance_and_the_diagnostics_say_so(tmp):
    """A full bin first (the node finds the bin region in its first frames), then the same bin
    emptied. And the default model's card has no label-free measures: 'no reference'."""
    full = bag_frames(tmp, "cylinder_sim")
    depth, K = _empty_bin_frames()
    empty = frames_file(tmp, "empty", depth, K)
    seg = start_segmenter("/cell_empty", "diagnostics_period:=0.2")
    try:
        got = drive(tmp, "/cell_empty", [
            ["publish", str(full), 5.0], ["labels", 6, 60.0], ["publish", str(empty), 5.0],
            ["idle", 1.0], ["labels", 4, 30.0], ["segment_next"], ["idle", 1.0]])
    finally:
        assert stop(seg) == 0
    instances = dict((s, n) for s, n in got["labels"])
    steps = got["steps"]
    assert all(instances[s] >= 3 for s in steps[1]["labels"])
    emptied = steps[4]["labels"] + steps[5]["labels"] + steps[6]["labels"]
    assert len(emptied) >= 5 and all(instances[s] == 0 for s in emptied), got["labels"]
    assert steps[5]["result"] == [True, "instances 0, picks 0; the bin is empty"]
    d = got["diagnostics"]["segmenter: bin"]
    assert d["_level"] == 1 and d["_message"].startswith("bin empty"), d
    assert d["reference"].startswith("no reference: the model card has no label-free"), d


def test_the_bin_check_warns_on_another_part_and_not_on_the_models_own(tmp):
    """The cylinder model of the tilted RealSense camera shown the hex nuts of the same camera,
    then its own sample bag, in one node: the medians of the frames' label-free measures
    against its card's (models/cylinder_tilted/card.json `measures`) go WARN, then OK again;
    each change is logged once, at its own severity, and the node serves on."""
    other = bag_frames(tmp, "hex_nut_tilted_realsense", 8)
    own = bag_frames(tmp, "cylinder_tilted_realsense", 8)
    seg = start_segmenter("/cell_bin", "model_path:=cylinder_tilted", "diagnostics_period:=0.2",
                          "bin_check_window:=6")
    try:
        got = drive(tmp, "/cell_bin", [
            ["publish", str(other), 4.0], ["labels", 8, 120.0], ["idle", 1.0],
            ["diagnostics", "segmenter: bin"],
            ["publish", str(own), 4.0], ["labels", 8, 120.0], ["idle", 1.0],
            ["diagnostics", "segmenter: bin"]])
    finally:
        rc = stop(seg)
    err = seg.stderr.read()
    assert rc == 0 and "Traceback" not in err, err
    wrong, right = got["steps"][3]["result"], got["steps"][7]["result"]
    print("another part:", wrong, "\nits own:", right)
    assert wrong["reference"] == "cylinder_tilted/card.json measures"
    assert wrong["_level"] == 1, wrong
    assert wrong["_message"].startswith("the bin does not look like the model's part (spill "), \
        wrong
    assert "another part in the bin, the camera moved" in wrong["_message"]
    assert float(wrong["median_spill"]) > float(wrong["card_spill"]) + 0.08
    assert right["_level"] == 0 and right["_message"] == "the bin looks like the model's part", \
        right
    warned = err.index("bin check: the bin does not look like the model's part")
    assert "bin check: the bin looks like the model's part" in err[warned:], err


def test_picks_in_the_robot_frame_match_the_camera_picks_moved_independently(tmp):
    """A fixed camera-to-robot transform: each pick (position and orientation) is the
    camera-frame pick (picks.py on the depth and labels that went over DDS) moved by the
    transform as scipy computes it, within 1 mm and 1 degree; header frame_id the robot's;
    the confidences come beside, one per pick, stamped alike. Bad transforms are refused."""
    from scipy.spatial.transform import Rotation

    from inseggan_ros.core.image_codec import depth_to_metres
    from inseggan_ros.runtime.picks import compute_picks
    from inseggan_ros.sim.scene import SceneConfig
    from test_picks import _run

    t = np.array([0.41, -0.12, 0.83])
    rot = Rotation.from_euler("xyz", [178.0, -3.0, 91.0], degrees=True)
    q = rot.as_quat()
    args = ("-p", "roi:=[58,57,167,166]", "-p", "target_frame:=robot_base",
            "-p", f"target_translation:={t.tolist()}", "-p", f"target_rotation:={q.tolist()}")
    got, err = _run(tmp, "/cell_tf", 4, seg_args=args)
    K = SceneConfig().camera.K
    for i in range(len(got["stamp"])):
        assert got["picks_frame_id"][i] == "robot_base"
        assert {m[3] for m in got["markers"][i]} == {"robot_base"}
        depth = depth_to_metres(got["depth"][i], "16UC1")
        want = compute_picks(depth, got["labels"][i], K)
        poses = got["poses"][i]
        assert len(poses) == len(want) >= 1
        for p, w in zip(poses, want):
            np.testing.assert_allclose(p[:3], rot.apply(w.position) + t, atol=1e-3)
            truth = rot * Rotation.from_quat(w.orientation())
            angle = np.degrees((truth.inv() * Rotation.from_quat(p[3:])).magnitude())
            assert angle < 1.0, angle
        conf = got["confidence"][i]  # keyed by the stamp its label names
        assert conf is not None and len(conf["values"]) == len(poses)
        assert all(0.0 <= c <= 1.0 for c in conf["values"]) and max(conf["values"]) > 0.3
        s = int(got["stamp"][i])
        assert conf["label"] == f"{s // 10**9}.{s % 10**9:09d}"


def test_target_transform_parameters_are_checked():
    seg = start_segmenter("/cell_tfparams")
    try:
        got = set_params("/cell_tfparams/segmenter",
                         ("target_rotation", "[0.0, 0.0, 0.0, 2.0]"),
                         ("target_translation", "[1.0, 2.0]"),
                         ("target_translation", "[0.1, 0.0, 0.0]"),
                         ("target_frame", "'robot_base'"),
                         ("target_translation", "[0.1, 0.0, 0.0]"),
                         ("target_rotation", "[0.0, 0.0, 0.70711, 0.70711]"),
                         ("target_rotation", "[0.0, 0.0, 0.0, 1.0005]"))
    finally:
        assert stop(seg) == 0
    assert got[0].startswith("rejected: target_rotation [0.0, 0.0, 0.0, 2.0] invalid: its norm "
                             "is 2.000000; valid: a unit quaternion"), got[0]
    assert got[1].startswith("rejected: target_translation [1.0, 2.0] invalid; valid: [x, y, z]")
    assert got[2].startswith("rejected: target_translation and target_rotation need "
                             "target_frame"), got[2]
    assert got[3:] == ["ok", "ok", "ok", "ok"], got


def test_compressed_depth_input(tmp):
    """input_transport compressedDepth: frames sent as image_transport's compressedDepth (a PNG
    made here, by the probe, not by the package's encoder) on <depth topic>/compressedDepth are
    segmented, on demand too."""
    frames = bag_frames(tmp, "cylinder_sim")
    seg = start_segmenter("/cell_cd", "input_transport:=compressedDepth")
    try:
        got = drive(tmp, "/cell_cd", [["publish", str(frames), 5.0, "compressedDepth"],
                                      ["labels", 3, 60.0], ["segment_next"]])
    finally:
        assert stop(seg) == 0
    assert all(n >= 3 for _, n in got["labels"]), got["labels"]
    assert results(got)[2][0] is True and results(got)[2][1].startswith("instances ")
