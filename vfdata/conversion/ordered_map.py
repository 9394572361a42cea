"""`ordered_map`: a thread pool map that keeps the input order and a bounded number of items in
flight, so a converter can encode frames in parallel while streaming a long recording."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def ordered_map(pool: ThreadPoolExecutor, fn: Callable[[T], R], items: Iterable[T], window: int) -> Iterator[R]:
    """Like `pool.map(fn, items)`, but at most `window` items are submitted and not yet consumed, so
    the input is pulled lazily (a video or bag is never held in memory). An exception in `fn` is
    raised when its result is reached; the items in flight behind it are cancelled."""
    pending: deque[Future[R]] = deque()
    try:
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) >= max(1, window):
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    finally:
        for future in pending:
            future.cancel()
