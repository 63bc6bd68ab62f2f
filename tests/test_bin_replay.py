"""bin_replay as a real process; a separate rclpy process receives its frames over DDS."""
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import BAGS, installed_executable, set_params

from inseggan_ros.io import bags
from inseggan_ros.core.image_codec import metres_to_depth
from inseggan_ros.sim.dataset import scene_seed
from inseggan_ros.sim.scene import BinSimulator, SceneConfig

pytestmark = pytest.mark.serial  # nodes over real DDS: run alone (setup.cfg)

HERE = Path(__file__).parent


def start_replay(ns, *params, env=None):
    args = [str(installed_executable("bin_replay")), "--ros-args", "-r", f"__ns:={ns}"]
    for p in params:
        args += ["-p", p]
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)


def stop(proc):
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


def receive(tmp, ns, count, *params, timeout=60, flags=()):
    """Start a receiver process (with `flags`, receiver.py's), then bin_replay; return the
    frames the receiver got."""
    out = tmp / "received.npz"
    recv = subprocess.Popen([sys.executable, str(HERE / "receiver.py"), str(out), str(count),
                             str(timeout), ns, *flags], stdout=subprocess.PIPE, text=True)
    assert recv.stdout.readline().strip() == "receiver ready"
    replay = start_replay(ns, *params)
    try:
        assert recv.wait(timeout=timeout + 30) == 0, "receiver did not get its frames"
    finally:
        rc = stop(replay)
        log = replay.stderr.read()
    assert rc == 0, log
    assert "Traceback" not in log
    return dict(np.load(out, allow_pickle=True))


def test_simulated_frames_arrive_over_dds(tmp):
    got = receive(tmp, "/sim_test", 4, "object:=cone", "seed:=5", "rate:=10.0")
    cfg = SceneConfig(object="cone")
    with BinSimulator(cfg) as sim:
        expected = [sim.render(scene_seed(5, "test", k)) for k in range(60)]
    matched = []
    for depth, labels, K in zip(got["depth"], got["labels"], got["K"]):
        ks = [k for k, s in enumerate(expected)
              if np.array_equal(depth, metres_to_depth(s.depth, "16UC1"))]
        assert len(ks) == 1, "received frame is not one of the simulated scenes"
        np.testing.assert_array_equal(labels, expected[ks[0]].labels)
        np.testing.assert_allclose(np.asarray(K, float).reshape(3, 3), cfg.camera.K)
        matched.append(ks[0])
    assert matched == sorted(matched) and len(set(matched)) == 4
    assert set(got["encoding"]) == {"16UC1"}
    assert set(got["frame_id"]) == {"camera_depth_optical_frame"}
    stamps = got["stamp"]
    assert (np.diff(stamps) > 0).all() and abs(stamps[-1] / 1e9 - time.time()) < 60


@pytest.mark.parametrize("bag", ["cylinder_sim", "hex_nut_sim_32fc1"])
def test_bag_frames_arrive_with_their_stamps(tmp, bag):
    source = {f.stamp_ns: f for f in bags.read_all(BAGS / bag)}
    got = receive(tmp, f"/bag_{bag}", 5, "source:=bag", f"bag_path:={BAGS / bag}",
                  "loop:=true", "rate:=20.0", "restamp:=false")
    for stamp, depth, labels, enc, fid in zip(got["stamp"], got["depth"], got["labels"],
                                              got["encoding"], got["frame_id"]):
        f = source[int(stamp)]  # the bag's own header stamp came through
        assert enc == f.encoding and fid == f.frame_id
        np.testing.assert_array_equal(depth, f.depth)
        np.testing.assert_array_equal(labels, f.labels)


@pytest.fixture(scope="module")
def compressed_bags(tmp_path_factory):
    """The 16UC1 and the 32FC1 sample bag with their depth as compressedDepth
    (tools/compress_bag.py; level 1: the values are the same at every level)."""
    from tools.compress_bag import compress_bag

    root = tmp_path_factory.mktemp("compressed")
    for name in ("cylinder_sim", "hex_nut_sim_32fc1"):
        compress_bag(BAGS / name, root / name, png_level=1)
    return root


@pytest.mark.parametrize("bag", ["cylinder_sim", "hex_nut_sim_32fc1"])
def test_compressed_bag_replays_as_raw_images(tmp, compressed_bags, bag):
    """A bag recorded as compressedDepth is published as raw Images (the default), decoded:
    16UC1 the millimetres of the raw bag it was made from, 32FC1 what image_transport
    decodes (NaN: no reading)."""
    path = compressed_bags / bag
    source = {f.stamp_ns: f for f in bags.read_all(path)}
    raw = {f.stamp_ns: f for f in bags.read_all(BAGS / bag)}
    got = receive(tmp, f"/cbag_{bag}", 4, "source:=bag", f"bag_path:={path}", "loop:=true",
                  "rate:=20.0", "restamp:=false")
    for stamp, depth, labels, enc in zip(got["stamp"], got["depth"], got["labels"],
                                         got["encoding"]):
        f = source[int(stamp)]
        assert enc == f.encoding
        np.testing.assert_array_equal(depth, f.depth)
        np.testing.assert_array_equal(labels, f.labels)
        if enc == "16UC1":
            np.testing.assert_array_equal(depth, raw[int(stamp)].depth)


def test_compressed_bag_replayed_as_compressed_depth_passes_its_bytes(tmp, compressed_bags):
    """depth_transport:=compressedDepth: a compressedDepth bag's messages go out byte for byte
    (a 32FC1 frame is not quantised twice) on .../image_rect_raw/compressedDepth."""
    path = compressed_bags / "hex_nut_sim_32fc1"
    source = {f.stamp_ns: f for f in bags.read_all(path)}
    got = receive(tmp, "/cbag_pass", 3, "source:=bag", f"bag_path:={path}", "loop:=true",
                  "rate:=20.0", "restamp:=false", "depth_transport:=compressedDepth",
                  flags=["--compressed"])
    for stamp, fmt, data, depth in zip(got["stamp"], got["format"], got["data"], got["depth"]):
        f = source[int(stamp)]
        assert (fmt, data) == f.compressed
        np.testing.assert_array_equal(depth, f.depth)


def test_simulated_frames_as_compressed_depth(tmp):
    """Simulated bins published as compressedDepth (and a raw bag's frames encoded so) decode
    to the same millimetres as the raw Images."""
    got = receive(tmp, "/sim_cd", 3, "object:=cone", "seed:=5", "rate:=10.0",
                  "depth_transport:=compressedDepth", flags=["--compressed"])
    cfg = SceneConfig(object="cone")
    with BinSimulator(cfg) as sim:
        expected = [metres_to_depth(sim.render(scene_seed(5, "test", k)).depth, "16UC1")
                    for k in range(60)]
    for depth, fmt in zip(got["depth"], got["format"]):
        assert fmt == "16UC1; compressedDepth png"
        assert sum(np.array_equal(depth, e) for e in expected) == 1
    source = {f.stamp_ns: f for f in bags.read_all(BAGS / "cylinder_sim")}
    got = receive(tmp, "/raw_cd", 3, "source:=bag", "bag_path:=cylinder_sim", "loop:=true",
                  "rate:=20.0", "restamp:=false", "depth_transport:=compressedDepth",
                  "png_level:=9", flags=["--compressed"])
    for stamp, depth in zip(got["stamp"], got["depth"]):
        np.testing.assert_array_equal(depth, source[int(stamp)].depth)


def test_shipped_bag_by_name_with_recorded_timing_stops_at_the_end(tmp):
    # bag_path may name a shipped bag; without loop the node stops when the bag ends.
    replay = start_replay("/once", "source:=bag", "bag_path:=cylinder_sim", "rate:=0.0")
    try:
        t0 = time.monotonic()
        assert replay.wait(timeout=60) == 0
        elapsed = time.monotonic() - t0
    finally:
        stop(replay)
    log = replay.stderr.read()
    assert "published 16 frames" in log
    assert elapsed > 1.4, "16 frames recorded at 10 Hz take 1.5 s at the recorded timing"


def test_max_frames_ends_the_node(tmp):
    replay = start_replay("/maxf", "max_frames:=3", "rate:=30.0")
    try:
        assert replay.wait(timeout=60) == 0
    finally:
        stop(replay)
    err = replay.stderr.read()
    assert "published 3 frames" in err
    # no Fast DDS profile set (conftest sets none): the node sets the shipped one itself
    assert "Fast DDS profile for large frames: " in err and "fastdds_large_frames.xml" in err


def test_a_profile_the_user_set_is_left_alone(tmp):
    import os

    env = dict(os.environ, FASTRTPS_DEFAULT_PROFILES_FILE=str(tmp / "mine.xml"))
    (tmp / "mine.xml").write_text('<?xml version="1.0" encoding="UTF-8"?>\n<profiles xmlns='
                                  '"http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"/>\n')
    replay = start_replay("/maxf2", "max_frames:=3", "rate:=30.0", env=env)
    try:
        assert replay.wait(timeout=60) == 0
    finally:
        stop(replay)
    err = replay.stderr.read()
    assert "published 3 frames" in err and "Fast DDS profile" not in err, err


@pytest.mark.parametrize("params,message", [
    (["object:=teapot"], "parameter object='teapot' invalid; valid: cylinder, cone"),
    (["instances:=99"], "parameter instances"),
    (["source:=camera"], "parameter source='camera' invalid; valid: sim, bag"),
    (["rate:=0.0"], "rate=0.0 invalid for source 'sim'"),
    (["source:=bag", "bag_path:=/no/such/bag"], "/no/such/bag: no such bag"),
    (["source:=bag", "bag_path:=not_shipped"],
     "shipped bags: bolt_sim, bolt_tilted_realsense, cone_sim"),
    (["source:=bag", "bag_path:=cylinder_sim", "topic:=/nope"],
     "topic '/nope' is not in the bag; topics: /camera/depth/camera_info"),
    (["depth_transport:=theora"],
     "parameter depth_transport='theora' invalid; valid: raw, compressedDepth"),
])
def test_bad_parameters_fail_at_start_with_one_clear_line(params, message):
    replay = start_replay("/bad", *params)
    try:
        rc = replay.wait(timeout=60)
    finally:
        stop(replay)
    err = replay.stderr.read()
    assert rc == 1
    assert message in err, err
    assert "Traceback" not in err
    assert len([line for line in err.splitlines() if "error" in line]) == 1, err


def test_parameter_changes_are_validated_at_run_time():
    replay = start_replay("/params", "rate:=5.0")
    try:
        got = set_params("/params/bin_replay", ("rate", "20.0"), ("rate", "0.0"),
                         ("rate", "5000.0"), ("object", "'bolt'"))
        assert len(got) == 4 and got[0] == "ok", got
        assert got[1].startswith("rejected: parameter rate=0.0 invalid"), got
        assert got[2].startswith("rejected")  # outside 0..1000
        assert got[3].startswith("rejected")  # read-only
        assert replay.poll() is None, "the node keeps running"
    finally:
        assert stop(replay) == 0


def test_large_frames_arrive_with_only_what_ros2_run_sets_up():
    """No profile variable set: each process applies the shipped Fast DDS profile itself (as
    the nodes do, nodes/common.py), and 1280 x 720 frames at 30 Hz all arrive (with Fast DDS's
    built-in transports 144 of 600 did here: tests/delivery_probe.py)."""
    probe = [sys.executable, str(HERE / "delivery_probe.py")]
    sub = subprocess.Popen([*probe, "sub", "1280", "720", "90", "30", "ros2run"],
                           stdout=subprocess.PIPE, text=True)
    try:
        assert sub.stdout.readline().strip() == "ready"
        pub = subprocess.run([*probe, "pub", "1280", "720", "90", "30", "ros2run"],
                             capture_output=True, text=True, timeout=90)
        assert pub.returncode == 0, pub.stderr
        out, _ = sub.communicate(timeout=60)
    finally:
        stop(sub)
    assert int(out.strip().splitlines()[-1]) >= 88, out


def test_a_bad_frame_in_a_bag_is_skipped_and_said(tmp):
    """A compressedDepth frame cut short in the middle of a bag: the node says which and why,
    skips it and replays the rest (looping: every pass)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    frames = bags.read_all(BAGS / "cylinder_sim", limit=4)
    store = bags.typestore()
    with Writer(tmp / "bag", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection(bags.COMPRESSED_DEPTH_TOPIC, bags.COMPRESSED_TYPE,
                                typestore=store)
        for k, f in enumerate(frames):
            fmt, data = bags.image_codec.encode_compressed_depth(f.depth, f.encoding)
            msg = store.types[bags.COMPRESSED_TYPE](
                header=bags._header(store, f.stamp_ns, f.frame_id), format=fmt,
                data=np.frombuffer(data[:-30] if k == 2 else data, np.uint8))
            w.write(conn, f.stamp_ns, store.serialize_cdr(msg, bags.COMPRESSED_TYPE))
    replay = start_replay("/badframe", "source:=bag", f"bag_path:={tmp / 'bag'}", "loop:=true",
                          "rate:=50.0", "max_frames:=6")
    try:
        assert replay.wait(timeout=60) == 0
    finally:
        stop(replay)
    log = replay.stderr.read()
    assert "published 6 frames" in log and "Traceback" not in log, log
    bad = [line for line in log.splitlines() if "cut short before its IEND chunk" in line]
    assert len(bad) == 2, log  # frames 0, 1, 3 a pass: the bad one met twice in 6 frames
    assert f"(the frame stamped {frames[2].stamp_ns}); skipped" in bad[0]
