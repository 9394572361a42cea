"""Where an export puts episodes, for each layout (docs/lerobot.md, "The two layouts"):

- `V3Files` (codebase v3.0): the episodes follow one another in `data/chunk-000/file-000.parquet` and,
  per camera, `videos/<key>/chunk-000/file-000.mp4`, a new file once one passes its size
  (`data_files_size_in_mb`, `video_files_size_in_mb`); `meta/episodes/chunk-000/file-000.parquet`
  says where each episode is; `meta/tasks.parquet`, `meta/stats.json`.
- `V21Files` (codebase v2.1, Open-H's pinned LeRobot 0.3.3): one Parquet file and one MP4 per camera
  per episode, `meta/episodes.jsonl`, `meta/tasks.jsonl`, `meta/episodes_stats.jsonl`.

Both take an episode as: `start(index)`, its frames per camera (`video(key).write`), `finish_episode`
with its columns and statistics; then `finish` writes the metadata."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from vfdata.lerobot import folder
from vfdata.lerobot.columns import to_arrow, write_table
from vfdata.lerobot.stats import to_json
from vfdata.lerobot.video import Mp4Writer

CHUNK_SIZE = 1000  # files per chunk folder (LeRobot's default)
DATA_FILE_MB = 100
VIDEO_FILE_MB = 200
_MB = 2**20


class _Files:
    def __init__(self, root: Path, fps: int, frame_size: tuple[int, int], codec: str, crf: int | None, gop: int):
        self.root, self.fps, self.size, self.codec, self.crf, self.gop = root, fps, frame_size, codec, crf, gop
        self.records: list[dict] = []
        self.episode_stats: list[dict] = []

    def _mp4(self, path: Path) -> Mp4Writer:
        path.parent.mkdir(parents=True, exist_ok=True)
        return Mp4Writer(path, self.fps, *self.size, codec=self.codec, crf=self.crf, gop=self.gop)


def _stats_record(stats: dict[str, dict[str, np.ndarray]]) -> dict:
    return {f"stats/{feature}/{name}": np.asarray(value).tolist() for feature, values in stats.items()
            for name, value in values.items()}


class V3Files(_Files):
    version = "v3.0"
    data_path, video_path = folder.V3_DATA_PATH, folder.V3_VIDEO_PATH

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.data_file = (0, 0)
        self.data_writer: pq.ParquetWriter | None = None
        self.data_bytes = 0
        self.rows = 0
        self.videos: dict[str, tuple[Mp4Writer, tuple[int, int]]] = {}
        self.starts: dict[str, float] = {}

    def start(self, index: int, video_keys: list[str]) -> None:
        """An episode begins: every camera's MP4 continues, or a new one starts past the size limit."""
        for key in video_keys:
            writer, where = self.videos.get(key, (None, (0, -1)))
            if writer is None or writer.bytes >= VIDEO_FILE_MB * _MB:
                if writer is not None:
                    writer.close()
                where = _next_file(where)
                path = self.root / self.video_path.format(video_key=key, chunk_index=where[0], file_index=where[1])
                writer = self._mp4(path)
                self.videos[key] = (writer, where)
            self.starts[key] = writer.seconds

    def video(self, key: str) -> Mp4Writer:
        return self.videos[key][0]

    def finish_episode(self, index: int, columns: dict[str, np.ndarray], shapes: dict[str, tuple[int, ...]],
                       stats: dict, tasks: list[str], extra: dict) -> None:
        frames = len(columns["frame_index"])
        if self.data_writer is not None and self.data_bytes >= DATA_FILE_MB * _MB:
            self.data_writer.close()
            self.data_writer, self.data_bytes = None, 0
            self.data_file = _next_file(self.data_file)
        table = pa.table({name: to_arrow(values, shapes[name]) for name, values in columns.items()})
        if self.data_writer is None:
            path = self.root / self.data_path.format(chunk_index=self.data_file[0], file_index=self.data_file[1])
            path.parent.mkdir(parents=True, exist_ok=True)
            self.data_writer = pq.ParquetWriter(path, table.schema, compression="snappy")
        self.data_writer.write_table(table)
        self.data_bytes += table.nbytes
        record = {"episode_index": index, "tasks": tasks, "length": frames,
                  "data/chunk_index": self.data_file[0], "data/file_index": self.data_file[1],
                  "dataset_from_index": self.rows, "dataset_to_index": self.rows + frames}
        for key, (writer, (chunk, file)) in self.videos.items():
            record.update({f"videos/{key}/chunk_index": chunk, f"videos/{key}/file_index": file,
                           f"videos/{key}/from_timestamp": self.starts[key],
                           f"videos/{key}/to_timestamp": writer.seconds})
        record.update(_stats_record(stats))
        record.update({"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0, **extra})
        self.records.append(record)
        self.episode_stats.append(stats)
        self.rows += frames

    def close_files(self) -> None:
        for writer, _where in self.videos.values():
            writer.close()
        if self.data_writer is not None:
            self.data_writer.close()

    def finish(self, info: dict, tasks: list[str], stats: dict) -> None:
        self.close_files()
        write_table(self.root / folder.V3_EPISODES_PATH.format(chunk_index=0, file_index=0),
                    {k: pa.array([r[k] for r in self.records]) for k in self.records[0]})
        _write_tasks_parquet(self.root / folder.V3_TASKS, tasks)
        _write_json(self.root / folder.V3_STATS, to_json(stats))
        _write_json(self.root / folder.INFO, {**info, "data_files_size_in_mb": DATA_FILE_MB,
                                              "video_files_size_in_mb": VIDEO_FILE_MB})


class V21Files(_Files):
    version = "v2.1"
    data_path, video_path = folder.V2_DATA_PATH, folder.V2_VIDEO_PATH

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.videos: dict[str, Mp4Writer] = {}

    def start(self, index: int, video_keys: list[str]) -> None:
        chunk = index // CHUNK_SIZE
        self.videos = {key: self._mp4(self.root / self.video_path.format(episode_chunk=chunk, video_key=key,
                                                                         episode_index=index))
                       for key in video_keys}

    def video(self, key: str) -> Mp4Writer:
        return self.videos[key]

    def finish_episode(self, index: int, columns: dict[str, np.ndarray], shapes: dict[str, tuple[int, ...]],
                       stats: dict, tasks: list[str], extra: dict) -> None:
        self.close_files()
        path = self.root / self.data_path.format(episode_chunk=index // CHUNK_SIZE, episode_index=index)
        write_table(path, {name: to_arrow(values, shapes[name]) for name, values in columns.items()})
        self.records.append({"episode_index": index, "tasks": tasks, "length": len(columns["frame_index"]), **extra})
        self.episode_stats.append({"episode_index": index, "stats": to_json(stats)})

    def close_files(self) -> None:
        for writer in self.videos.values():
            writer.close()
        self.videos = {}

    def finish(self, info: dict, tasks: list[str], stats: dict) -> None:
        self.close_files()
        episodes = len(self.records)
        _write_jsonl(self.root / folder.V2_EPISODES, self.records)
        _write_jsonl(self.root / folder.V2_TASKS, [{"task_index": i, "task": t} for i, t in enumerate(tasks)])
        _write_jsonl(self.root / folder.V2_EPISODES_STATS, self.episode_stats)
        videos = sum(1 for f in info["features"].values() if f["dtype"] == "video")
        _write_json(self.root / folder.INFO, {**info, "total_videos": videos * episodes,
                                              "total_chunks": (episodes - 1) // CHUNK_SIZE + 1})


def _next_file(where: tuple[int, int]) -> tuple[int, int]:
    chunk, file = where
    return (chunk + 1, 0) if file + 1 == CHUNK_SIZE else (chunk, file + 1)


def _write_json(path: Path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=4, ensure_ascii=False, allow_nan=False) + "\n", encoding="utf-8")


def _write_jsonl(path: Path, records: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(json.dumps(r, ensure_ascii=False, allow_nan=False) + "\n" for r in records),
                    encoding="utf-8")


def _write_tasks_parquet(path: Path, tasks: list[str]) -> None:
    """meta/tasks.parquet as LeRobot (through pandas) writes it: `task_index`, and the task text as
    the frame's index (pandas' own Parquet metadata says so, so that pandas.read_parquet restores it)."""
    pandas_meta = {
        "index_columns": ["__index_level_0__"],
        "column_indexes": [{"name": None, "field_name": None, "pandas_type": "unicode", "numpy_type": "object",
                            "metadata": {"encoding": "UTF-8"}}],
        "columns": [{"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64",
                     "metadata": None},
                    {"name": None, "field_name": "__index_level_0__", "pandas_type": "unicode", "numpy_type": "object",
                     "metadata": None}],
        "attributes": {}, "creator": {"library": "pyarrow", "version": pa.__version__}, "pandas_version": "2.2.0",
    }
    write_table(path, {"task_index": pa.array(np.arange(len(tasks), dtype=np.int64)),
                       "__index_level_0__": pa.array(tasks, pa.string())},
                metadata={b"pandas": json.dumps(pandas_meta).encode()})
