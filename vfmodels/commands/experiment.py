"""`vfdata experiment MANIFEST --out DIR`: the paper's grid (the models, ablations, baselines x seeds)
on one dataset, then Tables I-III, the timing table and the figures (docs/experiments.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from vfmodels.experiment.variants import (
    EXTRA_VARIANTS,
    LADDER_MODELS,
    PAPER_VARIANTS,
    SIMULATOR_VARIANTS,
    VISIONFORCE_VARIANTS,
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "experiment", help="train and test every model variant x seed on a dataset; write the tables and plots",
        description="Converts and processes every recording of the manifest (once per tracker needed; existing "
                    "outputs are kept), trains and tests each variant with each seed (finished runs are not "
                    "repeated), and writes Tables I-III, the timing table and the figures into OUT. Variants: "
                    + ", ".join(VISIONFORCE_VARIANTS) + " (the project's pipeline) and the paper's "
                    + ", ".join(PAPER_VARIANTS) + "; on simulated recordings, only when named: "
                    + ", ".join(SIMULATOR_VARIANTS) + " (the simulator's true tracks); beyond the paper, "
                    "only when named: " + ", ".join(EXTRA_VARIANTS) + ".")
    p.add_argument("manifest", type=Path, help="dataset manifest, e.g. datasets/glove.manifest.yaml")
    p.add_argument("--out", type=Path, required=True, help="results folder, e.g. results/glove")
    p.add_argument("--seeds", type=int, default=3, help="seeds per variant (default 3)")
    p.add_argument("--epochs", type=int, help="training epochs (default: the config's)")
    p.add_argument("--variants", nargs="+", metavar="NAME", help="only these variants (default: the paper's grid)")
    p.add_argument("--ladder", action="store_true",
                   help="simulated recordings: also the attribution ladder for " + ", ".join(LADDER_MODELS)
                        + " (each stage replaced by the simulator's truth in turn; ladder.md)")
    p.add_argument("--configs", type=Path, help="folder of the training configs (default: the repository's configs/)")
    p.add_argument("--depth", default="sgbm", help="depth backend for processing (default sgbm)")
    p.add_argument("--segment", default="colortrack", help="mask backend for processing (default colortrack)")
    p.add_argument("--prompt", help="first-frame tissue prompt (box:x0,y0,x1,y1) for recordings whose metadata "
                                    "and manifest entry give none")
    p.add_argument("--workers", type=int, default=1, help="recordings processed in parallel (default 1)")
    p.add_argument("--executor", default="local", choices=["local", "ray"],
                   help="where processing jobs and training runs go: local (default: processing in --workers "
                        "processes, runs one after the other) or ray (one task per recording and per run on a Ray "
                        "cluster sharing OUT's file system: docs/cluster.md; the 'ray' extra)")
    p.add_argument("--device", default="cpu",
                   help="cpu (default), cuda or auto: the geometry tracker of the processing and the training runs "
                        "(Lightning's accelerator); auto: the training on CUDA when present, the processing on the "
                        "CPU (measured faster there: docs/gpu.md)")
    p.add_argument("--ray-address", help="the Ray cluster (default: the running one, or a new local instance; "
                                         "'auto': the cluster this machine belongs to)")
    p.add_argument("--max-frames", type=int, help="process only the first N frames of each recording (quick runs)")
    p.add_argument("--keep-doubtful", action="store_true",
                   help="train and validate on recordings `vfdata process` judged doubtful too (by default they "
                        "are left out and listed in OUT/doubtful.md; doubtful test recordings always stay)")
    p.add_argument("--reports-only", action="store_true", help="only (re)write the tables and plots of OUT")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--train-arg", dest="train_args", action="append", default=[], metavar="ARG",
                   help="an extra LightningCLI argument for every run, repeatable "
                        "(e.g. --train-arg=--data.batch_size=16; on a CPU with bf16 instructions "
                        "--train-arg=--model.compile_model=true --train-arg=--trainer.precision=bf16-mixed "
                        "can train 2.5x faster, docs/models.md)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # here, not at the top: the runner and report pull in torch; `vfdata --help` starts without it
    from vfmodels.experiment.report import summary_text, write_reports
    from vfmodels.experiment.runner import ExperimentOptions, run_experiment

    if args.reports_only:
        print(summary_text(write_reports(args.out, args.manifest)))
        return 0
    options = ExperimentOptions(seeds=args.seeds, epochs=args.epochs, variants=args.variants, ladder=args.ladder,
                                depth=args.depth,
                                segment=args.segment, prompt=args.prompt, workers=args.workers,
                                executor=args.executor, ray_address=args.ray_address, device=args.device,
                                max_frames=args.max_frames, progress=not args.quiet, train_args=args.train_args,
                                keep_doubtful=args.keep_doubtful)
    if args.configs is not None:
        options.configs = args.configs
    result = run_experiment(args.manifest, args.out, options)
    print(summary_text(result.reports))
    print("wall time: " + ", ".join(f"{k} {v:.0f} s" for k, v in result.seconds.items()))
    return 0
