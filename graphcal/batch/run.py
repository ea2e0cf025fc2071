"""The task loop of a batch: submit tasks to a :class:`concurrent.futures.Executor`, hand each
result over as it arrives, keep going when a task fails or its worker dies.

A task that raises is reported with its error (the others go on). A worker process that dies (killed,
out of memory, a crash in native code) breaks a local process pool for every task in flight in it,
so those tasks are *suspects*: the tasks not yet started go on in a fresh pool, then each suspect is
run again alone in a pool of one process, where a second death is its own and is reported as
"worker died". On Dask the scheduler does this itself (it reruns a dead worker's tasks elsewhere and
gives up on a task after ``distributed.scheduler.allowed-failures`` deaths, raising ``KilledWorker``);
that is reported as "worker died" too.
"""

from __future__ import annotations

import contextlib
import logging
import sys
import time
import traceback
from concurrent.futures import FIRST_COMPLETED, Executor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any, Callable, Sequence

__all__ = ["TaskOutcome", "run_tasks"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TaskOutcome:
    """One task's end: ``index`` into the task list; ``status`` "done", "failed" (the task raised) or
    "worker died"; ``value`` the task's return value (done) or None; ``error`` one line (failed,
    worker died) or None; ``detail`` the traceback text, if any; ``wall_s`` seconds from its
    submission to its result as seen by the caller (s; includes the time it waited in the queue)."""

    index: int
    status: str
    value: Any = None
    error: str | None = None
    detail: str | None = None
    wall_s: float = float("nan")


def _error_outcome(index: int, exc: BaseException, wall_s: float) -> TaskOutcome:
    name = type(exc).__name__
    died = name == "KilledWorker" or isinstance(exc, BrokenProcessPool)
    line = " ".join(f"{name}: {exc}".split())
    detail = "".join(traceback.format_exception(exc))
    return TaskOutcome(index, "worker died" if died else "failed", error=line, detail=detail, wall_s=wall_s)


class _Loop:
    """The bookkeeping of one :func:`run_tasks` call."""

    def __init__(self, fn, items, on_outcome, bar):
        self.fn, self.items, self.on_outcome, self.bar = fn, items, on_outcome, bar
        self.outcomes: dict[int, TaskOutcome] = {}
        self.suspects: list[int] = []

    def finish(self, outcome: TaskOutcome) -> None:
        self.outcomes[outcome.index] = outcome
        if outcome.status != "done":
            log.warning("task %d (%s): %s: %s", outcome.index, self.items[outcome.index], outcome.status,
                        outcome.error)
        if self.on_outcome is not None:
            self.on_outcome(outcome)
        if self.bar is not None:
            self.bar.update(1)
            bad = sum(o.status != "done" for o in self.outcomes.values())
            if bad:
                self.bar.set_postfix_str(f"{bad} failed")

    def drain(self, executor: Executor, queue: list[int], cap: int) -> bool:
        """Run the tasks of ``queue`` (consumed from the front) on ``executor``, at most ``cap`` in
        flight. Returns False when the pool broke (the tasks in flight then are in ``suspects``)."""
        flight: dict = {}
        broken = False
        while (queue and not broken) or flight:
            while queue and not broken and len(flight) < cap:
                i = queue.pop(0)
                try:
                    flight[executor.submit(self.fn, self.items[i])] = (i, time.perf_counter())
                except BrokenProcessPool:
                    queue.insert(0, i)
                    broken = True
            if not flight:
                break
            done, _ = wait(list(flight), return_when=FIRST_COMPLETED)
            for fut in done:
                i, t0 = flight.pop(fut)
                try:
                    value = fut.result()
                except BrokenProcessPool:
                    broken = True
                    self.suspects.append(i)
                    continue
                except Exception as exc:  # noqa: BLE001  a task's failure is reported, the batch goes on
                    self.finish(_error_outcome(i, exc, time.perf_counter() - t0))
                    continue
                self.finish(TaskOutcome(i, "done", value=value, wall_s=time.perf_counter() - t0))
        return not broken


def run_tasks(fn: Callable[[Any], Any], items: Sequence[Any], executor: Executor, *,
              on_outcome: Callable[[TaskOutcome], None] | None = None, progress: bool = True,
              desc: str = "tasks", max_in_flight: int | None = None,
              fresh_pool: Callable[[int], Executor] | None = None, pool_size: int = 1) -> list[TaskOutcome]:
    """Run ``fn(item)`` for every item on ``executor``; returns one :class:`TaskOutcome` per item, in
    the order of ``items``. ``on_outcome`` is called in this process as each task ends (in the order
    they end). ``fn`` and the items must be picklable (``fn`` a module-level function).

    Args:
        fn, items: the task function and its arguments, one task per item.
        executor: a :class:`concurrent.futures.Executor` (local pool or Dask's).
        on_outcome: called with each outcome as it arrives (e.g. to write a summary file).
        progress: a tqdm bar over the tasks on stderr.
        desc: the bar's label.
        max_in_flight: tasks submitted at once (default: all). On a local pool give its size: a dead
            worker breaks the pool for every task queued in it, and those all become suspects that are
            rerun one at a time.
        fresh_pool: ``fresh_pool(n)`` -> a new local pool of ``n`` processes, to go on after a worker
            died and broke ``executor`` (a ``ProcessPoolExecutor``); None: those tasks are reported
            as "worker died" with no retry.
        pool_size: the size of the fresh pool that replaces a broken one.
    """
    bar = None
    redirect = contextlib.nullcontext()
    if progress:
        from tqdm.contrib.logging import logging_redirect_tqdm

        from graphcal.progress import ProgressBar

        bar = ProgressBar(total=len(items), desc=desc, unit="task", file=sys.stderr, leave=True)
        redirect = logging_redirect_tqdm([logging.getLogger("graphcal")])  # messages above the bar
    with redirect:
        return _run(fn, items, executor, on_outcome, bar, max_in_flight, fresh_pool, pool_size)


def _run(fn, items, executor, on_outcome, bar, max_in_flight, fresh_pool, pool_size) -> list[TaskOutcome]:
    """:func:`run_tasks` without the bar's set-up."""
    loop = _Loop(fn, items, on_outcome, bar)
    cap = max(1, max_in_flight or len(items) or 1)
    queue = list(range(len(items)))
    try:
        ok = loop.drain(executor, queue, cap)
        while not ok and fresh_pool is not None and queue:  # the rest in a fresh pool
            log.warning("a worker process died; %d task(s) in flight will be rerun one at a time, %d go on in "
                        "a fresh pool", len(loop.suspects), len(queue))
            with fresh_pool(pool_size) as pool:
                ok = loop.drain(pool, queue, cap)
        for i in list(queue):  # the pool broke and there is no fresh one: never started
            queue.remove(i)
            loop.finish(TaskOutcome(i, "not run", error="a worker process died and broke the pool before this "
                                    "task started"))
        for i in list(loop.suspects):  # each alone: a death now is its own
            loop.suspects.remove(i)
            if fresh_pool is None:
                loop.finish(TaskOutcome(i, "worker died", error="the worker process died (pool broken)"))
                continue
            t0 = time.perf_counter()
            with fresh_pool(1) as pool:
                alone = _Loop(fn, items, None, None)
                alone.drain(pool, [i], 1)
            got = alone.outcomes.get(i)
            if got is None:  # broke the pool again, alone
                got = TaskOutcome(i, "worker died", error="the worker process died while running this task, "
                                  "twice (the second time alone in its pool)", wall_s=time.perf_counter() - t0)
            loop.finish(got)
    finally:
        if bar is not None:
            bar.close()
    return [loop.outcomes[i] for i in range(len(items)) if i in loop.outcomes]
