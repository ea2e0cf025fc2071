"""Benchmark: graphcal's legged filter (``run_filter``) and GTSAM 4.3's three legged estimators
(``LeggedInvariantEKF``, ``LeggedInvariantIEKF``, ``LeggedFixedLagSmoother``) on the same inputs.

(a) The simulated walks with truth (graphcal.simulation.walking, in memory, no clouds): the hexapod
    tripod walk and the a1 trot. Same IMU (IMU frame, T_body_imu), same body-frame foot points (the
    forward kinematics of the measured joints), same stance mask (graphcal's), same noise
    (graphcal's EkfNoise defaults = the simulator's, mapped to GTSAM's parameters by
    graphcal.locomotion.gtsam_legged.legged_params). Drift (% of distance), APE RMSE, mean pose
    NEES (6 dof; GTSAM's EKFs' covariance converted to graphcal's order), wall time. Also both with
    the true IMU biases removed from the readings (GTSAM's EKFs have no bias in their state).
(b) GTSAM's Spot stair sample (gtsam/Data/legged_staircase in the installed wheel, CC BY-NC-SA:
    read from there, never copied): no truth; the final IMU position (x, y from the start, z above
    the start floor) of the three with the example's settings, and graphcal's on the same inputs.

Usage: .venv/bin/python bench/legged_side_by_side.py [--distance M] [--smoother-every K] [--json PATH]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
from pathlib import Path

import numpy as np


def _metrics(res, truth) -> dict:
    from graphcal.locomotion.metrics import nees_against_truth, trajectory_metrics

    m = trajectory_metrics(res.times, res.T_world_body, truth)
    nees = float(np.mean(nees_against_truth(res, truth)[1])) if len(res.cov_index) else None
    return {"drift_percent": m["drift_percent"], "ape_rmse_m": m["ape_rmse_m"], "nees": nees,
            "time_s": res.processing_s, "distance_m": m["distance_m"]}


def _simulated(program: str, distance: float, smoother_every: int, *, no_bias: bool) -> dict:
    from graphcal.locomotion.estimator import TrackerConfig, run_filter
    from graphcal.locomotion.gtsam_legged import VARIANTS, GtsamLeggedSettings, run_gtsam_legged
    from graphcal.locomotion.metrics import Truth
    from graphcal.locomotion.track_inputs import inputs_from_walking
    from graphcal.simulation.walking import WalkingConfig, simulate_walking

    w = simulate_walking(WalkingConfig(program=program, distance_m=distance, cloud_rate_hz=0))
    inp = inputs_from_walking(w, clouds=False)
    if no_bias:
        inp = dataclasses.replace(inp, gyro=inp.gyro - w.gyro_bias, accel=inp.accel - w.accel_bias)
    truth = Truth(w.times, w.T_world_body, {})
    cfg = TrackerConfig(icp=False)
    r = run_filter(inp, cfg)
    rows = {"graphcal run_filter": _metrics(r, truth)}
    for v in VARIANTS:
        st = GtsamLeggedSettings(contact_every=smoother_every if v == "fixed_lag" else cfg.stance_every)
        g = run_gtsam_legged(inp, v, noise=cfg.noise, settings=st, stance_mask=r.stance_mask)
        rows[f"gtsam {v}"] = _metrics(g, truth)
    return rows


def _spot() -> dict:
    import gtsam

    from graphcal.locomotion.estimator import TrackerConfig, run_filter
    from graphcal.locomotion.gtsam_legged import EXAMPLE_NOISE, VARIANTS, GtsamLeggedSettings, run_gtsam_legged
    from graphcal.logs.foot_points import foot_point_inputs

    folder = Path(os.path.dirname(gtsam.__file__)) / "Data" / "legged_staircase"
    if not folder.is_dir():
        return {"note": f"no {folder}: this gtsam wheel has no legged sample"}
    inp, events = foot_point_inputs(folder)
    out = {}
    for v in VARIANTS:
        g = run_gtsam_legged(inp, v, noise=EXAMPLE_NOISE, settings=GtsamLeggedSettings.example(), contact_samples=events)
        p = g.T_world_imu[:, :3, 3]
        out[f"gtsam {v}"] = {"final_imu_xyz_m": [float(p[-1, 0] - p[0, 0]), float(p[-1, 1] - p[0, 1]), float(p[-1, 2])],
                             "time_s": g.processing_s}
    try:
        r = run_filter(inp, TrackerConfig(noise=dataclasses.replace(EXAMPLE_NOISE, kinematic_sigma_m=0.03), icp=False))
    except Exception as exc:  # noqa: BLE001 -- reported, not hidden
        out["graphcal run_filter"] = {"error": f"{type(exc).__name__}: {exc}"}
        return out
    T_wi = r.T_world_body @ inp.T_body_imu
    p = T_wi[:, :3, 3]
    out["graphcal run_filter"] = {"final_imu_xyz_m": [float(p[-1, 0] - p[0, 0]), float(p[-1, 1] - p[0, 1]),
                                                      float(p[-1, 2] - p[0, 2] + _start_imu_height(inp))],
                                  "time_s": r.processing_s}
    return out


def _start_imu_height(inp) -> float:
    """The IMU's height above the first stance feet at the start (graphcal's world: feet at z = 0)."""
    st = inp.contact[0] if inp.contact[0].any() else np.ones(len(inp.robot.feet), dtype=bool)
    return float(inp.T_body_imu[2, 3] - inp.p_body_foot[st, 0, 2].mean())


def _table(rows: dict) -> str:
    lines = ["| estimator | drift % | APE RMSE m | mean NEES (6) | time s |", "|---|---|---|---|---|"]
    for name, m in rows.items():
        nees = f"{m['nees']:.1f}" if m["nees"] is not None else "--"
        lines.append(f"| {name} | {m['drift_percent']:.3f} | {m['ape_rmse_m']:.4f} | {nees} | {m['time_s']:.2f} |")
    return "\n".join(lines)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--distance", type=float, default=5.0, help="walk length (m)")
    ap.add_argument("--smoother-every", type=int, default=25, help="contacts every k-th sample for the smoother")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    doc = {}
    for program in ("tripod-walk", "trot"):
        for no_bias in (False, True):
            key = f"{program}{' (true biases removed)' if no_bias else ''}"
            doc[key] = _simulated(program, a.distance, a.smoother_every, no_bias=no_bias)
            print(f"\n{key}, {a.distance:g} m\n{_table(doc[key])}", flush=True)
    doc["spot"] = _spot()
    print("\nSpot stair sample: final IMU position (x, y from the start; z above the start floor)")
    for name, m in doc["spot"].items():
        print(f"  {name}: {m}")
    if a.json:
        a.json.write_text(json.dumps(doc, indent=1))
    return doc


if __name__ == "__main__":
    main()
