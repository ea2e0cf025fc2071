"""Benchmark: the legged EKF's real-time factor on 1 kHz data, one core, against the obvious
per-sample implementation, side by side in this process.

Data: the simulated qingzhui walks (graphcal.simulation.walking) in memory: the 20 m level walk
(clouds at 10 Hz) and the stairs sequence (clouds at 10 Hz). Timed round-robin (load changes hit
every variant alike), ``--repeats`` times each; medians. The real-time factor is data duration /
processing time (support detection, kinematics, preintegration, the loop and ICP included; file
reading excluded). Variants:

* graphcal ``run_filter`` default: IMU preintegrated between updates, stance update every 5th
  sample (200 Hz), ICP between keyframes (every 0.3 m);
* the same without ICP;
* the same with a stance update at every sample (1 kHz);
* baseline: the obvious implementation, filterpy ``predict`` and ``update`` at every sample (the
  same model and code, graphcal's filter with ``stance_every=1``: covariance propagated and
  kinematics fused at 1 kHz, filterpy's Joseph update);
* machine unit: a bare numpy dead-reckoning loop (R <- R Exp(w dt), v, p) at 1 kHz, no filter:
  what a 1 kHz Python loop costs here at all.

Also reported: drift (% of distance) and APE of each variant against the truth.

Target (issue 6): >= 10x real time on 1 kHz data, one core.

Usage: .venv/bin/python bench/ekf.py [--repeats R] [--distance M] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

TARGET_RTF = 10.0


def _dead_reckoning(inp) -> float:
    """Bare 1 kHz numpy loop: the machine's cost of touching every sample from Python."""
    from graphcal.geometry import so3_exp as _exp

    t0 = time.perf_counter()
    R = np.eye(3)
    v = np.zeros(3)
    p = np.zeros(3)
    g = np.array([0.0, 0.0, -9.80665])
    dts = np.diff(inp.times, prepend=inp.times[0])
    for k in range(1, len(inp.times)):
        a = R @ inp.accel[k] + g
        p = p + v * dts[k] + 0.5 * a * dts[k] ** 2
        v = v + a * dts[k]
        R = R @ _exp(inp.gyro[k] * dts[k])
    return time.perf_counter() - t0


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=2, help="timed runs of each variant (default 2)")
    ap.add_argument("--distance", type=float, default=20.0, help="level walk length, m (default 20)")
    ap.add_argument("--json", type=Path, default=None, help="write the results to this JSON file")
    args = ap.parse_args(argv)

    import filterpy

    from graphcal.locomotion.estimator import TrackerConfig, run_filter
    from graphcal.locomotion.metrics import pose_errors
    from graphcal.locomotion.track_inputs import inputs_from_walking
    from graphcal.simulation.walking import WalkingConfig, simulate_walking

    walks = {
        f"level {args.distance:g} m": simulate_walking(WalkingConfig(distance_m=args.distance, cloud_rate_hz=10.0)),
        "stairs": simulate_walking(WalkingConfig(program="tripod-stairs", cloud_rate_hz=10.0)),
    }
    variants = {
        "graphcal default (200 Hz updates, ICP)": TrackerConfig(),
        "graphcal, no ICP": TrackerConfig(icp=False),
        # graphcal's filter is filterpy's predict and update (locomotion/ekf.py): with the stance
        # update at every sample it is the obvious implementation, the baseline
        "baseline: filterpy predict+update every sample (stance update every sample)": TrackerConfig(stance_every=1),
    }
    rows = []
    for wname, walk in walks.items():
        inp = inputs_from_walking(walk)
        duration = float(walk.times[-1] - walk.times[0])

        def run(cfg):
            return run_filter(inp, cfg)

        run(TrackerConfig(icp=False))  # warm up (imports, first calls)
        times = {name: [] for name in variants}
        times["machine unit: bare 1 kHz numpy dead reckoning"] = []
        acc = {}
        for _ in range(args.repeats):
            for name, cfg in variants.items():
                res = run(cfg)
                times[name].append(res.processing_s)
                e = pose_errors(res.T_world_body[-1:], walk.T_world_body[-1:])[0]
                d = res.T_world_body[:, :3, 3] - walk.T_world_body[:, :3, 3]
                acc[name] = (100 * np.linalg.norm(e[:3]) / walk.distance_m,
                             float(np.sqrt(np.mean(np.sum(d**2, axis=1)))))
            times["machine unit: bare 1 kHz numpy dead reckoning"].append(_dead_reckoning(inp))
        ref = float(np.median(times["graphcal default (200 Hz updates, ICP)"]))
        for name, ts in times.items():
            med = float(np.median(ts))
            row = {"data": wname, "variant": name, "duration_s": duration, "samples": len(walk.times),
                   "median_s": med, "real_time_factor": duration / med, "x_graphcal_default": med / ref,
                   "us_per_sample": 1e6 * med / len(walk.times)}
            if name in acc:
                row["drift_percent"], row["ape_rmse_m"] = acc[name]
            rows.append(row)

    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    result = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": {"cores": os.cpu_count(), "load_avg_1_5_15": list(load), "python": platform.python_version(),
                    "numpy": np.__version__, "filterpy": filterpy.__version__},
        "repeats": args.repeats,
        "target_real_time_factor": TARGET_RTF,
        "rows": rows,
    }
    print(f"EKF real-time factor (data duration / processing time), medians of {args.repeats}; "
          f"load average {load[0]:.1f}")
    print(f"{'data':<14} {'variant':<48} {'RTF':>7} {'us/sample':>10} {'x default':>10} {'drift %':>8} {'APE mm':>7}")
    for r in rows:
        print(f"{r['data']:<14} {r['variant']:<48} {r['real_time_factor']:7.1f} {r['us_per_sample']:10.1f} "
              f"{r['x_graphcal_default']:10.2f} {r.get('drift_percent', float('nan')):8.3f} "
              f"{1e3 * r.get('ape_rmse_m', float('nan')):7.2f}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
