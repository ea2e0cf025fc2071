"""Benchmark: gait parameters per step (graphcal.planning.gait.gait_parameters) on the simulated stairs.

Setup (as tests/test_gait.py): the qingzhui hexapod walks from the floor onto the three 130 x 300 mm
steps with the alternating tripod gait, 12 steps, planned on the stairs model estimated from ten
simulated depth clouds with pose errors (graphcal.simulation.stairs_clouds, seed 3). The 12 planning states
(body pose, stance tripod, footholds) are recorded once; then, round-robin over states and
repeats (so that load changes hit both alike), timed side by side in this process:

* graphcal ``gait_parameters``: batched IK (one Gauss-Newton over all configurations of a leg)
  and vectorised segment / box distances;
* baseline: the same configurations evaluated one at a time -- ``ik_leg`` on one target,
  ``segment_distances`` on one shin, the box distance on one shin -- the obvious loop
  implementation of Zhao's per-foot test. It evaluates exactly the configurations graphcal
  evaluated for that state (counted by instrumenting graphcal), so the ratio is the price of
  not batching.

Target (Zhao 2020): <= 100 ms per step for graphcal.
Also timed, for information: ``model_stairs`` on the ten clouds with and without ICP stitching.

Usage: python bench/gait.py [--repeats R] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

TARGET_MS = 100.0


def record_states(robot, info, model, steps, n_steps: int = 12):
    """Planning states of the walk (as tests/test_gait.py): (T_world_body, stance, feet)."""
    from graphcal.geometry import pose_matrix
    from graphcal.planning.gait import gait_parameters
    from graphcal.simulation.stairs_clouds import stairs_height

    T = pose_matrix(np.eye(3), [0.1, 0.0, info.default_body_height_m])
    feet = {f: T[:3, :3] @ p + T[:3, 3] for f, p in info.nominal_stance.items()}
    stance, states = "A", []
    for _ in range(n_steps):
        states.append((T.copy(), stance, {f: p.copy() for f, p in feet.items()}))
        gp = gait_parameters(robot, T, stance, model, feet)
        for f, p in gp.p_world_land.items():
            feet[f] = np.array([p[0], p[1], stairs_height(steps, [p[0]])[0]])
        T = gp.T_world_body_end
        stance = "B" if stance == "A" else "A"
    return states


def configurations_of(robot, model, state):
    """The (leg, R_world_body, p_world_body, p_world_foot) configurations graphcal checks for a
    state, captured by instrumenting graphcal.planning.gait._shin_check."""
    import graphcal.planning.gait as G

    captured = []
    orig = G._shin_check

    def spy(ctx, st, R, o, p, cfg):
        R = np.broadcast_to(R, (len(o), 3, 3))
        captured.append((ctx, st, np.array(R), np.array(o), np.array(p)))
        return orig(ctx, st, R, o, p, cfg)

    G._shin_check = spy
    try:
        T, stance, feet = state
        G.gait_parameters(robot, T, stance, model, feet)
    finally:
        G._shin_check = orig
    return captured


def baseline_step(captured, cfg) -> int:
    """Evaluate every captured configuration one at a time (ik_leg on one target, one shin's
    distances); returns the number of configurations."""
    from graphcal.models.kinematics import ik_leg, joint_frames
    from graphcal.planning.gait import _solid_distance, segment_distances

    n = 0
    for ctx, st, R, o, p in captured:
        T_sw = st.T_stairs_world
        for i in range(len(o)):
            p_body = R[i].T @ (p[i] - o[i])
            q, ok = ik_leg(ctx.leg, p_body, ctx.q_ref, tol=1e-7, ok_tol=1e-4, max_iter=8)
            _, origins, _, foot_b = joint_frames(ctx.leg, q[None])
            R_sb = T_sw[:3, :3] @ R[i]
            o_s = T_sw[:3, :3] @ o[i] + T_sw[:3, 3]
            knee = R_sb @ origins[0, -1] + o_s
            foot = R_sb @ foot_b[0] + o_s
            d_edge = segment_distances(knee, foot, st.edges0, st.edges1).min() if len(st.edges0) else np.inf
            ball = foot + [0.0, 0.0, cfg.shin_radius_m]
            f = np.linspace(0.0, 1.0, cfg.shin_samples)
            d_solid = _solid_distance(st, knee + f[:, None] * (ball - knee)).min()
            _ = bool(ok) and d_edge >= cfg.shin_radius_m + cfg.edge_radius_m and d_solid >= cfg.shin_radius_m
            n += 1
    return n


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3, help="timed runs of graphcal per state (default 3)")
    ap.add_argument("--json", type=Path, default=None, help="write the results to this JSON file")
    args = ap.parse_args(argv)

    from graphcal.locomotion.stairs import StairsModelConfig, model_stairs
    from graphcal.models.builtin import builtin_info
    from graphcal.models.robot import load_robot
    from graphcal.planning.gait import GaitConfig, gait_parameters
    from graphcal.simulation.stairs_clouds import simulate_stairs_clouds

    robot, info = load_robot(model="qingzhui"), builtin_info("qingzhui")
    seq = simulate_stairs_clouds(seed=3)
    t_model, t_model_noicp = [], []
    for _ in range(2):
        t0 = time.perf_counter()
        model = model_stairs(seq.clouds_sensor, seq.T_world_sensor_est)
        t_model.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        model_stairs(seq.clouds_sensor, seq.T_world_sensor_est, config=StairsModelConfig(icp=False))
        t_model_noicp.append(time.perf_counter() - t0)
    states = record_states(robot, info, model, seq.terrain.stairs)
    cfg = GaitConfig()
    captured = [configurations_of(robot, model, s) for s in states]

    t_ours = {i: [] for i in range(len(states))}
    t_base = {i: [] for i in range(len(states))}
    n_conf = {}
    for r in range(args.repeats):
        for i, (T, stance, feet) in enumerate(states):  # round-robin
            t0 = time.perf_counter()
            gait_parameters(robot, T, stance, model, feet)
            t_ours[i].append(time.perf_counter() - t0)
            if r == 0:  # the loop baseline is slow: once per state
                t0 = time.perf_counter()
                n_conf[i] = baseline_step(captured[i], cfg)
                t_base[i].append(time.perf_counter() - t0)
    ours = np.array([np.median(t_ours[i]) for i in t_ours]) * 1e3
    base = np.array([np.median(t_base[i]) for i in t_base]) * 1e3
    confs = np.array([n_conf[i] for i in n_conf])
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    result = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": {"cores": os.cpu_count(), "load_avg_1_5_15": list(load), "python": platform.python_version(),
                    "numpy": np.__version__},
        "states": len(states),
        "repeats": args.repeats,
        "configurations_per_step_median": int(np.median(confs)),
        "graphcal_ms_median": float(np.median(ours)),
        "graphcal_ms_max": float(np.max(ours)),
        "baseline_ms_median": float(np.median(base)),
        "ratio_baseline_to_graphcal": float(np.median(base / ours)),
        "target_ms": TARGET_MS,
        "target_met": bool(np.max(ours) <= TARGET_MS),
        "model_stairs_s": float(np.median(t_model)),
        "model_stairs_no_icp_s": float(np.median(t_model_noicp)),
        "clouds": len(seq.clouds_sensor),
        "points": int(sum(len(c) for c in seq.clouds_sensor)),
    }
    print(f"Gait parameters on the stairs walk: {len(states)} steps x {args.repeats} repeats; "
          f"{os.cpu_count()} cores, load average {load[0]:.2f}")
    print(f"  configurations checked per step (median): {result['configurations_per_step_median']}")
    print(f"  graphcal gait_parameters: median {result['graphcal_ms_median']:.1f} ms, max {result['graphcal_ms_max']:.1f} ms")
    print(f"  baseline (one configuration at a time): median {result['baseline_ms_median']:.0f} ms "
          f"({result['ratio_baseline_to_graphcal']:.1f}x graphcal)")
    print(f"  target <= {TARGET_MS:.0f} ms per step (every step): {'MET' if result['target_met'] else 'NOT MET'}")
    print(f"  model_stairs, {result['clouds']} clouds ({result['points']} points): {result['model_stairs_s']:.2f} s "
          f"with ICP stitching, {result['model_stairs_no_icp_s']:.2f} s without")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")
        print(f"wrote {args.json}")
    return result


if __name__ == "__main__":
    main()
