"""`vfdata inspect-bag BAG`: the topics of a ROS 1 or ROS 2 bag (types, counts, rates) and which of
them `vfdata convert` would read, with the stereo pairing and force coverage it would find.

`add_bag_arguments` and `bag_arguments` are shared with `vfdata convert` (same topic options)."""

from __future__ import annotations

import argparse
from array import array
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader
from tqdm import tqdm

from vfdata.calibration import StereoCalibration
from vfdata.conversion import bag_scan, bag_topics, bags, rgbd_bags
from vfdata.errors import InputError
from vfdata.force_coverage import FORCE_GAP_PERIODS, MIN_FORCE_GAP_NS

# How a bag without random access (`bag_index`) is read.
STREAMING = ("streaming through rosbags (compressed chunks or bag): every message is read twice, images "
             "included; slower than random access")


def add_bag_arguments(p: argparse.ArgumentParser) -> None:
    """The topic remapping and camera options of a bag conversion."""
    g = p.add_argument_group("ROS bags (defaults: dVRK topic names, auto-detected by type when absent)")
    g.add_argument("--left-topic", metavar="TOPIC",
                   help=f"left images, Image or CompressedImage (default {bag_topics.LEFT_IMAGE_DEFAULTS[0]})")
    g.add_argument("--right-topic", metavar="TOPIC",
                   help=f"right images (default {bag_topics.RIGHT_IMAGE_DEFAULTS[0]})")
    g.add_argument("--left-info-topic", metavar="TOPIC", help="left CameraInfo (default: camera_info beside the "
                                                              "left image topic)")
    g.add_argument("--right-info-topic", metavar="TOPIC", help="right CameraInfo (default: beside the right images)")
    g.add_argument("--force-topic", metavar="TOPIC",
                   help=f"force sensor WrenchStamped (default: first of {', '.join(bag_topics.FORCE_DEFAULTS)})")
    g.add_argument("--pose-topic", metavar="TOPIC",
                   help=f"ECM pose, PoseStamped or TransformStamped (default {bag_topics.POSE_DEFAULTS[0]}; "
                        f"'{bag_topics.NO_TOPIC}' to leave it out)")
    g.add_argument("--calibration", type=Path, metavar="YAML",
                   help="stereo calibration (docs/raw_layout.md) to use instead of the bag's CameraInfo; "
                        "for an RGB-D raw folder, its rgbd_calibration.yaml when not in the folder")
    g.add_argument("--pair-tolerance-ms", type=float, metavar="MS",
                   help="largest left/right stamp difference of a stereo pair (default half the frame period)")


def bag_arguments(args: argparse.Namespace) -> dict:
    """Keyword arguments of `bags.convert_bag` from the options of `add_bag_arguments`."""
    return {
        "topics": bag_topics.BagTopics(args.left_topic, args.right_topic, args.left_info_topic, args.right_info_topic,
                                 args.force_topic, args.pose_topic),
        "calibration": args.calibration,
        "pair_tolerance_ns": _pair_tolerance_ns(args.pair_tolerance_ms),
    }


def _pair_tolerance_ns(ms: float | None) -> int | None:
    if ms is None:
        return None
    if not 0 <= ms < 1e9:  # also NaN and inf
        raise InputError("--pair-tolerance-ms", f"must be a number of milliseconds, 0 or more, not {ms}")
    return int(ms * 1e6)


def add_force_gap_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--force-gap-ms", type=float, default=None, metavar="MS",
                   help=f"largest gap allowed in the force stream over the video span (default "
                        f"{FORCE_GAP_PERIODS}x the stream's median sample interval, at least "
                        f"{MIN_FORCE_GAP_NS / 1e6:.0f} ms)")


def force_gap_option_ns(args: argparse.Namespace) -> int | None:
    """The --force-gap-ms of `add_force_gap_argument` in ns (None: the stream's default)."""
    if args.force_gap_ms is None:
        return None
    if not 0 < args.force_gap_ms < 1e9:  # also NaN and inf
        raise InputError("--force-gap-ms", f"must be a positive number of milliseconds, not {args.force_gap_ms}")
    return int(args.force_gap_ms * 1e6)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("inspect-bag", help="list a ROS bag's topics and which ones convert would use",
                       description="List the topics of a ROS 1 (.bag) or ROS 2 (folder, .db3, .mcap) bag with "
                                   "types, counts and rates, and say which ones `vfdata convert` would read. "
                                   "Exits 0 when convert would succeed, 1 (after the listing, with the reason "
                                   "in one line) when it would stop.")
    p.add_argument("bag", type=Path, help="ROS 1 .bag file or ROS 2 bag folder")
    add_bag_arguments(p)
    add_force_gap_argument(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    kwargs = bag_arguments(args)
    report = inspect_bag(args.bag, kwargs["topics"], kwargs["calibration"], kwargs["pair_tolerance_ns"],
                         force_gap_option_ns(args), progress=not args.quiet)
    print(report.text, flush=True)
    if report.problem is not None:  # listed above; a script checking the bag sees it in the exit status
        raise InputError(args.bag, f"cannot convert: {report.problem}")
    return 0


@dataclass(frozen=True)
class BagReport:
    text: str  # what `vfdata inspect-bag` prints
    problem: str | None  # why `vfdata convert` would stop; None when it would convert


def inspect_bag_text(path: str | Path, topics: bag_topics.BagTopics | None = None, calibration: Path | None = None,
                     pair_tolerance_ns: int | None = None, force_gap_ns: int | None = None,
                     progress: bool = False) -> str:
    """The report printed by `vfdata inspect-bag` (`inspect_bag(...).text`)."""
    return inspect_bag(path, topics, calibration, pair_tolerance_ns, force_gap_ns, progress).text


def inspect_bag(path: str | Path, topics: bag_topics.BagTopics | None = None, calibration: Path | None = None,
                pair_tolerance_ns: int | None = None, force_gap_ns: int | None = None,
                progress: bool = False) -> BagReport:
    """What a bag holds and whether it converts. A bag that cannot be converted is still listed, with
    the reason under "conversion" (and in `problem`)."""
    path = Path(path)
    lines = []
    with bag_scan.open_bag(path) as reader:
        types = bag_topics.topic_types(reader)
        size = sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) if path.is_dir() else path.stat().st_size
        lines.append(f"bag: {path}  ({bag_scan.bag_kind(path)}, {size / 1e6:.1f} MB, {reader.message_count} messages, "
                     f"{reader.duration / 1e9:.3f} s)")
        choice = scan = None
        try:
            asked = topics or bag_topics.BagTopics()
            rgbd = rgbd_bags.rgbd_topics(types, asked)
            choice = rgbd_bags.rgbd_choice(path, types, *rgbd, asked) if rgbd else bag_topics.choose_topics(
                path, types, asked, use_camera_info=calibration is None)
            scan = bag_scan.scan_bag(reader, path, choice, all_topics=True, progress=progress)
            counts, receive = scan.counts, scan.receive_ns
            reading = scan.indexed.reading if scan.indexed is not None else STREAMING
            bag_scan.close_scan(scan)  # the rest needs only what the scan found
        except InputError as exc:  # still list the topics, then say why convert would stop
            problem = exc.problem
            counts = {name: info.msgcount for name, info in reader.topics.items()}
            receive = receive_times(reader, path, progress)
    rates = topic_rates_hz(receive)
    used = _used_topics(choice)
    width = max([34, *(len(t) + 2 for t in types)])
    lines.append("")
    lines.append(f"{'topic':{width}} {'type':36} {'count':>8} {'rate Hz':>9}  used as")
    for topic, msgtype in types.items():
        lines.append(f"{topic:{width}} {msgtype:36} {counts.get(topic, 0):>8} {rates.get(topic, 0.0):>9.2f}  "
                     f"{used.get(topic, '')}".rstrip())
    lines.append("")
    lines.append("conversion:")
    if scan is None:
        lines.append(f"  cannot convert: {problem}")
        return BagReport("\n".join(lines), problem)
    lines.append(f"  reading: {reading}")
    conversion, problem = _conversion_lines(scan, calibration, pair_tolerance_ns, force_gap_ns)
    return BagReport("\n".join(lines + conversion), problem)


def receive_times(reader: AnyReader, path: Path, progress: bool = False) -> dict[str, np.ndarray]:
    """Bag receive times (ns) of every topic, reading the whole bag."""
    times: dict[str, array] = {}
    with tqdm(total=reader.message_count, desc=f"read {path.name}", unit="msg", disable=not progress,
              mininterval=0.5) as bar:
        for connection, receive_ns, _raw in bag_scan.bag_messages(reader, path, reader.connections):
            times.setdefault(connection.topic, array("q")).append(receive_ns)
            bar.update()
    return {topic: np.frombuffer(values, np.int64) for topic, values in times.items()}


def topic_rates_hz(receive_ns: dict[str, np.ndarray]) -> dict[str, float]:
    """Mean message rate of each topic over its receive times (0 for fewer than two messages)."""
    rates = {}
    for topic, times in receive_ns.items():
        span = (int(times.max()) - int(times.min())) / 1e9 if len(times) > 1 else 0.0
        rates[topic] = (len(times) - 1) / span if span > 0 else 0.0
    return rates


def _used_topics(choice: bag_topics.TopicChoice | None) -> dict[str, str]:
    if choice is None:
        return {}
    roles = [
        ("left images", choice.left, "left"), ("right images", choice.right, "right"),
        ("left camera info", choice.left_info, "left_info"), ("right camera info", choice.right_info, "right_info"),
        ("force", choice.force, "force"), ("ECM pose", choice.pose, "pose"),
    ]
    return {topic: f"{role} ({choice.how.get(key, '')})" for role, topic, key in roles if topic}


def _conversion_lines(scan: bag_scan.BagScan, calibration: Path | None, pair_tolerance_ns: int | None,
                      force_gap_ns: int | None) -> tuple[list[str], str | None]:
    """The "conversion" section's lines, and the problem that would stop convert (None: it converts)."""
    lines = []
    for stream in (scan.left, scan.right):
        lines.append(f"  {stream.topic}: {stream.count} frames, {stream.width}x{stream.height} {stream.encoding}"
                     + (f", {stream.fallback_count} with header.stamp 0 (receive time used)"
                        if stream.fallback_count else ""))
    if scan.choice.pose is None:
        lines.append(f"  ECM pose: {scan.choice.how.get('pose', 'none')}")
    try:
        plan = bags.plan_pairs(scan, pair_tolerance_ns)
    except InputError as exc:
        lines.append(f"  cannot convert: {exc.problem}")
        return lines, exc.problem
    lines.append(f"  stereo pairs: {len(plan.stamps_ns)} within {plan.tolerance_ns / 1e6:.1f} ms (largest offset "
                 f"{plan.max_offset_ns / 1e6:.3f} ms); unpaired: {plan.unpaired_left} left, "
                 f"{plan.unpaired_right} right")
    force = scan.force
    lines.append(f"  force: {len(force.stamps_ns)} samples, frame '{force.frame_id}'"
                 + (f", {force.fallback_count} with header.stamp 0" if force.fallback_count else "")
                 + (f", {force.duplicate_count} repeated stamps dropped" if force.duplicate_count else ""))
    if scan.choice.how.get("right") == bag_topics.RGBD_DEPTH:  # an RGB-D driver's bag: colour = left, depth = right
        try:
            color, depth = (bags.bag_camera_info(scan.path, topic, msg, frame) for topic, msg, frame in (
                (scan.choice.left_info, scan.left_info, "color"), (scan.choice.right_info, scan.right_info, "depth")))
            lines.append(f"  RGB-D camera: camera_info topics {scan.choice.left_info}, {scan.choice.right_info}; "
                         f"colour fx {color.p[0, 0]:.1f} px, depth fx {depth.p[0, 0]:.1f} px")
            bags.check_force_span(scan, plan, force_gap_ns)
        except InputError as exc:
            lines.append(f"  cannot convert: {exc.problem}")
            return lines, exc.problem
        lines.append("  ready to convert (RGB-D layout)")
        return lines, None
    try:
        calib = StereoCalibration.load(calibration) if calibration is not None else None
        _left, right, tf, source = bags.camera_model(scan, calib, calibration)
        baseline_mm = tf.transforms[0].translation[0] * 1e3
        lines.append(f"  camera: {source}; fx {right.p[0, 0]:.1f} px, baseline {baseline_mm:.2f} mm")
        bags.check_force_span(scan, plan, force_gap_ns)
    except InputError as exc:
        lines.append(f"  cannot convert: {exc.problem}")
        return lines, exc.problem
    lines.append("  ready to convert")
    return lines, None
