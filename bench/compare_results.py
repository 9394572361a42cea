"""Two `vfdata experiment` results folders of one variant, seed by seed: is a change in the test RMSE larger
than what the training seeds alone move it by?

A fixed-seed figure is the mean over a few training seeds, and one seed's test RMSE moves by ~10% with
the seed alone (colon seed 0: 0.91-1.10 N over three seeds). Any change to the processing reshuffles
every training run, so "no worse than 5%" needs the seeds' spread beside it. This prints each folder's
per-seed pooled test RMSE (N), R² and per-view RMSE, the ratio of the means with a bootstrap interval
that resamples each folder's seeds apart, and the seeds' own ratios (seed k against seed k) with theirs:
a seed fixes the initial weights and the batch order, so seed k of the two folders tend to err alike
(colon seed 0: seed 1 the worst of three on both sides) and the paired interval is the narrower.

    python bench/compare_results.py results/before results/after [--variant visionforce]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def seed_figures(out: Path, variant: str) -> list[dict]:
    """Per finished seed of `variant` in the results folder `out`: pooled RMSE (N), R², RMSE per view."""
    rows = []
    for path in sorted((out / "runs" / variant).glob("seed*/metrics.json"), key=lambda p: int(p.parent.name[4:])):
        m = json.loads(path.read_text())
        rows.append({"seed": int(path.parent.name[4:]), "rmse": m["pooled"]["rmse"], "r2": m["pooled"]["r2"],
                     "views": {k: g["rmse"] for k, g in m.get("groups", {}).items()},
                     "val": m.get("val", {}).get("rmse", float("nan"))})
    if not rows:
        raise SystemExit(f"{out}: no finished {variant} runs (runs/{variant}/seed*/metrics.json)")
    return rows


DRAWS = 10000  # bootstrap resamples


def resampled_means(values: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(DRAWS,) means of `values` resampled with replacement: the bootstrap of a mean over seeds."""
    return rng.choice(values, size=(DRAWS, len(values))).mean(axis=1)


def interval(draws: np.ndarray) -> tuple[float, float]:
    """The central 90% of bootstrap draws."""
    low, high = np.quantile(draws, [0.05, 0.95])
    return float(low), float(high)


def describe(name: str, rows: list[dict]) -> None:
    rmse = np.array([r["rmse"] for r in rows])
    views = sorted({v for r in rows for v in r["views"]}, key=float)
    per_view = "  ".join(f"{float(v):.0f} deg {np.mean([r['views'][v] for r in rows if v in r['views']]):.3f}"
                         for v in views)
    print(f"{name}: {len(rows)} seeds, RMSE {rmse.mean():.3f} N (median {np.median(rmse):.3f}, "
          f"seeds {rmse.min():.3f}-{rmse.max():.3f}, sd {rmse.std(ddof=1) if len(rmse) > 1 else 0:.3f}), "
          f"R² {np.mean([r['r2'] for r in rows]):.3f}, val {np.mean([r['val'] for r in rows]):.3f}; {per_view}")
    print("  per seed: " + "  ".join(f"{r['seed']}: {r['rmse']:.3f}" for r in rows))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    parser.add_argument("--variant", default="visionforce")
    args = parser.parse_args()
    before, after = seed_figures(args.before, args.variant), seed_figures(args.after, args.variant)
    describe(f"before {args.before}", before)
    describe(f"after  {args.after}", after)
    b, a = np.array([r["rmse"] for r in before]), np.array([r["rmse"] for r in after])
    rng = np.random.default_rng(0)
    b_draws = resampled_means(b, rng)
    low, high = interval(resampled_means(a, rng) / b_draws)
    print(f"after / before: {a.mean() / b.mean():.3f} (90% interval, seeds resampled apart {low:.3f}-{high:.3f})")
    shared = sorted({r["seed"] for r in before} & {r["seed"] for r in after})
    if len(shared) > 1:
        old, new = {r["seed"]: r["rmse"] for r in before}, {r["seed"]: r["rmse"] for r in after}
        ratios = np.array([new[k] / old[k] for k in shared])
        low, high = interval(resampled_means(ratios, np.random.default_rng(0)))
        each = "  ".join(f"{k}: {q:.3f}" for k, q in zip(shared, ratios, strict=True))
        print(f"seed by seed ({len(ratios)} shared): {each}; "
              f"mean {ratios.mean():.3f} (90% interval {low:.3f}-{high:.3f})")


if __name__ == "__main__":
    main()
