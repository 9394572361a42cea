"""Which axis doubts are right? Every processed recording's axis fits against the simulator's truth.

`vfdata process` marks an axis doubtful (`vfdata.recon.tissue_frame.chosen_axis`) when the roundest fit
still leaves the cloud far from a tube (residual over `AXIS_DOUBT_RESIDUAL`), when the two roundest fits
are about as round and far apart, or when a rival cloud's fit is as round and points more than `RIVAL_DEG`
away. A doubtful training recording is left out of training, so a false alarm costs a tissue, and the
tissues trained on are what the error on a new one depends on most (docs/results.md, "The tissues trained
on"). This reads the diagnostics each derived file keeps (`object_frame_check`: every fit's angle to the
chosen one and its residual, the rivals) and prints, per recording, the Z error against the simulator's
clamp axis and against the tissue's own axis (`bench/sweep.py`'s `droop_figures`), which rules fired, and
the verdict the file was written with (`stored`) and the one this code's rule gives on the same fits
(`code`, the residual judged by `tissue_frame.residual_doubtful`): since 2026-12-06 a residual up to
`AXIS_AGREE_WAIVER` times the threshold is waived when `AXIS_AGREE_FITS` fits or more, on clouds cleaned
differently, all point within `RIVAL_DEG` of the chosen one.

    python bench/study_axis_doubt.py /data/sweep/colon_1*/data/colon.manifest.yaml --tracker klt
    python bench/study_axis_doubt.py /data/first_frames/*/glove.manifest.yaml --tracker geometry
    python bench/study_axis_doubt.py /data/sweep/*/data/*.manifest.yaml --end   # the clamped end's doubts

`--end` prints, for every recording whose clamped end this code's rule doubts (`clamped_end.decide` on the
stored cues), each cue's vote / strength, the Z error, whether the end is right, and the reason (`end`, or
`taper` for a taper outvoted by two sure cues): docs/results.md, "Which cue was right".
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from sweep import droop_figures  # noqa: E402

from vfdata.manifest import load_manifest  # noqa: E402
from vfdata.recon.clamped_end import Cue, decide  # noqa: E402
from vfdata.recon.tissue_frame import (  # noqa: E402
    AXIS_DOUBT_DEG,
    AXIS_DOUBT_RESIDUAL,
    AXIS_TIE,
    residual_doubtful,
)
from vfdata.recording.derived import DerivedRecording  # noqa: E402
from vfmodels.experiment.prepare import derived_path  # noqa: E402

PROMISE_DEG = 10.0


def recording_row(entry, label: str, tracker: str) -> dict | None:
    path = derived_path(entry, tracker)
    if not path.is_file() or not (entry.raw / "ground_truth").is_dir():
        return None
    with DerivedRecording.open(path) as derived:
        check = derived.meta.json("object_frame_check") or {}
        z_axis = derived.object_frame.z_axis
        verdict = derived.meta.confidence
    fits = check.get("axis_fits", {})
    if not fits:
        return None
    best = fits[check["axis_from"]]
    spread = max(f["deg"] for f in fits.values())
    residual = best["residual"] > AXIS_DOUBT_RESIDUAL
    waived = residual and not residual_doubtful(best["residual"], [f["deg"] for f in fits.values()])
    rivals = bool(check.get("axis_rivals"))
    # the tie of the two roundest (the whole and the metal-free clouds are the candidates that matter here)
    tie = any(f["residual"] <= AXIS_TIE * best["residual"] and f["deg"] > AXIS_DOUBT_DEG
              for name, f in fits.items() if name in ("cloud", "clean") and name != check["axis_from"])
    other = [r for r in (verdict.reasons if verdict else []) if r != "axis"]
    now = bool(check.get("axis_doubtful")) or bool(other)
    proposed = (residual and not waived) or rivals or tie or bool(other)
    truth = droop_figures(entry.raw, z_axis)
    true_z = np.asarray(json.loads((entry.raw / "ground_truth" / "object_frame.json").read_text())["rotation"])[:, 2]
    z_err = float(np.degrees(np.arccos(np.clip(z_axis @ true_z, -1, 1))))
    stored = check.get("end", {}).get("cues", {})
    cues = [Cue(name, c.get("vote", 0.0), c.get("strength", 0.0)) for name, c in stored.items()]
    return {"id": f"{label}/{entry.id}", "split": entry.split, "z_err": z_err, "end_doubt": decide(cues).doubt,
            "cues": " ".join(f"{c.name} {c.vote:+.0f}/{c.strength:.1f}" for c in cues),
            "tissue_err": truth["tissue_err_deg"], "residual": best["residual"], "spread": spread,
            "rules": [n for n, on in (("residual", residual), ("rival", rivals), ("tie", tie)) if on] + other,
            "now": now, "proposed": proposed}


def summary(rows: list[dict], key: str, label: str) -> str:
    far = [r for r in rows if r["z_err"] > PROMISE_DEG]
    near = [r for r in rows if r["z_err"] <= PROMISE_DEG]
    return (f"{label}: {sum(r[key] for r in rows)} flagged of {len(rows)}; beyond 10 deg {len(far)}, of them "
            f"flagged {sum(r[key] for r in far)}; within 10 deg {len(near)}, of them flagged (false alarms) "
            f"{sum(r[key] for r in near)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("manifests", nargs="+", type=Path)
    parser.add_argument("--tracker", default="klt")
    parser.add_argument("--end", action="store_true", help="the clamped end's doubts instead of the axis's")
    args = parser.parse_args()
    rows = []
    for manifest in args.manifests:
        label = (manifest.parent.parent if manifest.parent.name == "data" else manifest.parent).name
        for entry in load_manifest(manifest).entries:
            row = recording_row(entry, label, args.tracker)
            if row is not None:
                rows.append(row)
                if args.end:
                    if row["end_doubt"]:
                        print(f"{row['id']:>28} {row['split']:>5}  {row['cues']:42}  Z {row['z_err']:5.1f} deg  end "
                              f"{'right' if row['z_err'] < 90 else 'REVERSED'}  reason {row['end_doubt']}")
                    continue
                if row["now"] or row["proposed"] or row["z_err"] > PROMISE_DEG:
                    print(f"{row['id']:>28} {row['split']:>5}  Z {row['z_err']:5.1f} deg "
                          f"(tissue {row['tissue_err']:5.1f})  residual {row['residual']:.3f}  "
                          f"fits within {row['spread']:5.1f} deg  rules {','.join(row['rules']) or '-'}  "
                          f"stored {'DOUBT' if row['now'] else 'ok'}  code {'DOUBT' if row['proposed'] else 'ok'}")
    if args.end:
        doubted = [r for r in rows if r["end_doubt"]]
        taper = [r for r in doubted if r["end_doubt"] == "taper"]
        print(f"{len(doubted)} of {len(rows)} recordings' ends doubted; reversed among them "
              f"{sum(r['z_err'] >= 90 for r in doubted)}; reason taper {len(taper)} (beyond 10 deg "
              f"{sum(r['z_err'] > PROMISE_DEG for r in taper)})")
        return
    print(summary(rows, "now", "as stored"))
    print(summary(rows, "proposed", "this code's rule"))


if __name__ == "__main__":
    main()
