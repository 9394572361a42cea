"""`vfdata sync REC.mcap`: how late the force (and ECM pose) stamps run against the video's, estimated
from the data (vfdata.clock_offset), and the `vfdata convert --time-offset-ms` that aligns them."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import cv2

from vfdata.clock_offset import OffsetEstimate, RecordingOffsets, recording_offsets
from vfdata.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sync", help="estimate the force's (and ECM pose's) clock offset against the video",
                       description="Estimate the constant offset between a recording's video and its force (and "
                                   "ECM pose) stamps from the data: the image motion in the tissue region against "
                                   "the force's change, at every offset within the search (docs/sync.md). Prints "
                                   "the offset, its uncertainty and the `vfdata convert --time-offset-ms` that "
                                   "aligns the streams. Reads the file only.")
    p.add_argument("recording", type=Path, help="recording MCAP (stereo or RGB-D)")
    p.add_argument("--max-offset-ms", type=float, default=500.0,
                   help="search offsets within +-MS (default 500)")
    p.add_argument("--max-frames", type=int, help="only the first N frames")
    p.add_argument("--json", action="store_true", help="print the estimates as one JSON object")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not math.isfinite(args.max_offset_ms) or not 0 < args.max_offset_ms <= 60_000:
        raise InputError("--max-offset-ms", f"must be a positive number of milliseconds up to 60000, not "
                                            f"{args.max_offset_ms}")
    if args.max_frames is not None and args.max_frames < 3:
        raise InputError("--max-frames", f"must be 3 or more, not {args.max_frames}")
    cv2.setNumThreads(1)  # one thread per process (vfdata/threads.py): the flow of quarter-size images
    result = recording_offsets(args.recording, args.max_offset_ms, args.max_frames, progress=not args.quiet)
    print(json.dumps(as_json(result), indent=2) if args.json else report(args.recording, result))
    return 0


def _ms(value: float | None) -> float | None:
    return None if value is None or not math.isfinite(value) else round(value / 1e6, 3)


def as_json(result: RecordingOffsets) -> dict:
    def one(estimate: OffsetEstimate | None) -> dict | None:
        if estimate is None:
            return None
        return {"offset_ms": _ms(estimate.offset_ns), "uncertainty_ms": _ms(estimate.uncertainty_ns),
                "fit_r2": None if not math.isfinite(estimate.fit_r2) else round(estimate.fit_r2, 4),
                "lead_ms": _ms(estimate.lead_ns), "intervals": estimate.intervals, "confident": estimate.confident,
                "reason": estimate.reason or None}

    return {"frames": result.frames, "duration_s": round(result.duration_s, 3), "region": result.region,
            "applied_ms": result.applied_ns / 1e6, "force": one(result.force), "pose": one(result.pose)}


def report(path: Path, result: RecordingOffsets) -> str:
    where = (f"in the tissue region x {result.region[0]}-{result.region[2]}, y {result.region[1]}-{result.region[3]} "
             "px (the first frame's box, grown by a quarter)" if result.region else "over the whole image (no tissue "
             "box in the metadata)")
    lines = [f"{path}: {result.frames} frames, {result.duration_s:.1f} s; image motion {where}"]
    force = result.force
    if force.offset_ns is None:
        lines.append(f"force:    no estimate: {force.reason}")
    else:
        late = "late" if force.offset_ns >= 0 else "early"
        lines.append(f"force:    runs {abs(force.offset_ns) / 1e6:.1f} ms {late} against the video (+-"
                     f"{force.uncertainty_ns / 1e6:.1f} ms, fit R2 {force.fit_r2:.2f}, {force.intervals} frame "
                     f"intervals); beyond that the force leads the tissue's motion by {force.lead_ns / 1e6:.0f} ms "
                     "(its viscous response: physics, not a clock, and left as it is)")
        total = force.offset_ns + result.applied_ns
        if result.applied_ns:
            lines.append(f"          its conversion already moved the sensors by {result.applied_ns / 1e6:g} ms: "
                         f"{total / 1e6:.1f} ms in all")
        if force.confident:
            lines.append(f"          align: vfdata convert SRC {path} --overwrite --time-offset-ms {total / 1e6:.1f}")
        else:
            why = force.reason or ("the image motion explains little of the force" if force.fit_r2 < 0.3
                                   else "the parts of the recording disagree")
            lines.append(f"          weak estimate ({why}): check it on another recording of the set-up")
    pose = result.pose
    if pose is None:
        lines.append("ECM pose: none in the recording")
    elif pose.offset_ns is None:
        lines.append(f"ECM pose: no estimate: {pose.reason}")
    else:
        late = "late" if pose.offset_ns >= 0 else "early"
        weak = "" if pose.confident else " (weak)"
        lines.append(f"ECM pose: runs {abs(pose.offset_ns) / 1e6:.1f} ms {late} against the video (+-"
                     f"{pose.uncertainty_ns / 1e6:.1f} ms, fit R2 {pose.fit_r2:.2f}){weak}; --time-offset-ms moves "
                     "force and pose together")
    return "\n".join(lines)
