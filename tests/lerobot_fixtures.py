"""Small LeRobot datasets written by the tests themselves, in the documented layouts (v2.1: a file per
episode; v3.0: episodes sharing one Parquet file and one MP4 per camera, found through
meta/episodes), with PyAV and pyarrow directly (not through vfdata's writers)."""

from __future__ import annotations

import json
from fractions import Fraction
from pathlib import Path

import av
import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from vfdata.calibration import StereoCalibration

FPS = 30
WIDTH, HEIGHT = 64, 48


def calibration(width: int = WIDTH, height: int = HEIGHT) -> StereoCalibration:
    K = np.array([[60.0, 0, width / 2], [0, 60.0, height / 2], [0, 0, 1]])
    return StereoCalibration(width, height, K, np.zeros(5), K.copy(), np.zeros(5), np.eye(3), np.array([-4.6, 0, 0]))


def level(episode: int, frame: int) -> int:
    """The grey level of frame `frame` of `episode` (up to 3 episodes of 8 frames): tells frames apart
    after lossy video coding."""
    return 20 + 80 * episode + 10 * frame


def image(episode: int, frame: int, side: int = 0) -> np.ndarray:
    """Grey at `level`, with a red band on the left quarter (side 0, the left view) or the right one."""
    bgr = np.full((HEIGHT, WIDTH, 3), level(episode, frame), np.uint8)
    band = slice(0, WIDTH // 4) if side == 0 else slice(WIDTH - WIDTH // 4, WIDTH)
    bgr[:, band, 2] = 255
    return bgr


def force(episode: int, frames: int) -> np.ndarray:
    k = np.arange(frames)[:, None]
    return (np.sin(0.3 * k + np.arange(6)[None, :] + episode) * [1, 2, 3, 0.01, 0.02, 0.03]).astype(np.float32)


def _list(values: np.ndarray) -> pa.Array:
    return pa.FixedSizeListArray.from_arrays(pa.array(values.reshape(-1)), values.shape[1])


def write_mp4(path: Path, images: list[np.ndarray]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=FPS, options={"crf": "10", "g": "2"})
        stream.width, stream.height, stream.pix_fmt = WIDTH, HEIGHT, "yuv420p"
        for k, bgr in enumerate(images):
            frame = av.VideoFrame.from_ndarray(bgr, format="bgr24")
            frame.pts, frame.time_base = k, Fraction(1, FPS)
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)


def write_dataset(root: Path, version: str = "v3.0", episodes: int = 2, frames: int = 8,
                  views: tuple[str, str] = ("observation.images.left", "observation.images.right"),
                  force_key: str = "observation.meta.force_torque", force_names: list[str] | None = None,
                  state: bool = True, splits: dict | None = None, calibrate: bool = True,
                  extra_views: tuple[str, ...] = (), depth: str | None = None) -> Path:
    """A stereo dataset (or, with `depth` "image" or "array", colour + depth: `views[0]` the colour
    video, `observation.images.depth` the depth in mm); force fx..tz at the frame rate; the state an ECM
    pose x y z qx qy qz qw."""
    force_names = force_names or ["fx", "fy", "fz", "tx", "ty", "tz"]
    video = {"dtype": "video", "shape": [HEIGHT, WIDTH, 3], "names": ["height", "width", "channels"]}
    cameras = list(views if depth is None else views[:1]) + list(extra_views)
    features = {key: dict(video) for key in cameras}
    if depth == "image":
        features["observation.images.depth"] = {"dtype": "image", "shape": [HEIGHT, WIDTH, 1], "names": None}
    elif depth == "array":
        features["observation.images.depth"] = {"dtype": "uint16", "shape": [HEIGHT, WIDTH], "names": None}
    features[force_key] = {"dtype": "float32", "shape": [len(force_names)], "names": force_names,
                           "info": {"sensor": "wrist_ft", "units": "N + N m"}}
    if state:
        features["observation.state"] = {"dtype": "float32", "shape": [7],
                                         "names": ["x", "y", "z", "qx", "qy", "qz", "qw"]}
    for name, dtype in (("timestamp", "float32"), ("frame_index", "int64"), ("episode_index", "int64"),
                        ("index", "int64"), ("task_index", "int64")):
        features[name] = {"dtype": dtype, "shape": [1], "names": None}
    v3 = version == "v3.0"
    info = {"codebase_version": version, "robot_type": "dvrk", "total_episodes": episodes,
            "total_frames": episodes * frames, "total_tasks": 1, "chunks_size": 1000, "fps": FPS,
            "splits": splits or {"train": f"0:{episodes}"},
            "data_path": ("data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet" if v3
                          else "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"),
            "video_path": ("videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4" if v3
                           else "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"),
            "features": features}
    (root / "meta").mkdir(parents=True, exist_ok=True)
    (root / "meta" / "info.json").write_text(json.dumps(info, indent=2))
    tables, videos = [], {key: [] for key in cameras}
    for e in range(episodes):
        columns = {}
        for key in cameras:
            side = 1 if key in views[1:] else 0
            videos[key].append([image(e, k, side) for k in range(frames)])
        if depth == "image":
            columns["observation.images.depth"] = pa.array(
                [{"bytes": cv2.imencode(".png", np.full((HEIGHT, WIDTH), 500 + 10 * k, np.uint16))[1].tobytes(),
                  "path": None} for k in range(frames)],
                pa.struct([("bytes", pa.binary()), ("path", pa.string())]))
        elif depth == "array":
            depth_mm = np.stack([np.full((HEIGHT, WIDTH), 500 + 10 * k, np.uint16) for k in range(frames)])
            columns["observation.images.depth"] = pa.FixedSizeListArray.from_arrays(
                _list(depth_mm.reshape(frames * HEIGHT, WIDTH)), HEIGHT)
        columns[force_key] = _list(force(e, frames)[:, : len(force_names)])
        if state:
            pose = np.zeros((frames, 7), np.float32)
            pose[:, 2], pose[:, 6] = 0.1 + 0.001 * np.arange(frames), 1.0
            columns["observation.state"] = _list(pose)
        columns.update({"timestamp": pa.array((np.arange(frames) / FPS).astype(np.float32)),
                        "frame_index": pa.array(np.arange(frames)), "episode_index": pa.array(np.full(frames, e)),
                        "index": pa.array(e * frames + np.arange(frames)), "task_index": pa.array(np.zeros(frames,
                                                                                                          np.int64))})
        tables.append(pa.table(columns))
    if v3:
        (root / "data" / "chunk-000").mkdir(parents=True)
        pq.write_table(pa.concat_tables(tables), root / "data" / "chunk-000" / "file-000.parquet")
        for key, clips in videos.items():
            write_mp4(root / "videos" / key / "chunk-000" / "file-000.mp4", [im for clip in clips for im in clip])
        records = []
        for e in range(episodes):
            record = {"episode_index": e, "tasks": ["press"], "length": frames, "data/chunk_index": 0,
                      "data/file_index": 0, "dataset_from_index": e * frames, "dataset_to_index": (e + 1) * frames}
            for key in cameras:
                record.update({f"videos/{key}/chunk_index": 0, f"videos/{key}/file_index": 0,
                               f"videos/{key}/from_timestamp": e * frames / FPS,
                               f"videos/{key}/to_timestamp": (e + 1) * frames / FPS})
            records.append(record)
        (root / "meta" / "episodes" / "chunk-000").mkdir(parents=True)
        pq.write_table(pa.Table.from_pylist(records), root / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    else:
        (root / "data" / "chunk-000").mkdir(parents=True)
        for e, table in enumerate(tables):
            pq.write_table(table, root / "data" / "chunk-000" / f"episode_{e:06d}.parquet")
            for key in cameras:
                write_mp4(root / "videos" / "chunk-000" / key / f"episode_{e:06d}.mp4", videos[key][e])
        (root / "meta" / "episodes.jsonl").write_text("".join(
            json.dumps({"episode_index": e, "tasks": ["press"], "length": frames}) + "\n" for e in range(episodes)))
        (root / "meta" / "tasks.jsonl").write_text(json.dumps({"task_index": 0, "task": "press"}) + "\n")
    if calibrate and depth is None:
        calibration().save(root / "meta" / "calibration.yaml")
    if calibrate and depth is not None:
        camera = {"width": WIDTH, "height": HEIGHT, "fx": 60.0, "fy": 60.0, "cx": 32.0, "cy": 24.0}
        (root / "meta" / "rgbd_calibration.yaml").write_text(json.dumps({"depth": camera, "color": camera}))
    return root
