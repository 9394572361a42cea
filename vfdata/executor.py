"""Where independent jobs run (one recording processed, one training run): here, in local processes,
or as tasks of a Ray cluster (`--executor local|ray`, docs/cluster.md).

    for result in run_jobs(process_one, jobs, executor="ray", ray_address="auto"):
        ...

Results come back in the jobs' order whatever the executor, and a job computes the same thing
wherever it runs (each job sets its own thread count). Ray is an optional extra (`pip install
'visionforce[ray]'`) imported only here, and only when asked for. A job's own error (a bad recording)
comes back as it was raised, one line, not wrapped in Ray's traceback."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from typing import TypeVar

from vfdata.errors import VisionForceError

EXECUTORS = ("local", "ray")
J = TypeVar("J")
R = TypeVar("R")


def import_ray():
    try:
        import ray  # the `ray` extra, only for --executor ray
    except ImportError:
        raise VisionForceError("--executor ray needs the ray package: pip install 'visionforce[ray]'") from None
    return ray


def run_jobs(fn: Callable[[J], R], jobs: Iterable[J], executor: str = "local", workers: int = 1,
             ray_address: str | None = None, num_cpus: float = 1.0) -> Iterator[R]:
    """`fn(job)` for every job, results in order. `local`: in this process (`workers` 1) or in
    `workers` processes; `ray`: one Ray task per job (`num_cpus` each) on the cluster at `ray_address`
    ("auto": the one this machine belongs to; None: the running instance, or a new local one). `fn`
    and the jobs must pickle (module-level functions, plain values)."""
    jobs = list(jobs)
    if executor not in EXECUTORS:
        raise VisionForceError(f"unknown executor '{executor}' (known: {', '.join(EXECUTORS)})")
    if executor == "local":
        if workers > 1 and len(jobs) > 1:
            with ProcessPoolExecutor(workers) as pool:
                yield from pool.map(fn, jobs)
        else:
            yield from map(fn, jobs)
        return
    yield from _ray_jobs(fn, jobs, ray_address, num_cpus)


def _ray_jobs(fn, jobs: list, address: str | None, num_cpus: float):
    ray = import_ray()
    started_here = not ray.is_initialized()
    if started_here:
        try:
            ray.init(address=address, include_dashboard=False, log_to_driver=False, configure_logging=False)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            raise VisionForceError(f"cannot connect to the Ray cluster at {address or 'a new local instance'} "
                                   f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    try:
        task = ray.remote(num_cpus=num_cpus, max_retries=0)(fn)
        refs = [task.remote(job) for job in jobs]
        for ref in refs:
            try:
                yield ray.get(ref)
            except ray.exceptions.RayTaskError as exc:
                cause = exc.cause
                if isinstance(cause, VisionForceError):
                    raise cause from None
                raise
    finally:
        if started_here:
            ray.shutdown()
