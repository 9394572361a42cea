"""What several validation tissues do to the yardstick and to the band (issues 32 and 35).

A test recording's error on a fresh tissue is mostly that tissue's gain (docs/results.md, "What the errors
are"), and one validation tissue is a poor sample of that spread: the band is calibrated on it, and the
target "no test view's RMSE above 2x validation's" compares two single tissues. This study reads finished
`vfdata experiment` runs of datasets made with several validation tissues (`bench/sweep.py
--val-recordings 3`, i.e. `vfdata synth --val-recordings 3`; `visionforce` trains a fixed number of
epochs, so the model is the very one a single validation tissue gives) and compares, on the same model:

- `first`: the band calibrated on the first validation tissue only (the presets' one), and the worst test
  view's RMSE over that tissue's;
- `pooled`: the band calibrated on all validation tissues' frames pooled (`band.calibrate`: what training
  does with such a dataset), and the worst view over the RMSE of all validation frames;
- `largest`: the weights of `pooled`, and per component the largest of the tissues' own conformal scales
  (`band.conformal_quantile` of each tissue's |error| / signal): a band that covers the stated share of
  *every* validation tissue.

Per rule: pooled coverage of the test frames, the worst view's, views below 80%, views whose mean
half-width is within 2.5x their RMSE, and Spearman(per-view half-width, per-view RMSE). Writes
OUT/val_tissues.json.

    python bench/study_val_tissues.py --out /tmp/vt SWEEP/colon_101/results/runs/visionforce/seed0 ...
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from vfmodels.evaluation.band import calibrate, conformal_quantile, half_width, signal, stretch
from vfmodels.evaluation.metrics import force_metrics

RULES = ("first", "pooled", "largest")


def load(run: Path) -> tuple[dict, dict]:
    """(validation, test) frames of a run with a force: pred, true, spread (M, 3) N, distance, recording."""
    frames = []
    for name in ("validation.npz", "predictions.npz"):
        data = dict(np.load(run / name))
        known = np.isfinite(data["true"]).all(axis=1)
        frames.append({k: v[known] for k, v in data.items()})
    return frames[0], frames[1]


def tissues(frames: dict) -> list[str]:
    return list(dict.fromkeys(frames["recording"].astype(str).tolist()))


def band(val: dict, test: dict, rule: str) -> tuple[np.ndarray, float]:
    """The test frames' half-widths (M, 3) N under `rule`, and the validation RMSE (N) the rule reads."""
    if rule == "first":
        keep = val["recording"].astype(str) == tissues(val)[0]
        val = {k: v[keep] for k, v in val.items()}
    c = calibrate(val["pred"], val["true"], val["spread"], distance=val["distance"])
    scale = np.array(c.scale)
    if rule == "largest":
        size, error = np.abs(val["pred"]), np.abs(val["pred"] - val["true"])
        s = signal(val["spread"], size, np.array(c.weight), np.array(c.force_weight))
        names = val["recording"].astype(str)
        scale = np.array([max(conformal_quantile(error[names == t, i] / s[names == t, i]) for t in tissues(val))
                          for i in range(3)])
    half = half_width(test["spread"], np.abs(test["pred"]), scale, np.array(c.weight), np.array(c.force_weight))
    return half * stretch(test["distance"], c.distance_ref)[:, None], force_metrics(val["pred"], val["true"])["rmse"]


def judge(runs: list[Path], rule: str) -> dict:
    views, pooled, over_val = [], [], []
    for run in runs:
        val, test = load(run)
        half, val_rmse = band(val, test, rule)
        inside = np.abs(test["pred"] - test["true"]) <= half
        pooled.append(float(inside.mean()))
        names = test["recording"].astype(str)
        rmses = []
        for t in tissues(test):
            at = names == t
            rmse = force_metrics(test["pred"][at], test["true"][at])["rmse"]
            rmses.append(rmse)
            views.append({"run": str(run), "recording": t, "coverage": float(inside[at].mean()),
                          "half_width": float(half[at].mean()), "rmse": rmse})
        over_val.append(max(rmses) / val_rmse)
    cover = np.array([v["coverage"] for v in views])
    ratio = np.array([v["half_width"] / v["rmse"] for v in views])
    return {"coverage": float(np.mean(pooled)), "worst_view": float(cover.min()),
            "views_below_80": int((cover < 0.8).sum()), "views": len(views),
            "within_2_5x": int((ratio <= 2.5).sum()), "width_over_rmse_median": float(np.median(ratio)),
            "spearman": float(spearmanr([v["half_width"] for v in views], [v["rmse"] for v in views]).statistic),
            "worst_view_over_val": [float(r) for r in over_val], "per_view": views}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+", help="run folders (RESULTS/runs/visionforce/seed0)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    results = {rule: judge(args.runs, rule) for rule in RULES}
    print("| rule | pooled | worst view | views < 80% | half-width <= 2.5x RMSE | median half-width / RMSE "
          "| Spearman | worst view / validation RMSE, per run |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | --- |")
    for rule, r in results.items():
        print(f"| {rule} | {r['coverage']:.1%} | {r['worst_view']:.1%} | {r['views_below_80']} of {r['views']} | "
              f"{r['within_2_5x']} of {r['views']} | {r['width_over_rmse_median']:.2f} | {r['spearman']:+.2f} | "
              + ", ".join(f"{x:.2f}" for x in r["worst_view_over_val"]) + " |")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "val_tissues.json").write_text(json.dumps(results, indent=2))
    print(f"wrote {args.out / 'val_tissues.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
