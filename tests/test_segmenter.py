"""The segmenter node as a real process, fed over real DDS by bin_replay or by a probe process."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import (BAGS, REPO, checkpoint_without_settings, get_params,
                      installed_executable, set_params)

from inseggan_ros.io import bags
from inseggan_ros.core import image_codec
from inseggan_ros.evaluation.baselines import kmeans
from inseggan_ros.core.metrics import mean_miou, miou_batch
from inseggan_ros.ros.segmenter import DEFAULT_MODEL
from test_bin_replay import start_replay, stop

pytestmark = pytest.mark.serial  # nodes over real DDS: run alone (setup.cfg)

HERE = Path(__file__).parent


def start_segmenter(ns, *params, extra=()):
    args = [str(installed_executable("segmenter")), "--ros-args", "-r", f"__ns:={ns}", *extra]
    for p in params:
        args += ["-p", p]
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def probe(tmp, ns, count, timeout, frames=None):
    out = tmp / "probe.npz"
    args = [sys.executable, str(HERE / "seg_probe.py"), str(out), ns, str(count), str(timeout)]
    if frames is not None:
        np.savez(tmp / "frames.npz", **frames)
        args.append(str(tmp / "frames.npz"))
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "probe ready"
    return proc, out


def finish(proc, out, timeout):
    rc = proc.wait(timeout=timeout + 30)
    got = dict(np.load(out, allow_pickle=True))
    got["diagnostics"] = got["diagnostics"].item()
    return rc, got


def shipped_params_file(profile: str) -> Path:
    """config/<profile>.yaml as installed with the package."""
    return (installed_executable("segmenter").parents[2] / "share" / "inseggan_ros" / "config"
            / f"{profile}.yaml")


@pytest.fixture(scope="module")
def replayed(tmp_path_factory):
    """bin_replay (shipped bag with ground truth) -> segmenter -> probe, run once per module
    with the model's default settings (config/realtime.yaml, the one that meets the latency
    target: make bench-node). config/quality.yaml's settings give the same messages at about
    a second a frame: test_shipped_parameter_files_set_the_segmenter checks that the file sets
    the node, test_models the segmentation they give on the same bag."""
    return replay_to_segmenter(tmp_path_factory.mktemp("e2e"), "/seg_e2e", "cylinder_sim", 4.0)


def replay_to_segmenter(tmp, ns, bag, rate, *params):
    """bin_replay (a shipped bag) -> segmenter (`params`) -> probe, until every frame of the bag
    has been labelled once (the bag loops until all have come round: the same frames a model
    card's full-resolution scores were measured on) -> what the probe got."""
    seg = start_segmenter(ns, *params)
    proc, out = probe(tmp, ns, len(bags.read_all(BAGS / bag)), 150)
    # looped with the bag's own stamps: frames lost while DDS discovery settles come round again
    replay = start_replay(ns, "source:=bag", f"bag_path:={bag}", f"rate:={rate}",
                          "restamp:=false", "loop:=true")
    try:
        rc, got = finish(proc, out, 150)
    finally:
        stop(replay)
        seg_rc = stop(seg)
    err = seg.stderr.read()
    assert seg_rc == 0 and "Traceback" not in err, err
    assert rc == 0, f"got {len(got['stamp'])} label images\n{err}"
    return got


def test_replayed_bag_is_segmented_with_headers_masks_and_diagnostics(replayed):
    got = replayed
    for i in range(len(got["stamp"])):
        lab, g, d = got["labels"][i], got["gt"][i], got["depth"][i]
        assert d is not None and g is not None, "depth and ground truth of every labelled stamp"
        # header passed through unchanged: stamp (the key) and frame_id
        assert got["frame_id"][i] == "camera_depth_optical_frame"
        assert lab.shape == d.shape and lab.dtype == np.uint8
        assert lab.max() <= 5
        m = got["masks"][i]
        assert m.shape == (*d.shape, 5) and set(np.unique(m)) <= {0, 255}
        np.testing.assert_array_equal(m.argmax(-1)[lab > 0] + 1, lab[lab > 0])
        np.testing.assert_array_equal((m > 0).sum(-1), (lab > 0).astype(int))
        assert got["overlay"][i].shape == (*d.shape, 3)
        rec = got["reconstruction"][i]
        assert rec.shape == d.shape and rec.dtype == np.float32
    diag = got["diagnostics"]
    assert int(diag["frames_segmented"]) >= 12 and diag["frames_skipped"] == "0"
    assert float(diag["latency_p50_ms"]) > 0
    ours, _ = _scores(got)
    assert ours > 0.3, "well above labelling everything as one object (about 0.2)"


def _scores(got) -> tuple[float, float]:
    pred, gt, depth = [], [], []
    for i in range(len(got["stamp"])):
        pred.append(got["labels"][i])
        gt.append(got["gt"][i])
        depth.append(image_codec.depth_to_metres(got["depth"][i], str(got["depth_encoding"][i])))
    ours = mean_miou(miou_batch(np.stack(pred), np.stack(gt)))
    # K-Means on (x, y, height) of the same frames, at the same resolution, on the true foreground
    km = mean_miou(miou_batch(np.stack([kmeans(-d, g > 0, 5) for d, g in zip(depth, gt)]),
                              np.stack(gt)))
    print(f"segmenter mIoU {ours:.3f} vs K-Means {km:.3f} on {len(pred)} frames")
    return ours, km


def test_replayed_bag_is_segmented_better_than_kmeans(replayed, request):
    from test_models import CPU_TOLERANCE, below_kmeans

    card = json.loads((REPO / "models" / DEFAULT_MODEL / "card.json").read_text())
    full = card["sample_bag_scores"]["full_resolution"]
    if abs(full["inseggan"] - full["kmeans"]) <= CPU_TOLERANCE:
        pytest.skip(f"the default model's card records a tie with K-Means on this sample bag at "
                    f"full resolution ({full['inseggan']:.3f} vs {full['kmeans']:.3f}), which "
                    "another CPU's rounding may flip")
    if below_kmeans(card, full_resolution=True):
        request.applymarker(pytest.mark.xfail(strict=True, reason=(
            f"the default model's card records InSeGAN {full['inseggan']:.3f} vs K-Means "
            f"{full['kmeans']:.3f} on this sample bag at full resolution")))
    ours, km = _scores(replayed)
    assert ours > km


def test_tilted_realsense_recording_is_segmented_end_to_end(tmp):
    """The real-camera path over DDS: bin_replay replays the tilted RealSense sample bag (848 x
    480, noise, the bin off-centre) to the segmenter running the model made from a recording
    of that camera (models/hex_nut_tilted); its label images score as its card's full-resolution
    figure (measured in-process at export) and above K-Means on the same frames."""
    from test_models import CPU_TOLERANCE

    card = json.loads((REPO / "models" / "hex_nut_tilted" / "card.json").read_text())
    got = replay_to_segmenter(tmp, "/seg_tilted", card["sample_bag"], 2.0,
                              "model_path:=hex_nut_tilted")
    assert all(lab.shape == (480, 848) and lab.max() <= 5 for lab in got["labels"])
    ours, km = _scores(got)
    full = card["sample_bag_scores"]["full_resolution"]
    assert ours == pytest.approx(full["inseggan"], abs=CPU_TOLERANCE)
    assert ours > km


def _frame(arr, encoding, step=None, data=None, width=None, height=None):
    s, payload = image_codec.encode(arr, encoding) if arr is not None else (0, b"")
    return {"encoding": encoding, "width": width if width is not None else arr.shape[1],
            "height": height if height is not None else arr.shape[0],
            "step": step if step is not None else s,
            "data": np.frombuffer(data if data is not None else payload, np.uint8)}


def test_bad_frames_are_counted_and_skipped_and_the_node_keeps_serving(tmp):
    from inseggan_ros.io.bags import read_all
    from conftest import BAGS

    good = [f.depth for f in read_all(BAGS / "cylinder_sim")[:2]]  # 224 x 224 16UC1
    h, w = good[0].shape
    frames = [
        _frame(good[0], "16UC1"),  # establishes the stream's resolution
        _frame(np.zeros((h, w, 3), np.uint8), "rgb8"),  # not a depth encoding
        _frame(good[0], "16UC1", data=image_codec.encode(good[0], "16UC1")[1][:-10]),  # short
        _frame(None, "16UC1", width=0, height=0),  # empty
        _frame(np.zeros((h, w), np.uint16), "16UC1"),  # no valid depth
        _frame(np.full((h, w), np.nan, np.float32), "32FC1"),  # NaN everywhere
        _frame(good[0][:, :200].copy(), "16UC1"),  # another resolution
        _frame(good[1], "16UC1"),  # good again
        _frame(good[0].astype(np.float32) / 1000, "32FC1"),  # good, metres
    ]
    frames = {k: np.array([f[k] for f in frames], dtype=object if k == "data" else None)
              for k in frames[0]}
    ns = "/seg_bad"
    # without refinement: the probe sends a frame every 0.3 s, and at the shipped ~0.5 s a
    # frame one can arrive while the node is still at work on the last, so that keep-last 1
    # drops one and the counts below no longer add up exactly
    seg = start_segmenter(ns, "diagnostics_period:=0.5", "refine_steps:=0")
    proc, out = probe(tmp, ns, 3, 90, frames)
    try:
        rc, got = finish(proc, out, 90)
        assert seg.poll() is None, "the segmenter died on a bad frame"
    finally:
        assert stop(seg) == 0
    err = seg.stderr.read()
    assert "Traceback" not in err, err
    assert rc == 0 and int(got["sent"]) == 9
    assert sorted(got["frame_id"]) == ["probe_0", "probe_7", "probe_8"]  # the good ones only
    d = got["diagnostics"]
    # frame 0 may have been sent more than once (until answered); every other frame once
    assert int(d["frames_received"]) - int(d["frames_segmented"]) == 6
    assert d["frames_skipped"] == "6"
    assert d["frames_skipped_encoding"] == "1"
    assert d["frames_skipped_size"] == "2"  # short data, empty image
    assert d["frames_skipped_depth"] == "2"  # all zero, all NaN
    assert d["frames_skipped_resolution"] == "1"
    assert d["_level"] == "1"  # WARN: frames were skipped
    for text in ("unsupported encoding 'rgb8'", "data has", "empty image", "no valid depth",
                 "200x224 frame, but the stream is 224x224"):
        assert text in err, (text, err)


@pytest.mark.parametrize("params, message", [
    (["model_path:=/nonexistent/model.pt"], "no such model file"),
    (["model_path:=no_such_shipped_model"], "shipped models: bolt, bolt_tilted, cone"),
    (["device:=tpu"], "device='tpu' invalid"),
    (["roi:=[1, 2, 3]"], "roi [1, 2, 3] invalid"),
    (["tau:=3.0"], "parameter tau"),
])
def test_bad_start_up_gives_one_clear_error(params, message):
    seg = start_segmenter("/seg_badstart", *params)
    try:
        rc = seg.wait(timeout=60)
    finally:
        stop(seg)
    err = seg.stderr.read()
    assert rc == 1, err
    assert message in err, err
    assert "Traceback" not in err, err


def test_an_incompatible_model_file_stops_the_node(tmp):
    bad = tmp / "model.pt"
    bad.write_bytes(b"not a checkpoint")
    seg = start_segmenter("/seg_badmodel", f"model_path:={bad}")
    rc = seg.wait(timeout=60)
    err = seg.stderr.read()
    assert rc == 1 and "not a readable checkpoint" in err and "Traceback" not in err, err


def test_parameter_changes_are_validated_at_run_time():
    seg = start_segmenter("/seg_params")
    cases = [  # (name, value, what the node answers: exactly, or how it starts)
        ("tau", "-0.5", "ok"),
        ("tau", "2.0", "rejected"),  # outside -1..1
        ("roi", "[10, 10, 5, 50]", "rejected: roi [10, 10, 5, 50] invalid"),
        ("roi", "[10, 10, 200, 200]", "ok"),
        ("bin_polygon", "[1.0, 2.0]", "rejected: bin_polygon"),
        ("model_path", "'other.pt'", "rejected"),  # read-only
        ("superpixel_thread", "False", "rejected"),  # read-only
        ("smooth_iters", "5", "ok"),
        ("smooth_iters", "-1", "rejected"),  # outside 0..200
        ("superpixel_scale", "50", "ok"),
        ("superpixel_scale", "-1", "rejected"),  # outside 0..10000
        ("split_scale", "800", "ok"),
        ("split_scale", "10001", "rejected"),  # outside 0..10000
        ("rim_band", "0.0", "ok"),
        ("rim_band", "1.5", "rejected"),  # outside 0..1
        ("rim_step", "0.0", "rejected"),  # outside 0.0001..0.1
        ("encoder_precision", "'bfloat16'", "ok"),
        ("encoder_precision", "'float16'",
         "rejected: encoder_precision 'float16' invalid; valid: float32, bfloat16, auto"),
        ("centre_precision", "'auto'", "ok"),
        ("centre_precision", "'half'",
         "rejected: centre_precision 'half' invalid; valid: float32, bfloat16, auto"),
        # the shipped cylinder model labels with its centre votes; off, the z-buffer's labels
        ("centre_votes", "'off'", "ok"),
        # it has no label head
        ("label_head", "'on'", "rejected: label_head on: this model has no label head; "
                               "valid: off"),
        ("label_head", "'maybe'", "rejected: label_head 'maybe' invalid"),
        ("label_head", "'off'", "ok"),
        ("centre_votes", "'yes'", "rejected: centre_votes 'yes' invalid"),
        ("centre_votes", "'on'", "ok"),
    ]
    try:
        got = set_params("/seg_params/segmenter", *((name, value) for name, value, _ in cases))
        assert len(got) == len(cases), got
        for (name, value, want), answer in zip(cases, got):
            exact = want == "ok" or want.endswith(("auto", "valid: off"))
            assert answer == want if exact else answer.startswith(want), (name, value, answer)
    finally:
        assert stop(seg) == 0


@pytest.mark.parametrize("profile", ["realtime", "fastest", "quality", "d435"])
def test_shipped_parameter_files_set_the_segmenter(profile):
    """config/<profile>.yaml, as installed, applies to the segmenter in any namespace (its
    `/**/segmenter` section), and a -p after it still wins."""
    from inseggan_ros.core.settings import read_params_file

    path = shipped_params_file(profile)
    wanted = read_params_file(path)
    ns = f"/seg_{profile}"
    args = [str(installed_executable("segmenter")), "--ros-args", "-r", f"__ns:={ns}",
            "--params-file", str(path), "-p", "tau:=-0.3"]
    seg = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert get_params(f"{ns}/segmenter", *wanted, "tau") == {**wanted, "tau": -0.3}
        got = set_params(f"{ns}/segmenter", ("refine_swaps", "3"), ("refine_keep", "-1"),
                         ("refine_swaps", "-1"))
        assert got[0] == "ok" and got[1].startswith("rejected")  # refine_keep: 0..32
        assert got[2].startswith("rejected")
    finally:
        assert stop(seg) == 0


def test_quality_file_keeps_the_models_own_vote_and_a_training_checkpoint_runs_realtime(
        tmp_path):
    """quality.yaml leaves the vote's and the split's scales to the model: the pin connector
    keeps its own (a vote at 160, not realtime.yaml's 50, and its split off). A training
    checkpoint stores no settings: the node runs it with realtime.yaml's, and the same file
    applies over those (the vote and the split stay on)."""
    from inseggan_ros.core import checkpoint
    from inseggan_ros.core.settings import read_params_file

    quality = read_params_file(shipped_params_file("quality"))
    realtime = read_params_file(shipped_params_file("realtime"))
    bare = checkpoint_without_settings(tmp_path / "bare.pt")
    names = ("superpixel_scale", "split_scale", "refine_steps", "refine_hypotheses")
    stored = checkpoint.load(REPO / "models" / "pin_connector" / "model.pt")["inference"]
    own = {**quality, "superpixel_scale": stored["superpixel_scale"],
           "split_scale": stored["split_scale"]}  # the pin connector's
    scales = ("superpixel_scale", "split_scale")
    assert [own[k] for k in scales] != [realtime[k] for k in scales]
    cases = [(("model_path:=pin_connector",), True, own),
             ((f"model_path:={bare}",), True, {**realtime, **quality}),
             ((f"model_path:={bare}",), False, realtime)]
    for k, (params, with_file, want) in enumerate(cases):
        ns = f"/seg_own_scale_{k}"
        extra = ("--params-file", str(shipped_params_file("quality"))) if with_file else ()
        seg = start_segmenter(ns, *params, extra=extra)
        try:
            got = get_params(f"{ns}/segmenter", *names)
        finally:
            assert stop(seg) == 0
        assert got == {name: want[name] for name in names}, (params, with_file)
