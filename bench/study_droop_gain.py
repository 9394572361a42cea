"""Gravity as a free calibration load: does a tissue's droop tell its stiffness, and so its force gain?

A tissue clamped at one end hangs under its own weight. On the sweep of fresh seeds (docs/results.md,
"The droop"), the straight axis through the tissue (ours) leans down from the clamp's axis by 4-9 degrees,
and a softer tissue leans more. The error on an unseen tissue is mostly a gain its mechanics set, which
the shape alone cannot tell. This study asks whether the lean, measured from the estimated object frame
and gravity, carries that gain, on a sweep's processed recordings (`bench/sweep.py`):

- per test and validation recording, the model's gain (least squares of predicted on true force, the
  sweep's `visionforce` run) against the lean relative to the training tissues' (log ratio);
- the ridge rung (`vfmodels.networks.ridge`, the `visionforce` tokens) trained as the product trains it
  (`plain`) and with each recording's force label multiplied by its lean in degrees (`scaled`: the
  model learns force x lean and its estimate is divided by the test recording's lean; no parameter is
  fitted: at fixed geometry a cantilever's sag under its weight is inversely proportional to its modulus,
  and so is its force for a given deformation).

- the experiment's note (`vfdata.tissue_lean`, `lean.md`): per test view, whether its tissue hangs outside
  the training tissues' range by more than `MARGIN_DEG`, against the view's RMSE (the sweep's run), and the
  Spearman correlation between how far outside (no margin) and the RMSE.

The lean is measured as a user's recording allows: the angle of the estimated Z below the horizontal,
gravity from the ECM pose (the simulator's clamp is level, so it is the tissue's droop plus the frame's
error). A lab needs its clamp's axis fixed in the gravity frame for the same.

    python bench/study_droop_gain.py /data/sweep --seeds 101-108            # the note and the gain
    python bench/study_droop_gain.py /data/sweep --seeds 101-108 --ridge    # and the ridge with scaled labels
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from vfdata.clips.decode import decode_recording
from vfdata.manifest import ManifestEntry, load_manifest
from vfdata.tissue_lean import MARGIN_DEG, beyond_range, lean_report, read_lean
from vfmodels.experiment.prepare import derived_path
from vfmodels.experiment.ridge_run import config_spec
from vfmodels.networks.ridge import RidgeForceModel

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "visionforce.yaml"


def lean_deg(entry: ManifestEntry) -> float:
    """The recording's lean (deg), as the experiment reads it."""
    return read_lean(derived_path(entry, "klt"), entry.mcap)


def rmse(pred: np.ndarray, true: np.ndarray) -> float:
    """The mean over Fx, Fy, Fz of each component's RMSE (N), finite rows only (the experiment's RMSE)."""
    ok = np.isfinite(true).all(axis=1)
    return float(np.sqrt(((pred[ok] - true[ok]) ** 2).mean(axis=0)).mean())


def seed_study(folder: Path, ridge: bool) -> dict:
    experiment = load_manifest(folder / "results" / "manifests" / "klt.manifest.yaml")
    spec = config_spec(CONFIG)
    cache = folder / "results" / "cache"
    decoded = {e.id: decode_recording(e, spec, cache) for e in experiment.entries}
    lean = {e.id: lean_deg(e) for e in experiment.entries}
    split = {s: [e.id for e in experiment.split(s)] for s in ("train", "val", "test")}
    reference = float(np.mean([np.log(lean[i]) for i in split["train"]]))

    # the network's gain per recording, from the sweep's own run
    gains = []
    run = folder / "results" / "runs" / "visionforce" / "seed0"
    for name in ("predictions.npz", "validation.npz"):
        pred = np.load(run / name)
        for rec in np.unique(pred["recording"]):
            k = pred["recording"] == rec
            p, t = pred["pred"][k], pred["true"][k]
            ok = np.isfinite(t).all(axis=1)
            gains.append((str(rec), float(np.log((p[ok] * t[ok]).sum() / (t[ok] ** 2).sum())),
                          float(np.log(lean[str(rec)]) - reference)))

    out = {"lean_deg": lean, "gains": gains, "rmse": {}, "note": note_rows(folder)}
    for mode in ("plain", "scaled") if ridge else ():
        factor = {i: (lean[i] if mode == "scaled" else 1.0) for i in lean}
        labelled = {i: replace(decoded[i], force_n=decoded[i].force_n * np.float32(factor[i])) for i in lean}
        model = RidgeForceModel(mirror=spec.mirror_augment, rotate=spec.rotate_augment)
        model.fit([labelled[i] for i in split["train"]], [labelled[i] for i in split["val"]])
        per = {i: model.predict(decoded[i]) / factor[i] for i in split["test"]}
        pooled = rmse(np.concatenate(list(per.values())), np.concatenate([decoded[i].force_n for i in per]))
        out["rmse"][mode] = {"pooled": pooled, **{i: rmse(per[i], decoded[i].force_n) for i in per}}
    return out


def note_rows(folder: Path) -> list[dict]:
    """Per test view: its tissue's distance outside the training range (deg, no margin), whether the note
    names it (beyond `MARGIN_DEG`), and the view's RMSE over its validation's (the sweep's run)."""
    doubtful = {d["id"] for d in json.loads((folder / "results" / "doubtful.json").read_text())}
    entries = {e.id: e for e in load_manifest(folder / "data" / "colon.manifest.yaml").entries}
    leans = {i: (entries[i].split, read_lean(derived_path(entries[i], "klt"), entries[i].mcap)) for i in entries}
    report = lean_report(leans, doubtful)
    train = [lean for i, (split, lean) in leans.items() if split == "train" and i not in doubtful]
    metrics = json.loads((folder / "results" / "runs" / "visionforce" / "seed0" / "metrics.json").read_text())
    pred = np.load(folder / "results" / "runs" / "visionforce" / "seed0" / "predictions.npz")
    rows = []
    for row in report["recordings"]:
        if row["split"] != "test":
            continue
        k = pred["recording"] == row["id"]
        rows.append({"id": row["id"], "named": bool(row["beyond_deg"]), "lean_deg": row["lean_deg"],
                     "outside_deg": abs(beyond_range(row["lean_deg"], train, 0.0)),
                     "rmse": rmse(pred["pred"][k], pred["true"][k]),
                     "over_val": rmse(pred["pred"][k], pred["true"][k]) / metrics["val"]["rmse"]})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweep", type=Path, help="a bench/sweep.py output folder")
    parser.add_argument("--seeds", default="101-108", help="colon seeds, e.g. 101-108")
    parser.add_argument("--ridge", action="store_true", help="also train the ridge with and without scaled labels")
    args = parser.parse_args()
    lo, _, hi = args.seeds.partition("-")
    results, gains = {}, []
    for seed in range(int(lo), int(hi or lo) + 1):
        study = seed_study(args.sweep / f"colon_{seed}", args.ridge)
        results[seed] = study
        gains += study["gains"]
        print(f"colon {seed}: " + "; ".join(f"{n['id']} lean {n['lean_deg']:.1f} outside {n['outside_deg']:.1f} "
                                            f"{'NAMED ' if n['named'] else ''}RMSE {n['rmse']:.2f} N "
                                            f"({n['over_val']:.2f}x val)" for n in study["note"]), flush=True)
        if not args.ridge:
            continue
        r = study["rmse"]
        tests = [k for k in r["plain"] if k != "pooled"]
        print(f"colon {seed}: ridge test RMSE plain {r['plain']['pooled']:.3f} N, scaled by the lean "
              f"{r['scaled']['pooled']:.3f} N ({r['scaled']['pooled'] / r['plain']['pooled']:.2f}x); per recording "
              + ", ".join(f"{t} {r['plain'][t]:.2f}->{r['scaled'][t]:.2f}" for t in tests)
              + "; lean (deg) " + ", ".join(f"{k} {v:.1f}" for k, v in study["lean_deg"].items()), flush=True)
    log_gain = np.array([g[1] for g in gains])
    log_lean = np.array([g[2] for g in gains])
    notes = [n for s in results for n in results[s]["note"]]
    named = [n for n in notes if n["named"]]
    others = [n for n in notes if not n["named"]]
    print(f"the note (beyond the training range by more than {MARGIN_DEG} deg): {len(named)} of {len(notes)} test "
          f"views named; median RMSE {np.median([n['rmse'] for n in named]) if named else float('nan'):.2f} N "
          f"({np.median([n['over_val'] for n in named]) if named else float('nan'):.2f}x validation) against "
          f"{np.median([n['rmse'] for n in others]):.2f} N ({np.median([n['over_val'] for n in others]):.2f}x) for "
          f"the others; Spearman(distance outside, RMSE) "
          f"{spearmanr([n['outside_deg'] for n in notes], [n['rmse'] for n in notes])[0]:+.2f}")
    print(f"network's log gain against log lean (relative to training), {len(gains)} validation and test "
          f"recordings: Spearman {spearmanr(log_lean, log_gain)[0]:+.2f}, slope "
          f"{np.polyfit(log_lean, log_gain, 1)[0]:+.2f}")
    if not args.ridge:
        return
    ratios = [results[s]["rmse"]["scaled"]["pooled"] / results[s]["rmse"]["plain"]["pooled"] for s in results]
    print(f"ridge, scaled by the lean / plain: median RMSE ratio {np.median(ratios):.3f}, better on "
          f"{sum(r < 1 for r in ratios)} of {len(ratios)} seeds; median pooled RMSE "
          f"{np.median([results[s]['rmse']['plain']['pooled'] for s in results]):.3f} -> "
          f"{np.median([results[s]['rmse']['scaled']['pooled'] for s in results]):.3f} N")


if __name__ == "__main__":
    main()
