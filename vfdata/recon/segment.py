"""Stage 2: the tissue mask of every frame, from a first-frame prompt.

A segmenter is a small state machine over a video: `start(first_image, prompt)` returns the first
mask, then `track(image)` the next one per frame (`segment_video` runs both over a sequence). Backends
by name (`make_segmenter`):

- `colortrack` (default, runs anywhere without weights): GrabCut from the prompt on the first frame;
  then per frame a colour model of tissue and surroundings (histograms of the Lab chroma, updated as
  the video goes), a spatial prior from the previous mask carried along by dense optical flow, an
  optional depth cue, morphological clean-up and the component that continues the previous mask.
  The instrument (grey, metallic) is cut out where it covers the tissue; the tissue-coloured
  surroundings stay out because they are far from the carried-over mask (and at another depth).
- `sam2`: Meta's SAM2 video predictor from the user's local config and checkpoint.

Prompts (`Prompt`): a box and/or positive and negative points, from the command line
(`Prompt.parse`), the recording's metadata (`prompt_box`) or a detector (`detector_prompt`, the
paper's fine-tuned Faster R-CNN).

Images are (H, W, 3) uint8 BGR; masks (H, W) bool.
"""

from __future__ import annotations

import re
import tempfile
from abc import ABC, abstractmethod
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from vfdata.errors import BackendError, InputError

# ------------------------------------------------------------------------------------------ prompts


@dataclass(frozen=True)
class Prompt:
    """A first-frame prompt in pixels: `box` (x0, y0, x1, y1) and/or points on the tissue
    (`positive`) and off it (`negative`)."""

    box: tuple[float, float, float, float] | None = None
    positive: tuple[tuple[float, float], ...] = ()
    negative: tuple[tuple[float, float], ...] = ()

    def __post_init__(self):
        if self.box is None and not self.positive:
            raise InputError("prompt", "needs a box or at least one positive point")
        if self.box is not None:
            x0, y0, x1, y1 = self.box
            if not (x1 > x0 and y1 > y0):
                raise InputError(
                    "prompt", f"box {list(self.box)} must be x0,y0,x1,y1 with x1 > x0 and y1 > y0"
                )

    @classmethod
    def parse(cls, text: str) -> Prompt:
        """Parse "box:x0,y0,x1,y1", "points:x,y;x,y" (on the tissue) and "neg:x,y;x,y" (off it),
        several joined by spaces, e.g. "box:100,80,400,300 neg:250,200"."""
        box = None
        positive: list[tuple[float, float]] = []
        negative: list[tuple[float, float]] = []
        parts = [p for p in re.split(r"[\s|]+", text.strip()) if p]
        if not parts:
            raise InputError(
                "prompt", "empty prompt (expected e.g. 'box:100,80,400,300' or 'points:320,240')"
            )
        for part in parts:
            kind, _, values = part.partition(":")
            kind = kind.lower()
            try:
                if kind == "box":
                    numbers = [float(v) for v in values.split(",")]
                    if len(numbers) != 4:
                        raise ValueError
                    box = (numbers[0], numbers[1], numbers[2], numbers[3])
                elif kind in ("points", "pos", "point"):
                    positive += _parse_points(values)
                elif kind in ("neg", "negative"):
                    negative += _parse_points(values)
                else:
                    raise InputError("prompt", f"unknown part '{part}' (use box:, points: or neg:)")
            except ValueError:
                raise InputError(
                    "prompt", f"cannot read '{part}' (e.g. box:100,80,400,300 or points:320,240;300,200)"
                ) from None
        return cls(box=box, positive=tuple(positive), negative=tuple(negative))

    @classmethod
    def from_box(cls, box: Sequence[float]) -> Prompt:
        if len(box) != 4:
            raise InputError("prompt", f"a box has 4 numbers x0,y0,x1,y1, not {len(box)}")
        return cls(box=tuple(float(v) for v in box))  # type: ignore[arg-type]

    def check_inside(self, width: int, height: int) -> None:
        """Raise InputError if any part of the prompt lies outside a width x height image."""

        def inside(x: float, y: float) -> bool:
            return 0 <= x <= width - 1 and 0 <= y <= height - 1

        if self.box is not None:
            # Box corners are continuous coordinates: the far edge may sit on the image border.
            x0, y0, x1, y1 = self.box
            if not (0 <= x0 and 0 <= y0 and x1 <= width and y1 <= height):
                raise InputError("prompt", f"box {list(self.box)} is outside the {width}x{height} image")
        for x, y in self.positive + self.negative:
            if not inside(x, y):
                raise InputError("prompt", f"point ({x:g}, {y:g}) is outside the {width}x{height} image")

    def to_dict(self) -> dict:
        return {
            "box": list(self.box) if self.box else None,
            "positive": [list(p) for p in self.positive],
            "negative": [list(p) for p in self.negative],
        }


def _parse_points(values: str) -> list[tuple[float, float]]:
    points = []
    for pair in values.split(";"):
        numbers = [float(v) for v in pair.split(",")]
        if len(numbers) != 2:
            raise ValueError
        points.append((numbers[0], numbers[1]))
    return points


# ---------------------------------------------------------------------------------------- interface


class Segmenter(ABC):
    """A video tissue segmenter: `start` on the first frame with a prompt, then `track` per frame."""

    name: str = ""

    @abstractmethod
    def start(self, image: np.ndarray, prompt: Prompt, depth_mm: np.ndarray | None = None) -> np.ndarray:
        """First frame + prompt -> (H, W) bool mask. Resets any previous video."""

    @abstractmethod
    def track(self, image: np.ndarray, depth_mm: np.ndarray | None = None) -> np.ndarray:
        """Next frame -> (H, W) bool mask."""

    def segment_video(
        self, frames: Iterable[np.ndarray], prompt: Prompt, depths: Iterable[np.ndarray] | None = None
    ) -> list[np.ndarray]:
        """Masks of a whole video (optionally with per-frame depth in mm)."""
        depth_iter = iter(depths) if depths is not None else None
        masks = []
        for i, frame in enumerate(frames):
            depth = next(depth_iter) if depth_iter is not None else None
            masks.append(self.start(frame, prompt, depth) if i == 0 else self.track(frame, depth))
        return masks

    def parameters(self) -> dict:
        return {"backend": self.name}


def _check_image(image: np.ndarray) -> None:
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise InputError("image", f"expected an (H, W, 3) uint8 BGR image, got {image.shape} {image.dtype}")


# --------------------------------------------------------------------------------------- colortrack


@dataclass(frozen=True)
class ColorTrackSettings:
    """Settings of the `colortrack` segmenter (pixels are full-resolution ones)."""

    scale: float = 0.5  # working resolution
    grabcut_iterations: int = 5
    bins: int = 32  # per chroma axis (a*, b*) of the colour histograms ...
    chroma_step: int = 3  # ... each this wide (OpenCV's 8-bit Lab units) ...
    chroma_low: int = 80  # ... from this value up (a*, b* = 128 is grey); the ends absorb the rest
    lightness_bins: int = 8  # L* bins: pale tissue vs grey metal and dark shadows
    model_update: float = 0.2  # how fast the colour model follows the video (0: frozen) ...
    model_every: int = 4  # ... updated every this many frames
    mask_threshold: float = 0.35  # of the upsampled soft mask: tissue edges are dark and shaded, so
    # the working-resolution mask sits slightly inside the true edge; a low threshold and ...
    edge_dilate_px: int = 1  # ... a dilation of the full-resolution mask even that out
    prior_inside: float = 2.0  # log-odds bonus deep inside the carried-over mask ...
    prior_edge: float = 1.0  # ... and at its edge: colours seen in neither model (the shaded rim)
    # stay tissue, so the mask does not erode frame after frame; the grey instrument still leaves
    prior_slope: float = 0.5  # log-odds per working pixel of depth into the carried-over mask ...
    growth_slope: float = 1.0  # ... and per working pixel of distance outside it (steeper: the bed has
    # patches the colour of shaded tissue, which a gentle slope lets the mask creep into)
    max_growth_px: int = 12  # the mask may grow at most this far (working px) per frame
    depth_tolerance_mm: float = 6.0  # depth cue: slack on the tissue's depth range ...
    depth_jump: float = 0.04  # ... a depth step over this fraction of the tissue depth per working pixel
    depth_penalty: float = 6.0  # ... is an edge; both get this log-odds penalty
    min_hole_px: int = 400  # holes in the mask smaller than this (full-res px) are filled
    grey_chroma: float = 7.0  # Lab chroma below which a (non-highlight) pixel is taken as metal ...
    grey_penalty: float = 4.0  # ... and gets this log-odds penalty (0: off); tissue is never grey


class ColorTrackSegmenter(Segmenter):
    """The embedded default: colour model + flow-carried prior (see the module docstring)."""

    name = "colortrack"

    def __init__(self, **options):
        fields = ColorTrackSettings.__dataclass_fields__
        unknown = sorted(set(options) - set(fields))
        if unknown:
            raise BackendError(
                f"colortrack: unknown option(s) {', '.join(unknown)}; known: {', '.join(fields)}"
            )
        self.settings = ColorTrackSettings(**options)
        s = self.settings
        self._chroma_lut = np.clip((np.arange(256) - s.chroma_low) // s.chroma_step, 0, s.bins - 1).astype(
            np.int32
        )
        self._flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST)
        self._prev_grey: np.ndarray | None = None
        self._prev_mask: np.ndarray | None = None  # working resolution, float32 0/1
        self._prev_depth: np.ndarray | None = None
        self._log_ratio: np.ndarray | None = None
        self._hist_fg: np.ndarray | None = None
        self._hist_bg: np.ndarray | None = None
        self._full_size: tuple[int, int] = (0, 0)
        self._frame = 0

    def parameters(self) -> dict:
        return {"backend": self.name, **self.settings.__dict__}

    # -- helpers on the working resolution

    def _work(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """-> (small BGR, grey, colour-bin index, metal-like) at working resolution."""
        h, w = image.shape[:2]
        size = (max(8, round(w * self.settings.scale)), max(8, round(h * self.settings.scale)))
        small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        grey = cv2.cvtColor(small, cv2.COLOR_BGR2GRAY)
        lab = cv2.cvtColor(small, cv2.COLOR_BGR2Lab)
        s = self.settings
        # uint8 Lab: L in 0..255, a and b offset by 128; quantise into one bin index.
        # Tissue, instrument and tissue bed differ by only ~10 units of a*, b* around grey: fine
        # chroma bins where the colours are, coarse lightness bins.
        lut = self._chroma_lut
        l_bin = (lab[..., 0].astype(np.int32) * s.lightness_bins) >> 8
        bins = (l_bin * s.bins + lut[lab[..., 1]]) * s.bins + lut[lab[..., 2]]
        # Instruments and clamps are grey metal: near-neutral chroma, except specular highlights
        # (near-white), which also occur on wet tissue.
        chroma2 = (lab[..., 1].astype(np.int32) - 128) ** 2 + (lab[..., 2].astype(np.int32) - 128) ** 2
        metal = (chroma2 < s.grey_chroma**2) & (lab[..., 0] < 235)
        return small, grey, bins, metal

    def _histogram(self, bins: np.ndarray, where: np.ndarray) -> np.ndarray:
        s = self.settings
        n = s.lightness_bins * s.bins * s.bins
        hist = np.bincount(bins[where], minlength=n).astype(np.float32)
        # Smooth over neighbouring chroma bins so unseen-but-close colours are not impossible.
        hist = hist.reshape(s.lightness_bins, s.bins, s.bins)
        hist = np.stack([cv2.GaussianBlur(layer, (5, 5), 1.0) for layer in hist])
        return hist.ravel() / max(1.0, float(hist.sum()))

    def _update_model(self, bins: np.ndarray, mask: np.ndarray, rate: float) -> None:
        # Learn only from confident pixels: away from the mask's edge on either side.
        kernel = np.ones((5, 5), np.uint8)
        inner = cv2.erode(mask.astype(np.uint8), kernel).astype(bool)
        outer = ~cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)
        if not inner.any() or not outer.any():
            return
        fg, bg = self._histogram(bins, inner), self._histogram(bins, outer)
        if self._hist_fg is None or rate >= 1.0:
            self._hist_fg, self._hist_bg = fg, bg
        else:
            self._hist_fg = (1 - rate) * self._hist_fg + rate * fg
            self._hist_bg = (1 - rate) * self._hist_bg + rate * bg
        eps = 1e-5
        self._log_ratio = np.clip(np.log((self._hist_fg + eps) / (self._hist_bg + eps)), -6, 6).astype(
            np.float32
        )

    def _to_full(self, mask_small: np.ndarray) -> np.ndarray:
        w, h = self._full_size
        up = cv2.resize(mask_small.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
        mask = up > self.settings.mask_threshold
        if self.settings.edge_dilate_px > 0:
            k = 2 * self.settings.edge_dilate_px + 1
            mask = cv2.dilate(mask.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
        return mask

    # -- the two steps

    def start(self, image: np.ndarray, prompt: Prompt, depth_mm: np.ndarray | None = None) -> np.ndarray:
        _check_image(image)
        h, w = image.shape[:2]
        prompt.check_inside(w, h)
        self._full_size = (w, h)
        small, grey, bins, metal = self._work(image)
        sh, sw = grey.shape
        sx, sy = sw / w, sh / h
        gc = np.full((sh, sw), cv2.GC_BGD, np.uint8)
        if prompt.box is not None:
            x0, y0, x1, y1 = prompt.box
            box = (int(x0 * sx), int(y0 * sy), max(1, int((x1 - x0) * sx)), max(1, int((y1 - y0) * sy)))
        else:
            # Points only: GrabCut still needs a region; take the points' extent, generously grown.
            pts = np.array(prompt.positive)
            pad = 0.15 * max(w, h)
            x0, y0 = np.maximum(pts.min(axis=0) - pad, 0)
            x1, y1 = np.minimum(pts.max(axis=0) + pad, [w - 1, h - 1])
            box = (int(x0 * sx), int(y0 * sy), max(1, int((x1 - x0) * sx)), max(1, int((y1 - y0) * sy)))
        bx, by, bw, bh = box
        gc[by : by + bh, bx : bx + bw] = cv2.GC_PR_FGD
        if self.settings.grey_penalty > 0:
            gc[metal & (gc == cv2.GC_PR_FGD)] = cv2.GC_PR_BGD
        radius = max(2, round(4 * self.settings.scale * 2))
        for x, y in prompt.positive:
            cv2.circle(gc, (int(x * sx), int(y * sy)), radius, cv2.GC_FGD, -1)
        for x, y in prompt.negative:
            cv2.circle(gc, (int(x * sx), int(y * sy)), radius, cv2.GC_BGD, -1)
        if depth_mm is not None:
            # Pixels of the box far off the tissue's depth are probably background: instruments in
            # front, the bed behind. The tissue's depth is taken in the middle fifth of the box: an
            # elongated tissue lying diagonally passes through the box's centre but leaves most of
            # the box to the bed, whose depth would then be the box's median (and GrabCut would take
            # in tissue-coloured bed).
            depth_small = cv2.resize(
                np.nan_to_num(depth_mm.astype(np.float32), nan=0), (sw, sh), interpolation=cv2.INTER_NEAREST
            )
            inside = depth_small[by : by + bh, bx : bx + bw]
            usable = inside > 0
            if self.settings.grey_penalty > 0:  # metal is not the tissue
                usable &= ~metal[by : by + bh, bx : bx + bw]
            middle = np.zeros_like(usable)
            middle[bh * 2 // 5 : max(bh * 3 // 5, 1), bw * 2 // 5 : max(bw * 3 // 5, 1)] = True
            # Positive points are on the tissue by definition; else the middle, else the whole box.
            points = np.zeros_like(usable)
            for x, y in prompt.positive:
                u, v = int(x * sx) - bx, int(y * sy) - by
                points[max(v - 2, 0) : max(v + 3, 0), max(u - 2, 0) : max(u + 3, 0)] = True
            good = next((inside[usable & where] for where in (points, middle, np.ones_like(usable))
                         if (usable & where).sum() >= 20), inside[inside > 0])
            if good.size:
                median = np.median(good)
                tol = self.settings.depth_tolerance_mm * 3
                region = gc[by : by + bh, bx : bx + bw]
                region[(inside > 0) & (np.abs(inside - median) > tol) & (region == cv2.GC_PR_FGD)] = (
                    cv2.GC_PR_BGD
                )
        bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
        try:
            # GrabCut's GMM initialisation draws from OpenCV's global generator: seed it, so the mask does
            # not depend on whatever ran earlier in the process.
            cv2.setRNGSeed(0)
            cv2.grabCut(small, gc, None, bgd, fgd, self.settings.grabcut_iterations, cv2.GC_INIT_WITH_MASK)
        except cv2.error as exc:
            raise InputError("prompt", f"GrabCut could not separate the prompted region: {exc.err}") from exc
        mask = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
        prompt_mask = self._prompt_mask(prompt, sw, sh, sx, sy)
        mask = self._clean(mask, seed=None, prompt_mask=prompt_mask)
        if not mask.any():
            raise InputError(
                "prompt", "the first frame's mask is empty: the prompt does not cover the tissue"
            )
        # GrabCut's colour models are global and often take in metal touching the tissue inside the
        # box; re-decide every pixel once with the finer histogram model, GrabCut's mask as prior.
        self._update_model(bins, mask, rate=1.0)
        depth_small = self._small_depth(depth_mm, (sw, sh))
        refined = self._decide(bins, metal, mask, depth_small)
        refined &= cv2.dilate(prompt_mask.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
        refined = self._clean(refined, seed=mask, prompt_mask=None)
        if refined.any():
            mask = refined
        self._update_model(bins, mask, rate=1.0)
        self._prev_grey = grey
        self._prev_mask = mask.astype(np.float32)
        self._prev_depth = self._small_depth(depth_mm, (sw, sh))
        self._frame = 0
        return self._to_full(mask)

    def _prompt_mask(self, prompt: Prompt, sw: int, sh: int, sx: float, sy: float) -> np.ndarray:
        m = np.zeros((sh, sw), bool)
        if prompt.box is not None:
            x0, y0, x1, y1 = prompt.box
            m[int(y0 * sy) : int(y1 * sy) + 1, int(x0 * sx) : int(x1 * sx) + 1] = True
        for x, y in prompt.positive:
            m[min(sh - 1, int(y * sy)), min(sw - 1, int(x * sx))] = True
        return m

    @staticmethod
    def _small_depth(depth_mm: np.ndarray | None, size: tuple[int, int]) -> np.ndarray | None:
        if depth_mm is None:
            return None
        d = np.asarray(depth_mm, dtype=np.float32)
        return cv2.resize(
            np.where(np.isfinite(d), d, 0).astype(np.float32), size, interpolation=cv2.INTER_NEAREST
        )

    def track(self, image: np.ndarray, depth_mm: np.ndarray | None = None) -> np.ndarray:
        if self._prev_mask is None or self._log_ratio is None:
            raise BackendError("colortrack: track() before start(): give the first frame and a prompt first")
        _check_image(image)
        if (image.shape[1], image.shape[0]) != self._full_size:
            raise InputError(
                "image", f"frame size {image.shape[1]}x{image.shape[0]} differs from the first frame's"
            )
        s = self.settings
        small, grey, bins, metal = self._work(image)
        sh, sw = grey.shape
        # Carry the previous mask to this frame: flow from this frame to the previous one, so each
        # pixel here looks up where it was.
        # (Computed at half the working resolution: the mask only needs its coarse motion.)
        half = (sw // 2, sh // 2)
        flow = self._flow.calc(
            cv2.resize(grey, half, interpolation=cv2.INTER_AREA),
            cv2.resize(self._prev_grey, half, interpolation=cv2.INTER_AREA),
            None,
        )
        flow = cv2.resize(flow, (sw, sh), interpolation=cv2.INTER_LINEAR) * np.float32(sw / half[0])
        map_x = flow[..., 0] + np.arange(sw, dtype=np.float32)[None, :]
        map_y = flow[..., 1] + np.arange(sh, dtype=np.float32)[:, None]
        carried = (
            cv2.remap(self._prev_mask, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT) > 0.5
        )
        depth_small = self._small_depth(depth_mm, (sw, sh))
        mask = self._decide(bins, metal, carried, depth_small)
        mask = self._clean(mask, seed=carried, prompt_mask=None)
        if not mask.any():
            # Lost (e.g. the tissue fully covered for a frame): keep the carried mask.
            mask = carried
        self._frame += 1
        if self._frame % s.model_every == 0:
            self._update_model(bins, mask, rate=s.model_update)
        self._prev_grey = grey
        self._prev_mask = mask.astype(np.float32)
        self._prev_depth = depth_small
        return self._to_full(mask)

    def _decide(
        self, bins: np.ndarray, metal: np.ndarray, prior_mask: np.ndarray, depth: np.ndarray | None
    ) -> np.ndarray:
        """Per pixel: colour log-odds + spatial prior from `prior_mask` (+ depth evidence) > 0.
        The prior is positive inside (bounded, so strong colour evidence such as the grey instrument
        wins), falls with distance outside and forbids growing beyond the growth limit."""
        s = self.settings
        prior_u8 = prior_mask.astype(np.uint8)
        dist_out = cv2.distanceTransform(1 - prior_u8, cv2.DIST_L2, 3)
        dist_in = cv2.distanceTransform(prior_u8, cv2.DIST_L2, 3)
        inside = np.clip(s.prior_edge + (dist_in - 1) * s.prior_slope, 0, s.prior_inside) * prior_mask
        score = self._log_ratio[bins] + inside
        score -= dist_out * s.growth_slope
        if s.grey_penalty > 0:
            score[metal] -= s.grey_penalty
        if depth is not None:
            score += self._depth_evidence(depth, prior_mask)
        return (score > 0) & (dist_out <= s.max_growth_px)

    def _depth_evidence(self, depth: np.ndarray, carried: np.ndarray) -> np.ndarray:
        """Log-odds from depth. The tissue's outline is a depth discontinuity (the tissue stands
        off the bed; the instrument is in front of it): pixels on a depth jump are barriers the
        mask cannot cross, so tissue-coloured surroundings cannot leak in. Pixels far off the
        tissue's depth range (median +- a robust spread of the carried mask's depth) are not tissue."""
        s = self.settings
        valid = depth > 0
        filled = np.where(valid, depth, np.float32(0)).astype(np.float32)
        kernel = np.ones((3, 3), np.uint8)
        # The far side of a depth step (a pixel well behind its nearest neighbour): the bed just
        # outside the tissue's silhouette. The near side, the tissue's own edge, stays eligible.
        jump = filled - cv2.erode(np.where(valid, filled, np.float32(1e6)), kernel)
        # The jump threshold grows with depth (disparity noise makes depth noise grow with depth^2;
        # a relative threshold is a fair compromise on the working range).
        evidence = np.zeros_like(filled)
        inside = carried & valid
        if inside.sum() < 20:
            return evidence
        tissue = filled[inside]
        median = float(np.median(tissue))
        spread = float(np.percentile(np.abs(tissue - median), 90)) + s.depth_tolerance_mm
        # Only growth is policed: inside the carried mask colour and the prior decide (depth noise
        # at the tissue's own silhouette would otherwise eat its edge).
        outside = valid & ~carried
        evidence[outside & (jump > s.depth_jump * median)] = -s.depth_penalty
        evidence[outside & (np.abs(filled - median) > 2 * spread)] = -s.depth_penalty
        # Locally: a pixel outside must lie near the depth of the nearest tissue pixel (the tissue
        # bed behind the silhouette is further away, the instrument in front nearer).
        source = (~inside).astype(np.uint8)
        _dist, labels = cv2.distanceTransformWithLabels(
            source, cv2.DIST_L2, 3, labelType=cv2.DIST_LABEL_PIXEL
        )
        ys, xs = np.nonzero(inside)
        # Labels number the zero pixels of `source` (the tissue pixels) in row-major order from 1.
        nearest_depth = np.concatenate([[0.0], filled[ys, xs]]).astype(np.float32)[labels]
        evidence[outside & (np.abs(filled - nearest_depth) > s.depth_jump * median * 2)] = -s.depth_penalty
        return evidence

    def _clean(self, mask: np.ndarray, seed: np.ndarray | None, prompt_mask: np.ndarray | None) -> np.ndarray:
        """Open/close, keep the component(s) continuing the previous mask (or the prompt), fill small
        holes (noise) but keep large ones (the instrument covering the tissue)."""
        m = mask.astype(np.uint8)
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, kernel)
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, kernel)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
        if n <= 1:
            return m.astype(bool)
        anchor = seed if seed is not None else prompt_mask
        if anchor is not None and anchor.any():
            overlap = np.bincount(labels[anchor], minlength=n)
            overlap[0] = 0
            if overlap.max() == 0:
                keep = [int(np.argmax(stats[1:, cv2.CC_STAT_AREA])) + 1]
            else:
                # The main continuation plus any component mostly inside the old mask (the tissue
                # split in two by the instrument).
                share = overlap / np.maximum(stats[:, cv2.CC_STAT_AREA], 1)
                keep = [i for i in range(1, n) if overlap[i] == overlap.max() or share[i] > 0.5]
        else:
            keep = [int(np.argmax(stats[1:, cv2.CC_STAT_AREA])) + 1]
        out = np.isin(labels, keep)
        # Fill small holes: background components not touching the border and smaller than the limit.
        inv = (~out).astype(np.uint8)
        nh, hl, hs, _ = cv2.connectedComponentsWithStats(inv, connectivity=4)
        limit = self.settings.min_hole_px * self.settings.scale**2
        small_holes = [
            i
            for i in range(1, nh)
            if hs[i, cv2.CC_STAT_AREA] < limit and not _touches_border(hs[i], inv.shape)
        ]
        if small_holes:
            out |= np.isin(hl, small_holes)
        return out


def _touches_border(stat: np.ndarray, shape: tuple[int, int]) -> bool:
    x, y, w, h = stat[:4]
    return x == 0 or y == 0 or x + w >= shape[1] or y + h >= shape[0]


# --------------------------------------------------------------------------------------------- sam2


class Sam2Segmenter(Segmenter):
    """Adapter over the `sam2` package's video predictor (Ravi et al., 2024), from a local model
    config (e.g. configs/sam2.1/sam2.1_hiera_l.yaml, as the package names it) and checkpoint.

    SAM2 propagates over a whole video held in memory, so this backend works on `segment_video`;
    `start` segments a single frame and `track` refuses (re-propagating per frame would be
    quadratic in the video length)."""

    name = "sam2"

    def __init__(
        self, config: str | None = None, checkpoint: str | Path | None = None, *, device: str = "cuda"
    ):
        if config is None or checkpoint is None:
            raise BackendError(
                "sam2: needs config=<model config, e.g. configs/sam2.1/sam2.1_hiera_l.yaml> and "
                "checkpoint=<sam2.1_hiera_large.pt>; the weights cannot be downloaded by vfdata"
            )
        checkpoint = Path(checkpoint).expanduser()
        if not checkpoint.is_file():
            raise BackendError(f"sam2: checkpoint {checkpoint} not found")
        try:
            from sam2.build_sam import build_sam2_video_predictor
        except ImportError as exc:
            raise BackendError(
                f"sam2: the 'sam2' package is not installed ({exc}); "
                "pip install it from github.com/facebookresearch/sam2"
            ) from exc
        try:
            self._predictor = build_sam2_video_predictor(config, str(checkpoint), device=device)
        except Exception as exc:  # hydra/config errors come in many types
            raise BackendError(
                f"sam2: cannot build the predictor from {config} + {checkpoint}: {exc}"
            ) from exc
        self.config, self.checkpoint, self.device = config, checkpoint, device
        self._frames: list[np.ndarray] = []
        self._prompt: Prompt | None = None
        self._masks: list[np.ndarray] = []

    def parameters(self) -> dict:
        return {"backend": self.name, "config": self.config, "checkpoint": str(self.checkpoint)}

    def segment_video(
        self, frames: Iterable[np.ndarray], prompt: Prompt, depths: Iterable[np.ndarray] | None = None
    ) -> list[np.ndarray]:
        import torch

        frames = list(frames)
        if not frames:
            return []
        h, w = frames[0].shape[:2]
        prompt.check_inside(w, h)
        with tempfile.TemporaryDirectory(prefix="vfdata-sam2-") as folder:
            # The predictor reads a folder of JPEG frames named by index.
            for i, frame in enumerate(frames):
                cv2.imwrite(str(Path(folder) / f"{i:06d}.jpg"), frame, [cv2.IMWRITE_JPEG_QUALITY, 95])
            with torch.inference_mode():
                state = self._predictor.init_state(video_path=folder)
                points = list(prompt.positive) + list(prompt.negative)
                labels = [1] * len(prompt.positive) + [0] * len(prompt.negative)
                self._predictor.add_new_points_or_box(
                    inference_state=state,
                    frame_idx=0,
                    obj_id=1,
                    points=np.array(points, np.float32) if points else None,
                    labels=np.array(labels, np.int32) if points else None,
                    box=np.array(prompt.box, np.float32) if prompt.box is not None else None,
                )
                masks: list[np.ndarray | None] = [None] * len(frames)
                for idx, _obj_ids, logits in self._predictor.propagate_in_video(state):
                    masks[idx] = (logits[0, 0] > 0).cpu().numpy()
        if masks[0] is None or not masks[0].any():
            raise InputError(
                "prompt", "the first frame's mask is empty: the prompt does not cover the tissue"
            )
        return [m if m is not None else np.zeros((h, w), bool) for m in masks]

    def start(self, image: np.ndarray, prompt: Prompt, depth_mm: np.ndarray | None = None) -> np.ndarray:
        self._frames, self._prompt = [image], prompt
        self._masks = self.segment_video(self._frames, prompt)
        return self._masks[0]

    def track(self, image: np.ndarray, depth_mm: np.ndarray | None = None) -> np.ndarray:
        # Re-propagating per frame would be quadratic; SAM2 is meant for segment_video.
        raise BackendError("sam2: propagates over a whole video; use segment_video(frames, prompt)")


# ----------------------------------------------------------------------------------------- detector


@dataclass
class DetectorPrompt:
    """A prompt source: torchvision Faster R-CNN (ResNet-50 FPN) with the user's fine-tuned weights,
    as in the paper; the best-scoring box of the first frame becomes the prompt.

    `weights` is a state dict saved from `fasterrcnn_resnet50_fpn(num_classes=...)` (optionally
    under a "model" or "state_dict" key); `label` is the tissue class id."""

    weights: str | Path | None = None
    num_classes: int = 2
    label: int = 1
    min_score: float = 0.5
    min_size: int = 800  # torchvision's input rescaling (shorter side), as in training
    device: str = "cpu"
    _model: object = field(default=None, init=False, repr=False)

    def __post_init__(self):
        if self.weights is None:
            raise BackendError(
                "detector: needs weights=<fine-tuned Faster R-CNN state dict (.pth)>; "
                "no pretrained tissue detector can be downloaded by vfdata"
            )
        path = Path(self.weights).expanduser()
        if not path.is_file():
            raise BackendError(f"detector: weights {path} not found")
        import torch
        from torchvision.models.detection import fasterrcnn_resnet50_fpn

        model = fasterrcnn_resnet50_fpn(
            weights=None, weights_backbone=None, num_classes=self.num_classes, min_size=self.min_size
        )
        state = torch.load(path, map_location="cpu")
        for key in ("model", "state_dict"):
            if isinstance(state, dict) and key in state:
                state = state[key]
        try:
            model.load_state_dict(state)
        except RuntimeError as exc:
            raise BackendError(
                f"detector: {path} does not fit Faster R-CNN with {self.num_classes} classes: "
                f"{str(exc).splitlines()[0]}"
            ) from exc
        self._model = model.to(self.device).eval()

    def __call__(self, image: np.ndarray) -> Prompt:
        """The best box of class `label` on this (BGR) frame."""
        import torch

        _check_image(image)
        rgb = torch.from_numpy(cv2.cvtColor(image, cv2.COLOR_BGR2RGB)).permute(2, 0, 1).float() / 255
        with torch.no_grad():
            out = self._model([rgb.to(self.device)])[0]  # type: ignore[operator]
        keep = (out["labels"] == self.label) & (out["scores"] >= self.min_score)
        if not bool(keep.any()):
            raise InputError("detector", f"no tissue box with score >= {self.min_score} on the first frame")
        best = int(torch.argmax(torch.where(keep, out["scores"], torch.zeros_like(out["scores"]))))
        h, w = image.shape[:2]
        x0, y0, x1, y1 = out["boxes"][best].tolist()
        return Prompt.from_box([max(0.0, x0), max(0.0, y0), min(float(w), x1), min(float(h), y1)])


# ------------------------------------------------------------------------------------------ factory

SEGMENT_BACKENDS = {"colortrack": ColorTrackSegmenter, "sam2": Sam2Segmenter}


def make_segmenter(name: str = "colortrack", **options) -> Segmenter:
    """The segmenter `name` with its options (see each backend's class)."""
    try:
        cls = SEGMENT_BACKENDS[name]
    except KeyError:
        raise BackendError(
            f"unknown segmentation backend '{name}'; known: {', '.join(SEGMENT_BACKENDS)}"
        ) from None
    try:
        return cls(**options)
    except TypeError as exc:
        raise BackendError(f"{name}: bad options {sorted(options)}: {exc}") from exc


def segment_video(
    frames: Iterable[np.ndarray],
    prompt: Prompt | str,
    *,
    backend: str = "colortrack",
    depths: Iterable[np.ndarray] | None = None,
    **options,
) -> list[np.ndarray]:
    """Convenience: masks of a whole video from a prompt (a Prompt or its CLI string)."""
    if isinstance(prompt, str):
        prompt = Prompt.parse(prompt)
    return make_segmenter(backend, **options).segment_video(frames, prompt, depths)


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks (1.0 when both are empty)."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0
