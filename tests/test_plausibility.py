"""The plausibility verdict (issue 42 item 3): the filter's estimate on a simulated a1 trot and a
qingzhui tripod walk is ``plausible`` with the robot's own legs, ``implausible`` with thigh and shank
0.8 times as long (naming a time within the walk), and a trajectory sinking through the floor is
named at the first time it is below and by how much."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from graphcal.locomotion.plausibility import (
    PlausibilityConfig,
    check_plausibility,
    feet_in_body,
    leg_reach,
    plausibility_section,
    track_plausibility,
)


def _scaled_legs(robot, scale: float):
    """The robot with every thigh and shank ``scale`` times as long (the links ending at the
    third joint and at the foot), through its URDF (graphcal.models.perturb)."""
    from graphcal.models.perturb import LegPerturbation, apply_perturbation, link_length_delta
    from graphcal.models.robot import load_robot

    deltas = {}
    for f in robot.feet:
        leg = robot.leg(f)
        knee = leg.joint_names[2]
        foot_joint = f.replace("_foot", "_foot_joint")
        deltas[knee] = tuple(link_length_delta(robot, knee, (scale - 1) * np.linalg.norm(leg.T_parent_joint[2][:3, 3])))
        deltas[foot_joint] = tuple(link_length_delta(robot, foot_joint, (scale - 1) * np.linalg.norm(leg.T_lastjoint_foot[:3, 3])))
    urdf = apply_perturbation(robot.urdf_xml, LegPerturbation(origin_deltas_m=deltas))
    return load_robot(urdf_xml=urdf, feet=robot.feet)


@pytest.fixture(scope="module", params=["trot", "tripod-walk"])
def walk(request):
    from graphcal.locomotion.estimator import run_filter
    from graphcal.locomotion.track_inputs import inputs_from_walking
    from graphcal.simulation.walking import WalkingConfig, simulate_walking

    sim = simulate_walking(WalkingConfig(program=request.param, duration_s=9.0, rate_hz=400.0, cloud_rate_hz=0.0,
                                         seed=3))
    inp = inputs_from_walking(sim, clouds=False)
    wrong = replace(inp, robot=_scaled_legs(inp.robot, 0.8))
    return sim, inp, run_filter(inp), wrong, run_filter(wrong)


def test_leg_reach_of_the_builtin_models():
    from graphcal.models.robot import load_robot

    a1 = leg_reach(load_robot(model="a1"))
    assert a1.leg_length_m == pytest.approx(0.08 + 0.2 + 0.2)  # hip offset omega, thigh, calf
    assert np.allclose(np.abs(a1.p_body_hip[:, :2]), [0.1805, 0.047])
    assert leg_reach(load_robot(model="qingzhui")).leg_length_m == pytest.approx(0.30 + 0.45)
    assert leg_reach(_scaled_legs(load_robot(model="a1"), 0.8)).leg_length_m == pytest.approx(0.08 + 0.32)


def test_the_right_legs_give_a_plausible_trajectory(walk):
    sim, inp, res, _, _ = walk
    pl = track_plausibility(res, inp, level_ground=True)
    assert pl.verdict == "plausible", pl.reason
    assert pl.failures == ()
    assert abs(pl.floor_z_m) < 1e-3  # the world's z = 0 is the ground under the first stance
    checks = {c.kind: c for c in pl.checks}
    assert set(checks) == {"touchdown", "body_below_floor", "body_above_reach", "attitude", "slip"}
    assert all(c.tested and c.reason == "" for c in checks.values())
    # measured: touchdowns within 5 mm of the floor, 1.1 deg of sway, stance feet still to 2 mm
    assert checks["touchdown"].worst < 0.01 and checks["attitude"].worst < 1.5 and checks["slip"].worst < 0.005
    assert checks["body_below_floor"].worst < -0.2  # the body stays 0.27 m (a1) / 0.44 m above the floor
    json.dumps(plausibility_section(pl))  # plain JSON


def test_a_wrong_leg_model_is_implausible_and_named_within_the_walk(walk):
    sim, _, _, wrong, res = walk
    pl = track_plausibility(res, wrong, level_ground=True)
    assert pl.verdict == "implausible"
    gait = sim.times[~sim.contact.all(axis=1)]  # from the first lift-off to the last touchdown
    first = pl.failures[0]
    assert gait[0] <= first.time_s <= gait[-1] + 0.5
    assert first.message in pl.reason and f"{first.peak_s:.1f} s" in first.message
    kinds = {f.kind for f in pl.failures}
    # measured: trot roll 8.6 deg (bound 5), touchdowns 6 cm above the floor (bound 4 cm);
    # tripod walk touchdowns 10 cm below it (bound 6 cm)
    assert "touchdown" in kinds
    worst = max(f.size for f in pl.failures if f.kind == "touchdown")
    assert worst > 1.3 * PlausibilityConfig().height_tolerance_m(pl.leg_length_m)
    section = plausibility_section(pl)
    assert section["verdict"] == "implausible" and section["failures"][0]["time_s"] == pytest.approx(first.time_s)


def _standing_then_sinking(rate_hz: float = 100.0):
    """A synthetic a1 trotting in place 0.28 m above the floor for 4 s, then sinking at 0.1 m/s
    until 10 s (body 0.32 m below the floor at the end)."""
    from graphcal.models.robot import load_robot

    robot = load_robot(model="a1")
    t = np.arange(0.0, 10.0 + 0.5 / rate_hz, 1.0 / rate_hz)
    N = len(t)
    T = np.tile(np.eye(4), (N, 1, 1))
    T[:, 2, 3] = 0.28 - 0.1 * np.clip(t - 4.0, 0.0, None)
    p_body_foot = np.array([np.tile([x, y, -0.28], (N, 1)) for x, y in ((0.18, 0.13), (0.18, -0.13),
                                                                       (-0.18, 0.13), (-0.18, -0.13))])
    pair = (np.floor(t / 0.25) % 2).astype(bool)  # diagonal pairs, 0.25 s each, all four for the first 1 s
    stance = np.column_stack([~pair, pair, pair, ~pair]) | (t < 1.0)[:, None]
    return robot, t, T, stance, p_body_foot


def test_a_trajectory_sinking_through_the_floor_names_its_first_time_and_size():
    robot, t, T, stance, pbf = _standing_then_sinking()
    pl = check_plausibility(t, T, stance, pbf, leg_reach(robot), level_ground=True)
    assert pl.verdict == "implausible"
    assert PlausibilityConfig().height_tolerance_m(0.48) == pytest.approx(0.048)
    below = next(f for f in pl.failures if f.kind == "body_below_floor")
    # the body origin is 0.048 m below the floor at 4 + (0.28 + 0.048) / 0.1 = 7.28 s
    assert below.time_s == pytest.approx(7.28, abs=0.011)
    assert below.size == pytest.approx(0.32, abs=1e-9) and below.peak_s == pytest.approx(10.0)
    assert below.message.startswith("body 0.32 m below the floor it stood on at 10.0 s")
    td = pl.failures[0]  # the feet go below the floor first: 0.048 m at 4.48 s, the next touchdown at 4.5 s
    assert td.kind == "touchdown" and td.time_s == pytest.approx(4.5, abs=1e-9) and "below the floor" in td.message
    # the planted feet carried down with the body move 1.9 cm over a 0.25 s stance (less the trims):
    # within the a1's slip bound (2.4 cm)
    assert {f.kind for f in pl.failures} == {"touchdown", "body_below_floor"}
    assert {c.kind: c for c in pl.checks}["slip"].worst == pytest.approx(0.019, abs=1e-3)


def test_a_trajectory_above_the_reach_or_tilted_is_named():
    robot, t, T, stance, pbf = _standing_then_sinking()
    T[:, 2, 3] = 0.28
    T[t > 6.0, 2, 3] = 0.6  # 0.12 m beyond the legs' 0.48 m
    c, s = np.cos(np.radians(7.0)), np.sin(np.radians(7.0))
    T[(t > 2.0) & (t < 3.0), :3, :3] = [[1, 0, 0], [0, c, -s], [0, s, c]]
    pl = check_plausibility(t, T, stance, pbf, leg_reach(robot), level_ground=True)
    kinds = {f.kind: f for f in pl.failures}
    assert kinds["attitude"].time_s == pytest.approx(2.01) and kinds["attitude"].size == pytest.approx(7.0)
    assert kinds["attitude"].message.startswith("body roll 7.0 deg on level ground at 2.0 s")
    assert kinds["body_above_reach"].time_s == pytest.approx(6.01) and kinds["body_above_reach"].size == pytest.approx(0.12)


def test_off_level_ground_only_slip_is_tested_and_active_samples_limit_the_checks():
    robot, t, T, stance, pbf = _standing_then_sinking()
    pl = check_plausibility(t, T, stance, pbf, leg_reach(robot), level_ground=False)
    checks = {c.kind: c for c in pl.checks}
    assert not checks["touchdown"].tested and "not declared level" in checks["touchdown"].reason
    assert checks["slip"].tested and checks["slip"].worst == pytest.approx(0.019, abs=1e-3)
    assert pl.verdict == "plausible" and "not tested: touchdown" in pl.reason and pl.floor_z_m is None
    T[:, 0, 3] = 0.2 * t  # the body sliding over its planted feet: 3.8 cm a stance
    pl = check_plausibility(t, T, stance, pbf, leg_reach(robot), level_ground=False)
    assert pl.verdict == "implausible" and {f.kind for f in pl.failures} == {"slip"}
    assert pl.failures[0].time_s == pytest.approx(1.0 - 0.03 - 0.01, abs=0.02)  # the first stance's worst sample
    robot, t, T, stance, pbf = _standing_then_sinking()
    pl = check_plausibility(t, T, stance, pbf, leg_reach(robot), level_ground=True, active=t < 4.0)
    assert pl.verdict == "plausible" and "not tested" not in pl.reason
    none = check_plausibility(t, T, np.zeros_like(stance), pbf, leg_reach(robot), level_ground=True)
    assert none.verdict == "not tested" and "no foot in stance" in none.reason


def test_feet_in_body_is_the_forward_kinematics():
    from graphcal.models.kinematics import foot_positions
    from graphcal.models.robot import load_robot

    robot = load_robot(model="a1")
    rng = np.random.default_rng(0)
    q = {j: rng.uniform(-0.3, 0.3, 5) - (1.5 if "calf" in j else 0.0) for f in robot.feet for j in robot.leg(f).joint_names}
    p = feet_in_body(robot, q)
    leg = robot.leg("rl_foot")
    assert np.allclose(p[2], foot_positions(leg, np.column_stack([q[j] for j in leg.joint_names])))
