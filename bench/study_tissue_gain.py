"""Which unseen tissue does the force model get wrong, and would knowing where it is grasped help? (issues 32, 35)

On fresh simulated tissues a test recording's error is mostly a gain: the estimate follows the truth at
0.4-1.6x its size (docs/results.md, "What the errors are"). This study reads finished `bench/sweep.py`
datasets (their `predictions.npz` and each recording's `ground_truth/params.json`; no training here) and
for every test recording:

- its gain per component (least-squares slope of estimate on truth) and its RMSE (N, mean of Fx/Fy/Fz);
- each drawn parameter of its tissue relative to the mean of the training tissues: length, radius, grasp
  place along the tube, modulus, wall, stiffening, Maxwell ratio and time constant;
- Spearman's correlation of each parameter with the gains and with the RMSE over the test views;
- an oracle: the forces multiplied by the beam law with the *true* grasp place, (mean training grasp /
  this grasp)^k for k = (3, 3, 2) (a cantilever's lateral and, roughly, its axial stiffness), and the
  band stretched by the same factor (at least 1): the view RMSE and the band's worst view and Spearman
  (half-width, RMSE) before and after. What a perfect estimator of the grasp could give at most.

Writes OUT/tissue_gain.json.

    python bench/study_tissue_gain.py --out /tmp/tg /data/sweep3/colon_101 /data/sweep3/colon_102 ...
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from vfdata.manifest import load_manifest

PARAMETERS = ("length_mm", "base_radius_mm", "grasp_fraction", "modulus_mpa", "wall_mm", "stiffening",
              "maxwell_ratio", "maxwell_tau_s")
BEAM_EXPONENTS = np.array([3.0, 3.0, 2.0])


def tissue(params: dict) -> dict[str, float]:
    """The drawn parameters of one recording's tissue, flat."""
    flat = {**params["tube"], **params["material"], "grasp_fraction": params["grasp_fraction"]}
    return {k: float(flat[k]) for k in PARAMETERS}


def views(dataset: Path) -> list[dict]:
    """Per test recording of one finished sweep dataset: gain, RMSE, band and relative tissue parameters."""
    manifest = next((dataset / "data").glob("*.manifest.yaml"))
    entries = load_manifest(manifest).entries
    params = {e.id: tissue(json.loads((e.raw / "ground_truth" / "params.json").read_text())) for e in entries}
    trained = {k: np.mean([params[e.id][k] for e in entries if e.split == "train"]) for k in PARAMETERS}
    frames = np.load(dataset / "results" / "runs" / "visionforce" / "seed0" / "predictions.npz")
    rows = []
    for rec in np.unique(frames["recording"]):
        at = frames["recording"] == rec
        pred, true, band = frames["pred"][at], frames["true"][at], frames["band"][at]
        lever = trained["grasp_fraction"] / params[str(rec)]["grasp_fraction"]
        corrected = pred * lever**BEAM_EXPONENTS
        stretched = band * max(1.0, lever) ** BEAM_EXPONENTS
        rows.append({
            "dataset": dataset.name, "recording": str(rec),
            "gain": [float((pred[:, c] * true[:, c]).sum() / (true[:, c] ** 2).sum()) for c in range(3)],
            "rmse": float(np.sqrt(((pred - true) ** 2).mean(axis=0)).mean()),
            "rmse_beam": float(np.sqrt(((corrected - true) ** 2).mean(axis=0)).mean()),
            "coverage": float((np.abs(pred - true) <= band).mean()),
            "coverage_beam": float((np.abs(pred - true) <= stretched).mean()),
            "half_width": float(band.mean()), "half_width_beam": float(stretched.mean()),
            "relative": {k: params[str(rec)][k] / trained[k] for k in PARAMETERS},
        })
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", type=Path, nargs="+", help="sweep dataset folders (OUT/colon_101 ...)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    rows = [row for d in args.datasets for row in views(d)]
    gains, rmse = np.array([r["gain"] for r in rows]), np.array([r["rmse"] for r in rows])
    print(f"{len(rows)} test views; Spearman of each parameter (relative to the training tissues') with the gain "
          "(Fx / Fy / Fz) and with the view's RMSE:")
    correlations = {}
    for k in PARAMETERS:
        v = [r["relative"][k] for r in rows]
        correlations[k] = {"gain": [float(spearmanr(v, gains[:, c]).statistic) for c in range(3)],
                           "rmse": float(spearmanr(v, rmse).statistic)}
        print(f"  {k:16s} gain " + " / ".join(f"{g:+.2f}" for g in correlations[k]["gain"])
              + f"   RMSE {correlations[k]['rmse']:+.2f}")
    summary = {}
    for name, suffix in (("as trained", ""), ("beam law, true grasp", "_beam")):
        r_view = np.array([r["rmse" + suffix] for r in rows])
        cover = np.array([r["coverage" + suffix] for r in rows])
        width = np.array([r["half_width" + suffix] for r in rows])
        summary[name] = {"rmse_mean": float(r_view.mean()), "rmse_worst": float(r_view.max()),
                         "coverage_worst_view": float(cover.min()),
                         "spearman_width_rmse": float(spearmanr(width, rmse).statistic)}
        s = summary[name]
        print(f"{name:22s} view RMSE mean {s['rmse_mean']:.3f} N, worst {s['rmse_worst']:.3f} N; band worst view "
              f"{s['coverage_worst_view']:.1%}, Spearman(half-width, RMSE) {s['spearman_width_rmse']:+.2f}")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "tissue_gain.json").write_text(json.dumps(
        {"views": rows, "correlations": correlations, "summary": summary}, indent=2))
    print(f"wrote {args.out / 'tissue_gain.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
