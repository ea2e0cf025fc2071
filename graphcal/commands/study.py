"""``graphcal study --robot R --program P --runs N --out DIR``: Monte Carlo of a station program.

N independent simulated calibrations (seeds S .. S+N-1; planes written from the simulated clouds,
``cloud_stride`` 8, as bench/calibration_nees.py), each one task on the batch executor (a local
process pool, or a Dask cluster: :mod:`graphcal.batch.executor`), each calibrated with the product's
defaults (noise learned). Per sensor and per body axis (rx, ry, rz about, x, y, z along the BODY axes)
the study reports the RMS and mean error (deg, mm), the mean reported 1-sigma, and the mean
(error/sigma)^2 -- 1 when the reported sigma is honest, with its 95 % interval chi2.ppf(., n)/n --
and the mean NEES (6 dof; 95 % interval chi2.ppf(., 6n)/n), with plots. Files in DIR (written as one
atomic set; DIR new, empty, or a previous study): ``study.yaml`` (format ``graphcal-study/1``),
``runs.csv``, ``nees_SENSOR.png``, ``errors_SENSOR.png``, ``report.html``.

The simulated datasets live in a scratch folder on the worker and are removed after each run.
"""

from __future__ import annotations

import csv
import io
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from graphcal.batch.executor import local_executor, open_executor
from graphcal.batch.run import run_tasks
from graphcal.errors import GraphcalError
from graphcal.io.atomic import atomic_directory, atomic_write_bytes, check_command_output

__all__ = ["STUDY_FORMAT", "AXES", "StudyJob", "StudyResult", "study_task", "summarise", "run"]

STUDY_FORMAT = "graphcal-study/1"
AXES = ("rx", "ry", "rz", "x", "y", "z")
_UNITS = {"rx": "deg", "ry": "deg", "rz": "deg", "x": "mm", "y": "mm", "z": "mm"}


@dataclass(frozen=True)
class StudyJob:
    """One Monte Carlo run: simulate ``robot`` doing ``program`` with ``seed`` (``n_stations`` for the
    random program; ``effects`` as (cause, {key: text}) pairs, SI units), write planes, calibrate."""

    robot: str
    program: str
    seed: int
    n_stations: int | None = None
    effects: tuple = ()
    cloud_stride: int = 8

    def __str__(self) -> str:
        return f"seed {self.seed}"


def study_task(job: StudyJob) -> dict:
    """One run (in a worker): simulate, write the dataset to a scratch folder, calibrate, compare.
    Returns ``{"seed", "simulate_s", "calibrate_s", "sensors": {name: {"error", "sigma", "z2", "nees"}}}``
    (:func:`graphcal.solvers.covariance.extrinsic_errors`: deg and mm along the body axes)."""
    from graphcal.calibration.calibrate import calibrate
    from graphcal.commands import simulate
    from graphcal.geometry import pose_from_xyz_quat_wxyz
    from graphcal.solvers.covariance import extrinsic_errors

    tmp = Path(tempfile.mkdtemp(prefix=f"graphcal-study-{job.seed}-"))
    try:
        t0 = time.perf_counter()
        simulate.run(robot=job.robot, program=job.program, ground="level", out_dir=tmp / "ds", seed=job.seed,
                     n_stations=job.n_stations, output="planes", cloud_stride=job.cloud_stride,
                     effects=[(c, dict(p)) for c, p in job.effects], progress=False)
        truth = yaml.safe_load((tmp / "ds" / "truth.yaml").read_text(encoding="utf-8"))
        t1 = time.perf_counter()
        result = calibrate(tmp / "ds", progress=False)
        t2 = time.perf_counter()
        sensors = {}
        for name, est in result.sensors.items():
            t = truth["sensors"][name]["T_body_sensor"]
            T_true = pose_from_xyz_quat_wxyz(t["xyz"], t["quaternion_wxyz"])
            e = extrinsic_errors(est.T_body_sensor, T_true, est.covariance)
            sensors[name] = {"error": e["error"].tolist(), "sigma": e["sigma"].tolist(), "z2": e["z2"].tolist(),
                             "nees": e["nees"]}
        return {"seed": job.seed, "simulate_s": t1 - t0, "calibrate_s": t2 - t1, "sensors": sensors}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def summarise(runs: list[dict]) -> dict:
    """Per sensor: runs, mean NEES and its 95 % interval, per axis RMS/mean error, mean sigma, mean
    (error/sigma)^2 with its 95 % interval (units: deg for rx ry rz, mm for x y z)."""
    from scipy.stats import chi2

    out = {}
    for name in sorted({s for r in runs for s in r["sensors"]}):
        rs = [r["sensors"][name] for r in runs if name in r["sensors"]]
        n = len(rs)
        err = np.array([r["error"] for r in rs])
        sig = np.array([r["sigma"] for r in rs])
        z2 = np.array([r["z2"] for r in rs])
        v = np.array([r["nees"] for r in rs])
        lo, hi = (chi2.ppf([0.025, 0.975], 6 * n) / n).tolist()
        lo1, hi1 = (chi2.ppf([0.025, 0.975], n) / n).tolist()
        mean = float(v.mean())
        out[name] = {
            "runs": n,
            "nees_mean": mean, "nees_median": float(np.median(v)), "nees_interval_95": [lo, hi],
            "nees_verdict": "honest" if lo <= mean <= hi else ("conservative (sigma too large)" if mean < lo
                                                               else "overconfident (sigma too small)"),
            "per_axis": {a: {"unit": _UNITS[a], "rms_error": float(np.sqrt(np.mean(err[:, k] ** 2))),
                             "mean_error": float(err[:, k].mean()), "mean_sigma": float(sig[:, k].mean()),
                             "mean_z2": float(z2[:, k].mean())} for k, a in enumerate(AXES)},
            "z2_interval_95": [lo1, hi1],
        }
    return out


def _figures(runs: list[dict], summary: dict) -> dict[str, bytes]:
    from scipy.stats import chi2

    from graphcal.report.plots import figure_png, new_figure

    pngs = {}
    for name, s in summary.items():
        rs = [r["sensors"][name] for r in runs if name in r["sensors"]]
        v = np.array([r["nees"] for r in rs])
        fig = new_figure(6.5, 3.2)
        ax = fig.add_subplot(1, 1, 1)
        ax.hist(v, bins=max(5, min(40, len(v) // 2)), density=True, color="#4a7ab5", alpha=0.7, label="runs")
        x = np.linspace(0, max(float(v.max()), chi2.ppf(0.999, 6)), 200)
        ax.plot(x, chi2.pdf(x, 6), "k-", lw=1.2, label="chi2(6), honest")
        ax.axvline(s["nees_mean"], color="#c03030", lw=1.2, label=f"mean {s['nees_mean']:.2f}")
        ax.set_xlabel("NEES (6 dof)")
        ax.set_ylabel("density")
        ax.set_title(f"{name}: NEES over {len(v)} runs")
        ax.legend(fontsize=8)
        pngs[f"nees_{name}.png"] = figure_png(fig)
        err = np.array([r["error"] for r in rs])
        sig = np.array([r["sigma"] for r in rs])
        fig = new_figure(9.0, 4.8)
        for k, a in enumerate(AXES):
            ax = fig.add_subplot(2, 3, k + 1)
            ax.plot(np.arange(len(err)), err[:, k], "o", ms=3, color="#4a7ab5", label="error")
            ax.plot(np.arange(len(err)), 2 * sig[:, k], "-", color="#999", lw=0.8, label="±2 sigma")
            ax.plot(np.arange(len(err)), -2 * sig[:, k], "-", color="#999", lw=0.8)
            ax.set_title(f"{a} ({_UNITS[a]}): mean z² {s['per_axis'][a]['mean_z2']:.2f}", fontsize=9)
            ax.set_xlabel("run", fontsize=8)
        fig.axes[0].legend(fontsize=7)
        pngs[f"errors_{name}.png"] = figure_png(fig)
    return pngs


def _runs_csv(runs: list[dict]) -> str:
    buf = io.StringIO()
    buf.write("# graphcal study runs: error of the truth relative to the estimate along the BODY axes "
              "(rx ry rz deg, x y z mm), reported 1-sigma in the same units, NEES (6 dof); times in s\n")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["seed", "sensor", *[f"error_{a}" for a in AXES], *[f"sigma_{a}" for a in AXES], "nees",
                "simulate_s", "calibrate_s"])
    for r in sorted(runs, key=lambda r: r["seed"]):
        for name, s in r["sensors"].items():
            w.writerow([r["seed"], name, *[f"{x:.6g}" for x in s["error"]], *[f"{x:.6g}" for x in s["sigma"]],
                        f"{s['nees']:.6g}", f"{r['simulate_s']:.3f}", f"{r['calibrate_s']:.3f}"])
    return buf.getvalue()


def _check_out(out: Path) -> None:
    check_command_output(out, "study.yaml", ("study.yaml", "runs.csv", "report.html"), "graphcal-study/",
                         what="graphcal study")


@dataclass(frozen=True)
class StudyResult:
    """What ``graphcal study`` found.

    Attributes:
        doc: study.yaml's document (setup, executor, per sensor NEES and per-axis errors, failed runs).
        runs: the finished runs (:func:`study_task`'s dicts: seed, times, per sensor errors).
        out: the study folder.
        files: the files written (study.yaml, runs.csv, plots, report.html).
        warnings: one per run that did not finish (``status: seed N: error``).
        executor: where the runs ran, in words.
        verdict: none (None); per sensor, ``nees_verdicts``.
    """

    doc: dict
    runs: tuple[dict, ...]
    out: Path
    files: tuple[Path, ...]
    warnings: tuple[str, ...]
    executor: str
    verdict: str | None = None

    @property
    def nees_verdicts(self) -> dict[str, str]:
        """Sensor -> honest, conservative (sigma too large) or overconfident (sigma too small)."""
        return {name: s["nees_verdict"] for name, s in self.doc["sensors"].items()}

    def summary_text(self) -> str:
        """Runs and time, then per sensor the mean NEES, its interval and verdict, the RMS error per axis."""
        d = self.doc
        n_jobs = d["runs_done"] + len(d["runs_failed"])
        lines = [f"study {d['setup']['robot']} / {d['setup']['program']}: {d['runs_done']} of {n_jobs} runs in "
                 f"{d['wall_s']:.0f} s on {self.executor}; wrote {self.out}"]
        for name, s in d["sensors"].items():
            pa = s["per_axis"]
            lines.append(f"  {name}: NEES mean {s['nees_mean']:.2f} (95 % [{s['nees_interval_95'][0]:.2f}, "
                         f"{s['nees_interval_95'][1]:.2f}]: {s['nees_verdict']}); RMS error "
                         + " ".join(f"{a} {pa[a]['rms_error']:.3g}" for a in AXES) + " (deg, mm)")
        lines += [f"  {w}" for w in self.warnings]
        return "\n".join(lines)


def run(*, robot: str, program: str, runs: int, out_dir: str | Path, first_seed: int = 0,
        n_stations: int | None = None, effects=(), cloud_stride: int = 8, scheduler: str | None = None,
        workers: int | None = None, progress: bool = True) -> StudyResult:
    """``graphcal study`` (module docstring). Returns a :class:`StudyResult` (its summary: NEES and
    RMS error per sensor).

    Args:
        robot, program: built-in robot model and station program (as ``graphcal simulate``).
        runs: number of seeds (>= 2); seeds ``first_seed`` .. ``first_seed + runs - 1``.
        out_dir: study folder (new, empty, or a previous study: replaced at the end).
        n_stations: stations of the random program.
        effects: (cause, {key: text}) pairs hidden in every run (``--effect``; SI units).
        cloud_stride: camera pixel stride of the simulated clouds the planes are fitted to.
        scheduler, workers: the executor (:func:`graphcal.batch.executor.open_executor`).
        progress: a progress bar over the runs.
    """
    from graphcal.report.study_page import study_html

    out = Path(out_dir)
    if isinstance(runs, bool) or int(runs) < 2:
        raise GraphcalError(f"--runs must be >= 2 (a Monte Carlo needs runs to average), got {runs}")
    if first_seed < 0:
        raise GraphcalError(f"--first-seed must be >= 0, got {first_seed}")
    _check_out(out)
    eff = tuple((str(c), tuple(sorted(dict(p).items()))) for c, p in effects)
    jobs = [StudyJob(robot, program, first_seed + i, n_stations, eff, cloud_stride) for i in range(int(runs))]
    t0 = time.perf_counter()
    with open_executor(scheduler, workers) as (executor, info):
        outcomes = run_tasks(study_task, jobs, executor, progress=progress, desc="study",
                             fresh_pool=local_executor if info.kind == "local" else None, pool_size=info.workers,
                             max_in_flight=info.workers if info.kind == "local" else None)
    wall = time.perf_counter() - t0
    done = [o.value for o in outcomes if o.status == "done"]
    failed = [{"seed": jobs[o.index].seed, "status": o.status, "error": o.error} for o in outcomes if o.status != "done"]
    if len(done) < 2:
        raise GraphcalError(f"study: only {len(done)} of {len(jobs)} runs finished; first error: "
                            f"{failed[0]['error'] if failed else '-'}")
    summary = summarise(done)
    doc = {
        "format": STUDY_FORMAT,
        "units": {"rx, ry, rz": "deg, about the BODY axes", "x, y, z": "mm, along the BODY axes",
                  "error": "truth relative to the estimate (Log(T_est^-1 T_true) rotated to the body axes)",
                  "nees": "xi^T inv(cov) xi, 6 dof (honest: mean 6)", "mean_z2": "mean (error/sigma)^2 (honest: 1)",
                  "times": "s"},
        "setup": {"robot": robot, "program": program, "n_stations": n_stations, "seeds": [jobs[0].seed, jobs[-1].seed],
                  "effects": [{"cause": c, "parameters": dict(p)} for c, p in eff], "cloud_stride": cloud_stride,
                  "output": "planes", "calibration": "CalibrationOptions() defaults (noise learned)"},
        "executor": info.to_dict(),
        "wall_s": wall,
        "runs_done": len(done),
        "runs_failed": failed,
        "calibrate_s_mean": float(np.mean([r["calibrate_s"] for r in done])),
        "simulate_s_mean": float(np.mean([r["simulate_s"] for r in done])),
        "sensors": summary,
    }
    pngs = _figures(done, summary)
    files = {"study.yaml": (f"# graphcal study ({STUDY_FORMAT}): Monte Carlo of {robot} / {program}; "
                            "angles deg, lengths mm, times s\n" + yaml.safe_dump(doc, sort_keys=False, width=120)).encode(),
             "runs.csv": _runs_csv(done).encode(), **pngs}
    doc["output_files"] = sorted(list(files) + ["report.html"])
    files["study.yaml"] = (f"# graphcal study ({STUDY_FORMAT}): Monte Carlo of {robot} / {program}; "
                           "angles deg, lengths mm, times s\n" + yaml.safe_dump(doc, sort_keys=False, width=120)).encode()
    files["report.html"] = study_html(doc, pngs, title=f"graphcal study: {robot}, {program}, {len(done)} runs").encode()
    with atomic_directory(out, overwrite=True) as tmp:
        for name, data in files.items():
            atomic_write_bytes(tmp / name, data)
        _check_out(out)
    return StudyResult(doc=doc, runs=tuple(done), out=out, files=tuple(out / name for name in doc["output_files"]),
                       warnings=tuple(f"{f['status']}: seed {f['seed']}: {f['error']}" for f in failed),
                       executor=info.describe())
