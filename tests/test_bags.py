"""rosbag2 bags written and read back for real (MCAP and sqlite3), and every expected error."""
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import BAGS, installed_executable, refused, run_cli
from test_bin_replay import stop

from inseggan_ros.io import bags
from inseggan_ros.io.bags import BagError, BagWriter, CameraInfo, read_all


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
    with warnings.catch_warnings():
        warnings.simplefilter("error", bags.TruncatedBagWarning)  # a complete bag: no warning
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


def test_mcap_chunks_are_compressed_unless_asked_not_to(tmp):
    """Compressed (zstd) chunks by default for MCAP (depth frames shrink several times; read back
    unchanged), none on request; sqlite3 has no chunks, so zstd there, or an unknown
    compression, is refused by name."""
    frames = _frames(4, shape=(120, 160))
    for frame in frames:  # a smooth depth image, as a camera's is (uniform noise does not shrink)
        frame[1][:] = np.linspace(0.3, 0.6, frame[1].size, dtype=np.float32).reshape(frame[1].shape)
        frame[2][:] = 0
    sizes = {}
    for compression in ("zstd", "none"):
        bags.write_frames(tmp / compression, frames, compression=compression)
        mcap = next((tmp / compression).glob("*.mcap"))
        sizes[compression] = mcap.stat().st_size
        raw = bags.image_codec.metres_to_depth(frames[0][1], "16UC1").tobytes()
        assert (mcap.read_bytes().find(raw[:400]) == -1) == (compression == "zstd")
        back = read_all(tmp / compression)
        np.testing.assert_array_equal(back[0].metres(), read_all(tmp / "zstd")[0].metres())
    assert sizes["zstd"] < sizes["none"] / 4, sizes
    bags.write_frames(tmp / "default", frames)
    assert next((tmp / "default").glob("*.mcap")).stat().st_size < sizes["none"] / 4
    with pytest.raises(ValueError, match="valid with sqlite3: none"):
        BagWriter(tmp / "db", storage="sqlite3", compression="zstd")
    with pytest.raises(ValueError, match="compression 'lz4' invalid; valid: none, zstd"):
        BagWriter(tmp / "x", compression="lz4")
    assert not (tmp / "db").exists() and not (tmp / "x").exists()


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
    assert total < 12e6  # zstd-compressed chunks: the 848 x 480 bags about 1-1.3 MB each
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


def test_nothing_recoverable_is_an_error(tmp):
    rng = np.random.default_rng(3)
    bags.write_frames(tmp / "good", _frames(5))
    mcap = next((tmp / "good").glob("*.mcap")).read_bytes()
    junk = rng.integers(0, 256, 4096, dtype=np.uint8).tobytes()
    files = {"junk.mcap": junk, "empty.mcap": b"", "magic_only.mcap": mcap[:8],
             "header_only.mcap": mcap[:60],  # cut before the first message
             "junk.db3": b"SQLite format 3\0" + junk, "empty.db3": b""}
    for name, content in files.items():
        (tmp / name).write_bytes(content)
        _expect(tmp / name, "cannot open bag")
    _expect(tmp / "header_only.mcap", "no complete message could be recovered")
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
        p = refused("bag-info", bag)
        assert p.returncode == 2
        lines = p.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"inseggan bag-info: error: {bag}:"), \
            p.stderr
        assert "Traceback" not in p.stderr
    p = refused("bag-info", BAGS / "cylinder_sim", "--topic", "/none")
    assert p.returncode == 2 and "topics: /camera/depth/camera_info" in p.stderr
    p = run_cli("bag-info", BAGS / "cylinder_sim")
    assert p.returncode == 0 and "224x224 16UC1" in p.stdout


def test_cli_simulate_bag_is_atomic(tmp):
    p = run_cli("simulate-bag", "--quiet", "--count", "3", "--object", "cone", "--encoding",
                "32FC1", "--out", tmp / "cones", check=True)
    frames = read_all(tmp / "cones")
    assert len(frames) == 3 and frames[0].encoding == "32FC1"
    assert "wrote" in p.stdout
    p = refused("simulate-bag", "--count", "3", "--object", "teapot", "--out", tmp / "x")
    assert p.returncode == 2 and "'teapot' is neither a part (cylinder," in p.stderr
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


def test_cli_simulate_bag_in_another_cell(tmp):
    """--mount-height and --bin-size: the same scene seen from a camera 20 % higher, in a bin
    20 % larger, has its floor 20 % farther and its bin as many pixels across."""
    from inseggan_ros.runtime.preprocess import prepare

    base = ("simulate-bag", "--quiet", "--count", "1", "--seed", "5", "--instances", "3")
    run_cli(*base, "--out", tmp / "here", check=True)
    run_cli(*base, "--mount-height", "0.42", "--bin-size", "0.108,0.108", "--out",
            tmp / "there", check=True)
    here, there = (prepare(read_all(tmp / name)[0].metres()) for name in ("here", "there"))
    assert there.floor_depth / here.floor_depth == pytest.approx(1.2, rel=0.02)
    sides = np.subtract(there.roi[2:], there.roi[:2]) / np.subtract(here.roi[2:], here.roi[:2])
    assert np.allclose(sides, 1.0, atol=0.08), (here.roi, there.roi)
    for bad, why in ((("--bin-size", "0.09"), "is not two lengths like 0.09,0.09"),
                     (("--bin-size", "0.02,0.02"), "valid: 0.03..2 m per side"),
                     (("--mount-height", "0.01"), "need 0 < near < mount_height < far")):
        p = refused("simulate-bag", *bad, "--out", tmp / "bad")
        assert p.returncode == 2 and why in p.stderr, p.stderr
        assert not (tmp / "bad").exists()


# ------------------------------------------------- compressedDepth, and camera info by stamp
@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
def test_compressed_depth_round_trip(tmp, storage, encoding):
    """Depth written as image_transport's compressedDepth reads back as the raw Image does:
    16UC1 the same millimetres, 32FC1 within the quantisation's bound; labels, camera info,
    stamps as they were; the topic found without naming it and listed as a depth topic."""
    frames = _frames()
    bags.write_frames(tmp / "raw", frames, encoding=encoding, storage=storage)
    bags.write_frames(tmp / "small", frames, encoding=encoding, storage=storage,
                      transport="compressedDepth")
    topics = bags.list_topics(tmp / "small")
    assert topics[bags.COMPRESSED_DEPTH_TOPIC] == ("sensor_msgs/msg/CompressedImage", 3)
    assert bags.DEPTH_TOPIC not in topics
    assert bags.depth_topics(topics) == [bags.COMPRESSED_DEPTH_TOPIC]
    raw, small = read_all(tmp / "raw"), read_all(tmp / "small")
    assert [f.stamp_ns for f in small] == [f[0] for f in frames]
    for r, c in zip(raw, small):
        assert c.encoding == encoding and c.frame_id == r.frame_id and r.compressed is None
        assert c.compressed[0] == f"{encoding}; compressedDepth png"
        np.testing.assert_array_equal(c.labels, r.labels)
        np.testing.assert_array_equal(c.camera_info.K, r.camera_info.K)
        if encoding == "16UC1":
            np.testing.assert_array_equal(c.depth, r.depth)
        else:
            a, _ = bags.image_codec.inverse_depth_params()
            bound = bags.image_codec.quantisation_bound(r.metres(), a) + 1e-6
            assert (np.abs(c.metres() - r.metres()) <= bound).all()
            np.testing.assert_array_equal(c.metres() == 0, r.metres() == 0)
    assert len(read_all(tmp / "small", depth_topic=bags.COMPRESSED_DEPTH_TOPIC)) == 3


def _write_messages(path, messages):
    """A bag of (topic, msgtype, stamp_ns, message) as given, in that order."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = bags.typestore()
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {}
        for topic, msgtype, stamp, msg in messages:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=store)
            w.write(conns[topic], stamp, store.serialize_cdr(msg, msgtype))


def _compressed(stamp_ns, fmt, data):
    store = bags.typestore()
    header = bags._header(store, stamp_ns, "cam")
    return store.types[bags.COMPRESSED_TYPE](header=header, format=fmt,
                                             data=np.frombuffer(data, np.uint8))


def test_compressed_depth_on_any_topic_beside_a_colour_jpeg(tmp):
    """A robot's recording: compressedDepth on its own topic name beside a JPEG colour
    CompressedImage: the depth topic is the only one that can be depth, so it is found; the
    JPEG topic named as depth, or a garbled depth frame, is an error naming topic and problem."""
    import cv2

    mm = np.arange(12, dtype=np.uint16).reshape(3, 4) * 100
    jpeg = cv2.imencode(".jpg", np.zeros((3, 4, 3), np.uint8))[1].tobytes()
    fmt, data = bags.image_codec.encode_compressed_depth(mm, "16UC1")
    depth_topic = "/robot/depth/image_raw/compressedDepth"
    colour_topic = "/robot/color/image_raw/compressed"
    _write_messages(tmp / "robot", [
        (colour_topic, bags.COMPRESSED_TYPE, 0, _compressed(0, "jpeg", jpeg)),
        (depth_topic, bags.COMPRESSED_TYPE, 1, _compressed(1, fmt, data)),
        (depth_topic, bags.COMPRESSED_TYPE, 2, _compressed(2, fmt, data[:-40]))])
    topics = bags.list_topics(tmp / "robot")
    assert bags.depth_topics(topics) == [depth_topic]
    first = next(bags.read_frames(tmp / "robot"))
    np.testing.assert_array_equal(first.depth, mm)
    assert first.frame_id == "cam" and first.camera_info is None
    _expect(tmp / "robot", f"topic '{depth_topic}': format '16UC1; compressedDepth png': the "
                           "PNG .* is cut short before its IEND chunk")
    _expect(tmp / "robot", f"topic '{colour_topic}': format 'jpeg' is not "
                           "compressed_depth_image_transport's", depth_topic=colour_topic)
    _write_messages(tmp / "two", [(t, bags.COMPRESSED_TYPE, 1, _compressed(1, fmt, data))
                                  for t in (depth_topic, "/other/compressedDepth")])
    _expect(tmp / "two", "no depth topic .* name one; depth topics: /other/compressedDepth, "
                         f"{depth_topic}")


def _info(fx):
    return CameraInfo(40, 30, np.array([[fx, 0, 19.5], [0, fx, 14.5], [0, 0, 1]]))


def _fx(frames):
    return [None if f.camera_info is None else f.camera_info.K[0, 0] for f in frames]


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_camera_info_recorded_after_its_image(tmp, storage):
    """Recorders often write each CameraInfo just after its image: every frame, the first
    included, gets the one of its own stamp."""
    frames = _frames(4)
    with BagWriter(tmp / "bag", storage=storage, transport="compressedDepth") as w:
        for k, (stamp, depth, _, _) in enumerate(frames):
            w.write(stamp, depth)
            w.write_camera_info(stamp, _info(100 + k))
    assert _fx(read_all(tmp / "bag")) == [100, 101, 102, 103]
    assert _fx(read_all(tmp / "bag", limit=1)) == [100]  # what bag-info reads
    p = run_cli("bag-info", tmp / "bag")
    assert p.returncode == 0 and "camera_info yes" in p.stdout, p.stdout + p.stderr


def test_camera_info_nearest_in_stamp_wherever_it_was_recorded(tmp):
    """Each frame takes the CameraInfo nearest in header stamp (the earlier on a tie), however
    far ahead in the bag it was recorded; one CameraInfo anywhere serves every frame."""
    ms = 1_000_000
    frames = _frames(6)
    stamps = [f[0] for f in frames]  # 50 ms apart
    with BagWriter(tmp / "bag") as w:
        w.write(stamps[0], frames[0][1])
        w.write_camera_info(stamps[0], _info(10))  # frame 0's own
        w.write(stamps[1], frames[1][1])
        w.write(stamps[2], frames[2][1])
        w.write_camera_info(stamps[1] + 20 * ms, _info(12))  # nearer to frame 1 than 0's
        w.write(stamps[3], frames[3][1])
        w.write(stamps[4], frames[4][1])
        w.write(stamps[5], frames[5][1])
        w.write_camera_info(stamps[4] - 10 * ms, _info(14))  # recorded last
    # frame 2: 30 ms to 12, 60 to 14; frame 3: 80 ms to 12, 40 ms to 14
    assert _fx(read_all(tmp / "bag")) == [10, 12, 12, 14, 14, 14]
    with BagWriter(tmp / "tie") as w:
        w.write(stamps[1], frames[1][1])
        w.write_camera_info(stamps[0], _info(20))
        w.write_camera_info(stamps[2], _info(22))
    assert _fx(read_all(tmp / "tie")) == [20]
    with BagWriter(tmp / "late") as w:
        for stamp, depth, _, _ in frames:
            w.write(stamp, depth)
        w.write_camera_info(stamps[-1] + 10**9, _info(30))  # a second after the last frame
    assert _fx(read_all(tmp / "late")) == [30] * 6
    assert _fx(read_all(tmp / "late", limit=1)) == [30]
    bags.write_frames(tmp / "none", [(s, d, None, None) for s, d, _, _ in frames])
    assert _fx(read_all(tmp / "none")) == [None] * 6


def test_camera_info_after_the_image_in_a_cut_bag(tmp):
    """A recording cut short is read from its files record by record: camera info is matched
    by stamp there too."""
    frames = _frames(6)
    with BagWriter(tmp / "bag", compression="none") as w:
        for k, (stamp, depth, _, _) in enumerate(frames):
            w.write(stamp, depth)
            w.write_camera_info(stamp, _info(50 + k))
    (tmp / "bag" / "metadata.yaml").unlink()
    got, _ = _read_warned(tmp / "bag")
    assert _fx(got) == [50, 51, 52, 53, 54, 55]
    mcap = next((tmp / "bag").glob("*.mcap"))
    cut = _message_ends(mcap)[bags.DEPTH_TOPIC][4] + 1  # frame 4 whole, its camera info lost
    mcap.write_bytes(mcap.read_bytes()[:cut])
    got, warning = _read_warned(tmp / "bag")
    assert "truncated bag" in warning
    assert _fx(got) == [50, 51, 52, 53, 53]  # frame 4: the nearest left, 50 ms before it


# ------------------------------------------------------------------ bags as robots leave them
def _read_warned(path, **kw):
    """read_all, and the one TruncatedBagWarning it must emit (asserted)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        frames = read_all(path, **kw)
    warned = [str(w.message) for w in caught if issubclass(w.category, bags.TruncatedBagWarning)]
    assert len(warned) == 1, warned
    assert warned[0].startswith(f"{path}: ")
    return frames, warned[0]


def _assert_originals(got, originals, labels_from=None):
    """`got` are the first frames of `originals`, identical; frames from index `labels_from` on
    may have lost their labels (their label message was after the cut)."""
    assert len(got) <= len(originals)
    for k, (g, o) in enumerate(zip(got, originals)):
        assert (g.stamp_ns, g.frame_id, g.encoding) == (o.stamp_ns, o.frame_id, o.encoding)
        np.testing.assert_array_equal(g.depth, o.depth)
        np.testing.assert_array_equal(g.camera_info.K, o.camera_info.K)
        if labels_from is None or k < labels_from:
            np.testing.assert_array_equal(g.labels, o.labels)
        else:
            assert g.labels is None


def _message_ends(mcap_file) -> dict[str, list[int]]:
    """{topic: where each message record ends in the file} of a complete MCAP file with
    uncompressed chunks. A message record ends with the message's bytes, so each is found by
    searching the file for them: independent of the reader under test."""
    from rosbags.rosbag2 import Reader

    data = mcap_file.read_bytes()
    ends: dict[str, list[int]] = {}
    with Reader(mcap_file) as reader:
        for conn, _, raw in reader.messages():
            pos = data.find(raw)
            assert pos > 0 and data.find(raw, pos + 1) == -1  # unique: stamps and depths differ
            ends.setdefault(conn.topic, []).append(pos + len(raw))
    return ends


def _chunks(mcap_file) -> list[tuple[int, int]]:
    """(where the chunk record ends, its last message time) of each chunk, from the summary."""
    from mcap.reader import make_reader

    with open(mcap_file, "rb") as f:
        return [(c.chunk_start_offset + c.chunk_length, c.message_end_time)
                for c in make_reader(f).get_summary().chunk_indexes]


def _chunk_ends(mcap_file) -> list[int]:
    return [end for end, _ in _chunks(mcap_file)]


def _rewrite_mcap(src, dst, **writer_options):
    """The messages of an MCAP file written again by the `mcap` package's writer: unchunked (as
    rosbag2's "fastwrite" preset writes) or in compressed chunks."""
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader
    from mcap.writer import Writer

    schemas, channels = {}, {}
    with open(src, "rb") as f, open(dst, "wb") as out:
        writer = Writer(out, **writer_options)
        writer.start(profile="ros2", library="test")
        for r in StreamReader(f).records:
            if isinstance(r, Schema) and r.id not in schemas:
                schemas[r.id] = writer.register_schema(r.name, r.encoding, r.data)
            elif isinstance(r, Channel) and r.id not in channels:
                channels[r.id] = writer.register_channel(r.topic, r.message_encoding,
                                                         schemas[r.schema_id], r.metadata)
            elif isinstance(r, Message):
                writer.add_message(channels[r.channel_id], r.log_time, r.data, r.publish_time,
                                   r.sequence)
        writer.finish()


@pytest.mark.parametrize("layout", ["chunks", "unchunked"])
def test_cut_mcap_bag_gives_every_complete_frame(tmp, layout):
    # 1.1 MB in uncompressed chunks (two), so that each message's bytes can be found
    bags.write_frames(tmp / "bag", _frames(30, shape=(96, 128)), compression="none")
    originals = read_all(tmp / "bag")
    mcap = next((tmp / "bag").glob("*.mcap"))
    if layout == "unchunked":
        _rewrite_mcap(mcap, tmp / "unchunked.mcap", use_chunking=False)
        mcap = tmp / "unchunked.mcap"
    data = mcap.read_bytes()
    ends = _message_ends(mcap)
    depth_ends, label_ends = ends[bags.DEPTH_TOPIC], ends[bags.LABELS_TOPIC]
    assert len(depth_ends) == len(label_ends) == 30
    chunk_ends = _chunk_ends(mcap)
    assert len(chunk_ends) == (2 if layout == "chunks" else 0)
    cuts = {depth_ends[0] - 1, depth_ends[0], label_ends[0], depth_ends[7] + 1, label_ends[7] - 1,
            depth_ends[-1], label_ends[-1], len(data) - 1}
    cuts |= {c + d for c in chunk_ends[:1] for d in (-1, 0, 10)}
    rng = np.random.default_rng(18)
    cuts |= {int(c) for c in rng.integers(0, len(data), 8)}
    for i, cut in enumerate(sorted(cuts)):
        # as a robot leaves it: a directory without metadata.yaml, or the storage file alone
        bag = tmp / f"cut{i}" / "cut.mcap" if i % 2 else tmp / f"cut{i}.mcap"
        bag.parent.mkdir(exist_ok=True)
        bag.write_bytes(data[:cut])
        bag = bag.parent if i % 2 else bag
        n = sum(e <= cut for e in depth_ends)
        if n == 0:
            with pytest.raises(BagError), warnings.catch_warnings():
                warnings.simplefilter("ignore", bags.TruncatedBagWarning)  # a camera_info only
                read_all(bag)
            continue
        got, warning = _read_warned(bag)
        assert len(got) == n, (cut, len(data))
        _assert_originals(got, originals, labels_from=sum(e <= cut for e in label_ends))
        assert "truncated bag" in warning and f"{n} on {bags.DEPTH_TOPIC}" in warning
        assert ("no metadata.yaml" in warning) == (i % 2 == 1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", bags.TruncatedBagWarning)
            assert bags.list_topics(bag)[bags.DEPTH_TOPIC] == (bags.IMAGE_TYPE, n)
    assert any(sum(e <= c for e in depth_ends) == 30 for c in cuts)  # all frames, no footer


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_unfinished_bag_without_metadata(tmp, storage):
    bags.write_frames(tmp / "bag", _frames(5), storage=storage)
    originals = read_all(tmp / "bag")
    (tmp / "bag" / "metadata.yaml").unlink()
    got, warning = _read_warned(tmp / "bag")
    assert len(got) == 5
    _assert_originals(got, originals)
    assert "unfinished bag (no metadata.yaml" in warning
    assert "recovered 15 complete messages" in warning and f"5 on {bags.DEPTH_TOPIC}" in warning


def test_cut_sqlite_bag_gives_a_correct_prefix(tmp):
    """Best effort: sqlite reads what it still can of a cut .db3, in recorded order."""
    bags.write_frames(tmp / "bag", _frames(30, shape=(96, 128)), storage="sqlite3")
    originals = read_all(tmp / "bag")
    db = next((tmp / "bag").glob("*.db3"))
    data = db.read_bytes()
    rng = np.random.default_rng(18)
    cuts = sorted({len(data) - 4096, len(data) - 5000,
                   *range(len(data) - 4095, len(data), 512),  # inside the last page
                   *(int(c) for c in rng.integers(0, len(data), 10))})
    recovered = {}
    for i, cut in enumerate(cuts):
        bag = tmp / f"cut{i}"  # no metadata.yaml: the recorder died
        bag.mkdir()
        (bag / db.name).write_bytes(data[:cut])
        try:
            got, warning = _read_warned(bag)
        except BagError as e:
            assert str(bag) in str(e)
            continue
        assert "truncated bag" in warning and f"{len(got)} on {bags.DEPTH_TOPIC}" in warning
        _assert_originals(got, originals, labels_from=len(got) - (got[-1].labels is None))
        recovered[cut] = len(got)
    assert recovered.get(len(data) - 4095, 0) >= 25, recovered  # most of a bag cut near its end


def test_cli_shows_the_warning_once(tmp):
    bags.write_frames(tmp / "bag", _frames(5))
    (tmp / "bag" / "metadata.yaml").unlink()
    mcap = next((tmp / "bag").glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[:-100])
    p = run_cli("bag-info", tmp / "bag")
    assert p.returncode == 0, p.stderr
    # once, though bag-info opens the bag twice (Python shows a warning text once)
    assert p.stderr.count(f"TruncatedBagWarning: {tmp / 'bag'}: truncated bag") == 1, p.stderr
    assert f"5 on {bags.DEPTH_TOPIC}" in p.stderr


@pytest.mark.serial  # a node over real DDS: run alone (setup.cfg)
def test_bin_replay_node_replays_a_cut_bag_and_warns_once(tmp):
    """The node reads bags through read_frames: a cut recording replays (looping, so it is read
    many times) over real DDS to a separate receiver process, with one warning in its log."""
    bags.write_frames(tmp / "bag", _frames(8), compression="none")  # messages found by bytes
    originals = {f.stamp_ns: f for f in read_all(tmp / "bag")}
    (tmp / "bag" / "metadata.yaml").unlink()
    mcap = next((tmp / "bag").glob("*.mcap"))
    ends = _message_ends(mcap)
    cut = ends[bags.DEPTH_TOPIC][5] + 1  # frames 0-5 whole, labels of frame 5 lost
    mcap.write_bytes(mcap.read_bytes()[:cut])
    out = tmp / "received.npz"
    recv = subprocess.Popen([sys.executable, str(Path(__file__).parent / "receiver.py"), str(out),
                             "12", "60", "/cut_bag", "--labels-optional"],
                            stdout=subprocess.PIPE, text=True)
    assert recv.stdout.readline().strip() == "receiver ready"
    replay = subprocess.Popen([str(installed_executable("bin_replay")), "--ros-args", "-r",
                               "__ns:=/cut_bag", "-p", "source:=bag", "-p",
                               f"bag_path:={tmp / 'bag'}", "-p", "loop:=true", "-p", "rate:=30.0",
                               "-p", "restamp:=false"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert recv.wait(timeout=90) == 0, "receiver did not get its frames"
    finally:
        stop(replay)
        log = replay.stderr.read()
    assert replay.returncode == 0 and "Traceback" not in log, log
    assert log.count(f"{tmp / 'bag'}: truncated bag") == 1, log  # however often it loops
    assert "recovered 17 complete messages" in log
    got = dict(np.load(out, allow_pickle=True))
    assert set(got["stamp"]) <= set(sorted(originals)[:6])  # nothing from after the cut
    assert len(got["stamp"]) == 12  # from 6 frames: it looped
    lost = sorted(originals)[5]
    assert lost in set(got["stamp"])  # frame 5 itself is replayed, without its labels
    for stamp, depth, labels in zip(got["stamp"], got["depth"], got["labels"]):
        np.testing.assert_array_equal(depth, originals[stamp].depth)
        if stamp == lost:
            assert labels is None
        elif labels is not None:  # (a first frame's may come before its topic is matched)
            np.testing.assert_array_equal(labels, originals[stamp].labels)
    # looped twice: every frame before the cut but the last came with its labels at least once
    labelled = {s for s, labels in zip(got["stamp"], got["labels"]) if labels is not None}
    assert labelled == set(sorted(originals)[:5])


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_cut_compressed_mcap_bag(tmp, compression):
    """Compressed chunks (zstd: BagWriter's default for MCAP, as rosbag2's zstd presets write;
    lz4): every frame of the whole chunks before the cut, and of the part of the cut chunk that
    decompresses."""
    from mcap.writer import CompressionType

    bags.write_frames(tmp / "bag", _frames(30, shape=(96, 128)), compression="none")
    originals = read_all(tmp / "bag")
    stamps = [f.stamp_ns for f in originals]
    mcap = tmp / "compressed.mcap"
    if compression == "lz4":  # chunks of 200 kB, as a recorder configured so writes them
        _rewrite_mcap(next((tmp / "bag").glob("*.mcap")), mcap, chunk_size=200_000,
                      compression=CompressionType.LZ4)
    else:
        bags.write_frames(tmp / "zstd", _frames(30, shape=(96, 128)))  # the default
        mcap = next((tmp / "zstd").glob("*.mcap"))
    data = mcap.read_bytes()
    assert data.find(originals[0].depth.tobytes()[:200]) == -1  # compressed indeed
    chunks = _chunks(mcap)
    assert len(chunks) >= 2
    whole = [sum(s < end_time for s in stamps) for _, end_time in chunks]  # frames in chunks 0..j
    rng = np.random.default_rng(18)
    cuts = {*(end for end, _ in chunks), *(end - 10 for end, _ in chunks),
            *(int(c) for c in rng.integers(0, len(data), 6))}
    counts = []
    for cut in sorted(cuts):
        (tmp / "cut.mcap").write_bytes(data[:cut])
        try:
            got, warning = _read_warned(tmp / "cut.mcap")
        except BagError:
            got = []
        _assert_originals(got, originals,
                          labels_from=len(got) - bool(got and got[-1].labels is None))
        counts.append(len(got))
        for j, (end, _) in enumerate(chunks):
            if cut == end:  # whole chunks 0..j
                assert len(got) >= whole[j], (cut, j)
            if cut == end - 10:  # whole chunks 0..j-1 and most of chunk j
                assert len(got) > (whole[j - 1] if j else 0), (cut, j)
    assert counts == sorted(counts)  # a longer file never gives fewer frames


def test_split_recording_cut_in_its_last_file(tmp):
    """A recording split by size (rec_9.mcap, rec_10.mcap, ...) whose recorder died in the last
    file: the files in split order, the last one up to its cut."""
    frames = _frames(10)
    bags.write_frames(tmp / "a", frames[:5])
    bags.write_frames(tmp / "b", frames[5:], compression="none")  # its messages found by bytes
    originals = read_all(tmp / "a") + read_all(tmp / "b")
    (tmp / "rec").mkdir()
    next((tmp / "a").glob("*.mcap")).rename(tmp / "rec" / "rec_9.mcap")
    second = next((tmp / "b").glob("*.mcap"))
    cut = _message_ends(second)[bags.LABELS_TOPIC][2]  # frames 5-7 whole
    (tmp / "rec" / "rec_10.mcap").write_bytes(second.read_bytes()[:cut])
    got, warning = _read_warned(tmp / "rec")
    assert len(got) == 8
    _assert_originals(got, originals)
    assert "rec_10.mcap (" in warning and "rec_9.mcap" not in warning  # only the last is cut
    assert f"8 on {bags.DEPTH_TOPIC}" in warning
