"""Tissue on a flat board, seen by a depth camera: the board's plane, the tissue mask as what stands
above it (`PlaneSegmenter`, backend `plane`), and the board frame (normal = up) that replaces the
tube's object frame for a flat organ (docs/reconstruction.md, "RGB-D: the board").

A plane in the camera frame is a plane in inverse depth over the pixels: for n.p + d = 0 and
p = z ((u - cx) / fx, (v - cy) / fy, 1), 1/z = a u + b v + c. So the board is fitted (RANSAC, then
least squares on its inliers) as 1/z linear in (u, v), without the intrinsics; `plane_in_camera` turns
it into a metric plane with them. Depths in mm, NaN = unknown."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vfdata.calibration import PinholeCamera
from vfdata.errors import InputError
from vfdata.recon.object_frame import ObjectFrame
from vfdata.recon.prompt import Prompt
from vfdata.recon.segmenter import Segmenter

MIN_PLANE_PIXELS = 50


@dataclass(frozen=True)
class InverseDepthPlane:
    """1/z = a u + b v + c (z in mm, u, v in pixels)."""

    a: float
    b: float
    c: float
    inlier_fraction: float  # of the pixels with depth used in the fit

    def depth_mm(self, shape: tuple[int, int]) -> np.ndarray:
        """The board's depth at every pixel of an image of `shape` (NaN behind the camera)."""
        v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
        inverse = self.a * u + self.b * v + self.c
        with np.errstate(divide="ignore"):
            return np.where(inverse > 0, 1.0 / inverse, np.nan)


def fit_board_plane(depth_mm: np.ndarray, exclude: np.ndarray | None = None, tolerance_mm: float = 3.0,
                    iterations: int = 300, seed: int = 0) -> InverseDepthPlane:
    """The dominant plane of a depth image (RANSAC over `iterations` triples, inliers within
    `tolerance_mm` along the ray, refitted by least squares), leaving out the `exclude` pixels."""
    depth = np.asarray(depth_mm, dtype=np.float64)
    valid = np.isfinite(depth) & (depth > 0)
    if exclude is not None:
        valid &= ~np.asarray(exclude, bool)
    v, u = np.nonzero(valid)
    if len(u) < MIN_PLANE_PIXELS:
        raise InputError("depth", f"only {len(u)} pixels with depth: no board plane can be fitted")
    z = depth[v, u]
    design = np.stack([u, v, np.ones_like(u)], axis=1).astype(np.float64)
    target = 1.0 / z
    rng = np.random.default_rng(seed)
    best, best_count = None, -1
    for _ in range(iterations):
        pick = rng.choice(len(u), 3, replace=False)
        try:
            coeffs = np.linalg.solve(design[pick], target[pick])
        except np.linalg.LinAlgError:
            continue
        inliers = _inliers(design, z, coeffs, tolerance_mm)
        count = int(inliers.sum())
        if count > best_count:
            best, best_count = inliers, count
    coeffs = np.linalg.lstsq(design[best], target[best], rcond=None)[0]
    inliers = _inliers(design, z, coeffs, tolerance_mm)
    coeffs = np.linalg.lstsq(design[inliers], target[inliers], rcond=None)[0]
    return InverseDepthPlane(*(float(c) for c in coeffs), float(inliers.mean()))


def _inliers(design: np.ndarray, z: np.ndarray, coeffs: np.ndarray, tolerance_mm: float) -> np.ndarray:
    inverse = design @ coeffs
    with np.errstate(divide="ignore"):
        plane_z = np.where(inverse > 0, 1.0 / inverse, np.inf)
    return np.abs(plane_z - z) <= tolerance_mm


def plane_in_camera(plane: InverseDepthPlane, camera: PinholeCamera) -> tuple[np.ndarray, float]:
    """(n, d) with n.p + d = 0 for camera-frame points p in mm, |n| = 1 and n pointing to the camera's
    side of the board (d > 0): the board's up."""
    normal = np.array([plane.a * camera.fx, plane.b * camera.fy,
                       plane.a * camera.cx + plane.b * camera.cy + plane.c])
    length = float(np.linalg.norm(normal))
    normal, offset = normal / length, -1.0 / length
    if offset < 0:
        normal, offset = -normal, -offset
    return normal, offset


def board_frame(plane: InverseDepthPlane, camera: PinholeCamera, tissue_cloud_mm: np.ndarray) -> ObjectFrame:
    """The board frame: Z = the board's normal towards the camera (up, for a level board), origin = the
    tissue's centroid dropped onto the board, X = the camera's x axis laid into the board (image right),
    Y = Z x X. Coordinates in mm; Z of a point is its height above the board."""
    normal, offset = plane_in_camera(plane, camera)
    cloud = np.asarray(tissue_cloud_mm, dtype=np.float64)
    centroid = cloud.mean(axis=0)
    origin = centroid - (normal @ centroid + offset) * normal
    x_axis = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(normal, x_axis)
    tilt = float(np.degrees(np.arccos(np.clip(-normal[2], -1.0, 1.0))))
    return ObjectFrame(np.stack([x_axis, y_axis, normal], axis=1), origin, False, float("nan"),
                       {"kind": "board_plane", "view_tilt_deg": tilt, "board_inliers": plane.inlier_fraction})


def camera_frame() -> ObjectFrame:
    """The camera frame itself, as an ObjectFrame (identity), for recordings with no object frame."""
    return ObjectFrame(np.eye(3), np.zeros(3), False, float("nan"), {"kind": "camera"})


def _largest_component(mask: np.ndarray, near: np.ndarray | None = None) -> np.ndarray:
    """The largest connected region of `mask` (the one overlapping `near` most, when given)."""
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if count <= 1:
        return np.zeros_like(mask, bool)
    areas = stats[1:, cv2.CC_STAT_AREA].astype(np.float64)
    if near is not None and near.any():
        overlap = np.bincount(labels[near].ravel(), minlength=count)[1:]
        if overlap.any():
            areas = overlap.astype(np.float64)
    return labels == 1 + int(np.argmax(areas))


class PlaneSegmenter(Segmenter):
    """Tissue = what stands between `min_height_mm` and `max_height_mm` above the board (along the
    camera's rays) inside the prompt's box: the largest such region on the first frame, then the one
    overlapping the previous mask most. The board is fitted once, on the first frame's depth outside
    the box when enough of it lies there (else on the whole frame); the camera must not move. A frame
    whose board outside the box no longer lies on that plane (under `board_share` of the first frame's
    share of pixels on it: a glitched depth frame, a moved camera) gets an empty mask, so the cloud is
    empty and the trackers hold their points as not visible; `glitched_frames` lists them. Needs
    depth; the image is not used (so a colour view that is not registered to the depth does no harm)."""

    name = "plane"

    def __init__(self, min_height_mm: float = 6.0, max_height_mm: float = 150.0, tolerance_mm: float = 3.0,
                 open_px: int = 1, board_share: float = 0.5, seed: int = 0):
        self.min_height_mm, self.max_height_mm = float(min_height_mm), float(max_height_mm)
        self.board_share = float(board_share)
        self.glitched_frames: list[int] = []
        self._frame = 0
        self._first_share = 0.0
        self.tolerance_mm, self.open_px, self.seed = float(tolerance_mm), int(open_px), int(seed)
        self.plane: InverseDepthPlane | None = None
        self._box: np.ndarray | None = None
        self._previous: np.ndarray | None = None

    def start(self, image: np.ndarray, prompt: Prompt, depth_mm: np.ndarray | None = None) -> np.ndarray:
        if depth_mm is None:
            raise InputError("segment plane", "the plane segmenter needs the depth image")
        h, w = depth_mm.shape
        self._box = np.ones((h, w), bool)
        if prompt.box is not None:
            x0, y0, x1, y1 = (int(round(v)) for v in prompt.box)
            self._box = np.zeros((h, w), bool)
            self._box[max(0, y0):min(h, y1), max(0, x0):min(w, x1)] = True
        outside = ~self._box & np.isfinite(depth_mm)
        exclude = self._box if outside.sum() >= max(MIN_PLANE_PIXELS, 0.1 * h * w) else None
        self.plane = fit_board_plane(depth_mm, exclude, self.tolerance_mm, seed=self.seed)
        self._outside = ~self._box if exclude is not None else np.ones((h, w), bool)
        self._first_share = self._share_on_board(depth_mm)
        self.glitched_frames, self._frame = [], 0
        self._previous = None
        mask = self._mask(depth_mm)
        if prompt.positive:
            seeds = np.zeros_like(mask)
            for x, y in prompt.positive:
                seeds[min(h - 1, max(0, int(y))), min(w - 1, max(0, int(x)))] = True
            mask = _largest_component(mask, seeds)
        self._previous = mask
        return mask

    def track(self, image: np.ndarray, depth_mm: np.ndarray | None = None) -> np.ndarray:
        if self.plane is None or depth_mm is None:
            raise InputError("segment plane", "track before start, or no depth image")
        self._frame += 1
        if self._share_on_board(depth_mm) < self.board_share * self._first_share:
            self.glitched_frames.append(self._frame)
            return np.zeros(depth_mm.shape, bool)
        self._previous = self._mask(depth_mm)
        return self._previous

    def _share_on_board(self, depth_mm: np.ndarray) -> float:
        """Share of the valid pixels outside the box within the tolerance of the first frame's board."""
        valid = self._outside & np.isfinite(depth_mm)
        if not valid.any():
            return 0.0
        board = self.plane.depth_mm(depth_mm.shape)
        with np.errstate(invalid="ignore"):
            return float((np.abs(board[valid] - depth_mm[valid]) <= self.tolerance_mm).mean())

    def _mask(self, depth_mm: np.ndarray) -> np.ndarray:
        height = self.plane.depth_mm(depth_mm.shape) - depth_mm
        with np.errstate(invalid="ignore"):
            above = (height >= self.min_height_mm) & (height <= self.max_height_mm) & self._box
        if self.open_px > 0:
            kernel = np.ones((2 * self.open_px + 1,) * 2, np.uint8)
            above = cv2.morphologyEx(above.astype(np.uint8), cv2.MORPH_OPEN, kernel) > 0
        return _largest_component(above, self._previous)

    def parameters(self) -> dict:
        plane = None if self.plane is None else [self.plane.a, self.plane.b, self.plane.c]
        return {"backend": self.name, "min_height_mm": self.min_height_mm, "max_height_mm": self.max_height_mm,
                "tolerance_mm": self.tolerance_mm, "open_px": self.open_px, "board_share": self.board_share,
                "inverse_depth_plane": plane, "glitched_frames": list(self.glitched_frames)}
