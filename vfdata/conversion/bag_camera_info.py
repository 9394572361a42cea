"""A bag's `sensor_msgs/CameraInfo` as the recording's CameraInfo, checked: the one reader of camera
models that stereo (`bags`) and RGB-D (`rgbd_bags`) bag conversion share."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vfdata.calibration import DISTORTION_LENGTHS
from vfdata.errors import InputError
from vfdata.recording.messages import CameraInfo


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
    if not (np.isfinite(info.k).all() and np.isfinite(info.d).all() and np.isfinite(info.r).all()
            and info.k[0, 0] > 0 and info.k[1, 1] > 0):
        raise InputError(path, f"{topic}: K has no positive focal length, or K, D or R hold NaN or inf (camera not "
                               "calibrated?); pass --calibration FILE")
    if len(info.d) not in DISTORTION_LENGTHS:
        raise InputError(path, f"{topic}: D has {len(info.d)} coefficients (OpenCV's models have 4, 5, 8, 12 or 14); "
                               "pass --calibration FILE")
    return info
