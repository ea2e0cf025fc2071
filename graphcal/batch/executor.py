"""The executor a batch runs on: a local process pool, or a Dask distributed cluster.

Both are :class:`concurrent.futures.Executor` s (Dask's through ``Client.get_executor()``), so the
task loop (:func:`graphcal.batch.run.run_tasks`) does not know which one it got. One task is one
process's work: gtsam's optimisers hold Python's GIL, so threads give no speed-up; the local pool
has one process per worker, and Dask workers should run with one thread each
(``dask worker tcp://HOST:PORT --nthreads 1``; docs/batch.md).
"""

from __future__ import annotations

import contextlib
import logging
import os
from concurrent.futures import Executor, ProcessPoolExecutor
from dataclasses import dataclass
from typing import Iterator

from graphcal.errors import GraphcalError

__all__ = ["SCHEDULER_ENV", "ExecutorInfo", "scheduler_address", "default_workers", "open_executor",
           "local_executor", "worker_init"]

log = logging.getLogger(__name__)

#: the environment variable Dask itself reads for the scheduler's address
SCHEDULER_ENV = "DASK_SCHEDULER_ADDRESS"


@dataclass(frozen=True)
class ExecutorInfo:
    """What a batch ran on: ``kind`` "local" or "dask"; ``address`` the scheduler (Dask) or None;
    ``workers`` the number of worker processes (Dask: those connected when the batch started);
    ``threads_per_worker`` (Dask: the largest of the connected workers; 1 is what graphcal wants)."""

    kind: str
    address: str | None
    workers: int
    threads_per_worker: int

    def describe(self) -> str:
        if self.kind == "local":
            return f"local process pool, {self.workers} worker process(es)"
        return (f"Dask scheduler {self.address}, {self.workers} worker(s) with up to "
                f"{self.threads_per_worker} thread(s) each")

    def to_dict(self) -> dict:
        return {"kind": self.kind, "address": self.address, "workers": self.workers,
                "threads_per_worker": self.threads_per_worker}


def scheduler_address(given: str | None) -> str | None:
    """The scheduler to use: ``given`` (``--scheduler``), else ``$DASK_SCHEDULER_ADDRESS``, else None
    (the local pool). An empty string means the local pool too."""
    addr = given if given is not None else os.environ.get(SCHEDULER_ENV)
    addr = (addr or "").strip()
    return addr or None


def default_workers() -> int:
    """Worker processes of the local pool: the CPUs this process may run on (at least 1)."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    return max(1, n)


def worker_init() -> None:
    """Run in each local worker process before its first task: one BLAS thread (the parallelism is
    across processes; several BLAS threads per process only compete for the same cores)."""
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(name, "1")


def local_executor(workers: int | None = None) -> ProcessPoolExecutor:
    """A local process pool of ``workers`` processes (default :func:`default_workers`), started with
    ``spawn`` (a fresh interpreter: nothing inherited from a parent that holds gtsam or Open3D
    threads) and :func:`worker_init` in each."""
    import multiprocessing

    n = default_workers() if workers is None else int(workers)
    if n < 1:
        raise GraphcalError(f"--workers must be >= 1, got {workers}")
    return ProcessPoolExecutor(max_workers=n, mp_context=multiprocessing.get_context("spawn"),
                               initializer=worker_init)


def _dask_client(address: str, timeout_s: float):
    try:
        from dask.distributed import Client
    except ImportError as exc:  # pragma: no cover - dask[distributed] is a dependency
        raise GraphcalError(f"--scheduler {address}: dask.distributed is not installed ({exc}); "
                            "pip install 'dask[distributed]'") from None
    try:
        return Client(address, timeout=timeout_s, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise GraphcalError(f"--scheduler {address}: cannot reach the Dask scheduler ({exc}); start one with "
                            "`dask scheduler` and workers with `dask worker ADDRESS --nthreads 1` "
                            "(docs/batch.md)") from None


@contextlib.contextmanager
def open_executor(scheduler: str | None = None, workers: int | None = None, *,
                  timeout_s: float = 30.0) -> Iterator[tuple[Executor, ExecutorInfo]]:
    """``with open_executor(scheduler, workers) as (executor, info):`` submit tasks to ``executor``.

    Args:
        scheduler: a Dask scheduler address (``tcp://HOST:PORT``), or None for
            ``$DASK_SCHEDULER_ADDRESS``, or the local pool when neither is set
            (:func:`scheduler_address`).
        workers: local pool size (default: the machine's CPUs). With a scheduler the cluster's
            workers are used and ``workers`` only caps the tasks in flight at once (None: no cap).
        timeout_s: seconds to wait for the scheduler to answer (s).

    Raises:
        GraphcalError: the scheduler cannot be reached, or ``workers`` < 1.
    """
    address = scheduler_address(scheduler)
    if address is None:
        n = default_workers() if workers is None else int(workers)
        pool = local_executor(n)
        try:
            yield pool, ExecutorInfo("local", None, n, 1)
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
        return
    if workers is not None and int(workers) < 1:
        raise GraphcalError(f"--workers must be >= 1, got {workers}")
    client = _dask_client(address, timeout_s)
    try:
        info = client.scheduler_info()
        threads = [int(w.get("nthreads", 1)) for w in info.get("workers", {}).values()]
        if any(t > 1 for t in threads):
            log.warning("Dask workers at %s run %d threads each: graphcal's tasks hold the GIL, so only one "
                        "thread per worker is busy (start them with --nthreads 1; docs/batch.md)",
                        address, max(threads))
        ex = client.get_executor(pure=False)
        yield ex, ExecutorInfo("dask", address, len(threads), max(threads, default=1))
    finally:
        client.close()
