"""`vfdata export --lerobot RECORDINGS... OUT`: recordings as a LeRobot dataset (docs/lerobot.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from vfdata.commands.outputs import skip_existing
from vfdata.errors import InputError

TRACKS_SUFFIX = ".processed.mcap"
ESTIMATE_SUFFIX = ".force.mcap"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="write recordings as a LeRobot dataset",
                       description="Write recording MCAPs as a LeRobot dataset (docs/lerobot.md): the stereo views as "
                                   "videos, the force at the frame rate (observation.meta.force_torque) and at the "
                                   "sensor's own rate, the ECM pose as observation.state, a dataset card. `vfdata "
                                   "convert` reads it back.")
    p.add_argument("--lerobot", action="store_true", required=True, help="the format to write (the one there is)")
    p.add_argument("paths", type=Path, nargs="+", metavar="RECORDINGS... OUT",
                   help="recording MCAPs (one episode each), then the output dataset folder")
    p.add_argument("--version", choices=["v3.0", "v2.1"], default="v3.0",
                   help="LeRobot dataset format (default v3.0; v2.1 is Open-H's, LeRobot 0.3.3)")
    p.add_argument("--codec", choices=["av1", "h264"], default="av1", help="video codec (default av1, as LeRobot)")
    p.add_argument("--crf", type=int, default=None, help="video quality, lower is better (default: av1 20, h264 18)")
    p.add_argument("--gop", type=int, default=2, help="frames between keyframes (default 2, as LeRobot)")
    p.add_argument("--fps", type=int, default=None,
                   help="frames per second LeRobot's clock counts (default: the recordings' rate, rounded)")
    p.add_argument("--task", default=None, help="the task text of every frame")
    p.add_argument("--robot-type", default="dvrk", help="info.json robot_type (default dvrk)")
    p.add_argument("--tracks", nargs="?", const=TRACKS_SUFFIX, default=None, metavar="SUFFIX",
                   help=f"add the tracks of each recording's derived file (<id>{TRACKS_SUFFIX}, or <id>SUFFIX)")
    p.add_argument("--estimate", nargs="?", const=ESTIMATE_SUFFIX, default=None, metavar="SUFFIX",
                   help=f"add the force `vfdata predict` estimated (<id>{ESTIMATE_SUFFIX}, or <id>SUFFIX)")
    p.add_argument("--license", default=None, help="the dataset card's license (a Hugging Face license id)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    p.add_argument("--skip-existing", action="store_true", help="keep an existing output folder and exit 0")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # pyarrow and PyAV (the `lerobot` extra) only for this command
    from vfdata.lerobot.export import DEFAULT_TASK, ExportOptions, export_lerobot

    if len(args.paths) < 2:
        raise InputError(args.paths[0], "give the recordings and then the output folder")
    *recordings, out = args.paths
    if out.suffix == ".mcap":
        raise InputError(out, "the last path is the output dataset folder, not a recording")
    if skip_existing(args, out):
        return 0
    for option, suffix in (("--tracks", args.tracks), ("--estimate", args.estimate)):
        if suffix is not None and (not suffix.startswith(".") or "/" in suffix):
            # `--tracks a.mcap b.mcap OUT` would take a.mcap as the suffix: say how to write it instead
            raise InputError(option, f"{suffix!r} is not a suffix such as .klt.mcap: give the option after the paths, "
                                     f"or as {option}=SUFFIX")
    if args.crf is not None and not 0 <= args.crf <= 63:
        raise InputError("--crf", f"must be 0-63, not {args.crf}")
    if args.gop < 1:
        raise InputError("--gop", f"must be 1 or more, not {args.gop}")
    options = ExportOptions(version=args.version, codec=args.codec, crf=args.crf, gop=args.gop, fps=args.fps,
                            task=args.task or DEFAULT_TASK, robot_type=args.robot_type, tracks=args.tracks,
                            estimate=args.estimate, license=args.license, progress=not args.quiet)
    export_lerobot(recordings, out, overwrite=args.overwrite, options=options)
    print(f"wrote {out} ({len(recordings)} episode(s), LeRobot {args.version})")
    return 0
