"""A procedural deforming tissue sheet with exact ground truth, for tests and benchmarks of the trackers
without the full simulator.

The sheet is a bumpy height field facing the camera, parametrised by material coordinates (u, v) in
mm. Over the frames it is indented by a moving Gaussian dent (an instrument pushing), stretched, and
translated; every frame's cloud is a fresh random sample of the surface, so there is no point
correspondence between frames, exactly as with clouds from depth maps. Material points, their
surface normals, tissue masks, depth maps and a textured left image come out of the same map.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vfdata.calibration import PinholeCamera

CAMERA = PinholeCamera(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480)


@dataclass(frozen=True)
class SheetMotion:
    """Per-frame motion (arrays of length F): translation (mm), uniform stretch factor along the
    surface, and the depth (mm, +z away from the camera) and centre (u, v mm) of the dent."""

    translation_mm: np.ndarray  # (F, 3)
    stretch: np.ndarray  # (F,)
    dent_depth_mm: np.ndarray  # (F,)
    dent_center_mm: np.ndarray  # (F, 2)
    dent_sigma_mm: float = 8.0

    @property
    def num_frames(self) -> int:
        return len(self.stretch)


def press_and_stretch(num_frames: int = 60, depth_mm: float = 4.0, stretch: float = 0.05) -> SheetMotion:
    """A press-and-release cycle: the dent deepens then relaxes while the sheet stretches by `stretch`
    and drifts by a few mm, the kind of motion a grasped or pushed tissue makes."""
    s = np.sin(np.linspace(0.0, np.pi, num_frames)) ** 2
    drift = np.linspace(0.0, 1.0, num_frames)
    translation = np.stack([1.5 * drift, -1.0 * drift, 2.0 * s], axis=1)
    centre = np.stack([np.full(num_frames, 3.0), np.linspace(-2.0, 2.0, num_frames)], axis=1)
    return SheetMotion(translation, 1.0 + stretch * s, depth_mm * s, centre)


def rigid_translation(num_frames: int, total_mm: np.ndarray) -> SheetMotion:
    t = np.linspace(0.0, 1.0, num_frames)[:, None] * np.asarray(total_mm, dtype=np.float64)[None, :]
    return SheetMotion(t, np.ones(num_frames), np.zeros(num_frames), np.zeros((num_frames, 2)))


class DeformingSheet:
    """The sheet under `motion`; width_mm square of material, at `distance_mm` from the camera."""

    def __init__(self, motion: SheetMotion, width_mm: float = 60.0, distance_mm: float = 80.0, seed: int = 0):
        self.motion = motion
        self.half = 0.5 * width_mm
        self.distance_mm = distance_mm
        self.seed = seed
        rng = np.random.default_rng(seed)
        # A few smooth bumps give the surface shape that the Chamfer term can lock onto.
        self._bumps = [
            (rng.uniform(-self.half, self.half, 2), rng.uniform(6, 14), rng.uniform(-3, 3)) for _ in range(6)
        ]
        noise = rng.standard_normal((256, 256)).astype(np.float32)
        self._texture = cv2.GaussianBlur(noise, (0, 0), 2.0)
        self._texture = (self._texture - self._texture.min()) / np.ptp(self._texture)

    @property
    def num_frames(self) -> int:
        return self.motion.num_frames

    def surface(self, uv: np.ndarray, frame: int) -> np.ndarray:
        """(N, 2) material coordinates (mm) -> (N, 3) camera-frame points (mm) at `frame`."""
        m = self.motion
        u, v = uv[:, 0], uv[:, 1]
        z = np.full(len(uv), self.distance_mm)
        for centre, sigma, height in self._bumps:
            z += height * np.exp(-((u - centre[0]) ** 2 + (v - centre[1]) ** 2) / (2 * sigma**2))
        dc = m.dent_center_mm[frame]
        z += m.dent_depth_mm[frame] * np.exp(-((u - dc[0]) ** 2 + (v - dc[1]) ** 2) / (2 * m.dent_sigma_mm**2))
        points = np.stack([u * m.stretch[frame], v * m.stretch[frame], z], axis=1)
        return points + m.translation_mm[frame]

    def normals(self, uv: np.ndarray, frame: int) -> np.ndarray:
        """(N, 3) unit surface normals (facing the camera) by central differences in (u, v)."""
        h = 1e-3
        du = self.surface(uv + [h, 0], frame) - self.surface(uv - [h, 0], frame)
        dv = self.surface(uv + [0, h], frame) - self.surface(uv - [0, h], frame)
        n = np.cross(du, dv)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        return np.where(n[:, 2:3] > 0, -n, n)

    def material_grid(self, per_side: int = 60) -> np.ndarray:
        g = np.linspace(-self.half, self.half, per_side)
        uu, vv = np.meshgrid(g, g)
        return np.stack([uu.ravel(), vv.ravel()], axis=1)

    def cloud(self, frame: int, num_points: int = 20000) -> np.ndarray:
        """A fresh uniform random sample of the surface at `frame` (seeded by frame), (M, 3) mm."""
        rng = np.random.default_rng((self.seed, frame))
        return self.surface(rng.uniform(-self.half, self.half, (num_points, 2)), frame)

    def image(self, frame: int, camera: PinholeCamera = CAMERA) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(gray uint8 image, bool tissue mask, depth mm with 0 off the tissue) seen by `camera`,
        rendered by splatting a dense material grid (the sheet is a height field facing the camera)."""
        uv = self.material_grid(700)
        p = self.surface(uv, frame)
        pix = camera.project(p)
        col = np.floor(pix[:, 0] + 0.5).astype(np.int64)
        row = np.floor(pix[:, 1] + 0.5).astype(np.int64)
        ok = (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
        flat = row[ok] * camera.width + col[ok]
        size = camera.width * camera.height
        count = np.bincount(flat, minlength=size)
        tex_idx = np.clip(((uv[ok] + self.half) / (2 * self.half) * 255).astype(np.int64), 0, 255)
        tex = self._texture[tex_idx[:, 1], tex_idx[:, 0]]
        intensity = np.bincount(flat, weights=tex, minlength=size) / np.maximum(count, 1)
        depth = np.bincount(flat, weights=p[ok, 2], minlength=size) / np.maximum(count, 1)
        mask = (count > 0).reshape(camera.height, camera.width)
        image = (40 + 200 * intensity).reshape(camera.height, camera.width)
        image[~mask] = 0
        return image.astype(np.uint8), mask, np.where(mask, depth.reshape(mask.shape), 0.0)

    def reference_tracks(self, reference_points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact ground-truth trajectories (F, N, 3) and normals (F, N, 3) of points picked on frame 0.

        Frame 0 maps (u, v) -> (u s + tx, v s + ty, z), so the material coordinates of a point follow
        from its x, y alone."""
        m = self.motion
        uv = (reference_points[:, :2] - m.translation_mm[0, :2]) / m.stretch[0]
        tracks = np.stack([self.surface(uv, f) for f in range(self.num_frames)])
        normals = np.stack([self.normals(uv, f) for f in range(self.num_frames)])
        return tracks, normals
