"""`vfdata convert SRC OUT.mcap`: a raw recording folder (or a ROS bag, or an episode of a LeRobot
dataset) to a recording MCAP; `vfdata convert LEROBOT_DATASET OUT_DIR`: every episode and a manifest."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from vfdata.commands.inspect_bag import add_bag_arguments, add_force_gap_argument, bag_arguments, force_gap_option_ns
from vfdata.commands.outputs import skip_existing
from vfdata.conversion.bag_scan import is_bag
from vfdata.conversion.bags import convert_bag
from vfdata.conversion.options import MAX_DEFAULT_WORKERS, ConvertOptions, default_workers
from vfdata.conversion.raw_folder import convert_raw_folder
from vfdata.conversion.raw_meta import parse_meta_pairs
from vfdata.conversion.raw_rgbd import convert_rgbd_folder, is_rgbd_folder
from vfdata.errors import InputError
from vfdata.lerobot.folder import is_lerobot_dataset

MAX_TIME_OFFSET_MS = 3_600_000.0  # an hour: a larger offset is another clock, not a latency


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("convert", help="convert a raw recording folder, a ROS bag or a LeRobot dataset to recording "
                                       "MCAPs",
                       description="Convert a raw recording folder (docs/raw_layout.md), a ROS 1/ROS 2 bag "
                                   "(docs/bags.md) or a LeRobot dataset (docs/lerobot.md) to MCAP files of the "
                                   "VisionForce layout (docs/format.md).")
    p.add_argument("src", type=Path, help="raw recording folder, ROS 1 .bag, ROS 2 bag folder, or LeRobot dataset "
                                          "folder (v2.x, v3.0)")
    p.add_argument("out", type=Path, help="output .mcap file; for a LeRobot dataset without --episode, a folder for "
                                          "every episode's MCAP and a manifest of them")
    p.add_argument("--format", dest="image_format", choices=["jpeg", "png"], default="jpeg",
                   help="image compression in the MCAP (default jpeg)")
    p.add_argument("--quality", type=int, default=95, help="JPEG quality 1-100 (default 95)")
    p.add_argument("--reencode", action="store_true",
                   help="re-encode colour JPEG input frames at --quality (default: store them as they are)")
    add_force_gap_argument(p)
    p.add_argument("--time-offset-ms", type=float, default=0.0, metavar="MS",
                   help="how late the force and pose stamps run against the video's, ms (negative: early), as "
                        "`vfdata sync` estimates it; they are moved onto the video's clock (default 0)")
    p.add_argument("--workers", type=int, default=None,
                   help=f"image encoding threads (default: one per CPU core, at most {MAX_DEFAULT_WORKERS}; "
                        f"{default_workers()} here)")
    p.add_argument("--meta", action="append", default=[], metavar="KEY=VALUE",
                   help="metadata the source lacks, repeatable (docs/bags.md): gravity_up=X,Y,Z (up in the ECM "
                        "pose's frame), orientation_deg=DEG, tissue=NAME, prompt=box:x0,y0,x1,y1 (or points:x,y;...), "
                        "sensor_to_object=xyz_deg:RX,RY,RZ (or 9 numbers: the force sensor's frame turned into the "
                        "object frame), id=, split=, any other key; replaces meta.yaml's. For an RGB-D folder, "
                        "also the path of the meta.yaml to use when it is not in the folder. For a LeRobot dataset, "
                        "N:KEY=VALUE (or A-B:KEY=VALUE) sets a key for episode N (A to B) only")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--skip-existing", action="store_true",
                   help="keep an existing output and exit 0 (outputs are only ever complete: re-run a loop "
                        "after an interruption)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_bag_arguments(p)
    g = p.add_argument_group("LeRobot datasets (docs/lerobot.md)")
    g.add_argument("--episode", type=int, metavar="N", help="convert this episode only, to OUT (.mcap)")
    g.add_argument("--topics", action="append", default=[], metavar="KEY=FEATURE,...",
                   help="the features to read, as a manifest's topics: left, right (a stereo pair), color, depth "
                        "(RGB-D), force, pose (pose=none: leave it out); default: found by name (docs/lerobot.md)")
    g.add_argument("--clock", choices=["timestamp", "frame_index"], default="timestamp",
                   help="the frames' times: the timestamp column (default), or frame_index / fps when it holds "
                        "something else (exports of ours keep exact stamps and ignore this)")
    g.add_argument("--splits", action="append", default=[], metavar="SPLIT=START:STOP,...",
                   help="episodes of each split for the manifest (train, val, test), instead of info.json's splits")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if skip_existing(args, args.out):
        return 0
    if not 1 <= args.quality <= 100:
        raise InputError("--quality", f"JPEG quality must be 1-100, not {args.quality}")
    if not math.isfinite(args.time_offset_ms) or abs(args.time_offset_ms) > MAX_TIME_OFFSET_MS:
        raise InputError("--time-offset-ms", f"must be a number of milliseconds within +-{MAX_TIME_OFFSET_MS:g}, "
                                             f"not {args.time_offset_ms}")
    threads = {"workers": args.workers} if args.workers else {}  # else ConvertOptions' default
    options = ConvertOptions(
        image_format=args.image_format, jpeg_quality=args.quality, keep_jpeg=not args.reencode,
        force_gap_tolerance_ns=force_gap_option_ns(args), progress=not args.quiet,
        time_offset_ns=round(args.time_offset_ms * 1e6), **threads,
    )
    if is_lerobot_dataset(args.src):
        return _convert_lerobot(args, options)
    if args.episode is not None or args.topics or args.splits or args.clock != "timestamp":
        raise InputError(args.src, "--episode, --topics, --splits and --clock are for LeRobot datasets (a folder "
                                   "with meta/info.json)")
    rgbd = not is_bag(args.src) and is_rgbd_folder(args.src)
    files = [Path(m) for m in args.meta if "=" not in m]
    pairs = parse_meta_pairs([m for m in args.meta if "=" in m])
    if files and (not rgbd or len(files) > 1):
        raise InputError(files[0], "--meta takes KEY=VALUE; a meta.yaml path only for an RGB-D raw folder "
                                   "(depth/ and color/), once")
    meta = {"meta": pairs} if pairs else {}  # only when given: the converters' own default otherwise
    if rgbd:
        if pairs:
            raise InputError(args.src, "--meta KEY=VALUE is for stereo raw folders and bags; an RGB-D folder takes "
                                       "its meta.yaml (--meta FILE)")
        out = convert_rgbd_folder(args.src, args.out, overwrite=args.overwrite, options=options,
                                  calibration=args.calibration, meta=files[0] if files else None)
    elif is_bag(args.src):
        out = convert_bag(args.src, args.out, overwrite=args.overwrite, options=options, **meta,
                          **bag_arguments(args))
    else:
        out = convert_raw_folder(args.src, args.out, overwrite=args.overwrite, options=options, **meta)
    print(f"wrote {out}")
    return 0


def _convert_lerobot(args: argparse.Namespace, options: ConvertOptions) -> int:
    # pyarrow and PyAV (the `lerobot` extra) only when a LeRobot dataset is converted
    from vfdata.conversion.lerobot_dataset import (
        convert_lerobot_dataset,
        episode_meta_pairs,
        manifest_note,
        parse_splits,
    )
    from vfdata.conversion.lerobot_episodes import convert_lerobot_episode
    from vfdata.lerobot.features import parse_topics

    files = [m for m in args.meta if "=" not in m]
    if files:
        raise InputError(files[0], "--meta takes KEY=VALUE for a LeRobot dataset")
    common, scoped = episode_meta_pairs(args.meta)
    meta = parse_meta_pairs(common)
    episode_meta = {episode: parse_meta_pairs(pairs) for episode, pairs in scoped.items()}
    topics = parse_topics(args.topics)
    bag_only = [name for name, value in (("--left-info-topic", args.left_info_topic),
                                         ("--right-info-topic", args.right_info_topic),
                                         ("--pair-tolerance-ms", args.pair_tolerance_ms)) if value is not None]
    for key, value in (("left", args.left_topic), ("right", args.right_topic), ("force", args.force_topic),
                       ("pose", args.pose_topic)):
        if value is not None:
            if key in topics and topics[key] != value:
                raise InputError(args.src, f"--{key}-topic {value} and --topics {key}={topics[key]} disagree")
            topics[key] = value
    if bag_only:
        raise InputError(args.src, f"{bag_only[0]} is for ROS bags; a LeRobot dataset's frames are paired already")
    # pyarrow (the `lerobot` extra) only when a LeRobot dataset is converted
    from vfdata.lerobot.features import choose_features
    from vfdata.lerobot.folder import read_dataset

    choice = choose_features(read_dataset(args.src), topics)
    if not args.quiet:
        said = [f"{key}={getattr(choice, key)} ({choice.how[key]})" for key in ("left", "right", "depth", "color")
                if getattr(choice, key)]
        pose = f"pose={choice.pose} ({choice.how['pose']})" if choice.pose else f"pose: {choice.how['pose']}"
        print(f"features: {', '.join(said)}, force={choice.force} ({choice.how['force']}), {pose}")
    single = args.episode is not None or args.out.suffix == ".mcap"
    if single:
        if args.splits:
            raise InputError("--splits", "names the splits of a manifest: convert every episode to a folder")
        episode = args.episode
        if episode is None:
            episodes = read_dataset(args.src).episodes
            if len(episodes) != 1:
                raise InputError(args.out, f"the dataset has {len(episodes)} episodes: give --episode N for one, or "
                                           "a folder (not .mcap) for all of them")
            episode = episodes[0].index
        out = convert_lerobot_episode(args.src, episode, args.out, overwrite=args.overwrite, options=options,
                                      topics=topics, calibration=args.calibration,
                                      meta={**meta, **episode_meta.get(episode, {})}, clock=args.clock)
        print(f"wrote {out}")
        return 0
    manifest = convert_lerobot_dataset(args.src, args.out, overwrite=args.overwrite, options=options, topics=topics,
                                       calibration=args.calibration, meta=meta, splits=parse_splits(args.splits),
                                       episode_meta=episode_meta, clock=args.clock)
    print(f"wrote {args.out} (manifest {manifest})")
    note = manifest_note(manifest)
    if note:
        print(f"note: {note}")
    return 0
