"""Which end of the tissue is clamped: independent cues, each a vote with a strength.

The object frame's +Z runs from the clamped (wide) end to the free end. The paper decides it by the
taper alone, and one frame's taper is fragile: an instrument lying along the tube leaves a silhouette
whose width barely changes (the simulator's colon seed 11, colon_004: slope -0.001 mm/mm, Z 173 degrees
off), and a mask cut short by the view takes the taper of what is left. Each cue here looks at another
physical fact, and says how sure it is:

- `taper_cue`: the silhouette narrows toward the free end (the paper's cue), trusted as far as its
  slope clears its own noise (the spread of the slope over resampled slabs).
- `fixture_cue`: the clamp that holds the tissue is a grey (metal) fixture just beyond the clamped end
  in the image; beyond the free end lies the bed.
- `motion_cue`: over the recording, the grasper moves the free end and the clamped end stays: each
  point's displacement against its place along the axis.

A cue's `vote` is +1 when it puts the clamped end at the low end of the axis (small t = p . axis), -1 at
the high end, 0 when it cannot tell; `strength` is how many times the evidence exceeds its noise (about a
z-score: 3 is strong, under 1 is no evidence). `decide` combines them and says how far they agree.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from vfdata.calibration import PinholeCamera
from vfdata.recon.colortrack import metal_pixels
from vfdata.recon.object_frame import trimmed_slope

STRONG = 3.0  # a cue this sure decides alone, and one as sure against it makes the frame doubtful
WEAK = 1.0  # below this a cue has no say
MAX_STRENGTH = 10.0  # no single cue counts for more than this in the sum
BOOTSTRAP = 200
MIN_MOTION_MM = 1.0  # the moving end's median displacement under which the motion cue has no say
FIXTURE_NOISE = 0.08  # spread (share of metal pixels) of the region beyond a free end, on clean views


@dataclass(frozen=True)
class Cue:
    name: str
    vote: float  # +1: clamped end at the low end of the axis; -1: at the high end; 0: no opinion
    strength: float  # evidence over its noise (0: none)
    detail: dict = field(default_factory=dict)

    @property
    def weight(self) -> float:
        """The signed say of this cue in the sum (0 under WEAK, at most MAX_STRENGTH)."""
        return 0.0 if self.strength < WEAK else float(np.sign(self.vote)) * min(self.strength, MAX_STRENGTH)

    def to_dict(self) -> dict:
        return {"vote": round(float(self.vote), 4), "strength": round(float(self.strength), 2), **self.detail}


@dataclass(frozen=True)
class EndDecision:
    """The combined verdict: `low_end_clamped` (the clamped end at small t), `margin` (the summed weights'
    magnitude), `agree` (no strong cue against the verdict), and each cue."""

    low_end_clamped: bool
    margin: float
    agree: bool
    cues: tuple[Cue, ...]

    @property
    def doubtful(self) -> bool:
        """True when no cue is sure of the end, or a sure cue says the other end."""
        return self.margin < STRONG or not self.agree

    @property
    def doubt(self) -> str | None:
        """Why the end is doubtful (None: it is not). `taper` when the taper, however sure, is the one sure cue
        against two or more sure cues that agree (and the sum still clears STRONG): the end is theirs, and
        what disagrees is the silhouette's width along this axis. On the fresh sweeps' 256 recordings (colon
        101-116, glove 209-212) that happened 8 times: the end was right all 8 times, the axis 4.8-8.7 degrees
        off in 4 and 10.5-19.3 in 4 (docs/results.md, "Which cue was right"). `end` otherwise: no cue sure, or
        the sure cues split without two agreeing against one, where Z may be reversed."""
        if not self.doubtful:
            return None
        sure = [c for c in self.cues if c.weight != 0 and c.strength >= STRONG]
        against = [c for c in sure if (c.weight > 0) != self.low_end_clamped]
        backing = [c for c in sure if (c.weight > 0) == self.low_end_clamped]
        if self.margin >= STRONG and [c.name for c in against] == ["taper"] and len(backing) >= 2:
            return "taper"
        return "end"

    def to_dict(self) -> dict:
        return {"low_end_clamped": self.low_end_clamped, "margin": round(self.margin, 2), "agree": self.agree,
                "cues": {c.name: c.to_dict() for c in self.cues}}


def decide(cues: list[Cue] | tuple[Cue, ...]) -> EndDecision:
    """The end the cues put the clamp at, by their summed weights (ties: the low end, as the taper's sign
    convention has it when it has no say). A sure taper against a sure motion has no say: an instrument
    lying along the tube fakes a taper, and nothing fakes the clamped end's stillness. On the fresh sweeps'
    12 recordings where the two were sure and disagreed, the motion's end was right all 12 times; on colon
    138's `colon_008` (taper 10.4, motion 8.2) the sum took the taper's, reversed (docs/results.md, "Which
    cue was right"). The recording stays doubtful (the taper is still a sure cue against the verdict), as
    it must: a sure motion can be wrong too (glove 218's `glove_018`, 5.3, against a weak taper)."""
    sure = {c.name: c for c in cues if c.weight != 0 and c.strength >= STRONG}
    muted = "taper" in sure and "motion" in sure and (sure["taper"].weight > 0) != (sure["motion"].weight > 0)
    total = sum(c.weight for c in cues if not (muted and c.name == "taper"))
    low = total >= 0
    against = [c for c in cues if c.weight != 0 and (c.weight > 0) != low and c.strength >= STRONG]
    return EndDecision(bool(low), float(abs(total)), not against, tuple(cues))


# ---- taper -------------------------------------------------------------------------------------------


def taper_cue(t: np.ndarray, width_mm: np.ndarray, rng: np.random.Generator | None = None) -> Cue:
    """The silhouette's width (`width_mm` per slab at `t` mm along the axis, `tube_axis.slab_widths`) falls
    toward the free end: the paper's slope (`object_frame.trimmed_slope`); its noise is the spread of that
    slope over slabs resampled with replacement."""
    t, width_mm = np.asarray(t, dtype=np.float64), np.asarray(width_mm, dtype=np.float64)
    if len(t) < 6:
        return Cue("taper", 0.0, 0.0, {"slabs": int(len(t))})
    slope = trimmed_slope(t, width_mm)
    rng = rng if rng is not None else np.random.default_rng(0)
    draws = np.sort(rng.integers(0, len(t), (BOOTSTRAP, len(t))), axis=1)
    noise = float(np.std([trimmed_slope(t[d], width_mm[d]) for d in draws]))
    strength = abs(slope) / noise if noise > 0 else 0.0
    return Cue("taper", float(-np.sign(slope)), float(strength), {"slope": round(slope, 4), "noise": round(noise, 4)})


# ---- the fixture ---------------------------------------------------------------------------------------


def fixture_cue(image_bgr: np.ndarray, mask: np.ndarray, camera: PinholeCamera, ends_mm: np.ndarray,
                axis: np.ndarray, width_mm: tuple[float, float]) -> Cue:
    """The clamp is a grey fixture just beyond the clamped end. `ends_mm` (2, 3): the centreline's points
    at the low and the high end (camera frame, mm); `axis` (3,) from low to high; `width_mm` the tissue's
    width at each end. For each end, the share of grey (metal) pixels outside the tissue mask in a box
    beyond it, along the axis as seen in the image, as wide as the tissue and half as long."""
    lab = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2Lab)
    metal = metal_pixels(lab)
    shares = []
    for end, outward, width in ((ends_mm[0], -axis, width_mm[0]), (ends_mm[1], axis, width_mm[1])):
        shares.append(_share_beyond(metal, mask, camera, end, outward, width))
    low, high = shares
    if low is None or high is None:
        return Cue("fixture", 0.0, 0.0, {"metal_low": low, "metal_high": high})
    diff = low - high
    return Cue("fixture", float(np.sign(diff)), abs(diff) / FIXTURE_NOISE,
               {"metal_low": round(low, 3), "metal_high": round(high, 3)})


def _share_beyond(metal: np.ndarray, mask: np.ndarray, camera: PinholeCamera, end: np.ndarray,
                  outward: np.ndarray, width_mm: float) -> float | None:
    """Share of metal among the non-tissue pixels of the box beyond `end` (None: the box is mostly out of
    the image, or holds no pixel outside the tissue)."""
    length = 0.6 * width_mm
    corners_mm = []
    across = np.cross(outward, end / np.linalg.norm(end))  # across the axis, as the camera sees it
    if np.linalg.norm(across) < 1e-6:
        return None
    across /= np.linalg.norm(across)
    for a in (-0.6, 0.6):
        for b in (-0.1, 1.0):
            corners_mm.append(end + outward * (b * length) + across * (a * width_mm))
    uv = camera.project(np.array(corners_mm))
    if not np.isfinite(uv).all():
        return None
    box = np.zeros(mask.shape, np.uint8)
    hull = cv2.convexHull(np.round(uv).astype(np.int32))
    cv2.fillConvexPoly(box, hull, 1)
    inside = box.astype(bool)
    area = cv2.contourArea(hull.astype(np.float32))
    if area < 20 or inside.sum() < 0.5 * area:  # mostly out of the image: this end is not seen
        return None
    outside = inside & ~mask
    if outside.sum() < 10:
        return None
    return float(metal[outside].mean())


# ---- motion -------------------------------------------------------------------------------------------


def motion_cue(points_mm: np.ndarray, visible: np.ndarray, axis: np.ndarray, centre: np.ndarray) -> Cue:
    """The free end moves, the clamped end stays. `points_mm` (F, N, 3) tracked points (camera frame,
    mm), `visible` (F, N); each point's displacement from its first visible position (the 90th percentile
    over the frames it is seen in) against its place along `axis` (from `centre`) in the first frame it is
    seen. The strength is the rank correlation times the square root of the points that moved, a rough
    z-score of the correlation."""
    points = np.asarray(points_mm, dtype=np.float64)
    visible = np.asarray(visible, dtype=bool) & np.isfinite(points).all(axis=-1)
    seen = visible.any(axis=0)
    if seen.sum() < 10 or len(points) < 2:
        return Cue("motion", 0.0, 0.0, {"points": int(seen.sum())})
    first = np.argmax(visible, axis=0)
    n = np.arange(points.shape[1])
    start = points[first, n]
    disp = np.linalg.norm(points - start[None], axis=-1)
    disp = np.where(visible, disp, np.nan)
    moved = np.nanpercentile(disp[:, seen], 90, axis=0)
    place = (start[seen] - centre) @ axis
    ok = np.isfinite(moved)
    place, moved = place[ok], moved[ok]
    q = np.quantile(place, [0.25, 0.75]) if len(place) else (0.0, 0.0)
    low_mm = float(np.median(moved[place <= q[0]])) if len(place) else 0.0
    high_mm = float(np.median(moved[place >= q[1]])) if len(place) else 0.0
    detail = {"low_mm": round(low_mm, 2), "high_mm": round(high_mm, 2)}
    if max(low_mm, high_mm) < MIN_MOTION_MM:  # the free end did not move enough to tell
        return Cue("motion", 0.0, 0.0, detail)
    rho = _spearman(place, moved)
    return Cue("motion", float(np.sign(rho)), abs(rho) * np.sqrt(len(place)), {"rho": round(rho, 3), **detail})


def _spearman(x: np.ndarray, y: np.ndarray) -> float:
    rx, ry = np.argsort(np.argsort(x)), np.argsort(np.argsort(y))
    c = np.corrcoef(rx, ry)[0, 1]
    return float(c) if np.isfinite(c) else 0.0
