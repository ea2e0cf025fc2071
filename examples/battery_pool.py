"""Run a battery's cases in worker processes: the one pool the example batteries share
(diagnosis_battery.py, diagnosis_openworld.py, diagnosis_bookkeeping.py)."""

from __future__ import annotations

import multiprocessing as mp
import os


def run_cases(run_one, args: list, jobs: int) -> list:
    """``[run_one(a) for a in args]``, in ``jobs`` spawned processes when ``jobs > 1`` (in order).
    ``run_one`` must be a module-level function (it is pickled by name). Each worker uses one BLAS
    thread: the workers share the cores."""
    if jobs <= 1:
        return [run_one(a) for a in args]
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    with mp.get_context("spawn").Pool(jobs) as pool:
        return list(pool.imap(run_one, args, chunksize=1))
