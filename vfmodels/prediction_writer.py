"""`ForceEstimateWriter`: the callback behind `train.py predict`. It gathers the per-frame forces of
every predicted clip and, at the end, writes one MCAP per recording with `/force/estimate`
(geometry_msgs/msg/WrenchStamped, N, frame `tissue_object`, torque NaN: not estimated), beside the
recording or in `output_dir`, as `<id>.force.mcap` (vfdata.predict.write_force_mcap, the same file
`vfdata predict` writes).

Clips overlap, so a frame is predicted several times; each frame is written once, from the clip in
which it had the most history (the latest position), as an online causal estimator would give it.
The datamodule must say where each recording lives: `entries` (vfdata.datasets.ManifestEntry list).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lightning.pytorch.callbacks import BasePredictionWriter
from lightning.pytorch.utilities import rank_zero_info

from vfdata.errors import InputError


class ForceEstimateWriter(BasePredictionWriter):
    def __init__(self, output_dir: str | None = None, overwrite: bool = True):
        super().__init__(write_interval="batch")
        self.output_dir = Path(output_dir) if output_dir else None
        self.overwrite = overwrite
        self.written: list[Path] = []
        self._frames: dict[str, dict[int, tuple[int, np.ndarray]]] = {}

    def on_predict_start(self, trainer, pl_module) -> None:
        self._frames = {}
        self.written = []

    def write_on_batch_end(self, trainer, pl_module, prediction: dict[str, Any], batch_indices, batch,
                           batch_idx: int, dataloader_idx: int = 0) -> None:
        if prediction.get("frame_time_ns") is None or not prediction.get("recording"):
            return
        force = prediction["force_n"].numpy()
        times = prediction["frame_time_ns"].numpy()
        for b, rid in enumerate(prediction["recording"]):
            frames = self._frames.setdefault(rid, {})
            for position, (t, f) in enumerate(zip(times[b], force[b], strict=True)):
                known = frames.get(int(t))
                if known is None or position > known[0]:
                    frames[int(t)] = (position, f)

    def on_predict_end(self, trainer, pl_module) -> None:
        from vfdata.predict import write_force_mcap
        from vfdata.recording import Recording, layout

        if trainer.world_size > 1:  # every rank predicted a share of the clips: merge on rank 0
            gathered: list = [None] * trainer.world_size
            torch.distributed.all_gather_object(gathered, self._frames)
            merged: dict[str, dict[int, tuple[int, np.ndarray]]] = {}
            for part in gathered:
                for rid, frames in part.items():
                    into = merged.setdefault(rid, {})
                    for t, (position, f) in frames.items():
                        if t not in into or position > into[t][0]:
                            into[t] = (position, f)
            self._frames = merged
        if not trainer.is_global_zero:
            return
        entries = {e.id: e for e in getattr(trainer.datamodule, "entries", [])}
        model = type(pl_module.model).__name__
        for rid, frames in sorted(self._frames.items()):
            entry = entries.get(rid)
            if entry is None and self.output_dir is None:
                raise InputError(Path(rid), "recording not in the datamodule's manifest: pass output_dir")
            rotation, origin = np.eye(3), np.zeros(3)
            if entry is not None and entry.processed.is_file():
                with Recording.open(entry.processed) as rec:
                    meta = rec.metadata_records.get(layout.DERIVED_METADATA, {})
                if "object_frame" in meta:
                    frame = json.loads(meta["object_frame"])
                    rotation, origin = np.asarray(frame["rotation"]), np.asarray(frame["origin"])
            folder = self.output_dir or entry.mcap.parent
            folder.mkdir(parents=True, exist_ok=True)
            times = np.array(sorted(frames), dtype=np.int64)
            force = np.stack([frames[int(t)][1] for t in times]).astype(np.float64)
            path = write_force_mcap(folder / f"{rid}.force.mcap", times, force, rotation, origin,
                                    {"stage": "train.py predict", "model": model, "recording": rid,
                                     "source": str(entry.processed if entry else "")}, overwrite=self.overwrite)
            self.written.append(path)
            rank_zero_info(f"wrote {path} ({len(times)} frames)")
