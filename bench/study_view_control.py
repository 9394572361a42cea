"""Is it the view or the recording? The same test recordings (tissue, material, motion, camera draws) made
again at another orientation, and a trained model's error on both.

A seed of `bench/sweep.py` tests each recording at one random view, so a bad view and a bad recording look
alike. The simulator draws everything of a recording from its seed and index, not from its orientation, so
`--orientation 0` makes the very recordings again as the training recordings are turned, and the model
that was tested on them runs on both through `vfdata predict` (one path: the forces the experiment scores).

    python bench/study_view_control.py /work/data/sweep/colon_108 --out /tmp/view_control/colon_108

prints, per test recording, the RMSE (N, mean of Fx, Fy, Fz, as Table I) at the sweep's view and at the
given orientation, and writes OUT/view_control.json.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import re
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from vfdata.manifest import load_manifest
from vfdata.sim.render import warm_up
from vfdata.sim.synthesize import _make_one

RMSE = re.compile(r"RMSE against the recording's force sensor: ([0-9.]+) N")


def predict_rmse(recording: Path, ckpt: Path, out: Path) -> float:
    """`vfdata predict`'s RMSE against the recording's sensor (N)."""
    done = subprocess.run([sys.executable, "-m", "vfdata", "predict", str(recording), "--ckpt", str(ckpt), "--out",
                           str(out), "--no-video", "--overwrite", "--quiet"], capture_output=True, text=True)
    found = RMSE.search(done.stdout)
    if done.returncode or not found:
        raise SystemExit(f"{recording}: vfdata predict failed: {done.stderr.strip().splitlines()[-1:]}")
    return float(found.group(1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("seed_folder", type=Path, help="a seed of bench/sweep.py (data/ and results/ inside)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--orientation", type=float, default=0.0, help="degrees about the vertical (default 0: "
                        "the training recordings')")
    parser.add_argument("--variant", default="visionforce")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    manifest_path = next((args.seed_folder / "data").glob("*.manifest.yaml"))
    manifest = load_manifest(manifest_path)
    preset_name, seed = args.seed_folder.name.rsplit("_", 1)  # as bench/sweep.py names its folders
    tests = [e for e in manifest.entries if e.split == "test"]
    indices = [int(e.id.rsplit("_", 1)[1]) for e in tests]  # a preset's ids are <name>_<index>
    args.out.mkdir(parents=True, exist_ok=True)
    warm_up()
    jobs = [(preset_name, int(seed), i, str(args.out), None, "jpeg", (args.orientation,) * len(tests))
            for i in indices]
    with ProcessPoolExecutor(args.workers, mp_context=mp.get_context("spawn")) as pool:
        list(pool.map(_make_one, jobs))
    ckpt = args.seed_folder / "results" / "runs" / args.variant / "seed0"
    rows = []
    for entry in tests:
        turned = args.out / f"{entry.id}.mcap"
        if not turned.is_file():
            subprocess.run([sys.executable, "-m", "vfdata", "convert", "--quiet", str(args.out / entry.id),
                            str(turned)], check=True)
        at_view = predict_rmse(entry.mcap, ckpt, args.out / "at_sweep_view")
        at_turn = predict_rmse(turned, ckpt, args.out / "turned")
        rows.append({"id": entry.id, "sweep_view_deg": entry.orientation_deg, "rmse_at_sweep_view": at_view,
                     "orientation_deg": args.orientation, "rmse_at_orientation": at_turn})
        print(f"{entry.id}: {entry.orientation_deg:.0f} deg {at_view:.3f} N, "
              f"{args.orientation:.0f} deg {at_turn:.3f} N", flush=True)
    (args.out / "view_control.json").write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
