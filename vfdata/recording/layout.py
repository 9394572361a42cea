"""The VisionForce MCAP layout, version 1: topic names, message types, frame ids and the recording
metadata record. `docs/format.md` is the human-readable version of this module."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field

LAYOUT_VERSION = "1"
PROFILE = "ros2"
MESSAGE_ENCODING = "cdr"
SCHEMA_ENCODING = "ros2msg"

# Recording topics.
LEFT_IMAGE = "/stereo/left/image/compressed"
RIGHT_IMAGE = "/stereo/right/image/compressed"
LEFT_INFO = "/stereo/left/camera_info"
RIGHT_INFO = "/stereo/right/camera_info"
WRENCH = "/force_sensor/wrench"
ECM_POSE = "/ecm/measured_cp"
TF_STATIC = "/tf_static"
TF = "/tf"  # the ECM pose as a transform (recordings); the live view's object frame with every frame
ECM_FRAME = "ecm"  # child frame of the ECM pose on /tf (parent WORLD_FRAME)

RECORDING_TOPICS: dict[str, str] = {
    LEFT_IMAGE: "sensor_msgs/msg/CompressedImage",
    RIGHT_IMAGE: "sensor_msgs/msg/CompressedImage",
    LEFT_INFO: "sensor_msgs/msg/CameraInfo",
    RIGHT_INFO: "sensor_msgs/msg/CameraInfo",
    WRENCH: "geometry_msgs/msg/WrenchStamped",
    ECM_POSE: "geometry_msgs/msg/PoseStamped",
    TF: "tf2_msgs/msg/TFMessage",  # the ECM pose again, world -> ecm (files from before have none)
    TF_STATIC: "tf2_msgs/msg/TFMessage",
}
REQUIRED_TOPICS = (LEFT_IMAGE, RIGHT_IMAGE, LEFT_INFO, RIGHT_INFO, WRENCH, TF_STATIC)

# RGB-D recordings (a colour and a depth camera instead of a stereo pair), named as realsense-ros
# names them. The depth image is 16UC1 in millimetres (REP 118, 0 = no depth); the colour view is
# optional (a depth camera alone, or a colour crop that cannot be registered to the depth).
COLOR_IMAGE = "/camera/color/image/compressed"
COLOR_INFO = "/camera/color/camera_info"
DEPTH_IMAGE = "/camera/depth/image"
DEPTH_INFO = "/camera/depth/camera_info"

RGBD_TOPICS: dict[str, str] = {
    COLOR_IMAGE: "sensor_msgs/msg/CompressedImage",
    COLOR_INFO: "sensor_msgs/msg/CameraInfo",
    DEPTH_IMAGE: "sensor_msgs/msg/Image",
    DEPTH_INFO: "sensor_msgs/msg/CameraInfo",
    WRENCH: "geometry_msgs/msg/WrenchStamped",
    ECM_POSE: "geometry_msgs/msg/PoseStamped",
    TF: "tf2_msgs/msg/TFMessage",
    TF_STATIC: "tf2_msgs/msg/TFMessage",
}
RGBD_REQUIRED_TOPICS = (DEPTH_IMAGE, DEPTH_INFO, WRENCH, TF_STATIC)

# Derived topics (written by later stages into separate files beside the recording).
TISSUE_MASK = "/tissue/mask"
TISSUE_DEPTH = "/tissue/depth"
TISSUE_POINTS = "/tissue/points"
TRACKING_POINTS = "/tracking/points"
FORCE_ESTIMATE = "/force/estimate"
# Beside each estimate (same stamp, object frame, N; torque zeros): the half-width of its calibrated band
# (the estimate +- it covers the stated share of frames, 90%; NaN when the model has no calibration)
# and how far each component lies beyond the training forces' range (signed, 0 inside). Beside them, a
# bare number (log time = the estimate's stamp): how unlike training's the frame's input is, its
# embedding distance over the limit that 99% of validation's frames keep within (> 1: unlike training).
FORCE_BAND = "/force/estimate/band"
FORCE_BEYOND = "/force/estimate/beyond"
FORCE_UNLIKE = "/force/estimate/unlike"

DERIVED_TOPICS: dict[str, str] = {
    TISSUE_MASK: "sensor_msgs/msg/CompressedImage",
    TISSUE_DEPTH: "sensor_msgs/msg/Image",
    TISSUE_POINTS: "sensor_msgs/msg/PointCloud2",
    TRACKING_POINTS: "sensor_msgs/msg/PointCloud2",
    FORCE_ESTIMATE: "geometry_msgs/msg/WrenchStamped",
    FORCE_BAND: "geometry_msgs/msg/WrenchStamped",
    FORCE_BEYOND: "geometry_msgs/msg/WrenchStamped",
    FORCE_UNLIKE: "std_msgs/msg/Float64",
    TF_STATIC: "tf2_msgs/msg/TFMessage",
}

# What `vfdata live` serves (and its --record file holds, stage 'live'): the view it saw (the left
# image, or an RGB-D source's depth image) with its camera info, the derived topics, and the object
# frame on /tf with every frame (a client that connects later never sees a message sent once).
LIVE_TOPICS: dict[str, str] = {
    LEFT_IMAGE: "sensor_msgs/msg/CompressedImage",
    LEFT_INFO: "sensor_msgs/msg/CameraInfo",
    DEPTH_IMAGE: "sensor_msgs/msg/Image",
    DEPTH_INFO: "sensor_msgs/msg/CameraInfo",
    TISSUE_MASK: DERIVED_TOPICS[TISSUE_MASK],
    TISSUE_POINTS: DERIVED_TOPICS[TISSUE_POINTS],
    TRACKING_POINTS: DERIVED_TOPICS[TRACKING_POINTS],
    FORCE_ESTIMATE: DERIVED_TOPICS[FORCE_ESTIMATE],
    FORCE_BAND: DERIVED_TOPICS[FORCE_BAND],
    FORCE_BEYOND: DERIVED_TOPICS[FORCE_BEYOND],
    FORCE_UNLIKE: DERIVED_TOPICS[FORCE_UNLIKE],
    TF: "tf2_msgs/msg/TFMessage",
}

# Frame ids (tf tree: world -> left camera (ECM pose), left -> right, left -> object).
WORLD_FRAME = "world"
LEFT_FRAME = "stereo_left_optical"
RIGHT_FRAME = "stereo_right_optical"
SENSOR_FRAME = "force_sensor"
OBJECT_FRAME = "tissue_object"
COLOR_FRAME = "camera_color_optical_frame"
DEPTH_FRAME = "camera_depth_optical_frame"

RECORDING_METADATA = "visionforce.recording"
DERIVED_METADATA = "visionforce.derived"

UNITS = {
    "time": "ns since the Unix epoch (header.stamp == MCAP log_time)",
    "force": "N, sensor frame",
    "torque": "N*m, sensor frame",
    "ecm_pose": "m, camera pose in the world frame",
    "camera_info.p": "pixels; right P[0,3] = -fx * baseline in m (ROS)",
}
RGBD_UNITS = {**{k: v for k, v in UNITS.items() if k != "camera_info.p"},
              "depth_image": "16UC1, mm (REP 118), 0 = no depth", "camera_info.p": "pixels (ROS)"}


@dataclass
class RecordingMeta:
    """The `visionforce.recording` metadata record. MCAP metadata is a string map: scalars are
    written as text, lists and dicts as JSON."""

    recording_id: str = ""
    study: str = ""
    tissue: str = ""
    orientation_deg: float = 0.0
    split: str = ""
    source: str = ""
    converter: str = "vfdata"
    converter_version: str = ""
    layout_version: str = LAYOUT_VERSION
    gravity_up_world: tuple[float, float, float] = (0.0, 0.0, 1.0)
    units: dict[str, str] = field(default_factory=lambda: dict(UNITS))
    extra: dict[str, str] = field(default_factory=dict)

    def to_record(self) -> dict[str, str]:
        record = {}
        for key, value in asdict(self).items():
            if key == "extra":
                continue
            record[key] = json.dumps(list(value) if isinstance(value, tuple) else value) if isinstance(
                value, (tuple, list, dict)) else str(value)
        for key, value in self.extra.items():
            record.setdefault(key, str(value))
        return record

    @classmethod
    def from_record(cls, record: dict[str, str]) -> RecordingMeta:
        meta = cls()
        known = set(meta.__dataclass_fields__) - {"extra"}
        for key, text in record.items():
            if key not in known:
                meta.extra[key] = text
            elif key == "orientation_deg":
                meta.orientation_deg = float(text) if text else 0.0
            elif key == "gravity_up_world":
                meta.gravity_up_world = tuple(float(v) for v in json.loads(text))
            elif key == "units":
                meta.units = json.loads(text)
            else:
                setattr(meta, key, text)
        return meta
