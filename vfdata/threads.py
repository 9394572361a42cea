"""The thread policy of every command and library entry point: one torch/OpenCV thread per worker
process by default, all cores used through processes or pipelining.

The work is many small tensors and images per frame or batch: extra intra-op threads only add
synchronisation, and on a machine that runs other work (a lab's workstation often does) OpenMP
threads waiting on each other cost far more CPU than the work itself (`vfdata process` measured 8x
the CPU time and 6-15x the wall time at torch's default, `train.py fit` 2x: bench/bench_threads.py).
`--threads N` (commands) or `threads=N` (library options) asks for another count; `None` leaves the
process's settings as they are.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager

DEFAULT_THREADS = 1
THREADS_HELP = ("torch/OpenCV threads of this process (default 1: the fastest for per-frame and small-batch work, "
                "and what leaves the other cores to other processes; bench/bench_threads.py measures it)")


def check_threads(threads: int | None) -> int | None:
    """`threads` when it is None or a positive count; a ValueError naming it otherwise."""
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
        raise ValueError(f"threads must be a positive whole number, not {threads!r}")
    return threads


def positive_int(text: str) -> int:
    """argparse type of `--threads`: a whole number of at least 1."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number of at least 1")
    return value


def set_threads(threads: int | None = DEFAULT_THREADS) -> None:
    """Set torch's intra-op and OpenCV's thread counts for the rest of the process (None: leave them).
    Also sets OMP_NUM_THREADS for worker processes started later (DataLoader workers, DDP ranks)."""
    if check_threads(threads) is None:
        return
    import cv2  # here, not at the top: the command line starts without it

    cv2.setNumThreads(threads)
    os.environ["OMP_NUM_THREADS"] = str(threads)
    # torch only when this process has loaded it: torch takes its intra-op count from OMP_NUM_THREADS when it
    # loads, so a process that never needs torch (a simulator worker) is not made to load it (1-2 s, 300 MB)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(threads)


@contextmanager
def thread_limit(threads: int | None = DEFAULT_THREADS) -> Iterator[int]:
    """Run a block with `threads` torch/OpenCV threads and restore the caller's counts afterwards;
    yields the torch thread count in force (the one stage rates are measured with)."""
    import cv2  # here, not at the top: the command line starts without torch
    import torch

    check_threads(threads)
    before = torch.get_num_threads(), cv2.getNumThreads()
    if threads is not None:
        torch.set_num_threads(threads)
        cv2.setNumThreads(threads)
    try:
        yield torch.get_num_threads()
    finally:
        torch.set_num_threads(before[0])
        cv2.setNumThreads(before[1])
