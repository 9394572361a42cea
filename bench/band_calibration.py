"""How sure, measured: the band of `vfmodels.evaluation.band` on finished `vfdata experiment` runs (docs/results.md,
"How sure").

For each run folder (RESULTS/runs/<variant>/seed<k>) it takes the validation frames the band is calibrated
on and the test frames it is judged on: from the run's validation.npz and predictions.npz when they carry
the views' spread (runs made since the band), else by running the run's checkpoint again over its
validation and test clips (`vfmodels.experiment.runner.test_predictions`, into OUT/rescored/; the run's
folder is only read; a checkpoint from before the band's stretch takes its embedding reference from the
run's training clips, as training now does). Then:
- at the stated 90%: coverage and mean half-width per component, pooled and per test view, against the
  RMSE there; Spearman's correlation between per-view mean half-width and RMSE over every view given;
- the calibration plot, OUT/band_calibration.png: for stated coverages 50-98% the band calibrated on
  validation at that coverage (`vfmodels.evaluation.band.calibrate`), and the share of test frames inside it, pooled
  and per view (grey), against the diagonal.
Writes OUT/band.json and OUT/band.md and prints the table. `--val-recordings K` calibrates on the first K
validation recordings only: on a dataset made with `vfdata synth --val-recordings 3`, the band of one
validation tissue against three, on the same model.

    python bench/band_calibration.py --out /tmp/band RESULTS/runs/visionforce/seed0 [MORE ...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy.stats import spearmanr  # noqa: E402

from vfmodels.evaluation.band import band_metrics, calibrate, half_width, stretch  # noqa: E402
from vfmodels.evaluation.metrics import force_metrics  # noqa: E402

STATED = (0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.95, 0.98)


def frames_of(run: Path, out: Path) -> tuple[dict, dict]:
    """(validation, test) frames of a run: pred, true, spread (M, 3) N, orientation_deg, recording."""
    val_path, test_path = run / "validation.npz", run / "predictions.npz"
    if val_path.is_file() and test_path.is_file():
        val, test = dict(np.load(val_path)), dict(np.load(test_path))
        if "distance" in val and "distance" in test:
            return val, test
    name = "_".join(run.parts[-5:-3] + run.parts[-2:])
    kept = out / "rescored" / name
    if not (kept / "validation.npz").is_file():
        rescore(run, kept)
    return dict(np.load(kept / "validation.npz")), dict(np.load(kept / "predictions.npz"))


def rescore(run: Path, kept: Path) -> None:
    """The run's checkpoint over its validation and test clips, as the experiment tests it."""
    import torch

    from vfdata.clips.datamodule import ForceDataModule, spec_from_checkpoint_hparams
    from vfmodels.experiment.runner import test_predictions
    from vfmodels.training.checkpoint import best_checkpoint, read_checkpoint
    from vfmodels.training.regressor import REFERENCE_CLIPS, ForceRegressor

    torch.set_num_threads(1)
    summary = json.loads((run / "metrics.json").read_text())
    ckpt = best_checkpoint(run / "checkpoints")
    regressor = ForceRegressor.load(ckpt)
    spec = spec_from_checkpoint_hparams(read_checkpoint(ckpt).get("datamodule_hyper_parameters") or {}, ckpt)
    manifest = run.parent.parent.parent / "manifests" / f"{summary.get('tracker', 'klt')}.manifest.yaml"
    data = ForceDataModule(str(manifest), spec, batch_size=8, cache_dir=str(kept.parent / "cache"), progress=False)
    data.setup("fit")
    data.setup("test")
    if regressor.causal and regressor.embedding_reference is None:  # a run from before the stretch
        regressor.take_embedding_reference(data.reference_dataloader(REFERENCE_CLIPS))
    validation, _ = test_predictions(regressor, data.val_dataloader())
    test, _ = test_predictions(regressor, data.test_dataloader())
    kept.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(kept / "validation.npz", **validation)
    np.savez_compressed(kept / "predictions.npz", **test)


def band_for(val: dict, test: dict, coverage: float, stretched: bool = True) -> np.ndarray:
    """The test frames' half-widths (M, 3) N of the band calibrated on `val` at `coverage`, stretched by
    their embedding distance as the model does (`stretched`)."""
    known = np.isfinite(val["true"]).all(axis=1)
    c = calibrate(val["pred"][known], val["true"][known], val["spread"][known], coverage,
                  distance=val["distance"][known] if stretched else None)
    half = half_width(test["spread"], np.abs(test["pred"]), np.array(c.scale), np.array(c.weight),
                      np.array(c.force_weight))
    return half * stretch(test["distance"], c.distance_ref)[:, None] if stretched else half


def first_recordings(frames: dict, k: int) -> dict:
    """The frames of the first k recordings, in the order they come (the manifest's)."""
    names = list(dict.fromkeys(frames["recording"].astype(str).tolist()))[:k]
    keep = np.isin(frames["recording"].astype(str), names)
    return {key: value[keep] for key, value in frames.items()}


def views_of(test: dict) -> list[tuple[str, float]]:
    return sorted(set(zip(test["recording"].astype(str).tolist(), test["orientation_deg"].tolist(), strict=True)))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--no-stretch", dest="stretched", action="store_false",
                        help="the band without its stretch by the embedding distance (as before 2026-12-05)")
    parser.add_argument("--val-recordings", type=int, metavar="K",
                        help="calibrate on the first K validation recordings only (the same model: what more "
                             "validation tissues do to the band alone)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows, curves = [], {"pooled": [], "views": []}
    for run in args.runs:
        val, test = frames_of(run, args.out)
        if args.val_recordings:
            val = first_recordings(val, args.val_recordings)
        known = np.isfinite(test["true"]).all(axis=1)
        test = {k: v[known] for k, v in test.items()}
        label = "/".join(run.parts[-5:-3])
        band = band_for(val, test, 0.9, args.stretched)
        val_rmse = force_metrics(val["pred"], val["true"])["rmse"]
        for rec, angle in [("pooled", None), *views_of(test)]:
            rows_of = np.ones(len(test["true"]), bool) if angle is None else \
                (test["recording"].astype(str) == rec) & (test["orientation_deg"] == angle)
            m = band_metrics(test["pred"][rows_of], test["true"][rows_of], band[rows_of])
            f = force_metrics(test["pred"][rows_of], test["true"][rows_of])
            rows.append({"run": label, "view": rec if angle is None else f"{rec}@{angle:g}",
                         "frames": int(rows_of.sum()), "val_rmse": val_rmse, **m,
                         **{k: f[k] for k in ("rmse", "rmse_fx", "rmse_fy", "rmse_fz")}})
        pooled_curve, view_curves = [], {}
        for p in STATED:
            b = band_for(val, test, p, args.stretched)
            pooled_curve.append(band_metrics(test["pred"], test["true"], b)["coverage"])
            for rec, angle in views_of(test):
                r = (test["recording"].astype(str) == rec) & (test["orientation_deg"] == angle)
                view_curves.setdefault(f"{label} {rec}@{angle:g}", []).append(
                    band_metrics(test["pred"][r], test["true"][r], b[r])["coverage"])
        curves["pooled"].append(pooled_curve)
        curves["views"] += list(view_curves.values())
        print(f"{label}: validation RMSE {val_rmse:.3f} N, test coverage "
              f"{rows[-len(views_of(test)) - 1]['coverage']:.1%}", flush=True)
    views = [r for r in rows if r["view"] != "pooled"]
    pooled = [r for r in rows if r["view"] == "pooled"]
    rho = spearmanr([r["half_width"] for r in views], [r["rmse"] for r in views]).statistic if len(views) >= 3 \
        else None
    all_test = {"coverage": float(np.mean([r["coverage"] for r in pooled])),
                "coverage_by_component": [float(np.mean([r[f"coverage_{c}"] for r in pooled]))
                                          for c in ("fx", "fy", "fz")],
                "worst_view_coverage": float(min(r["coverage"] for r in views)),
                "views_below_80": int(sum(r["coverage"] < 0.8 for r in views)), "views": len(views),
                "half_width_over_rmse_by_view": [r["half_width"] / r["rmse"] for r in views],
                "spearman_width_rmse": None if rho is None else float(rho)}
    (args.out / "band.json").write_text(json.dumps({"rows": rows, "summary": all_test, "stated": STATED,
                                                    "curves": curves}, indent=2))
    lines = ["| run | view | frames | coverage Fx / Fy / Fz | half-width Fx / Fy / Fz (N) | RMSE Fx / Fy / Fz (N) "
             "| half-width / RMSE |", "| --- | --- | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        lines.append(f"| {r['run']} | {r['view']} | {r['frames']} | "
                     + " / ".join(f"{r['coverage_' + c]:.0%}" for c in ("fx", "fy", "fz")) + " | "
                     + " / ".join(f"{r['half_width_' + c]:.2f}" for c in ("fx", "fy", "fz")) + " | "
                     + " / ".join(f"{r['rmse_' + c]:.2f}" for c in ("fx", "fy", "fz"))
                     + f" | {r['half_width'] / r['rmse']:.2f} |")
    ratio = np.array(all_test["half_width_over_rmse_by_view"])
    lines += ["", f"Pooled over runs: coverage {all_test['coverage']:.1%} (Fx / Fy / Fz "
              + " / ".join(f"{c:.1%}" for c in all_test["coverage_by_component"]) + f"); worst view "
              f"{all_test['worst_view_coverage']:.1%}, {all_test['views_below_80']} of {all_test['views']} views "
              f"below 80%; half-width / RMSE per view median {np.median(ratio):.2f} (max {ratio.max():.2f}); "
              f"Spearman(half-width, RMSE) over views {all_test['spearman_width_rmse']}"]
    (args.out / "band.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))

    fig, ax = plt.subplots(figsize=(5, 5))
    for curve in curves["views"]:
        ax.plot(STATED, curve, color="0.7", lw=0.8)
    ax.plot(STATED, np.mean(curves["pooled"], axis=0), color="black", lw=2, marker="o",
            label=f"test frames pooled ({len(args.runs)} runs)")
    ax.plot([0.45, 1], [0.45, 1], color="tab:red", ls="--", lw=1, label="stated = observed")
    ax.plot([], [], color="0.7", lw=0.8, label=f"each test view ({len(curves['views'])})")
    ax.set_xlabel("stated coverage (calibrated on validation)")
    ax.set_ylabel("observed coverage on test frames")
    ax.set_xlim(0.45, 1.0)
    ax.set_ylim(0.0, 1.0)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title("How sure: the band's calibration")
    fig.tight_layout()
    fig.savefig(args.out / "band_calibration.png", dpi=120)
    print(f"wrote {args.out / 'band_calibration.png'}, {args.out / 'band.md'}, {args.out / 'band.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
