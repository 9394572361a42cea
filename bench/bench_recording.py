"""Recording-layer benchmark (issue 2). Prints figures as ratios to the bare bound measured in the
same run, on the same cores.

    python bench/bench_recording.py [--frames 300] [--big-gb 2.0] [--workdir /tmp/vf_bench]

1. conversion rate vs the bare bound (decode the source PNGs + JPEG-encode them, same thread pool);
2. full read-and-decode of all frames vs bare JPEG decoding of the same bytes (one thread each);
3. the whole force series of a 3-minute recording (180k samples at 1 kHz);
4. a random 16-frame clip (compressed stereo images + force at the frame times), and decoded;
5. peak memory (RSS) while streaming every frame of a file of --big-gb GB;
6. (--records) the records `McapWriter` packs itself against `mcap.records`' builders, the figures
   quoted beside the writer's code.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from rawfixtures import make_raw  # noqa: E402

from vfdata.conversion.ordered_map import ordered_map  # noqa: E402
from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder  # noqa: E402
from vfdata.recording import Recording, layout  # noqa: E402
from vfdata.recording.messages import CompressedImage, WrenchStamped  # noqa: E402
from vfdata.recording.writer import McapWriter  # noqa: E402

W, H = 640, 512


def textured_raw(folder: Path, frames: int) -> Path:
    """A 640x512 raw folder with tissue-like smooth texture (so JPEG sizes are realistic)."""
    make_raw(folder, n=frames, width=W, height=H, pose=True)
    rng = np.random.default_rng(1)
    base = np.zeros((H, W * 2, 3), np.float32)
    for scale in (4, 16, 64):
        noise = rng.normal(0, 1, (H // scale + 2, W * 2 // scale + 2, 3)).astype(np.float32)
        base += cv2.resize(noise, (W * 2, H), interpolation=cv2.INTER_CUBIC) * (scale / 8)
    base = np.clip(128 + 20 * base + [20, 30, 80], 0, 255).astype(np.uint8)
    for i in range(frames):
        cv2.imwrite(str(folder / "left" / f"{i:06d}.png"), np.roll(base, i, axis=1)[:, :W])
        cv2.imwrite(str(folder / "right" / f"{i:06d}.png"), np.roll(base, i + 20, axis=1)[:, :W])
    return folder


def bench_conversion(workdir: Path, frames: int) -> None:
    src = textured_raw(workdir / "raw", frames)
    files = [(p, src / "right" / p.name) for p in sorted((src / "left").iterdir())]

    def bare(item):
        out = []
        for path in item:
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            out.append(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes())
        return out

    bare_times, ours_times = [], []
    for _ in range(3):
        t = time.perf_counter()
        with ThreadPoolExecutor(2) as pool:
            for _ in ordered_map(pool, bare, iter(files), window=8):
                pass
        bare_times.append(time.perf_counter() - t)
        out = workdir / "conv.mcap"
        t = time.perf_counter()
        convert_raw_folder(src, out, overwrite=True, options=ConvertOptions(progress=False, workers=2))
        ours_times.append(time.perf_counter() - t)
    b, o = statistics.median(bare_times), statistics.median(ours_times)
    print(
        f"conversion: {frames / o:.1f} stereo frames/s vs bare bound {frames / b:.1f} -> ratio {b / o:.2f} "
        f"(target >= 0.7; median of 3, {frames} frames 640x512, 1 kHz force)"
    )

    rec = Recording.open(out)
    payloads = [rec.frame_images(i) for i in range(rec.num_frames)]
    bare_times, ours_times = [], []
    cv2.setNumThreads(1)
    for _ in range(3):
        t = time.perf_counter()
        for left, right in payloads:
            cv2.imdecode(np.frombuffer(left.data, np.uint8), cv2.IMREAD_COLOR)
            cv2.imdecode(np.frombuffer(right.data, np.uint8), cv2.IMREAD_COLOR)
        bare_times.append(time.perf_counter() - t)
        t = time.perf_counter()
        fresh = Recording.open(out)
        for _ in fresh.frames():
            pass
        ours_times.append(time.perf_counter() - t)
    b, o = statistics.median(bare_times), statistics.median(ours_times)
    print(
        f"read+decode all frames: {frames / o:.1f} frames/s vs bare JPEG decoding {frames / b:.1f} -> "
        f"ratio {b / o:.2f} (target >= 0.7; one thread)"
    )


def write_long(path: Path, seconds: float, jpeg_pair: tuple[bytes, bytes], unique: bool = False) -> None:
    """A long recording: 1 kHz force and 30 Hz stereo images. `unique`: every image gets different
    (random, incompressible) bytes of the same size, so the file really is as large as its images."""
    t0 = 1_700_000_000_000_000_000
    noise = np.random.default_rng(1)
    n_force = int(seconds * 1000)
    with McapWriter(path, overwrite=True, separate_topics=(layout.WRENCH,)) as w:
        w.add_metadata(layout.RECORDING_METADATA, layout.RecordingMeta(recording_id="bench").to_record())
        rng = np.random.default_rng(0)
        values = rng.normal(0, 3, (n_force, 6))
        for k in range(n_force):
            stamp = t0 + k * 1_000_000
            v = values[k]
            w.write(
                layout.WRENCH, WrenchStamped(stamp, "force_sensor", (v[0], v[1], v[2]), (v[3], v[4], v[5]))
            )
            if k % 33 == 0:
                left, right = jpeg_pair
                if unique:
                    left = noise.bytes(len(left))
                    right = noise.bytes(len(right))
                w.write(layout.LEFT_IMAGE, CompressedImage(stamp, layout.LEFT_FRAME, "jpeg", left))
                w.write(layout.RIGHT_IMAGE, CompressedImage(stamp, layout.RIGHT_FRAME, "jpeg", right))


def bench_force_and_clips(workdir: Path) -> None:
    conv = Recording.open(workdir / "conv.mcap")
    pair = tuple(image.data for image in conv.frame_images(0))
    path = workdir / "long.mcap"
    write_long(path, 180.0, pair)
    times = []
    for _ in range(5):
        t = time.perf_counter()
        force = Recording.open(path).force
        times.append(time.perf_counter() - t)
    print(
        f"force series of a 3-minute recording ({len(force.times_ns)} samples): "
        f"{statistics.median(times) * 1e3:.0f} ms median of 5, open included (target <= 500 ms)"
    )

    rec = Recording.open(path)
    rng = np.random.default_rng(0)
    fetch, decode = [], []
    for _ in range(50):
        start = int(rng.integers(0, rec.num_frames - 16))
        t = time.perf_counter()
        images = [rec.frame_images(i) for i in range(start, start + 16)]
        rec.force_at(rec.frame_times_ns[start : start + 16])
        fetch.append(time.perf_counter() - t)
        t = time.perf_counter()
        for i in range(start, start + 16):
            rec.frame(i)
        decode.append(time.perf_counter() - t)
    del images
    print(
        f"random 16-frame clip: {statistics.median(fetch) * 1e3:.2f} ms compressed images + force "
        f"(target <= 5 ms); {statistics.median(decode) * 1e3:.1f} ms with all 32 images decoded to BGR"
    )


def bench_streaming_memory(workdir: Path, gigabytes: float) -> None:
    conv = Recording.open(workdir / "conv.mcap")
    pair = tuple(image.data for image in conv.frame_images(0))
    seconds = gigabytes * 1e9 / (len(pair[0]) + len(pair[1])) / 30
    path = workdir / "big.mcap"
    write_long(path, seconds, pair, unique=True)
    size = path.stat().st_size
    code = (
        "import resource, sys\n"
        "from vfdata.recording import Recording\n"
        "rec = Recording.open(sys.argv[1])\n"
        "n = 0\n"
        "for i in range(rec.num_frames):\n"
        "    l, r = rec.frame_images(i); n += len(l.data) + len(r.data)\n"
        "f = rec.force\n"
        "print(n, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)\n"
    )
    t = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, check=True)
    elapsed = time.perf_counter() - t
    nbytes, rss_kb = (int(v) for v in out.stdout.split())
    print(
        f"streaming a {size / 1e9:.2f} GB file (all {nbytes / 1e9:.2f} GB of images + the force series): "
        f"peak RSS {rss_kb / 1024:.0f} MB (target <= 500 MB), {size / 1e6 / elapsed:.0f} MB/s"
    )


def bench_record_builders() -> None:
    """The three records the writer packs itself (message records, chunk heads, message indexes),
    against `mcap.records`' own builders at equal work."""
    import struct

    from mcap.data_stream import RecordBuilder
    from mcap.records import Chunk, Message, MessageIndex

    from vfdata.mcap_io.records import CHUNK_FIELDS, MESSAGE_HEAD, MESSAGE_INDEX_HEAD, RECORD_HEAD

    def best(f, n=5):
        times = []
        for _ in range(n):
            t = time.perf_counter()
            f()
            times.append(time.perf_counter() - t)
        return min(times)

    image, force = os.urandom(100_000), os.urandom(80)
    for name, payload, count in (("100 kB image", image, 40), ("80 B force sample", force, 2048)):
        def library(payload=payload, count=count):
            builder = RecordBuilder()
            for i in range(count):
                Message(1, i, payload, i, i).write(builder)
            builder.end()

        def packed(payload=payload, count=count):
            parts = []
            for i in range(count):
                parts += (MESSAGE_HEAD.pack(5, 22 + len(payload), 1, i, i, i), payload)

        print(f"message record, {name}: mcap.records {best(library) / count * 1e6:.2f} us, "
              f"packed head {best(packed) / count * 1e6:.2f} us")
    pieces = [image] * 42
    size = sum(len(p) for p in pieces)

    def library_chunk():
        builder = RecordBuilder()
        Chunk("", b"".join(pieces), 1, 0, 0, size).write(builder)
        builder.end()

    def packed_chunk():
        body = CHUNK_FIELDS.pack(0, 1, size, 0) + struct.pack("<I", 0) + struct.pack("<Q", size)
        RECORD_HEAD.pack(6, len(body) + size)  # the pieces then go to the file as they are

    print(f"chunk record of {size / 1e6:.1f} MB of images: mcap.records {best(library_chunk) * 1e3:.2f} ms, "
          f"packed head {best(packed_chunk) * 1e3:.4f} ms")
    entries = [(i, i * 100) for i in range(2048)]

    def library_index():
        builder = RecordBuilder()
        MessageIndex(1, entries).write(builder)
        builder.end()

    def packed_index():
        pairs = np.array(entries, "<u8").tobytes()
        MESSAGE_INDEX_HEAD.pack(7, 6 + len(pairs), 1, len(pairs))

    print(f"message index of 2048 entries: mcap.records {best(library_index) * 1e3:.2f} ms, "
          f"numpy {best(packed_index) * 1e3:.2f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--big-gb", type=float, default=2.0, help="0 skips the streaming-memory figure")
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/vf_bench_recording"))
    parser.add_argument("--records", action="store_true", help="only the record-builder figures")
    args = parser.parse_args()
    if args.records:
        bench_record_builders()
        return
    shutil.rmtree(args.workdir, ignore_errors=True)
    args.workdir.mkdir(parents=True)
    print(
        f"cores: {os.cpu_count()}; peak RSS of this process so far "
        f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB"
    )
    bench_conversion(args.workdir, args.frames)
    bench_force_and_clips(args.workdir)
    if args.big_gb > 0:
        bench_streaming_memory(args.workdir, args.big_gb)
    shutil.rmtree(args.workdir, ignore_errors=True)


if __name__ == "__main__":
    main()
