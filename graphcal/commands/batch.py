"""``graphcal batch COMMAND DATASET... --out DIR``: one command (calibrate, diagnose, identify-legs,
track) over many datasets, on a local process pool or a Dask cluster (:mod:`graphcal.batch.executor`).

Each dataset's outputs go to their own folder ``DIR/NAME`` (NAME the dataset folder's name; a
repeated name gets ``-2``, ``-3``, ... in the order given), written atomically by the command's own
``run`` (so a folder is either a complete output or absent). A rerun skips every dataset whose
folder already holds a finished output of the command (its manifest file: calibration.yaml,
diagnosis.json, legs.yaml, metrics.json); ``redo`` runs them again. A dataset that fails, or whose
worker dies, is reported with its error and the batch goes on. ``DIR/batch.yaml`` lists every task
with its status, rewritten as each one ends; at the end the fleet view ``DIR/fleet.html`` and
``DIR/fleet.csv`` (:mod:`graphcal.batch.fleet`, :mod:`graphcal.report.fleet_page`) cover every
finished folder, this run's and earlier ones'. docs/batch.md.
"""

from __future__ import annotations

import glob
import logging
import os
import socket
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import yaml

from graphcal.batch.executor import local_executor, open_executor
from graphcal.batch.run import TaskOutcome, run_tasks
from graphcal.errors import GraphcalError
from graphcal.io.atomic import InterruptedAfterWrite, atomic_write_text, previous_output_files

__all__ = ["COMMANDS", "OPTIONS", "BATCH_FORMAT", "BatchTask", "TaskResult", "BatchResult", "expand_datasets",
           "folder_names", "is_finished", "run_task", "plan_tasks", "run_batch", "run_batch_results", "write_fleet", "run"]

log = logging.getLogger(__name__)

BATCH_FORMAT = "graphcal-batch/1"
#: command -> (manifest file of a finished output, its format prefix)
COMMANDS = {
    "calibrate": ("calibration.yaml", "graphcal-calibration/"),
    "diagnose": ("diagnosis.json", "graphcal-diagnosis/"),
    "identify-legs": ("legs.yaml", "graphcal-legs/"),
    "track": ("metrics.json", "graphcal-track/"),
}
#: the options each command takes in a batch (keyword arguments of its run, plain values)
OPTIONS = {"calibrate": ("legs", "incremental", "ground_roughness_m"), "diagnose": (),
           "identify-legs": ("origins", "mocap_free"), "track": ("icp", "tum_rate_hz")}


@dataclass(frozen=True)
class BatchTask:
    """One dataset's work: ``command`` on ``dataset`` (folder, as given) into ``out`` (its output
    folder); ``options`` the command's keyword arguments as (name, value) pairs (:data:`OPTIONS`)."""

    command: str
    dataset: str
    out: str
    options: tuple = field(default=())

    def __str__(self) -> str:
        return self.dataset


def expand_datasets(patterns: list[str]) -> list[Path]:
    """Dataset folders from paths and glob patterns (``*``, ``?``, ``[...]``, ``**``), each pattern's
    matches sorted, in the order given, repeats dropped. GraphcalError when a pattern matches no
    folder or a path is not a folder."""
    out: list[Path] = []
    for pat in patterns:
        if glob.has_magic(pat):
            hits = [Path(h) for h in sorted(glob.glob(pat, recursive=True)) if Path(h).is_dir()]
            if not hits:
                raise GraphcalError(f"{pat}: matches no dataset folder")
        else:
            if not Path(pat).is_dir():
                raise GraphcalError(f"{pat}: expected a dataset folder (dataset.yaml and its files), found "
                                    + ("a file" if Path(pat).exists() else "nothing"))
            hits = [Path(pat)]
        out += [h for h in hits if h not in out]
    if not out:
        raise GraphcalError("no dataset given")
    return out


def folder_names(datasets: list[Path]) -> list[str]:
    """One output folder name per dataset: its folder's name, ``-2``, ``-3``... added to repeats."""
    seen: dict[str, int] = {}
    names = []
    for d in datasets:
        base = d.resolve().name or "dataset"
        k = seen.get(base, 0) + 1
        seen[base] = k
        names.append(base if k == 1 else f"{base}-{k}")
    return names


def is_finished(command: str, out: str | Path) -> bool:
    """Whether ``out`` holds a finished output of ``command`` (its manifest, with its format)."""
    manifest, prefix = COMMANDS[command]
    return previous_output_files(Path(out), manifest, (), prefix) is not None


def _call(command: str, dataset: str, out: str, opts: dict):
    """The command's ``run`` on one dataset; returns its result (:mod:`graphcal.commands.result`)."""
    if command == "calibrate":
        from graphcal.commands import calibrate

        return calibrate.run(dataset, out, progress=False, **opts)
    if command == "diagnose":
        from graphcal.commands import diagnose

        return diagnose.run(dataset, out, progress=False)
    if command == "identify-legs":
        from graphcal.commands import identify_legs

        return identify_legs.run(dataset, out, progress=False, **opts)
    from graphcal.commands import track
    from graphcal.locomotion.estimator import TrackerConfig

    icp = opts.pop("icp", True)
    return track.run(dataset, out, progress=False, config=TrackerConfig(icp=icp), **opts)


@dataclass(frozen=True)
class TaskResult:
    """One finished task, as it comes back from its worker (plain values: it crosses process and
    Dask boundaries): the command's ``verdict``, ``files`` written and ``warnings``
    (:mod:`graphcal.commands.result`), and where and how long it ran (``compute_s``: wall s of the
    command's run; ``cpu_s``: CPU s of the worker process; ``host``, ``pid``)."""

    command: str
    dataset: str
    out: str
    verdict: str | None
    files: tuple[str, ...]
    warnings: tuple[str, ...]
    compute_s: float
    cpu_s: float
    host: str
    pid: int


def run_task(task: BatchTask) -> TaskResult:
    """Run one task (in a worker process): the command's ``run`` writes ``task.out`` atomically.
    Returns its :class:`TaskResult`; exceptions propagate."""
    t0, c0 = time.perf_counter(), time.process_time()
    result = _call(task.command, task.dataset, task.out, dict(task.options))
    return TaskResult(task.command, task.dataset, task.out, result.verdict, tuple(str(p) for p in result.files),
                      tuple(result.warnings), time.perf_counter() - t0, time.process_time() - c0,
                      socket.gethostname(), os.getpid())


def plan_tasks(command: str, patterns: list[str], out: Path, *, options: dict | None = None) -> list[BatchTask]:
    """The tasks of a batch (one per dataset folder matched by ``patterns``), outputs under ``out``."""
    if command not in COMMANDS:
        raise GraphcalError(f"batch: COMMAND must be one of {', '.join(COMMANDS)}, got {command!r}")
    opts = tuple(sorted((k, v) for k, v in (options or {}).items() if v is not None))
    bad = [k for k, _ in opts if k not in OPTIONS[command]]
    if bad:
        raise GraphcalError(f"batch {command}: option(s) {', '.join(bad)} do not apply to {command}")
    datasets = expand_datasets(patterns)
    # absolute paths: a Dask worker runs in its own working folder (the cluster must mount the same paths)
    return [BatchTask(command, str(d.absolute()), str((out / n).absolute()), opts)
            for d, n in zip(datasets, folder_names(datasets))]


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


class _Summary:
    """batch.yaml: every task's status, rewritten atomically as tasks end."""

    def __init__(self, out: Path, tasks: list[BatchTask], executor: dict, statuses: list[str]):
        self.path = out / "batch.yaml"
        self.results: list[TaskResult | None] = [None] * len(tasks)
        self.doc = {
            "format": BATCH_FORMAT,
            "units": {"wall_s": "s, from submission to result, seen by the caller (includes queueing)",
                      "compute_s": "s, the command's run in its worker (wall clock)",
                      "cpu_s": "s, CPU time of the worker process during the run (below compute_s when the "
                               "machine is busy)"},
            "command": tasks[0].command if tasks else None,
            "options": {k: v for k, v in (tasks[0].options if tasks else ())},
            "executor": executor,
            "started": _now(),
            "finished": None,
            "counts": {},
            "tasks": [{"dataset": t.dataset, "output": t.out, "status": s, "error": None, "wall_s": None,
                       "compute_s": None, "cpu_s": None, "worker": None} for t, s in zip(tasks, statuses)],
        }
        self.write()

    def record(self, index: int, outcome: TaskOutcome) -> None:
        e = self.doc["tasks"][index]
        e["status"] = outcome.status
        e["error"] = outcome.error
        e["wall_s"] = round(float(outcome.wall_s), 3) if outcome.wall_s == outcome.wall_s else None
        if outcome.value:
            self.results[index] = outcome.value
            e["compute_s"] = round(float(outcome.value.compute_s), 3)
            e["cpu_s"] = round(float(outcome.value.cpu_s), 3)
            e["worker"] = f"{outcome.value.host}:{outcome.value.pid}"
        if outcome.detail:
            e["traceback"] = outcome.detail
        self.write()

    def write(self, final: bool = False) -> None:
        counts: dict[str, int] = {}
        for e in self.doc["tasks"]:
            counts[e["status"]] = counts.get(e["status"], 0) + 1
        self.doc["counts"] = counts
        if final:
            self.doc["finished"] = _now()
        head = f"# graphcal batch ({BATCH_FORMAT}): the status of every task; durations in s\n"
        atomic_write_text(self.path, head + yaml.safe_dump(self.doc, sort_keys=False, width=120))


def run_batch(tasks: list[BatchTask], out: Path, **kwargs) -> dict:
    """:func:`run_batch_results` without the results: batch.yaml's document."""
    return run_batch_results(tasks, out, **kwargs)[0]


def run_batch_results(tasks: list[BatchTask], out: Path, *, scheduler: str | None = None, workers: int | None = None,
                      redo: bool = False, progress: bool = True,
                      task=run_task) -> tuple[dict, tuple[TaskResult | None, ...]]:
    """Run ``tasks`` (skipping finished ones unless ``redo``) and write ``out/batch.yaml``; returns
    its document and, per task, its :class:`TaskResult` (None: skipped, failed or not run).
    ``scheduler``/``workers``: see :func:`graphcal.batch.executor.open_executor`; ``task`` the
    function run per task (a module-level function; tests wrap :func:`run_task`)."""
    out.mkdir(parents=True, exist_ok=True)
    statuses = ["skipped" if not redo and is_finished(t.command, t.out) else "pending" for t in tasks]
    todo = [i for i, s in enumerate(statuses) if s == "pending"]
    with open_executor(scheduler, workers) as (executor, info):
        log.info("batch %s: %d dataset(s), %d to run, %d finished before (skipped); %s",
                 tasks[0].command if tasks else "-", len(tasks), len(todo), len(tasks) - len(todo), info.describe())
        summary = _Summary(out, tasks, info.to_dict(), statuses)
        fresh = None
        if info.kind == "local":
            fresh = local_executor
        # local: no more in flight than workers, so that a dead worker makes suspects of the tasks
        # that were running only (a broken pool fails every task queued in it)
        cap = info.workers if info.kind == "local" else (workers or None)
        try:
            run_tasks(task, [tasks[i] for i in todo], executor,
                      on_outcome=lambda o: summary.record(todo[o.index], o), progress=progress,
                      desc=f"batch {tasks[0].command if tasks else ''}", max_in_flight=cap, fresh_pool=fresh,
                      pool_size=info.workers)
        except KeyboardInterrupt:  # what finished is in place; the rest stays "pending" for a rerun
            summary.write(final=True)
            raise InterruptedAfterWrite(summary.path) from None
    summary.write(final=True)
    return summary.doc, tuple(summary.results)


def write_fleet(tasks: list[BatchTask], out: Path, command: str, doc: dict | None = None) -> tuple[Path, Path, list]:
    """fleet.html and fleet.csv over the finished outputs of ``tasks``; returns their paths and the
    flags. ``doc`` (batch.yaml's document) adds the tasks that did not finish to the page."""
    from graphcal.batch.fleet import ALPHA, fleet_flags, read_robot
    from graphcal.report.fleet_page import fleet_csv, fleet_html

    robots = [read_robot(t.out) for t in tasks if is_finished(t.command, t.out)]
    table, flags = fleet_flags(robots)
    html_path, csv_path = out / "fleet.html", out / "fleet.csv"
    atomic_write_text(csv_path, fleet_csv(robots, table, ALPHA))
    unfinished = [(e["dataset"], e["status"], e["error"] or "") for e in (doc or {}).get("tasks", [])
                  if e["status"] not in ("done", "skipped")]
    atomic_write_text(html_path, fleet_html(robots, table, flags, title=f"graphcal fleet: {command} over "
                                            f"{len(robots)} dataset(s) in {out}", unfinished=unfinished))
    return html_path, csv_path, flags


@dataclass(frozen=True)
class BatchResult:
    """What ``graphcal batch`` did.

    Attributes:
        command: the command run over the datasets.
        out: the batch folder.
        doc: batch.yaml's document (every task's status, error, durations, worker).
        results: per task (batch.yaml's order), its :class:`TaskResult` when it ran and finished
            in this run, else None (skipped: finished before; failed; worker died).
        flags: the fleet's flagged values (:func:`graphcal.batch.fleet.fleet_flags`).
        files: batch.yaml, fleet.html, fleet.csv.
        warnings: one per task that did not finish (``status: dataset: error``), one per flag.
        verdict: none (None).
    """

    command: str
    out: Path
    doc: dict
    results: tuple[TaskResult | None, ...]
    flags: tuple
    files: tuple[Path, ...]
    warnings: tuple[str, ...]
    verdict: str | None = None

    @property
    def statuses(self) -> dict[str, str]:
        """Dataset (as in batch.yaml) -> its status (done, skipped, failed, worker died, pending)."""
        return {e["dataset"]: e["status"] for e in self.doc["tasks"]}

    def summary_text(self) -> str:
        """Counts, the tasks that did not finish, the flagged robots, the files."""
        counts = ", ".join(f"{n} {s}" for s, n in self.doc["counts"].items())
        lines = [f"batch {self.command}: {len(self.doc['tasks'])} dataset(s) on {self.doc['executor']['kind']} "
                 f"({counts}); wrote {self.out}"]
        lines += [f"  {w}" for w in _unfinished(self.doc)]
        lines += [f"  flagged {f.text()}" for f in self.flags]
        _, html, csv = self.files
        lines.append(f"  summary {self.out / 'batch.yaml'}; fleet {html}, {csv}")
        return "\n".join(lines)


def _unfinished(doc: dict) -> list[str]:
    """``status: dataset: error`` of each task of batch.yaml's ``doc`` that did not finish."""
    return [f"{e['status']}: {e['dataset']}: {e['error']}" for e in doc["tasks"]
            if e["status"] not in ("done", "skipped")]


def run(command: str, datasets: list[str], out_dir: str | Path, *, scheduler: str | None = None,
        workers: int | None = None, redo: bool = False, options: dict | None = None,
        progress: bool = True) -> BatchResult:
    """``graphcal batch``: run ``command`` over ``datasets`` (folders or globs) into ``out_dir``;
    returns a :class:`BatchResult` (its summary: counts, failures, flagged robots). See the module
    docstring.

    Args:
        command: calibrate, diagnose, identify-legs or track.
        datasets: dataset folders or glob patterns.
        out_dir: the batch's folder (created): one sub-folder per dataset, batch.yaml, fleet.html, fleet.csv.
        scheduler: Dask scheduler address (default ``$DASK_SCHEDULER_ADDRESS``; none: local pool).
        workers: local pool size (default: the machine's CPUs); with Dask, the most tasks in flight.
        redo: run datasets whose output is finished again.
        options: the command's options (:data:`OPTIONS`; SI units).
        progress: a progress bar over the tasks.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise GraphcalError(f"--out {out}: exists and is not a folder")
    tasks = plan_tasks(command, list(datasets), out, options=options)
    doc, results = run_batch_results(tasks, out, scheduler=scheduler, workers=workers, redo=redo, progress=progress)
    html, csv, flags = write_fleet(tasks, out, command, doc)
    return BatchResult(command=command, out=out, doc=doc, results=results, flags=tuple(flags),
                       files=(out / "batch.yaml", html, csv),
                       warnings=tuple(_unfinished(doc)) + tuple(f"flagged {f.text()}" for f in flags))
