"""rosbag2 bags (MCAP or sqlite3) of depth frames, read and written with `rosbags` (no ROS needed).

Topics follow the camera-driver convention (realsense2_camera, depth_image_proc):
  /camera/depth/image_rect_raw     sensor_msgs/msg/Image   16UC1 millimetres or 32FC1 metres
  /camera/depth/camera_info        sensor_msgs/msg/CameraInfo
  /camera/depth/instance_labels    sensor_msgs/msg/Image   mono8 ground truth (simulated bags only)
  /camera/depth/image_rect_raw/compressedDepth  sensor_msgs/msg/CompressedImage: the depth as
      image_transport's compressedDepth plugin publishes it (a 16-bit PNG; image_codec), read as
      the raw Image is, and written on request (BagWriter's `transport`)
The reader takes any topic names and any bag `ros2 bag record` writes; camera info goes to each
frame by header stamp, wherever the recorder put it; expected problems (missing
or corrupt bag, absent topic, unsupported encoding) raise `BagError` naming the bag and the
problem. Bags as robots leave them are read too: a recording cut short (recorder killed, power
lost) or never finished (no metadata.yaml) gives every complete message in it, with one
`TruncatedBagWarning` saying what was recovered; only a bag with nothing recoverable is an error.
The writer writes into a hidden temporary directory and renames it into place when the bag is
complete, so a failed or interrupted write leaves nothing behind.
"""
from __future__ import annotations

import bisect
import os
import re
import shutil
import tempfile
import warnings
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

from inseggan_ros.core import image_codec
from inseggan_ros.core.image_codec import DEPTH_ENCODINGS, ImageFormatError

DEPTH_TOPIC = "/camera/depth/image_rect_raw"
INFO_TOPIC = "/camera/depth/camera_info"
LABELS_TOPIC = "/camera/depth/instance_labels"
IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
DEPTH_TYPES = (IMAGE_TYPE, COMPRESSED_TYPE)
COMPRESSED_SUFFIX = "/" + image_codec.COMPRESSED_DEPTH  # image_transport's topic for it
COMPRESSED_DEPTH_TOPIC = DEPTH_TOPIC + COMPRESSED_SUFFIX
TRANSPORTS = ("raw", image_codec.COMPRESSED_DEPTH)  # how depth is written (BagWriter)
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
DEFAULT_FRAME_ID = "camera_depth_optical_frame"


class BagError(Exception):
    """An expected problem with a bag: the message names the bag and what is wrong."""

    def __init__(self, path, problem: str):
        super().__init__(f"{path}: {problem}")
        self.path, self.problem = str(path), problem


@dataclass
class CameraInfo:
    """The parts of sensor_msgs/CameraInfo this package uses."""

    width: int
    height: int
    K: np.ndarray  # (3, 3)
    D: np.ndarray = field(default_factory=lambda: np.zeros(5))
    distortion_model: str = "plumb_bob"

    @staticmethod
    def from_camera(cam) -> "CameraInfo":
        """From a `sim.camera.CameraConfig`."""
        return CameraInfo(cam.width, cam.height, cam.K)


@dataclass
class DepthFrame:
    stamp_ns: int
    frame_id: str
    encoding: str  # one of image_codec.DEPTH_ENCODINGS
    depth: np.ndarray  # (H, W) raw values: uint16 millimetres or float32 metres
    labels: np.ndarray | None = None  # (H, W) uint8 ground truth, when known
    camera_info: CameraInfo | None = None
    compressed: tuple[str, bytes] | None = None  # compressedDepth (format, data), as recorded

    def metres(self) -> np.ndarray:
        return image_codec.depth_to_metres(self.depth, self.encoding)


def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


typestore = _typestore  # the ROS 2 Jazzy message types, for tools that copy bags


def open_bag(path):
    """An opened rosbags Reader of a bag, or for a recording cut short or never finished a
    reader of its complete messages (with a TruncatedBagWarning): `topics`, `connections`,
    `messages(connections=())` and `close()`, for tools that copy whole bags. Close it."""
    return _open_reader(Path(path))


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


# --------------------------------------------------------------------------------- reading
def _open_reader(path: Path):
    from rosbags.rosbag2 import Reader

    if not path.exists():
        raise BagError(path, "no such bag (expected a rosbag2 directory, .mcap or .db3 file)")
    files = _storage_files(path)
    if any(_is_sqlite(f) and not _sqlite_intact(f) for f in files):
        # sqlite would open some cut files and read zeros where pages are missing
        return _recover(path, files, "a .db3 file is shorter than its header says")
    try:
        reader = Reader(path)
        reader.open()
    except Exception as e:  # rosbags raises several types for unreadable bags
        return _recover(path, files, str(e))
    return reader


def list_topics(path) -> dict[str, tuple[str, int]]:
    """{topic: (message type, message count)} of a bag."""
    path = Path(path)
    reader = _open_reader(path)
    try:
        return {t: (info.msgtype or "?", info.msgcount) for t, info in reader.topics.items()}
    finally:
        reader.close()


def _describe(topics: dict) -> str:
    return ", ".join(f"{t} [{typ}]" for t, (typ, _) in sorted(topics.items())) or "none"


def _pick_topic(path, topics: dict, wanted: str | None, default: str, msgtype: str,
                required: bool) -> str | None:
    if wanted:
        if wanted not in topics:
            raise BagError(path, f"topic {wanted!r} is not in the bag; topics: {_describe(topics)}")
        if topics[wanted][0] != msgtype:
            raise BagError(path, f"topic {wanted!r} has type {topics[wanted][0]}, expected "
                                 f"{msgtype}; topics: {_describe(topics)}")
        return wanted
    if default in topics and topics[default][0] == msgtype:
        return default
    if not required:
        return None
    candidates = [t for t, (typ, _) in topics.items() if typ == msgtype and "label" not in t]
    if len(candidates) == 1:
        return candidates[0]
    raise BagError(path, f"no {msgtype} topic {default!r}; name one; topics: {_describe(topics)}")


def depth_topics(topics: dict) -> list[str]:
    """The topics of `list_topics` that can be depth: Image topics (but label images), and
    CompressedImage topics image_transport's compressedDepth plugin names (.../compressedDepth)."""
    return sorted(t for t, (typ, _) in topics.items()
                  if typ == IMAGE_TYPE and "label" not in t
                  or typ == COMPRESSED_TYPE and t.endswith(COMPRESSED_SUFFIX))


def resolve_depth_topic(path, topics: dict, wanted: str | None = None) -> str:
    """The depth topic `read_frames` reads: `wanted` (an Image or a compressedDepth
    CompressedImage topic), else /camera/depth/image_rect_raw, its compressedDepth, or the bag's
    only depth topic (`depth_topics`). BagError naming the topics when there is no one topic."""
    if wanted:
        if wanted not in topics:
            raise BagError(path, f"topic {wanted!r} is not in the bag; topics: {_describe(topics)}")
        if topics[wanted][0] not in DEPTH_TYPES:
            raise BagError(path, f"topic {wanted!r} has type {topics[wanted][0]}, expected "
                                 f"{' or '.join(DEPTH_TYPES)}; topics: {_describe(topics)}")
        return wanted
    for topic, msgtype in ((DEPTH_TOPIC, IMAGE_TYPE), (COMPRESSED_DEPTH_TOPIC, COMPRESSED_TYPE)):
        if topics.get(topic, ("",))[0] == msgtype:
            return topic
    candidates = depth_topics(topics)
    if len(candidates) == 1:
        return candidates[0]
    raise BagError(path, f"no depth topic {DEPTH_TOPIC!r} ({IMAGE_TYPE}) or "
                         f"{COMPRESSED_DEPTH_TOPIC!r} ({COMPRESSED_TYPE}, compressedDepth); "
                         f"name one; depth topics: {', '.join(candidates) or 'none'}; topics: "
                         f"{_describe(topics)}")


def _info_sibling(depth_topic: str) -> str:
    """The camera_info beside a depth topic: .../image_rect_raw[/compressedDepth] ->
    .../camera_info."""
    base = depth_topic[:-len(COMPRESSED_SUFFIX)] if depth_topic.endswith(COMPRESSED_SUFFIX) \
        else depth_topic
    return base.rsplit("/", 1)[0] + "/camera_info"


def _camera_info(msg) -> CameraInfo:
    return CameraInfo(int(msg.width), int(msg.height), np.asarray(msg.k, float).reshape(3, 3),
                      np.asarray(msg.d, float), str(msg.distortion_model))


class _InfoTrack:
    """The CameraInfo nearest in header stamp to each depth frame (the earlier one on a tie),
    reading the info topic alone, ahead of the frames as far as a frame needs: up to the first
    CameraInfo stamped at or after it. So a recorder that writes each CameraInfo just after its
    image, or one CameraInfo anywhere in the bag, still gives every frame its camera info.
    Frames come in stamp order: CameraInfos older than the latest at or before a frame are
    dropped."""

    def __init__(self, stream: Iterator[tuple[int, CameraInfo]]):
        self._stream = stream
        self._stamps: list[int] = []  # sorted
        self._infos: list[CameraInfo] = []
        self._ended = False

    def nearest(self, stamp: int) -> CameraInfo | None:
        while not self._ended and (not self._stamps or self._stamps[-1] < stamp):
            got = next(self._stream, None)
            if got is None:
                self._ended = True
                break
            i = bisect.bisect_right(self._stamps, got[0])
            self._stamps.insert(i, got[0])
            self._infos.insert(i, got[1])
        i = bisect.bisect_right(self._stamps, stamp)  # _stamps[:i] are at or before it
        if i == 0:
            return self._infos[0] if self._infos else None  # none before: the first after
        pick = i - 1
        if i < len(self._stamps) and self._stamps[i] - stamp < stamp - self._stamps[i - 1]:
            pick = i  # the one after is nearer
        # a later frame is never nearest to one older than the latest at or before this frame
        del self._stamps[:i - 1], self._infos[:i - 1]
        return self._infos[pick - (i - 1)]


def _decode_depth(msgtype: str, msg) -> tuple[np.ndarray, str, tuple[str, bytes] | None]:
    """(raw depth, encoding, the compressedDepth (format, data) when it came so)."""
    if msgtype == COMPRESSED_TYPE:
        data = bytes(msg.data)
        depth, encoding = image_codec.decode_compressed_depth(str(msg.format), data)
        return depth, encoding, (str(msg.format), data)
    depth = image_codec.decode(msg.height, msg.width, msg.encoding, msg.is_bigendian, msg.step,
                               msg.data, allowed=DEPTH_ENCODINGS)
    return depth, str(msg.encoding), None


def read_frames(path, depth_topic: str | None = None, info_topic: str | None = None,
                labels_topic: str | None = None, limit: int | None = None,
                on_bad_frame: Callable[[str], None] | None = None) -> Iterator[DepthFrame]:
    """Yield the depth frames of a bag in time order, with ground truth and camera info if there.

    `depth_topic` (a sensor_msgs/Image, or a sensor_msgs/CompressedImage of image_transport's
    compressedDepth) defaults as `resolve_depth_topic` says; `info_topic` to the camera_info
    beside it; `labels_topic` to /camera/depth/instance_labels. Labels are matched to depth
    frames by header stamp; camera info is the one nearest in header stamp (`_InfoTrack`).
    A depth frame that does not decode is a BagError, or with `on_bad_frame` skipped after
    calling it with a line naming the frame and the problem (a node replaying the bag goes on).
    A recording cut short or never finished gives its complete messages in recorded order, with
    a TruncatedBagWarning (see _recover).
    """
    path = Path(path)
    reader = _open_reader(path)
    try:
        topics = {t: (i.msgtype or "?", i.msgcount) for t, i in reader.topics.items()}
        depth_topic = resolve_depth_topic(path, topics, depth_topic)
        sibling = _info_sibling(depth_topic)
        info_topic = _pick_topic(path, topics, info_topic,
                                 sibling if sibling in topics else INFO_TOPIC, INFO_TYPE, False)
        labels_topic = _pick_topic(path, topics, labels_topic, LABELS_TOPIC, IMAGE_TYPE, False)
        if labels_topic == depth_topic:
            raise BagError(path, f"labels topic and depth topic are the same: {depth_topic!r}")
        store = _typestore()

        def messages(topic):
            wanted = [c for c in reader.connections if c.topic == topic]
            for conn, _t, raw in reader.messages(connections=wanted):
                yield conn.msgtype, store.deserialize_cdr(raw, conn.msgtype)

        labels: dict[int, np.ndarray] = {}
        if labels_topic:  # first pass: ground truth by stamp (small, mono8)
            for _, msg in messages(labels_topic):
                labels[_stamp_ns(msg.header)] = image_codec.decode(
                    msg.height, msg.width, msg.encoding, msg.is_bigendian, msg.step, msg.data,
                    allowed=("mono8", "8UC1"))
        infos = _InfoTrack((_stamp_ns(m.header), _camera_info(m))
                           for _, m in (messages(info_topic) if info_topic else ()))
        count = 0
        for msgtype, msg in messages(depth_topic):
            stamp = _stamp_ns(msg.header)
            try:
                depth, encoding, compressed = _decode_depth(msgtype, msg)
            except ImageFormatError as e:
                problem = f"topic {depth_topic!r}: {e} (the frame stamped {stamp})"
                if on_bad_frame is None:
                    raise BagError(path, problem) from None
                on_bad_frame(f"{path}: {problem}; skipped")
                continue
            yield DepthFrame(stamp, str(msg.header.frame_id), encoding, depth,
                             labels.get(stamp), infos.nearest(stamp), compressed)
            count += 1
            if limit is not None and count >= limit:
                return
    except BagError:
        raise
    except ImageFormatError as e:
        raise BagError(path, f"topic {labels_topic!r}: {e}") from None
    except Exception as e:  # truncated chunk, bad CDR, ... inside a bag that opened
        raise BagError(path, f"corrupt or truncated bag: {type(e).__name__}: {e}") from None
    finally:
        reader.close()


def read_all(path, **kwargs) -> list[DepthFrame]:
    return list(read_frames(path, **kwargs))


# ------------------------------------------------------------------ bags as robots leave them
class TruncatedBagWarning(UserWarning):
    """A bag was read only in part: its recording was cut short (recorder killed, power lost) or
    never finished (no metadata.yaml). The message names the bag and what was recovered. Python
    shows a warning once per process for the same text, so a node looping a bag warns once."""


@dataclass(frozen=True)
class _Connection:  # what read_frames uses of a rosbags Connection
    topic: str
    msgtype: str


@dataclass
class _TopicInfo:  # what list_topics and read_frames use of a rosbags TopicInfo
    msgtype: str
    msgcount: int


@dataclass
class _FileScan:
    """How one storage file read: `cut` when it ends before its writer finished it."""

    name: str
    cut: bool = False
    detail: str = ""


def _storage_files(path: Path) -> list[Path]:
    """The storage files of a bag: the file itself, or a directory's .mcap/.db3 files in split
    order (bag_2 before bag_10)."""
    if not path.is_dir():
        return [path]
    files = [p for p in path.iterdir() if p.suffix in (".mcap", ".db3") and p.is_file()]
    return sorted(files, key=lambda p: [int(t) if t.isdigit() else t
                                        for t in re.split(r"(\d+)", p.name)])


def _is_sqlite(file: Path) -> bool:
    with open(file, "rb") as f:
        return f.read(16) == b"SQLite format 3\0"


def _sqlite_state(file: Path) -> tuple[int, bool]:
    """(page size, intact) of a sqlite file; intact = as long as its header says. Opened with
    immutable=1: read only, and a journal a dead writer left is neither used nor touched."""
    import sqlite3

    con = sqlite3.connect(file.resolve().as_uri() + "?immutable=1", uri=True)
    try:
        (page_size,) = con.execute("PRAGMA page_size").fetchone()
        try:  # sqlite refuses a file shorter than its header's page count
            (pages,) = con.execute("PRAGMA page_count").fetchone()
        except sqlite3.DatabaseError:
            return page_size, False
    except sqlite3.DatabaseError:  # not a database at all
        return 0, False
    finally:
        con.close()
    size = file.stat().st_size
    return page_size, size % page_size == 0 and size >= pages * page_size


def _sqlite_intact(file: Path) -> bool:
    return _sqlite_state(file)[1]


def _sqlite_messages(file: Path, scan: _FileScan) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, type, stamp, data) of each rosbag2 message sqlite can still read from a .db3 file,
    in recorded order, up to the first row it cannot read (best effort for a cut file)."""
    import sqlite3

    page_size, intact = _sqlite_state(file)
    if not intact:
        scan.cut, scan.detail = True, "is shorter than its header says"
    count = 0
    with tempfile.TemporaryDirectory(prefix="inseggan-bag-") as tmp:
        src = file
        if page_size and file.stat().st_size % page_size:
            # sqlite reads the missing end of a last, partial page as zeros: wrong data, no error.
            # A copy of the whole pages makes every missing page an error instead.
            src = Path(tmp) / file.name
            shutil.copyfile(file, src)
            os.truncate(src, file.stat().st_size // page_size * page_size)
        con = sqlite3.connect(src.resolve().as_uri() + "?immutable=1", uri=True)
        try:
            con.execute("PRAGMA writable_schema=ON")  # lets sqlite read a file shorter than its
            topics = {i: (name, typ) for i, name, typ in  # header says; writes nothing
                      con.execute("SELECT id, name, type FROM topics")}
            for topic_id, stamp, data in con.execute(
                    "SELECT topic_id, timestamp, data FROM messages ORDER BY id"):
                count += 1
                if topic_id in topics:
                    yield (*topics[topic_id], int(stamp), bytes(data))
        except sqlite3.DatabaseError as e:
            scan.cut = True
            scan.detail = (scan.detail + "; " if scan.detail else "") + \
                f"sqlite read {count} rows, then: {e}"
        finally:
            con.close()


def _mcap_errors() -> tuple:
    """What reading a cut or garbled MCAP file raises: the end of what can be read."""
    import struct

    from mcap.exceptions import McapError

    return McapError, struct.error, ValueError, EOFError


def _decompress(compression: str, data: bytes) -> bytes:
    """An MCAP chunk's records, decompressed as far as `data` goes: a cut chunk gives a prefix."""
    try:
        if compression == "":
            return data
        if compression == "zstd":  # what rosbags uses (the mcap package wants `zstandard`)
            try:
                from compression import zstd
            except ImportError:
                from backports import zstd
            return zstd.ZstdDecompressor().decompress(data)
        if compression == "lz4":
            import lz4.frame

            return lz4.frame.LZ4FrameDecompressor().decompress(data)
    except Exception:  # garbled compressed data: nothing of this chunk can be trusted
        return b""
    return b""  # an unknown compression


def _chunk_records(chunk) -> Iterator:
    """The whole records in an MCAP chunk, or in the part of it that is in the file."""
    from mcap.stream_reader import StreamReader

    data = _decompress(chunk.compression, chunk.data)
    try:
        yield from StreamReader(BytesIO(data), skip_magic=True,
                                record_size_limit=len(data)).records
    except _mcap_errors():  # the end of the chunk (or of the part of it there is)
        return


def _mcap_records(file: Path, scan: _FileScan) -> Iterator:
    """The records of an MCAP file up to where it is cut, read with the `mcap` package's
    record-level stream reader. The record the file ends inside is lost, except when it is a
    chunk: then the whole records in the part of the chunk before the cut are read too."""
    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    size = file.stat().st_size
    with open(file, "rb") as f:
        good_end = 0  # where the last whole record ends
        try:
            for record in StreamReader(f, emit_chunks=True, record_size_limit=size).records:
                if isinstance(record, Chunk):
                    yield from _chunk_records(record)
                else:
                    yield record
                good_end = f.tell()
            return  # through the footer and the closing magic: a complete file
        except _mcap_errors():
            pass
        scan.cut = True
        scan.detail = (f"({size:,} bytes) ends in, or is garbled at, the record at byte "
                       f"{good_end:,}")
        f.seek(good_end)
        stream = ReadDataStream(f)
        try:
            if good_end and stream.read1() == Opcode.CHUNK:
                stream.read8()  # its length, which the file does not hold
                yield from _chunk_records(Chunk.read(stream))  # Chunk.read takes what is there
        except _mcap_errors():
            pass


def _mcap_messages(file: Path, scan: _FileScan) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, type, log time, data) of each complete message of an MCAP file, in file order."""
    from mcap.records import Channel, Message, Schema

    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str]] = {}
    for record in _mcap_records(file, scan):
        if isinstance(record, Schema):
            schemas[record.id] = record.name
        elif isinstance(record, Channel):
            channels[record.id] = (record.topic, schemas.get(record.schema_id, "?"))
        elif isinstance(record, Message) and record.channel_id in channels:
            yield (*channels[record.channel_id], record.log_time, record.data)


def _file_messages(file: Path, scan: _FileScan) -> Iterator[tuple[str, str, int, bytes]]:
    return (_sqlite_messages if _is_sqlite(file) else _mcap_messages)(file, scan)


class _PartialBag:
    """A bag rosbags cannot open -- its recording was cut short or never finished -- read from its
    storage files record by record: every complete message, in recorded order. It offers what
    list_topics and read_frames use of a rosbags Reader (topics, connections, messages, close);
    each messages() call reads the files again, as rosbags does."""

    def __init__(self, path: Path, files: list[Path], reason: str):
        self.path, self.files, self.reason = path, files, reason
        self.scans = [_FileScan(f.name) for f in files]
        counts: dict[str, int] = {}
        types: dict[str, str] = {}
        for file, scan in zip(files, self.scans):
            for topic, msgtype, _, _ in _file_messages(file, scan):
                counts[topic] = counts.get(topic, 0) + 1
                types[topic] = msgtype
        self.topics = {t: _TopicInfo(types[t], n) for t, n in counts.items()}
        self.connections = [_Connection(t, types[t]) for t in counts]
        self.count = sum(counts.values())

    def messages(self, connections=()) -> Iterator[tuple[_Connection, int, bytes]]:
        wanted = {c.topic: c for c in (connections or self.connections)}
        for file in self.files:
            for topic, _, stamp, data in _file_messages(file, _FileScan(file.name)):
                if topic in wanted:
                    yield wanted[topic], stamp, data

    def close(self) -> None:
        pass

    def describe(self) -> str:
        """What happened to the recording and what was recovered, for the warning."""
        problems = [f"{s.name} {s.detail}" for s in self.scans if s.cut]
        if self.path.is_dir() and not (self.path / "metadata.yaml").exists():
            problems.insert(0, "no metadata.yaml: the recording was not finished")
        state = "truncated" if any(s.cut for s in self.scans) else "unfinished"
        per_topic = ", ".join(f"{info.msgcount} on {t}" for t, info in sorted(self.topics.items()))
        lost = "; whatever came after the cut is lost" if state == "truncated" else ""
        return (f"{self.path}: {state} bag ({'; '.join(problems) or self.reason}): recovered "
                f"{self.count} complete messages ({per_topic}){lost}")


def _recover(path: Path, files: list[Path], reason: str) -> _PartialBag:
    """Every complete message of a bag rosbags cannot open, with one TruncatedBagWarning; a
    BagError when there is none."""
    bag = _PartialBag(path, files, reason)
    if bag.count == 0:
        raise BagError(path, f"cannot open bag: {reason}; no complete message could be "
                             "recovered") from None
    warnings.warn(bag.describe(), TruncatedBagWarning, stacklevel=1)
    return bag


# --------------------------------------------------------------------------------- writing
def _header(store, stamp_ns: int, frame_id: str):
    Time = store.types["builtin_interfaces/msg/Time"]
    Header = store.types["std_msgs/msg/Header"]
    return Header(stamp=Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000),
                  frame_id=frame_id)


def _image_msg(store, header, array: np.ndarray, encoding: str):
    step, data = image_codec.encode(array, encoding)
    Image = store.types[IMAGE_TYPE]
    return Image(header=header, height=array.shape[0], width=array.shape[1], encoding=encoding,
                 is_bigendian=0, step=step, data=np.frombuffer(data, np.uint8))


def _compressed_msg(store, header, array: np.ndarray, encoding: str, png_level: int):
    fmt, data = image_codec.encode_compressed_depth(array, encoding, png_level=png_level)
    return store.types[COMPRESSED_TYPE](header=header, format=fmt,
                                        data=np.frombuffer(data, np.uint8))


def _info_msg(store, header, info: CameraInfo):
    CI = store.types[INFO_TYPE]
    ROI = store.types["sensor_msgs/msg/RegionOfInterest"]
    K = np.asarray(info.K, float)
    P = np.zeros((3, 4))
    P[:, :3] = K
    return CI(header=header, height=info.height, width=info.width,
              distortion_model=info.distortion_model, d=np.asarray(info.D, float),
              k=K.reshape(-1), r=np.eye(3).reshape(-1), p=P.reshape(-1), binning_x=0,
              binning_y=0, roi=ROI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


class BagWriter:
    """Write depth frames (+ camera info, + labels) to a new rosbag2 bag, atomically.

    with BagWriter("out/bag", encoding="16UC1") as w:
        w.write(stamp_ns, depth_m, labels=labels, camera_info=info)

    `compression`: "zstd" compresses each MCAP chunk (the MCAP format's own chunk compression,
    as rosbag2's MCAP plugin writes it with its zstd presets; depth frames shrink several
    times), "none" writes them as they are; default zstd for MCAP, none for sqlite3, which has
    no chunks to compress.

    `transport`: "raw" writes depth as sensor_msgs/Image on /camera/depth/image_rect_raw;
    "compressedDepth" as image_transport's compressedDepth plugin publishes it, a
    sensor_msgs/CompressedImage (a 16-bit PNG: 16UC1 exact, 32FC1 within
    `image_codec.quantisation_bound`) on /camera/depth/image_rect_raw/compressedDepth, at PNG
    level `png_level` (image_transport's default 9 is the smallest and slowest: on 848 x 480
    RealSense frames about 150 kB in 1.5-2.5 s a frame measured here, level 6 160 kB in 0.1 s,
    level 1 200 kB in 0.02 s).
    """

    def __init__(self, path, encoding: str = "16UC1", storage: str = "mcap",
                 depth_topic: str | None = None, info_topic: str = INFO_TOPIC,
                 labels_topic: str = LABELS_TOPIC, frame_id: str = DEFAULT_FRAME_ID,
                 compression: str | None = None, transport: str = "raw",
                 png_level: int = image_codec.PNG_LEVEL):
        if encoding not in ("16UC1", "32FC1"):
            raise ValueError(f"bag depth encoding {encoding!r} invalid; valid: 16UC1, 32FC1")
        if transport not in TRANSPORTS:
            raise ValueError(f"bag depth transport {transport!r} invalid; valid: "
                             f"{', '.join(TRANSPORTS)}")
        if not 0 <= png_level <= 9:
            raise ValueError(f"PNG level {png_level} invalid; valid: 0 to 9")
        self.transport, self.png_level = transport, png_level
        depth_topic = depth_topic or (DEPTH_TOPIC if transport == "raw" else COMPRESSED_DEPTH_TOPIC)
        if storage not in ("mcap", "sqlite3"):
            raise ValueError(f"bag storage {storage!r} invalid; valid: mcap, sqlite3")
        compression = compression or ("zstd" if storage == "mcap" else "none")
        if compression not in ("none", "zstd"):
            raise ValueError(f"bag compression {compression!r} invalid; valid: none, zstd")
        if compression == "zstd" and storage != "mcap":
            raise ValueError(f"bag compression zstd is MCAP's chunk compression; valid with "
                             f"{storage}: none")
        self.compression = compression
        self.path = Path(path)
        if self.path.exists():
            raise BagError(self.path, "exists already; not overwriting")
        self.encoding, self.storage, self.frame_id = encoding, storage, frame_id
        self.topics = (depth_topic, info_topic, labels_topic)
        self.count = 0
        self._writer = None

    def __enter__(self) -> "BagWriter":
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmpdir = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.partial-",
                                             dir=self.path.parent))
        self._store = _typestore()
        plugin = StoragePlugin.MCAP if self.storage == "mcap" else StoragePlugin.SQLITE3
        self._writer = Writer(self._tmpdir / self.path.name, version=9, storage_plugin=plugin)
        if self.compression == "zstd":
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._writer.open()
        self._conns = {}
        return self

    def _conn(self, topic: str, msgtype: str):
        if topic not in self._conns:
            self._conns[topic] = self._writer.add_connection(topic, msgtype, typestore=self._store)
        return self._conns[topic]

    def write(self, stamp_ns: int, depth_m: np.ndarray, labels: np.ndarray | None = None,
              camera_info: CameraInfo | None = None, frame_id: str | None = None) -> None:
        store, w = self._store, self._writer
        depth_topic, info_topic, labels_topic = self.topics
        header = _header(store, int(stamp_ns), frame_id or self.frame_id)
        raw = image_codec.metres_to_depth(depth_m, self.encoding)
        if camera_info is not None:
            msg = _info_msg(store, header, camera_info)
            w.write(self._conn(info_topic, INFO_TYPE), stamp_ns,
                    store.serialize_cdr(msg, INFO_TYPE))
        if self.transport == "raw":
            msg, msgtype = _image_msg(store, header, raw, self.encoding), IMAGE_TYPE
        else:
            msg = _compressed_msg(store, header, raw, self.encoding, self.png_level)
            msgtype = COMPRESSED_TYPE
        w.write(self._conn(depth_topic, msgtype), stamp_ns, store.serialize_cdr(msg, msgtype))
        if labels is not None:
            msg = _image_msg(store, header, np.asarray(labels, np.uint8), "mono8")
            w.write(self._conn(labels_topic, IMAGE_TYPE), stamp_ns,
                    store.serialize_cdr(msg, IMAGE_TYPE))
        self.count += 1

    def write_camera_info(self, stamp_ns: int, camera_info: CameraInfo,
                          frame_id: str | None = None) -> None:
        """A CameraInfo on its own, e.g. after the image it goes with, as recorders often
        order them."""
        header = _header(self._store, int(stamp_ns), frame_id or self.frame_id)
        self._writer.write(self._conn(self.topics[1], INFO_TYPE), int(stamp_ns),
                           self._store.serialize_cdr(_info_msg(self._store, header, camera_info),
                                                     INFO_TYPE))

    def write_image(self, topic: str, stamp_ns: int, array: np.ndarray, encoding: str,
                    frame_id: str | None = None) -> None:
        """Any other image (a segmentation output, an overlay) on a topic of its own."""
        header = _header(self._store, int(stamp_ns), frame_id or self.frame_id)
        msg = _image_msg(self._store, header, np.asarray(array), encoding)
        self._writer.write(self._conn(topic, IMAGE_TYPE), int(stamp_ns),
                           self._store.serialize_cdr(msg, IMAGE_TYPE))

    def __exit__(self, exc_type, exc, tb):
        try:
            self._writer.close()
            if exc_type is None:
                os.replace(self._tmpdir / self.path.name, self.path)
        finally:
            shutil.rmtree(self._tmpdir, ignore_errors=True)


def write_frames(path, frames: Iterable[DepthFrame | tuple], **kwargs) -> int:
    """Write (stamp_ns, depth_m, labels, camera_info) tuples or DepthFrames; returns the count."""
    with BagWriter(path, **kwargs) as w:
        for f in frames:
            if isinstance(f, DepthFrame):
                w.write(f.stamp_ns, f.metres(), f.labels, f.camera_info, f.frame_id)
            else:
                w.write(*f)
    return w.count
