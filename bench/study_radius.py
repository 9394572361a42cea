"""r0 in mm against r0 in tissue radii, on finished `vfdata experiment` runs (docs/results.md, "The radius a
model can trust").

For each RESULTS folder (an experiment's output, or a `bench/sweep.py` seed's `results/`) it retrains
`visionforce` twice from the experiment's token cache (RESULTS/cache, 12-channel `polar_z_disp_vel` arrays
written with r0 in mm) and its manifest (RESULTS/manifests/klt.manifest.yaml, the doubtful recordings
already left out): once as cached, once with each recording's r0 divided by the median r0 of its first
frame's valid tokens (what `ClipSpec.radius: tissue` computes from the first frame's visible points). The
derived MCAPs need not exist any more (a colon seed's are about 4 GB, and are often deleted to save disk):
the cache is all training reads. Prints per folder and training seed the pooled R², RMSE and each view's
RMSE for both, then the median ratio of the RMSEs. Runs go to OUT/<folder name>/<mm|tissue>/seed<k> and
are kept (a rerun resumes).

    python bench/study_radius.py --out /tmp/radius /data/sweep17/colon_131/results [MORE ...] [--seeds 0 1 2]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import vfdata.clips.dataset as clip_dataset
from vfdata.clips.decode import Decoded
from vfdata.clips.tokens import tissue_radius
from vfdata.errors import InputError
from vfdata.threads import set_threads
from vfmodels.evaluation.metrics import force_metrics
from vfmodels.experiment.runner import ExperimentOptions, run_one
from vfmodels.experiment.variants import ALL_VARIANTS

CHANNELS = 12  # polar_z_disp_vel: (cos th0, sin th0, r0), (0, 0, z0 - z_tip), displacement, velocity


def cached_tokens(cache: Path, recording: str) -> dict[str, np.ndarray]:
    """The cached arrays of one recording with r0 in mm (there may be a second cache of the same tokens
    for another variant's options: any one serves)."""
    for path in sorted(cache.glob(f"{recording}-*.npz")):
        with np.load(path) as z:
            if z["inputs"].shape[-1] == CHANNELS:
                arrays = {k: z[k] for k in z.files}
                first = arrays["valid"][0]
                if first.any() and np.median(arrays["inputs"][0][first][:, 2]) < 3.0:
                    raise InputError(path, "r0 is in tissue radii already: this cache was written with radius tissue")
                return arrays
    raise InputError(cache, f"no {CHANNELS}-channel token cache of {recording}")


def in_tissue_radii(tokens: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Tokens (F, N, 12) with r0 over the tissue's radius, as `track_tokens` divides it: `tissue_radius` of
    the first frame's valid points (their place (r0 cos th0, r0 sin th0) read back from the tokens), else
    the median r0 of every valid token."""
    place = tokens[0][:, [0, 1]] * tokens[0][:, [2]]
    radius = tissue_radius(np.column_stack([place, np.zeros(len(place))]), valid[0])
    out = tokens.copy()
    out[..., 2] /= radius or float(np.median(tokens[..., 2][valid]))
    return out


def train(results: Path, radius: str, seed: int, run_dir: Path) -> dict:
    """Train and test `visionforce` from RESULTS' cache with r0 as `radius` says -> the figures."""
    cache = results / "cache"

    def decode(entry, spec, cache_dir=None) -> Decoded:
        z = cached_tokens(cache, entry.id)
        tokens = z["inputs"] if radius == "mm" else in_tissue_radii(z["inputs"], z["valid"])
        return Decoded(z["times_ns"], z["force_n"], tokens.astype(np.float32), z["valid"], float(z["side"]))

    if not (run_dir / "metrics.json").is_file():
        clip_dataset.decode_recording = decode  # the dataset reads the cache, with r0 as asked
        run_one(ALL_VARIANTS["visionforce"], seed, results / "manifests" / "klt.manifest.yaml", run_dir,
                ExperimentOptions(train_args=[f"--data.spec.radius={radius}"]), run_dir / "no-cache")
    metrics = json.loads((run_dir / "metrics.json").read_text())
    pred = np.load(run_dir / "predictions.npz", allow_pickle=False)
    views = {int(v): force_metrics(pred["pred"][pred["orientation_deg"] == v],
                                   pred["true"][pred["orientation_deg"] == v])["rmse"]
             for v in np.unique(pred["orientation_deg"])}
    return {"r2": metrics["pooled"]["r2"], "rmse": metrics["pooled"]["rmse"], "views": views}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("results", type=Path, nargs="+", help="experiment output folders (with cache/ and manifests/)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    args = parser.parse_args()
    set_threads(1)
    ratios, report = [], []
    for results in args.results:
        name = results.resolve().parent.name if results.name == "results" else results.name
        for seed in args.seeds:
            row = {"folder": str(results), "seed": seed}
            for radius in ("mm", "tissue"):
                row[radius] = train(results, radius, seed, args.out / name / radius / f"seed{seed}")
            ratios.append(row["tissue"]["rmse"] / row["mm"]["rmse"])
            report.append(row)
            cells = "  ".join(f"{r}: R2 {row[r]['r2']:.2f} RMSE {row[r]['rmse']:.2f} N views "
                              + ", ".join(f"{v} {e:.2f}" for v, e in row[r]["views"].items()) for r in ("mm", "tissue"))
            print(f"{name} seed {seed}  {cells}", flush=True)
    print(f"RMSE in tissue radii / in mm: median {np.median(ratios):.3f} over {len(ratios)} runs")
    (args.out / "radius.json").write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
