"""`vfdata info` and `vfdata check`: what a file holds, and whether it follows the layout intact."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vfdata.errors import VisionForceError
from vfdata.mcap_io.records import crc32
from vfdata.recording import layout
from vfdata.recording.derived import DerivedMeta
from vfdata.recording.reader import FORCE_GAP_TOLERANCE_NS, Recording


@dataclass
class SyncStats:
    """How force samples sit against frame times (ns)."""

    samples_per_frame_median: float
    nearest_offset_median_ns: float
    nearest_offset_max_ns: float
    frames_without_force: int  # frames farther than the gap tolerance from any sample


def sync_stats(frame_ns: np.ndarray, force_ns: np.ndarray, tolerance_ns: int = FORCE_GAP_TOLERANCE_NS) -> SyncStats:
    pos = np.clip(np.searchsorted(force_ns, frame_ns), 1, len(force_ns) - 1) if len(force_ns) > 1 else np.zeros(
        len(frame_ns), dtype=int)
    nearest = np.minimum(np.abs(force_ns[pos] - frame_ns), np.abs(force_ns[np.maximum(pos - 1, 0)] - frame_ns))
    edges = np.searchsorted(force_ns, frame_ns)
    per_frame = np.diff(edges) if len(edges) > 1 else np.array([len(force_ns)])
    return SyncStats(
        float(np.median(per_frame)), float(np.median(nearest)), float(nearest.max()),
        int((nearest > tolerance_ns).sum()),
    )


def info_text(path: str | Path) -> str:
    rec = Recording.open(path)
    lines = [f"file: {rec.path}  ({rec.path.stat().st_size / 1e6:.1f} MB)"]
    start, end = rec.time_range_ns
    lines.append(f"duration: {(end - start) / 1e9:.3f} s  ({start} .. {end} ns)")
    meta = rec.metadata_records.get(layout.RECORDING_METADATA) or rec.metadata_records.get(layout.DERIVED_METADATA)
    if meta:
        shown = {k: v for k, v in meta.items() if k not in ("units", "confidence")}
        lines.append("metadata: " + ", ".join(f"{k}={v}" for k, v in shown.items() if v))
    verdict = derived_verdict(rec)
    if verdict is not None:
        lines.append(f"confidence: {verdict}")
    lines.append("")
    lines.append(f"{'topic':34} {'type':34} {'count':>8} {'rate Hz':>9} {'max gap ms':>11}")
    for info in rec.topics.values():
        times = rec.log_times_ns(info.topic) if info.count else np.zeros(0)
        gap = np.diff(times).max() / 1e6 if len(times) > 1 else 0.0
        lines.append(f"{info.topic:34} {info.msgtype:34} {info.count:>8} {info.rate_hz:>9.2f} {gap:>11.2f}")
    # A damaged chunk or payload leaves its section out; `damaged:` below says why.
    unreadable = []
    if rec.has(layout.WRENCH) and rec.num_frames:
        try:
            stats = sync_stats(rec.frame_times_ns, rec.force.times_ns)
            lines.append("")
            lines.append(
                f"force-to-frame sync: {stats.samples_per_frame_median:.0f} samples per frame (median); nearest "
                f"sample {stats.nearest_offset_median_ns / 1e6:.3f} ms median, "
                f"{stats.nearest_offset_max_ns / 1e6:.3f} ms max; {stats.frames_without_force} frame(s) farther "
                f"than {FORCE_GAP_TOLERANCE_NS / 1e6:.0f} ms from any sample"
            )
        except VisionForceError as exc:
            unreadable.append(exc.problem if hasattr(exc, "problem") else str(exc))
    for topic, name in ((layout.DEPTH_INFO, "depth camera"), (layout.COLOR_INFO, "colour camera")):
        if rec.has(topic):
            try:
                cam = rec.depth_camera if topic == layout.DEPTH_INFO else rec.color_camera
                lines.append(f"{name}: {cam.width}x{cam.height}, fx {cam.fx:.1f} fy {cam.fy:.1f} cx {cam.cx:.1f} "
                             f"cy {cam.cy:.1f} px")
            except VisionForceError as exc:
                unreadable.append(exc.problem if hasattr(exc, "problem") else str(exc))
    if rec.is_rgbd:
        registered = rec.metadata.extra.get("depth_color_registered")
        known = "known" if registered == "true" else "unknown"
        lines.append("layout: RGB-D" + ("" if registered is None else f" (depth-to-colour transform {known})"))
    if rec.has(layout.LEFT_INFO):
        try:
            stereo = rec.stereo
            cam = stereo.left
            lines.append(
                f"camera: {cam.width}x{cam.height}, fx {cam.fx:.1f} fy {cam.fy:.1f} cx {cam.cx:.1f} "
                f"cy {cam.cy:.1f} px, baseline {stereo.baseline_mm:.2f} mm"
            )
        except VisionForceError as exc:
            unreadable.append(exc.problem if hasattr(exc, "problem") else str(exc))
    for problem in dict.fromkeys(rec.problems + unreadable):
        lines.append(f"damaged: {problem}")
    return "\n".join(lines)


def derived_verdict(rec: Recording) -> str | None:
    """A derived file's verdict on its recording (`vfdata.confidence`) in words: 'ok' or 'doubtful: ...', and its notes;
    None when the file holds none (a recording, or a derived file from before it was judged)."""
    meta = rec.metadata_records.get(layout.DERIVED_METADATA)
    if not meta or "confidence" not in meta:
        return None
    confidence = DerivedMeta.from_record(rec.path, meta).confidence
    verdict = "ok" if not confidence.doubtful else f"doubtful: {confidence.describe()}"
    return verdict + (f" (notes: {confidence.describe(confidence.notes)})" if confidence.notes else "")


def file_verdict(path: str | Path) -> str | None:
    """`derived_verdict` of the file at `path` (a file that passed `check_file`)."""
    with Recording.open(path) as rec:
        return derived_verdict(rec)


def check_file(path: str | Path) -> list[str]:
    """Every problem found (empty when the file is sound and follows the layout). The file is read
    as `Recording.open(path, damaged="skip")` reads it: every chunk is checked (record, CRC, message
    index), so this lists exactly the damage the reader refuses, plus the data-section CRC, which
    covers what no other CRC does (metadata, the header, message indexes), and the layout."""
    path = Path(path)
    try:
        rec = Recording.open(path, damaged="skip")
    except VisionForceError as exc:  # the problem alone when it is this file's: the caller names the file
        return [exc.problem if getattr(exc, "path", None) == path and hasattr(exc, "problem") else str(exc)]
    problems = list(rec.problems)
    problems += _check_data_crc(rec)
    index = rec._mcap.index
    if index.profile != layout.PROFILE:
        problems.append(f"profile is '{index.profile}', expected '{layout.PROFILE}'")
    for channel in index.channels.values():
        if channel.message_encoding != layout.MESSAGE_ENCODING:
            problems.append(f"{channel.topic}: message encoding '{channel.message_encoding}', expected cdr")
        if channel.schema_encoding != layout.SCHEMA_ENCODING:
            problems.append(f"{channel.topic}: schema encoding '{channel.schema_encoding}', expected ros2msg")
    is_recording = layout.RECORDING_METADATA in rec.metadata_records
    rgbd = is_recording and rec.is_rgbd
    live = not is_recording and rec.metadata_records.get(layout.DERIVED_METADATA, {}).get("stage") == "live"
    expected = ((layout.RGBD_TOPICS if rgbd else layout.RECORDING_TOPICS) if is_recording else
                layout.LIVE_TOPICS if live else layout.DERIVED_TOPICS)
    if not is_recording and layout.DERIVED_METADATA not in rec.metadata_records:
        problems.append(f"no '{layout.RECORDING_METADATA}' or '{layout.DERIVED_METADATA}' metadata record")
    for topic, info in rec.topics.items():
        if topic not in expected:
            problems.append(f"{topic}: not a topic of the layout")
        elif info.msgtype != expected[topic]:
            problems.append(f"{topic}: type {info.msgtype}, expected {expected[topic]}")
    if is_recording:
        for topic in layout.RGBD_REQUIRED_TOPICS if rgbd else layout.REQUIRED_TOPICS:
            if not rec.has(topic):
                problems.append(f"{topic}: missing")
    for topic, info in rec.topics.items():
        if topic == layout.TF_STATIC or not info.count or topic not in expected:
            continue
        problems += _check_stamps(rec, topic)
    if is_recording and rec.has(layout.LEFT_IMAGE) and rec.has(layout.RIGHT_IMAGE):
        left, right = rec.log_times_ns(layout.LEFT_IMAGE), rec.log_times_ns(layout.RIGHT_IMAGE)
        if not np.array_equal(left, right):
            problems.append(f"left ({len(left)}) and right ({len(right)}) image stamps do not pair one to one")
    if rgbd and rec.has(layout.COLOR_IMAGE):
        depth, color = rec.log_times_ns(layout.DEPTH_IMAGE), rec.log_times_ns(layout.COLOR_IMAGE)
        if not np.array_equal(depth, color):
            problems.append(f"depth ({len(depth)}) and colour ({len(color)}) image stamps do not pair one to one")
    if is_recording and rec.num_frames and rec.has(layout.WRENCH):
        stats = sync_stats(rec.frame_times_ns, rec.force.times_ns)
        if stats.frames_without_force:
            problems.append(
                f"{stats.frames_without_force} frame(s) have no force sample within "
                f"{FORCE_GAP_TOLERANCE_NS / 1e6:.0f} ms"
            )
    return problems


def _check_stamps(rec: Recording, topic: str) -> list[str]:
    """Log times strictly increasing and equal to header.stamp."""
    problems = []
    times = rec.log_times_ns(topic)
    steps = np.diff(times)
    if (steps <= 0).any():
        problems.append(f"{topic}: {(steps <= 0).sum()} stamp(s) repeat or go backwards")
    mismatched = 0
    try:
        if topic in (layout.WRENCH, layout.ECM_POSE):
            stamps = rec.force.times_ns if topic == layout.WRENCH else rec.ecm_pose.times_ns
            mismatched = int((np.sort(stamps) != times).sum())
        else:
            for log_time, message in rec.messages(topic):
                if getattr(message, "stamp_ns", log_time) != log_time:
                    mismatched += 1
    except VisionForceError as exc:
        problems.append(exc.problem if hasattr(exc, "problem") else str(exc))
    if mismatched:
        problems.append(f"{topic}: {mismatched} message(s) with header.stamp != log time")
    return problems


def _check_data_crc(rec: Recording, block: int = 16 * 1024 * 1024) -> list[str]:
    """The data-section CRC of the DataEnd record, where the writer computed one."""
    mcap = rec._mcap
    end, expected = mcap.index.data_end_offset, mcap.index.data_section_crc
    if end is None and mcap.index.library.startswith("visionforce"):  # our writer always writes one
        return ["no DataEnd record before the summary"]
    if end is None or not expected:
        return []
    crc = 0
    for pos in range(0, end, block):
        crc = crc32(mcap.read_at(pos, min(block, end - pos)), crc)
    return [] if crc == expected else ["data section CRC mismatch (the header, metadata, message indexes or "
                                       "chunk records are damaged)"]
