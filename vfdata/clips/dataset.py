"""`ForceClipDataset`: clips of processed recordings for the force models (a plain torch Dataset).

A clip is `spec.clip_frames` consecutive frames (one starting every `spec.stride` frames) of one
recording; clips never span a gap (consecutive frames more than 1.5 frame periods apart), and a last
clip ends on each gap-free run's last frame so no frame is left out. Each item is a dict (the batch
contract of `vfmodels.ForceRegressor`):

- the model input under `spec.input_key`: `tokens` (T, N, C) float32 with `valid` (T, N) bool for point
  inputs, `images` (T, 3, S, S) uint8 RGB, or `depth` (T, 1, S, S) float32 mm (0 off the tissue);
- `force` (T, 3) float32 N: the sensor's force at each frame time (NaN where the sensor stream has a
  gap); the sensor is mounted under the tissue and turns with it, so its frame is the object's;
- `orientation_deg`, `recording` (id), `frame_time_ns` (T,) int64, `frame_index` (T,) int64;
- `side` (+1 or -1): the factor applied to the y of the points and of the force (`canonical_side`);
  multiply a predicted Fy by it to get the sensor's.

    ds = ForceClipDataset.from_manifest("datasets/mini.manifest.yaml", split="train")
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset
from tqdm import tqdm

from vfdata.clips.decode import Decoded, decode_recording
from vfdata.clips.spec import ClipSpec
from vfdata.clips.tokens import (
    clip_starts,
    frame_rate,
    segments,
    tilt_about,
    tilt_tokens,
    transform_tokens,
    turn_about_z,
)
from vfdata.errors import InputError
from vfdata.manifest import ManifestEntry, load_manifest


class ForceClipDataset(Dataset):
    """Clips of the given manifest entries, made as `spec` says (see the module docstring)."""

    def __init__(self, recordings: list[ManifestEntry], spec: ClipSpec | None = None,
                 cache_dir: str | Path | None = None, progress: bool = True, augment: bool = False):
        if isinstance(recordings, (str, Path)):
            raise TypeError("ForceClipDataset takes manifest entries; for a manifest file use "
                            "ForceClipDataset.from_manifest(path, split=...)")
        self.spec = spec or ClipSpec()
        self.augment = augment  # training only: the spec's augmentations (mirror, rotation) are applied
        self.entries = list(recordings)
        self.recordings: list[Decoded] = [
            decode_recording(e, self.spec, cache_dir)
            for e in tqdm(self.entries, desc=f"decoding {self.spec.input}", unit="recording", disable=not progress)
        ]
        index = [(r, int(start)) for r, d in enumerate(self.recordings)
                 for start in clip_starts(segments(d.times_ns), self.spec.clip_frames, self.spec.stride)]
        self.index = np.asarray(index, dtype=np.int64).reshape(-1, 2)

    @classmethod
    def from_manifest(cls, manifest: str | Path, split: str = "train", spec: ClipSpec | None = None,
                      cache_dir: str | Path | None = None, progress: bool = True) -> ForceClipDataset:
        """The clips of one split (train, val or test) of a dataset manifest."""
        return cls(load_manifest(manifest).split(split), spec, cache_dir, progress)

    @property
    def fps(self) -> float:
        """The frame rate used for velocities: the spec's, or the median over the recordings."""
        if self.spec.fps:
            return float(self.spec.fps)
        rates = [frame_rate(d.times_ns) for d in self.recordings if len(d.times_ns) > 1]
        return float(np.median(rates)) if rates else 30.0

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> dict:
        r, start = (int(v) for v in self.index[i])
        entry, d = self.entries[r], self.recordings[r]
        window = slice(start, start + self.spec.clip_frames)
        item = {
            self.spec.input_key: torch.from_numpy(np.ascontiguousarray(d.inputs[window])),
            "force": torch.from_numpy(np.ascontiguousarray(d.force_n[window])),
            "orientation_deg": torch.tensor(entry.orientation_deg, dtype=torch.float32),
            "recording": entry.id,
            "frame_time_ns": torch.from_numpy(np.ascontiguousarray(d.times_ns[window])),
            "frame_index": torch.arange(start, start + self.spec.clip_frames, dtype=torch.int64),
            "side": torch.tensor(d.side, dtype=torch.float32),
        }
        if self.spec.input_key == "depth":
            item["depth"] = item["depth"].float()
        if d.valid is not None:
            item["valid"] = torch.from_numpy(np.ascontiguousarray(d.valid[window]))
        if self.augment and (self.spec.mirror_augment or self.spec.rotate_augment or self.spec.tilt_augment_deg):
            self._augment(item)
        return item

    def _augment(self, item: dict) -> None:
        """Tilt the object frame (points only, the force is the sensor's), then mirror across its XZ
        plane (probability 1/2) and turn about its Z axis (uniform angle), as the spec asks: points and
        force alike. torch's generator, so that each data-loader worker draws its own."""
        if self.spec.tilt_augment_deg:
            axis_angle, fraction = (float(v) for v in torch.rand(2))
            tilt = tilt_about(2 * np.pi * axis_angle, np.radians(self.spec.tilt_augment_deg) * fraction)
            item["tokens"] = torch.from_numpy(tilt_tokens(item["tokens"].numpy(), self.spec.features, tilt))
        mirror = bool(self.spec.mirror_augment and torch.rand(()) < 0.5)
        angle = float(torch.rand(()) * 2 * np.pi) if self.spec.rotate_augment else 0.0
        matrix = turn_about_z(angle, mirror)
        item["tokens"] = torch.from_numpy(transform_tokens(item["tokens"].numpy(), matrix.astype(np.float32)))
        item["force"] = item["force"] @ torch.from_numpy(matrix.T.astype(np.float32))
        if mirror:
            item["side"] = -item["side"]

    def normalisation(self) -> dict[str, torch.Tensor]:
        """Input and force statistics of this dataset (every frame of its recordings once): tokens
        per channel over valid points; depth over tissue pixels; RGB none (the model normalises RGB
        itself with its backbone's statistics)."""
        force = np.concatenate([d.force_n for d in self.recordings])
        force = force[np.isfinite(force).all(axis=1)]
        if len(force) < 2:
            raise InputError(self.entries[0].mcap if self.entries else Path("."), "no force samples for statistics")
        mean, std = self._symmetric_moments(force.astype(np.float64))
        stats = {"force_mean": torch.tensor(mean), "force_std": torch.tensor(std + 1e-6)}
        if self.spec.input_key == "tokens":
            values = np.concatenate([d.inputs[d.valid] for d in self.recordings]).astype(np.float64)
            mean, std = self._symmetric_moments(values)
            stats["input_mean"] = torch.tensor(mean)
            stats["input_std"] = torch.tensor(std + 1e-6)
        elif self.spec.input_key == "depth":
            values = np.concatenate([d.inputs[d.inputs > 0] for d in self.recordings]).astype(np.float64)
            stats["input_mean"] = torch.tensor([values.mean()])
            stats["input_std"] = torch.tensor([values.std() + 1e-6])
        else:
            stats["input_mean"], stats["input_std"] = torch.zeros(0), torch.zeros(0)
        return {k: v.float() for k, v in stats.items()}


    def _symmetric_moments(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-channel mean and std of (M, C) 3-vector channels over what training will see: with the
        mirror, y has mean 0; with the rotation about Z, x and y have mean 0 and one shared spread.
        Without augmentation, the plain moments."""
        mean, second = values.mean(0), (values ** 2).mean(0)
        if self.augment and (self.spec.mirror_augment or self.spec.rotate_augment):
            mean[1::3] = 0.0
            if self.spec.rotate_augment:
                mean[0::3] = 0.0
                second[0::3] = second[1::3] = 0.5 * (second[0::3] + second[1::3])
        return mean, np.sqrt(np.maximum(second - mean ** 2, 0.0))


def collate_clips(items: list[dict]) -> dict:
    """Stack tensors; keep the recording ids as a list."""
    out = {}
    for key in items[0]:
        values = [item[key] for item in items]
        out[key] = values if isinstance(values[0], str) else torch.stack(values)
    return out
