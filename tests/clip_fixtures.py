"""Small in-memory clips that follow the batch contract of vfmodels.ForceRegressor, for model tests.

The points are a 2D grid pressed by a smooth, time-varying indentation; the force is a fixed linear
function (an elastic response) of the indentation, so a model can learn it from the point motion.
"""

from __future__ import annotations

import lightning.pytorch as L
import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader, Dataset


def make_clips(clips: int = 8, frames: int = 16, points: int = 36, seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(seed)
    side = int(round(np.sqrt(points)))
    gx, gy = np.meshgrid(np.linspace(-20, 20, side), np.linspace(-20, 20, side))
    grid = np.stack([gx.ravel(), gy.ravel(), np.zeros(side * side)], axis=1)  # mm
    out = []
    for i in range(clips):
        phase, amp = rng.uniform(0, 2 * np.pi), rng.uniform(2, 6)
        t = np.arange(frames) / 30.0
        depth = amp * (1 + np.sin(2 * np.pi * 0.8 * t + phase))  # mm, indentation at the centre
        shift = rng.uniform(-3, 3, size=2) * np.sin(2 * np.pi * 0.5 * t[:, None] + phase)  # mm, lateral drag
        bump = np.exp(-(grid[:, 0] ** 2 + grid[:, 1] ** 2) / 200.0)
        pos = np.repeat(grid[None], frames, axis=0)
        pos[:, :, 2] -= depth[:, None] * bump
        pos[:, :, :2] += shift[:, None, :] * bump[None, :, None]
        vel = np.gradient(pos, 1 / 30.0, axis=0)
        force = np.stack([0.3 * shift[:, 0], 0.3 * shift[:, 1], 0.5 * depth], axis=1)  # N
        valid = rng.random((frames, side * side)) > 0.1
        out.append({
            "tokens": torch.tensor(np.concatenate([pos, vel], axis=2), dtype=torch.float32),
            "valid": torch.tensor(valid),
            "force": torch.tensor(force, dtype=torch.float32),
            "orientation_deg": torch.tensor(float(30 * (i % 2))),
            "recording": f"synthetic_{i:03d}",
            "frame_time_ns": torch.arange(frames, dtype=torch.int64) * 33_333_333 + i * 10**10,
        })
    return out


class ClipList(Dataset):
    def __init__(self, clips: list[dict]):
        self.clips = clips

    def __len__(self) -> int:
        return len(self.clips)

    def __getitem__(self, i: int) -> dict:
        return self.clips[i]


def normalisation(clips: list[dict]) -> dict[str, torch.Tensor]:
    tokens = torch.cat([c["tokens"][c["valid"]] for c in clips])
    force = torch.cat([c["force"] for c in clips])
    return dict(input_mean=tokens.mean(0), input_std=tokens.std(0) + 1e-6,
                force_mean=force.mean(0), force_std=force.std(0) + 1e-6)


class SyntheticClipDataModule(L.LightningDataModule):
    def __init__(self, clips: int = 8, frames: int = 16, points: int = 36, batch_size: int = 4):
        super().__init__()
        self.clips = make_clips(clips, frames, points)
        self.batch_size = batch_size
        self.normalisation = normalisation(self.clips)

    def _loader(self) -> DataLoader:
        return DataLoader(ClipList(self.clips), batch_size=self.batch_size)

    def train_dataloader(self) -> DataLoader:
        return self._loader()

    val_dataloader = test_dataloader = predict_dataloader = train_dataloader


@pytest.fixture(autouse=True)
def single_thread():
    """One intra-op thread for the model tests: the tensors are tiny, and on a loaded machine two
    OpenMP threads waiting on each other spend far more CPU than the work itself."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
