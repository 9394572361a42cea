"""Our recordings as LeRobot episodes: what the whole dataset shares (`plan`: frame rate, image size,
force window length, which features), and one recording's rows (`episode_columns`): per frame its
stamp, the force interpolated at it, the native force samples since the frame before, the ECM pose,
and the processed outputs (tracks, estimated force) when asked for."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vfdata.calibration import StereoCalibration
from vfdata.errors import InputError
from vfdata.force_coverage import default_force_gap_ns
from vfdata.lerobot import features as names
from vfdata.lerobot.windows import pack_windows, window_length
from vfdata.recording import Recording, layout
from vfdata.recording.derived import read_force_estimate, read_tracks
from vfdata.recording.messages import CameraInfo

RATE_SLACK = 0.01  # a recording's frame rate may differ this much (relative) from the whole fps LeRobot stores
SPLIT_ORDER = ("train", "val", "test")


@dataclass
class Source:
    """One recording to export, with the derived files asked for."""

    path: Path
    rec: Recording
    tracks: Path | None = None
    estimate: Path | None = None

    @property
    def split(self) -> str:
        return self.rec.metadata.split


@dataclass(frozen=True)
class Plan:
    """What every episode of the dataset shares."""

    fps: int
    width: int
    height: int
    window: int  # force samples a frame interval holds, at most
    pose: bool  # every recording has an ECM pose
    track_points: int | None  # tracks asked for: points per frame
    estimate: bool

    @property
    def period_ns(self) -> int:
        return round(1e9 / self.fps)


def frame_rate(rec: Recording) -> float:
    """Frames per second: 1 / the median frame interval."""
    steps = np.diff(rec.frame_times_ns)
    return 1e9 / float(np.median(steps)) if len(steps) else 0.0


def plan(sources: list[Source], fps: int | None = None) -> Plan:
    """The dataset's shared shape; InputError naming a recording that does not fit the others."""
    first = sources[0]
    for source in sources:
        if source.rec.is_rgbd:
            raise InputError(source.path, "an RGB-D recording: the LeRobot export writes stereo recordings (docs/"
                                          "lerobot.md)")
        if source.rec.num_frames < 2:
            raise InputError(source.path, f"{source.rec.num_frames} frame(s): an episode needs at least 2")
    rates = [frame_rate(s.rec) for s in sources]
    if fps is None:
        fps = round(rates[0])
        for source, rate in zip(sources, rates, strict=True):
            if abs(rate - fps) > RATE_SLACK * fps:
                raise InputError(source.path, f"frames come at {rate:.3f}/s and LeRobot stores a whole number of "
                                              f"frames per second ({fps}): give --fps N (the exact stamps are kept "
                                              f"in {names.STAMP})")
    if fps <= 0:
        raise InputError(first.path, f"--fps must be positive, not {fps}")
    camera = first.rec.camera
    window = 1
    for source in sources:
        size = (source.rec.camera.width, source.rec.camera.height)
        if size != (camera.width, camera.height):
            raise InputError(source.path, f"{size[0]}x{size[1]} images where {first.path.name} has "
                                          f"{camera.width}x{camera.height}: one dataset has one image size")
        force = source.rec.force
        window = max(window, window_length(source.rec.frame_times_ns, force.times_ns, round(1e9 / fps)))
    points = None
    if first.tracks is not None:
        counts = {s.path: read_tracks(s.tracks).points_object_mm.shape[1] for s in sources}
        if len(set(counts.values())) != 1:
            raise InputError(first.tracks, f"tracks of {len(set(counts.values()))} different point counts "
                                           f"({sorted(set(counts.values()))}): one dataset has one shape")
        points = next(iter(counts.values()))
    pose = all(s.rec.has(layout.ECM_POSE) for s in sources)
    return Plan(fps, camera.width, camera.height, window, pose, points, first.estimate is not None)


def ordered(sources: list[Source]) -> list[Source]:
    """Episodes in split order (train, val, test, others; each in the order given): LeRobot's info.json
    gives a split as one range of episodes."""
    rank = {name: i for i, name in enumerate(SPLIT_ORDER)}
    return sorted(sources, key=lambda s: rank.get(s.split, len(SPLIT_ORDER)))


def split_ranges(sources: list[Source]) -> dict[str, str]:
    """info.json `splits` of episodes in `ordered` order: {"train": "0:2", "val": "2:3", ...};
    recordings without a split are `unassigned` (all `train` when none has one)."""
    if not any(s.split in SPLIT_ORDER for s in sources):
        return {"train": f"0:{len(sources)}"}
    spans: dict[str, list[int]] = {}
    for i, source in enumerate(sources):
        spans.setdefault(source.split if source.split in SPLIT_ORDER else "unassigned", []).append(i)
    return {name: f"{ix[0]}:{ix[-1] + 1}" for name, ix in spans.items()}


def episode_columns(source: Source, shared: Plan) -> dict[str, np.ndarray]:
    """The feature columns of one recording (frames, *shape), ours only (not the images, not LeRobot's
    index columns)."""
    rec, path = source.rec, source.path
    frame_ns = rec.frame_times_ns.astype(np.int64)
    force = rec.force
    at_frames = rec.force_at(frame_ns, max_gap_ns=default_force_gap_ns(force.times_ns))
    missing = ~np.isfinite(at_frames).all(axis=1)
    if missing.any():
        raise InputError(path, f"frame {int(np.argmax(missing))}: no force around its stamp (the force stream has a "
                               "gap or ends there)")
    samples, stamps, counts = pack_windows(frame_ns, force.times_ns, force.wrench, shared.period_ns, shared.window)
    columns = {names.STAMP: frame_ns.reshape(-1, 1), names.FORCE: at_frames.astype(np.float32),
               names.SAMPLES: samples, names.SAMPLE_STAMPS: stamps, names.SAMPLE_COUNT: counts.reshape(-1, 1)}
    if shared.pose:
        position, quat = rec.ecm_pose_at(frame_ns)
        pose = np.hstack([position, quat])
        bad = ~np.isfinite(pose).all(axis=1)
        if bad.any():
            raise InputError(path, f"frame {int(np.argmax(bad))}: no ECM pose around its stamp")
        columns[names.STATE] = pose.astype(np.float32)
    if shared.track_points is not None:
        columns.update(_tracks(source, frame_ns))
    if shared.estimate:
        columns[names.FORCE_ESTIMATE] = _estimate(source, frame_ns)
    return columns


def _tracks(source: Source, frame_ns: np.ndarray) -> dict[str, np.ndarray]:
    tracks = read_tracks(source.tracks)
    at = np.searchsorted(tracks.times_ns, frame_ns)
    found = (at < len(tracks.times_ns)) & (tracks.times_ns[np.minimum(at, len(tracks.times_ns) - 1)] == frame_ns)
    if not found.all():
        raise InputError(source.tracks, f"tracks cover {int(found.sum())} of the {len(frame_ns)} frames of "
                                        f"{source.path.name} (process it whole)")
    return {names.TRACKS: tracks.points_object_mm[at].astype(np.float32), names.TRACKS_VISIBLE: tracks.visible[at]}


def _estimate(source: Source, frame_ns: np.ndarray) -> np.ndarray:
    """The estimated force (N, object frame) at each frame; NaN on frames the model gave none for."""
    times, force = read_force_estimate(source.estimate)
    out = np.full((len(frame_ns), 3), np.nan, dtype=np.float32)
    at = np.searchsorted(times, frame_ns)
    ok = (at < len(times)) & (times[np.minimum(at, len(times) - 1)] == frame_ns)
    out[ok] = force[at[ok]]
    if not ok.any():
        raise InputError(source.estimate, f"no estimate stamped like a frame of {source.path.name}")
    return out


def calibration_of(rec: Recording) -> StereoCalibration:
    """The raw stereo calibration a recording's camera infos describe: K and D of each view from the
    infos, and R, T from the rectification (R = R2^T R1; T = R2^T (-baseline, 0, 0) in mm)."""
    left, right = rec.camera_infos
    return calibration_from_infos(left, right)


def calibration_from_infos(left: CameraInfo, right: CameraInfo) -> StereoCalibration:
    r1, r2 = (np.asarray(i.r, dtype=np.float64).reshape(3, 3) for i in (left, right))
    p2 = np.asarray(right.p, dtype=np.float64).reshape(3, 4)
    baseline_mm = -p2[0, 3] / p2[0, 0] * 1000.0
    rotation = r2.T @ r1
    translation = r2.T @ np.array([-baseline_mm, 0.0, 0.0])
    return StereoCalibration(int(left.width), int(left.height), np.asarray(left.k, dtype=np.float64).reshape(3, 3),
                             _distortion(left), np.asarray(right.k, dtype=np.float64).reshape(3, 3), _distortion(right),
                             rotation, translation)


def _distortion(info: CameraInfo) -> np.ndarray:
    return np.asarray(info.d, dtype=np.float64)
