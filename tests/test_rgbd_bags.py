"""ROS bags of RGB-D camera drivers (realsense-ros, Azure Kinect names) converted to the RGB-D layout:
colour and depth paired by stamp, depth in mm (16UC1 kept, 32FC1 m converted), camera infos of each."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from vfdata.conversion.bags import convert_bag
from vfdata.conversion.options import ConvertOptions
from vfdata.errors import InputError
from vfdata.recording import Recording, layout
from vfdata.recording.inspect import check_file

T0 = 1_700_000_000_000_000_000
W, H, N = 32, 24, 6


def depth_frame(i: int) -> np.ndarray:
    v, u = np.mgrid[0:H, 0:W]
    depth = (600 + 3 * v + i).astype(np.uint16)
    depth[0, :4] = 0  # no depth
    return depth


def write_rgbd_bag(path, ros2: bool, color: str, depth: str, depth_encoding: str = "16UC1", info: bool = True):
    ts = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    T = ts.types

    def header(stamp, frame):
        time = T["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9)
        return T["std_msgs/msg/Header"](stamp=time, frame_id=frame) if ros2 else \
            T["std_msgs/msg/Header"](seq=0, stamp=time, frame_id=frame)

    messages = []
    for i in range(N):
        stamp = T0 + i * 33_333_333
        image = np.full((H, W, 3), 40 * i % 255, np.uint8)
        messages.append((stamp + 1000, color, "sensor_msgs/msg/Image", T["sensor_msgs/msg/Image"](
            header=header(stamp, "color"), height=H, width=W, encoding="bgr8", is_bigendian=0, step=3 * W,
            data=image.ravel())))
        d = depth_frame(i)
        if depth_encoding == "32FC1":
            data = np.where(d > 0, d / 1000.0, np.nan).astype("<f4").view(np.uint8).ravel()
            step = 4 * W
        else:
            data, step = d.astype("<u2").view(np.uint8).ravel(), 2 * W
        messages.append((stamp + 2000, depth, "sensor_msgs/msg/Image", T["sensor_msgs/msg/Image"](
            header=header(stamp + 1_000_000, "depth"), height=H, width=W, encoding=depth_encoding, is_bigendian=0,
            step=step, data=data)))
        if info and i == 0:
            for topic in (color.rsplit("/", 1)[0] + "/camera_info", depth.rsplit("/", 1)[0] + "/camera_info"):
                names = ("d", "k", "r", "p") if ros2 else ("D", "K", "R", "P")
                values = (np.zeros(5), np.array([50.0, 0, 15.5, 0, 50.0, 11.5, 0, 0, 1]), np.eye(3).ravel(),
                          np.array([50.0, 0, 15.5, 0, 0, 50.0, 11.5, 0, 0, 0, 1, 0]))
                roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                            do_rectify=False)
                messages.append((stamp + 10, topic, "sensor_msgs/msg/CameraInfo", T["sensor_msgs/msg/CameraInfo"](
                    header=header(stamp, "cam"), height=H, width=W, distortion_model="plumb_bob",
                    **dict(zip(names, values, strict=True)), binning_x=0, binning_y=0, roi=roi)))
    vec = T["geometry_msgs/msg/Vector3"]
    for k, stamp in enumerate(range(T0 - 30_000_000, T0 + N * 33_333_333 + 30_000_000, 10_000_000)):
        messages.append((stamp + 500, "/netft_data", "geometry_msgs/msg/WrenchStamped",
                         T["geometry_msgs/msg/WrenchStamped"](header=header(stamp, "ati"), wrench=T[
                             "geometry_msgs/msg/Wrench"](force=vec(x=0.0, y=0.0, z=-0.1 * k), torque=vec(x=0.0, y=0.0,
                                                                                                        z=0.0)))))
    messages.sort(key=lambda m: m[0])
    writer = Writer2(path, version=9, storage_plugin=StoragePlugin.SQLITE3) if ros2 else Writer1(path)
    serialize = ts.serialize_cdr if ros2 else ts.serialize_ros1
    with writer:
        connections = {}
        for receive, topic, msgtype, msg in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(connections[topic], receive, serialize(msg, msgtype))
    return path


@pytest.mark.parametrize(("ros2", "color", "depth", "encoding", "registered"), [
    (False, "/camera/color/image_raw", "/camera/depth/image_rect_raw", "16UC1", False),  # realsense-ros
    (True, "/rgb/image_raw", "/depth_to_rgb/image_raw", "32FC1", True),  # Azure Kinect, depth in metres
])
def test_rgbd_bags_convert_to_the_rgbd_layout(tmp_path, ros2, color, depth, encoding, registered):
    bag = write_rgbd_bag(tmp_path / ("rec" if ros2 else "rec.bag"), ros2, color, depth, encoding)
    out = convert_bag(bag, tmp_path / "rec.mcap", options=ConvertOptions(progress=False, workers=1))
    rec = Recording.open(out)
    assert rec.is_rgbd and rec.num_frames == N and check_file(out) == []
    assert rec.metadata.extra["depth_color_registered"] == str(registered).lower()
    assert rec.metadata.extra["bag_depth_topic"] == depth
    for i in (0, N - 1):
        depth_mm = rec.depth_mm(i)
        expected = depth_frame(i).astype(np.float32)
        np.testing.assert_array_equal(np.isnan(depth_mm), expected == 0)
        np.testing.assert_array_equal(depth_mm[expected > 0], expected[expected > 0])
    assert rec.color_image(2).shape == (H, W, 3) and rec.depth_camera.fx == 50.0
    assert len(rec.message(layout.TF_STATIC, 0).transforms) == int(registered)


def test_an_rgbd_bag_without_camera_info_is_one_clear_error(tmp_path):
    bag = write_rgbd_bag(tmp_path / "rec.bag", False, "/camera/color/image_raw", "/camera/depth/image_rect_raw",
                         info=False)
    with pytest.raises(InputError, match=r"no /camera/color/camera_info beside /camera/color/image_raw"):
        convert_bag(bag, tmp_path / "rec.mcap", options=ConvertOptions(progress=False, workers=1))
    assert not (tmp_path / "rec.mcap").exists()


def test_inspect_bag_reads_an_rgbd_bag_as_rgbd(tmp_path):
    from vfdata.commands.inspect_bag import inspect_bag_text

    bag = write_rgbd_bag(tmp_path / "rec.bag", False, "/camera/color/image_raw", "/camera/depth/image_rect_raw")
    text = inspect_bag_text(bag)
    lines = {line.split()[0]: line for line in text.splitlines() if line.startswith("/")}
    assert "left images (RGB-D colour)" in lines["/camera/color/image_raw"]
    assert "right images (RGB-D depth)" in lines["/camera/depth/image_rect_raw"]
    assert "colour fx 50.0 px, depth fx 50.0 px" in text and "ready to convert (RGB-D layout)" in text
