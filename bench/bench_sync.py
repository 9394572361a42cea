"""Clock offsets planted in simulated recordings, recovered by `vfdata sync` (docs/sync.md).

Simulates `mini` recordings at 15 s each (seeds 1-4, three recordings a seed), plants ten offsets from
-100 to +100 ms by shifting the stamps of each raw folder's force.csv (one offset a recording), converts
and estimates. The truth is the planted offset plus the simulator's own sensor clock offset (2-9 ms,
`ground_truth/params.json`). Then converts the first one again with `--time-offset-ms` set to its
estimate and estimates what is left. Targets: within one frame (33 ms) on >= 9 of 10, median error
<= 10 ms.

    python bench/bench_sync.py [--data DIR] [--frames 450]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from vfdata.clock_offset import recording_offsets  # noqa: E402
from vfdata.conversion.options import ConvertOptions  # noqa: E402
from vfdata.conversion.raw_folder import convert_raw_folder  # noqa: E402
from vfdata.sim import synthesize  # noqa: E402

PLANTED_MS = (-100, -75, -50, -30, -10, 10, 30, 50, 75, 100)
SEEDS = (1, 2, 3, 4)


def planted_folder(raw: Path, out: Path, planted_ms: float) -> Path:
    """A copy of a raw folder (its images and tables linked) whose force.csv stamps are `planted_ms` later."""
    out.mkdir(parents=True, exist_ok=True)
    for entry in raw.iterdir():
        if entry.name not in ("force.csv", "ground_truth"):
            target = out / entry.name
            if not target.exists():
                os.symlink(entry.resolve(), target)
    lines = (raw / "force.csv").read_text().splitlines()
    shift = round(planted_ms * 1e6)
    rows = [lines[0]] + [f"{int(line.split(',', 1)[0]) + shift},{line.split(',', 1)[1]}" for line in lines[1:]]
    (out / "force.csv").write_text("\n".join(rows) + "\n")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, help="folder for the simulated recordings (kept; reused when there)")
    parser.add_argument("--frames", type=int, default=450, help="frames per recording (default 450: 15 s)")
    args = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import cv2

    cv2.setNumThreads(1)
    with tempfile.TemporaryDirectory(prefix="vf_sync_") as tmp:
        data = args.data or Path(tmp) / "sim"
        raws = []
        started = time.perf_counter()
        for seed in SEEDS:
            folder = data / f"seed{seed}"
            if not (folder / "mini.manifest.yaml").is_file():
                with threadpool_limits(1):  # the physics' small solves: far slower with OpenBLAS's threads
                    synthesize("mini", folder, seed=seed, frames=args.frames, progress=False)
            raws += sorted(p for p in folder.iterdir() if p.is_dir())
        print(f"{len(raws)} simulated recordings of {args.frames} frames ({time.perf_counter() - started:.0f} s)")
        rows = []
        options = ConvertOptions(progress=False)
        print(f"{'recording':16} {'planted ms':>10} {'truth ms':>9} {'estimate ms':>11} {'error ms':>9} "
              f"{'+- ms':>6} {'R2':>5} {'lead ms':>8} {'confident':>9} {'seconds':>7}")
        for raw, planted in zip(raws, PLANTED_MS, strict=False):
            truth_ms = planted + json.loads((raw / "ground_truth" / "params.json").read_text())["sensor"][
                "clock_offset_ns"] / 1e6
            src = planted_folder(raw, Path(tmp) / "planted" / raw.parent.name / raw.name, planted)
            mcap = Path(tmp) / f"{raw.parent.name}_{raw.name}.mcap"
            convert_raw_folder(src, mcap, overwrite=True, options=options)
            started = time.perf_counter()
            force = recording_offsets(mcap, progress=False).force
            seconds = time.perf_counter() - started
            error = force.offset_ns / 1e6 - truth_ms
            rows.append((raw, mcap, src, planted, truth_ms, force, error))
            name = f"{raw.parent.name}/{raw.name}"
            print(f"{name:16} {planted:>10.0f} {truth_ms:>9.1f} {force.offset_ns / 1e6:>11.1f} "
                  f"{error:>+9.1f} {force.uncertainty_ns / 1e6:>6.1f} {force.fit_r2:>5.2f} {force.lead_ns / 1e6:>8.1f} "
                  f"{str(force.confident):>9} {seconds:>7.1f}", flush=True)
        errors = np.abs([r[-1] for r in rows])
        print(f"\nwithin one frame (33 ms): {(errors <= 1000 / 30).sum()} of {len(errors)}; median error "
              f"{np.median(errors):.1f} ms, largest {errors.max():.1f} ms; confident: "
              f"{sum(r[5].confident for r in rows)} of {len(rows)}")
        # the estimate applied: what is left afterwards
        raw, mcap, src, planted, truth_ms, force, _ = rows[0]
        aligned = mcap.with_name("aligned.mcap")
        convert_raw_folder(src, aligned, options=ConvertOptions(progress=False, time_offset_ns=round(force.offset_ns)))
        left = recording_offsets(aligned, progress=False).force
        print(f"{raw.parent.name}/{raw.name} converted again with --time-offset-ms {force.offset_ns / 1e6:.1f}: "
              f"{left.offset_ns / 1e6:+.1f} ms left (truth {truth_ms - force.offset_ns / 1e6:+.1f} ms)")


if __name__ == "__main__":
    main()
