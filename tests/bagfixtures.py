"""ROS 1 and ROS 2 bags written by the tests themselves with `rosbags` (dVRK topic names, both ECM pose
types, raw and compressed images), with what was written kept for the checks."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from vfdata.recording import layout
from vfdata.recording.inspect import check_file
from vfdata.recording.reader import Recording

T0_NS = 1_700_000_000_123_456_789
FRAME_NS = 33_333_333
FORCE_NS = 1_000_000
LEFT, RIGHT = "/jhu_daVinci/left/image_raw", "/jhu_daVinci/right/image_raw"
LEFT_INFO, RIGHT_INFO = "/jhu_daVinci/left/camera_info", "/jhu_daVinci/right/camera_info"
FX, CX, CY, BASELINE_M = 300.0, 31.5, 23.5, 0.0045


@dataclass
class BagSpec:
    """What to write, and (filled in by `write_bag`) what was written."""

    ros2: bool = False
    storage: StoragePlugin = StoragePlugin.SQLITE3
    frames: int = 8
    width: int = 64
    height: int = 48
    encoding: str = "bgr8"  # or "compressed" (JPEG), "compressed_png", "rgb8", "mono8", ...
    pose_type: str | None = "PoseStamped"
    left: str = LEFT
    right: str = RIGHT
    force_topics: tuple[str, ...] = ("/netft_data",)
    camera_info: bool = True
    right_offset_ns: int = 2_000_000  # right camera stamps lag the left ones
    extra_right_ns: tuple[int, ...] = ()  # right frames with no left partner
    force_shift_ns: int = 0
    zero_stamps: bool = False  # image headers left at 0
    with_images: bool = True
    lz4: bool = False  # ROS 1 chunk compression
    zstd: bool = False  # MCAP storage chunk compression (`ros2 bag record --storage-preset-profile zstd_fast`)
    compression_mode: CompressionMode | None = None  # `ros2 bag record --compression-mode file|message` (zstd)
    force_step_ns: int = FORCE_NS  # force sample interval
    drop_force: tuple[int, ...] = ()  # force samples left out (a sensor dropping samples)
    camera_k: tuple[float, ...] | None = None  # CameraInfo K (default: FX, CX, CY)
    camera_d: tuple[float, ...] = (0.01, -0.02, 0.0, 0.0, 0.001)  # CameraInfo D
    force_payload: bytes | None = None  # every force message's serialised bytes replaced by these
    # filled in
    images: list = field(default_factory=list)
    frame_ns: np.ndarray | None = None
    force_ns: np.ndarray | None = None
    wrench: np.ndarray | None = None
    pose_ns: np.ndarray | None = None
    pose: np.ndarray | None = None


def pattern(spec: BagSpec, i: int, side: int) -> np.ndarray:
    rng = np.random.default_rng(10 * i + side)
    image = rng.integers(0, 256, (spec.height, spec.width, 3), dtype=np.uint8)
    return cv2.GaussianBlur(image, (5, 5), 0)


def write_bag(path: Path, spec: BagSpec) -> BagSpec:
    ts = get_typestore(Stores.ROS2_HUMBLE if spec.ros2 else Stores.ROS1_NOETIC)
    T = ts.types
    Time = T["builtin_interfaces/msg/Time"]

    def header(stamp_ns: int, frame: str):
        time = Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
        if spec.ros2:
            return T["std_msgs/msg/Header"](stamp=time, frame_id=frame)
        return T["std_msgs/msg/Header"](seq=0, stamp=time, frame_id=frame)

    def vec(x, y, z):
        return T["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z))

    n = spec.frames
    spec.frame_ns = T0_NS + np.arange(n, dtype=np.int64) * FRAME_NS
    spec.images = [(pattern(spec, i, 0), pattern(spec, i, 1)) for i in range(n)]
    spec.force_ns = np.arange(spec.frame_ns[0] - 5 * FORCE_NS, spec.frame_ns[-1] + 5 * FORCE_NS, spec.force_step_ns,
                              dtype=np.int64) + spec.force_shift_ns
    spec.force_ns = np.delete(spec.force_ns, list(spec.drop_force))
    phase = (spec.force_ns - T0_NS) / 1e9
    spec.wrench = np.stack([np.sin(phase * 7 * k + k) * k for k in range(1, 7)], axis=1)
    spec.pose_ns = spec.frame_ns[::2] + 1_000_000
    angles = 0.05 * np.arange(len(spec.pose_ns))
    spec.pose = np.stack([0.1 + 0 * angles, 0.2 + 0.001 * np.arange(len(angles)), 0.3 + 0 * angles,
                          np.sin(angles / 2), 0 * angles, 0 * angles, np.cos(angles / 2)], axis=1)

    messages = []  # (receive_ns, topic, msgtype, message)

    def image_msg(image: np.ndarray, stamp: int, frame: str):
        if spec.encoding.startswith("compressed"):
            fmt = "png" if spec.encoding == "compressed_png" else "jpeg"
            data = cv2.imencode("." + fmt.replace("jpeg", "jpg"), image)[1].ravel()
            fmt = "bgr8; png compressed bgr8" if fmt == "png" else "rgb8; jpeg compressed bgr8"
            return "sensor_msgs/msg/CompressedImage", T["sensor_msgs/msg/CompressedImage"](
                header=header(stamp, frame), format=fmt, data=data)
        if spec.encoding == "rgb8":
            pixels = image[..., ::-1]
        elif spec.encoding == "mono8":
            pixels = image[..., 1]
        else:
            pixels = image
        pixels = np.ascontiguousarray(pixels)
        step = spec.width * (pixels.shape[2] if pixels.ndim == 3 else 1)
        return "sensor_msgs/msg/Image", T["sensor_msgs/msg/Image"](
            header=header(stamp, frame), height=spec.height, width=spec.width, encoding=spec.encoding,
            is_bigendian=0, step=step, data=pixels.ravel())

    for i, stamp in enumerate(spec.frame_ns if spec.with_images else []):
        left, right = spec.images[i]
        l_stamp, r_stamp = int(stamp), int(stamp) + spec.right_offset_ns
        for side_topic, image, st, frame in ((spec.left, left, l_stamp, "left"), (spec.right, right, r_stamp, "right")):
            msgtype, msg = image_msg(image, 0 if spec.zero_stamps else st, frame)
            messages.append((st + 5_000_000, side_topic, msgtype, msg))
    for extra in spec.extra_right_ns:
        msgtype, msg = image_msg(spec.images[0][1], int(extra), "right")
        messages.append((int(extra) + 5_000_000, spec.right, msgtype, msg))
    if spec.camera_info:
        for i in range(3):
            stamp = int(spec.frame_ns[0]) + i * 10 * FRAME_NS
            for side_topic, tx in ((LEFT_INFO, 0.0), (RIGHT_INFO, -FX * BASELINE_M)):
                K = list(spec.camera_k) if spec.camera_k is not None else [FX, 0, CX, 0, FX, CY, 0, 0, 1]
                P = [FX, 0, CX, tx, 0, FX, CY, 0, 0, 0, 1, 0]
                names = ("d", "k", "r", "p") if spec.ros2 else ("D", "K", "R", "P")
                values = (np.array(spec.camera_d, float), np.array(K, float), np.eye(3).ravel(),
                          np.array(P, float))
                roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                            do_rectify=False)
                msg = T["sensor_msgs/msg/CameraInfo"](
                    header=header(stamp, "cam"), height=spec.height, width=spec.width, distortion_model="plumb_bob",
                    **dict(zip(names, values, strict=True)), binning_x=0, binning_y=0, roi=roi)
                messages.append((stamp + 1, side_topic, "sensor_msgs/msg/CameraInfo", msg))
    Wrench = T["geometry_msgs/msg/Wrench"]
    for j, topic in enumerate(spec.force_topics):
        for stamp, w in zip(spec.force_ns, spec.wrench, strict=True):
            msg = T["geometry_msgs/msg/WrenchStamped"](header=header(int(stamp), "ati_sensor"),
                                                       wrench=Wrench(force=vec(*w[:3]), torque=vec(*w[3:])))
            messages.append((int(stamp) + 200_000 + j, topic, "geometry_msgs/msg/WrenchStamped", msg))
    if spec.pose_type:
        for stamp, v in zip(spec.pose_ns, spec.pose, strict=True):
            quat = T["geometry_msgs/msg/Quaternion"](x=v[3], y=v[4], z=v[5], w=v[6])
            if spec.pose_type == "PoseStamped":
                pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=v[0], y=v[1], z=v[2]),
                                                   orientation=quat)
                msg = T["geometry_msgs/msg/PoseStamped"](header=header(int(stamp), "ECM_base"), pose=pose)
            else:
                transform = T["geometry_msgs/msg/Transform"](translation=vec(*v[:3]), rotation=quat)
                msg = T["geometry_msgs/msg/TransformStamped"](header=header(int(stamp), "ECM_base"),
                                                              child_frame_id="ECM", transform=transform)
            messages.append((int(stamp) + 300_000, "/ECM/measured_cp", f"geometry_msgs/msg/{spec.pose_type}", msg))

    messages.sort(key=lambda m: m[0])
    if spec.ros2:
        writer = Writer2(path, version=9, storage_plugin=spec.storage)
        if spec.zstd:
            writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        if spec.compression_mode is not None:
            writer.set_compression(spec.compression_mode, CompressionFormat.ZSTD)
        serialize = ts.serialize_cdr
    else:
        writer = Writer1(path)
        if spec.lz4:
            writer.set_compression(Writer1.CompressionFormat.LZ4)
        serialize = ts.serialize_ros1
    with writer:
        connections = {}
        for _, topic, msgtype, _msg in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=ts)
        for receive_ns, topic, msgtype, msg in messages:
            garbage = spec.force_payload is not None and msgtype == "geometry_msgs/msg/WrenchStamped"
            writer.write(connections[topic], receive_ns, spec.force_payload if garbage else serialize(msg, msgtype))
    return spec


def check_recording(out: Path, spec: BagSpec) -> Recording:
    """The converted recording `out` against the bag `spec` it came from, topic by topic, value by value."""
    assert check_file(out) == []  # what `vfdata check` runs: layout, stamps, CRCs
    rec = Recording.open(out)
    n = spec.frames
    # frames: the left stamps, both images carry them; pixels exact for PNG output
    assert np.array_equal(rec.frame_times_ns, spec.frame_ns)
    assert np.array_equal(rec.log_times_ns(layout.RIGHT_IMAGE), spec.frame_ns)
    for i in range(n):
        frame = rec.frame(i)
        left, right = spec.images[i]
        if spec.encoding == "mono8":
            left, right = (cv2.cvtColor(img[..., 1], cv2.COLOR_GRAY2BGR) for img in (left, right))
        assert np.array_equal(frame.left, left) and np.array_equal(frame.right, right)
    # camera info every frame, with the bag's K, D, P and the layout's frame ids
    assert rec.topics[layout.LEFT_INFO].count == n and rec.topics[layout.RIGHT_INFO].count == n
    info_l, info_r = rec.camera_infos
    assert (info_l.frame_id, info_r.frame_id) == (layout.LEFT_FRAME, layout.RIGHT_FRAME)
    assert (info_l.width, info_l.height) == (spec.width, spec.height)
    assert np.array_equal(info_l.k, [[FX, 0, CX], [0, FX, CY], [0, 0, 1]])
    assert np.array_equal(info_l.d, [0.01, -0.02, 0.0, 0.0, 0.001])
    assert info_r.p[0, 3] == -FX * BASELINE_M
    assert rec.stereo.baseline_mm == pytest.approx(BASELINE_M * 1000)
    tf = rec.message(layout.TF_STATIC, 0).transforms[0]
    assert (tf.frame_id, tf.child_frame_id) == (layout.LEFT_FRAME, layout.RIGHT_FRAME)
    assert tf.translation == pytest.approx((BASELINE_M, 0.0, 0.0))
    # force: every sample, stamps and values exact
    force = rec.force
    assert np.array_equal(force.times_ns, spec.force_ns)
    assert np.array_equal(force.wrench, spec.wrench)
    assert force.frame_id == "ati_sensor"
    # pose, as PoseStamped whatever the bag had
    if spec.pose_type:
        pose = rec.ecm_pose
        assert np.array_equal(pose.times_ns, spec.pose_ns)
        assert np.allclose(pose.position_m, spec.pose[:, :3], atol=1e-15)
        assert np.allclose(pose.quaternion_xyzw, spec.pose[:, 3:], atol=1e-15)
        assert rec.topics[layout.ECM_POSE].msgtype == "geometry_msgs/msg/PoseStamped"
    else:
        assert not rec.has(layout.ECM_POSE)
    # the file is in time order
    assert rec.metadata.converter.startswith("vfdata convert (ROS")
    return rec
