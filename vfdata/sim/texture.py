"""Procedural tissue textures: tileable fractal noise, vessels, and the albedo, bump and gloss maps
of a surface from its colour palette (OpenCV and NumPy, no compiled kernels: the presets import the
palettes without loading the renderer)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


def tileable_noise(rng: np.random.Generator, height: int, width: int, cells: tuple[int, int]) -> np.ndarray:
    """Smooth value noise (unit variance-ish), periodic in both directions: random values on a cells
    grid, bicubically interpolated with wrap-around (pixel centres as cv2.resize places them)."""
    gh, gw = cells
    low = rng.standard_normal((gh, gw)).astype(np.float32)
    # Bicubic from the cell grid to at most 16 samples per cell, then bilinear to the full size (the
    # field is smooth at that scale), both as affine warps that wrap around: about three times
    # cheaper than bicubic all the way for the coarse octaves.
    mid_w, mid_h = min(width, 16 * gw), min(height, 16 * gh)
    mid = _wrap_resize(low, mid_w, mid_h, cv2.INTER_CUBIC)
    return mid if (mid_w, mid_h) == (width, height) else _wrap_resize(mid, width, height, cv2.INTER_LINEAR)


def _wrap_resize(img: np.ndarray, width: int, height: int, interpolation: int) -> np.ndarray:
    """Resize a periodic image (pixel centres as cv2.resize places them), wrapping around the borders."""
    sx, sy = width / img.shape[1], height / img.shape[0]
    m = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5]])
    return cv2.warpAffine(img, m, (width, height), flags=interpolation, borderMode=cv2.BORDER_WRAP)


def fractal_noise(rng: np.random.Generator, height: int, width: int, base_cells: int, octaves: int,
                  aspect: float = 1.0) -> np.ndarray:
    out = np.zeros((height, width), np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        cells = (max(2, int(base_cells * 2**o * aspect)), max(2, int(base_cells * 2**o)))
        out += amp * tileable_noise(rng, height, width, cells)
        total += amp
        amp *= 0.55
    return out / total


def draw_vessels(rng: np.random.Generator, height: int, width: int, count: int, thickness: tuple[int, int],
                 length_px: tuple[int, int]) -> np.ndarray:
    """A mask (float32, 0..1) of branching, meandering vessels, periodic in both directions."""
    canvas = np.zeros((3 * height, 3 * width), np.uint8)

    def walk(x: float, y: float, heading: float, length: int, thick: int, depth: int) -> None:
        step = 4.0
        n = max(2, int(length / step))
        headings = heading + np.cumsum(rng.normal(0, 0.22, n))
        xs = x + step * np.cumsum(np.cos(headings))
        ys = y + step * np.cumsum(np.sin(headings))
        if depth < 2:
            for k in np.nonzero(rng.random(n) < 0.035)[0]:
                walk(xs[k], ys[k], headings[k] + rng.choice([-1, 1]) * rng.uniform(0.5, 1.1), int(length * 0.5),
                     max(1, thick - 1), depth + 1)
        pts = np.concatenate([[[x, y]], np.stack([xs, ys], axis=1)])
        cv2.polylines(canvas, [np.round(pts * 16).astype(np.int32)], False, 255, thick, cv2.LINE_AA, 4)

    for _ in range(count):
        walk(rng.uniform(width, 2 * width), rng.uniform(height, 2 * height), rng.uniform(0, 2 * np.pi),
             int(rng.integers(*length_px)), int(rng.integers(*thickness)), 0)
    tiles = canvas.reshape(3, height, 3, width).max(axis=(0, 2))
    return cv2.GaussianBlur(tiles.astype(np.float32) / 255.0, (0, 0), 0.8)


@dataclass(frozen=True)
class Palette:
    light: tuple[float, float, float]   # linear RGB albedo
    dark: tuple[float, float, float]
    vessel: tuple[float, float, float]
    blotch: tuple[float, float, float]
    vessel_count: int
    gloss: float                        # mean specular strength
    shininess: float
    grain: float                        # amplitude of fine texture (what stereo matching locks on)


@dataclass
class Texture:
    """Material textures sampled by (u, v) pixel coordinates; u wraps around. Albedo and gloss share
    one 4-channel map (OpenCV remaps 4 channels about twice as fast as 3); the bump gradients are two
    single-channel maps (OpenCV remaps two 1-channel images in less than half the time of one
    2-channel image)."""

    albedo_gloss: np.ndarray  # (H, W, 4) float32: linear RGB albedo, gloss
    bump_u: np.ndarray        # (H, W) float32: bump d/du
    bump_v: np.ndarray        # (H, W) float32: bump d/dv

    @property
    def albedo(self) -> np.ndarray:
        return self.albedo_gloss[..., :3]

    def sample(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Albedo (3, P), gloss (P,) and bump gradients (2, P) at texture pixel coordinates u, v (P,)."""
        n = len(u)
        cols = 1024  # remap maps are images: lay the samples out in rows
        rows = max(1, -(-n // cols))
        mx = np.zeros(rows * cols, np.float32)
        my = np.zeros(rows * cols, np.float32)
        mx[:n] = u
        my[:n] = v
        mx, my = mx.reshape(rows, cols), my.reshape(rows, cols)
        ag = cv2.remap(self.albedo_gloss, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        bump = np.empty((2, rows, cols), np.float32)
        for k, plane in enumerate((self.bump_u, self.bump_v)):
            cv2.remap(plane, mx, my, cv2.INTER_LINEAR, dst=bump[k], borderMode=cv2.BORDER_WRAP)
        ag = ag.reshape(-1, 4)[:n].T
        return ag[:3], ag[3], bump.reshape(2, -1)[:, :n]


def make_texture(rng: np.random.Generator, height: int, width: int, palette: Palette) -> Texture:
    """Procedural tissue: smooth colour variation, mottling, vessels, fine grain with weak-texture
    patches, a wetness (gloss) map and a bump map."""
    base = fractal_noise(rng, height, width, 3, 3)
    mix = np.clip(0.5 + 0.6 * base, 0, 1)[..., None]
    albedo = (np.array(palette.light, np.float32) * (1 - mix) + np.array(palette.dark, np.float32) * mix)
    blotch = np.clip(fractal_noise(rng, height, width, 10, 2) * 1.6 - 0.4, 0, 1)[..., None]
    albedo = albedo * (1 - 0.5 * blotch) + np.array(palette.blotch, np.float32) * 0.5 * blotch
    grain = fractal_noise(rng, height, width, 48, 3)
    # Weak-texture patches: the fine grain fades out in places.
    patch = np.clip(0.6 + 1.4 * fractal_noise(rng, height, width, 4, 1), 0.05, 1.0)
    albedo *= (1 + palette.grain * grain * patch)[..., None]
    if palette.vessel_count:
        vessels = draw_vessels(rng, height, width, palette.vessel_count, (2, 5), (height // 4, height))
        fine = draw_vessels(rng, height, width, palette.vessel_count * 2, (1, 2), (height // 10, height // 3))
        # Vessels lie at varying depth under the surface: their contrast fades in and out.
        fade = np.clip(0.55 + 0.7 * fractal_noise(rng, height, width, 5, 2), 0.1, 1.0)
        v = (np.clip(0.85 * vessels + 0.45 * fine, 0, 1) * fade)[..., None]
        albedo = albedo * (1 - 0.75 * v) + np.array(palette.vessel, np.float32) * 0.75 * v
    albedo = np.clip(albedo, 0.0, 1.0).astype(np.float32)
    gloss = np.clip(palette.gloss * (0.55 + 0.9 * fractal_noise(rng, height, width, 12, 2)), 0, None)
    bump = fractal_noise(rng, height, width, 14, 2)
    gu = (np.roll(bump, -1, axis=1) - np.roll(bump, 1, axis=1)) / 2.0  # wraps around the tube
    gv = np.gradient(bump, axis=0)
    return Texture(np.dstack([albedo, gloss]).astype(np.float32), gu.astype(np.float32), gv.astype(np.float32))
