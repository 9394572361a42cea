"""`vfdata process IN.mcap [OUT.mcap]`: depth, tissue mask, clouds, object frame and tracks."""

from __future__ import annotations

import argparse
from pathlib import Path

from vfdata.commands.engine_flags import add_engine_flags, engine_settings
from vfdata.commands.outputs import skip_existing
from vfdata.device import DEVICE_HELP, resolve_device, tracker_device_options
from vfdata.errors import InputError, VisionForceError
from vfdata.threads import positive_int

# vfdata.processing and the tracker registry (torch, the stages) are imported in `run`, so that
# `vfdata --help` starts fast; the registry checks the tracker's name.


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("process", help="reconstruct and track the tissue of a recording",
                       description="Write a derived MCAP beside the recording (default IN.processed.mcap) with "
                                   "/tissue/mask, /tissue/depth, /tissue/points, /tf_static and /tracking/points, and "
                                   "a picture of the first frame's mask, object frame and tracked points beside it "
                                   "(OUT with .png: look at it before training). The source is never modified.")
    p.add_argument("paths", type=Path, nargs="+", metavar="IN [OUT]",
                   help="recording MCAP and the derived MCAP (default: IN.processed.mcap); with --many, any "
                        "number of recordings, each written beside itself")
    p.add_argument("--many", action="store_true",
                   help="process every IN given (one job each; existing outputs are kept, so a run resumes)")
    p.add_argument("--executor", default="local", choices=["local", "ray"],
                   help="with --many: where the jobs run: local (default; --workers processes) or ray (one task "
                        "per recording on a Ray cluster: docs/cluster.md; the 'ray' extra)")
    p.add_argument("--ray-address", help="the Ray cluster (default: the running one, or a new local instance; "
                                         "'auto': the cluster this machine belongs to)")
    p.add_argument("--workers", type=positive_int, default=1,
                   help="with --many --executor local: recordings processed in parallel processes (default 1)")
    p.add_argument("--prompt", help="first-frame tissue prompt: box:x0,y0,x1,y1 or points:x,y;x,y "
                                    "(default: prompt_box in the recording's metadata)")
    p.add_argument("--ground-truth", type=Path, help="simulator ground_truth/ folder (default: beside the raw folder)")
    p.add_argument("--max-frames", type=int, help="process only the first N frames")
    add_engine_flags(p, tracker_default="geometry", device_help=DEVICE_HELP.replace("and the force model ", ""))
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--skip-existing", action="store_true",
                   help="keep an existing output (and its picture) and exit 0: re-run a loop after an interruption")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _tracker_device(args: argparse.Namespace) -> dict:
    return tracker_device_options(args.tracker, resolve_device(args.device))


def process_job(job: tuple[str, str, object, bool]) -> str:
    """One recording of `--many` (module level: it crosses to a worker process or a Ray task)."""
    from vfdata.processing import process_recording  # the engine (OpenCV, torch): not for `vfdata --help`

    src, out, options, overwrite = job
    return str(process_recording(src, out, options, overwrite=overwrite))


def run(args: argparse.Namespace) -> int:
    # here, not at the top: processing pulls in torch (the tracker); `vfdata --help` starts without it
    from vfdata.processing import ProcessOptions, default_output, preview_path, process_recording

    if not args.many and len(args.paths) > 2:
        raise VisionForceError(f"{len(args.paths)} paths: give IN [OUT], or --many IN IN ... to process several")
    if args.many and args.ground_truth is not None:
        raise VisionForceError("--ground-truth names one recording's ground truth: not with --many (each "
                               "recording's is found beside its raw folder)")
    if not args.many and (args.executor != "local" or args.workers > 1):
        raise VisionForceError("--executor and --workers are for --many (several recordings)")
    if not args.many:
        args.src = args.paths[0]
        args.out = args.paths[1] if len(args.paths) == 2 else None
        target = args.out or default_output(args.src)
        if skip_existing(args, target, preview_path(target)):
            return 0
    settings = engine_settings(args)
    settings["tracker_options"].update(_tracker_device(args))
    options = ProcessOptions(**settings,
                             prompt=args.prompt, ground_truth=args.ground_truth, max_frames=args.max_frames,
                             progress=not args.quiet, threads=args.threads)
    if args.many:
        return _many(args, options)
    out = process_recording(args.src, target, options, overwrite=args.overwrite)
    print(f"wrote {out} and {preview_path(out).name} (the first frame's mask, object frame and points)")
    return 0


def _many(args: argparse.Namespace, options) -> int:
    # the engine (OpenCV, torch) and the executors: not for `vfdata --help`
    from vfdata.executor import run_jobs
    from vfdata.processing import default_output

    options.progress = False
    for src in args.paths:
        if not src.is_file():
            raise InputError(src, "recording not found")
    jobs = [(str(src), str(default_output(src)), options, args.overwrite) for src in args.paths
            if args.overwrite or not default_output(src).is_file()]
    kept = len(args.paths) - len(jobs)
    if kept:
        print(f"{kept} of {len(args.paths)} recordings already processed: kept (--overwrite to redo them)")
    for out in run_jobs(process_job, jobs, args.executor, args.workers, args.ray_address):
        print(f"wrote {out}", flush=True)
    return 0
