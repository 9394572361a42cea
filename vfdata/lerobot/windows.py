"""A force sensor's native-rate samples packed per frame, and unpacked again (pure functions on arrays).

LeRobot stores one row per frame. A 1 kHz sensor under 30 Hz video gives ~33 samples between two
frames; frame k carries the samples stamped in (t[k-1], t[k]] (frame 0: the one frame period before
it), oldest first, in a fixed-length window padded with zeros, with their stamps and how many there
are. Unpacking the windows of an episode gives back every sample of the span (t[0] - period, t[-1]]
exactly: same stamps, same float64 values."""

from __future__ import annotations

import numpy as np


def window_bounds(frame_ns: np.ndarray, force_ns: np.ndarray, period_ns: int) -> np.ndarray:
    """(F + 1,) indices into the sorted force stamps: frame k's samples are force[b[k]:b[k+1]]."""
    edges = np.concatenate([[int(frame_ns[0]) - int(period_ns)], np.asarray(frame_ns, dtype=np.int64)])
    return np.searchsorted(np.asarray(force_ns, dtype=np.int64), edges, side="right")


def window_length(frame_ns: np.ndarray, force_ns: np.ndarray, period_ns: int) -> int:
    """The most samples any frame interval holds (at least 1)."""
    return max(1, int(np.diff(window_bounds(frame_ns, force_ns, period_ns)).max()))


def pack_windows(frame_ns: np.ndarray, force_ns: np.ndarray, wrench: np.ndarray, period_ns: int, length: int,
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame: samples (F, length, 6) float64, their stamps (F, length) int64 ns, counts (F,) int64;
    padding rows are zero. `length` must be at least `window_length(...)`."""
    bounds = window_bounds(frame_ns, force_ns, period_ns)
    counts = np.diff(bounds)
    if counts.max(initial=0) > length:
        raise ValueError(f"a frame interval holds {counts.max()} samples, more than the window's {length}")
    frames = len(frame_ns)
    samples = np.zeros((frames, length, wrench.shape[1]), dtype=np.float64)
    stamps = np.zeros((frames, length), dtype=np.int64)
    rows = np.repeat(np.arange(frames), counts)
    slots = np.arange(bounds[-1] - bounds[0]) - np.repeat(bounds[:-1] - bounds[0], counts)
    samples[rows, slots] = wrench[bounds[0]:bounds[-1]]
    stamps[rows, slots] = np.asarray(force_ns, dtype=np.int64)[bounds[0]:bounds[-1]]
    return samples, stamps, counts.astype(np.int64)


def unpack_windows(samples: np.ndarray, stamps: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of `pack_windows`: (stamps (N,) int64, values (N, 6)) of every packed sample, in order."""
    counts = np.asarray(counts, dtype=np.int64).reshape(-1)
    if (counts < 0).any() or (counts > samples.shape[1]).any():
        raise ValueError(f"window counts must be 0..{samples.shape[1]}")
    keep = np.arange(samples.shape[1])[None, :] < counts[:, None]
    return stamps[keep].astype(np.int64), samples[keep].astype(np.float64)
