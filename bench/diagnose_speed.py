"""``graphcal diagnose`` against ``graphcal calibrate`` on the same datasets, side by side: the
issue's budget is diagnose at most 3x calibrate's time. Each dataset (simulated here: the
battery's ``random`` program, 48 stations in 3 sessions, planes only) is calibrated and diagnosed
in this process, CPU and wall time of each, after one warm-up run.

    .venv/bin/python bench/diagnose_speed.py [--cases clean,joint_offset,foot_radius]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from graphcal.calibration.calibrate import calibrate
from graphcal.commands.simulate import run as simulate_to_folder
from graphcal.diagnosis import diagnose


def one(folder: Path, robot: str, effect: str, seed: int) -> tuple[float, float, float, float]:
    """(calibrate CPU s, diagnose CPU s, calibrate wall s, diagnose wall s) on one simulated dataset."""
    simulate_to_folder(robot=robot, program="random", ground="level", out_dir=folder, seed=seed, n_stations=48,
                       n_sessions=3, output="planes", cloud_stride=8, progress=False,
                       effects=[] if effect == "clean" else [(effect, {})], session_heading_step_deg=40.0,
                       overwrite=True)
    t0, w0 = time.process_time(), time.perf_counter()
    calibrate(folder)
    t_cal, w_cal = time.process_time() - t0, time.perf_counter() - w0
    t0, w0 = time.process_time(), time.perf_counter()
    diagnose(folder)
    return t_cal, time.process_time() - t0, w_cal, time.perf_counter() - w0


def main(cases: tuple[str, ...]) -> list[tuple]:
    rows = []
    with tempfile.TemporaryDirectory(prefix="graphcal-speed-") as tmp:
        one(Path(tmp) / "warm", "octopus", "clean", 1)
        for k, effect in enumerate(cases):
            robot = ("octopus", "qingzhui")[k % 2]
            t_cal, t_diag, w_cal, w_diag = one(Path(tmp) / f"{effect}_{k}", robot, effect, 200 + k)
            rows.append((effect, robot, t_cal, t_diag, t_diag / t_cal, w_diag / w_cal))
            print(f"{effect:18s} {robot:9s} CPU: calibrate {t_cal:6.2f} s  diagnose {t_diag:6.2f} s  ratio "
                  f"{t_diag / t_cal:4.1f}x | wall: {w_cal:6.2f} s  {w_diag:6.2f} s  ratio {w_diag / w_cal:4.1f}x")
    worst = max(r[4] for r in rows)
    print(f"worst ratio diagnose / calibrate: {worst:.1f}x (budget 3x)")
    return rows


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="clean,joint_offset,foot_radius,session_offset")
    main(tuple(ap.parse_args().cases.split(",")))
