"""`rgbd_calibration.yaml` of an RGB-D raw folder (docs/raw_layout.md): the intrinsics of the depth
camera and, when the folder has colour frames, of the colour camera, and the depth-to-colour transform
when it is known. Plain YAML (not OpenCV FileStorage), every value checked:

```yaml
depth: {width: 151, height: 151, fx: 582.62, fy: 582.69, cx: 75.0, cy: 75.0}  # pixels
color: {width: 224, height: 224, fx: 518.86, fy: 519.47, cx: 111.5, cy: 111.5} # optional
depth_to_color:          # optional: x_color = R x_depth + T; leave out when the views are not registered
  R: [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
  T: [25.0, 0.7, -0.3]
  units: mm              # of T: mm (default) or m
depth_unit_mm: 1.0       # optional: millimetres per depth PNG count (default 1: REP 118)
```

Other keys (e.g. `assumptions:`, a list of what the values rest on) are allowed and kept in the
recording's metadata as text."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from vfdata.calibration import PinholeCamera
from vfdata.errors import InputError
from vfdata.recording.messages import CameraInfo, TFMessage, TransformStamped

CALIBRATION_FILE = "rgbd_calibration.yaml"
_KNOWN = ("depth", "color", "depth_to_color", "depth_unit_mm")


@dataclass(frozen=True)
class RgbdCalibration:
    depth: PinholeCamera
    color: PinholeCamera | None = None
    depth_to_color_R: np.ndarray | None = None  # (3, 3)
    depth_to_color_T_mm: np.ndarray | None = None  # (3,)
    depth_unit_mm: float = 1.0
    notes: dict[str, str] = field(default_factory=dict)  # other keys, as text (JSON for non-text)

    @property
    def registered(self) -> bool:
        """True when the depth-to-colour transform is known."""
        return self.depth_to_color_R is not None

    @classmethod
    def load(cls, path: str | Path) -> RgbdCalibration:
        path = Path(path)
        if not path.is_file():
            raise InputError(path, "RGB-D calibration file not found (docs/raw_layout.md: rgbd_calibration.yaml)")
        try:
            data = yaml.safe_load(path.read_bytes().decode("utf-8-sig"))
        except UnicodeDecodeError as exc:
            raise InputError(path, f"not UTF-8 text (byte {exc.start})") from None
        except yaml.YAMLError as exc:
            raise InputError(path, f"not valid YAML ({str(exc).splitlines()[0]})") from None
        if not isinstance(data, dict) or "depth" not in data:
            raise InputError(path, "needs a 'depth' camera: {width, height, fx, fy, cx, cy}")
        depth = _camera(data["depth"], "depth", path)
        color = _camera(data["color"], "color", path) if data.get("color") is not None else None
        rotation = translation = None
        if data.get("depth_to_color") is not None:
            rotation, translation = _transform(data["depth_to_color"], path)
        unit = data.get("depth_unit_mm", 1.0)
        if isinstance(unit, bool) or not isinstance(unit, (int, float)) or not 0 < unit < 1e3:
            raise InputError(path, f"depth_unit_mm must be a positive number (mm per count), got {unit!r}")
        notes = {str(k): v if isinstance(v, str) else json.dumps(v) for k, v in data.items() if k not in _KNOWN}
        return cls(depth, color, rotation, translation, float(unit), notes)


def _number(block: dict, key: str, name: str, path: Path) -> float:
    value = block.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise InputError(path, f"{name}.{key} must be a number, got {value!r}")
    return float(value)


def _camera(block, name: str, path: Path) -> PinholeCamera:
    if not isinstance(block, dict):
        raise InputError(path, f"'{name}' must be a mapping {{width, height, fx, fy, cx, cy}}")
    width, height = (block.get(k) for k in ("width", "height"))
    for key, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise InputError(path, f"{name}.{key} must be a positive whole number, got {value!r}")
    fx, fy, cx, cy = (_number(block, k, name, path) for k in ("fx", "fy", "cx", "cy"))
    if fx <= 0 or fy <= 0:
        raise InputError(path, f"{name}: focal lengths fx = {fx:g}, fy = {fy:g} must be positive")
    return PinholeCamera(fx, fy, cx, cy, width, height)


def _transform(block, path: Path) -> tuple[np.ndarray, np.ndarray]:
    if not isinstance(block, dict) or "R" not in block or "T" not in block:
        raise InputError(path, "depth_to_color needs R (3x3) and T (3 numbers)")
    try:
        rotation = np.asarray(block["R"], dtype=np.float64).reshape(3, 3)
        translation = np.asarray(block["T"], dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise InputError(path, "depth_to_color: R must be 3x3 numbers and T 3 numbers") from None
    if not np.isfinite(rotation).all() or not np.isfinite(translation).all():
        raise InputError(path, "depth_to_color: NaN or inf value")
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-3) or np.linalg.det(rotation) < 0:
        raise InputError(path, "depth_to_color: R is not a rotation (R R^T = I, det R = 1)")
    units = block.get("units", "mm")
    if units not in ("mm", "m"):
        raise InputError(path, f"depth_to_color.units must be mm or m, not {units!r}")
    return rotation, translation * (1000.0 if units == "m" else 1.0)


def camera_info(camera: PinholeCamera, frame_id: str, stamp_ns: int) -> CameraInfo:
    """A distortion-free CameraInfo of `camera` (the views of an RGB-D folder are stored as they are)."""
    k = camera.K
    p = np.hstack([k, np.zeros((3, 1))])
    return CameraInfo(stamp_ns, frame_id, camera.height, camera.width, "plumb_bob", np.zeros(5), k, np.eye(3), p)


def depth_to_color_tf(calib: RgbdCalibration, depth_frame: str, color_frame: str, stamp_ns: int) -> TFMessage:
    """depth -> colour optical frame (metres), or no transform when the views are not registered.
    A transform parent -> child holds the child's pose in the parent: x_depth = R^T (x_color - T)."""
    if not calib.registered:
        return TFMessage([])
    rotation = calib.depth_to_color_R.T
    origin_m = -(rotation @ calib.depth_to_color_T_mm) / 1000.0
    quat = tuple(float(q) for q in Rotation.from_matrix(rotation).as_quat())
    return TFMessage([TransformStamped(stamp_ns, depth_frame, color_frame, tuple(float(v) for v in origin_m), quat)])
