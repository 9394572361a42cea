"""`vfdata process IN.mcap [OUT.mcap]`: depth, tissue mask, clouds, object frame and tracks."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from vfdata.commands.outputs import skip_existing
from vfdata.device import DEVICE_HELP, resolve_device, tracker_device_options
from vfdata.errors import VisionForceError
from vfdata.object_frames import OBJECT_FRAME_HELP, OBJECT_FRAMES
from vfdata.threads import DEFAULT_THREADS, THREADS_HELP, positive_int
from vfdata.tracker_kinds import TRACKER_HELP

# vfdata.processing and the tracker registry (torch, the stages) are imported in `run`, so that
# `vfdata --help` starts fast; the registry checks the tracker's name.


def _options(text: str | None) -> dict:
    """`key=value,key=value` (values parsed as JSON when they can be: numbers, true/false)."""
    result = {}
    for item in filter(None, (text or "").split(",")):
        if "=" not in item:
            raise VisionForceError(f"option '{item}' is not key=value")
        key, value = item.split("=", 1)
        try:
            result[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            result[key.strip()] = value
    return result


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
    p.add_argument("--depth", default="sgbm", help="depth backend: sgbm (default), stereoanyvideo, recorded; an "
                                                   "RGB-D recording's own depth (sensor) is always used")
    p.add_argument("--depth-options", help="backend options, key=value,... (e.g. code=DIR,checkpoint=FILE)")
    p.add_argument("--working-range-mm", type=float, nargs=2, default=(40.0, 300.0), metavar=("NEAR", "FAR"),
                   help="nearest and farthest surface in front of the scope; sets the sgbm disparity range "
                        "(default 40 300)")
    p.add_argument("--segment", default="colortrack",
                   help="mask backend: colortrack (default for stereo), sam2, plane (default for RGB-D: what stands "
                        "above a flat board)")
    p.add_argument("--object-frame", default="auto", choices=list(OBJECT_FRAMES), help=OBJECT_FRAME_HELP)
    p.add_argument("--segment-options", help="backend options, key=value,... (e.g. config=...,checkpoint=...)")
    p.add_argument("--prompt", help="first-frame tissue prompt: box:x0,y0,x1,y1 or points:x,y;x,y "
                                    "(default: prompt_box in the recording's metadata)")
    p.add_argument("--tracker", default="geometry", help=TRACKER_HELP)
    p.add_argument("--tracker-options", help="tracker options, key=value,... (e.g. for klt: lift=stereo, "
                   "smoothing=0.5; docs/tracking.md)")
    p.add_argument("--points", type=int, default=256, help="tracked points (default 256)")
    p.add_argument("--ground-truth", type=Path, help="simulator ground_truth/ folder (default: beside the raw folder)")
    p.add_argument("--max-frames", type=int, help="process only the first N frames")
    p.add_argument("--seed", type=int, default=0,
                   help="random seed of the point sampling and the tracker (default 0; same seed: same tracks)")
    p.add_argument("--device", default="cpu", help=DEVICE_HELP.replace("and the force model ", ""))
    p.add_argument("--threads", type=positive_int, default=DEFAULT_THREADS, help=THREADS_HELP)
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--skip-existing", action="store_true",
                   help="keep an existing output (and its picture) and exit 0: re-run a loop after an interruption")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _tracker_device(args: argparse.Namespace) -> dict:
    return tracker_device_options(args.tracker, resolve_device(args.device))


def process_job(job: tuple[str, str, object, bool]) -> str:
    """One recording of `--many` (module level: it crosses to a worker process or a Ray task)."""
    from vfdata.processing import process_recording

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
    options = ProcessOptions(
        depth=args.depth, depth_options=_options(args.depth_options), segment=args.segment,
        segment_options=_options(args.segment_options), prompt=args.prompt, tracker=args.tracker,
        tracker_options={**_options(args.tracker_options), **_tracker_device(args)}, num_points=args.points,
        seed=args.seed,
        ground_truth=args.ground_truth, max_frames=args.max_frames, progress=not args.quiet,
        working_range_mm=tuple(args.working_range_mm), object_frame=args.object_frame, threads=args.threads,
    )
    if args.many:
        return _many(args, options)
    out = process_recording(args.src, target, options, overwrite=args.overwrite)
    print(f"wrote {out} and {preview_path(out).name} (the first frame's mask, object frame and points)")
    return 0


def _many(args: argparse.Namespace, options) -> int:
    from vfdata.errors import InputError
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
