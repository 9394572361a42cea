"""Does the force stream cover the video? The tolerance for its gaps, by default relative to the
stream's own rate: a 1 kHz sensor that stops for 50 ms has failed, a 30 Hz one that drops one sample
(a 67 ms gap) has not."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vfdata.errors import InputError

MIN_FORCE_GAP_NS = 50_000_000  # the default tolerance never goes below 50 ms
FORCE_GAP_PERIODS = 3  # ... and is 3 median sample intervals for slower streams


def default_force_gap_ns(force_ns: np.ndarray) -> int:
    """The default gap tolerance of a force stream (sorted stamps, ns): 3x its median sample interval,
    at least 50 ms. A single dropped sample (a gap of 2 intervals) passes; a stall does not."""
    steps = np.diff(np.asarray(force_ns, np.int64))
    median = int(np.median(steps)) if len(steps) else 0
    return max(MIN_FORCE_GAP_NS, FORCE_GAP_PERIODS * median)


def check_force_covers(path: Path, force_ns: np.ndarray, frame_ns: np.ndarray, tolerance_ns: int | None = None,
                       ) -> None:
    """The force stream must cover the video span with no gap longer than `tolerance_ns` (None: the
    stream's default, `default_force_gap_ns`); InputError naming `path` otherwise."""
    given = tolerance_ns is not None
    tolerance_ns = int(tolerance_ns) if given else default_force_gap_ns(force_ns)
    how = (f"tolerance {tolerance_ns / 1e6:.0f} ms, --force-gap-ms" if given else
           f"default tolerance {tolerance_ns / 1e6:.0f} ms, {FORCE_GAP_PERIODS}x the median sample interval and at "
           f"least {MIN_FORCE_GAP_NS / 1e6:.0f} ms; --force-gap-ms MS allows more")
    first, last = int(frame_ns[0]), int(frame_ns[-1])
    if force_ns[0] > first + tolerance_ns:
        raise InputError(path, f"force starts {(force_ns[0] - first) / 1e6:.1f} ms after the first frame ({how})")
    if force_ns[-1] < last - tolerance_ns:
        raise InputError(path, f"force ends {(last - force_ns[-1]) / 1e6:.1f} ms before the last frame ({how})")
    lo = max(int(np.searchsorted(force_ns, first)) - 1, 0)
    hi = min(int(np.searchsorted(force_ns, last)) + 1, len(force_ns))
    gaps = np.diff(force_ns[lo:hi])
    if len(gaps) and gaps.max() > tolerance_ns:
        i = lo + int(np.argmax(gaps))
        raise InputError(path, f"gap of {gaps.max() / 1e6:.1f} ms in the force stream after {force_ns[i]} ns ({how})")
