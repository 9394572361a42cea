"""Bag conversion rate against bare JPEG encoding of the same frames.

Writes bags of raw bgr8 640x512 stereo frames at 30 Hz with a WrenchStamped stream (1 kHz by
default) and dVRK topic names, one per kind asked for (ROS 1; ROS 2 in sqlite3, MCAP or zstd MCAP
storage), then measures, with the same number of threads:
  - bare: cv2.imencode (JPEG, quality 95) of every left and right frame, already in memory;
  - convert: `convert_bag` end to end (open, scan, pairing, reading, decoding, encoding, MCAP).
Runs alternate (bare, each bag, bare, each bag, ...) so all see the same load; prints every run,
the median rates and CPU times, and each bag's ratios to bare (target >= 0.7). Compare bags within
one invocation: on a machine shared with other jobs, figures move by 0.1 between invocations. The
CPU-time ratio is the steadier figure; with as many threads as cores, the wall ratio tends to it.

    python bench/bench_bags.py [--bags ros1 sqlite3 mcap mcap-zstd] [--frames 200] [--workers 2]
                               [--convert-workers N] [--force-hz 1000] [--pose-hz 0] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from vfdata.conversion.bags import convert_bag
from vfdata.conversion.raw_folder import ConvertOptions

WIDTH, HEIGHT = 640, 512
T0_NS = 1_700_000_000_000_000_000
FRAME_NS = 33_333_333
QUALITY = 95


def tissue_like_frames(n: int, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Smooth textured frames with some sensor noise, drifting over time, so JPEG does real work."""
    rng = np.random.default_rng(seed)
    base = cv2.resize(rng.integers(0, 256, (HEIGHT // 8, (WIDTH + 64) // 8, 3), dtype=np.uint8), (WIDTH + 64, HEIGHT),
                      interpolation=cv2.INTER_CUBIC)
    detail = cv2.GaussianBlur(rng.integers(0, 256, (HEIGHT, WIDTH + 64, 3), dtype=np.uint8), (3, 3), 0)
    scene = cv2.addWeighted(base, 0.7, detail, 0.3, 0)
    frames = []
    for i in range(n):
        shift = i % 32
        noise = rng.normal(0, 2.0, (2, HEIGHT, WIDTH, 3))
        left = np.clip(scene[:, shift:shift + WIDTH] + noise[0], 0, 255).astype(np.uint8)
        right = np.clip(scene[:, shift + 24:shift + 24 + WIDTH] + noise[1], 0, 255).astype(np.uint8)
        frames.append((left, right))
    return frames


KINDS = ("ros1", "sqlite3", "mcap", "mcap-zstd")  # ROS 1; ROS 2 storages
DEFAULT_KINDS = ["ros1", "sqlite3", "mcap"]  # the bags read in place; zstd MCAP is streamed, 4x slower


def write_bag(path: Path, frames: list[tuple[np.ndarray, np.ndarray]], kind: str, force_hz: float,
              pose_hz: float = 0.0) -> None:
    ros2 = kind != "ros1"
    ts = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    T = ts.types
    serialize = ts.serialize_cdr if ros2 else ts.serialize_ros1

    def header(stamp: int, frame: str):
        time_msg = T["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9)
        fields = {"stamp": time_msg, "frame_id": frame} if ros2 else {"seq": 0, "stamp": time_msg, "frame_id": frame}
        return T["std_msgs/msg/Header"](**fields)

    plugin = StoragePlugin.SQLITE3 if kind == "sqlite3" else StoragePlugin.MCAP
    writer = Writer2(path, version=9, storage_plugin=plugin) if ros2 else Writer1(path)
    if kind == "mcap-zstd":  # read through rosbags' iterator, not in place
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        image_type, wrench_type = "sensor_msgs/msg/Image", "geometry_msgs/msg/WrenchStamped"
        left_c = writer.add_connection("/jhu_daVinci/left/image_raw", image_type, typestore=ts)
        right_c = writer.add_connection("/jhu_daVinci/right/image_raw", image_type, typestore=ts)
        info_c = {side: writer.add_connection(f"/jhu_daVinci/{side}/camera_info", "sensor_msgs/msg/CameraInfo",
                                              typestore=ts) for side in ("left", "right")}
        force_c = writer.add_connection("/netft_data", wrench_type, typestore=ts)
        pose_type = "geometry_msgs/msg/PoseStamped"
        pose_c = writer.add_connection("/ECM/measured_cp", pose_type, typestore=ts) if pose_hz else None
        vec = T["geometry_msgs/msg/Vector3"]
        names = ("d", "k", "r", "p") if ros2 else ("D", "K", "R", "P")
        for side, tx in (("left", 0.0), ("right", -500.0 * 0.005)):
            values = (np.zeros(5), np.array([500.0, 0, 320, 0, 500, 256, 0, 0, 1]), np.eye(3).ravel(),
                      np.array([500.0, 0, 320, tx, 0, 500, 256, 0, 0, 0, 1, 0]))
            roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
            info = T["sensor_msgs/msg/CameraInfo"](
                header=header(T0_NS, side), height=HEIGHT, width=WIDTH, distortion_model="plumb_bob",
                **dict(zip(names, values, strict=True)), binning_x=0, binning_y=0, roi=roi)
            writer.write(info_c[side], T0_NS, serialize(info, "sensor_msgs/msg/CameraInfo"))
        force_t = pose_t = T0_NS - 5_000_000 + 250_000  # pose samples between the force samples
        for i, (left, right) in enumerate(frames):
            stamp = T0_NS + i * FRAME_NS
            while pose_c is not None and pose_t <= stamp + FRAME_NS:
                pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=0.1, y=0.2, z=0.3),
                                                   orientation=T["geometry_msgs/msg/Quaternion"](x=0, y=0, z=0, w=1))
                writer.write(pose_c, pose_t + 100_000, serialize(T[pose_type](header=header(pose_t, "ECM_base"),
                                                                              pose=pose), pose_type))
                pose_t += int(1e9 / pose_hz)
            while force_t <= stamp + FRAME_NS:
                msg = T[wrench_type](header=header(force_t, "ft"), wrench=T["geometry_msgs/msg/Wrench"](
                    force=vec(x=0.1, y=0.2, z=1.0), torque=vec(x=0.0, y=0.0, z=0.01)))
                writer.write(force_c, force_t + 100_000, serialize(msg, wrench_type))
                force_t += int(1e9 / force_hz)
            for connection, image, frame in ((left_c, left, "left"), (right_c, right, "right")):
                msg = T[image_type](header=header(stamp, frame), height=HEIGHT, width=WIDTH, encoding="bgr8",
                                    is_bigendian=0, step=WIDTH * 3, data=image.ravel())
                writer.write(connection, stamp + 2_000_000, serialize(msg, image_type))


def bare_jpeg_seconds(frames: list[tuple[np.ndarray, np.ndarray]], workers: int) -> tuple[float, float]:
    """(wall, CPU) seconds to JPEG-encode every image on `workers` threads."""
    images = [image for pair in frames for image in pair]
    with ThreadPoolExecutor(workers) as pool:
        start, cpu = time.perf_counter(), time.process_time()
        sizes = list(pool.map(lambda im: len(cv2.imencode(".jpg", im, [cv2.IMWRITE_JPEG_QUALITY, QUALITY])[1]),
                              images))
        elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
    assert all(sizes)
    return elapsed, cpu


def _bytes(bag: Path) -> int:
    """Size of a bag file, or of all the files of a ROS 2 bag folder."""
    return sum(p.stat().st_size for p in bag.rglob("*")) if bag.is_dir() else bag.stat().st_size


def timed_conversion(bag: Path, out: Path, options: ConvertOptions) -> tuple[float, float, float]:
    """(wall, CPU, main-thread CPU) seconds of one `convert_bag`."""
    start, cpu, main_cpu = time.perf_counter(), time.process_time(), time.thread_time()
    convert_bag(bag, out, options=options)
    elapsed = (time.perf_counter() - start, time.process_time() - cpu, time.thread_time() - main_cpu)
    # Outside the timing: a user converts to a new file; replacing the last run's 40 MB output inside
    # convert_bag cost up to 70 ms (0.35 ms a frame) of unlinking that no user pays.
    out.unlink()
    return elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bags", nargs="+", choices=KINDS, default=None,
                        help="bags to convert, alternating in one sitting: ros1, or a ROS 2 storage (sqlite3; mcap, "
                             "the default of ROS 2 Iron onwards; mcap-zstd: zstd chunks) (default ros1 sqlite3 mcap)")
    parser.add_argument("--ros2", action="store_true", help="older spelling of --bags STORAGE")
    parser.add_argument("--storage", choices=KINDS[1:], default="sqlite3", help="with --ros2 (default sqlite3)")
    parser.add_argument("--frames", type=int, default=200, help="stereo frames in the bag (default 200)")
    parser.add_argument("--workers", type=int, default=2, help="encoding threads for both (default 2)")
    parser.add_argument("--convert-workers", type=int, default=None,
                        help="encoding threads of the conversion only (default: --workers)")
    parser.add_argument("--force-hz", type=float, default=1000.0, help="WrenchStamped rate (default 1000 Hz)")
    parser.add_argument("--pose-hz", type=float, default=0.0,
                        help="ECM PoseStamped rate, between the force samples (default 0: no pose topic)")
    parser.add_argument("--repeat", type=int, default=3, help="runs of each, alternating; medians are reported "
                                                              "(default 3)")
    args = parser.parse_args()
    kinds = list(dict.fromkeys(args.bags or ([args.storage] if args.ros2 else DEFAULT_KINDS)))

    cv2.setNumThreads(1)  # the thread pool is the only parallelism in both measurements
    frames = tissue_like_frames(args.frames)
    load_before = os.getloadavg()[0]
    options = ConvertOptions(image_format="jpeg", jpeg_quality=QUALITY, progress=False,
                             workers=args.convert_workers or args.workers)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out.mcap"
        bags, sizes = {}, {}
        for kind in kinds:
            bags[kind] = Path(tmp) / ("bench.bag" if kind == "ros1" else kind)
            write_bag(bags[kind], frames, kind, args.force_hz, args.pose_hz)
            sizes[kind] = _bytes(bags[kind])
            timed_conversion(bags[kind], out, options)  # warm-up: imports, page cache
        bare: list[tuple[float, float]] = []
        runs: dict[str, list[tuple[float, float, float]]] = {kind: [] for kind in kinds}
        for _ in range(args.repeat):
            bare.append(bare_jpeg_seconds(frames, args.workers))
            for kind in kinds:
                runs[kind].append(timed_conversion(bags[kind], out, options))
    load = (load_before + os.getloadavg()[0]) / 2
    n = args.frames
    pose = f", pose {args.pose_hz:g} Hz" if args.pose_hz else ""
    print(f"{n} stereo frames bgr8 {WIDTH}x{HEIGHT}, force {args.force_hz:g} Hz{pose}; JPEG quality {QUALITY}; "
          f"{args.workers} threads (conversion: {options.workers}); {os.cpu_count()} CPUs, load average {load:.1f}")
    for i, (bw, bc) in enumerate(bare):
        line = "; ".join(f"{kind} {runs[kind][i][0]:.2f} s (ratio {bw / runs[kind][i][0]:.2f})" for kind in kinds)
        print(f"  run {i}: bare {bw:.2f} s wall, {bc:.2f} s CPU | {line}")
    bare_wall, bare_cpu = (statistics.median(b[i] for b in bare) for i in range(2))
    print(f"bare JPEG encoding: {n / bare_wall:6.1f} stereo frames/s; CPU {bare_cpu * 1e3 / n:.2f} ms a frame")
    print(f"TARGET conversion / bare JPEG >= 0.7, medians of {args.repeat}:")
    for kind in kinds:
        wall, cpu, main_cpu = (statistics.median(r[i] for r in runs[kind]) for i in range(3))
        print(f"  {kind:9s} ({sizes[kind] / 1e6:4.0f} MB): {n / wall:6.1f} stereo frames/s, wall ratio "
              f"{bare_wall / wall:.2f}, CPU-time ratio {bare_cpu / cpu:.2f}; CPU {cpu * 1e3 / n:.2f} ms a frame, "
              f"of which main thread {main_cpu * 1e3 / n:.2f} ms")


if __name__ == "__main__":
    main()
