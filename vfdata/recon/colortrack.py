"""The `colortrack` segmenter, the default: runs anywhere without weights.

GrabCut from the prompt on the first frame; then per frame a colour model of tissue and surroundings
(histograms of the Lab chroma, updated as the video goes), a spatial prior from the previous mask
carried along by dense optical flow, an optional depth cue, morphological clean-up and the component
that continues the previous mask. The instrument (grey, metallic) is cut out where it covers the
tissue; the tissue-coloured surroundings stay out because they are far from the carried-over mask
(and at another depth).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vfdata.errors import BackendError, InputError
from vfdata.recon.depth_ramp import ramp_gate
from vfdata.recon.prompt import Prompt
from vfdata.recon.segmenter import Segmenter, check_image

HIGHLIGHT_L = 235  # OpenCV Lab lightness from which a grey pixel is a specular highlight


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
    ramp_gate_mm: float = 12.0  # first frame: box pixels this far off the tissue's depth ramp are probably bed
    # (vfdata.recon.depth_ramp). 18 let in the bed beside a near end the tube sags toward (IoU 0.46 and 0.72 on
    # two fresh colon views into depth, 0.94 and 0.89 at 12); 9 lost most of a tube an instrument crosses (0.66)
    depth_tolerance_mm: float = 6.0  # depth cue: slack on the tissue's depth range ...
    depth_jump: float = 0.04  # ... a depth step over this fraction of the tissue depth per working pixel
    depth_penalty: float = 6.0  # ... is an edge; both get this log-odds penalty
    min_hole_px: int = 400  # holes in the mask smaller than this (full-res px) are filled
    grey_chroma: float = 7.0  # Lab chroma below which a (non-highlight) pixel is taken as metal ...
    grey_penalty: float = 4.0  # ... and gets this log-odds penalty (0: off); tissue is never grey


def metal_pixels(lab: np.ndarray, max_chroma: float = ColorTrackSettings.grey_chroma) -> np.ndarray:
    """(H, W) bool of an (H, W, 3) uint8 Lab image (OpenCV's): grey metal, as instruments and clamps are:
    chroma under `max_chroma`. A specular highlight (near-white) belongs to what surrounds it: wet tissue
    shines too, so a highlight is metal only where metal makes up most of its rim. (Taking every highlight
    as tissue let a clamp ring's highlight into the simulator's colon seed 0 at 180 deg: mask IoU 0.93.)"""
    chroma2 = (lab[..., 1].astype(np.int32) - 128) ** 2 + (lab[..., 2].astype(np.int32) - 128) ** 2
    grey = chroma2 < max_chroma**2
    highlight = grey & (lab[..., 0] >= HIGHLIGHT_L)
    metal = grey & ~highlight
    if highlight.any() and metal.any():
        metal |= _enclosed_by(highlight, metal)
    return metal


def _enclosed_by(spots: np.ndarray, around: np.ndarray, share: float = 0.5) -> np.ndarray:
    """(H, W) bool: the 8-connected components of `spots` whose one-pixel rim is at least `share` `around`."""
    n, labels = cv2.connectedComponents(spots.astype(np.uint8), connectivity=8)
    # Each rim pixel takes the label of the spot beside it (a 3x3 maximum of the labels).
    grown = cv2.dilate(labels.astype(np.float32), np.ones((3, 3), np.uint8)).astype(np.int32)
    rim = (grown > 0) & ~spots
    total = np.bincount(grown[rim], minlength=n)
    covered = np.bincount(grown[rim & around], minlength=n)
    enclosed = covered >= share * np.maximum(total, 1)
    enclosed[0] = False
    return enclosed[labels]


class ColorTrackSegmenter(Segmenter):
    """The embedded default: colour model + flow-carried prior (see the module docstring)."""

    name = "colortrack"
    any_frame = True

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
        return small, grey, bins, metal_pixels(lab, s.grey_chroma)

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
        check_image(image)
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
            seed = next((usable & where for where in (points, middle, np.ones_like(usable))
                         if (usable & where).sum() >= 20), inside > 0)
            # The tissue's depth follows a ramp across the box where it runs into depth (vfdata.recon.depth_ramp).
            # An instrument across the tube splits its visible surface in two: the metal bridges them.
            bridge = metal[by : by + bh, bx : bx + bw] if self.settings.grey_penalty > 0 else None
            gate = ramp_gate(inside, usable, seed, self.settings.ramp_gate_mm, bridge)
            region = gc[by : by + bh, bx : bx + bw]
            region[(inside > 0) & ~gate & (region == cv2.GC_PR_FGD)] = cv2.GC_PR_BGD
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
        # box; re-decide every pixel once with the finer histogram model, GrabCut's mask as prior. The
        # tissue's colours are learnt without the metal GrabCut took in (a grasper's jaws on the tissue).
        self._update_model(bins, mask & ~metal, rate=1.0)
        depth_small = self._small_depth(depth_mm, (sw, sh))
        refined = self._decide(bins, metal, mask, depth_small)
        refined &= cv2.dilate(prompt_mask.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
        refined = self._clean(refined, seed=mask, prompt_mask=None)
        if refined.any():
            mask = refined
        self._update_model(bins, mask, rate=1.0)
        self._prev_grey = grey
        self._prev_mask = mask.astype(np.float32)
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
        check_image(image)
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
