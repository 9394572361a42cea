"""The thread policy measured: `vfdata process` and `train.py fit` at the default thread count (1, see
vfdata/threads.py) against every other count up to the cores, in one run.

    python bench/bench_threads.py [--frames 40] [--epochs 3] [--repeats 2] [--threads 1 2 ...]

Simulates `mini` (shortened to --frames) and converts it, then, for each thread count in turn
(interleaved over --repeats rounds, so that other work on the machine weighs on every setting alike):
- process: `process_recording` of the test recording (sgbm depth, colortrack mask, geometry tracker),
  wall seconds and this process's CPU seconds;
- fit: `train.py fit --config configs/proposed.yaml --threads N` on the three processed recordings for
  --epochs epochs, the median of `time/epoch_s` over its epochs.
Prints the medians per setting and the ratio of the default to the best (target: <= 1.10).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def prepare(workdir: Path, frames: int):
    from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder
    from vfdata.manifest import load_manifest
    from vfdata.processing import ProcessOptions, process_recording
    from vfdata.sim import synthesize

    workdir = workdir / f"frames{frames}"
    manifest = workdir / "mini.manifest.yaml"  # kept from an earlier run of the same length
    if not manifest.is_file():
        manifest = synthesize("mini", workdir, seed=0, workers=1, progress=False, frames=frames)
    entries = list(load_manifest(manifest))
    for e in entries:
        if not e.mcap.is_file():
            convert_raw_folder(e.raw, e.mcap, options=ConvertOptions(progress=False))
        if not e.processed.is_file():  # training data (the timed runs write elsewhere)
            process_recording(e.mcap, e.processed, ProcessOptions(progress=False))
    return manifest, entries


def time_process(mcap: Path, out: Path, threads: int) -> tuple[float, float]:
    from vfdata.processing import ProcessOptions, process_recording

    wall, cpu = time.perf_counter(), time.process_time()
    process_recording(mcap, out, ProcessOptions(progress=False, threads=threads), overwrite=True)
    return time.perf_counter() - wall, time.process_time() - cpu


def time_fit(manifest: Path, root: Path, threads: int, epochs: int) -> float:
    from vfmodels.training.train import main as train_main

    with contextlib.redirect_stdout(io.StringIO()):
        train_main(["fit", f"--config={ROOT / 'configs' / 'proposed.yaml'}", f"--data.manifest={manifest}",
                    "--data.cache_dir=null", "--data.progress=false", f"--trainer.default_root_dir={root}",
                    f"--trainer.max_epochs={epochs}", "--trainer.enable_progress_bar=false",
                    "--trainer.accelerator=cpu", "--trainer.enable_model_summary=false", f"--threads={threads}"])
    rows = list(csv.DictReader(next(root.glob("csv/version_*/metrics.csv")).open()))
    return float(np.median([float(r["time/epoch_s"]) for r in rows if r.get("time/epoch_s")]))


def report(name: str, results: dict[int, list[float]], default: int, unit: str) -> float:
    medians = {t: float(np.median(v)) for t, v in results.items()}
    best = min(medians, key=medians.get)
    for t, m in medians.items():
        tag = " (default)" if t == default else ""
        print(f"  {name:8s} threads={t}{tag}: {m:7.2f} {unit}  runs: {', '.join(f'{v:.2f}' for v in results[t])}")
    ratio = medians[default] / medians[best]
    print(f"  {name:8s} default / best (threads={best}): {ratio:.2f}  (target <= 1.10)")
    return ratio


def main() -> int:
    cores = len(os.sched_getaffinity(0))
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=40, help="frames per recording (default 40)")
    parser.add_argument("--epochs", type=int, default=3, help="training epochs per fit (default 3)")
    parser.add_argument("--repeats", type=int, default=2, help="rounds over the settings (default 2)")
    parser.add_argument("--threads", type=int, nargs="+", default=sorted({1, 2, cores}),
                        help=f"thread counts to compare (default 1, 2 and the cores: {cores})")
    parser.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "vf_bench_threads")
    args = parser.parse_args()
    sys.argv = sys.argv[:1]  # the fits pass their own arguments to Lightning's CLI

    import torch

    from vfdata.threads import DEFAULT_THREADS

    print(f"cores {cores}, torch's own default {torch.get_num_threads()} threads, OMP_NUM_THREADS="
          f"{os.environ.get('OMP_NUM_THREADS', 'unset')}; load average {os.getloadavg()[0]:.1f}")
    manifest, entries = prepare(args.workdir, args.frames)
    test = next(e for e in entries if e.split == "test")
    settings = sorted(set(args.threads) | {DEFAULT_THREADS})
    process: dict[int, list[float]] = {t: [] for t in settings}
    cpu: dict[int, list[float]] = {t: [] for t in settings}
    fit: dict[int, list[float]] = {t: [] for t in settings}
    with tempfile.TemporaryDirectory(dir=manifest.parent) as tmp:
        for round_ in range(args.repeats):
            for t in settings if round_ % 2 == 0 else reversed(settings):
                wall, cpu_s = time_process(test.mcap, Path(tmp) / f"p{t}.processed.mcap", t)
                process[t].append(args.frames / wall)
                cpu[t].append(cpu_s)
                fit[t].append(time_fit(manifest, Path(tmp) / f"fit{t}_{round_}", t, args.epochs))
    print(f"process ({args.frames} frames of {test.id}, sgbm + colortrack + geometry), frames/s: higher is better")
    # Ratio of rates inverted so that both ratios read as time(default) / time(best).
    rates = {t: [1.0 / v for v in vals] for t, vals in process.items()}
    p_ratio = report("process", rates, DEFAULT_THREADS, "s/frame")
    for t in settings:
        print(f"  process  threads={t}: {np.median(process[t]):.2f} frames/s, CPU {np.median(cpu[t]):.1f} s")
    print(f"fit (proposed.yaml, 3 recordings of {args.frames} frames, {args.epochs} epochs), seconds per epoch")
    f_ratio = report("fit", fit, DEFAULT_THREADS, "s/epoch")
    return 0 if max(p_ratio, f_ratio) <= 1.10 else 1


if __name__ == "__main__":
    sys.exit(main())
