"""ROS 2 message definitions (schema encoding `ros2msg`), as `ros2 bag` writes them into MCAP.

Each schema is the top-level definition followed by the definitions it depends on, each preceded by
a line of 80 `=` and `MSG: package/Type` (the concatenated format of rosbag2 and Foxglove)."""

from __future__ import annotations

_DEFS: dict[str, str] = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/Float64": "float64 data\n",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/Pose": "Point position\nQuaternion orientation\n",
    "geometry_msgs/PoseStamped": "std_msgs/Header header\nPose pose\n",
    "geometry_msgs/Wrench": "Vector3 force\nVector3 torque\n",
    "geometry_msgs/WrenchStamped": "std_msgs/Header header\nWrench wrench\n",
    "geometry_msgs/Transform": "Vector3 translation\nQuaternion rotation\n",
    "geometry_msgs/TransformStamped": "std_msgs/Header header\nstring child_frame_id\nTransform transform\n",
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "sensor_msgs/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n",
    "sensor_msgs/Image": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\n"
        "uint32 step\nuint8[] data\n"
    ),
    "sensor_msgs/RegionOfInterest": (
        "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n"
    ),
    "sensor_msgs/CameraInfo": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\n"
        "float64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\n"
        "RegionOfInterest roi\n"
    ),
    "sensor_msgs/PointField": (
        "uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\nuint8 INT32=5\nuint8 UINT32=6\n"
        "uint8 FLOAT32=7\nuint8 FLOAT64=8\nstring name\nuint32 offset\nuint8 datatype\nuint32 count\n"
    ),
    "sensor_msgs/PointCloud2": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nPointField[] fields\nbool is_bigendian\n"
        "uint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n"
    ),
}

# Which definitions each type pulls in, in the order they are appended.
_DEPS: dict[str, list[str]] = {
    "std_msgs/Float64": [],
    "geometry_msgs/PoseStamped": [
        "std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Pose", "geometry_msgs/Point",
        "geometry_msgs/Quaternion",
    ],
    "geometry_msgs/WrenchStamped": [
        "std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Wrench", "geometry_msgs/Vector3",
    ],
    "geometry_msgs/TransformStamped": [
        "std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Transform", "geometry_msgs/Vector3",
        "geometry_msgs/Quaternion",
    ],
    "tf2_msgs/TFMessage": [
        "geometry_msgs/TransformStamped", "std_msgs/Header", "builtin_interfaces/Time",
        "geometry_msgs/Transform", "geometry_msgs/Vector3", "geometry_msgs/Quaternion",
    ],
    "sensor_msgs/CompressedImage": ["std_msgs/Header", "builtin_interfaces/Time"],
    "sensor_msgs/Image": ["std_msgs/Header", "builtin_interfaces/Time"],
    "sensor_msgs/CameraInfo": ["std_msgs/Header", "builtin_interfaces/Time", "sensor_msgs/RegionOfInterest"],
    "sensor_msgs/PointCloud2": ["std_msgs/Header", "builtin_interfaces/Time", "sensor_msgs/PointField"],
}

_SEPARATOR = "=" * 80


def schema_text(msgtype: str) -> str:
    """The concatenated ros2msg definition of `msgtype` ('pkg/msg/Type' or 'pkg/Type')."""
    short = msgtype.replace("/msg/", "/")
    if short not in _DEFS:
        raise ValueError(f"no ros2msg definition for {msgtype} (the layout's types: {', '.join(sorted(_DEPS))})")
    parts = [_DEFS[short]]
    for dep in _DEPS.get(short, []):
        parts.append(f"{_SEPARATOR}\nMSG: {dep}\n{_DEFS[dep]}")
    return "".join(parts)

