"""Our recordings -> a LeRobot dataset (`vfdata export --lerobot RECORDINGS... OUT`; docs/lerobot.md).

One recording is one episode. The stereo views become MP4 videos, the force the Open-H feature
`observation.meta.force_torque` at each frame plus every native sample in per-frame windows, the ECM
pose `observation.state`, each frame's exact stamp `observation.meta.stamp_ns`, and, when asked for,
the tracks of `vfdata process` and the force `vfdata predict` estimated. meta/ holds the camera
calibration (`calibration.yaml`, the raw folder's format), each recording's metadata record in its
episode record, statistics, and the dataset card (README.md, Open-H's template).

The output folder is written whole or not at all (a temporary folder beside it, renamed at the
end); recordings are only read."""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from vfdata.atomic import atomic_output, check_output
from vfdata.errors import InputError
from vfdata.lerobot import features as names
from vfdata.lerobot.card import dataset_card
from vfdata.lerobot.episodes import Plan, Source, calibration_of, episode_columns, ordered, plan, split_ranges
from vfdata.lerobot.folder import require_packages
from vfdata.lerobot.stats import aggregate, feature_stats, image_sample, image_stats, reduced
from vfdata.lerobot.video import PIX_FMT
from vfdata.recording import Recording

VERSIONS = ("v3.0", "v2.1")
DEFAULT_TASK = "tissue manipulation under a stereo endoscope, with a force/torque sensor"


@dataclass(frozen=True)
class ExportOptions:
    version: str = "v3.0"
    codec: str = "av1"  # or h264
    crf: int | None = None  # the codec's default (`video.DEFAULT_CRF`)
    gop: int = 2
    fps: int | None = None  # default: the recordings' frame rate, rounded
    task: str = DEFAULT_TASK
    robot_type: str = "dvrk"
    tracks: str | None = None  # suffix of the derived files whose tracks to add, e.g. ".processed.mcap"
    estimate: str | None = None  # suffix of the force files whose estimate to add, e.g. ".force.mcap"
    license: str | None = None
    progress: bool = True


def export_lerobot(recordings: list[str | Path], out: str | Path, overwrite: bool = False,
                   options: ExportOptions | None = None) -> Path:
    """Write the recordings as a LeRobot dataset folder `out`. Returns `out`."""
    options = options or ExportOptions()
    require_packages()
    if options.version not in VERSIONS:
        raise InputError("--version", f"LeRobot format {options.version!r}: choose {' or '.join(VERSIONS)}")
    out = Path(out)
    paths = [Path(p) for p in recordings]
    if not paths:
        raise InputError(out, "no recordings to export")
    if len({p.resolve() for p in paths}) != len(paths):
        raise InputError(paths[0], "a recording is given twice")
    derived = _derived(paths, options)
    inputs = [*paths, *(p for pair in derived for p in pair if p is not None)]
    check_output(out, overwrite, inputs=inputs)
    sources = []
    try:
        for path, (tracks, estimate) in zip(paths, derived, strict=True):
            sources.append(Source(path, Recording.open(path), tracks, estimate))
        sources = ordered(sources)
        shared = plan(sources, options.fps)
        with atomic_output(out, overwrite, inputs=inputs) as tmp:
            tmp.mkdir()
            _write(tmp, sources, shared, options, out.name)
    finally:
        for source in sources:
            source.rec.close()
    return out


def _derived(paths: list[Path], options: ExportOptions) -> list[tuple[Path | None, Path | None]]:
    """Each recording's derived file (tracks) and force file (estimate), when asked for; they must exist."""
    pairs = []
    for path in paths:
        stem = path.name.removesuffix(".mcap")
        pair = []
        for suffix, what in ((options.tracks, "tracks (vfdata process)"), (options.estimate, "estimate (vfdata "
                                                                                           "predict)")):
            found = path.with_name(stem + suffix) if suffix else None
            if found is not None and not found.is_file():
                raise InputError(found, f"not found: the {what} of {path.name}")
            pair.append(found)
        pairs.append((pair[0], pair[1]))
    return pairs


def feature_set(shared: Plan, sources: list[Source], options: ExportOptions) -> dict[str, dict]:
    """info.json `features` of the export (ours, then LeRobot's index columns)."""
    video = {"dtype": "video", "shape": [shared.height, shared.width, 3], "names": ["height", "width", "channels"],
             "info": {"video.height": shared.height, "video.width": shared.width, "video.codec": options.codec,
                      "video.pix_fmt": PIX_FMT, "video.is_depth_map": False, "video.fps": shared.fps,
                      "video.channels": 3, "has_audio": False}}
    frame_ids = {s.rec.force.frame_id for s in sources}
    force_info = {"units": names.FORCE_UNITS, **({"sensor": frame_ids.pop()} if len(frame_ids) == 1 else {})}
    fts = list(names.FORCE_NAMES)
    features = {
        names.LEFT: video, names.RIGHT: copy.deepcopy(video),
        names.FORCE: {"dtype": "float32", "shape": [6], "names": fts, "info": force_info},
        names.SAMPLES: {"dtype": "float64", "shape": [shared.window, 6], "names": None,
                        "info": {"rows": "samples since the previous frame, oldest first", "columns": fts,
                                 "units": names.FORCE_UNITS}},
        names.SAMPLE_STAMPS: {"dtype": "int64", "shape": [shared.window], "names": None,
                              "info": {"units": "ns since the epoch"}},
        names.SAMPLE_COUNT: {"dtype": "int64", "shape": [1], "names": None},
        names.STAMP: {"dtype": "int64", "shape": [1], "names": None},
    }
    if shared.pose:
        features[names.STATE] = {"dtype": "float32", "shape": [7], "names": list(names.STATE_NAMES),
                                 "info": {"frame": "ECM camera pose in the world frame", "units": "m"}}
    if shared.track_points is not None:
        n = shared.track_points
        features[names.TRACKS] = {"dtype": "float32", "shape": [n, 3], "names": None,
                                  "info": {"columns": ["x", "y", "z"], "frame": "tissue_object", "units": "mm"}}
        features[names.TRACKS_VISIBLE] = {"dtype": "bool", "shape": [n], "names": None}
    if shared.estimate:
        features[names.FORCE_ESTIMATE] = {"dtype": "float32", "shape": [3], "names": ["fx", "fy", "fz"],
                                          "info": {"frame": "tissue_object", "units": "N"}}
    index = {"timestamp": "float32", "frame_index": "int64", "episode_index": "int64", "index": "int64",
             "task_index": "int64"}
    features.update({name: {"dtype": dtype, "shape": [1], "names": None} for name, dtype in index.items()})
    return features


def _write(root: Path, sources: list[Source], shared: Plan, options: ExportOptions, name: str) -> None:
    from vfdata.lerobot.writers import V3Files, V21Files  # pyarrow and PyAV: only with the extra installed

    features = feature_set(shared, sources, options)
    shapes = {key: tuple(f["shape"]) for key, f in features.items()}
    views = (names.LEFT, names.RIGHT)
    files = (V3Files if options.version == "v3.0" else V21Files)(root, shared.fps, (shared.width, shared.height),
                                                                 options.codec, options.crf, options.gop)
    total = sum(s.rec.num_frames for s in sources)
    per_feature: dict[str, list[dict]] = {}
    rows = 0
    try:
        with tqdm(total=total, desc=f"export {name}", unit="frame", disable=not options.progress) as bar:
            for episode, source in enumerate(sources):
                columns = episode_columns(source, shared)
                frames = source.rec.num_frames
                columns.update({
                    "timestamp": (np.arange(frames) / shared.fps).astype(np.float32).reshape(-1, 1),
                    "frame_index": np.arange(frames, dtype=np.int64).reshape(-1, 1),
                    "episode_index": np.full((frames, 1), episode, dtype=np.int64),
                    "index": np.arange(rows, rows + frames, dtype=np.int64).reshape(-1, 1),
                    "task_index": np.zeros((frames, 1), dtype=np.int64)})
                columns = {key: columns[key] for key in features if key in columns}  # info.json's order
                sampled = _write_videos(files, episode, source, views, bar)
                stats = {key: feature_stats(values) for key, values in columns.items()}
                stats.update({key: image_stats(np.stack(sampled[key])) for key in views})
                for key, value in stats.items():
                    per_feature.setdefault(key, []).append(value)
                record = {names.RECORDING_KEY: json.dumps(source.rec.metadata.to_record(), sort_keys=True)}
                files.finish_episode(episode, columns, shapes, stats, [options.task], record)
                rows += frames
    except BaseException:
        files.close_files()
        raise
    info = {"codebase_version": files.version, "robot_type": options.robot_type, "total_episodes": len(sources),
            "total_frames": rows, "total_tasks": 1, "chunks_size": 1000, "fps": shared.fps,
            "splits": split_ranges(sources), "data_path": files.data_path, "video_path": files.video_path,
            "features": features}
    files.finish(info, [options.task], {key: aggregate(values) for key, values in per_feature.items()})
    _write_calibration(root, sources)
    card = dataset_card(name, info, [_summary(s) for s in sources], _sensor_rate(sources), options.task,
                        options.license)
    (root / "README.md").write_text(card, encoding="utf-8")
    (root / "meta" / "README.md").write_text(card, encoding="utf-8")  # Open-H asks for it in the metadata folder


def _write_videos(files, episode: int, source: Source, views: tuple[str, str], bar) -> dict[str, list[np.ndarray]]:
    """Every frame of the recording into the cameras' MP4s; returns the reduced RGB frames statistics use."""
    files.start(episode, list(views))
    keep = set(image_sample(source.rec.num_frames).tolist())
    sampled: dict[str, list[np.ndarray]] = {key: [] for key in views}
    for i in range(source.rec.num_frames):
        frame = source.rec.frame(i)
        for key, image in zip(views, (frame.left, frame.right), strict=True):
            files.video(key).write(image)
            if i in keep:
                sampled[key].append(reduced(image[..., ::-1]))
        bar.update()
    return sampled


def _write_calibration(root: Path, sources: list[Source]) -> None:
    """meta/calibration.yaml when every recording has one calibration, else one file per episode
    (meta/calibration/episode_NNNNNN.yaml): the raw folder's format, which `vfdata convert` reads back."""
    calibrations = [calibration_of(s.rec) for s in sources]
    first = calibrations[0]
    same = all(_same(first, c) for c in calibrations[1:])
    if same:
        first.save(root / "meta" / "calibration.yaml")
        return
    (root / "meta" / "calibration").mkdir(parents=True, exist_ok=True)
    for episode, calib in enumerate(calibrations):
        calib.save(root / "meta" / "calibration" / f"episode_{episode:06d}.yaml")


def _same(a, b) -> bool:
    return (a.width, a.height) == (b.width, b.height) and all(
        np.shape(x) == np.shape(y) and np.array_equal(x, y)
        for x, y in ((a.K1, b.K1), (a.D1, b.D1), (a.K2, b.K2), (a.D2, b.D2), (a.R, b.R), (a.T, b.T)))


def _summary(source: Source) -> dict:
    meta = source.rec.metadata
    return {"id": meta.recording_id, "split": meta.split, "study": meta.study, "tissue": meta.tissue,
            "orientation_deg": meta.orientation_deg, "frames": source.rec.num_frames,
            "synthetic": meta.extra.get("synthetic") == "true"}


def _sensor_rate(sources: list[Source]) -> float:
    steps = np.concatenate([np.diff(s.rec.force.times_ns) for s in sources])
    return 1e9 / float(np.median(steps)) if len(steps) else 0.0
