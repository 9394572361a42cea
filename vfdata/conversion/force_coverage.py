"""Does the force stream cover the video?"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vfdata.errors import InputError


def check_force_covers(path: Path, force_ns: np.ndarray, frame_ns: np.ndarray, tolerance_ns: int) -> None:
    """The force stream must cover the video span with no gap longer than `tolerance_ns`."""
    first, last = int(frame_ns[0]), int(frame_ns[-1])
    if force_ns[0] > first + tolerance_ns:
        raise InputError(path, f"force starts {(force_ns[0] - first) / 1e6:.1f} ms after the first frame")
    if force_ns[-1] < last - tolerance_ns:
        raise InputError(path, f"force ends {(last - force_ns[-1]) / 1e6:.1f} ms before the last frame")
    lo = max(int(np.searchsorted(force_ns, first)) - 1, 0)
    hi = min(int(np.searchsorted(force_ns, last)) + 1, len(force_ns))
    gaps = np.diff(force_ns[lo:hi])
    if len(gaps) and gaps.max() > tolerance_ns:
        i = lo + int(np.argmax(gaps))
        raise InputError(
            path, f"gap of {gaps.max() / 1e6:.1f} ms in the force stream after {force_ns[i]} ns "
            f"(tolerance {tolerance_ns / 1e6:.0f} ms)",
        )
