"""ROS bags from RGB-D camera drivers -> recording MCAP with the RGB-D topics (docs/bags.md, "RGB-D
bags"; docs/format.md). A bag is read as RGB-D when no stereo topics are asked for and it holds one of
the depth topics the drivers publish (realsense-ros, openni/openni2, Azure Kinect); colour and depth
are paired by stamp as a stereo pair is, with the bag's CameraInfo of each. Depth `16UC1`/`mono16`
(mm) is stored as it is, `32FC1` (m, as some drivers publish) converted to mm; colour as for stereo.

The scan, the pairing, the force checks and the write loop are the stereo bag converter's."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader

from vfdata import __version__
from vfdata.conversion.bag_camera_info import bag_camera_info
from vfdata.conversion.bag_scan import BagScan, deserialize, image_message_of
from vfdata.conversion.bag_topics import (
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    IMAGE,
    IMAGE_TYPES,
    RGBD_DEPTH,
    BagTopics,
    TopicChoice,
    camera_info_topic,
    choose_force_and_pose,
)
from vfdata.conversion.image_messages import image_message
from vfdata.conversion.options import ConvertOptions
from vfdata.conversion.raw_rgbd import COLOR_VIEW, DEPTH_VIEW
from vfdata.conversion.ros_images import UnsupportedImage, compressed_to_bgr, raw_image_to_bgr
from vfdata.conversion.write_recording import StampedSeries, compressed_image_payload, encode_image, write_recording
from vfdata.errors import InputError
from vfdata.recording import layout
from vfdata.recording.messages import Image, PoseStamped, TFMessage, TransformStamped, WrenchStamped

# In order of preference: depth registered to the colour view first (the drivers' aligned topics).
DEPTH_DEFAULTS = ("/camera/aligned_depth_to_color/image_raw", "/camera/depth_registered/image_raw",
                  "/depth_to_rgb/image_raw", "/camera/depth/image_rect_raw", "/camera/depth/image_raw",
                  "/camera/depth/image", "/depth/image_raw")
COLOR_DEFAULTS = ("/camera/color/image_raw", "/camera/rgb/image_raw", "/camera/rgb/image_color", "/rgb/image_raw",
                  "/camera/color/image_raw/compressed", "/camera/rgb/image_raw/compressed",
                  "/rgb/image_raw/compressed")
REGISTERED_DEPTH = ("aligned_depth_to_color", "depth_registered", "depth_to_rgb")


def rgbd_topics(types: dict[str, str], asked: BagTopics) -> tuple[str, str] | None:
    """(colour, depth) topics when the bag is an RGB-D driver's and no stereo topics were asked for."""
    if asked.left or asked.right:
        return None
    depth = next((t for t in DEPTH_DEFAULTS if types.get(t) == IMAGE), None)
    color = next((t for t in COLOR_DEFAULTS if types.get(t) in IMAGE_TYPES), None)
    return (color, depth) if depth and color else None


def rgbd_choice(path: Path, types: dict[str, str], color: str, depth: str, asked: BagTopics) -> TopicChoice:
    """The topics of an RGB-D conversion: colour as `left`, depth as `right`, their camera infos, and
    the force and pose chosen as for stereo."""
    infos = []
    for topic in (color, depth):
        info = camera_info_topic(topic)
        if types.get(info) != CAMERA_INFO:
            raise InputError(path, f"no {info} beside {topic}: the RGB-D camera's intrinsics are needed")
        infos.append(info)
    how = {"left": "RGB-D colour", "right": RGBD_DEPTH}
    force, pose = choose_force_and_pose(path, types, asked, how)
    return TopicChoice(color, depth, infos[0], infos[1], force, pose, how)


def depth_mm(height: int, width: int, encoding: str, is_bigendian: int, step: int, data) -> np.ndarray:
    """A depth Image's pixels as (H, W) uint16 mm (0 = none)."""
    buffer = np.frombuffer(data, np.uint8)
    if encoding in ("16UC1", "mono16"):
        dtype = np.dtype(">u2" if is_bigendian else "<u2")
    elif encoding == "32FC1":
        dtype = np.dtype(">f4" if is_bigendian else "<f4")
    else:
        raise UnsupportedImage(f"depth encoding '{encoding}' (expected 16UC1 mm, mono16 or 32FC1 m)")
    if step < width * dtype.itemsize or len(buffer) < step * height:
        raise UnsupportedImage(f"depth image {width}x{height} step {step} holds {len(buffer)} bytes")
    rows = buffer[:step * height].reshape(height, step)[:, :width * dtype.itemsize]
    values = np.ascontiguousarray(rows).view(dtype).reshape(height, width)
    if dtype.kind == "f":
        metres = np.nan_to_num(values.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)
        return np.clip(np.rint(metres * 1000.0), 0, 65535).astype(np.uint16)
    return values.astype(np.uint16)


def convert_rgbd_scanned(reader: AnyReader, src: Path, out: Path, overwrite: bool, options: ConvertOptions,
                         scan: BagScan, plan, messages, infos) -> None:
    """Write an RGB-D bag's paired frames (`plan`, `messages` of the stereo converter; colour = left,
    depth = right) with the camera `infos` (colour, depth) of the bag."""

    color_info = bag_camera_info(scan.path, scan.choice.left_info, infos[0], layout.COLOR_FRAME)
    depth_info = bag_camera_info(scan.path, scan.choice.right_info, infos[1], layout.DEPTH_FRAME)
    for stream, info in ((scan.left, color_info), (scan.right, depth_info)):
        if stream.width and (info.width, info.height) != (stream.width, stream.height):
            raise InputError(scan.path, f"{stream.topic} is {stream.width}x{stream.height}, its camera_info "
                                        f"{info.width}x{info.height}")
    registered = any(name in scan.right.topic for name in REGISTERED_DEPTH)
    # depth registered to the colour view by the driver: one optical frame, the identity between them
    tf = TFMessage([TransformStamped(0, layout.DEPTH_FRAME, layout.COLOR_FRAME, (0.0, 0.0, 0.0),
                                     (0.0, 0.0, 0.0, 1.0))] if registered else [])
    record = layout.RecordingMeta(
        recording_id=src.stem if src.is_file() else src.name, source=str(src.resolve()),
        converter=f"vfdata convert ({scan.kind} RGB-D bag)", converter_version=__version__,
        units=dict(layout.RGBD_UNITS),
        extra={"camera": "rgbd", "depth_color_registered": str(registered).lower(),
               "bag_color_topic": scan.left.topic, "bag_depth_topic": scan.right.topic,
               "bag_force_topic": scan.choice.force, "bag_pose_topic": scan.choice.pose or "",
               "pair_tolerance_ns": str(plan.tolerance_ns), "unpaired_color_frames": str(plan.unpaired_left),
               "unpaired_depth_frames": str(plan.unpaired_right)})
    connection_of = {c.topic: c for c in reader.connections}

    def fetch_message(stream, fetch: Callable[[], bytes | memoryview]):
        raw = fetch()
        msg = image_message(raw, stream.msgtype, reader.is2)
        return msg if msg is not None else image_message_of(deserialize(reader, scan.path, raw,
                                                                        connection_of[stream.topic]))

    def encode(item) -> tuple[bytes, bytes]:
        k, color_fetch, depth_fetch = item
        stamp = int(plan.stamps_ns[k])
        try:
            msg = fetch_message(scan.right, depth_fetch)
            depth = depth_mm(msg.head.height, msg.head.width, msg.head.encoding, msg.is_bigendian, msg.step, msg.data)
            msg = fetch_message(scan.left, color_fetch)
            color = (compressed_to_bgr(msg.head.encoding, msg.data) if scan.left.msgtype == COMPRESSED_IMAGE else
                     raw_image_to_bgr(msg.head.height, msg.head.width, msg.head.encoding, msg.is_bigendian, msg.step,
                                      msg.data))
        except UnsupportedImage as exc:
            raise InputError(scan.path, f"frame {k}: {exc}") from None
        h, w = depth.shape
        data = encode_image(color, options)
        if data is None:
            raise InputError(scan.path, f"{scan.left.topic}: frame {k}: image cannot be encoded")
        return (Image(stamp, layout.DEPTH_FRAME, h, w, "16UC1", 0, 2 * w, depth.astype("<u2").tobytes()).encode(),
                compressed_image_payload(stamp, layout.COLOR_FRAME, options.image_format, data))

    series = [StampedSeries(layout.WRENCH, WrenchStamped.msgtype, scan.force.stamps_ns, scan.force.values,
                            scan.force.frame_id or layout.SENSOR_FRAME)]
    if scan.pose is not None:
        series.append(StampedSeries(layout.ECM_POSE, PoseStamped.msgtype, scan.pose.stamps_ns, scan.pose.values,
                                    layout.WORLD_FRAME))
    write_recording(out, overwrite, options, record, (depth_info, color_info), tf, plan.stamps_ns, messages,
                    encode, series, scan.path.name, views=(DEPTH_VIEW, COLOR_VIEW))
