"""Opening a bag and the first of the converter's two passes, the scan: the stamp, encoding and size of
every image, all force and pose samples, the first camera info of each side. Topics are chosen, frames
paired and the force checked against the video span from the scan, so a bad bag fails before
anything is encoded.

Where the storage allows random access (ROS 1 bags and ROS 2 MCAP storage with uncompressed chunks,
ROS 2 sqlite3 bags; `bag_index`), the scan reads only the first bytes of each image; elsewhere
(compressed chunks or bags) it streams the bag through `rosbags`' iterator."""

from __future__ import annotations

import logging
import re
from array import array
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
import yaml
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.typesys import Stores, get_typestore
from tqdm import tqdm

from vfdata.conversion.bag_index import IndexedBag, open_indexed_bag, ros2_storage
from vfdata.conversion.bag_topics import IMAGE, POSE_STAMPED, RGBD_DEPTH, WRENCH_STAMPED, TopicChoice, topic_types
from vfdata.conversion.image_messages import ImageHead, ImageMessage, image_head
from vfdata.conversion.ros_images import DEPTH_ENCODINGS, RAW_ENCODINGS, UnsupportedImage, compressed_to_bgr
from vfdata.errors import InputError, VisionForceError
from vfdata.mcap_io.cdr import CdrError
from vfdata.recording.messages import (
    MAX_STAMP_NS,
    NS_PER_S,
    CameraInfo,
    decode_stamped_batch,
    stamped_batch_frame_id,
)

log = logging.getLogger(__name__)
_MCAP_MAGIC = b"\x89MCAP0\r\n"


# -- opening -------------------------------------------------------------------------------------
def is_bag(path: str | Path) -> bool:
    """A ROS 1 bag (`.bag` file) or a ROS 2 bag (a folder with metadata.yaml, or one `.db3` or `.mcap`
    storage file of it); also what an unfinished recording leaves (`.bag.active`, a folder of storage
    files without metadata.yaml), for which `open_bag` says what to do."""
    path = Path(path)
    if path.is_dir():
        unfinished = bool(_storage_files(path)) and not (path / "frames.csv").exists()  # frames.csv: a raw folder
        return (path / "metadata.yaml").is_file() or unfinished
    return path.is_file() and (path.suffix in (".bag", ".db3", ".mcap") or path.name.endswith(".bag.active"))


def _storage_files(folder: Path) -> list[Path]:
    """The storage files of a ROS 2 bag folder, found by rosbag2's naming (FOLDER_0.db3, FOLDER_1.db3,
    ...; FOLDER.mcap from other writers), not by metadata.yaml, which a killed recorder may not have
    written. Other MCAP files in a folder (converted recordings) are not storage files."""
    stem = re.compile(rf"{re.escape(folder.name)}(_\d+)?\.(db3|mcap)")
    return sorted(file for file in folder.iterdir() if stem.fullmatch(file.name) and file.is_file())


def _ends_with_mcap_magic(file: Path) -> bool:
    """An MCAP file ends with the magic bytes it starts with; a recorder killed mid-file leaves none."""
    with open(file, "rb") as stream:
        if stream.seek(0, 2) < len(_MCAP_MAGIC):
            return False
        stream.seek(-len(_MCAP_MAGIC), 2)
        return stream.read() == _MCAP_MAGIC


def bag_kind(path: str | Path) -> str:
    return "ROS 1" if Path(path).suffix == ".bag" else "ROS 2"


@contextmanager
def open_bag(path: str | Path) -> Iterator[AnyReader]:
    """`with open_bag(path) as reader:` an open `rosbags` reader. ROS 2 bags recorded without message
    definitions are read with the standard ROS 2 types."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "bag not found")
    if not is_bag(path):
        raise InputError(path, "not a ROS bag (a .bag file, or a ROS 2 bag folder with metadata.yaml)")
    if path.name.endswith(".bag.active"):
        raise InputError(path, "an unfinished ROS 1 bag (rosbag record did not end cleanly) has no index: copy it "
                               "to NAME.bag, run `rosbag reindex NAME.bag` and convert that")
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        raise InputError(path, "a ROS 2 bag folder without metadata.yaml (the recording did not end cleanly?): "
                               "`ros2 bag reindex` writes one, or convert one storage file alone "
                               f"({_storage_files(path)[0].name})")
    try:
        _, files = ros2_storage(path) or ("", [])
    except (OSError, KeyError, TypeError, yaml.YAMLError):
        files = []  # a damaged metadata.yaml: rosbags' error below says so
    for file in files:
        if file.suffix == ".mcap" and not _ends_with_mcap_magic(file):
            raise InputError(file, "the MCAP file stops before its end (the recording did not end cleanly?): "
                                   "`mcap recover` (the mcap CLI) rebuilds it from its complete chunks; convert "
                                   "a copy of the bag with the rebuilt file in its place")
    for wal in _leftover_wals(files):
        log.warning("warning: %s: %s is left beside it (the recording did not end cleanly): messages that are "
                    "only in it, at most the recorder's last batch, are not read", path, wal.name)
    try:
        try:
            reader = AnyReader([path])
            reader.open()
        except AnyReaderError as exc:
            if "no type definitions" not in str(exc):
                raise
            # Loading the standard types takes a while, so only for the bags that need them.
            reader = AnyReader([path], default_typestore=get_typestore(Stores.LATEST))
            reader.open()
    except (AnyReaderError, Ros1ReaderError, Ros2ReaderError, FileNotFoundError, KeyError, ValueError) as exc:
        raise InputError(path, f"cannot read the bag ({_first_line(exc)})") from None
    try:
        yield reader
    finally:
        reader.close()


def _leftover_wals(files: list[Path]) -> list[Path]:
    """The non-empty write-ahead logs (`<file>.db3-wal`) beside these storage files of a ROS 2 bag.

    `ros2 bag record --storage-preset-profile resilient` writes through such a log; sqlite copies it
    into the .db3 after a commit once it passes 1000 pages, and deletes it when the recording ends.
    One left behind means the recorder did not end cleanly, and what it wrote last may be only in the
    log. The bag is read as the .db3 holds it (`rosbags` and our random access both open it
    immutable): reading the log as well would mean writing a shared-memory file beside the bag."""
    wals = [file.with_name(file.name + "-wal") for file in files if file.suffix == ".db3"]
    return [wal for wal in wals if wal.is_file() and wal.stat().st_size > 0]


# -- scanning -------------------------------------------------------------------------------------
def header_stamp_ns(msg) -> int:
    stamp = msg.header.stamp
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def acquisition_ns(header_ns: np.ndarray, receive_ns: np.ndarray) -> tuple[np.ndarray, int]:
    """header.stamp where it is set, the bag receive time where it is 0 -> (stamps, how many fell back)."""
    header_ns = np.asarray(header_ns, dtype=np.int64)
    unset = header_ns == 0
    return np.where(unset, np.asarray(receive_ns, dtype=np.int64), header_ns), int(unset.sum())


@dataclass
class ImageStream:
    """One image topic as scanned: stamps of every message, the look of the first one."""

    topic: str
    msgtype: str
    header_ns: array = field(default_factory=lambda: array("q"))
    receive_ns: array = field(default_factory=lambda: array("q"))
    encoding: str = ""  # Image encoding, or CompressedImage format
    width: int = 0
    height: int = 0
    depth: bool = False  # an RGB-D bag's depth topic (32FC1 metres allowed)

    @property
    def count(self) -> int:
        return len(self.header_ns)

    @property
    def stamps_ns(self) -> np.ndarray:
        return acquisition_ns(np.frombuffer(self.header_ns, np.int64), np.frombuffer(self.receive_ns, np.int64))[0]

    @property
    def fallback_count(self) -> int:
        return int((np.frombuffer(self.header_ns, np.int64) == 0).sum())


@dataclass
class Series:
    """A stamped numeric series (force or pose) sorted by acquisition time, duplicates dropped."""

    topic: str
    stamps_ns: np.ndarray  # (N,) int64
    values: np.ndarray  # (N, 6) fx fy fz tx ty tz (N, N*m), or (N, 7) x y z qx qy qz qw (m)
    frame_id: str
    fallback_count: int = 0
    duplicate_count: int = 0


@dataclass
class BagScan:
    path: Path
    kind: str
    choice: TopicChoice
    counts: dict[str, int]
    receive_ns: dict[str, np.ndarray]  # topic -> bag receive times (every topic scanned)
    left: ImageStream
    right: ImageStream
    force: Series
    pose: Series | None
    left_info: object | None  # the first CameraInfo message of each side (vfdata's or rosbags')
    right_info: object | None
    indexed: IndexedBag | None = None  # random access to the messages, where the storage allows it


def scan_bag(reader: AnyReader, path: Path, choice: TopicChoice, all_topics: bool = False,
             progress: bool = True) -> BagScan:
    """Image stamps, force, pose and the first camera info of each side (and the receive times of every
    topic when `all_topics`, for `inspect-bag`). Where the storage allows random access (ROS 1 bags
    with uncompressed chunks, ROS 2 sqlite3 bags: `bag_index`), the images' pixels are not read here
    and the returned scan keeps that access open for the convert pass (`BagScan.indexed`; close it
    with `close_scan`); otherwise this is one streaming pass over the bag."""
    types = topic_types(reader)
    wanted = {choice.left, choice.right, choice.force, choice.left_info, choice.right_info, choice.pose} - {None}
    topics = set(types) if all_topics else wanted
    counts = {name: info.msgcount for name, info in reader.topics.items()}
    left = ImageStream(choice.left, types[choice.left])
    right = ImageStream(choice.right, types[choice.right], depth=choice.how.get("right") == RGBD_DEPTH)
    images = {choice.left: left, choice.right: right}
    infos = {choice.left_info, choice.right_info} - {None}
    series = {choice.force: _SeriesReader(reader, path, choice.force, 6)}
    if choice.pose is not None:
        series[choice.pose] = _SeriesReader(reader, path, choice.pose, 7)
    indexed = open_indexed_bag(reader, path, topics)
    try:
        with tqdm(total=sum(counts[t] for t in topics), desc=f"scan {path.name}", unit="msg", disable=not progress,
                  mininterval=0.5) as bar:
            if indexed is not None:
                receive, first_infos = _scan_indexed(reader, path, indexed, topics, images, series, infos, bar)
            else:
                receive, first_infos = _scan_streaming(reader, path, topics, images, series, infos, bar)
        for stream in (left, right):
            if stream.count == 0:
                raise InputError(path, f"{stream.topic} has no messages")
            _check_stamps(path, stream.topic, stream.stamps_ns)
        force = series[choice.force].result()
        pose = series[choice.pose].result() if choice.pose is not None else None
        for found in (force, pose):
            if found is not None:
                _check_stamps(path, found.topic, found.stamps_ns, sorted_by_time=True)
        if pose is not None:
            norms = np.linalg.norm(pose.values[:, 3:], axis=1)
            if (norms < 1e-6).any():
                raise InputError(path, f"{choice.pose}: message {int(np.argmax(norms < 1e-6))}: quaternion has "
                                       "zero length")
            pose.values[:, 3:] /= norms[:, None]
    except BaseException:
        if indexed is not None:
            indexed.close()
        raise
    return BagScan(path, bag_kind(path), choice, counts, receive, left, right, force, pose,
                   first_infos.get(choice.left_info), first_infos.get(choice.right_info), indexed)


def _check_stamps(path: Path, topic: str, stamps_ns: np.ndarray, sorted_by_time: bool = False) -> None:
    """Acquisition stamps must lie in ROS 2 time (0 .. 2**31 s): a negative header.stamp (ROS 2's sec
    is signed) or one past 2038 (ROS 1's is unsigned) cannot be written."""
    bad = (stamps_ns < 0) | (stamps_ns > MAX_STAMP_NS)
    if bad.any():
        k = int(np.argmax(bad))
        what = "negative" if stamps_ns[k] < 0 else "beyond ROS 2 time (2**31 s after 1970)"
        where = "a message" if sorted_by_time else f"message {k}"
        raise InputError(path, f"{topic}: {where} has header.stamp {stamps_ns[k]} ns, {what}")


def close_scan(scan: BagScan) -> None:
    """Release the random access a scan kept open (a no-op for a streamed scan)."""
    if scan.indexed is not None:
        scan.indexed.close()
        scan.indexed = None


def _scan_streaming(reader: AnyReader, path: Path, topics: set[str], images: dict[str, ImageStream],
                    series: dict[str, _SeriesReader], infos: set[str], bar: tqdm,
                    ) -> tuple[dict[str, np.ndarray], dict[str, object]]:
    """The scan as one pass over `rosbags`' message iterator: every image is read and deserialised."""
    receive = {t: array("q") for t in topics}
    first_infos: dict[str, object] = {}
    for connection, receive_ns, raw in bag_messages(reader, path, [c for c in reader.connections if c.topic in topics]):
        topic = connection.topic
        receive[topic].append(receive_ns)
        bar.update()
        if topic in series:
            series[topic].add(connection, receive_ns, raw)
        elif topic in images:
            msg = deserialize(reader, path, raw, connection)
            _scan_image(path, images[topic], _head_of(msg), receive_ns, lambda msg=msg: msg)
        elif topic in infos and topic not in first_infos:  # the first message describes the camera
            first_infos[topic] = deserialize(reader, path, raw, connection)
    return {t: np.frombuffer(v, np.int64) for t, v in receive.items()}, first_infos


def _scan_indexed(reader: AnyReader, path: Path, indexed: IndexedBag, topics: set[str],
                  images: dict[str, ImageStream], series: dict[str, _SeriesReader], infos: set[str], bar: tqdm,
                  ) -> tuple[dict[str, np.ndarray], dict[str, object]]:
    """The scan through random access: only the first bytes of each image (stamp, encoding, size), the
    force and pose series in blocks, the first camera info of each side."""
    connection_of = {c.topic: c for c in reader.connections}
    receive = {t: indexed.receive_ns(t) for t in topics}

    def load(topic: str, i: int):
        return deserialize(reader, path, bytes(indexed.message(topic, i)), connection_of[topic])

    for topic, stream in images.items():
        for i, receive_ns in enumerate(receive[topic].tolist()):
            message = partial(load, topic, i)
            head = image_head(indexed.head(topic, i), stream.msgtype, reader.is2)
            _scan_image(path, stream, head or _head_of(message()), receive_ns, message)
        bar.update(len(receive[topic]))
    for topic, reader_of in series.items():
        for receive_ns, payloads in indexed.payload_blocks(topic):
            reader_of.add_block(connection_of[topic], receive_ns, payloads)
            bar.update(len(receive_ns))
    first_infos = {topic: _first_camera_info(reader, path, bytes(indexed.message(topic, 0)), connection_of[topic])
                   for topic in infos if len(receive[topic])}
    return receive, first_infos


def _first_camera_info(reader: AnyReader, path: Path, raw: bytes, connection):
    """A camera info message: a vfdata CameraInfo from little-endian CDR (ROS 2; compiling rosbags'
    deserialiser for this one message cost ~13 ms a bag), else rosbags' message."""
    if reader.is2:
        try:
            return CameraInfo.decode(raw)
        except (CdrError, UnicodeDecodeError, ValueError):
            pass  # e.g. big-endian CDR: rosbags reads it, or says what is wrong
    return deserialize(reader, path, raw, connection)


def bag_messages(reader: AnyReader, path: Path, connections) -> Iterator[tuple[object, int, bytes]]:
    """The reader's messages, with rosbags' errors on a damaged bag turned into one-line InputErrors."""
    if not connections:
        return
    try:
        yield from reader.messages(connections=connections)
    except VisionForceError:
        raise
    except Exception as exc:  # noqa: BLE001 - a damaged bag fails deep in rosbags or its codecs in many ways
        # (a flipped bit: AssertionError, IndexError, LZ4's RuntimeError, struct.error, ...); all are the bag's.
        raise InputError(path, f"damaged bag ({_first_line(exc)})") from None


def deserialize(reader: AnyReader, path: Path, raw: bytes, connection):
    """One raw message through rosbags' deserialiser; a message it cannot read is a one-line InputError."""
    try:
        return reader.deserialize(raw, connection.msgtype)
    except (AnyReaderError, ValueError, IndexError) as exc:
        raise InputError(path, f"{connection.topic}: message cannot be decoded ({_first_line(exc)})") from None


def _head_of(msg) -> ImageHead:
    """The scanned fields of a deserialised Image or CompressedImage message."""
    if hasattr(msg, "encoding"):
        return ImageHead(header_stamp_ns(msg), msg.encoding, int(msg.width), int(msg.height))
    return ImageHead(header_stamp_ns(msg), msg.format)


def image_message_of(msg) -> ImageMessage:
    """`image_messages.image_message` of a deserialised Image or CompressedImage message."""
    data = memoryview(np.ascontiguousarray(msg.data, np.uint8)).cast("B")
    if hasattr(msg, "encoding"):
        return ImageMessage(_head_of(msg), data, int(msg.is_bigendian), int(msg.step))
    return ImageMessage(_head_of(msg), data)


def _scan_image(path: Path, stream: ImageStream, head: ImageHead, receive_ns: int, message: Callable[[], object],
                ) -> None:
    """Record one image message of `stream`; `message()` gives the whole deserialised message, needed
    for a compressed image only (its size is known once decoded)."""
    index = stream.count
    stream.header_ns.append(head.stamp_ns)
    stream.receive_ns.append(receive_ns)
    encoding = head.encoding
    if stream.msgtype == IMAGE:
        width, height = head.width, head.height
        if encoding not in RAW_ENCODINGS and not (stream.depth and encoding in DEPTH_ENCODINGS):
            raise InputError(path, f"{stream.topic}: message {index}: unsupported image encoding '{encoding}' "
                                   f"(supported: {', '.join(RAW_ENCODINGS)})")
    else:
        if index and encoding == stream.encoding:
            return  # decoding every compressed image twice would cost; pass 2 checks each size
        try:
            image = compressed_to_bgr(encoding, message().data)
        except UnsupportedImage as exc:
            raise InputError(path, f"{stream.topic}: message {index}: {exc}") from None
        height, width = image.shape[:2]
    if index == 0:
        stream.encoding, stream.width, stream.height = encoding, width, height
    elif (width, height) != (stream.width, stream.height):
        raise InputError(path, f"{stream.topic}: message {index} is {width}x{height}, the first one "
                               f"{stream.width}x{stream.height}")


def _pose_fields(msg):
    """(position, orientation) of a PoseStamped or TransformStamped message."""
    if hasattr(msg, "pose"):
        return msg.pose.position, msg.pose.orientation
    return msg.transform.translation, msg.transform.rotation


class _SeriesReader:
    """Collects a stamped force or pose series from raw payloads. At 1 kHz the per-message cost
    matters, so messages whose body is the header and then float64s only (WrenchStamped, PoseStamped)
    are decoded a block at a time with numpy when they have one frame_id, the usual case; other
    messages (TransformStamped, changing frame ids) go through rosbags one by one."""

    def __init__(self, reader: AnyReader, path: Path, topic: str, width: int, batch: int = 4096):
        self.reader, self.path, self.topic, self.width, self.batch = reader, path, topic, width, batch
        self.ros2 = reader.is2
        self.header, self.receive, self.values, self.frames = array("q"), array("q"), array("d"), set()
        self._raw: list[bytes] = []
        self._connection = None

    def add(self, connection, receive_ns: int, raw: bytes) -> None:
        """One message, as the streaming scan reads them (decoded `batch` at a time)."""
        self._connection = connection
        self.receive.append(receive_ns)
        self._raw.append(raw)
        if len(self._raw) >= self.batch:
            self._flush()

    def add_block(self, connection, receive_ns: np.ndarray, payloads: np.ndarray | list[bytes]) -> None:
        """A block of messages in bag order: payloads as an (n, L) uint8 array or a list of bytes."""
        self._flush()
        self._connection = connection
        self.receive.frombytes(np.asarray(receive_ns, np.int64).tobytes())
        self._decode(payloads)

    def _flush(self) -> None:
        raws, self._raw = self._raw, []
        if raws:
            self._decode(raws)

    def _decode(self, payloads: np.ndarray | list[bytes]) -> None:
        decoded = None
        # By the connection's type, not a deserialised first message: compiling rosbags' deserialiser
        # for it cost ~8 ms a bag.
        if self._connection.msgtype in (WRENCH_STAMPED, POSE_STAMPED):
            decoded = _decode_fixed_batch(payloads, self.width, self.ros2)
        if decoded is not None:
            stamps, values, frame_id = decoded
            self.header.frombytes(stamps.astype(np.int64).tobytes())
            self.values.frombytes(np.ascontiguousarray(values, np.float64).tobytes())
            self.frames.add(frame_id)
            return
        for raw in payloads:
            msg = deserialize(self.reader, self.path, bytes(raw), self._connection)
            self.header.append(header_stamp_ns(msg))
            if hasattr(msg, "wrench"):
                f, t = msg.wrench.force, msg.wrench.torque
                self.values.extend((f.x, f.y, f.z, t.x, t.y, t.z))
            else:
                p, q = _pose_fields(msg)
                self.values.extend((p.x, p.y, p.z, q.x, q.y, q.z, q.w))
            self.frames.add(msg.header.frame_id)

    def result(self) -> Series:
        """The series sorted by acquisition time, repeated stamps dropped; InputError on NaN."""
        self._flush()
        if len(self.header) == 0:
            raise InputError(self.path, f"{self.topic} has no messages")
        stamps, fallback = acquisition_ns(np.frombuffer(self.header, np.int64), np.frombuffer(self.receive, np.int64))
        table = np.frombuffer(self.values, np.float64).reshape(-1, self.width).copy()
        bad = ~np.isfinite(table).all(axis=1)
        if bad.any():
            raise InputError(self.path, f"{self.topic}: message {int(np.argmax(bad))}: NaN or inf value")
        order = np.argsort(stamps, kind="stable")
        stamps, table = stamps[order], table[order]
        keep = np.concatenate([[True], np.diff(stamps) > 0])
        frames = self.frames - {""}
        frame_id = frames.pop() if len(frames) == 1 else ""
        return Series(self.topic, stamps[keep], table[keep], frame_id, fallback, int((~keep).sum()))


def _decode_fixed_batch(payloads: np.ndarray | list[bytes], n_doubles: int, ros2: bool,
                        ) -> tuple[np.ndarray, np.ndarray, str] | None:
    """Header stamps (N,) and values (N, n_doubles) of messages that are a std_msgs/Header and then
    `n_doubles` float64, all of one length (an (N, L) uint8 array, or a list of bytes), and their one
    frame_id; None when they do not fit that layout."""
    if isinstance(payloads, list):
        if not payloads or any(len(raw) != len(payloads[0]) for raw in payloads):
            return None
        payloads = np.frombuffer(b"".join(payloads), np.uint8).reshape(len(payloads), -1)
    frame_id = stamped_batch_frame_id(payloads)
    if frame_id is None:
        return None
    try:
        stamps, values = decode_stamped_batch(payloads, n_doubles, ros1=not ros2)
    except CdrError:
        return None
    return stamps, values, frame_id


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]
