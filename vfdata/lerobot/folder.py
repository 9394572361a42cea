"""A local LeRobot dataset folder: `meta/info.json` and where each episode's rows and videos are, for
the two layouts in use (docs/lerobot.md):

- v2.0 / v2.1: one Parquet file and one MP4 per camera per episode, `meta/episodes.jsonl`,
  `meta/tasks.jsonl` (and `meta/episodes_stats.jsonl` in v2.1);
- v3.0: many episodes per Parquet file and per MP4, `meta/episodes/chunk-*/file-*.parquet` rows
  giving each episode's files, its rows (`dataset_from_index`, `dataset_to_index`) and its span of
  each video (`videos/<key>/from_timestamp`, `to_timestamp`), `meta/tasks.parquet`.

Everything is checked as it is read; a problem is an InputError naming the file. Path templates of
info.json may name only their documented fields, and every path must stay inside the dataset folder:
a dataset is data and can neither run code nor make us read files elsewhere."""

from __future__ import annotations

import importlib.util
import json
import math
import string
from dataclasses import dataclass, field
from pathlib import Path

from vfdata.errors import InputError, VisionForceError

INFO = "meta/info.json"
V2_EPISODES = "meta/episodes.jsonl"
V2_TASKS = "meta/tasks.jsonl"
V2_EPISODES_STATS = "meta/episodes_stats.jsonl"
V3_EPISODES_DIR = "meta/episodes"
V3_TASKS = "meta/tasks.parquet"
V3_STATS = "meta/stats.json"

V2_DATA_PATH = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
V2_VIDEO_PATH = "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"
V3_DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
V3_VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
V3_EPISODES_PATH = V3_EPISODES_DIR + "/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
_TEMPLATE_FIELDS = {"v2": {"episode_chunk", "episode_index", "video_key"}, "v3": {"chunk_index", "file_index",
                                                                                  "video_key"}}

VERSIONS = ("v2.0", "v2.1", "v3.0")
# The columns every LeRobot dataset has besides its own features.
INDEX_FEATURES = ("timestamp", "frame_index", "episode_index", "index", "task_index")
_JSON_BYTES = 64 * 2**20  # a metadata file larger than this is not metadata


@dataclass(frozen=True)
class VideoSpan:
    """Where an episode's frames of one camera are: the MP4 and the episode's start in it (s)."""

    path: Path
    from_s: float = 0.0


@dataclass(frozen=True)
class Episode:
    index: int
    length: int  # frames
    data_file: Path
    videos: dict[str, VideoSpan]
    tasks: tuple[str, ...] = ()
    extra: dict = field(default_factory=dict)  # the episode record's other fields (ours: visionforce.*)


@dataclass(frozen=True)
class DatasetFolder:
    """A LeRobot dataset on disk: its info.json and its episodes, in index order."""

    root: Path
    version: str
    fps: float
    features: dict[str, dict]
    episodes: tuple[Episode, ...]
    splits: dict[str, str]
    robot_type: str | None = None

    @property
    def info_path(self) -> Path:
        return self.root / INFO

    @property
    def name(self) -> str:
        return self.root.resolve().name

    def episode(self, index: int) -> Episode:
        for episode in self.episodes:
            if episode.index == index:
                return episode
        have = _ranges([e.index for e in self.episodes])
        raise InputError(self.root, f"no episode {index} (the dataset has {have})")

    def split_of(self, index: int) -> str | None:
        """The episode's split from info.json `splits` ("train": "0:85", ...; `validation` read as val)."""
        for name, span in self.splits.items():
            start, stop = _split_range(span)
            if start is not None and start <= index < stop:
                return {"validation": "val"}.get(name, name)
        return None


def require_packages() -> None:
    """pyarrow and PyAV, the `lerobot` extra: a one-line error saying how to install them when absent."""
    missing = [name for name in ("pyarrow", "av") if importlib.util.find_spec(name) is None]
    if missing:
        raise VisionForceError(f"LeRobot datasets need {' and '.join(missing)}: pip install 'visionforce[lerobot]'")


def is_lerobot_dataset(path: str | Path) -> bool:
    """A folder with meta/info.json (what both layouts have)."""
    path = Path(path)
    return path.is_dir() and (path / INFO).is_file()


def read_dataset(root: str | Path) -> DatasetFolder:
    """The dataset at `root`, its metadata checked (not its data: see `columns` and `video`)."""
    root = Path(root)
    if not is_lerobot_dataset(root):
        raise InputError(root, f"not a LeRobot dataset folder (no {INFO})")
    require_packages()
    info_path = root / INFO
    info = read_json(info_path)
    if not isinstance(info, dict):
        raise InputError(info_path, "must be a JSON object")
    version = info.get("codebase_version")
    if version not in VERSIONS:
        raise InputError(info_path, f"codebase_version {version!r} is not one this reader knows "
                                    f"({', '.join(VERSIONS)})")
    fps = info.get("fps")
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not (math.isfinite(fps) and fps > 0):
        raise InputError(info_path, f"fps must be a positive number, not {fps!r}")
    features = _features(info_path, info.get("features"))
    family = "v3" if version == "v3.0" else "v2"
    data_path = _template(info_path, info, "data_path", family)
    video_keys = [k for k, f in features.items() if f["dtype"] == "video"]
    video_path = _template(info_path, info, "video_path", family) if video_keys else None
    chunks = info.get("chunks_size", 1000)
    if isinstance(chunks, bool) or not isinstance(chunks, int) or chunks <= 0:
        raise InputError(info_path, f"chunks_size must be a positive whole number, not {chunks!r}")
    splits = info.get("splits") or {}
    if not isinstance(splits, dict) or not all(isinstance(v, str) for v in splits.values()):
        raise InputError(info_path, "splits must map names to 'start:stop' episode ranges")
    if family == "v3":
        episodes = _v3_episodes(root, data_path, video_path, video_keys)
    else:
        episodes = _v2_episodes(root, data_path, video_path, video_keys, chunks)
    if not episodes:
        raise InputError(info_path, "the dataset has no episodes")
    robot = info.get("robot_type")
    return DatasetFolder(root, version, float(fps), features, episodes, dict(splits),
                         robot if isinstance(robot, str) else None)


# -- info.json ----------------------------------------------------------------------------------------
def read_json(path: Path):
    """A JSON file, refused when it is not UTF-8 JSON (or absurdly large for metadata)."""
    if not path.is_file():
        raise InputError(path, "not found")
    if path.stat().st_size > _JSON_BYTES:
        raise InputError(path, f"larger than {_JSON_BYTES // 2**20} MB: not a metadata file")
    try:
        return json.loads(path.read_bytes().decode("utf-8-sig"), parse_constant=_no_constant)
    except UnicodeDecodeError as exc:
        raise InputError(path, f"not UTF-8 text (byte {exc.start})") from None
    except (json.JSONDecodeError, ValueError) as exc:
        raise InputError(path, f"not valid JSON ({exc})") from None


def read_jsonl(path: Path) -> list[dict]:
    """A JSON-lines file: one object per non-empty line."""
    if not path.is_file():
        raise InputError(path, "not found")
    if path.stat().st_size > _JSON_BYTES:
        raise InputError(path, f"larger than {_JSON_BYTES // 2**20} MB: not a metadata file")
    try:
        lines = path.read_bytes().decode("utf-8-sig").splitlines()
    except UnicodeDecodeError as exc:
        raise InputError(path, f"not UTF-8 text (byte {exc.start})") from None
    records = []
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            record = json.loads(line, parse_constant=_no_constant)
        except (json.JSONDecodeError, ValueError) as exc:
            raise InputError(path, f"line {number}: not valid JSON ({exc})") from None
        if not isinstance(record, dict):
            raise InputError(path, f"line {number}: must be a JSON object")
        records.append(record)
    return records


def _no_constant(name: str):
    raise ValueError(f"{name} is not JSON")


def _features(path: Path, features) -> dict[str, dict]:
    if not isinstance(features, dict) or not features:
        raise InputError(path, "features must be a non-empty object")
    checked = {}
    for key, feature in features.items():
        if not isinstance(feature, dict) or not isinstance(feature.get("dtype"), str):
            raise InputError(path, f"feature '{key}' needs a dtype")
        shape = feature.get("shape")
        if not isinstance(shape, (list, tuple)) or not all(isinstance(n, int) and not isinstance(n, bool) and n > 0
                                                           for n in shape):
            raise InputError(path, f"feature '{key}': shape must be a list of positive whole numbers, not {shape!r}")
        checked[key] = {**feature, "shape": tuple(shape)}
    return checked


def _template(path: Path, info: dict, key: str, family: str) -> str:
    """A path template of info.json, allowed only the fields of its layout (so formatting it can do no
    more than put numbers and a feature name in a path)."""
    template = info.get(key)
    if not isinstance(template, str) or not template:
        raise InputError(path, f"{key} must be a path template such as "
                               f"{V3_DATA_PATH if family == 'v3' else V2_DATA_PATH}")
    try:
        fields = [name for _text, name, _spec, _conv in string.Formatter().parse(template) if name is not None]
    except ValueError as exc:
        raise InputError(path, f"{key} {template!r} is not a path template ({exc})") from None
    allowed = _TEMPLATE_FIELDS[family]
    bad = [name for name in fields if name not in allowed]
    if bad:
        raise InputError(path, f"{key} {template!r} names {bad[0]!r}; a {info['codebase_version']} template may name "
                               f"{', '.join(sorted(allowed))}")
    return template


def inside(root: Path, relative: str, what: Path) -> Path:
    """root / relative, refused (naming `what`) when it leaves the dataset folder."""
    path = root / relative
    if not path.resolve().is_relative_to(root.resolve()):
        raise InputError(what, f"path {relative!r} leaves the dataset folder")
    return path


# -- episodes ---------------------------------------------------------------------------------------
def _whole(record: dict, key: str, where: Path, what: str) -> int:
    value = record.get(key)
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise InputError(where, f"{what}: '{key}' must be a whole number >= 0, not {value!r}")
    return value


def _tasks(record: dict) -> tuple[str, ...]:
    tasks = record.get("tasks")
    return tuple(t for t in tasks if isinstance(t, str)) if isinstance(tasks, list) else ()


def _v2_episodes(root: Path, data_path: str, video_path: str | None, video_keys: list[str], chunks: int,
                 ) -> tuple[Episode, ...]:
    path = root / V2_EPISODES
    episodes = []
    for record in read_jsonl(path):
        index = _whole(record, "episode_index", path, "episode")
        what = f"episode {index}"
        length = _whole(record, "length", path, what)
        chunk = index // chunks
        data = inside(root, data_path.format(episode_chunk=chunk, episode_index=index), path)
        videos = {key: VideoSpan(inside(root, video_path.format(episode_chunk=chunk, episode_index=index,
                                                                video_key=key), path))
                  for key in video_keys}
        extra = {k: v for k, v in record.items() if k not in ("episode_index", "length", "tasks")}
        episodes.append(Episode(index, length, data, videos, _tasks(record), extra))
    return _unique(path, episodes)


def _v3_episodes(root: Path, data_path: str, video_path: str | None, video_keys: list[str]) -> tuple[Episode, ...]:
    from vfdata.lerobot.columns import read_records  # pyarrow: only for v3 metadata and the data itself

    folder = root / V3_EPISODES_DIR
    files = sorted(folder.glob("*/*.parquet")) if folder.is_dir() else []
    if not files:
        raise InputError(folder, "no episode metadata (meta/episodes/chunk-*/file-*.parquet)")
    episodes = []
    for path in files:
        for record in read_records(path, skip_prefix="stats/"):
            index = _whole(record, "episode_index", path, "episode")
            what = f"episode {index}"
            length = _whole(record, "length", path, what)
            data = inside(root, data_path.format(chunk_index=_whole(record, "data/chunk_index", path, what),
                                                 file_index=_whole(record, "data/file_index", path, what)), path)
            videos = {}
            for key in video_keys:
                prefix = f"videos/{key}/"
                start = record.get(prefix + "from_timestamp")
                if isinstance(start, bool) or not isinstance(start, (int, float)) or not (math.isfinite(start)
                                                                                         and start >= 0):
                    raise InputError(path, f"{what}: '{prefix}from_timestamp' must be seconds >= 0, not {start!r}")
                file = video_path.format(video_key=key, chunk_index=_whole(record, prefix + "chunk_index", path, what),
                                         file_index=_whole(record, prefix + "file_index", path, what))
                videos[key] = VideoSpan(inside(root, file, path), float(start))
            extra = {k: v for k, v in record.items() if k not in ("episode_index", "length", "tasks")
                     and not k.startswith(("videos/", "data/", "meta/"))}
            episodes.append(Episode(index, length, data, videos, _tasks(record), extra))
    return _unique(folder, episodes)


def _unique(path: Path, episodes: list[Episode]) -> tuple[Episode, ...]:
    indices = [e.index for e in episodes]
    if len(set(indices)) != len(indices):
        twice = next(i for i in indices if indices.count(i) > 1)
        raise InputError(path, f"episode {twice} is listed twice")
    return tuple(sorted(episodes, key=lambda e: e.index))


def _split_range(span: str) -> tuple[int | None, int | None]:
    start, sep, stop = span.partition(":")
    if not sep or not start.strip().isdigit() or not stop.strip().isdigit():
        return None, None
    return int(start), int(stop)


def _ranges(indices: list[int]) -> str:
    if not indices:
        return "no episodes"
    return f"episodes {indices[0]}..{indices[-1]}" if indices == list(range(indices[0], indices[-1] + 1)) \
        else f"episodes {', '.join(map(str, indices[:10]))}{', ...' if len(indices) > 10 else ''}"
