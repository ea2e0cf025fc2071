"""``graphcal diagnose`` against ``graphcal calibrate`` on the same datasets, side by side: the
issue's budget is diagnose at most 3x calibrate's time. Each dataset (simulated here: the
battery's ``random`` program, 48 stations in 3 sessions, planes only) is calibrated and diagnosed
in this process, each up to the dict its command writes (calibration.yaml's, diagnosis.json's): CPU
and wall time of each, the median of ``--repeat`` runs taken alternately, after one warm-up run;
BLAS on one thread (its spinning threads would count as CPU time). ``--seeds N``: N datasets per
case (seeds 200 + case + 10 j; the first is the one earlier versions of this bench ran); per case
the ratio of each dataset, and the worst over all of them.

``--commands``: the whole commands instead, as a user runs them (``graphcal calibrate --quiet --out
DIR DATASET`` against ``graphcal diagnose --quiet --out DIR DATASET``, each a new process: the
imports, reading the dataset, the computation, and every file each command writes, its HTML report
with its figures among them), each into a new output folder; CPU time is the child process's own
(user + system, from the operating system's accounting of the finished process).

    .venv/bin/python bench/diagnose_speed.py [--cases clean,joint_offset,foot_radius] [--repeat 3] [--seeds 3]
    .venv/bin/python bench/diagnose_speed.py --cases outlier_stations --seed-range 200-229 [--commands]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # CPU time counts every BLAS thread's spinning: one each

import argparse  # noqa: E402
import resource  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from graphcal.calibration.calibrate import calibrate  # noqa: E402
from graphcal.commands.simulate import run as simulate_to_folder  # noqa: E402
from graphcal.diagnosis import diagnose  # noqa: E402
from graphcal.report.calibration_yaml import calibration_to_dict  # noqa: E402
from graphcal.report.diagnosis_json import diagnosis_to_dict  # noqa: E402


def calibrate_to_dict(folder: Path) -> dict:
    """What ``graphcal calibrate`` computes before writing its files: the result and calibration.yaml's dict."""
    return calibration_to_dict(calibrate(folder))


def diagnose_to_dict(folder: Path) -> dict:
    """What ``graphcal diagnose`` computes before writing its files: the diagnosis and diagnosis.json's dict
    (which holds the final model's verdict, judged again when it does not fit)."""
    return diagnosis_to_dict(diagnose(folder))


def command_job(command: str):
    """A job running ``graphcal <command> --quiet --out <new folder> <dataset>`` as a new process, as a
    user runs it; its output folder is removed afterwards. A failed command stops the bench with its
    last line of stderr."""

    def job(folder: Path) -> None:
        out = folder.parent / f"{folder.name}-{command}-out"
        shutil.rmtree(out, ignore_errors=True)
        run = subprocess.run([sys.executable, "-m", "graphcal", command, "--quiet", "--out", str(out), str(folder)],
                             capture_output=True, text=True)
        shutil.rmtree(out, ignore_errors=True)
        if run.returncode != 0:
            last = (run.stderr.strip().splitlines() or ["(no stderr)"])[-1]
            raise SystemExit(f"graphcal {command} {folder}: exit {run.returncode}: {last}")

    return job


def children_cpu() -> float:
    """User + system CPU seconds of every finished child process of this one so far."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def one(folder: Path, robot: str, effect: str, seed: int, repeat: int,
        commands: bool = False) -> tuple[float, float, float, float]:
    """(calibrate CPU s, diagnose CPU s, calibrate wall s, diagnose wall s), each the median of ``repeat``
    runs taken alternately, on one simulated dataset; ``commands``: the whole commands as processes."""
    simulate_to_folder(robot=robot, program="random", ground="level", out_dir=folder, seed=seed, n_stations=48,
                       n_sessions=3, output="planes", cloud_stride=8, progress=False,
                       effects=[] if effect == "clean" else [(effect, {})], session_heading_step_deg=40.0,
                       overwrite=True)
    jobs = (command_job("calibrate"), command_job("diagnose")) if commands else (calibrate_to_dict, diagnose_to_dict)
    cpu = children_cpu if commands else time.process_time
    times = []
    for _ in range(repeat):
        row = []
        for job in jobs:
            t0, w0 = cpu(), time.perf_counter()
            job(folder)
            row += [cpu() - t0, time.perf_counter() - w0]
        times.append(row)
    t_cal, w_cal, t_diag, w_diag = np.median(np.array(times), axis=0)
    return float(t_cal), float(t_diag), float(w_cal), float(w_diag)


def main(cases: tuple[str, ...], repeat: int = 3, seeds: int = 1,
         seed_range: tuple[int, int] | None = None, commands: bool = False) -> list[tuple]:
    """Time every case on its datasets; ``seed_range`` (first, last): these seeds for every case
    instead of 200 + case + 10 j; ``commands``: the whole commands (module docstring)."""
    rows = []
    print("timing " + ("the whole commands, each a new process" if commands else
                       "calibrate and diagnose in this process, up to the dicts their commands write"), flush=True)
    with tempfile.TemporaryDirectory(prefix="graphcal-speed-") as tmp:
        one(Path(tmp) / "warm", "octopus", "clean", 1, 1, commands)
        for k, effect in enumerate(cases):
            robot = ("octopus", "qingzhui")[k % 2]
            chosen = range(seed_range[0], seed_range[1] + 1) if seed_range else [200 + k + 10 * j for j in range(seeds)]
            for j, seed in enumerate(chosen):
                t_cal, t_diag, w_cal, w_diag = one(Path(tmp) / f"{effect}_{k}_{j}", robot, effect, seed, repeat,
                                                   commands)
                rows.append((effect, robot, seed, t_cal, t_diag, t_diag / t_cal, w_diag / w_cal))
                print(f"{effect:18s} {robot:9s} seed {seed}  CPU: calibrate {t_cal:6.2f} s  diagnose {t_diag:6.2f} s  "
                      f"ratio {t_diag / t_cal:4.2f}x | wall: {w_cal:6.2f} s  {w_diag:6.2f} s  ratio "
                      f"{w_diag / w_cal:4.2f}x", flush=True)
    worst = max(rows, key=lambda r: r[5])
    ratios = [r[5] for r in rows]
    print(f"worst ratio diagnose / calibrate: {worst[5]:.2f}x ({worst[0]}, seed {worst[2]}; budget 3x); median "
          f"{float(np.median(ratios)):.2f}x; {sum(x <= 3.0 for x in ratios)} of {len(ratios)} within 3x")
    return rows


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="clean,joint_offset,foot_radius,session_offset,joint_compliance,"
                                        "sensor_range_scale,outlier_stations")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each, alternately; the median is reported")
    ap.add_argument("--seeds", type=int, default=3, help="datasets per case (seeds 200 + case + 10 j)")
    ap.add_argument("--seed-range", default=None, metavar="FIRST-LAST",
                    help="these seeds (inclusive) for every case instead; e.g. --cases outlier_stations "
                         "--seed-range 200-229, the thirty outlier datasets of docs/diagnosis.md")
    ap.add_argument("--commands", action="store_true",
                    help="time the whole commands (graphcal calibrate / diagnose as new processes, every file "
                         "written) instead of the computation in this process")
    args = ap.parse_args()
    span = None
    if args.seed_range:
        try:
            first, last = (int(x) for x in args.seed_range.split("-"))
        except ValueError:
            ap.error(f"--seed-range: expected FIRST-LAST (two integers), got {args.seed_range!r}")
        span = (first, last)
    main(tuple(args.cases.split(",")), args.repeat, args.seeds, span, args.commands)
