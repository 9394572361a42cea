"""How sure a processed recording is, in one verdict a user can act on: `ok` or `doubtful`, with reasons.

A frame reversed by one mis-segmented or occluded first frame flips every force of a recording, and
nothing in the forces themselves shows it. So `vfdata process` judges each recording on what it can see:

- the object frame (`vfdata.recon.tissue_frame`): whether its fits of the axis agree, and whether the
  cues on the clamped end (taper, fixture, motion) are sure and agree;
- the tissue mask: whether its outline stays on depth steps (a tissue stands off its bed; a mask grown onto
  the bed has outline on smooth bed depth).

These can put the forces in a wrong frame (a reversed Z flips them): a recording they question is
`doubtful`, and `vfdata experiment` leaves it out of training. Two more figures are `notes`, said but not
held against the recording: the mask's area against the first frame's, and the share of tracked points
still followed at the end. On the fresh `colon` seed 101 (742 frames a recording) they fired on 3 of 5
training recordings whose masks matched the simulator's at IoU 0.75-0.96 over the whole recording: the
true mask's area changes 1.5-1.8x as the grasper pulls and covers the tissue, and KLT keeps 4-20% of
its points over 25 s, as on the project's own seeds where `visionforce` was measured.

The verdict and its figures go into the derived file's metadata (`confidence`, `doubtful`), which
`vfdata process`, `info`, `check`, `experiment`, `predict` and `live` read (`DerivedMeta.confidence`).
The thresholds were set on simulated recordings of seeds the yardstick does not use (docs/results.md,
"Never silently wrong").
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import cv2
import numpy as np

EDGE_EVERY = 15  # frames between two looks at the mask's outline (`edge_support` costs ~2 ms a look)
EDGE_STEP_MM = 3.0  # a depth step this deep across the outline marks the tissue's edge
EDGE_RING_PX = 4  # how far each side of the outline the step is looked for
MIN_EDGE_SUPPORT = 0.35  # median share of the outline on depth steps, under which the mask is doubtful
MAX_AREA_CHANGE = 2.0  # the mask's area grows or shrinks more than this factor from the first frame's
MIN_TRACKS_KEPT = 0.25  # share of the tracked points followed to the last frame

NOTES = ("mask_area", "tracks")  # said, but not a doubt on the recording (see the module docstring)
REASONS = {
    "axis": "object frame: the tissue's axis fits disagree (an occluder's depth may have turned it)",
    "end": "object frame: the cues disagree on, or cannot tell, which end is clamped (Z may be reversed)",
    "taper": "object frame: the tissue's taper points the other way than the clamp and the grasper's motion, "
             "which agree on the clamped end (the axis may be turned)",
    "mask_edges": "mask: its outline mostly off depth steps (it may have grown onto the bed)",
    "mask_area": "mask: its area changes more than {factor:g}x from the first frame's",
    "tracks": "tracks: {kept:.0%} of the points are still followed at the end",
}


@dataclass
class Confidence:
    """The verdict on one processed recording: `reasons` to doubt it and `notes` (keys of REASONS), and the
    figures behind them."""

    reasons: list[str] = field(default_factory=list)
    figures: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    @property
    def doubtful(self) -> bool:
        return bool(self.reasons)

    def describe(self, keys: list[str] | None = None) -> str:
        """The reasons (or the given keys, e.g. the notes) in words, '; '-joined ('ok' when there are none)."""
        keys = self.reasons if keys is None else keys
        if not keys:
            return "ok"
        return "; ".join(REASONS[r].format(factor=MAX_AREA_CHANGE, kept=self.figures.get("tracks_kept", 0.0))
                         for r in keys)

    def to_dict(self) -> dict:
        return {"doubtful": self.doubtful, "reasons": list(self.reasons), "notes": list(self.notes),
                "figures": {str(k): float(v) for k, v in self.figures.items()}}

    def metadata(self) -> dict[str, str]:
        """The derived metadata's two entries (`confidence`, `doubtful`): what process, predict and live write."""
        return {"confidence": json.dumps(self.to_dict()), "doubtful": str(self.doubtful).lower()}

    @classmethod
    def from_dict(cls, values: dict) -> Confidence:
        # files of 2026-12-04 kept the notes among the reasons
        keys = [str(r) for r in [*values.get("reasons", []), *values.get("notes", [])] if str(r) in REASONS]
        return cls([r for r in keys if r not in NOTES], dict(values.get("figures", {})),
                   list(dict.fromkeys(r for r in keys if r in NOTES)))


def edge_support(mask: np.ndarray, depth_mm: np.ndarray) -> float:
    """Share of the (H, W) mask's outline pixels that have, within EDGE_RING_PX outside, depth farther or
    nearer by more than EDGE_STEP_MM (the bed behind, an instrument in front) or no depth at all (NaN:
    where stereo fails at an occluding edge). NaN for an empty mask."""
    m = np.asarray(mask, dtype=np.uint8)
    if not m.any():
        return float("nan")
    depth = np.asarray(depth_mm, dtype=np.float32)
    kernel = np.ones((2 * EDGE_RING_PX + 1, 2 * EDGE_RING_PX + 1), np.uint8)
    outline = m.astype(bool) & ~cv2.erode(m, np.ones((3, 3), np.uint8)).astype(bool)
    outside = ~m.astype(bool)
    known = np.isfinite(depth) & (depth > 0)
    farthest = cv2.dilate(np.where(outside & known, depth, 0).astype(np.float32), kernel)
    nearest = cv2.erode(np.where(outside & known, depth, np.float32(1e9)).astype(np.float32), kernel)
    unknown_out = cv2.dilate((outside & ~known).astype(np.uint8), kernel).astype(bool)
    d = depth[outline]
    step = (farthest[outline] - d > EDGE_STEP_MM) | (d - nearest[outline] > EDGE_STEP_MM) | ~np.isfinite(d)
    step |= unknown_out[outline]
    return float(step.mean()) if outline.any() else float("nan")


def assess(frame_doubts: list[str], mask_areas: np.ndarray, edge_supports: np.ndarray,
           visible: np.ndarray | None, frame_figures: dict | None = None) -> Confidence:
    """The verdict from the object frame's doubts (`ObjectFrame.diagnostics["doubtful"]`), the mask's area
    per frame (pixels), its edge support on some frames (`edge_support`), and the tracks' (F, N) visibility
    (None: no tracker)."""
    reasons = [r for r in frame_doubts if r in REASONS]
    notes = []
    areas = np.asarray(mask_areas, dtype=np.float64)
    figures = dict(frame_figures or {})
    if len(areas) and areas[0] > 0:
        change = float(max(areas.max() / areas[0], areas[0] / max(areas.min(), 1.0)))
        figures["mask_area_change"] = round(change, 3)
        if change > MAX_AREA_CHANGE:
            notes.append("mask_area")
    supports = np.asarray(edge_supports, dtype=np.float64)
    supports = supports[np.isfinite(supports)]
    if len(supports):
        figures["mask_edge_support"] = round(float(np.median(supports)), 3)
        if np.median(supports) < MIN_EDGE_SUPPORT:
            reasons.append("mask_edges")
    if visible is not None and np.size(visible):
        vis = np.asarray(visible, dtype=bool)
        kept = float(vis[-1].sum() / max(vis[0].sum(), 1))
        figures["tracks_kept"] = round(kept, 3)
        if kept < MIN_TRACKS_KEPT:
            notes.append("tracks")
    return Confidence(reasons, figures, notes)


class ConfidenceWatch:
    """The verdict kept frame by frame, for a whole recording (`vfdata process`) or a stream (`vfdata live`,
    `predict --stream`, which cannot wait for the end): `add` each frame, `verdict()` at any time. Keeps
    what `assess` weighs in constant memory: the mask's first, largest and smallest area, its edge support
    every EDGE_EVERY frames, and the tracks' visibility at the first and latest frame."""

    def __init__(self, frame_doubts: list[str], frame_figures: dict | None = None):
        self.frame_doubts = list(frame_doubts)
        self.frame_figures = dict(frame_figures or {})
        self.areas: np.ndarray | None = None  # first, largest, smallest (pixels)
        self.supports: list[float] = []
        self.visible_ends: list[np.ndarray] = []  # first, latest
        self.frames = 0

    def add(self, mask: np.ndarray, depth_mm: np.ndarray | None, visible: np.ndarray | None = None) -> None:
        area = int(np.count_nonzero(mask))
        if self.areas is None:
            self.areas = np.array([area, area, area])
        self.areas[1:] = max(self.areas[1], area), min(self.areas[2], area)
        if depth_mm is not None and self.frames % EDGE_EVERY == 0:
            self.supports.append(edge_support(mask, depth_mm))
        if visible is not None:
            self.visible_ends[1:] = []
            self.visible_ends.append(np.asarray(visible, dtype=bool))
        self.frames += 1

    def set_tracks(self, visible: np.ndarray) -> None:
        """The (F, N) visibility of tracks made after the frames (an offline tracker)."""
        self.visible_ends = [np.asarray(visible[0], dtype=bool), np.asarray(visible[-1], dtype=bool)]

    def verdict(self) -> Confidence:
        visible = np.stack(self.visible_ends) if self.visible_ends else None
        return assess(self.frame_doubts, self.areas if self.areas is not None else np.zeros(0),
                      np.array(self.supports), visible, self.frame_figures)
