"""graphcal batch: speed-up of 2 workers over 1, and the Dask path's per-task overhead against the
local process pool, measured side by side.

    .venv/bin/python bench/batch.py [--tasks 20] [--repeats 1] [--noop 100] [--scratch DIR] [--json PATH]

Set-up: one simulated calibration dataset (octopus, Chai's 2015 program, planes from clouds at
``cloud_stride`` 8, seed 300: the dataset of bench/calibration_nees.py), copied into ``--tasks``
folders; ``graphcal batch calibrate`` (graphcal.commands.batch.run_batch, the command's own path:
outputs written atomically, batch.yaml rewritten after each task) over them on

* the local process pool with 1 and with 2 workers (spawn; the pool's start-up counted in the wall);
* a Dask ``LocalCluster(processes=True, threads_per_worker=1)`` with 1 and with 2 workers (started
  before the clock starts, as a cluster is; its first task pays the worker's imports, as the pool's do).

The configurations run round-robin ``--repeats`` times (so that changes of the machine's load hit all
of them alike). Reported per configuration: wall (s), the mean compute time of one calibration in its
worker (``compute_s`` of batch.yaml), and the overhead per task = (wall x workers - sum of compute)
/ tasks: what a task costs beyond its calibration (queueing, pickling, start-up, writing batch.yaml).
Speed-up = wall(1 worker) / wall(2 workers). The CPU time of each calibration (``cpu_s``) is printed
beside its wall time: when the two differ, other processes had the cores. The Dask overhead per task against the pool's =
(overhead_dask - overhead_pool) / mean compute, with 1 worker (no competition for the cores). Also,
``--noop`` empty tasks through each executor with 1 worker (round-trip latency per task, no
calibration). Load average before and after each run is recorded: on a shared machine it matters.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402


def noop(x):
    return x


def _dataset(scratch: Path) -> Path:
    from graphcal.commands import simulate

    ds = scratch / "template"
    if not (ds / "dataset.yaml").is_file():
        shutil.rmtree(ds, ignore_errors=True)
        simulate.run(robot="octopus", program="chai2015", ground="level", out_dir=ds, seed=300, output="planes",
                     cloud_stride=8, progress=False)
    return ds


def _batch(datasets: list[Path], out: Path, scheduler: str | None, workers: int) -> dict:
    from graphcal.commands.batch import plan_tasks, run_batch

    shutil.rmtree(out, ignore_errors=True)
    tasks = plan_tasks("calibrate", [str(d) for d in datasets], out)
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    doc = run_batch(tasks, out, scheduler=scheduler, workers=None if scheduler else workers, progress=False)
    wall = time.perf_counter() - t0
    comp = [t["compute_s"] for t in doc["tasks"] if t["status"] == "done"]
    cpu = [t["cpu_s"] for t in doc["tasks"] if t["status"] == "done"]
    assert len(comp) == len(tasks), doc["counts"]
    return {"wall_s": wall, "compute_mean_s": float(np.mean(comp)), "compute_sum_s": float(np.sum(comp)),
            "cpu_mean_s": float(np.mean(cpu)),
            "overhead_per_task_s": (wall * workers - float(np.sum(comp))) / len(tasks),
            "load_start": load0, "load_end": os.getloadavg()[0]}


def _noop_latency(executor, n: int) -> float:
    from concurrent.futures import wait

    executor.submit(noop, 0).result()  # warm
    t0 = time.perf_counter()
    for i in range(n):  # one at a time: the round trip of a task
        wait([executor.submit(noop, i)])
    return (time.perf_counter() - t0) / n


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tasks", type=int, default=20, help="calibrations per configuration (default 20)")
    ap.add_argument("--repeats", type=int, default=1, help="round-robin passes over the configurations")
    ap.add_argument("--noop", type=int, default=100, help="empty tasks for the round-trip latency")
    ap.add_argument("--scratch", type=Path, default=Path("/tmp/graphcal-bench-batch"))
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    import logging

    from dask.distributed import Client, LocalCluster

    logging.getLogger("distributed").setLevel(logging.WARNING)

    from graphcal.batch.executor import local_executor

    args.scratch.mkdir(parents=True, exist_ok=True)
    template = _dataset(args.scratch)
    datasets = []
    for i in range(args.tasks):
        d = args.scratch / "fleet" / f"robot_{i:02d}"
        if not d.exists():
            shutil.copytree(template, d)
        datasets.append(d)
    clusters = {w: LocalCluster(processes=True, n_workers=w, threads_per_worker=1, dashboard_address=":0")
                for w in (1, 2)}
    results: dict = {}
    try:
        for rep in range(args.repeats):
            for kind in ("local", "dask"):
                for w in (1, 2):
                    name = f"{kind} {w}"
                    sched = clusters[w].scheduler_address if kind == "dask" else None
                    r = _batch(datasets, args.scratch / "out" / name.replace(" ", "_"), sched, w)
                    results.setdefault(name, []).append(r)
                    print(f"[pass {rep + 1}] {name} worker(s): wall {r['wall_s']:.1f} s, calibration "
                          f"{r['compute_mean_s']:.2f} s ({r['cpu_mean_s']:.2f} s CPU), overhead/task {r['overhead_per_task_s']:.3f} s "
                          f"(load {r['load_start']:.1f} -> {r['load_end']:.1f})", file=sys.stderr, flush=True)
        with local_executor(1) as pool:
            lat_pool = _noop_latency(pool, args.noop)
        with Client(clusters[1].scheduler_address) as c:
            lat_dask = _noop_latency(c.get_executor(pure=False), args.noop)
    finally:
        for c in clusters.values():
            c.close()

    def med(name, key):
        return float(np.median([r[key] for r in results[name]]))

    comp1 = med("local 1", "compute_mean_s")
    summary = {
        "speedup_local_2_over_1": med("local 1", "wall_s") / med("local 2", "wall_s"),
        "speedup_dask_2_over_1": med("dask 1", "wall_s") / med("dask 2", "wall_s"),
        "calibration_s": comp1,
        "overhead_per_task_s": {n: med(n, "overhead_per_task_s") for n in results},
        "dask_minus_pool_overhead_fraction_of_calibration":
            (med("dask 1", "overhead_per_task_s") - med("local 1", "overhead_per_task_s")) / comp1,
        "noop_roundtrip_s": {"local pool": lat_pool, "dask": lat_dask},
        "dask_minus_pool_noop_fraction_of_calibration": (lat_dask - lat_pool) / comp1,
    }
    report = {"tasks": args.tasks, "repeats": args.repeats, "cpus": os.cpu_count(), "runs": results,
              "summary": summary}
    s = summary
    print(f"\nbatch bench: {args.tasks} calibrations ({comp1:.2f} s each in a worker), {args.repeats} pass(es)")
    for n in results:
        print(f"  {n:8s} worker(s): wall {med(n, 'wall_s'):6.1f} s, calibration {med(n, 'compute_mean_s'):.2f} s wall, "
              f"{med(n, 'cpu_mean_s'):.2f} s CPU; overhead per task {med(n, 'overhead_per_task_s'):.3f} s")
    print(f"  speed-up 2 workers over 1: local pool {s['speedup_local_2_over_1']:.2f}x, "
          f"Dask {s['speedup_dask_2_over_1']:.2f}x (goal >= 1.7x)")
    print(f"  Dask overhead per task minus the pool's: "
          f"{100 * s['dask_minus_pool_overhead_fraction_of_calibration']:+.1f} % of one calibration (goal <= 5 %)")
    print(f"  empty task round trip: pool {1e3 * lat_pool:.2f} ms, Dask {1e3 * lat_dask:.2f} ms "
          f"({100 * s['dask_minus_pool_noop_fraction_of_calibration']:+.2f} % of one calibration)")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))
    return report


if __name__ == "__main__":
    main()
