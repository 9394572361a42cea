"""The band widens where a frame is unlike the training frames (`vfmodels.evaluation.familiarity`,
`vfmodels.evaluation.band.stretch`): the reference is taken before each validation, the checkpoint keeps it,
and checkpoints from before it load without a stretch."""

from __future__ import annotations

import lightning.pytorch as L
import numpy as np
import pytest
import torch
from clip_fixtures import single_thread  # noqa: F401
from lightning.pytorch.callbacks import EMAWeightAveraging
from test_band import ValidatedClips
from torch.utils.data import DataLoader, Subset

from vfmodels import ForceRegressor, SetTransformerLSTM
from vfmodels.evaluation import familiarity
from vfmodels.evaluation.band import BandCalibration, calibrate, stretch, unfamiliar


def test_the_distance_is_mahalanobis_from_the_training_frames():
    rng = np.random.default_rng(0)
    z = torch.from_numpy(rng.normal(size=(20000, 3)) * np.array([1.0, 2.0, 0.5]) + np.array([5.0, 0.0, -1.0]))
    mean, precision = familiarity.reference(z)
    probes = torch.tensor([[5.0, 0.0, -1.0], [8.0, 0.0, -1.0], [5.0, 6.0, -1.0], [5.0, 0.0, 0.5]])
    assert familiarity.distance(probes, mean, precision).numpy() == pytest.approx([0, 3, 3, 3], abs=0.1)
    assert familiarity.reference(z[:5]) is None  # 5 frames of 3 dimensions: too few for a covariance


def test_the_stretch_is_one_up_to_the_validation_median_then_grows_with_the_distance():
    assert stretch(np.array([0.5, 1.0, 3.0, np.nan]), 1.5).tolist() == [1.0, 1.0, 2.0, 1.0]
    assert stretch(torch.tensor([3.0, float("nan")]), 1.5).tolist() == [2.0, 1.0]
    assert stretch(np.array([30.0]), None).tolist() == [1.0]  # no reference: no stretch
    rng = np.random.default_rng(1)
    true = rng.normal(size=(400, 3))
    cal = calibrate(true + rng.normal(size=(400, 3)), true, np.zeros((400, 3)), distance=np.full(400, 4.0))
    assert cal.distance_ref == pytest.approx(4.0)
    assert BandCalibration.from_dict(cal.to_dict()) == cal
    with pytest.raises(ValueError, match="distance_ref"):
        BandCalibration.from_dict({**cal.to_dict(), "distance_ref": -1})


class ReferencedClips(ValidatedClips):
    """Synthetic clips with the training frames a model's familiarity is measured against."""

    def reference_dataloader(self, clips: int) -> DataLoader:
        return DataLoader(Subset(self.clips, range(min(clips, len(self.clips)))), batch_size=self.batch_size)


def test_training_keeps_a_reference_and_the_band_widens_far_from_it(tmp_path):
    L.seed_everything(0)
    dm = ReferencedClips(clips=8, frames=8, points=16, batch_size=4)
    regressor = ForceRegressor(SetTransformerLSTM(in_features=6, dim=8, heads=2, inducing_points=4, lstm_hidden=16),
                               symmetry_turns=1)
    regressor.set_normalisation(**dm.normalisation)
    # with weight averaging, as configs/visionforce.yaml trains: the averaged copy is made before the reference
    trainer = L.Trainer(max_epochs=2, logger=False, enable_progress_bar=False, enable_model_summary=False,
                        default_root_dir=tmp_path, accelerator="cpu", callbacks=[EMAWeightAveraging(decay=0.9)])
    trainer.fit(regressor, dm)
    path = trainer.checkpoint_callback.best_model_path
    loaded = ForceRegressor.load(path)
    mean, precision = loaded.embedding_reference
    assert mean.shape == (8,) and precision.shape == (8, 8)
    assert loaded.band_calibration.distance_ref > 0

    batch = {k: torch.stack([c[k] for c in dm.clips]) for k in ("tokens", "valid", "force")}
    far = {**batch, "tokens": batch["tokens"] * 5}
    with torch.no_grad():
        near, away = loaded.estimate(batch), loaded.estimate(far)
    # on the validation frames the band still holds at least its stated 90%
    inside = (near.force_n - batch["force"]).abs() <= near.band_n
    assert (inside.float().mean(dim=(0, 1)) >= 0.9).all()
    assert torch.median(away.distance) > 3 * loaded.band_calibration.distance_ref
    # the band's stretch is the frame's distance over validation's median, wherever it is beyond it
    plain = loaded.band_of(away.spread_n, away.force_n)
    ratio = away.band_n / plain
    expected = (away.distance / loaded.band_calibration.distance_ref).clamp(min=1)[..., None].expand_as(ratio)
    assert torch.allclose(ratio, expected, rtol=1e-4)
    assert torch.median(ratio) > 3
    unlike = unfamiliar(away.distance.numpy(), loaded.band_calibration)
    assert loaded.band_calibration.distance_limit > loaded.band_calibration.distance_ref
    assert unlike.mean() > 0.75 and unfamiliar(near.distance.numpy(), loaded.band_calibration).mean() < 0.1

    # a checkpoint from before the reference: it loads, the distance is unknown and the band unstretched
    checkpoint = torch.load(path, weights_only=True)
    del checkpoint["force_model"]["embedding_reference"]
    old = tmp_path / "old.ckpt"
    torch.save(checkpoint, old)
    before = ForceRegressor.load(old)
    with torch.no_grad():
        estimate = before.estimate(far)
    assert torch.isnan(estimate.distance).all()
    assert torch.allclose(estimate.band_n, before.band_of(estimate.spread_n, estimate.force_n))


def test_the_reference_clips_are_training_clips_evenly_spread(tmp_path):
    from test_datasets import frame_times, write_manifest, write_recording

    from vfdata.clips.datamodule import ForceDataModule

    write_recording(tmp_path, "a", frame_times(80))
    write_recording(tmp_path, "b", frame_times(40))
    manifest = write_manifest(tmp_path, [{"id": "a", "split": "train"}, {"id": "b", "split": "val"}])
    dm = ForceDataModule(str(manifest), batch_size=2, progress=False)
    dm.setup("fit")
    train = dm.dataset("train")
    assert len(train) > 4
    few = dm.reference_dataloader(3)
    assert few.dataset.indices == [0, (len(train) - 1) // 2, len(train) - 1]
    starts = [int(b["frame_time_ns"][i, 0]) for b in few for i in range(len(b["frame_time_ns"]))]
    assert starts == sorted(starts) and len(starts) == 3
    assert len(dm.reference_dataloader(10_000).dataset) == len(train)


def test_frames_beyond_validations_99th_percentile_are_unlike_training(tmp_path):
    from vfmodels.evaluation.band import distance_scale, unfamiliar_metrics
    from vfmodels.experiment.runs import write_run

    rng = np.random.default_rng(2)
    val_distance = rng.uniform(1.0, 3.0, 1000)
    ref, limit = distance_scale(val_distance)
    assert ref == pytest.approx(2.0, abs=0.1) and limit == pytest.approx(2.98, abs=0.02)
    assert distance_scale(np.full(5, np.nan)) == (None, None)
    true = rng.normal(size=(200, 3))
    pred = true + 0.1
    distance = np.full(200, 2.0)
    distance[:20] = 10.0
    pred[:20] += 1.0  # the unfamiliar frames err more
    cal = calibrate(pred, true, np.zeros((200, 3)), distance=val_distance[:200])
    assert unfamiliar(distance, cal).sum() == 20 and not unfamiliar(distance, None).any()
    m = unfamiliar_metrics(pred, true, distance, limit)
    assert m["frames"] == 20 and m["share"] == pytest.approx(0.1)
    assert m["rmse"] == pytest.approx(1.1) and m["rmse_rest"] == pytest.approx(0.1)

    frames = {"recording": np.array(["r"] * 200), "orientation_deg": np.zeros(200), "frame_time_ns": np.arange(200),
              "pred": pred, "true": true, "distance": distance}
    summary = write_run(tmp_path, frames, {}, {**frames, "distance": val_distance[:200]})
    assert summary["unfamiliar"]["frames"] == 20 and summary["unfamiliar"]["rmse"] == pytest.approx(1.1)
