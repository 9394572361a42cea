"""ROS 1 (`.bag`) and ROS 2 (sqlite3 or MCAP storage) bags -> recording MCAP (layout v1).

Read with the `rosbags` package, so no ROS installation is needed. What is read, with dVRK's usual
topic names as defaults (every one can be remapped, see `BagTopics`):

- stereo images, `sensor_msgs/Image` (bgr8, rgb8, bgra8, rgba8, mono8, mono16, bayer_*8/16, yuv422)
  or `sensor_msgs/CompressedImage` (jpeg, png); left and right paired by stamp;
- camera info from the bag's `sensor_msgs/CameraInfo` topics, or from a calibration file;
- force, `geometry_msgs/WrenchStamped` (ATI NetFT ROS driver `/netft_data`, cisst/SAW ATI component
  `/force_sensor/measured_cf`; auto-detected by type when the defaults are absent);
- ECM pose `/ECM/measured_cp`, `geometry_msgs/PoseStamped` or `TransformStamped`, optional.

Acquisition time is `header.stamp`; a message whose stamp is 0 (header never filled in) takes the
bag's receive time instead, with a warning.

Two steps:
1. scan: the stamp, encoding and size of every image, all force and pose samples, the first camera
   info of each side. Topics are chosen, frames paired and the force checked against the video span
   here, so a bad bag fails before anything is encoded.
2. convert: the two images of each pair, in pair order, deserialised, decoded and JPEG/PNG-encoded
   on a thread pool and written in stamp order with force and pose interleaved, as the folder
   converter does.
Where the storage allows random access (ROS 1 bags with uncompressed chunks, ROS 2 sqlite3 bags;
`bag_index`), the scan reads only the first bytes of each image and the convert step fetches each
image once, directly. Elsewhere (bz2/lz4 chunks, MCAP storage) both steps stream the bag through
`rosbags`' iterator, which reads the images twice."""

from __future__ import annotations

import logging
import re
import struct
from array import array
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import cv2
import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.typesys import Stores, get_typestore
from tqdm import tqdm

from vfdata import __version__
from vfdata.calibration import StereoCalibration
from vfdata.conversion.bag_index import (
    ImageHead,
    ImageMessage,
    IndexedBag,
    image_head,
    image_message,
    open_indexed_bag,
)
from vfdata.conversion.ordered_map import ordered_map
from vfdata.conversion.raw_folder import ConvertOptions, camera_infos, check_force_covers, stereo_tf
from vfdata.errors import InputError
from vfdata.recording import layout
from vfdata.recording.cdr import CdrError
from vfdata.recording.messages import (
    CameraInfo,
    CompressedImage,
    PoseStamped,
    TFMessage,
    TransformStamped,
    WrenchStamped,
    decode_pose_batch,
    decode_wrench_batch,
)
from vfdata.recording.writer import IMAGE_LEVEL, McapWriter

log = logging.getLogger(__name__)

_NS = 1_000_000_000
_STAMP = struct.Struct("<iI")  # header.stamp in CDR: int32 sec, uint32 nanosec
_U32 = struct.Struct("<I")

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
WRENCH_STAMPED = "geometry_msgs/msg/WrenchStamped"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)
POSE_TYPES = (POSE_STAMPED, TRANSFORM_STAMPED)

# dVRK defaults, in order of preference. Raw images before compressed ones: they are lossless.
LEFT_IMAGE_DEFAULTS = ("/jhu_daVinci/left/image_raw", "/jhu_daVinci/left/image_raw/compressed")
RIGHT_IMAGE_DEFAULTS = ("/jhu_daVinci/right/image_raw", "/jhu_daVinci/right/image_raw/compressed")
# ATI NetFT ROS driver (netft_rdt_driver / netft_utils) and the cisst/SAW ATI force sensor component.
FORCE_DEFAULTS = ("/netft_data", "/netft/netft_data", "/force_sensor/measured_cf", "/ati/measured_cf")
# dVRK 2.x CRTK name, the same under a namespace, and the dVRK 1.x name.
POSE_DEFAULTS = ("/ECM/measured_cp", "/dvrk/ECM/measured_cp", "/dvrk/ECM/position_cartesian_current")
# dVRK arms publish wrenches estimated from joint torques (e.g. /PSM1/body/measured_cf): never the
# force sensor, so auto-detection skips them.
DVRK_ARM_NAMESPACES = ("PSM1", "PSM2", "PSM3", "ECM", "MTML", "MTMR", "SUJ")
# Names that say "force sensor": netft anywhere, or ati / ft / force_sensor as a whole name part.
_SENSOR_NAME = re.compile(r"netft|(^|[/_])(ati|ft|force_sensor|ft_sensor|force_torque)([/_]|$)", re.IGNORECASE)
NO_TOPIC = "none"  # `--pose-topic none`: leave the ECM pose out

# sensor_msgs/Image encodings: name -> (channels, bytes per channel).
RAW_ENCODINGS: dict[str, tuple[int, int]] = {
    "bgr8": (3, 1), "rgb8": (3, 1), "bgra8": (4, 1), "rgba8": (4, 1), "mono8": (1, 1),
    "8UC1": (1, 1), "8UC3": (3, 1), "8UC4": (4, 1),
    "bgr16": (3, 2), "rgb16": (3, 2), "mono16": (1, 2), "16UC1": (1, 2),
    "bayer_rggb8": (1, 1), "bayer_bggr8": (1, 1), "bayer_gbrg8": (1, 1), "bayer_grbg8": (1, 1),
    "bayer_rggb16": (1, 2), "bayer_bggr16": (1, 2), "bayer_gbrg16": (1, 2), "bayer_grbg16": (1, 2),
    "yuv422": (2, 1), "uyvy": (2, 1), "yuv422_yuy2": (2, 1), "yuyv": (2, 1),
}
# To BGR. ROS bayer_rggb8 names the first 2x2 block, as OpenCV's RGGB-style codes do (its older
# BG-style names for the same codes describe the second row; cv_bridge uses those).
_COLOR_CODES = {
    "rgb": cv2.COLOR_RGB2BGR, "bgra": cv2.COLOR_BGRA2BGR, "rgba": cv2.COLOR_RGBA2BGR, "mono": cv2.COLOR_GRAY2BGR,
    "bayer_rggb": cv2.COLOR_BayerRGGB2BGR, "bayer_bggr": cv2.COLOR_BayerBGGR2BGR,
    "bayer_gbrg": cv2.COLOR_BayerGBRG2BGR, "bayer_grbg": cv2.COLOR_BayerGRBG2BGR,
    "uyvy": cv2.COLOR_YUV2BGR_UYVY, "yuyv": cv2.COLOR_YUV2BGR_YUY2,
}
_ENCODING_FAMILY = {
    "rgb8": "rgb", "rgb16": "rgb", "bgra8": "bgra", "8UC4": "bgra", "rgba8": "rgba",
    "mono8": "mono", "8UC1": "mono", "mono16": "mono", "16UC1": "mono",
    "yuv422": "uyvy", "uyvy": "uyvy", "yuv422_yuy2": "yuyv", "yuyv": "yuyv",
    **{f"bayer_{p}{b}": f"bayer_{p}" for p in ("rggb", "bggr", "gbrg", "grbg") for b in (8, 16)},
}


class UnsupportedImage(ValueError):
    """An image message this converter cannot turn into BGR pixels (the caller names the topic)."""


# -- opening and choosing topics ------------------------------------------------------------------
def is_bag(path: str | Path) -> bool:
    """A ROS 1 bag (`.bag` file) or a ROS 2 bag (a folder with metadata.yaml, or one `.db3` or `.mcap`
    storage file of it)."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.is_file() and path.suffix in (".bag", ".db3", ".mcap")


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


@dataclass(frozen=True)
class BagTopics:
    """Topics asked for on the command line; None means the dVRK default or auto-detection.
    `pose = "none"` leaves the ECM pose out."""

    left: str | None = None
    right: str | None = None
    left_info: str | None = None
    right_info: str | None = None
    force: str | None = None
    pose: str | None = None


@dataclass
class TopicChoice:
    """The topics a conversion reads, each with how it was chosen (for `inspect-bag`)."""

    left: str
    right: str
    left_info: str | None
    right_info: str | None
    force: str
    pose: str | None
    how: dict[str, str] = field(default_factory=dict)


def topic_types(reader: AnyReader) -> dict[str, str]:
    """Topic -> message type (ROS 2 style names, e.g. sensor_msgs/msg/Image, for both bag kinds)."""
    return {name: info.msgtype or "(mixed types)" for name, info in sorted(reader.topics.items())}


def choose_topics(path: Path, types: dict[str, str], asked: BagTopics, use_camera_info: bool = True) -> TopicChoice:
    """Resolve the topics to read: given ones are checked, missing ones defaulted or auto-detected.
    Raises InputError (naming the bag) when a required topic cannot be found."""
    how: dict[str, str] = {}
    left, right = _choose_images(path, types, asked, how)
    left_info = right_info = None
    if use_camera_info:
        left_info = _choose_info(path, types, asked.left_info, left, "left", "--left-info-topic", how)
        right_info = _choose_info(path, types, asked.right_info, right, "right", "--right-info-topic", how)
    force = _choose_force(path, types, asked.force, how)
    pose = _choose_pose(path, types, asked.pose, how)
    return TopicChoice(left, right, left_info, right_info, force, pose, how)


def _check_given(path: Path, types: dict[str, str], topic: str, allowed: tuple[str, ...], option: str) -> str:
    if topic not in types:
        raise InputError(path, f"{option} {topic}: no such topic in the bag")
    if types[topic] not in allowed:
        raise InputError(path, f"{option} {topic} is {types[topic]}, expected {' or '.join(allowed)}")
    return topic


def _choose_images(path: Path, types: dict[str, str], asked: BagTopics, how: dict[str, str]) -> tuple[str, str]:
    if asked.left:
        left = _check_given(path, types, asked.left, IMAGE_TYPES, "--left-topic")
        how["left"] = "given"
    if asked.right:
        right = _check_given(path, types, asked.right, IMAGE_TYPES, "--right-topic")
        how["right"] = "given"
    if asked.left and not asked.right:
        right = _swap_side(left, "left", "right")
        if right is None or types.get(right) not in IMAGE_TYPES:
            raise InputError(path, f"no right image topic beside {left}; pass --right-topic")
        how["right"] = "matches --left-topic"
    elif asked.right and not asked.left:
        left = _swap_side(right, "right", "left")
        if left is None or types.get(left) not in IMAGE_TYPES:
            raise InputError(path, f"no left image topic beside {right}; pass --left-topic")
        how["left"] = "matches --right-topic"
    elif not asked.left and not asked.right:
        for left_default, right_default in zip(LEFT_IMAGE_DEFAULTS, RIGHT_IMAGE_DEFAULTS, strict=True):
            if types.get(left_default) in IMAGE_TYPES and types.get(right_default) in IMAGE_TYPES:
                left, right = left_default, right_default
                how["left"] = how["right"] = "dVRK default"
                break
        else:
            left, right = _detect_image_pair(path, types)
            how["left"] = how["right"] = "auto-detected"
    if left == right:
        raise InputError(path, f"left and right image topics are the same ({left})")
    return left, right


def _swap_side(topic: str, side: str, other: str) -> str | None:
    return topic.replace(side, other) if side in topic else None


def _detect_image_pair(path: Path, types: dict[str, str]) -> tuple[str, str]:
    """The image topics that differ only by left/right. Raw before compressed, unrectified before
    rectified (the camera info describes the raw images), then the shortest name."""
    images = [t for t, kind in types.items() if kind in IMAGE_TYPES]
    if not images:
        raise InputError(path, "no image topic found (no sensor_msgs/Image or sensor_msgs/CompressedImage)")
    pairs = []
    for left in images:
        if "left" in left:
            right = left.replace("left", "right")
            if right in images:
                pairs.append((types[left] == COMPRESSED_IMAGE, "rect" in left, len(left), left, right))
    if not pairs:
        raise InputError(path, f"no left/right image topic pair found among {', '.join(images)}; "
                               "pass --left-topic and --right-topic")
    pairs.sort()
    if len(pairs) > 1:
        log.warning("warning: %s: several stereo image topics; using %s and %s (others: %s)", path,
                    pairs[0][3], pairs[0][4], ", ".join(p[3] for p in pairs[1:]))
    return pairs[0][3], pairs[0][4]


def camera_info_topic(image_topic: str) -> str:
    """The CameraInfo topic ROS publishes beside an image topic: /ns/left/image_raw[/compressed] ->
    /ns/left/camera_info."""
    base = re.sub(r"/(compressed|theora|ffmpeg|h264)$", "", image_topic)
    return base.rsplit("/", 1)[0] + "/camera_info"


def _choose_info(path: Path, types: dict[str, str], asked: str | None, image_topic: str, side: str,
                 option: str, how: dict[str, str]) -> str | None:
    if asked:
        how[f"{side}_info"] = "given"
        return _check_given(path, types, asked, (CAMERA_INFO,), option)
    beside = camera_info_topic(image_topic)
    if types.get(beside) == CAMERA_INFO:
        how[f"{side}_info"] = "beside the image topic"
        return beside
    candidates = [t for t, kind in types.items() if kind == CAMERA_INFO and side in t]
    if len(candidates) == 1:
        how[f"{side}_info"] = "auto-detected"
        return candidates[0]
    return None


def _choose_force(path: Path, types: dict[str, str], asked: str | None, how: dict[str, str]) -> str:
    if asked:
        how["force"] = "given"
        return _check_given(path, types, asked, (WRENCH_STAMPED,), "--force-topic")
    for topic in FORCE_DEFAULTS:
        if types.get(topic) == WRENCH_STAMPED:
            how["force"] = "default"
            return topic
    wrenches = [t for t, kind in types.items() if kind == WRENCH_STAMPED]
    not_arms = [t for t in wrenches if not set(t.strip("/").split("/")) & set(DVRK_ARM_NAMESPACES)]
    sensor_like = [t for t in not_arms if _SENSOR_NAME.search(t)]
    for tier in (sensor_like, not_arms):
        if len(tier) == 1:
            how["force"] = "auto-detected (the only force sensor WrenchStamped topic)"
            return tier[0]
        if len(tier) > 1:
            raise InputError(path, f"several WrenchStamped topics could be the force sensor ({', '.join(tier)}); "
                                   "pick one with --force-topic")
    if wrenches:
        raise InputError(path, f"no force sensor topic: the WrenchStamped topics ({', '.join(wrenches)}) are dVRK "
                               "arm estimates; pass --force-topic to use one anyway")
    raise InputError(path, f"no force topic: no geometry_msgs/WrenchStamped topic (looked for "
                           f"{', '.join(FORCE_DEFAULTS)}); pass --force-topic")


def _choose_pose(path: Path, types: dict[str, str], asked: str | None, how: dict[str, str]) -> str | None:
    if asked == NO_TOPIC:
        how["pose"] = "left out (--pose-topic none)"
        return None
    if asked:
        how["pose"] = "given"
        return _check_given(path, types, asked, POSE_TYPES, "--pose-topic")
    for topic in POSE_DEFAULTS:
        if types.get(topic) in POSE_TYPES:
            how["pose"] = "dVRK default"
            return topic
    namespaced = [t for t, kind in types.items() if kind in POSE_TYPES and t.endswith("/ECM/measured_cp")]
    if len(namespaced) == 1:
        how["pose"] = "auto-detected"
        return namespaced[0]
    how["pose"] = "none found (the recording will have no ECM pose)"
    return None


# -- scanning -------------------------------------------------------------------------------------
def header_stamp_ns(msg) -> int:
    stamp = msg.header.stamp
    return int(stamp.sec) * _NS + int(stamp.nanosec)


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
    left, right = ImageStream(choice.left, types[choice.left]), ImageStream(choice.right, types[choice.right])
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
        force = series[choice.force].result()
        pose = series[choice.pose].result() if choice.pose is not None else None
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
            msg = _deserialize(reader, path, raw, connection)
            _scan_image(path, images[topic], _head_of(msg), receive_ns, lambda msg=msg: msg)
        elif topic in infos and topic not in first_infos:  # the first message describes the camera
            first_infos[topic] = _deserialize(reader, path, raw, connection)
    return {t: np.frombuffer(v, np.int64) for t, v in receive.items()}, first_infos


def _scan_indexed(reader: AnyReader, path: Path, indexed: IndexedBag, topics: set[str],
                  images: dict[str, ImageStream], series: dict[str, _SeriesReader], infos: set[str], bar: tqdm,
                  ) -> tuple[dict[str, np.ndarray], dict[str, object]]:
    """The scan through random access: only the first bytes of each image (stamp, encoding, size), the
    force and pose series in blocks, the first camera info of each side."""
    connection_of = {c.topic: c for c in reader.connections}
    receive = {t: indexed.receive_ns(t) for t in topics}

    def load(topic: str, i: int):
        return _deserialize(reader, path, bytes(indexed.message(topic, i)), connection_of[topic])

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
    return _deserialize(reader, path, raw, connection)


def bag_messages(reader: AnyReader, path: Path, connections) -> Iterator[tuple[object, int, bytes]]:
    """The reader's messages, with rosbags' errors on a damaged bag turned into one-line InputErrors."""
    if not connections:
        return
    try:
        yield from reader.messages(connections=connections)
    except (AnyReaderError, Ros1ReaderError, Ros2ReaderError) as exc:
        raise InputError(path, f"damaged bag ({_first_line(exc)})") from None


def _deserialize(reader: AnyReader, path: Path, raw: bytes, connection):
    try:
        return reader.deserialize(raw, connection.msgtype)
    except (AnyReaderError, ValueError, IndexError) as exc:
        raise InputError(path, f"{connection.topic}: message cannot be decoded ({_first_line(exc)})") from None


def _head_of(msg) -> ImageHead:
    """The scanned fields of a deserialised Image or CompressedImage message."""
    if hasattr(msg, "encoding"):
        return ImageHead(header_stamp_ns(msg), msg.encoding, int(msg.width), int(msg.height))
    return ImageHead(header_stamp_ns(msg), msg.format)


def _image_message_of(msg) -> ImageMessage:
    """`bag_index.image_message` of a deserialised Image or CompressedImage message."""
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
        if encoding not in RAW_ENCODINGS:
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
            msg = _deserialize(self.reader, self.path, bytes(raw), self._connection)
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
        length = len(payloads[0])
        if any(len(raw) != length for raw in payloads):
            return None
        table = np.frombuffer(b"".join(payloads), np.uint8).reshape(len(payloads), length)
    else:
        table = payloads
    count, length = table.shape
    # One frame_id for the whole block (its length and bytes after the stamp), as the caller assumes.
    name_length = int(table[0, 12:16].copy().view("<u4")[0]) if length >= 16 else 0
    name = slice(12, 16 + name_length)
    if length < 16 or 16 + name_length > length or (table[:, name] != table[0, name]).any():
        return None
    try:  # CDR strings end with a NUL that ROS 1 strings do not have
        frame_id = table[0, 16:16 + name_length].tobytes().rstrip(b"\0").decode("utf-8")
    except UnicodeDecodeError:
        return None
    if ros2:
        try:
            stamps, values = (decode_wrench_batch if n_doubles == 6 else decode_pose_batch)(table)
        except CdrError:
            return None
        return stamps, values, frame_id
    # ROS 1: uint32 seq, uint32 sec, uint32 nsec, uint32 length + frame_id, float64s (no alignment).
    if 16 + name_length + 8 * n_doubles != length:
        return None
    sec = table[:, 4:8].copy().view("<u4").ravel().astype(np.int64)
    nanosec = table[:, 8:12].copy().view("<u4").ravel().astype(np.int64)
    values = table[:, 16 + name_length:].copy().view("<f8").reshape(count, n_doubles)
    return sec * _NS + nanosec, values, frame_id


# -- pairing --------------------------------------------------------------------------------------
def default_pair_tolerance_ns(stamps_ns: np.ndarray) -> int:
    """Half the median frame period of a stream (0 for fewer than two distinct stamps)."""
    steps = np.diff(np.unique(stamps_ns))
    return int(np.median(steps)) // 2 if len(steps) else 0


def pair_stamps(left_ns: np.ndarray, right_ns: np.ndarray, tolerance_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Pair left and right frames by stamp: each left frame with its nearest right frame, kept when
    that right frame's nearest left frame is the same one (mutual nearest neighbours) and the two
    stamps are at most `tolerance_ns` apart. Stamps need not be sorted. Returns the indices
    (left_i, right_i) of the pairs, ordered by left stamp; each frame is in at most one pair."""
    left_ns, right_ns = np.asarray(left_ns, np.int64), np.asarray(right_ns, np.int64)
    if len(left_ns) == 0 or len(right_ns) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    lo, ro = np.argsort(left_ns, kind="stable"), np.argsort(right_ns, kind="stable")
    ls, rs = left_ns[lo], right_ns[ro]
    to_right, to_left = _nearest(ls, rs), _nearest(rs, ls)
    keep = (to_left[to_right] == np.arange(len(ls))) & (np.abs(ls - rs[to_right]) <= tolerance_ns)
    return lo[keep], ro[to_right[keep]]


def _nearest(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each value of sorted `a`, the index of the nearest value in sorted `b` (ties: the earlier)."""
    pos = np.clip(np.searchsorted(b, a), 1, len(b) - 1) if len(b) > 1 else np.zeros(len(a), np.int64)
    if len(b) > 1:
        earlier = np.abs(a - b[pos - 1]) <= np.abs(b[pos] - a)
        pos = np.where(earlier, pos - 1, pos)
    return pos


@dataclass
class PairPlan:
    """The stereo frames of the recording: pair k has stamp `stamps_ns[k]` (the left frame's) and is
    made of the left and right messages whose acquisition stamps are given."""

    stamps_ns: np.ndarray  # (K,) strictly increasing
    left_ns: np.ndarray
    right_ns: np.ndarray
    tolerance_ns: int
    unpaired_left: int
    unpaired_right: int
    left_index: np.ndarray | None = None  # (K,) position of each pair's messages in their topic (bag order)
    right_index: np.ndarray | None = None

    @property
    def max_offset_ns(self) -> int:
        return int(np.abs(self.left_ns - self.right_ns).max()) if len(self.stamps_ns) else 0


def plan_pairs(scan: BagScan, tolerance_ns: int | None = None) -> PairPlan:
    """Pair the scanned frames; InputError when no frame pairs."""
    left_ns, right_ns = scan.left.stamps_ns, scan.right.stamps_ns
    if tolerance_ns is None:
        tolerance_ns = default_pair_tolerance_ns(left_ns)
    li, ri = pair_stamps(left_ns, right_ns, tolerance_ns)
    if len(li) == 0:
        raise InputError(
            scan.path, f"left and right images never pair within {tolerance_ns / 1e6:.1f} ms ({scan.left.topic} "
            f"stamps {_span(left_ns)}, {scan.right.topic} stamps {_span(right_ns)}); check the topics or "
            "--pair-tolerance-ms",
        )
    return PairPlan(left_ns[li], left_ns[li], right_ns[ri], int(tolerance_ns),
                    len(left_ns) - len(li), len(right_ns) - len(ri), li, ri)


def _span(stamps: np.ndarray) -> str:
    return f"{stamps.min() / 1e9:.3f}..{stamps.max() / 1e9:.3f} s" if len(stamps) else "none"


# -- camera model ---------------------------------------------------------------------------------
def bag_camera_info(path: Path, topic: str, msg, frame_id: str) -> CameraInfo:
    """A CameraInfo message (a vfdata CameraInfo, or rosbags' with ROS 1 names D K R P or ROS 2 names
    d k r p) in the layout's frame."""

    def values(name: str) -> np.ndarray:
        return np.asarray(getattr(msg, name) if hasattr(msg, name) else getattr(msg, name.upper()), np.float64)

    if isinstance(msg, CameraInfo):
        roi = msg.roi
    else:
        roi = (int(msg.roi.x_offset), int(msg.roi.y_offset), int(msg.roi.height), int(msg.roi.width),
               bool(msg.roi.do_rectify))
    info = CameraInfo(
        0, frame_id, int(msg.height), int(msg.width), msg.distortion_model or "plumb_bob", values("d"),
        values("k").reshape(3, 3), values("r").reshape(3, 3), values("p").reshape(3, 4),
        int(msg.binning_x), int(msg.binning_y), roi,
    )
    if not (np.isfinite(info.p).all() and info.p[0, 0] > 0 and info.p[1, 1] > 0):
        raise InputError(path, f"{topic}: P has no focal length (camera not calibrated); pass --calibration FILE")
    return info


def camera_model(scan: BagScan, calibration: StereoCalibration | None, calibration_path: Path | None,
                 ) -> tuple[CameraInfo, CameraInfo, TFMessage, str]:
    """Camera infos and the left -> right transform, from the calibration file when given, else from
    the bag's CameraInfo topics -> (left, right, tf, where from). Checks the image size."""
    size = (scan.left.width, scan.left.height)
    if (scan.right.width, scan.right.height) != size:
        raise InputError(scan.path, f"left images are {size[0]}x{size[1]}, right images "
                                    f"{scan.right.width}x{scan.right.height}")
    if calibration is not None:
        if (calibration.width, calibration.height) != size:
            raise InputError(calibration_path, f"image size {calibration.width}x{calibration.height} differs from "
                                               f"the bag's images ({size[0]}x{size[1]})")
        left, right = camera_infos(calibration, 0)
        return left, right, stereo_tf(calibration, 0), f"calibration file {calibration_path}"
    choice = scan.choice
    for side, topic, msg in (("left", choice.left_info, scan.left_info), ("right", choice.right_info, scan.right_info)):
        if topic is None:
            raise InputError(scan.path, f"no {side} camera_info topic (looked for "
                                        f"{camera_info_topic(getattr(choice, side))}); pass --{side}-info-topic "
                                        "or --calibration FILE")
        if msg is None:
            raise InputError(scan.path, f"{topic} has no messages; pass --calibration FILE")
    left = bag_camera_info(scan.path, choice.left_info, scan.left_info, layout.LEFT_FRAME)
    right = bag_camera_info(scan.path, choice.right_info, scan.right_info, layout.RIGHT_FRAME)
    for topic, info in ((choice.left_info, left), (choice.right_info, right)):
        if (info.width, info.height) != size:
            raise InputError(scan.path, f"{topic} is for {info.width}x{info.height} images, the images are "
                                        f"{size[0]}x{size[1]}")
    # ROS: right P[0, 3] = -fx * baseline (m); the right camera sits `baseline` along +x of the left one.
    baseline_m = -right.p[0, 3] / right.p[0, 0]
    if not baseline_m > 0:
        raise InputError(scan.path, f"{choice.right_info}: P[0,3] = {right.p[0, 3]:g} gives no stereo baseline "
                                    "(monocular calibrations?); pass --calibration FILE")
    tf = TFMessage([TransformStamped(0, layout.LEFT_FRAME, layout.RIGHT_FRAME, (baseline_m, 0.0, 0.0),
                                     (0.0, 0.0, 0.0, 1.0))])
    return left, right, tf, f"camera_info topics {choice.left_info}, {choice.right_info}"


# -- images ---------------------------------------------------------------------------------------
def raw_image_to_bgr(height: int, width: int, encoding: str, is_bigendian: int, step: int,
                     data: np.ndarray | bytes) -> np.ndarray:
    """sensor_msgs/Image fields -> (height, width, 3) BGR uint8. 16-bit values are scaled to 8 bits
    over their full range (v * 255 / 65535); Bayer mosaics are demosaiced (bilinear)."""
    if encoding not in RAW_ENCODINGS:
        raise UnsupportedImage(f"unsupported image encoding '{encoding}'")
    channels, depth = RAW_ENCODINGS[encoding]
    row_bytes = width * channels * depth
    buffer = np.frombuffer(data, np.uint8) if not isinstance(data, np.ndarray) else data.view(np.uint8).ravel()
    if step < row_bytes or len(buffer) < step * (height - 1) + row_bytes:
        raise UnsupportedImage(f"{encoding} image of {width}x{height} needs {row_bytes} bytes a row, "
                               f"has step {step} and {len(buffer)} bytes")
    if len(buffer) < step * height:  # the last row may lack its padding
        buffer = np.concatenate([buffer, np.zeros(step * height - len(buffer), np.uint8)])
    rows = buffer[: step * height].reshape(height, step)[:, :row_bytes]
    if depth == 2:
        pixels = np.ascontiguousarray(rows).view(">u2" if is_bigendian else "<u2").astype(np.uint16)
        pixels = ((pixels.astype(np.uint32) * 255 + 32767) // 65535).astype(np.uint8)
    else:
        pixels = rows
    family = _ENCODING_FAMILY.get(encoding)
    if family in ("uyvy", "yuyv"):
        image = pixels.reshape(height, width, 2)
    else:
        image = pixels.reshape(height, width, channels) if channels > 1 else pixels.reshape(height, width)
    image = np.ascontiguousarray(image)
    if family is None:  # bgr8, 8UC3, bgr16
        return image
    return cv2.cvtColor(image, _COLOR_CODES[family])


def compressed_format(fmt: str) -> str:
    """The codec of a CompressedImage `format` ('jpeg', 'png', or image_transport's 'rgb8; jpeg
    compressed bgr8') -> 'jpeg' or 'png'."""
    text = fmt.lower()
    if "compresseddepth" in text:
        raise UnsupportedImage(f"unsupported image format '{fmt}' (compressedDepth is a depth image)")
    if "jpeg" in text or "jpg" in text:
        return "jpeg"
    if "png" in text:
        return "png"
    raise UnsupportedImage(f"unsupported image format '{fmt}' (expected jpeg or png)")


def compressed_to_bgr(fmt: str, data: np.ndarray | bytes) -> np.ndarray:
    """CompressedImage data -> BGR uint8 (image_transport compresses colour images as bgr8)."""
    compressed_format(fmt)
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise UnsupportedImage(f"{fmt} image data cannot be decoded")
    return image


# -- conversion -----------------------------------------------------------------------------------
def convert_bag(src: str | Path, out: str | Path, overwrite: bool = False, options: ConvertOptions | None = None,
                topics: BagTopics | None = None, calibration: str | Path | None = None,
                pair_tolerance_ns: int | None = None) -> Path:
    """Convert a ROS 1 or ROS 2 bag to a recording MCAP at `out`. Returns `out`.

    `topics`: remapped topic names (None: dVRK defaults / auto-detection). `calibration`: a
    calibration.yaml used instead of the bag's CameraInfo topics. `pair_tolerance_ns`: largest
    left/right stamp difference of a stereo pair (default half the median left frame period)."""
    options = options or ConvertOptions()
    src, out = Path(src), Path(out)
    if options.image_format not in ("jpeg", "png"):
        raise InputError(out, f"image format must be jpeg or png, not {options.image_format}")
    calib = StereoCalibration.load(calibration) if calibration is not None else None
    with open_bag(src) as reader:
        choice = choose_topics(src, topic_types(reader), topics or BagTopics(), use_camera_info=calib is None)
        scan = scan_bag(reader, src, choice, progress=options.progress)
        try:
            _convert_scanned(reader, src, out, overwrite, options, scan, choice, calib, calibration, pair_tolerance_ns)
        finally:
            close_scan(scan)
    return out


def _convert_scanned(reader: AnyReader, src: Path, out: Path, overwrite: bool, options: ConvertOptions, scan: BagScan,
                     choice: TopicChoice, calib: StereoCalibration | None, calibration: str | Path | None,
                     pair_tolerance_ns: int | None) -> None:
    """Everything after the scan: pairing, checks, metadata, the convert pass."""
    plan = plan_pairs(scan, pair_tolerance_ns)
    info_l, info_r, tf, camera_source = camera_model(scan, calib, Path(calibration) if calibration else None)
    check_force_span(scan, plan, options.force_gap_tolerance_ns)
    _warn_about(scan, plan)
    record = layout.RecordingMeta(
        recording_id=src.stem if src.is_file() else src.name,
        source=str(src.resolve()),
        converter=f"vfdata convert ({scan.kind} bag)",
        converter_version=__version__,
        extra={
            "bag_left_topic": choice.left, "bag_right_topic": choice.right,
            "bag_force_topic": choice.force, "bag_pose_topic": choice.pose or "",
            "bag_force_frame_id": scan.force.frame_id,
            "bag_pose_frame_id": scan.pose.frame_id if scan.pose else "",
            "camera_info_source": camera_source,
            "pair_tolerance_ns": str(plan.tolerance_ns),
            "pair_max_offset_ns": str(plan.max_offset_ns),
            "unpaired_left_frames": str(plan.unpaired_left),
            "unpaired_right_frames": str(plan.unpaired_right),
        },
    )
    _write(reader, scan, plan, out, overwrite, options, record, info_l, info_r, tf)


def check_force_span(scan: BagScan, plan: PairPlan, tolerance_ns: int) -> None:
    force_ns, frame_ns = scan.force.stamps_ns, plan.stamps_ns
    if force_ns[-1] < frame_ns[0] or force_ns[0] > frame_ns[-1]:
        raise InputError(scan.path, f"{scan.force.topic}: force stamps {_span(force_ns)} lie outside the video "
                                    f"span {_span(frame_ns)} (different clocks?)")
    try:
        check_force_covers(scan.path, force_ns, frame_ns, tolerance_ns)
    except InputError as exc:
        raise InputError(scan.path, f"{scan.force.topic}: {exc.problem}") from None


def _warn_about(scan: BagScan, plan: PairPlan) -> None:
    for topic, count, total in (
        (scan.left.topic, scan.left.fallback_count, scan.left.count),
        (scan.right.topic, scan.right.fallback_count, scan.right.count),
        (scan.force.topic, scan.force.fallback_count, len(scan.force.stamps_ns)),
        *([(scan.pose.topic, scan.pose.fallback_count, len(scan.pose.stamps_ns))] if scan.pose else []),
    ):
        if count:
            log.warning("warning: %s: %s: %d of %d messages have header.stamp 0; using the bag receive time",
                        scan.path, topic, count, total)
    for series in (scan.force, scan.pose):
        if series is not None and series.duplicate_count:
            log.warning("warning: %s: %s: %d messages repeat an earlier stamp; kept the first", scan.path,
                        series.topic, series.duplicate_count)
    if plan.unpaired_left or plan.unpaired_right:
        log.warning("warning: %s: %d left and %d right frames have no partner within %.1f ms; left out",
                    scan.path, plan.unpaired_left, plan.unpaired_right, plan.tolerance_ns / 1e6)
    if scan.pose is not None and (scan.pose.stamps_ns[-1] < plan.stamps_ns[0]
                                  or scan.pose.stamps_ns[0] > plan.stamps_ns[-1]):
        log.warning("warning: %s: %s: pose stamps %s lie outside the video span %s", scan.path, scan.pose.topic,
                    _span(scan.pose.stamps_ns), _span(plan.stamps_ns))


def _stereo_messages(reader: AnyReader, scan: BagScan, plan: PairPlan,
                     ) -> Iterator[tuple[int, Callable[[], bytes | memoryview], Callable[[], bytes | memoryview]]]:
    """(k, left message, right message) for every pair of the plan, in pair order, each message as a
    function that returns it serialised: with random access, it is fetched when called, in the
    encoding thread that encodes it (a ROS 2 image is copied out of sqlite there, where the encoder
    then finds it in its core's cache)."""
    if scan.indexed is not None:
        indexed, left, right = scan.indexed, scan.left.topic, scan.right.topic
        for k, (i, j) in enumerate(zip(plan.left_index.tolist(), plan.right_index.tolist(), strict=True)):
            yield k, partial(indexed.message, left, i), partial(indexed.message, right, j)
        return
    # Streaming the bag: a message is found by its acquisition stamp; one waits in memory only until
    # its partner (and the pairs before it) have been read, a frame or two in a normal bag.
    wanted = ({int(t): k for k, t in enumerate(plan.left_ns)}, {int(t): k for k, t in enumerate(plan.right_ns)})
    side_of = {scan.left.topic: 0, scan.right.topic: 1}
    connections = [c for c in reader.connections if c.topic in side_of]
    pending: dict[int, list] = {}
    next_k = 0
    for connection, receive_ns, raw in bag_messages(reader, scan.path, connections):
        side = side_of[connection.topic]
        stamp = header_stamp_ns(_deserialize(reader, scan.path, raw, connection)) or receive_ns
        k = wanted[side].pop(stamp, None)
        if k is None:
            continue  # unpaired, or a repeated stamp whose first message was taken
        slot = pending.setdefault(k, [None, None])
        slot[side] = raw
        while next_k in pending and None not in pending[next_k]:
            left, right = pending.pop(next_k)
            yield next_k, partial(_same, left), partial(_same, right)
            next_k += 1
    if next_k != len(plan.stamps_ns):
        raise InputError(scan.path, f"pair {next_k} went missing on the second pass (was the bag modified?)")


def _same(value):
    return value


def restamped(payload: bytes, stamp_ns: int) -> bytes:
    """A CDR payload of a message that starts with a std_msgs/Header, with header.stamp set to
    `stamp_ns` (sec and nanosec are bytes 4..12, after the encapsulation header)."""
    sec, nanosec = divmod(int(stamp_ns), _NS)
    return payload[:4] + _STAMP.pack(sec, nanosec) + payload[12:]


def compressed_image_payload(stamp_ns: int, frame_id: str, fmt: str, data: bytes | np.ndarray) -> bytes:
    """`CompressedImage(stamp_ns, frame_id, fmt, data).encode()`, with one copy of `data` instead of three."""
    head = CompressedImage(stamp_ns, frame_id, fmt, b"").encode()[:-4]  # ends with the data length, 0
    return b"".join((head, _U32.pack(len(data)), memoryview(data).cast("B")))


def _write(reader: AnyReader, scan: BagScan, plan: PairPlan, out: Path, overwrite: bool, options: ConvertOptions,
           record: layout.RecordingMeta, info_l: CameraInfo, info_r: CameraInfo, tf: TFMessage) -> None:
    encode_params = (
        [cv2.IMWRITE_JPEG_QUALITY, options.jpeg_quality] if options.image_format == "jpeg"
        else [cv2.IMWRITE_PNG_COMPRESSION, 1]
    )
    extension = ".jpg" if options.image_format == "jpeg" else ".png"
    size = (scan.left.height, scan.left.width)
    connection_of = {c.topic: c for c in reader.connections}

    def encode_one(stream: ImageStream, k: int, fetch: Callable[[], bytes | memoryview], frame: str) -> bytes:
        """One image as a CompressedImage CDR payload, built here in an encoding thread."""
        raw = fetch()
        msg = image_message(raw, stream.msgtype, reader.is2)
        if msg is None:  # e.g. big-endian CDR: rosbags' deserialiser
            msg = _image_message_of(_deserialize(reader, scan.path, raw, connection_of[stream.topic]))
        encoding = msg.head.encoding
        try:
            if stream.msgtype == COMPRESSED_IMAGE:
                image = compressed_to_bgr(encoding, msg.data)
                # A JPEG kept as JPEG is copied, not re-encoded: no second generation of losses.
                passthrough = compressed_format(encoding) == "jpeg" == options.image_format
            else:
                image = raw_image_to_bgr(msg.head.height, msg.head.width, encoding, msg.is_bigendian, msg.step,
                                         msg.data)
                passthrough = False
        except UnsupportedImage as exc:
            raise InputError(scan.path, f"{stream.topic}: frame {k}: {exc}") from None
        if image.shape[:2] != size:
            raise InputError(scan.path, f"{stream.topic}: frame {k} is {image.shape[1]}x{image.shape[0]}, the "
                                        f"first one {size[1]}x{size[0]}")
        if passthrough:
            data = msg.data
        else:
            ok, data = cv2.imencode(extension, image, encode_params)
            if not ok:
                raise InputError(scan.path, f"{stream.topic}: frame {k}: image cannot be encoded")
        return compressed_image_payload(int(plan.stamps_ns[k]), frame, options.image_format, data)

    def encode(item) -> tuple[bytes, bytes]:
        k, left, right = item
        return (encode_one(scan.left, k, left, layout.LEFT_FRAME), encode_one(scan.right, k, right, layout.RIGHT_FRAME))

    first = int(plan.stamps_ns[0])
    for transform in tf.transforms:
        transform.stamp_ns = first
    # The camera infos differ from frame to frame only by their stamp: encoded once, restamped.
    info_payloads = ((layout.LEFT_INFO, info_l.encode()), (layout.RIGHT_INFO, info_r.encode()))
    with McapWriter(out, overwrite=overwrite, separate_topics=(layout.WRENCH, layout.ECM_POSE),
                     chunk_level=IMAGE_LEVEL) as writer, \
            ThreadPoolExecutor(max(1, options.workers)) as pool:
        writer.add_metadata(layout.RECORDING_METADATA, record.to_record())
        writer.write(layout.TF_STATIC, tf)
        # Samples up to each frame's stamp are written before it, so the file is in time order.
        series_writers = [_SeriesWriter(writer, layout.WRENCH, WrenchStamped.msgtype, scan.force,
                                        scan.force.frame_id or layout.SENSOR_FRAME)]
        if scan.pose is not None:
            series_writers.append(_SeriesWriter(writer, layout.ECM_POSE, PoseStamped.msgtype, scan.pose,
                                                layout.WORLD_FRAME))
        frames = ordered_map(pool, encode, _stereo_messages(reader, scan, plan), window=4 * max(1, options.workers))
        with tqdm(total=len(plan.stamps_ns), desc=f"convert {scan.path.name}", unit="frame",
                  disable=not options.progress) as bar:
            for k, (left_payload, right_payload) in enumerate(frames):
                stamp = int(plan.stamps_ns[k])
                for series_writer in series_writers:
                    series_writer.write_until(stamp)
                for topic, payload in info_payloads:
                    writer.write_payload(topic, CameraInfo.msgtype, stamp, restamped(payload, stamp))
                writer.write_payload(layout.LEFT_IMAGE, CompressedImage.msgtype, stamp, left_payload)
                writer.write_payload(layout.RIGHT_IMAGE, CompressedImage.msgtype, stamp, right_payload)
                bar.update()
        for series_writer in series_writers:
            series_writer.write_until(None)


def stamped_payload_table(stamps_ns: np.ndarray, frame_id: str, values: np.ndarray) -> np.ndarray:
    """CDR payloads of N stamped messages whose body is a header and then float64 values only
    (WrenchStamped: 6, PoseStamped: 7), as an (N, L) uint8 array built at once with numpy: row i is
    byte for byte what `WrenchStamped.encode()` / `PoseStamped.encode()` give for message i."""
    stamps_ns = np.asarray(stamps_ns, np.int64)
    values = np.ascontiguousarray(values, "<f8")
    name = frame_id.encode("utf-8") + b"\x00"
    head = 4 + 12 + len(name)  # encapsulation, sec, nanosec, string length, string
    body = head + (-(head - 4)) % 8  # float64s align to 8 counted after the encapsulation
    table = np.zeros((len(stamps_ns), body + 8 * values.shape[1]), np.uint8)
    table[:, 1] = 1  # 00 01 00 00: little-endian CDR
    sec, nanosec = np.divmod(stamps_ns, _NS)
    table[:, 4:8] = sec.astype("<i4")[:, None].view(np.uint8)
    table[:, 8:12] = nanosec.astype("<u4")[:, None].view(np.uint8)
    table[:, 12:16] = np.frombuffer(np.uint32(len(name)).astype("<u4").tobytes(), np.uint8)
    table[:, 16:head] = np.frombuffer(name, np.uint8)
    table[:, body:] = values.view(np.uint8)
    return table


def stamped_payloads(stamps_ns: np.ndarray, frame_id: str, values: np.ndarray) -> list[bytes]:
    """`stamped_payload_table` as one bytes object per message."""
    return [row.tobytes() for row in stamped_payload_table(stamps_ns, frame_id, values)]


class _SeriesWriter:
    """Writes a force or pose series in stamp order as the frames go by: `write_until(stamp)` makes sure
    every sample up to `stamp` is written. At 1 kHz the per-call costs add up, so samples are encoded
    and written `batch` at a time, whenever that many are due (the series has chunks of its own in the
    file, `McapWriter(separate_topics=...)`, so waiting a few frames moves nothing in the file)."""

    def __init__(self, writer: McapWriter, topic: str, msgtype: str, series: Series, frame_id: str,
                 batch: int = 512):
        self.writer, self.topic, self.msgtype, self.series, self.frame_id = writer, topic, msgtype, series, frame_id
        self.batch, self.done = batch, 0

    def write_until(self, stamp_ns: int | None) -> None:
        """The samples up to `stamp_ns` once `batch` of them are due; every remaining one for None."""
        stamps = self.series.stamps_ns
        stop = len(stamps) if stamp_ns is None else int(np.searchsorted(stamps, stamp_ns, side="right"))
        if stop - self.done < (1 if stamp_ns is None else self.batch):
            return
        for start in range(self.done, stop, 8 * self.batch):  # a bounded table even for a long gap
            rows = slice(start, min(stop, start + 8 * self.batch))
            self.writer.write_payloads(self.topic, self.msgtype, stamps[rows],
                                       stamped_payload_table(stamps[rows], self.frame_id, self.series.values[rows]))
        self.done = stop


def receive_times(reader: AnyReader, path: Path, progress: bool = False) -> dict[str, np.ndarray]:
    """Bag receive times (ns) of every topic, reading the whole bag."""
    times: dict[str, array] = {}
    with tqdm(total=reader.message_count, desc=f"read {path.name}", unit="msg", disable=not progress,
              mininterval=0.5) as bar:
        for connection, receive_ns, _raw in bag_messages(reader, path, reader.connections):
            times.setdefault(connection.topic, array("q")).append(receive_ns)
            bar.update()
    return {topic: np.frombuffer(values, np.int64) for topic, values in times.items()}


def topic_rates_hz(receive_ns: dict[str, np.ndarray]) -> dict[str, float]:
    """Mean message rate of each topic over its receive times (0 for fewer than two messages)."""
    rates = {}
    for topic, times in receive_ns.items():
        span = (int(times.max()) - int(times.min())) / 1e9 if len(times) > 1 else 0.0
        rates[topic] = (len(times) - 1) / span if span > 0 else 0.0
    return rates


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]
