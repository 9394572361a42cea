"""Which topics of a bag a conversion reads: the dVRK defaults, topics given on the command line, and
auto-detection by message type and name where neither is there."""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

from rosbags.highlevel import AnyReader

from vfdata.errors import InputError

log = logging.getLogger(__name__)

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
RGBD_DEPTH = "RGB-D depth"  # TopicChoice.how of an RGB-D bag's depth topic (vfdata.conversion.rgbd_bags)
NO_TOPIC = "none"  # `--pose-topic none`: leave the ECM pose out


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


def choose_force_and_pose(path: Path, types: dict[str, str], asked: BagTopics,
                          how: dict[str, str]) -> tuple[str, str | None]:
    """The force and (optional) pose topics, as `choose_topics` picks them (for RGB-D bags too)."""
    return _choose_force(path, types, asked.force, how), _choose_pose(path, types, asked.pose, how)


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
