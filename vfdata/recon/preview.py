"""A picture of what processing decided on the first frame: the tissue mask, the prompt, the object
frame and the tracked points, drawn on the left image.

Everything downstream rests on these first-frame decisions, and a wrong one is obvious to the eye
and hard to see in numbers: a mask that took in the bed beside the tissue, or an object frame whose
+Z points the wrong way, gives plausible-looking tracks and a model that fails on that recording.
`vfdata process` writes this picture beside the derived MCAP."""

from __future__ import annotations

import cv2
import numpy as np

from vfdata.calibration import PinholeCamera
from vfdata.recon.object_frame import ObjectFrame, x_axis_meaning

# BGR; the axes in the usual RGB = XYZ convention.
AXIS_COLOURS = ((60, 60, 235), (60, 200, 60), (235, 120, 40))
MASK_COLOUR = (80, 220, 80)
BOX_COLOUR = (0, 220, 255)
POINT_COLOUR = (255, 255, 0)


def first_frame_preview(image_bgr: np.ndarray, mask: np.ndarray, camera: PinholeCamera, frame: ObjectFrame,
                        points_mm: np.ndarray | None = None, box: tuple[float, float, float, float] | None = None,
                        axis_mm: float = 20.0, warning: str | None = None) -> np.ndarray:
    """A copy of the left image (H, W, 3) with: the mask tinted and outlined, the prompt `box`
    (x0, y0, x1, y1 px), the object frame's axes drawn `axis_mm` long from its origin (X red, Y green,
    Z blue; all in the left camera frame, mm), the tracked `points_mm` (N, 3) as dots, and a
    `warning` line in red."""
    out = np.ascontiguousarray(image_bgr).copy()
    inside = np.asarray(mask, dtype=bool)
    out[inside] = (0.6 * out[inside] + 0.4 * np.array(MASK_COLOUR)).astype(np.uint8)
    contours, _ = cv2.findContours(inside.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(out, contours, -1, MASK_COLOUR, 1, cv2.LINE_AA)
    if box is not None:
        x0, y0, x1, y1 = (int(round(v)) for v in box)
        cv2.rectangle(out, (x0, y0), (x1, y1), BOX_COLOUR, 1, cv2.LINE_AA)
    if points_mm is not None and len(points_mm):
        for u, v in camera.project(points_mm):
            if np.isfinite(u) and np.isfinite(v):
                cv2.circle(out, (int(round(u)), int(round(v))), 2, POINT_COLOUR, -1, cv2.LINE_AA)
    ends = frame.origin + axis_mm * frame.rotation.T  # rows: the tips of X, Y, Z
    uv = camera.project(np.vstack([frame.origin, ends]))
    if np.isfinite(uv).all():
        origin = tuple(int(round(c)) for c in uv[0])
        for (u, v), colour, name in zip(uv[1:], AXIS_COLOURS, "XYZ", strict=True):
            tip = (int(round(u)), int(round(v)))
            cv2.arrowedLine(out, origin, tip, colour, 2, cv2.LINE_AA, tipLength=0.15)
            draw_label(out, name, (tip[0] + 4, tip[1] + 4), colour)
        cv2.circle(out, origin, 4, (255, 255, 255), -1, cv2.LINE_AA)
    kind = frame.kind
    found = f"search score {frame.score_deg:.1f} deg, " if kind == "tissue" else f"{kind}, "
    draw_label(out, f"mask {int(inside.sum())} px; object frame: {found}X {x_axis_meaning(kind, frame.up_known)}",
               (8, 20))
    draw_label(out, f"axes {axis_mm:g} mm: X red, Y green, Z blue (wide end -> narrow); "
               f"{0 if points_mm is None else len(points_mm)} tracked points", (8, 40))
    if warning:
        draw_label(out, f"warning: {warning}", (8, 60), (90, 90, 255))
    return out


def draw_label(image: np.ndarray, text: str, at: tuple[int, int], colour: tuple[int, int, int] = (255, 255, 255),
               scale: float = 0.45) -> None:
    """`text` in place on a black box, its baseline starting at `at` (px). A box, not an outline: a
    thicker outline is also wider than the text and leaves a shadow of its end."""
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    x, y = at
    cv2.rectangle(image, (x - 2, y - h - 3), (x + w + 2, y + base), (0, 0, 0), -1)
    cv2.putText(image, text, at, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)
