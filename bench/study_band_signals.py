"""Which free signal tells where the force model is wrong? A study for the band (`vfmodels.evaluation.band`).

For finished `vfdata experiment` runs (a run folder: its checkpoint, its results' manifests) it computes
per validation and test frame, with no training:
- `mirror`: the spread (N) of the forces over the symmetry views the model is tested with (the clip and
  its mirror: what the band uses);
- `turns4`: the spread over 4 turns about Z each with its mirror (8 views; the model was trained with
  random turns, so they should agree where it knows the input);
- `embed`: the Mahalanobis distance of the frame's embedding (`encode_frames`, the set encoder's output
  before the LSTM) from the training frames' embeddings;
- `points`: 1 / the number of tracked points still visible (tracks thinning out).
Then, per signal, the band calibrated on validation as `vfmodels.evaluation.band.calibrate` does and judged on the
test views: coverage and mean half-width per view, and Spearman's correlation between per-view
half-width and RMSE over all views given. Writes OUT/signals.json and prints a table.

    python bench/study_band_signals.py --out /tmp/signals RESULTS/runs/visionforce/seed0 [MORE ...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from scipy.stats import spearmanr

from vfdata.clips.datamodule import ForceDataModule, spec_from_checkpoint_hparams
from vfdata.clips.tokens import latest_clip_frames
from vfmodels.evaluation.band import band_metrics
from vfmodels.evaluation.metrics import force_metrics
from vfmodels.training.checkpoint import best_checkpoint, read_checkpoint
from vfmodels.training.regressor import ForceRegressor

SIGNALS = ("none", "mirror", "turns4", "embed", "points", "force", "mirror+force", "embed+force", "turns4+force")


@torch.no_grad()
def frames_of(regressor: ForceRegressor, loader, embed_stats=None) -> dict[str, np.ndarray]:
    """Per frame (each once, from the clip it ends latest in): forces, truth, view and the signals."""
    parts: list[dict[str, np.ndarray]] = []
    turns = regressor.symmetry_turns
    for batch in loader:
        b, t = batch["force"].shape[:2]
        estimate = regressor.estimate(batch)
        regressor.symmetry_turns = 4
        turned = regressor.estimate(batch)
        regressor.symmetry_turns = turns
        z = regressor.model.encode_frames(regressor.normalise_input(batch["tokens"]), batch.get("valid"))
        side = batch["side"].float()[:, None] if "side" in batch else torch.ones(b, 1)
        pred, true = estimate.force_n.clone(), batch["force"].float().clone()
        pred[..., 1] *= side
        true[..., 1] *= side
        part = {"pred": pred.reshape(-1, 3).numpy(), "true": true.reshape(-1, 3).numpy(),
                "mirror": estimate.spread_n.reshape(-1, 3).numpy(), "turns4": turned.spread_n.reshape(-1, 3).numpy(),
                "z": z.reshape(b * t, -1).numpy(),
                "points": 1.0 / np.maximum(batch["valid"].sum(-1).reshape(-1).numpy(), 1),
                "orientation": np.repeat(np.asarray(batch["orientation_deg"], dtype=np.float64), t),
                "recording": np.repeat(np.asarray(batch["recording"], dtype=object), t).astype(str),
                "time": batch["frame_time_ns"].reshape(-1).numpy(), "position": np.tile(np.arange(t), b)}
        parts.append(part)
    frames = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    keep = latest_clip_frames(frames["recording"], frames["time"], frames["position"])
    frames = {k: v[keep] for k, v in frames.items()}
    known = np.isfinite(frames["true"]).all(axis=1)
    return {k: v[known] for k, v in frames.items()}


@torch.no_grad()
def embedding_stats(regressor: ForceRegressor, loader) -> tuple[np.ndarray, np.ndarray]:
    zs = []
    for batch in loader:
        z = regressor.model.encode_frames(regressor.normalise_input(batch["tokens"]), batch.get("valid"))
        zs.append(z.reshape(-1, z.shape[-1]).numpy())
    z = np.concatenate(zs)
    cov = np.cov(z.T) + 1e-6 * np.eye(z.shape[1])
    return z.mean(0), np.linalg.inv(cov)


def mahalanobis(z: np.ndarray, stats) -> np.ndarray:
    mean, inv = stats
    d = z - mean
    return np.sqrt(np.einsum("ij,jk,ik->i", d, inv, d))


def signal_of(frames: dict, name: str) -> np.ndarray:
    """(M, 3, K): per-component signals as they are, scalar ones broadcast; "a+b": both."""
    if name == "none":
        return np.zeros((len(frames["pred"]), 3, 1))
    if name == "force":
        return np.abs(frames["pred"])[..., None]
    if "+" in name:
        return np.concatenate([signal_of(frames, part) for part in name.split("+")], axis=2)
    value = frames[name]
    return (value if value.ndim == 2 else np.repeat(value[:, None], 3, axis=1))[..., None]


def calibrate_k(error: np.ndarray, signals: np.ndarray, coverage: float = 0.9):
    """`vfmodels.evaluation.band.calibrate` for K signals: half = scale * sqrt(1 + sum_k (w_k s_k)^2), the weights
    chosen on alternate 16-frame blocks among 0 and multiples of 1/median, the scale set on the others."""
    import itertools

    from vfmodels.evaluation.band import SIMPLER_BY, WEIGHT_STEPS, conformal_quantile

    choose = (np.arange(len(error)) // 16) % 2 == 0
    weights, scales = np.zeros((3, signals.shape[2])), np.zeros(3)
    for c in range(3):
        options = []
        for k in range(signals.shape[2]):
            typical = float(np.median(signals[choose, c, k]))
            options.append([0.0] + ([w / typical for w in WEIGHT_STEPS] if typical > 1e-9 else []))
        combos = list(itertools.product(*options))
        widths = []
        for w in combos:
            sig = np.sqrt(1 + ((np.array(w) * signals[choose, c]) ** 2).sum(-1))
            widths.append(conformal_quantile(error[choose, c] / sig, coverage) * sig.mean())
        enough = [i for i, w in enumerate(widths) if w <= min(widths) * (1 + SIMPLER_BY)]
        weights[c] = combos[min(enough, key=lambda i: (sum(v > 0 for v in combos[i]), widths[i]))]
        sig = np.sqrt(1 + ((weights[c] * signals[~choose, c]) ** 2).sum(-1))
        scales[c] = conformal_quantile(error[~choose, c] / sig, coverage)
    return scales, weights


def band_k(signals: np.ndarray, scales: np.ndarray, weights: np.ndarray) -> np.ndarray:
    return scales * np.sqrt(1 + ((weights[None] * signals) ** 2).sum(-1))


def model_frames(run: Path, cache: Path) -> tuple[dict, dict]:
    """The run's validation and test frames with every signal (the model's pass; kept in OUT/frames*.npz)."""
    ckpt = best_checkpoint(run / "checkpoints")
    regressor = ForceRegressor.load(ckpt)
    regressor.band_calibration = None
    spec = spec_from_checkpoint_hparams(read_checkpoint(ckpt).get("datamodule_hyper_parameters") or {}, ckpt)
    results = run.parent.parent.parent
    manifest = results / "manifests" / "klt.manifest.yaml"
    data = ForceDataModule(str(manifest), spec, batch_size=8, cache_dir=str(cache), progress=False)
    data.setup("fit")
    data.setup("test")
    torch.manual_seed(0)
    stats = embedding_stats(regressor, data.train_dataloader())
    val, test = frames_of(regressor, data.val_dataloader()), frames_of(regressor, data.test_dataloader())
    for frames in (val, test):
        frames["embed"] = mahalanobis(frames.pop("z"), stats)
    return val, test


def study(run: Path, val: dict, test: dict) -> dict:
    out = {"run": str(run), "val_rmse": force_metrics(val["pred"], val["true"])["rmse"], "signals": {}, "views": {}}
    views = sorted(set(zip(test["recording"].tolist(), test["orientation"].tolist(), strict=True)))
    for rec, angle in views:
        rows = (test["recording"] == rec) & (test["orientation"] == angle)
        out["views"][f"{rec}@{angle:g}"] = {"rmse": force_metrics(test["pred"][rows], test["true"][rows])["rmse"],
                                           "frames": int(rows.sum())}
    for name in SIGNALS:
        scale, weight = calibrate_k(np.abs(val["pred"] - val["true"]), signal_of(val, name))
        band = band_k(signal_of(test, name), scale, weight)
        error = np.abs(test["pred"] - test["true"])
        rho = [float(spearmanr(band[:, c], error[:, c]).statistic) if np.ptp(band[:, c]) > 0 else 0.0
               for c in range(3)]
        per_view = {}
        for rec, angle in views:
            rows = (test["recording"] == rec) & (test["orientation"] == angle)
            per_view[f"{rec}@{angle:g}"] = band_metrics(test["pred"][rows], test["true"][rows], band[rows])
        out["signals"][name] = {"weight": weight.tolist(), "scale": scale.tolist(),
                                "pooled": band_metrics(test["pred"], test["true"], band), "views": per_view,
                                "frame_spearman": rho,
                                "val_mean": signal_of(val, name).mean(axis=(0, 1)).tolist()}
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(1)
    studies = []
    for i, run in enumerate(args.runs):
        saved = args.out / f"frames{i}.npz"
        if saved.is_file():
            with np.load(saved) as kept:
                val = {k[4:]: kept[k] for k in kept.files if k.startswith("val_")}
                test = {k[5:]: kept[k] for k in kept.files if k.startswith("test_")}
        else:
            val, test = model_frames(run, args.out / f"cache{i}")
            np.savez_compressed(saved, **{f"val_{k}": v for k, v in val.items()},
                                **{f"test_{k}": v for k, v in test.items()})
        studies.append(study(run, val, test))
        print(f"{run}: validation RMSE {studies[-1]['val_rmse']:.3f} N", flush=True)
    (args.out / "signals.json").write_text(json.dumps(studies, indent=2))
    print(f"{'signal':14} {'coverage':>9} {'half/RMSE':>10} {'min view cov':>13} {'rho(view)':>10} {'rho(frame)':>11}")
    for name in SIGNALS:
        widths, rmses, covers, ratios, frame_rho = [], [], [], [], []
        for s in studies:
            for view, m in s["signals"][name]["views"].items():
                widths.append(m["half_width"])
                rmses.append(s["views"][view]["rmse"])
                covers.append(m["coverage"])
                ratios.append(m["half_width"] / s["views"][view]["rmse"])
            frame_rho.append(np.mean(s["signals"][name]["frame_spearman"]))
        pooled = np.mean([s["signals"][name]["pooled"]["coverage"] for s in studies])
        rho = spearmanr(widths, rmses).statistic if len(widths) >= 3 else float("nan")
        print(f"{name:14} {pooled:9.1%} {np.mean(ratios):10.2f} {min(covers):13.1%} {rho:10.2f} "
              f"{np.mean(frame_rho):11.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
