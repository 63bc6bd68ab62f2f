"""rosbag2 bags written and read back for real (MCAP and sqlite3), and every expected error."""
import os
import signal
import subprocess
import time

import numpy as np
import pytest
from conftest import BAGS, installed_executable, run_cli

from inseggan_ros import bags
from inseggan_ros.bags import BagError, BagWriter, CameraInfo, read_all


def _frames(n=3, shape=(30, 40), seed=0):
    rng = np.random.default_rng(seed)
    info = CameraInfo(shape[1], shape[0], np.array([[50.0, 0, 19.5], [0, 50, 14.5], [0, 0, 1]]))
    out = []
    for k in range(n):
        depth = rng.uniform(0.3, 0.6, shape).astype(np.float32)
        depth[0, :3] = 0  # missing readings stay missing
        labels = rng.integers(0, 6, shape).astype(np.uint8)
        out.append((1_000_000_000 + k * 50_000_000, depth, labels, info))
    return out


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
def test_write_read_round_trip(tmp, storage, encoding):
    frames = _frames()
    assert bags.write_frames(tmp / "bag", frames, encoding=encoding, storage=storage) == 3
    assert (tmp / "bag" / "metadata.yaml").is_file()
    topics = bags.list_topics(tmp / "bag")
    assert topics[bags.DEPTH_TOPIC] == ("sensor_msgs/msg/Image", 3)
    assert topics[bags.INFO_TOPIC] == ("sensor_msgs/msg/CameraInfo", 3)
    assert topics[bags.LABELS_TOPIC] == ("sensor_msgs/msg/Image", 3)
    back = read_all(tmp / "bag")
    assert [f.stamp_ns for f in back] == [f[0] for f in frames]
    for f, (stamp, depth, labels, info) in zip(back, frames):
        assert f.encoding == encoding and f.frame_id == bags.DEFAULT_FRAME_ID
        tol = 0.0005 if encoding == "16UC1" else 0
        np.testing.assert_allclose(f.metres(), depth, atol=tol + 1e-7)
        assert (f.metres()[0, :3] == 0).all()
        np.testing.assert_array_equal(f.labels, labels)
        np.testing.assert_array_equal(f.camera_info.K, info.K)
    # a bare storage file (no metadata.yaml) is read too, as rosbags and ros2 bag do
    suffix = ".mcap" if storage == "mcap" else ".db3"
    storage_file = next((tmp / "bag").glob("*" + suffix))
    assert len(read_all(storage_file)) == 3


def _raw_bag(path, images, topic="/robot/depth", msgtype="sensor_msgs/msg/Image"):
    """A bag as a robot would record it: our own messages, any topic, no labels, no info."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    Image = store.types["sensor_msgs/msg/Image"]
    Header = store.types["std_msgs/msg/Header"]
    Time = store.types["builtin_interfaces/msg/Time"]
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection(topic, msgtype, typestore=store)
        for k, (enc, h, wd, step, big, data) in enumerate(images):
            msg = Image(header=Header(stamp=Time(sec=k, nanosec=0), frame_id="cam"), height=h,
                        width=wd, encoding=enc, is_bigendian=big, step=step,
                        data=np.frombuffer(data, np.uint8))
            w.write(conn, k * 10**9, store.serialize_cdr(msg, msgtype))


def test_any_topic_padding_and_endianness(tmp):
    a = np.arange(12, dtype=np.float32).reshape(3, 4) / 10
    padded = np.zeros((3, 24), np.uint8)
    padded[:, :16] = a.view(np.uint8).reshape(3, 16)
    mm = np.array([[500, 501], [0, 65535]], np.uint16)
    _raw_bag(tmp / "robot", [("32FC1", 3, 4, 24, 0, padded.tobytes()),
                             ("16UC1", 2, 2, 4, 1, mm.astype(">u2").tobytes())])
    f0, f1 = read_all(tmp / "robot")  # the only Image topic is found without naming it
    np.testing.assert_array_equal(f0.depth, a)
    np.testing.assert_array_equal(f1.depth, mm)
    assert f0.labels is None and f0.camera_info is None and f0.frame_id == "cam"
    assert len(read_all(tmp / "robot", depth_topic="/robot/depth")) == 2


def test_shipped_sample_bags_are_small_and_readable():
    names = sorted(p.name for p in BAGS.iterdir() if p.is_dir())
    assert len(names) >= 3
    total = sum(f.stat().st_size for f in BAGS.rglob("*") if f.is_file())
    assert total < 20e6
    encodings = set()
    for name in names:
        frames = read_all(BAGS / name)
        assert len(frames) >= 5
        assert all(f.labels is not None and f.camera_info is not None for f in frames)
        encodings.add(frames[0].encoding)
    assert encodings == {"16UC1", "32FC1"}


# ------------------------------------------------------------------------- errors
def _expect(path, match, **kw):
    with pytest.raises(BagError, match=match) as e:
        read_all(path, **kw)
    assert str(path) in str(e.value)


def test_missing_bag(tmp):
    _expect(tmp / "nope", "no such bag")


def test_truncated_and_corrupt_bags(tmp):
    bags.write_frames(tmp / "good", _frames(5))
    mcap = next((tmp / "good").glob("*.mcap"))
    data = mcap.read_bytes()
    (tmp / "trunc.mcap").write_bytes(data[: len(data) // 2])
    _expect(tmp / "trunc.mcap", "cannot open bag|corrupt or truncated")
    (tmp / "junk.mcap").write_bytes(os.urandom(4096))
    _expect(tmp / "junk.mcap", "cannot open bag")
    (tmp / "empty").mkdir()
    _expect(tmp / "empty", "cannot open bag")


def test_missing_topic_lists_the_topics(tmp):
    bags.write_frames(tmp / "b", _frames(1))
    _expect(tmp / "b", r"topic '/nope' is not in the bag; topics: /camera/depth/camera_info "
                       r"\[sensor_msgs/msg/CameraInfo\]", depth_topic="/nope")
    _expect(tmp / "b", "has type sensor_msgs/msg/CameraInfo, expected sensor_msgs/msg/Image",
            depth_topic=bags.INFO_TOPIC)


def test_unsupported_encoding(tmp):
    _raw_bag(tmp / "rgb", [("rgb8", 2, 2, 6, 0, bytes(12))])
    _expect(tmp / "rgb", "unsupported encoding 'rgb8'; valid: 16UC1, mono16, 32FC1")


def test_writer_leaves_nothing_behind_on_failure(tmp):
    with pytest.raises(RuntimeError):
        with BagWriter(tmp / "out") as w:
            w.write(*_frames(1)[0])
            raise RuntimeError("killed mid-write")
    assert list(tmp.iterdir()) == []
    bags.write_frames(tmp / "out", _frames(1))
    with pytest.raises(BagError, match="exists already"):
        BagWriter(tmp / "out")


def test_cli_errors_are_one_line_without_traceback(tmp):
    (tmp / "junk.mcap").write_bytes(b"\x89MCAP0\r\n" + os.urandom(100))
    for bag in (tmp / "nope", tmp / "junk.mcap"):
        p = run_cli("bag-info", bag)
        assert p.returncode == 2
        lines = p.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"inseggan bag-info: error: {bag}:"), p.stderr
        assert "Traceback" not in p.stderr
    p = run_cli("bag-info", BAGS / "cylinder_sim", "--topic", "/none")
    assert p.returncode == 2 and "topics: /camera/depth/camera_info" in p.stderr
    p = run_cli("bag-info", BAGS / "cylinder_sim")
    assert p.returncode == 0 and "224x224 16UC1" in p.stdout


def test_cli_simulate_bag_is_atomic(tmp):
    p = run_cli("simulate-bag", "--quiet", "--count", "3", "--object", "cone", "--encoding",
                "32FC1", "--out", tmp / "cones", check=True)
    frames = read_all(tmp / "cones")
    assert len(frames) == 3 and frames[0].encoding == "32FC1"
    assert "wrote" in p.stdout
    p = run_cli("simulate-bag", "--count", "3", "--object", "teapot", "--out", tmp / "x")
    assert p.returncode == 2 and "invalid choice: 'teapot'" in p.stderr
    assert not (tmp / "x").exists()
    # killed while writing: no bag and no partial files
    # SIGINT at its default (a shell runs background jobs with it ignored, and Python keeps an
    # ignored SIGINT ignored)
    proc = subprocess.Popen([str(installed_executable("inseggan")), "simulate-bag", "--quiet",
                             "--count", "100000", "--out", str(tmp / "killed")],
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 60  # until it writes: its partial bag exists, with data
        while time.monotonic() < deadline and proc.poll() is None and not any(
                f.is_file() and f.stat().st_size > 0 for d in tmp.glob(".killed.partial-*")
                for f in d.rglob("*")):
            time.sleep(0.1)
        assert proc.poll() is None, "simulate-bag ended before it could be interrupted"
        proc.send_signal(signal.SIGINT)  # Ctrl-C while writing
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:  # never leave it running (it would simulate 100000 frames)
            proc.kill()
            proc.wait()
    assert proc.returncode == 130
    assert not (tmp / "killed").exists()
    assert [p.name for p in tmp.iterdir()] == ["cones"]
