"""Monte Carlo of the calibration from a walk (issue 43): N simulated qingzhui tripod walks, each
with its own seed, CAD error (15 mm / 1.5 deg per axis), camera delay drawn in [15, 40] ms and the
stance read from the joint torques; every run calibrated by ``graphcal calibrate``'s command
function. Prints per run the extrinsic error, NEES, the time offset's error and sigma, and the
summary (mean NEES against chi2(6)'s 95 % interval for the mean, share of runs inside the 0.999
bound, offset errors in sigma).

    .venv/bin/python bench/walking_calibration_mc.py [--runs 20] [--duration 15] [--first-seed 100] [--json PATH]
"""

from __future__ import annotations

import argparse
import csv
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def _walk(root: Path, seed: int, duration_s: float) -> tuple[Path, float]:
    from graphcal.simulation.walking import WalkingConfig, simulate_walking
    from graphcal.simulation.write import write_walking

    delay = float(np.round(np.random.default_rng([seed, 43]).uniform(0.015, 0.040), 3))
    cfg = WalkingConfig(program="tripod-walk", seed=seed, duration_s=duration_s, cloud_rate_hz=15.0,
                        cad_error_m=0.015, cad_error_rad=float(np.radians(1.5)), camera_delay_s=delay)
    out = write_walking(simulate_walking(cfg), root / f"walk{seed}")
    ts = out / "timeseries.csv"
    rows = list(csv.reader(ts.open()))
    keep = [i for i, h in enumerate(rows[0]) if not h.startswith("contact_")]  # stance from the torques
    with ts.open("w", newline="") as f:
        csv.writer(f).writerows([[r[i] for i in keep] for r in rows])
    return out, delay


def main() -> None:
    from graphcal.commands import calibrate
    from graphcal.stats import ppf

    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--duration", type=float, default=15.0)
    ap.add_argument("--first-seed", type=int, default=100)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(a.first_seed, a.first_seed + a.runs):
            walk, delay = _walk(Path(tmp), seed, a.duration)
            t0 = time.perf_counter()
            r = calibrate.run(walk, Path(tmp) / f"cal{seed}", progress=False)
            s, t = r.calibration.sensors["depth"], r.truth["depth"]
            row = {"seed": seed, "delay_ms": 1e3 * delay, "rot_err_deg": t["rotation_error_deg"],
                   "trans_err_mm": t["translation_error_mm"], "nees": t["nees"],
                   "offset_err_ms": t.get("time_offset_error_ms"), "verdict": r.verdict,
                   "offset_sigma_ms": None if s.time_offset_sigma_s is None else 1e3 * s.time_offset_sigma_s,
                   "seconds": time.perf_counter() - t0}
            runs.append(row)
            print(json.dumps(row), flush=True)
    nees = np.array([r["nees"] for r in runs])
    z = np.array([r["offset_err_ms"] / r["offset_sigma_ms"] for r in runs if r["offset_sigma_ms"]])
    n = len(nees)
    lo, hi = ppf(0.025, 6 * n) / n, ppf(0.975, 6 * n) / n
    summary = {"runs": n, "mean_nees": float(nees.mean()), "mean_nees_95": [float(lo), float(hi)],
               "inside_999": float(np.mean(nees < ppf(0.999, 6))),
               "max_rot_err_deg": max(r["rot_err_deg"] for r in runs),
               "max_trans_err_mm": max(r["trans_err_mm"] for r in runs),
               "max_abs_offset_err_ms": max(abs(r["offset_err_ms"]) for r in runs),
               "offset_err_over_sigma_rms": float(np.sqrt(np.mean(z**2))) if len(z) else None,
               "median_seconds": float(np.median([r["seconds"] for r in runs]))}
    print(json.dumps(summary, indent=1))
    if a.json:
        a.json.write_text(json.dumps({"runs": runs, "summary": summary}, indent=1))


if __name__ == "__main__":
    main()
