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

Modules, in the order a conversion uses them: `bag_topics` (which topics), `bag_scan` (opening the bag,
and the first pass: stamps, force, pose, camera info), this one (pairing, the camera model, the
convert pass), `ros_images` (pixels to BGR), `bag_index` (random access to the messages).

Two steps:
1. scan (`bag_scan`): the stamp, encoding and size of every image, all force and pose samples, the
   first camera info of each side. Topics are chosen, frames paired and the force checked against the
   video span here, so a bad bag fails before anything is encoded.
2. convert: the two images of each pair, in pair order, deserialised, decoded and JPEG/PNG-encoded
   on a thread pool and written in stamp order with force and pose interleaved, as the folder
   converter does.
Where the storage allows random access (ROS 1 bags with uncompressed chunks, ROS 2 sqlite3 bags;
`bag_index`), the scan reads only the first bytes of each image and the convert step fetches each
image once, directly. Elsewhere (bz2/lz4 chunks, MCAP storage) both steps stream the bag through
`rosbags`' iterator, which reads the images twice."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader

from vfdata import __version__
from vfdata.atomic import check_output
from vfdata.calibration import StereoCalibration
from vfdata.conversion.bag_camera_info import bag_camera_info
from vfdata.conversion.bag_scan import (
    BagScan,
    ImageStream,
    bag_messages,
    close_scan,
    deserialize,
    header_stamp_ns,
    image_message_of,
    open_bag,
    scan_bag,
)
from vfdata.conversion.bag_topics import (
    COMPRESSED_IMAGE,
    BagTopics,
    TopicChoice,
    camera_info_topic,
    choose_topics,
    topic_types,
)
from vfdata.conversion.image_messages import image_message
from vfdata.conversion.options import ConvertOptions
from vfdata.conversion.raw_meta import recording_fields
from vfdata.conversion.rgbd_bags import convert_rgbd_scanned, rgbd_choice, rgbd_topics
from vfdata.conversion.ros_images import UnsupportedImage, compressed_format, compressed_to_bgr, raw_image_to_bgr
from vfdata.conversion.write_recording import (
    camera_infos,
    compressed_image_payload,
    encode_image,
    sensor_series,
    stereo_tf,
    write_recording,
)
from vfdata.errors import InputError
from vfdata.force_coverage import check_force_covers
from vfdata.recording import layout
from vfdata.recording.messages import (
    CameraInfo,
    TFMessage,
    TransformStamped,
)

log = logging.getLogger(__name__)


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


# -- conversion -----------------------------------------------------------------------------------
def convert_bag(src: str | Path, out: str | Path, overwrite: bool = False, options: ConvertOptions | None = None,
                topics: BagTopics | None = None, calibration: str | Path | None = None,
                pair_tolerance_ns: int | None = None, meta: dict | None = None) -> Path:
    """Convert a ROS 1 or ROS 2 bag to a recording MCAP at `out`. Returns `out`.

    `meta`: what a bag does not say, as meta.yaml keys (`vfdata convert --meta KEY=VALUE`; docs/bags.md):
    gravity_up (the up direction in the ECM pose's frame; without it the object frame's X comes from the
    image, not from [0, 0, 1] of a base frame nobody checked), orientation_deg, tissue, prompt,
    sensor_to_object, id, split, any other key.

    `topics`: remapped topic names (None: dVRK defaults / auto-detection). `calibration`: a
    calibration.yaml used instead of the bag's CameraInfo topics. `pair_tolerance_ns`: largest
    left/right stamp difference of a stereo pair (default half the median left frame period)."""
    options = options or ConvertOptions()
    src, out = Path(src), Path(out)
    options.check_format(out)
    if src.exists():
        check_output(out, overwrite, inputs=[src, *([calibration] if calibration is not None else [])])
    calib = StereoCalibration.load(calibration) if calibration is not None else None
    with open_bag(src) as reader:
        types, asked = topic_types(reader), topics or BagTopics()
        rgbd = rgbd_topics(types, asked)
        if rgbd is not None:
            if calib is not None or meta:
                raise InputError(src, "an RGB-D bag takes its cameras from its camera_info topics: --calibration "
                                      "and --meta KEY=VALUE apply to stereo bags")
            choice = rgbd_choice(src, types, *rgbd, asked)
        else:
            choice = choose_topics(src, types, asked, use_camera_info=calib is None)
        scan = scan_bag(reader, src, choice, progress=options.progress)
        try:
            _sensors_on_video_clock(scan, options)
            if rgbd is not None:
                plan = plan_pairs(scan, pair_tolerance_ns)
                check_force_span(scan, plan, options.force_gap_tolerance_ns)
                convert_rgbd_scanned(reader, src, out, overwrite, options, scan, plan,
                                     _stereo_messages(reader, scan, plan), (scan.left_info, scan.right_info))
            else:
                _convert_scanned(reader, src, out, overwrite, options, scan, choice, calib, calibration,
                                 pair_tolerance_ns, meta or {})
        finally:
            close_scan(scan)
    return out


def _convert_scanned(reader: AnyReader, src: Path, out: Path, overwrite: bool, options: ConvertOptions, scan: BagScan,
                     choice: TopicChoice, calib: StereoCalibration | None, calibration: str | Path | None,
                     pair_tolerance_ns: int | None, meta: dict) -> None:
    """Everything after the scan: pairing, checks, metadata, the convert pass."""
    plan = plan_pairs(scan, pair_tolerance_ns)
    info_l, info_r, tf, camera_source = camera_model(scan, calib, Path(calibration) if calibration else None)
    check_force_span(scan, plan, options.force_gap_tolerance_ns)
    _warn_about(scan, plan)
    fields = recording_fields(meta, Path("--meta"), src.stem if src.is_file() else src.name,
                              (scan.left.width, scan.left.height))
    if "gravity_up" not in meta and "gravity_up_world" not in meta:
        # A bag does not say which way is up in its ECM pose's frame: `process` then takes X from the image.
        fields["extra"]["gravity_up_assumed"] = "true"
    record = layout.RecordingMeta(
        **{k: v for k, v in fields.items() if k != "extra"},
        source=str(src.resolve()),
        converter=f"vfdata convert ({scan.kind} bag)",
        converter_version=__version__,
        extra={**fields["extra"],
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


def _sensors_on_video_clock(scan: BagScan, options: ConvertOptions) -> None:
    """The scan's force and pose stamps moved by `--time-offset-ms` (ConvertOptions.on_video_clock)."""
    for name in ("force", "pose"):
        series = getattr(scan, name)
        if series is not None:
            stamps, = options.on_video_clock((series.stamps_ns,), scan.path)
            setattr(scan, name, replace(series, stamps_ns=stamps))


def check_force_span(scan: BagScan, plan: PairPlan, tolerance_ns: int | None) -> None:
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
        stamp = header_stamp_ns(deserialize(reader, scan.path, raw, connection)) or receive_ns
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


def _write(reader: AnyReader, scan: BagScan, plan: PairPlan, out: Path, overwrite: bool, options: ConvertOptions,
           record: layout.RecordingMeta, info_l: CameraInfo, info_r: CameraInfo, tf: TFMessage) -> None:
    size = (scan.left.height, scan.left.width)
    connection_of = {c.topic: c for c in reader.connections}

    def encode_one(stream: ImageStream, k: int, fetch: Callable[[], bytes | memoryview], frame: str) -> bytes:
        """One image as a CompressedImage CDR payload, built here in an encoding thread."""
        raw = fetch()
        msg = image_message(raw, stream.msgtype, reader.is2)
        if msg is None:  # e.g. big-endian CDR: rosbags' deserialiser
            msg = image_message_of(deserialize(reader, scan.path, raw, connection_of[stream.topic]))
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
        data = msg.data if passthrough else encode_image(image, options)
        if data is None:
            raise InputError(scan.path, f"{stream.topic}: frame {k}: image cannot be encoded")
        return compressed_image_payload(int(plan.stamps_ns[k]), frame, options.image_format, data)

    def encode(item) -> tuple[bytes, bytes]:
        k, left, right = item
        return (encode_one(scan.left, k, left, layout.LEFT_FRAME), encode_one(scan.right, k, right, layout.RIGHT_FRAME))

    series = sensor_series((scan.force.stamps_ns, scan.force.values, scan.force.frame_id or layout.SENSOR_FRAME),
                           None if scan.pose is None else (scan.pose.stamps_ns, scan.pose.values))
    write_recording(out, overwrite, options, record, (info_l, info_r), tf, plan.stamps_ns,
                    _stereo_messages(reader, scan, plan), encode, series, scan.path.name)
