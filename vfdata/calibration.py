"""Stereo calibration and the rectified pinhole camera model.

Conventions: pixel coordinates (u right, v down), camera frame x right, y down, z forward (OpenCV
and ROS optical frame); lengths in mm unless a name says otherwise. The *left rectified* camera is
the reference frame of every derived quantity (depth, clouds, tracks) in camera coordinates.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np

from vfdata.errors import InputError

_RECTIFIED_ATOL = 1e-9
DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)  # what OpenCV takes: none, plumb bob, rational, thin prism, tilted


def _node(fs: cv2.FileStorage, path: Path, name: str, required: bool = True):
    node = fs.getNode(name)
    if node.empty() and required:
        raise InputError(path, f"missing '{name}'")
    return node


def _integer(fs: cv2.FileStorage, path: Path, name: str) -> int:
    node = _node(fs, path, name)
    value = node.real() if node.isInt() or node.isReal() else None
    if value is None or not np.isfinite(value) or value != int(value):
        raise InputError(path, f"'{name}' must be a whole number")
    return int(value)


def _text(fs: cv2.FileStorage, path: Path, name: str, default: str) -> str:
    node = _node(fs, path, name, required=False)
    if node.empty():
        return default
    if not node.isString():
        raise InputError(path, f"'{name}' must be text")
    return node.string()


def _matrix(fs: cv2.FileStorage, path: Path, name: str, shape: tuple[int, ...] | None) -> np.ndarray:
    node = _node(fs, path, name)
    try:
        m = node.mat() if node.isMap() else None
    except (cv2.error, SystemError):
        m = None
    if m is None:
        raise InputError(path, f"'{name}' is not an OpenCV matrix (!!opencv-matrix with rows, cols, dt and as many "
                               "data values)")
    m = np.asarray(m, dtype=np.float64)
    if shape is not None and m.size != int(np.prod(shape)):
        raise InputError(path, f"'{name}' has {m.size} values, expected {int(np.prod(shape))}")
    return m.reshape(shape) if shape is not None else m.ravel()


def _cv2_problem(exc: BaseException) -> str:
    """OpenCV's parse error, e.g. "... in function 'calibration.yaml(7): Missing , between the
    elements'", as " (line 7: Missing , between the elements)"; "" when it says nothing useful."""
    text = str(exc.__cause__ or exc)
    found = re.search(r"\((\d+)\): ([^\n']+)", text)
    return f" (line {found[1]}: {found[2].strip()})" if found else ""


@dataclass(frozen=True)
class PinholeCamera:
    """A distortion-free pinhole camera (a rectified view). Intrinsics in pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def project(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points -> (N, 2) pixel (u, v); NaN for points at or behind the camera."""
        points = np.asarray(points, dtype=np.float64)
        z = points[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * points[:, 0] / z + self.cx
            v = self.fy * points[:, 1] / z + self.cy
        uv = np.stack([u, v], axis=1)
        uv[~(z > 0)] = np.nan
        return uv

    def in_mask(self, points: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """(N,) bool: the point projects to a pixel inside the image where `mask` is true."""
        uv = self.project(points)
        ok = np.isfinite(uv).all(axis=1)
        u = np.full(len(uv), -1, dtype=np.int64)
        v = np.full(len(uv), -1, dtype=np.int64)
        u[ok] = np.floor(uv[ok, 0] + 0.5).astype(np.int64)
        v[ok] = np.floor(uv[ok, 1] + 0.5).astype(np.int64)
        h, w = mask.shape[:2]
        ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
        visible = np.zeros(len(uv), dtype=bool)
        visible[ok] = mask[v[ok], u[ok]].astype(bool)
        return visible

    def backproject(self, depth_mm: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """Depth image (H, W) in mm -> (N, 3) camera-frame points (mm) of the pixels where the depth is
        finite and positive (and `mask` is true), in row-major pixel order."""
        depth = np.asarray(depth_mm, dtype=np.float32)
        valid = np.isfinite(depth) & (depth > 0)
        if mask is not None:
            valid &= mask.astype(bool)
        v, u = np.nonzero(valid)
        z = depth[v, u]
        x = (u.astype(np.float32) - np.float32(self.cx)) * z / np.float32(self.fx)
        y = (v.astype(np.float32) - np.float32(self.cy)) * z / np.float32(self.fy)
        return np.stack([x, y, z], axis=1)

    def depth_from_disparity(self, disparity_px: np.ndarray, baseline_mm: float) -> np.ndarray:
        """Rectified disparity (px) -> depth (mm); NaN where the disparity is not positive."""
        d = np.asarray(disparity_px, dtype=np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = np.float32(self.fx * baseline_mm) / d
        depth[~(d > 0)] = np.nan
        return depth


@dataclass(frozen=True)
class RectifiedStereo:
    """The rectified stereo pair: left view, baseline and the rectification of the raw views.

    `R1`, `R2` rotate raw camera coordinates into the rectified ones; `P1`, `P2` are the rectified
    3x4 projections with P2[0, 3] = -fx * baseline_mm (OpenCV; ROS uses metres there)."""

    left: PinholeCamera
    baseline_mm: float
    R1: np.ndarray = field(default_factory=lambda: np.eye(3))
    R2: np.ndarray = field(default_factory=lambda: np.eye(3))

    @property
    def P1(self) -> np.ndarray:
        return np.hstack([self.left.K, np.zeros((3, 1))])

    @property
    def P2(self) -> np.ndarray:
        p = self.P1.copy()
        p[0, 3] = -self.left.fx * self.baseline_mm
        return p


@dataclass(frozen=True, eq=False)
class StereoCalibration:
    """A raw stereo calibration (OpenCV conventions): T is the left-to-right translation in mm, i.e.
    x_right = R @ x_left + T; D are OpenCV (plumb_bob) distortion coefficients."""

    width: int
    height: int
    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    R: np.ndarray
    T: np.ndarray

    @classmethod
    def load(cls, path: str | Path) -> StereoCalibration:
        """Read `calibration.yaml` (OpenCV FileStorage: image_width, image_height, K1, D1, K2, D2, R,
        T, units mm|m). Raises InputError naming the file and the problem: an unreadable file, a
        missing or mistyped entry, or values no camera has (`check`)."""
        path = Path(path)
        if not path.is_file():
            raise InputError(path, "calibration file not found")
        path.open("rb").close()  # an unreadable file is said so (OSError), not "not a FileStorage file"
        try:
            fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        except (cv2.error, SystemError) as exc:  # OpenCV's parse errors come wrapped in a SystemError
            raise InputError(path, f"not a readable OpenCV FileStorage YAML file{_cv2_problem(exc)}") from None
        try:
            if not fs.isOpened():
                raise InputError(path, "not a readable OpenCV FileStorage YAML file")
            if not fs.root().isMap():
                raise InputError(path, "not a mapping of names to values (image_width, K1, D1, ...)")
            units = _text(fs, path, "units", "mm")
            if units not in ("mm", "m"):
                raise InputError(path, f"units must be 'mm' or 'm', not '{units}'")
            calib = cls(
                width=_integer(fs, path, "image_width"),
                height=_integer(fs, path, "image_height"),
                K1=_matrix(fs, path, "K1", (3, 3)),
                D1=_matrix(fs, path, "D1", None),
                K2=_matrix(fs, path, "K2", (3, 3)),
                D2=_matrix(fs, path, "D2", None),
                R=_matrix(fs, path, "R", (3, 3)),
                T=_matrix(fs, path, "T", (3,)) * (1000.0 if units == "m" else 1.0),
            )
        finally:
            fs.release()
        calib.check(path)
        return calib

    def check(self, path: str | Path) -> None:
        """InputError (naming `path`) unless this is a calibration a camera can have: positive image
        size; camera matrices [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0; 0, 4, 5, 8, 12
        or 14 distortion coefficients (OpenCV's models); R a rotation; T not zero; all finite."""
        if self.width <= 0 or self.height <= 0:
            raise InputError(path, "image_width and image_height must be positive")
        values = np.concatenate([self.K1.ravel(), self.K2.ravel(), self.R.ravel(), self.T, self.D1, self.D2])
        if not np.isfinite(values).all():
            raise InputError(path, "calibration holds NaN or inf")
        for name, K in (("K1", self.K1), ("K2", self.K2)):
            if not (K[0, 0] > 0 and K[1, 1] > 0):
                raise InputError(path, f"{name}: focal lengths fx = {K[0, 0]:g}, fy = {K[1, 1]:g} must be positive "
                                       "(a camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])")
            if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
                raise InputError(path, f"{name} is not a camera matrix: its last two rows must be [0, fy, cy], "
                                       "[0, 0, 1]")
        for name, D in (("D1", self.D1), ("D2", self.D2)):
            if len(D) not in DISTORTION_LENGTHS:
                raise InputError(path, f"{name} has {len(D)} coefficients; OpenCV's distortion models have "
                                       f"{', '.join(map(str, DISTORTION_LENGTHS[1:]))} (or none)")
        if not (np.allclose(self.R.T @ self.R, np.eye(3), atol=1e-3) and np.linalg.det(self.R) > 0):
            raise InputError(path, "R is not a rotation matrix (R^T R must be the identity, det R = 1)")
        if np.linalg.norm(self.T) <= 0:
            raise InputError(path, "T (left-to-right translation) is zero")

    def save(self, path: str | Path, units: str = "mm") -> None:
        scale = 1e-3 if units == "m" else 1.0
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        fs.write("image_width", int(self.width))
        fs.write("image_height", int(self.height))
        fs.write("K1", np.asarray(self.K1, dtype=np.float64))
        fs.write("D1", np.asarray(self.D1, dtype=np.float64).reshape(1, -1))
        fs.write("K2", np.asarray(self.K2, dtype=np.float64))
        fs.write("D2", np.asarray(self.D2, dtype=np.float64).reshape(1, -1))
        fs.write("R", np.asarray(self.R, dtype=np.float64))
        fs.write("T", np.asarray(self.T, dtype=np.float64).reshape(3, 1) * scale)
        fs.write("units", units)
        fs.release()

    @property
    def is_rectified(self) -> bool:
        """True when the views are already rectified: no distortion, no rotation, equal intrinsics,
        a purely horizontal baseline."""
        return (
            np.allclose(self.D1, 0, atol=_RECTIFIED_ATOL)
            and np.allclose(self.D2, 0, atol=_RECTIFIED_ATOL)
            and np.allclose(self.R, np.eye(3), atol=1e-9)
            and np.allclose(self.K1, self.K2, atol=1e-9)
            and abs(self.T[1]) < 1e-9
            and abs(self.T[2]) < 1e-9
        )

    @cached_property
    def rectified(self) -> RectifiedStereo:
        """The rectification (OpenCV stereoRectify, zero disparity at infinity, alpha 0: only valid
        pixels), or the identity when the views are already rectified."""
        if self.is_rectified:
            k = self.K1
            left = PinholeCamera(k[0, 0], k[1, 1], k[0, 2], k[1, 2], self.width, self.height)
            return RectifiedStereo(left=left, baseline_mm=float(abs(self.T[0])))
        R1, R2, P1, P2, _Q, _roi1, _roi2 = cv2.stereoRectify(
            self.K1, self.D1.reshape(1, -1), self.K2, self.D2.reshape(1, -1), (self.width, self.height), self.R,
            self.T.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0,
        )
        left = PinholeCamera(P1[0, 0], P1[1, 1], P1[0, 2], P1[1, 2], self.width, self.height)
        return RectifiedStereo(left=left, baseline_mm=float(-P2[0, 3] / P2[0, 0]), R1=R1, R2=R2)

    @cached_property
    def _maps(self) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
        rect = self.rectified
        size = (self.width, self.height)
        left = cv2.initUndistortRectifyMap(self.K1, self.D1, rect.R1, rect.P1, size, cv2.CV_16SC2)
        right = cv2.initUndistortRectifyMap(self.K2, self.D2, rect.R2, rect.P2, size, cv2.CV_16SC2)
        return left, right

    def rectify_pair(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raw images -> rectified images (unchanged when already rectified)."""
        if self.is_rectified:
            return left, right
        (l1, l2), (r1, r2) = self._maps
        return (
            cv2.remap(left, l1, l2, cv2.INTER_LINEAR),
            cv2.remap(right, r1, r2, cv2.INTER_LINEAR),
        )
