"""Stage 4: the object frame of the tissue: a right-handed frame on its axis (the paper's).

Z is the tissue's centreline (`vfdata.recon.tube_axis`), running from the clamped (wide) end to the free
one; the origin is the centreline point at the 2nd percentile of the cloud's projections on Z; X is
gravity-up made perpendicular to Z (Gram-Schmidt), Y = Z x X. `estimate_object_frame` is the paper's
method (the end by the taper alone); `vfdata.recon.tissue_frame` decides the axis and the end from more
cues, and says how sure it is.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from vfdata.errors import InputError
from vfdata.recon.tube_axis import CANDIDATE_STEPS, TubeAxis, slab_widths, tube_axis


@dataclass(frozen=True)
class ObjectFrame:
    """A right-handed frame attached to the tissue, expressed in the input (camera) coordinates.

    `rotation` (3, 3) has columns X, Y, Z; `origin` (3,) is in the input units (mm). A point p in
    input coordinates has object coordinates rotation.T @ (p - origin)."""

    rotation: np.ndarray
    origin: np.ndarray
    up_known: bool
    score_deg: float  # the chosen candidate's angle between slicing direction and centreline
    diagnostics: dict = field(default_factory=dict, compare=False)

    @property
    def kind(self) -> str:
        """'tissue' (the tube's frame, above), 'board_plane' or 'camera' (vfdata.recon.plane)."""
        return self.diagnostics.get("kind", "tissue")

    @property
    def z_axis(self) -> np.ndarray:
        return self.rotation[:, 2]

    @property
    def x_axis(self) -> np.ndarray:
        return self.rotation[:, 0]

    def to_object(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) input (camera) coordinates -> object coordinates, same units."""
        return (np.asarray(points, dtype=np.float64) - self.origin) @ self.rotation

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) object coordinates -> input (camera) coordinates."""
        return np.asarray(points, dtype=np.float64) @ self.rotation.T + self.origin

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous transform object -> input (camera) coordinates."""
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.origin
        return m

    def to_dict(self) -> dict:
        return {
            "rotation": self.rotation.tolist(),
            "origin": self.origin.tolist(),
            "up_known": self.up_known,
            "score_deg": self.score_deg,
        }

    @classmethod
    def from_dict(cls, values: dict) -> ObjectFrame:
        """The inverse of `to_dict` (e.g. the `object_frame` of a derived MCAP's metadata)."""
        return cls(np.asarray(values["rotation"], dtype=np.float64), np.asarray(values["origin"], dtype=np.float64),
                   bool(values["up_known"]), float(values["score_deg"]))


# What X is, by the frame's kind (a derived MCAP's `object_frame_kind`); before ':' the short form.
_X_AXIS = {"board_plane": "the image's right: the camera's x made perpendicular to the board's normal Z",
           "camera": "the image's right: the camera frame itself"}


def x_axis_meaning(kind: str, up_known: bool) -> str:
    """What a frame's X axis means, in words, for its kind ('tissue', 'board_plane', 'camera')."""
    if kind in _X_AXIS:
        return _X_AXIS[kind]
    return ("gravity up: from the ECM pose, made perpendicular to Z" if up_known else
            "arbitrary: the image's up direction made perpendicular to Z (no ECM pose)")


def frame_on_axis(axis: TubeAxis, points: np.ndarray, up: np.ndarray | None, clamped_low: bool,
                  diagnostics: dict | None = None) -> ObjectFrame:
    """The object frame on a tissue axis: +Z from the clamped end to the free one (`clamped_low`: the
    clamped end lies at the low end of `axis.direction`), the origin the centreline point at the 2nd
    percentile of the (N, 3) cloud's projections on Z, X gravity-up made perpendicular to Z (`up` in the
    cloud's coordinates; None: the image's up, -y of the camera, and `up_known` False), Y = Z x X."""
    z = axis.direction if clamped_low else -axis.direction
    pts = np.asarray(points, dtype=np.float64)
    proj = (pts[np.isfinite(pts).all(axis=1)] - axis.point) @ z
    origin = axis.point + np.percentile(proj, 2) * z
    up_known = up is not None
    ref = np.asarray(up, dtype=np.float64) if up_known else np.array([0.0, -1.0, 0.0])
    x = ref - (ref @ z) * z
    # Within 5 degrees of the axis, "up made perpendicular to Z" is dominated by noise.
    if np.linalg.norm(x) < np.sin(np.radians(5.0)) * np.linalg.norm(ref):
        if up_known:
            raise InputError(
                "up vector", "gravity-up is (nearly) parallel to the tissue axis: X is undefined"
            )
        ref = np.array([1.0, 0.0, 0.0])
        x = ref - (ref @ z) * z
    x /= np.linalg.norm(x)
    rotation = np.stack([x, np.cross(z, x), z], axis=1)
    return ObjectFrame(rotation=rotation, origin=origin, up_known=up_known, score_deg=axis.score_deg,
                       diagnostics=dict(diagnostics or {}))


def estimate_object_frame(
    points: np.ndarray, up: np.ndarray | None = None, *, steps: int = CANDIDATE_STEPS, refine: int = 3,
    size_points: np.ndarray | None = None,
) -> ObjectFrame:
    """The paper's object frame of an (N, 3) tissue cloud: its axis (`vfdata.recon.tube_axis`), +Z toward
    the narrower end (the silhouette's width falls along +Z), and `frame_on_axis`. `size_points` (M, 3),
    when given, are the cloud whose silhouette widths decide which end is the wide one (default: `points`).
    The product decides the end from more cues than the taper (`vfdata.recon.tissue_frame`)."""
    axis = tube_axis(points, steps=steps, refine=refine)
    pts = np.asarray(points, dtype=np.float64)
    centre = pts[np.isfinite(pts).all(axis=1)].mean(axis=0)
    sized = pts if size_points is None else np.asarray(size_points, dtype=np.float64)
    sized = sized[np.isfinite(sized).all(axis=1)] - centre
    t, size = slab_widths(sized, axis.direction, view=centre)
    slope = trimmed_slope(t, size)
    return frame_on_axis(axis, pts, up, clamped_low=slope <= 0, diagnostics={
        "size_slope": float(slope), "slab_t_mm": t.tolist(), "slab_width_mm": size.tolist(),
        "candidates": steps * steps, "points_used": axis.points_used})


def origin_cut_by_view(points: np.ndarray, frame: ObjectFrame, camera, margin_px: float = 8.0,
                       band_mm: float = 5.0, share: float = 0.05) -> bool:
    """True when the tissue may run out of the image at its wide end: at least `share` of the cloud's
    points (N, 3, camera frame, mm) within `band_mm` of the origin along Z project within `margin_px`
    of the image border (`camera`: a `vfdata.calibration.PinholeCamera`; the margin allows for the
    few pixels the mask and the cloud lose at the border). The origin, the 2nd percentile of what is
    visible, may then mark where the view cuts the tissue rather than its clamped end, shifting every
    object-frame z by the hidden length, which the image cannot tell (on glove: 20.5 mm on glove_016,
    1.3 mm on glove_017, both flagged)."""
    pts = np.asarray(points, dtype=np.float64)
    near = pts[frame.to_object(pts)[:, 2] < band_mm]
    if len(near) == 0:
        return False
    uv = camera.project(near)
    ok = np.isfinite(uv).all(axis=1)
    u, v = uv[ok, 0], uv[ok, 1]
    edge = (u < margin_px) | (v < margin_px) | (u > camera.width - 1 - margin_px) | (v > camera.height - 1 - margin_px)
    return bool(edge.mean() >= share) if len(edge) else False


def trimmed_slope(t: np.ndarray, size: np.ndarray) -> float:
    """Theil-Sen slope of size against t over the inner 80% of the slabs (the ends are the rounded
    tip and the clamp or cut, which say nothing about the taper)."""
    if len(t) < 4:
        return 0.0
    trim = max(1, len(t) // 10)
    t, size = np.asarray(t)[trim:-trim], np.asarray(size)[trim:-trim]
    i, j = np.triu_indices(len(t), k=1)
    dt = t[j] - t[i]
    ok = dt != 0
    return float(np.median((size[j] - size[i])[ok] / dt[ok])) if ok.any() else 0.0


def up_in_camera(quat_xyzw: np.ndarray, world_up: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Gravity-up in camera coordinates from the camera's pose: `quat_xyzw` rotates camera
    coordinates into the world frame (a ROS pose of the camera in the world), `world_up` is the
    world's up direction. Returns a unit 3-vector."""
    q = np.asarray(quat_xyzw, dtype=np.float64)
    norm = np.linalg.norm(q)
    if q.shape != (4,) or not np.isfinite(q).all() or norm < 1e-9:
        raise InputError(
            "ECM pose", f"orientation quaternion {q.tolist()} is not a valid (x, y, z, w) rotation"
        )
    up = Rotation.from_quat(q / norm).as_matrix().T @ np.asarray(world_up, dtype=np.float64)
    return up / np.linalg.norm(up)
