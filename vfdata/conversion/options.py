"""What a conversion is asked for: image format and quality, the force-gap tolerance, threads, chunks.
Shared by the raw-folder and the bag converters."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

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

    def check_format(self, out: Path) -> None:
        """InputError naming the output when the image format is not one the writer has."""
        if self.image_format not in ("jpeg", "png"):
            raise InputError(out, f"image format must be jpeg or png, not {self.image_format}")
