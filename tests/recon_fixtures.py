"""Shared helpers for the reconstruction tests: simulator recordings and synthetic tubes."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml


def make_sim_recording(folder: Path, index: int = 0, frames: int = 10, seed: int = 0) -> Path:
    """One recording of the simulator's `mini` preset (raw folder with ground_truth/)."""
    from vfdata.sim.presets import get_preset
    from vfdata.sim.synthesize import build_recording, write_recording

    plan = get_preset("mini").recordings[index]
    target = folder / plan.id
    if not target.exists():
        target.mkdir(parents=True)
        write_recording(build_recording(plan, seed, frames=frames), target, "mini", seed)
    return target


def load_sim_frames(rec: Path, frames: int) -> dict:
    """Images (BGR), ground-truth masks (bool) and depths (mm, NaN = none) and the prompt box."""
    out = {"left": [], "right": [], "mask": [], "depth": []}
    for i in range(frames):
        for side in ("left", "right"):
            (path,) = (rec / side).glob(f"{i:06d}.*")  # JPEG by default, PNG with --image-format png
            out[side].append(cv2.imread(str(path)))
        out["mask"].append(cv2.imread(str(rec / "ground_truth" / "mask" / f"{i:06d}.png"), 0) > 0)
        depth = cv2.imread(str(rec / "ground_truth" / "depth" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        depth = depth.astype(np.float32) / 10.0
        depth[depth == 0] = np.nan
        out["depth"].append(depth)
    out["prompt_box"] = yaml.safe_load((rec / "meta.yaml").read_text())["prompt_box"]
    return out


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def tapered_tube(
    rng: np.random.Generator,
    rotation: np.ndarray,
    *,
    n: int = 3000,
    length: float = 60.0,
    r_wide: float = 10.0,
    r_narrow: float = 6.0,
    noise: float = 0.3,
    distance: float = 120.0,
) -> np.ndarray:
    """Camera-frame points (mm) of the camera-facing half of a tapered tube: object Z along the
    axis from the wide end (z = 0) to the narrow end, placed at `distance` along the optical axis.
    Only surface points whose normal faces the camera are kept, as a stereo camera sees them."""
    z = rng.uniform(0, length, 4 * n)
    theta = rng.uniform(0, 2 * np.pi, 4 * n)
    r = r_wide + (r_narrow - r_wide) * z / length
    local = np.stack([r * np.cos(theta), r * np.sin(theta), z - length / 2], axis=1)
    normal = np.stack([np.cos(theta), np.sin(theta), np.full_like(z, (r_wide - r_narrow) / length)], axis=1)
    points = local @ rotation.T + np.array([0.0, 0.0, distance])
    facing = (normal @ rotation.T * points).sum(axis=1) < 0
    points = points[facing][:n]
    return points + rng.normal(scale=noise, size=points.shape)
