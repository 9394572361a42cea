"""What a conversion is asked for: image format and quality, the force-gap tolerance, the sensors' clock
offset, threads, chunks. Shared by the raw-folder and the bag converters."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vfdata.errors import InputError
from vfdata.recording.writer import CHUNK_SIZE

MAX_DEFAULT_WORKERS = 8


def default_workers() -> int:
    """Image encoding threads when none are asked for: one per CPU core this process may use, at most
    MAX_DEFAULT_WORKERS. On the development machine a thread JPEG-encodes about 370 stereo frames/s
    and the main thread, which reads the input and writes the MCAP, keeps up with 1,300-2,000 a
    second, so more threads would only wait for it."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return max(1, min(cores, MAX_DEFAULT_WORKERS))


@dataclass(frozen=True)
class ConvertOptions:
    image_format: str = "jpeg"  # "jpeg" or "png"
    jpeg_quality: int = 95
    # Largest gap allowed in the force stream over the video span, ns; None: relative to the stream's
    # own rate (`force_coverage.default_force_gap_ns`: 3 median sample intervals, at least 50 ms).
    force_gap_tolerance_ns: int | None = None
    workers: int = field(default_factory=default_workers)
    progress: bool = True
    chunk_size: int = CHUNK_SIZE  # bytes of messages per MCAP chunk
    keep_jpeg: bool = True  # store colour JPEG input frames byte for byte (jpeg output only)
    # How late the force and pose stamps run against the video's, ns: a sample stamped t was taken when
    # the video's clock read t - time_offset_ns (`vfdata sync` estimates it). The converters move the
    # samples onto the video's clock (`on_video_clock`) before anything else reads them.
    time_offset_ns: int = 0

    def on_video_clock(self, series: tuple | None, source: Path) -> tuple | None:
        """A (stamps_ns, values, ...) force or pose series with its stamps moved onto the video's clock
        (`time_offset_ns` subtracted); InputError naming `source` when a stamp would fall before 0."""
        if series is None or not self.time_offset_ns:
            return series
        stamps = np.asarray(series[0], dtype=np.int64) - np.int64(self.time_offset_ns)
        if len(stamps) and stamps[0] < 0:
            raise InputError(source, f"--time-offset-ms {self.time_offset_ns / 1e6:g} moves the first sample to "
                                     f"{stamps[0]} ns, before 0: stamps are ns since the epoch or the start")
        return (stamps, *series[1:])

    def check_format(self, out: Path) -> None:
        """InputError naming the output when the image format is not one the writer has."""
        if self.image_format not in ("jpeg", "png"):
            raise InputError(out, f"image format must be jpeg or png, not {self.image_format}")
