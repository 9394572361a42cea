"""`ForceDataModule`: train/val/test clips of a dataset manifest for Lightning. It knows nothing of the
network: the model gets the batches and the normalisation statistics of the training split."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any, Literal

import lightning.pytorch as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Subset

from vfdata.clips.dataset import ForceClipDataset, collate_clips
from vfdata.clips.spec import ClipSpec
from vfdata.errors import InputError
from vfdata.manifest import Manifest, check_guard_gaps, load_manifest
from vfdata.recording.derived import DerivedRecording, read_confidence, read_tracker_name
from vfdata.split_forces import training_range
from vfdata.tissue_lean import lean_report, recording_lean

DEFAULT_SPEC = ClipSpec()


def random_parts(count: int, test_share: float, val_share: float = 0.1, seed: int = 0) -> dict[str, np.ndarray]:
    """A random split of `count` samples (frames or clips), as code that splits frames at random does:
    one seeded shuffle, `test_share` of them for test, `val_share` of the rest for validation, the
    remainder for training; each part's indices sorted."""
    order = np.random.default_rng(seed).permutation(count)
    n_test = int(round(test_share * count))
    n_val = int(round(val_share * (count - n_test)))
    return {"test": np.sort(order[:n_test]), "val": np.sort(order[n_test:n_test + n_val]),
            "train": np.sort(order[n_test + n_val:])}


class ForceDataModule(L.LightningDataModule):
    """Clips of a dataset manifest, split as the manifest says (train and val share an orientation;
    test recordings are at others).

    Args:
        manifest: dataset manifest, e.g. datasets/glove.manifest.yaml.
        spec: how recordings become model input (ClipSpec: input, frame, features, clip length ...).
        batch_size: clips per batch.
        num_workers: DataLoader worker processes (0: load in the training process).
        cache_dir: folder for decoded arrays, reused by later runs (None: no cache).
        predict_split: the split `trainer.predict` runs over.
        progress: progress bars while decoding.
        random_split: 0 (default) splits as the manifest says; a share such as 0.2 pools the clips of
            every entry and draws that share of them at random for test (and a tenth of the rest for
            validation), as code that splits frames at random does. Neighbouring clips then land on
            both sides, so it flatters: for comparison with such results only (docs/results.md).

    The training split's statistics are `normalisation` (for `ForceRegressor`), its forces' range per
    component as training sees them (augmentation included) `force_range` ((low, high) N: the band's
    "beyond training" mark, `vfmodels.evaluation.band`), and the spec with
    the measured frame rate is saved with every checkpoint (`datamodule_hyper_parameters["spec"]`),
    so prediction makes the same tokens.
    """

    def __init__(self, manifest: str, spec: ClipSpec = DEFAULT_SPEC, batch_size: int = 32, num_workers: int = 0,
                 cache_dir: str | None = None, predict_split: Literal["train", "val", "test"] = "test",
                 progress: bool = True, random_split: float = 0.0):
        super().__init__()
        if not isinstance(manifest, (str, Path)):
            raise TypeError(f"ForceDataModule takes the path of a manifest file, not {type(manifest).__name__}")
        if not isinstance(spec, ClipSpec):  # a dict from a saved config
            spec = ClipSpec.from_dict(dict(spec))
        self.manifest: Manifest = load_manifest(manifest)
        check_guard_gaps(self.manifest, spec.clip_frames)
        self.spec = spec
        self.batch_size, self.num_workers, self.cache_dir = batch_size, num_workers, cache_dir
        self.predict_split, self.progress = predict_split, progress
        if not 0.0 <= random_split < 1.0:
            raise InputError(self.manifest.path, f"random_split must be a share in [0, 1), not {random_split}")
        self.random_split = float(random_split)
        self.datasets: dict[str, ForceClipDataset] = {}
        self.normalisation: dict[str, torch.Tensor] | None = None
        self.force_range: tuple[np.ndarray, np.ndarray] | None = None
        self._save_spec()

    @classmethod
    def from_manifest(cls, manifest: str | Path, spec: ClipSpec | None = None, **kwargs) -> ForceDataModule:
        """The one-line way in, as `ForceClipDataset.from_manifest`: every split of a manifest file."""
        return cls(str(manifest), spec or DEFAULT_SPEC, **kwargs)

    def _save_spec(self) -> None:
        # Plain values only: checkpoints load with torch.load(weights_only=True).
        self.save_hyperparameters({
            "manifest": str(self.manifest.path), "spec": self.spec.to_dict(), "batch_size": self.batch_size,
            "num_workers": self.num_workers, "cache_dir": self.cache_dir, "predict_split": self.predict_split,
            "random_split": self.random_split})

    @property
    def entries(self):
        return self.manifest.entries

    def dataset(self, split: str) -> ForceClipDataset:
        if split not in self.datasets and self.random_split:
            self.datasets[split] = self._random_part(split)
        if split not in self.datasets:
            data = ForceClipDataset(self.manifest.split(split), self.spec, self.cache_dir, self.progress,
                                    augment=split == "train")
            if len(data) == 0:
                raise InputError(self.manifest.path, f"the '{split}' recordings are shorter than one clip "
                                                     f"({self.spec.clip_frames} frames)")
            self.datasets[split] = data
        return self.datasets[split]

    def _random_part(self, split: str) -> ForceClipDataset:
        """The clips of every entry, `split`'s part of one seeded shuffle (test: `random_split` of
        them, val: a tenth of the rest, train: the remainder)."""
        data = ForceClipDataset(list(self.manifest.entries), self.spec, self.cache_dir, self.progress,
                                augment=split == "train")
        part = random_parts(len(data.index), self.random_split)[split]
        if len(part) == 0:
            raise InputError(self.manifest.path, f"random_split {self.random_split} leaves no '{split}' clips")
        data.index = data.index[part]
        return data

    @functools.cached_property
    def training_tracker(self) -> str | None:
        """The tracker whose tracks the training recordings hold (their derived files' metadata), or
        None when the clips are not tracks of processed recordings. Read once: every checkpoint saves it."""
        if self.spec.input != "tracks" or self.spec.source != "processed":
            return None
        entries = list(self.manifest.entries) if self.random_split else self.manifest.split("train")
        return next((read_tracker_name(e.processed) for e in entries if e.processed.is_file()), None)

    @functools.cached_property
    def training_lean_deg(self) -> list[float] | None:
        """[low, high] (deg): how low the training tissues hang below level (`vfdata.tissue_lean.lean_report`:
        recordings judged doubtful left out; None with fewer than three leans: no gravity, not processed).
        Read once: every checkpoint saves it, and prediction records whether a tissue hangs outside it."""
        if self.spec.source != "processed":
            return None
        entries = list(self.manifest.entries) if self.random_split else self.manifest.split("train")
        leans = {}
        for e in entries:
            if e.processed.is_file() and e.mcap.is_file() and e.id not in leans:
                with DerivedRecording.open(e.processed) as derived:
                    meta, frame = derived.meta, derived.object_frame
                leans[e.id] = ("train", recording_lean(meta, frame, e.mcap))
        return lean_report(leans, set(self.doubtful_recordings))["training_deg"]

    def state_dict(self) -> dict[str, Any]:
        # Lightning stores this in every checkpoint: prediction tracks a recording the way the
        # training recordings were tracked (vfmodels.inference.trained_model) and records how
        # the tissue hangs against the training tissues (TrainedModel.lean_deg).
        # The recordings trained and validated on, by id, and those of them judged doubtful, so that a lab
        # given only the file can read what the model has seen (`vfdata model-info`).
        state = {"tracker": self.training_tracker, "tissue_lean_deg": self.training_lean_deg,
                 "recordings": self.recording_ids, "doubtful": self.doubtful_recordings or None}
        return {k: v for k, v in state.items() if v is not None}

    @functools.cached_property
    def doubtful_recordings(self) -> dict[str, list[str]]:
        """The training and validation recordings `vfdata process` judged doubtful, by id, with their reasons
        (`vfdata.confidence`): their object frame may be wrong, so their labels may be too. `vfdata
        experiment` leaves them out; `train.py fit` warns and every checkpoint names them."""
        if self.spec.source != "processed":
            return {}
        entries = list(self.manifest.entries) if self.random_split else [
            e for e in self.manifest.entries if e.split in ("train", "val")]
        verdicts = {e.id: read_confidence(e.processed) for e in entries if e.processed.is_file()}
        return {rid: list(v.reasons) for rid, v in verdicts.items() if v is not None and v.doubtful}

    @property
    def recording_ids(self) -> dict[str, list[str]]:
        """The ids of the recordings training and validation read ({"train": [...], "val": [...]}), or
        {"shuffled": [...]} with a random split (the clips of all of them shuffled into train, val, test)."""
        if self.random_split:
            return {"shuffled": list(dict.fromkeys(e.id for e in self.manifest.entries))}
        return self.manifest.ids(("train", "val"))

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        pass  # nothing to restore: the tracker is read by prediction, not by training

    def setup(self, stage: str | None = None) -> None:
        if stage in (None, "fit", "validate"):
            train = self.dataset("train")
            self.dataset("val")
            if self.normalisation is None:
                self.normalisation = train.normalisation()
            if self.force_range is None:
                self.force_range = training_range(np.concatenate([d.force_n for d in train.recordings]),
                                                  self.spec.mirror_augment or self.spec.canonical_side,
                                                  self.spec.rotate_augment)
            if self.spec.fps is None:  # measured once, then saved with the checkpoint
                self.spec = self.spec.with_fps(train.fps)
                self._save_spec()
        if stage in (None, "test"):
            self.dataset("test")
        if stage == "predict":
            self.dataset(self.predict_split)

    def _loader(self, split: str, shuffle: bool) -> DataLoader:
        return DataLoader(self.dataset(split), batch_size=self.batch_size, shuffle=shuffle,
                          num_workers=self.num_workers, persistent_workers=self.num_workers > 0,
                          collate_fn=collate_clips, drop_last=False)

    def train_dataloader(self) -> DataLoader:
        return self._loader("train", shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", shuffle=False)

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", shuffle=False)

    def predict_dataloader(self) -> DataLoader:
        return self._loader(self.predict_split, shuffle=False)

    def reference_dataloader(self, clips: int) -> DataLoader:
        """At most `clips` training clips, evenly spread over the split and made as training makes them
        (augmented), in one pass without workers: the frames a model's familiarity is measured against
        (`vfmodels.evaluation.familiarity`)."""
        train = self.dataset("train")
        chosen = np.unique(np.linspace(0, len(train) - 1, min(clips, len(train))).astype(np.int64))
        return DataLoader(Subset(train, chosen.tolist()), batch_size=self.batch_size, shuffle=False,
                          num_workers=0, collate_fn=collate_clips)


def spec_from_checkpoint_hparams(hparams: dict[str, Any], where: Path) -> ClipSpec:
    """The ClipSpec a checkpoint was trained with: `spec` (this module), or the flat keys of
    checkpoints written before ClipSpec existed."""
    saved = hparams.get("spec")
    try:
        return ClipSpec.from_dict(dict(saved) if saved is not None else dict(hparams))
    except Exception as exc:  # a damaged or foreign checkpoint: say so in one line
        raise InputError(where, f"the checkpoint's data options are not a valid ClipSpec ({exc})") from None
