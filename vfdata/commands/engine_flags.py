"""The pipeline's flags, one definition for every command that runs the engine (`process`, `predict`,
`live`): the stages and their settings, the tracked points, the object frame, the device and threads.
`engine_settings(args)` turns them into `EngineOptions` fields, so a flag means the same everywhere."""

from __future__ import annotations

import argparse
import json

from vfdata.errors import VisionForceError
from vfdata.object_frames import OBJECT_FRAME_HELP, OBJECT_FRAMES
from vfdata.threads import DEFAULT_THREADS, THREADS_HELP, positive_int
from vfdata.tracker_kinds import TRACKER_HELP


def key_values(text: str | None) -> dict:
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


def add_engine_flags(p: argparse.ArgumentParser, *, tracker_default: str | None, tracker_help: str = TRACKER_HELP,
                     device_help: str) -> None:
    """The engine's flags on `p`, in one group. `tracker_default` None: the commands that run a trained model
    take the tracker its training tracks came from (the checkpoint says)."""
    g = p.add_argument_group("pipeline (the same flags in process, predict and live)")
    g.add_argument("--depth", default="sgbm", help="depth backend: sgbm (default), stereoanyvideo, recorded; an "
                                                   "RGB-D recording's own depth (sensor) is always used")
    g.add_argument("--depth-options", help="backend options, key=value,... (e.g. code=DIR,checkpoint=FILE)")
    g.add_argument("--working-range-mm", type=float, nargs=2, default=(40.0, 300.0), metavar=("NEAR", "FAR"),
                   help="nearest and farthest surface in front of the scope; sets the sgbm disparity range "
                        "(default 40 300)")
    g.add_argument("--segment", default="colortrack",
                   help="mask backend: colortrack (default for stereo), sam2, plane (default for RGB-D: what stands "
                        "above a flat board)")
    g.add_argument("--segment-options", help="backend options, key=value,... (e.g. config=...,checkpoint=...)")
    g.add_argument("--object-frame", default="auto", choices=list(OBJECT_FRAMES), help=OBJECT_FRAME_HELP)
    g.add_argument("--tracker", default=tracker_default, help=tracker_help)
    g.add_argument("--tracker-options", help="tracker options, key=value,... (e.g. for klt: lift=stereo, "
                                             "smoothing=0.5, recover=true; docs/tracking.md)")
    g.add_argument("--points", type=positive_int, default=256, help="tracked points (default 256)")
    g.add_argument("--seed", type=int, default=0,
                   help="random seed of the point sampling and the tracker (default 0; same seed: same tracks)")
    g.add_argument("--device", default="cpu", help=device_help)
    g.add_argument("--threads", type=positive_int, default=DEFAULT_THREADS, help=THREADS_HELP)


def engine_settings(args: argparse.Namespace) -> dict:
    """The `EngineOptions` fields of the flags `add_engine_flags` defined (the tracker's options as given;
    the caller adds what the device or a checkpoint implies)."""
    return {"depth": args.depth, "depth_options": key_values(args.depth_options), "segment": args.segment,
            "segment_options": key_values(args.segment_options), "tracker": args.tracker,
            "tracker_options": key_values(args.tracker_options), "num_points": args.points, "seed": args.seed,
            "working_range_mm": tuple(args.working_range_mm), "object_frame": args.object_frame}
