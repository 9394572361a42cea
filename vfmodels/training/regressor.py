"""`ForceRegressor`, the LightningModule around any force model: normalisation, MSE loss on
normalised forces, AdamW, and the paper's metrics at validation and test. It knows nothing about
files; batches follow the contract below, and normalisation statistics come from the datamodule.

Batch (a dict): the model's input under `model.input_key` ("tokens" (B, T, N, C), "images"
(B, T, 3, H, W) or "depth" (B, T, 1, H, W)), `valid` (B, T, N) bool (optional), `force` (B, T, 3) in
N, `orientation_deg` (B,), `recording` list[str], `frame_time_ns` (B, T) int64.

Models: an `nn.Module` with `forward(x, valid) -> (B, T, 3)` in normalised units, attributes
`input_key`, `channel_dim` (the input's feature axis, which the input statistics apply to) and
`config` (its constructor arguments as plain values, stored in checkpoints); registered in
`vfmodels.networks.registry.MODELS` so that a checkpoint can name it. That is enough for `train.py` (fit, test,
predict) and `vfdata experiment`.

Frame by frame (`vfdata predict`, `--stream`, `vfdata live`), a model also needs the causal interface,
which `SetTransformerLSTM` implements for reference:
- `encode_frames(x, valid) -> z (B, T, D)`: each frame's embedding from that frame alone;
- `decode_frames(z, state=None) -> (forces (B, T, 3) normalised, state)`: causal in time, from `state`
  (None: the zero state a training clip starts from) to the state after the last frame;
- `forward(x, valid) == decode_frames(encode_frames(x, valid))[0]`.
Nobody calls them directly: `ForceRegressor.encode_frames` / `decode_frames` add the normalisation and
the symmetry views, so that every caller gets the forces the test scores, and beside them the band of
each force (`Estimate`, `vfmodels.evaluation.band`), calibrated on the validation split. A model without them (the
image baselines: a 3D convolution looks both ways in time) trains and tests, and prediction refuses it
in one line.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import lightning.pytorch as L
import numpy as np
import torch
import torch.nn.functional as F
from lightning.pytorch.utilities import rank_zero_info
from torch import nn

from vfdata.clips.tokens import latest_clip_frames, turn_about_z
from vfdata.errors import InputError
from vfmodels.evaluation import band, familiarity
from vfmodels.evaluation.metrics import force_metrics, format_table, grouped_force_metrics
from vfmodels.networks.registry import build_model, class_path
from vfmodels.training.checkpoint import band_from_checkpoint, read_checkpoint, reference_from_checkpoint

STAT_NAMES = ("input_mean", "input_std", "force_mean", "force_std")
REFERENCE_CLIPS = 256  # training clips whose frames make the reference (evenly spread over the split)
COMPILED_PREFIX = "_compiled."


class Estimate(NamedTuple):
    """What the model says of each frame, every tensor (..., 3) in N in the object frame: the force (the
    mean over the symmetry views), the half-width of its band (`vfmodels.evaluation.band`: force +- band_n covers the
    calibration's stated share of frames; NaN without a calibration) and the views' spread (the band's
    signal: their population std, 0 with one view), and (...) the distance of the frame's embedding from the
    training frames' (`vfmodels.evaluation.familiarity`; NaN when the model has no reference), which stretches
    the band."""

    force_n: torch.Tensor
    band_n: torch.Tensor
    spread_n: torch.Tensor
    distance: torch.Tensor


class ForceRegressor(L.LightningModule):
    """Trains `model` to regress per-frame forces; see the module docstring for the batch contract.

    Normalisation statistics (`input_mean`/`input_std` over the input's feature axis, `force_mean`/
    `force_std` (3,) in N) are buffers: they are taken from `trainer.datamodule.normalisation` (a
    dict of those four tensors, from the training split) when fitting starts, are saved in every
    checkpoint and restored with it. Without statistics the inputs and forces pass unchanged.

    `compile_model=True` runs the model through `torch.compile` (state-dict keys are unchanged).

    The band (`vfmodels.evaluation.band`): `band_calibration`, set at the end of every validation epoch from that
    epoch's validation frames (split-conformal scaling of the symmetry views' spread), with the training
    forces' range from `trainer.datamodule.force_range`; saved in every checkpoint (`force_model.band`)
    and restored with it. None (no validation, too few frames): every band is NaN. A causal model's band
    is stretched where a frame is unlike the training frames: before each validation the embeddings of up
    to `REFERENCE_CLIPS` training clips (`trainer.datamodule.reference_dataloader`) give the reference
    (`embedding_reference`: mean and precision, saved in every checkpoint beside the band,
    `force_model.embedding_reference`, not as buffers: weight averaging would average them, and a
    reference that appears after fitting starts does not fit the averaged copy's empty buffers).

    `symmetry_turns=n` (n >= 1; 0 = off) averages every prediction outside training over the tube's
    symmetries: n turns about the object's Z axis (360/n degrees apart), each with its mirror across
    the XZ plane, 2n views in all; each view's tokens are turned, and its forces turned back. Only for
    token inputs made of 3-vectors in the object frame (`frame: object`); the mirror alone (n = 1) is
    exact for a tube hanging under gravity, the turns need a model trained with `rotate_augment`.

    Args:
        model: the network (`vfmodels.SetTransformerLSTM`, `RGBResNet3D` or `DepthViTLSTM`; a class_path
            and init_args in a config; `--model.model.help SetTransformerLSTM` lists its options).
        lr: AdamW learning rate.
        weight_decay: AdamW weight decay.
        compile_model: run the network through torch.compile (faster on GPUs, slow to start).
        symmetry_turns: outside training, average each prediction over this many turns about the
            object's Z axis, each with its XZ mirror (0: off; 1: the mirror only; token inputs in the
            object frame only).
    """

    def __init__(self, model: nn.Module, lr: float = 5e-4, weight_decay: float = 1e-3, compile_model: bool = False,
                 symmetry_turns: int = 0):
        super().__init__()
        if symmetry_turns < 0 or (symmetry_turns and getattr(model, "input_key", "tokens") != "tokens"):
            raise ValueError(f"symmetry_turns={symmetry_turns}: a number of turns >= 0, and only for token inputs")
        self.symmetry_turns = symmetry_turns
        self.save_hyperparameters(ignore=["model", "symmetry_turns"])
        self.model = model
        for name in STAT_NAMES:
            self.register_buffer(name, torch.empty(0))
        # Buffers start empty; a checkpoint's statistics replace them whatever their shape.
        self.register_load_state_dict_pre_hook(self._adopt_stat_shapes)
        self.register_load_state_dict_pre_hook(self._drop_compiled_copies)
        self._compiled = None
        self._outputs: dict[str, list] = {}
        self.test_results: dict[str, Any] | None = None
        self.band_calibration: band.BandCalibration | None = None
        self.embedding_reference: tuple[torch.Tensor, torch.Tensor] | None = None  # (mean (D,), precision (D, D))
        self._train_range: tuple[np.ndarray, np.ndarray] | None = None  # training forces' (low, high) N

    # ---- normalisation -------------------------------------------------------------------------

    def _drop_compiled_copies(self, module, state_dict, prefix, *args) -> None:
        # Checkpoints of compiled training from before `setup` kept the wrapper out of the module tree
        # hold every weight a second time under "_compiled._orig_mod.".
        for key in [k for k in state_dict if k.startswith(prefix + COMPILED_PREFIX)]:
            del state_dict[key]

    def _adopt_stat_shapes(self, module, state_dict, prefix, *args) -> None:
        for name in STAT_NAMES:
            if prefix + name in state_dict:
                setattr(self, name, torch.empty_like(state_dict[prefix + name], device=self.force_mean.device))

    def set_normalisation(
        self, input_mean: torch.Tensor, input_std: torch.Tensor, force_mean: torch.Tensor, force_std: torch.Tensor
    ) -> None:
        """Statistics from the training split: input ones over the model input's feature axis, force
        ones (3,) in N. Standard deviations must be positive."""
        values = dict(input_mean=input_mean, input_std=input_std, force_mean=force_mean, force_std=force_std)
        for name, value in values.items():
            value = torch.as_tensor(value, dtype=torch.float32).reshape(-1).to(self.force_mean.device)
            if name.endswith("std") and bool((value <= 0).any()):
                raise ValueError(f"{name} must be positive, got {value.tolist()}")
            setattr(self, name, value)

    def setup(self, stage: str) -> None:
        stats = getattr(getattr(self.trainer, "datamodule", None), "normalisation", None)
        # When fitting, the training split defines the statistics; otherwise a checkpoint restored
        # after setup brings its own, and the datamodule's only fill in for an untrained model.
        if stats is not None and (stage == "fit" or self.force_mean.numel() == 0):
            self.set_normalisation(**stats)
        force_range = getattr(getattr(self.trainer, "datamodule", None), "force_range", None)
        if stage == "fit" and force_range is not None:
            self._train_range = tuple(np.asarray(v, dtype=np.float64) for v in force_range)
        if self.hparams.compile_model and self._compiled is None:
            # Set past nn.Module's bookkeeping: as a submodule the wrapper would put a second copy of
            # every weight in the state dict ("_compiled._orig_mod.*") and break strict loading.
            object.__setattr__(self, "_compiled", torch.compile(self.model))

    def normalise_input(self, x: torch.Tensor) -> torch.Tensor:
        if self.input_mean.numel() == 0:
            return x.float()
        shape = [1] * x.ndim
        shape[self.model.channel_dim] = -1
        return (x.float() - self.input_mean.view(shape)) / self.input_std.view(shape)

    def normalise_force(self, force_n: torch.Tensor) -> torch.Tensor:
        return force_n if self.force_mean.numel() == 0 else (force_n - self.force_mean) / self.force_std

    def denormalise_force(self, force: torch.Tensor) -> torch.Tensor:
        return force if self.force_mean.numel() == 0 else force * self.force_std + self.force_mean

    # ---- forward -------------------------------------------------------------------------------

    def forward(self, batch: dict[str, Any]) -> torch.Tensor:
        """Normalised force predictions (B, T, 3); outside training averaged over the symmetry views."""
        if self.training or not self.symmetry_turns:
            model = self._compiled if self._compiled is not None else self.model
            return model(self.normalise_input(batch[self.model.input_key]), batch.get("valid"))
        return self.normalise_force(self.estimate(batch).force_n)

    def estimate(self, batch: dict[str, Any]) -> Estimate:
        """The forces (B, T, 3) in N of a batch of clips, averaged over the symmetry views, with their band.
        A causal model goes through `encode_frames` and `decode_frames`, as prediction and live do."""
        if self.causal:
            return self.decode_frames(self.encode_frames(batch[self.model.input_key], batch.get("valid")))[0]
        model = self._compiled if self._compiled is not None else self.model
        x, valid = self._views_of(batch[self.model.input_key], batch.get("valid"))
        return self._estimate_of_views(self.denormalise_force(model(self.normalise_input(x), valid)))

    def predict_forces(self, batch: dict[str, Any]) -> torch.Tensor:
        """Forces (B, T, 3) in N."""
        return self.denormalise_force(self(batch))

    # ---- the causal interface: `vfdata predict`, `--stream` and `vfdata live` (module docstring) ----

    @property
    def causal(self) -> bool:
        """Whether the model runs frame by frame (has `encode_frames` and `decode_frames`)."""
        return all(callable(getattr(self.model, name, None)) for name in ("encode_frames", "decode_frames"))

    def encode_frames(self, x: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        """Model inputs (B, T, ...) in their own units (tokens: mm, mm/s) -> per-frame embeddings
        (V * B, T, D) of the V symmetry views (V = 2 * symmetry_turns, 1 without), view by view."""
        x, valid = self._views_of(x, valid)
        return self.model.encode_frames(self.normalise_input(x), valid)

    def decode_frames(self, z: torch.Tensor, state: Any = None) -> tuple[Estimate, Any]:
        """Embeddings (V * B, T, D) of `encode_frames` -> (the `Estimate` (B, T, 3): forces in N, the mean
        of the views turned back, and their band; the temporal state after the last frame, to carry on
        from). `state` None: the zero state a clip starts from, so one call on a clip's embeddings gives
        what the test scores."""
        out, state = self.model.decode_frames(z, state)
        return self._estimate_of_views(self.denormalise_force(out), self.embedding_distance(z)), state

    def embedding_distance(self, z: torch.Tensor) -> torch.Tensor | None:
        """Embeddings (V * B, T, D) of `encode_frames` -> (B, T): the first (unturned) view's distance from the
        training frames' (`vfmodels.evaluation.familiarity`); None without a reference."""
        if self.embedding_reference is None:
            return None
        first = z.unflatten(0, (max(1, 2 * self.symmetry_turns), -1))[0]
        mean, precision = (v.to(first.device) for v in self.embedding_reference)
        return familiarity.distance(first, mean, precision)

    def set_embedding_reference(self, z: torch.Tensor) -> None:
        """The reference of `embedding_distance` from training frames' embeddings (M, D) (unchanged when
        there are too few of them)."""
        stats = familiarity.reference(z)
        if stats is not None:
            self.embedding_reference = tuple(v.detach().cpu() for v in stats)

    def _views_of(self, x: torch.Tensor, valid: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Inputs (B, ...) -> every view's (V * B, ...), in one batch: one network pass for all views."""
        if not self.symmetry_turns:
            return x, valid
        views = torch.stack(symmetry_views(self.symmetry_turns, device=x.device))  # (V, 3, 3)
        turned = torch.einsum("vij,...kj->v...ki", views, x.float().unflatten(-1, (-1, 3))).flatten(-2)
        both = None if valid is None else valid.expand(len(views), *valid.shape).flatten(0, 1)
        return turned.flatten(0, 1), both

    def _estimate_of_views(self, force_n: torch.Tensor, distance: torch.Tensor | None = None) -> Estimate:
        """Forces (V * B, ..., 3) in N of every view and the frames' embedding distance (B, ...) (None:
        unknown) -> the `Estimate` (B, ..., 3): each view turned back, their mean, their spread and its band."""
        if self.symmetry_turns:
            views = torch.stack(symmetry_views(self.symmetry_turns, device=force_n.device))
            turned = torch.einsum("v...i,vij->v...j", force_n.unflatten(0, (len(views), -1)), views)
            force, spread = turned.mean(0), turned.std(0, correction=0)
        else:
            force, spread = force_n, torch.zeros_like(force_n)
        if distance is None:
            distance = torch.full(force.shape[:-1], float("nan"), dtype=force.dtype, device=force.device)
        return Estimate(force, self.band_of(spread, force, distance), spread, distance)

    def band_of(self, spread_n: torch.Tensor, force_n: torch.Tensor, distance: torch.Tensor | None = None
                ) -> torch.Tensor:
        """The band's half-width (N) for the views' spread and the estimate, (..., 3) N each
        (`vfmodels.evaluation.band.half_width`), stretched by the frames' embedding `distance` (...)
        (`band.stretch`); NaN without a calibration."""
        calibration = self.band_calibration
        if calibration is None:
            return torch.full_like(spread_n, float("nan"))
        scale, weight, force_weight = (torch.tensor(v, dtype=spread_n.dtype, device=spread_n.device)
                                       for v in (calibration.scale, calibration.weight, calibration.force_weight))
        half = band.half_width(spread_n, force_n.abs(), scale, weight, force_weight)
        if distance is None:
            return half
        return half * band.stretch(distance, calibration.distance_ref)[..., None].to(half.dtype)

    def beyond_range(self, force_n: np.ndarray) -> np.ndarray:
        """How far (N, signed, 0 inside) each component of forces (..., 3) lies beyond the training forces'
        range (`vfmodels.evaluation.band.beyond_range`); zeros when the calibration does not know the range."""
        calibration = self.band_calibration
        force_n = np.asarray(force_n, dtype=np.float64)
        if calibration is None or calibration.train_min_n is None:
            return np.zeros_like(force_n)
        return band.beyond_range(force_n, np.asarray(calibration.train_min_n), np.asarray(calibration.train_max_n))

    # ---- loss and steps ------------------------------------------------------------------------

    def _loss(self, pred: torch.Tensor, force_n: torch.Tensor) -> torch.Tensor:
        # Frames without a force sample (NaN) take no part in the loss.
        target = self.normalise_force(force_n.float())
        known = torch.isfinite(target)
        return F.mse_loss(pred[known], target[known])

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor:
        loss = self._loss(self(batch), batch["force"])
        self.log("train/loss", loss, on_step=True, on_epoch=True, prog_bar=True, batch_size=len(batch["force"]))
        return loss

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        self._evaluate(batch, "val")

    def test_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        self._evaluate(batch, "test")

    def predict_step(self, batch: dict[str, Any], batch_idx: int, dataloader_idx: int = 0) -> dict[str, Any]:
        """{"force_n": (B, T, 3) N, "band_n" and "spread_n" (B, T, 3) N, "distance" (B, T) (`Estimate`),
        "recording": [...], "frame_time_ns": (B, T), "orientation_deg": (B,), and "true_n" (B, T, 3) N when
        the batch has the measured force} (CPU tensors). A clip of a mirrored recording (batch "side" -1)
        has its Fy turned back to the sensor's."""
        b = len(batch[self.model.input_key])
        estimate = self.estimate(batch)
        out = {
            "force_n": self.unmirror(estimate.force_n, batch),
            "band_n": estimate.band_n.detach().float().cpu(),
            "spread_n": estimate.spread_n.detach().float().cpu(),
            "distance": estimate.distance.detach().float().cpu(),
            "recording": list(batch.get("recording", [""] * b)),
            "frame_time_ns": batch["frame_time_ns"].cpu() if "frame_time_ns" in batch else None,
            "orientation_deg": torch.as_tensor(batch.get("orientation_deg", torch.zeros(b))).float().cpu(),
        }
        if "force" in batch:
            out["true_n"] = self.unmirror(batch["force"], batch)
        return out

    @staticmethod
    def unmirror(force_n: torch.Tensor, batch: dict[str, Any]) -> torch.Tensor:
        """Forces (B, T, 3) as a new float CPU tensor, with Fy turned back to the sensor's for the clips
        of a mirrored recording (batch "side" -1, `ForceClipDataset(canonical_side=True)`)."""
        out = force_n.detach().float().cpu().clone()
        if "side" in batch:
            out[..., 1] *= batch["side"].float().cpu()[:, None]
        return out

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.AdamW(self.parameters(), lr=self.hparams.lr, weight_decay=self.hparams.weight_decay)

    # ---- metrics -------------------------------------------------------------------------------

    def _evaluate(self, batch: dict[str, Any], split: str) -> None:
        estimate = self.estimate(batch)
        pred = self.normalise_force(estimate.force_n)
        force_n = batch["force"]
        b, t = force_n.shape[:2]
        self.log(f"{split}/loss", self._loss(pred, force_n), on_epoch=True, prog_bar=True, batch_size=b,
                 sync_dist=True)
        out = self._outputs.setdefault(split, [])
        orientation = batch.get("orientation_deg", torch.zeros(b))
        # The metrics in the sensor's frame, as the experiment's tables.
        pred_n, true_n = self.unmirror(estimate.force_n, batch), self.unmirror(force_n, batch)
        out.append(dict(
            pred_n=pred_n.numpy().reshape(-1, 3),
            true_n=true_n.numpy().reshape(-1, 3),
            band_n=estimate.band_n.detach().float().cpu().numpy().reshape(-1, 3),
            spread_n=estimate.spread_n.detach().float().cpu().numpy().reshape(-1, 3),
            distance=estimate.distance.detach().float().cpu().numpy().reshape(-1),
            orientation_deg=np.repeat(torch.as_tensor(orientation).cpu().numpy(), t),
            recording=np.repeat(np.asarray(batch.get("recording", [""] * b), dtype=object), t),
            frame_time_ns=(batch["frame_time_ns"].cpu().numpy().reshape(-1) if "frame_time_ns" in batch
                           else np.full(b * t, -1, dtype=np.int64)),
            position=np.tile(np.arange(t), b),
        ))

    def _collect(self, split: str) -> dict[str, np.ndarray] | None:
        parts = self._outputs.pop(split, [])
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            gathered: list[list] = [None] * torch.distributed.get_world_size()  # type: ignore[list-item]
            torch.distributed.all_gather_object(gathered, parts)
            parts = [p for rank_parts in gathered for p in rank_parts]
        if not parts:
            return None
        frames = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        if (frames["frame_time_ns"] >= 0).all():  # each frame once, from the clip it ends latest in
            keep = latest_clip_frames(frames["recording"], frames["frame_time_ns"], frames["position"])
            frames = {k: v[keep] for k, v in frames.items()}
        known = np.isfinite(frames["true_n"]).all(axis=1)
        return {k: v[known] for k, v in frames.items()}

    def on_validation_epoch_start(self) -> None:
        # The reference of the weights about to be validated (callbacks such as EMAWeightAveraging have
        # swapped theirs in already), so that validation's distances and the band's `distance_ref` match.
        clips = getattr(getattr(self.trainer, "datamodule", None), "reference_dataloader", None)
        if self.causal and clips is not None and not self.trainer.sanity_checking:
            self.take_embedding_reference(clips(REFERENCE_CLIPS))

    @torch.no_grad()
    def take_embedding_reference(self, batches) -> None:
        """Sets the reference of `embedding_distance` from the training clips of `batches` (their first
        view's embeddings), with the random draws of their augmentation seeded and the caller's stream kept."""
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            z = [self.model.encode_frames(self.normalise_input(batch[self.model.input_key].to(self.device)),
                                          None if batch.get("valid") is None else batch["valid"].to(self.device))
                 for batch in batches]
        self.set_embedding_reference(torch.cat([e.reshape(-1, e.shape[-1]) for e in z]))

    def on_validation_epoch_end(self) -> None:
        frames = self._collect("val")
        if frames is None or self.trainer.sanity_checking or len(frames["true_n"]) < 2:
            return
        metrics = force_metrics(frames["pred_n"], frames["true_n"])
        self.log_dict({f"val/{k}": v for k, v in metrics.items()}, sync_dist=False)
        # The band of these weights, from their validation frames: the checkpoint saved after this
        # validation holds both (with EMAWeightAveraging, validation ran on the averaged weights, which
        # the checkpoint saves).
        self.calibrate_band(frames["pred_n"], frames["true_n"], frames["spread_n"], frames["distance"])

    def calibrate_band(self, pred_n: np.ndarray, true_n: np.ndarray, spread_n: np.ndarray,
                       distance: np.ndarray | None = None) -> None:
        """Sets `band_calibration` from validation frames (M, 3) N (`vfmodels.evaluation.band.calibrate`) and their
        embedding distances (M,), with the training range when it is known (kept from the calibration it
        replaces otherwise)."""
        calibration = band.calibrate(pred_n, true_n, spread_n, distance=distance)
        train_range = self._train_range
        if train_range is None and self.band_calibration is not None and self.band_calibration.train_min_n:
            train_range = (self.band_calibration.train_min_n, self.band_calibration.train_max_n)
        if calibration is not None and train_range is not None:
            calibration = calibration.with_training_range(*train_range)
        self.band_calibration = calibration

    def on_test_epoch_end(self) -> None:
        frames = self._collect("test")
        if frames is None or len(frames["true_n"]) < 2:
            return
        result = grouped_force_metrics(frames["pred_n"], frames["true_n"], frames["orientation_deg"])
        logged = {f"test/{k}": v for k, v in result["pooled"].items()}
        if len(result["groups"]) > 1:
            logged.update({f"test/mean/{k}": v for k, v in result["mean"].items()})
            logged.update({f"test/std/{k}": v for k, v in result["std"].items()})
        result["band"] = band.grouped_band_metrics(frames["pred_n"], frames["true_n"], frames["band_n"],
                                                   frames["orientation_deg"])
        if self.band_calibration is not None:
            logged.update({f"test/band/{k}": v for k, v in result["band"]["pooled"].items()})
        self.log_dict(logged, sync_dist=False)
        self.test_results = result
        rank_zero_info(f"test: {len(frames['true_n'])} frames, orientations (deg) "
                       f"{sorted(result['groups'])}\n{format_table(result)}\n"
                       f"{band.format_band_table(result['band'], self.band_calibration)}")

    # ---- checkpoints ---------------------------------------------------------------------------

    def on_fit_start(self) -> None:
        initialisation = getattr(self.model, "initialisation", "random")
        if initialisation != "random":  # worth a line only when weights were loaded (it is in the hparams)
            rank_zero_info(f"{type(self.model).__name__}: initialisation {initialisation}")
        if self.logger is not None:
            self.logger.log_hyperparams({"model_class": type(self.model).__name__, "initialisation": initialisation})

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        # Enough to rebuild the model without the training config (see `load`); plain values only,
        # so the checkpoint loads with torch.load(weights_only=True).
        checkpoint["force_model"] = {
            "class_path": class_path(self.model),
            "init_args": dict(getattr(self.model, "config", {})),
            "initialisation": getattr(self.model, "initialisation", "random"),
            "symmetry_turns": self.symmetry_turns,
            "band": None if self.band_calibration is None else self.band_calibration.to_dict(),
            "embedding_reference": None if self.embedding_reference is None else
            dict(zip(("mean", "precision"), self.embedding_reference, strict=True)),
        }

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        # `train.py test/predict --ckpt_path` restore through Lightning, not `load`.
        self.band_calibration = band_from_checkpoint(checkpoint, Path("checkpoint"))
        self.embedding_reference = reference_from_checkpoint(checkpoint, Path("checkpoint"))

    @classmethod
    def load(cls, path: str | Path, checkpoint: dict[str, Any] | None = None) -> ForceRegressor:
        """A trained regressor from a checkpoint file alone (or its contents already read, `checkpoint`), in
        eval mode on the CPU. The file is read as data (`weights_only=True`) and may name only a model of
        `vfmodels.networks.registry`. Pretrained-weight files named in the model config are not needed: the
        checkpoint has the weights."""
        path = Path(path)
        checkpoint = read_checkpoint(path) if checkpoint is None else checkpoint
        spec = checkpoint.get("force_model")
        if not isinstance(spec, dict) or not isinstance(spec.get("init_args", {}), dict):
            raise InputError(path, "not a ForceRegressor checkpoint (no 'force_model' entry)")
        init_args = dict(spec.get("init_args", {}))
        if "weights_path" in init_args:
            init_args["weights_path"] = None
        model = build_model(path, spec.get("class_path", ""), init_args)
        hparams = {k: v for k, v in checkpoint.get("hyper_parameters", {}).items() if k in ("lr", "weight_decay")}
        turns = spec.get("symmetry_turns", 0)
        if not isinstance(turns, int) or isinstance(turns, bool) or turns < 0:
            raise InputError(path, f"symmetry_turns {turns!r} in the checkpoint is not a number of turns >= 0")
        regressor = cls(model, **hparams, symmetry_turns=turns)
        try:
            regressor.load_state_dict(checkpoint["state_dict"])
        except (KeyError, RuntimeError) as exc:
            raise InputError(path, f"the checkpoint's weights do not fit its model ({str(exc).splitlines()[0]})") \
                from None
        regressor.band_calibration = band_from_checkpoint(checkpoint, path)
        regressor.embedding_reference = reference_from_checkpoint(checkpoint, path)
        return regressor.eval()


def symmetry_views(turns: int, device: torch.device | str = "cpu") -> list[torch.Tensor]:
    """The 2 * `turns` (3, 3) orthogonal maps of the object frame that the tube is (nearly) symmetric
    under: turns about Z by 360/`turns` degrees, each without and with the mirror across XZ (y negated)."""
    return [torch.as_tensor(turn_about_z(2 * np.pi * k / turns, mirror), dtype=torch.float32, device=device)
            for k in range(turns) for mirror in (False, True)]
