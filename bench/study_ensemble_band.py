"""Does an ensemble of the seeds `vfdata experiment` trains tell where the force model is wrong? (issue 35)

The band of today (`vfmodels.evaluation.band`) reads one model: the spread over the tube's symmetry views
and |F|, stretched by the embedding distance. On the sweep's fresh views it covered 87% pooled but as
little as 52% at a view, and its per-view width hardly followed the per-view RMSE (Spearman 0.24): it
misses whole recordings whose error is a bias of the view, on which one model's symmetry views agree.
Models trained from other seeds need not share that bias. This study reads finished experiments trained
with several seeds (`bench/sweep.py --seeds 3`: each seed's `validation.npz` and `predictions.npz`, no
training here) and compares, calibrated on validation alike (`band.calibrate`, split-conformal) and
judged on the test views:

- `seed0`: the band each seed-0 model states today (its `band` column), around seed 0's forces;
- `mirror`: the ensemble's mean force, with the members' mean symmetry-view spread as the signal;
- `members`: the ensemble's mean force, with the members' disagreement (population std over seeds, N);
- `both`: the ensemble's mean force, with sqrt(mirror^2 + members^2);
- `+stretch` on each ensemble signal: the band stretched by the members' mean embedding distance over
  their validation medians (as `band.stretch`).

Prints per signal the pooled coverage, the worst view's coverage, the views under 80%, the share of views
whose half-width is within 2.5x their RMSE, Spearman(per-view half-width, per-view RMSE), and the RMSE
and R^2 of seed 0 against the ensemble's mean. Writes OUT/ensemble_band.json.

    python bench/study_ensemble_band.py --out /tmp/eb /data/sweep3/colon_101 /data/sweep3/colon_102 ...
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from vfmodels.evaluation.band import band_metrics, calibrate, half_width, stretch
from vfmodels.evaluation.metrics import force_metrics

SIGNALS = ("seed0", "mirror", "members", "both", "mirror+stretch", "members+stretch", "both+stretch")


def members(dataset: Path, variant: str) -> tuple[list[dict], list[dict]]:
    """Each seed's validation and test frames, checked to be the same frames in the same order."""
    runs = sorted((dataset / "results" / "runs" / variant).glob("seed*"), key=lambda p: int(p.name[4:]))
    val = [dict(np.load(r / "validation.npz", allow_pickle=False)) for r in runs]
    test = [dict(np.load(r / "predictions.npz", allow_pickle=False)) for r in runs]
    for frames in (val, test):
        for other in frames[1:]:
            if not (np.array_equal(other["frame_time_ns"], frames[0]["frame_time_ns"])
                    and np.array_equal(other["recording"], frames[0]["recording"])):
                raise SystemExit(f"{dataset}: the seeds' frames differ")
    return val, test


def ensemble(frames: list[dict], references: list[float]) -> dict[str, np.ndarray]:
    """The members' mean force and the signals of the module docstring."""
    pred = np.stack([f["pred"] for f in frames])  # (seeds, M, 3)
    distance = np.stack([f["distance"] / ref for f, ref in zip(frames, references, strict=True)])
    mirror = np.mean([f["spread"] for f in frames], axis=0)
    spread = pred.std(axis=0)
    return {"pred": pred.mean(axis=0), "true": frames[0]["true"], "mirror": mirror, "members": spread,
            "both": np.hypot(mirror, spread), "distance": distance.mean(axis=0)}


def study(datasets: list[Path], variant: str) -> dict:
    per_signal: dict[str, list[dict]] = {s: [] for s in SIGNALS}
    accuracy = []
    for dataset in datasets:
        val, test = members(dataset, variant)
        # each member's own validation median distance: its `distance_ref`
        references = [float(np.nanmedian(v["distance"])) for v in val]
        v, t = ensemble(val, references), ensemble(test, references)
        views = test[0]["orientation_deg"]
        single, mean = force_metrics(test[0]["pred"], t["true"]), force_metrics(t["pred"], t["true"])
        accuracy.append({"dataset": dataset.name, "seeds": len(val), "seed0_rmse": single["rmse"],
                         "seed0_r2": single["r2"], "ensemble_rmse": mean["rmse"], "ensemble_r2": mean["r2"]})
        for name in SIGNALS:
            if name == "seed0":
                pred, band = test[0]["pred"], test[0]["band"]
            else:
                base = name.split("+")[0]
                cal = calibrate(v["pred"], v["true"], v[base], distance=v["distance"])
                pred = t["pred"]
                band = half_width(t[base], np.abs(pred), np.array(cal.scale), np.array(cal.weight),
                                  np.array(cal.force_weight))
                if name.endswith("+stretch"):
                    band = band * stretch(t["distance"], cal.distance_ref)[:, None]
            for view in np.unique(views):
                k = views == view
                m = band_metrics(pred[k], t["true"][k], band[k])
                per_signal[name].append({"dataset": dataset.name, "view": int(view), "coverage": m["coverage"],
                                         "half_width": m["half_width"],
                                         "rmse": force_metrics(pred[k], t["true"][k])["rmse"], "frames": int(k.sum())})
    summary = {}
    for name, rows in per_signal.items():
        cover = np.array([r["coverage"] for r in rows])
        frames = np.array([r["frames"] for r in rows])
        width, rmse = np.array([r["half_width"] for r in rows]), np.array([r["rmse"] for r in rows])
        summary[name] = {"pooled_coverage": float((cover * frames).sum() / frames.sum()),
                         "worst_view_coverage": float(cover.min()), "views_under_80": int((cover < 0.8).sum()),
                         "views": len(rows), "width_within_2.5x_rmse": int((width <= 2.5 * rmse).sum()),
                         "spearman_width_rmse": float(spearmanr(width, rmse).statistic),
                         "mean_half_width": float((width * frames).sum() / frames.sum())}
    return {"summary": summary, "accuracy": accuracy, "views": per_signal}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("datasets", type=Path, nargs="+", help="sweep dataset folders (OUT/colon_101, ...)")
    parser.add_argument("--variant", default="visionforce")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    result = study(args.datasets, args.variant)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ensemble_band.json").write_text(json.dumps(result, indent=1))
    print(f"{'signal':>16} {'pooled':>7} {'worst':>6} {'<80%':>5} {'w<=2.5r':>8} {'spearman':>9} {'width N':>8}")
    for name, s in result["summary"].items():
        print(f"{name:>16} {s['pooled_coverage']:7.1%} {s['worst_view_coverage']:6.1%} {s['views_under_80']:>2}/"
              f"{s['views']:<2} {s['width_within_2.5x_rmse']:>5}/{s['views']:<2} {s['spearman_width_rmse']:9.2f} "
              f"{s['mean_half_width']:8.3f}")
    for a in result["accuracy"]:
        print(f"{a['dataset']}: {a['seeds']} seeds; seed 0 RMSE {a['seed0_rmse']:.3f} N R2 {a['seed0_r2']:.3f}; "
              f"ensemble RMSE {a['ensemble_rmse']:.3f} N R2 {a['ensemble_r2']:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
