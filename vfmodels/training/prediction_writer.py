"""`trainer.predict` callbacks: `PredictionCollector` gathers the per-frame forces of every predicted
clip (each frame once, from the clip in which it had the most history, as a causal online estimator
gives it), and `ForceEstimateWriter` (behind `train.py predict`) writes them as one `/force/estimate`
MCAP per recording (`vfdata.recording.derived.write_force_estimate`, the file `vfdata predict` writes).

The writer needs to know where each recording lives: the datamodule's `entries` (manifest entries).
Like every `vfdata` command it refuses to replace an existing file unless `overwrite`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from lightning.pytorch.callbacks import BasePredictionWriter
from lightning.pytorch.utilities import rank_zero_info

from vfdata.clips.tokens import latest_clip_frames
from vfdata.errors import InputError, OutputExistsError
from vfdata.recon.object_frame import ObjectFrame
from vfdata.recording import layout
from vfdata.recording.derived import DerivedRecording, write_force_estimate
from vfdata.tissue_lean import lean_metadata, recording_lean
from vfmodels.evaluation.band import unlikeness

FIELDS = ("recording", "orientation_deg", "frame_time_ns", "position", "pred", "true", "band", "spread", "distance")
VECTORS = ("pred", "true", "band", "spread")  # (M, 3) N


class PredictionCollector(BasePredictionWriter):
    """Per-frame predictions of a `trainer.predict` run, available as `frames` after it: recording
    (M,) str, orientation_deg (M,), frame_time_ns (M,) int64, pred (M, 3) N, true (M, 3) N (NaN where
    the batches had no measured force), band (M, 3) N (the half-width of each component's band, NaN
    without a calibration), spread (M, 3) N and distance (M,) (its signals: `vfmodels.training.regressor.Estimate`;
    NaN where unknown), sorted by recording and time."""

    def __init__(self) -> None:
        super().__init__(write_interval="batch")
        self._parts: list[dict[str, np.ndarray]] = []
        self.frames: dict[str, np.ndarray] | None = None

    def on_predict_start(self, trainer, pl_module) -> None:
        self._parts, self.frames = [], None

    def write_on_batch_end(self, trainer, pl_module, prediction: dict[str, Any], batch_indices, batch,
                           batch_idx: int, dataloader_idx: int = 0) -> None:
        if prediction.get("frame_time_ns") is None:
            return
        pred = prediction["force_n"].numpy()
        b, t = pred.shape[:2]
        true = prediction["true_n"].numpy() if "true_n" in prediction else np.full_like(pred, np.nan)
        band = prediction["band_n"].numpy() if "band_n" in prediction else np.full_like(pred, np.nan)
        spread = prediction["spread_n"].numpy() if "spread_n" in prediction else np.full_like(pred, np.nan)
        distance = prediction["distance"].numpy() if "distance" in prediction else np.full(pred.shape[:2], np.nan)
        self._parts.append({
            "recording": np.repeat(np.asarray(prediction["recording"], dtype=object), t).astype(str),
            "orientation_deg": np.repeat(prediction["orientation_deg"].numpy().astype(np.float64), t),
            "frame_time_ns": prediction["frame_time_ns"].numpy().reshape(-1).astype(np.int64),
            "position": np.tile(np.arange(t), b),
            "pred": pred.reshape(-1, 3).astype(np.float64),
            "true": true.reshape(-1, 3).astype(np.float64),
            "band": band.reshape(-1, 3).astype(np.float64),
            "spread": spread.reshape(-1, 3).astype(np.float64),
            "distance": distance.reshape(-1).astype(np.float64),
        })

    def on_predict_end(self, trainer, pl_module) -> None:
        parts = self._parts
        if trainer.world_size > 1:  # every rank predicted a share of the clips: merge them
            gathered: list = [None] * trainer.world_size
            torch.distributed.all_gather_object(gathered, parts)
            parts = [p for rank in gathered for p in rank]
        if not parts:
            self.frames = {k: np.zeros((0, 3) if k in VECTORS else 0) for k in FIELDS if k != "position"}
        else:
            frames = {k: np.concatenate([p[k] for p in parts]) for k in FIELDS}
            keep = latest_clip_frames(frames["recording"], frames["frame_time_ns"], frames["position"])
            self.frames = {k: v[keep] for k, v in frames.items() if k != "position"}
        if trainer.is_global_zero:
            self.publish(trainer, pl_module)

    def publish(self, trainer, pl_module) -> None:
        """What to do with the frames once gathered (rank 0): nothing here; see ForceEstimateWriter."""


class ForceEstimateWriter(PredictionCollector):
    """Writes `<id>.force.mcap` per predicted recording, beside its recording or in `output_dir`.

    Args:
        output_dir: folder of the force files (default: beside each recording).
        overwrite: replace existing force files (default: refuse, as every vfdata command).
    """

    def __init__(self, output_dir: str | None = None, overwrite: bool = False):
        super().__init__()
        self.output_dir = Path(output_dir) if output_dir else None
        self.overwrite = overwrite
        self.written: list[Path] = []

    def _targets(self, trainer, recordings: list[str]) -> dict[str, tuple[Path, Any]]:
        entries = {e.id: e for e in getattr(trainer.datamodule, "entries", [])}
        targets = {}
        for rid in recordings:
            entry = entries.get(rid)
            if entry is None and self.output_dir is None:
                raise InputError(Path(rid), "recording not in the datamodule's manifest: pass output_dir")
            path = (self.output_dir or entry.mcap.parent) / f"{rid}.force.mcap"
            if path.exists() and not self.overwrite:
                raise OutputExistsError(path)
            targets[rid] = (path, entry)
        return targets

    def publish(self, trainer, pl_module) -> None:
        self.written = []
        frames = self.frames
        recordings = sorted(set(frames["recording"].tolist()))
        targets = self._targets(trainer, recordings)  # every refusal before anything is written
        model = type(pl_module.model).__name__
        # the training tissues' leans, recorded beside the force: the training split, the model's
        trained = getattr(trainer.datamodule, "training_lean_deg", None)
        for rid in recordings:
            path, entry = targets[rid]
            rows = frames["recording"] == rid
            frame, camera = ObjectFrame(np.eye(3), np.zeros(3), False, float("nan")), layout.LEFT_FRAME
            lean = None
            if entry is not None and entry.processed.is_file():
                with DerivedRecording.open(entry.processed) as derived:
                    frame, camera = derived.object_frame, derived.meta.camera_frame_id
                    lean = recording_lean(derived.meta, frame, entry.mcap) if entry.mcap.is_file() else None
            lean_meta = lean_metadata(lean, trained)[1]
            path.parent.mkdir(parents=True, exist_ok=True)
            write_force_estimate(path, frames["frame_time_ns"][rows], frames["pred"][rows], frame,
                                 {"stage": "train.py predict", "model": model, "recording": rid,
                                  "source": str(entry.processed if entry else ""), **lean_meta},
                                 overwrite=self.overwrite,
                                 camera_frame_id=camera, band_n=frames["band"][rows],
                                 beyond_n=pl_module.beyond_range(frames["pred"][rows]),
                                 unlike=unlikeness(frames["distance"][rows], pl_module.band_calibration))
            self.written.append(path)
            rank_zero_info(f"wrote {path} ({int(rows.sum())} frames)")
