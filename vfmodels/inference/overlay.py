"""The force drawn on the video (the paper's Fig. 8): an arrow for the in-plane part, a circle for the
part along the optical axis, with a legend and a scale, and the measured force beside the estimate
when the recording has one; written as an MP4."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from vfdata.errors import VisionForceError
from vfdata.recon.preview import draw_label

ESTIMATE_COLOUR = (0, 220, 255)  # BGR: amber arrow
MEASURED_COLOUR = (255, 255, 255)  # white arrow
TOWARD_COLOUR, AWAY_COLOUR = (60, 60, 230), (60, 200, 60)  # circle: red toward the camera, green away


def force_to_camera(force_object_n: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """(..., 3) forces in the object frame -> left camera frame. `rotation` (3, 3) has the object
    axes X, Y, Z as columns in camera coordinates (`ObjectFrame.rotation`)."""
    return np.asarray(force_object_n, dtype=np.float64) @ np.asarray(rotation, dtype=np.float64).T


def overlay_scale(force_camera_n: np.ndarray, image_width: int) -> float:
    """Pixels per newton so that the largest in-plane force (99th percentile) spans a fifth of the
    image width: readable arrows whatever the force range of the recording."""
    force = np.asarray(force_camera_n, dtype=np.float64).reshape(-1, 3)
    magnitude = np.linalg.norm(force[np.isfinite(force).all(axis=1)], axis=1)
    big = float(np.percentile(magnitude, 99)) if len(magnitude) else 0.0
    return 0.2 * image_width / big if big > 1e-6 else 40.0


def _draw_force(out: np.ndarray, origin: tuple[int, int], force: np.ndarray, px_per_n: float,
                colour: tuple[int, int, int], thickness: int) -> None:
    if not np.isfinite(force).all():
        return
    radius = int(round(px_per_n * abs(force[2])))
    if radius > 0:
        cv2.circle(out, origin, radius, AWAY_COLOUR if force[2] > 0 else TOWARD_COLOUR, thickness, cv2.LINE_AA)
    tip = (int(round(origin[0] + px_per_n * force[0])), int(round(origin[1] + px_per_n * force[1])))
    if tip != origin:
        cv2.arrowedLine(out, origin, tip, colour, thickness + 1, cv2.LINE_AA, tipLength=0.2)


def _legend(out: np.ndarray, px_per_n: float, measured: bool) -> None:
    h, w = out.shape[:2]
    newtons = next(n for n in (0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 50, 100) if n * px_per_n >= 0.08 * w)
    length = int(round(newtons * px_per_n))
    x0, y0 = 12, h - 16
    cv2.line(out, (x0, y0), (x0 + length, y0), (255, 255, 255), 2, cv2.LINE_AA)
    draw_label(out, f"{newtons:g} N", (x0 + length + 6, y0 + 5))
    lines = [("arrow: estimated force in the image plane", ESTIMATE_COLOUR)]
    if measured:
        lines.append(("white arrow: measured", MEASURED_COLOUR))
    lines.append(("circle: force along the view axis (green away, red toward)", (200, 200, 200)))
    for k, (text, colour) in enumerate(reversed(lines)):
        draw_label(out, text, (x0, y0 - 20 - 18 * k), colour=colour, scale=0.42)


def draw_force_overlay(image_bgr: np.ndarray, origin_uv: tuple[float, float], force_camera_n: np.ndarray,
                       px_per_n: float = 40.0, label: str | None = None,
                       measured_camera_n: np.ndarray | None = None, legend: bool = True) -> np.ndarray:
    """A copy of `image_bgr` with the force drawn at `origin_uv` (pixels), as the paper's Fig. 8.

    The in-plane part (Fx, Fy of the camera frame: right, down) is an arrow of `px_per_n` pixels per
    newton; the part along the optical axis is a circle of radius `px_per_n` * |Fz|, green when the
    force points away from the camera (into the scene), red when it points toward it. The measured
    force, when given, is drawn thinner in white. A legend and a scale bar (bottom left) say so; a NaN
    force draws only the origin marker."""
    out = np.ascontiguousarray(image_bgr).copy()
    origin = (int(round(origin_uv[0])), int(round(origin_uv[1])))
    cv2.drawMarker(out, origin, (255, 255, 255), cv2.MARKER_CROSS, 10, 1, cv2.LINE_AA)
    if measured_camera_n is not None:
        _draw_force(out, origin, np.asarray(measured_camera_n, dtype=np.float64), px_per_n, MEASURED_COLOUR, 1)
    _draw_force(out, origin, np.asarray(force_camera_n, dtype=np.float64), px_per_n, ESTIMATE_COLOUR, 2)
    if legend:
        _legend(out, px_per_n, measured_camera_n is not None)
    if label:
        draw_label(out, label, (10, 24), scale=0.6)
    return out


class OverlayVideo:
    """An MP4 (mp4v) writer for overlay frames; the size comes from the first frame. Written to a
    temporary name and renamed on close, like every other output."""

    def __init__(self, path: str | Path, fps: float = 30.0):
        self.path = Path(path)
        self.tmp = self.path.with_name(f".{self.path.stem}.partial{self.path.suffix}")
        self.fps = fps
        self.writer = None
        self.frames = 0

    def write(self, image_bgr: np.ndarray) -> None:
        if self.writer is None:
            h, w = image_bgr.shape[:2]
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.writer = cv2.VideoWriter(str(self.tmp), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, (w, h))
            if not self.writer.isOpened():
                raise VisionForceError(f"{self.path}: OpenCV cannot write mp4v video here")
        self.writer.write(np.ascontiguousarray(image_bgr))
        self.frames += 1

    def close(self) -> Path:
        if self.writer is not None:
            self.writer.release()
            self.tmp.replace(self.path)
        return self.path

    def __enter__(self) -> OverlayVideo:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        elif self.writer is not None:
            self.writer.release()
            self.tmp.unlink(missing_ok=True)
