"""`vfdata quickstart [DIR]`: the whole pipeline on a small simulated dataset in one command.

Simulates the `mini` preset (three short recordings: train, validation, test at another orientation),
converts and processes them, trains VisionForce's model (the default for users) and the paper's
proposed model for a few epochs, tests them, and prints Table I with the paths of the tables and
plots. Budget: 15 minutes on 2 CPU cores. Everything already made in DIR is reused, so a second run only re-prints."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("quickstart", help="simulate, process, train and test on a small dataset (about 15 min)",
                       description=__doc__.split("\n\n", 1)[1])
    p.add_argument("dir", nargs="?", type=Path, default=Path("data/quickstart"),
                   help="working folder (default data/quickstart)")
    p.add_argument("--epochs", type=int, default=8, help="training epochs (default 8)")
    p.add_argument("--variants", nargs="+", default=["visionforce", "proposed"],
                   help="variants to train (default: visionforce proposed)")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="parallel processes")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # here, not at the top: the runner and report pull in torch; `vfdata --help` starts without it
    from vfdata.sim import synthesize
    from vfmodels.experiment.report import summary_text
    from vfmodels.experiment.runner import ExperimentOptions, run_experiment

    started = time.perf_counter()
    progress = sys.stderr.isatty()
    print(f"[1/3] simulating the mini preset into {args.dir}", flush=True)
    manifest = synthesize("mini", args.dir, seed=0, workers=args.workers, progress=progress)
    synth_s = time.perf_counter() - started
    print(f"[2/3] converting, processing, training ({args.epochs} epochs) and testing: "
          f"{', '.join(args.variants)}", flush=True)
    options = ExperimentOptions(seeds=1, epochs=args.epochs, variants=args.variants, workers=args.workers,
                                progress=progress)
    result = run_experiment(manifest, args.dir / "results", options)
    print("[3/3] results\n")
    print(summary_text(result.reports))
    total = time.perf_counter() - started
    steps = {"synthesis": synth_s, **result.seconds}
    print("\nwall time: " + ", ".join(f"{k} {v:.0f} s" for k, v in steps.items()) + f"; total {total / 60:.1f} min")
    return 0
