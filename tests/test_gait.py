"""Tests of graphcal.planning.gait: tread zones, Zhao's shin / stair-edge cylinder test, and a tripod walk
onto the simulated stairs planned on the stairs model *estimated from depth clouds*
(graphcal.simulation.stairs_clouds + graphcal.locomotion.stairs), checked against the true stairs by an independent test
(the shin capsule against the true step boxes, legs by graphcal.models.kinematics.ik_leg).

World: z up, floor z = 0, three 130 x 300 mm steps from x = 1.2 m (landing on top), robot
qingzhui walking along +x with the alternating tripod gait (A = MF, RB, LB; B = MB, RF, LF).
"""

from __future__ import annotations

import numpy as np
import pytest

from graphcal.errors import GraphcalError
from graphcal.geometry import pose_matrix
from graphcal.locomotion.stairs import model_stairs, stairs_model_from_steps
from graphcal.models.builtin import builtin_info
from graphcal.models.kinematics import foot_positions, ik_leg, joint_frames
from graphcal.models.robot import load_robot
from graphcal.planning.gait import (
    GaitConfig,
    GaitError,
    body_path,
    feet_from_joint_angles,
    gait_parameters,
    segment_distances,
    swing_collides,
    swing_trajectory,
)
from graphcal.simulation.stairs_clouds import simulate_stairs_clouds, stairs_height

CFG = GaitConfig()


@pytest.fixture(scope="module")
def robot():
    return load_robot(model="qingzhui")


@pytest.fixture(scope="module")
def info():
    return builtin_info("qingzhui")


@pytest.fixture(scope="module")
def seq():
    return simulate_stairs_clouds(seed=3)


@pytest.fixture(scope="module")
def estimated(seq):
    return model_stairs(seq.clouds_sensor, seq.T_world_sensor_est)


@pytest.fixture(scope="module")
def truth(seq):
    return stairs_model_from_steps(seq.terrain.stairs)


def _stance(info, x_body: float):
    T = pose_matrix(np.eye(3), [x_body, 0.0, info.default_body_height_m])
    return T, {f: T[:3, :3] @ p + T[:3, 3] for f, p in info.nominal_stance.items()}


# ----------------------------------------------------------------------------- independent check
def _true_clearance(robot, foot, T0, T1, p0, p1, H, steps, r=CFG.shin_radius_m, n=101, mid=False):
    """Smallest distance (m) between the shin capsule's surface and the true staircase (step boxes
    and the floor) over the swing (``mid``: over its middle, 20-80 %), and whether the leg follows
    the whole path; own IK (ik_leg with line search) and own box distance. The capsule runs from the
    knee to a ball of radius r resting on the foot point (a foot on the ground touches it:
    clearance 0)."""
    leg = robot.leg(foot)
    tau = np.linspace(0.0, 1.0, n)
    P = swing_trajectory(p0, p1, H, tau, lift_fraction=CFG.lift_fraction)
    R, O = body_path(T0, T1, tau)
    p_body = np.einsum("nji,nj->ni", R, P - O)
    q_lift, ok0 = ik_leg(leg, p_body[0], np.zeros(leg.n_joints))
    if not bool(ok0):
        return -np.inf, False
    q, ok = ik_leg(leg, p_body, q_lift)
    _, origins, _, feet_b = joint_frames(leg, q)
    knee = np.einsum("nij,nj->ni", R, origins[:, -1]) + O
    ball = np.einsum("nij,nj->ni", R, feet_b) + O + [0.0, 0.0, r]
    f = np.linspace(0.0, 1.0, 60)
    pts = knee[:, None] + f[None, :, None] * (ball - knee)[:, None]  # (n, 60, 3)
    boxes = [((s.x_start_m, -s.width_m / 2, -1.0), (s.x_start_m + s.depth_m, s.width_m / 2, s.height_m)) for s in steps]
    boxes.append(((-50.0, -50.0, -1.0), (50.0, 50.0, 0.0)))  # the floor
    d = np.full(pts.shape[:2], np.inf)
    for lo, hi in boxes:
        g = np.maximum(np.asarray(lo) - pts, pts - np.asarray(hi))
        dist = np.where(g.max(axis=-1) > 0, np.linalg.norm(np.maximum(g, 0.0), axis=-1), g.max(axis=-1))
        d = np.minimum(d, dist)
    c = (d - r).min(axis=1)
    if mid:
        c = c[(tau >= 0.2) & (tau <= 0.8)]
    return float(c.min()), bool(ok.all())


def _walk(robot, info, steps, plan, n_steps: int, x0: float = 0.1):
    """Tripod walk from the nominal stance at body x = x0. ``plan(T, stance, feet)`` ->
    (L, H, T_end, p_land). Execution: the feet land on the TRUE surface below the planned
    footholds, and the body ends at the planned pose shifted by the swing feet's mean height
    error (the body keeps its planned height above the real feet; the model's frame is off by
    the pose estimate's mean error, ~1 cm and ~0.5 deg). Yields per swing foot
    (step, foot, T, T_end, p_lift, p_land, H, L), then (None, None, T, None, feet, ...)."""
    T, feet = _stance(info, x0)
    stance = "A"
    for k in range(n_steps):
        L, H, T_end, p_land = plan(T, stance, feet)
        p_true = {f: np.array([p[0], p[1], stairs_height(steps, [p[0]])[0]]) for f, p in p_land.items()}
        T_end = T_end.copy()
        T_end[2, 3] += np.mean([p_true[f][2] - p_land[f][2] for f in p_land])
        for f in p_land:
            yield k, f, T, T_end, feet[f].copy(), p_true[f], H, L
            feet[f] = p_true[f]
        T = T_end
        stance = "B" if stance == "A" else "A"
    yield None, None, T, None, feet, None, None, None


# ----------------------------------------------------------------------------- tests
def test_segment_distances_against_brute_force():
    rng = np.random.default_rng(0)
    a0, a1, b0, b1 = (rng.normal(size=(120, 3)) for _ in range(4))
    b1[:20] = b0[:20] + 2.0 * (a1[:20] - a0[:20])  # parallel pairs
    b1[20:30] = b0[20:30]  # the second segment is a point
    a1[30:35] = a0[30:35]  # the first one
    a1[35:40], b1[35:40] = a0[35:40], b0[35:40]  # both
    d = segment_distances(a0, a1, b0, b1)
    s = np.linspace(0.0, 1.0, 401)
    for i in range(len(d)):
        A = a0[i] + s[:, None] * (a1[i] - a0[i])
        B = b0[i] + s[:, None] * (b1[i] - b0[i])
        brute = np.min(np.linalg.norm(A[:, None] - B[None], axis=-1))
        assert d[i] <= brute + 1e-12 and brute - d[i] < 0.01, i  # grid: 1/400 of each segment
    # crossing lines far from the segments: Zhao's line distance (Eq. 11) would be 0
    assert segment_distances([0, 0, 0], [1, 0, 0], [5, -1, 0], [5, 1, 0]) == pytest.approx(4.0)


def test_swing_trajectory_shape():
    p0, p1 = np.array([1.0, 0.2, 0.0]), np.array([1.3, 0.2, 0.13])
    tau = np.linspace(0.0, 1.0, 201)
    P = swing_trajectory(p0, p1, 0.05, tau)
    assert np.allclose(P[0], p0) and np.allclose(P[-1], p1)
    assert P[:, 2].max() == pytest.approx(0.13 + 0.05)
    assert np.all(np.diff(P[:, 0]) >= -1e-12)  # never backwards
    # the foot is at the apex height (30 % of the swing) before it has moved 15 % of the way
    i = np.argmax(P[:, 2] >= 0.18 - 1e-9)
    assert (P[i, 0] - p0[0]) / 0.3 < 0.15 and tau[i] == pytest.approx(0.3, abs=0.01)


def test_zones_and_interference(robot, info, truth):
    # body at x = 0.2: MF foot at x = 1.0 on the floor, 0.2 m before the first riser; A swings
    T, feet = _stance(info, 0.2)
    gp = gait_parameters(robot, T, "B", truth, feet)
    assert set(gp.swing_feet) == {"mf_foot", "rb_foot", "lb_foot"}
    mf = gp.feet["mf_foot"]
    # floor middle zone ends 5 cm before the riser (1.15 m); tread 0 middle zone 1.25..1.45 m
    assert mf.zone_intervals_m[0] == pytest.approx((0.0, 0.15))
    assert mf.zone_intervals_m[1] == pytest.approx((0.25, 0.30))
    # the interference test only removes step lengths; the chosen one lands in a middle zone
    for lo, hi in mf.step_length_intervals_m:
        assert any(a - 1e-9 <= lo and hi <= b + 1e-9 for a, b in mf.zone_intervals_m)
    L = gp.step_length_m
    assert any(lo <= L <= hi for lo, hi in gp.step_length_intervals_m)
    x_land = gp.p_world_land["mf_foot"][0]
    assert not (1.15 < x_land < 1.25)
    assert gp.step_height_m >= gp.step_height_intervals_m[0][0]
    # MF climbing onto tread 0: the step height must clear the nosing
    if x_land > 1.2:
        assert gp.step_height_m >= 0.03


def test_edge_test_catches_near_zone_and_low_swing(robot, info, truth, seq):
    """The checks can fail: MF stepping up from x = 1.0 m onto tread 0 (nosing at 1.2 m)."""
    T, feet = _stance(info, 0.2)
    p0 = feet["mf_foot"]
    T1 = T.copy()
    T1[:3, 3] += [0.2, 0.0, 0.03]

    def check(x_land, H):
        p1 = np.array([x_land, 0.0, 0.13])
        own = swing_collides(robot, "mf_foot", T, T1, p0, p1, H, truth)
        phys, ok = _true_clearance(robot, "mf_foot", T, T1, p0, p1, H, seq.terrain.stairs)
        phys_mid, _ = _true_clearance(robot, "mf_foot", T, T1, p0, p1, H, seq.terrain.stairs, mid=True)
        assert ok
        return own, phys, phys_mid

    own, phys, phys_mid = check(1.35, 0.08)  # middle zone, enough height: clear
    assert not own.collides and own.min_edge_clearance_m > 0.0 and phys > -1e-3 and phys_mid > 0.03
    own, phys, _ = check(1.205, 0.08)  # 5 mm past the nosing: Zhao's edge test says no
    assert own.edge_collision and not own.solid_collision and phys > -1e-3  # (not a physical hit)
    own, phys, phys_mid = check(1.35, 0.0)  # no clearance: the foot grazes the nosing
    assert own.edge_collision and phys_mid < 0.005
    # Zhao's test with line (not segment) distances would flag a step far from the stairs
    T_far, feet_far = _stance(info, -1.0)
    T_far1 = T_far.copy()
    T_far1[:3, 3] += [0.1, 0.0, 0.0]
    q = feet_far["mf_foot"]
    assert not swing_collides(robot, "mf_foot", T_far, T_far1, q, q + [0.2, 0.0, 0.0], 0.05, truth).collides


def test_walk_on_the_estimated_model_is_collision_free(robot, info, seq, estimated, truth):
    steps = seq.terrain.stairs

    def plan(T, stance, feet):
        gp = gait_parameters(robot, T, stance, estimated, feet)
        return gp.step_length_m, gp.step_height_m, gp.T_world_body_end, dict(gp.p_world_land)

    n_swings, lengths, heights = 0, [], []
    for k, f, T, T_end, p0, p1, H, L in _walk(robot, info, steps, plan, 10):
        if k is None:
            final_T, final_feet = T, p0
            break
        own = swing_collides(robot, f, T, T_end, p0, p1, H, truth)
        phys, ok = _true_clearance(robot, f, T, T_end, p0, p1, H, steps)
        assert not own.collides, (k, f, own)
        assert ok and phys > -1e-3, (k, f, phys)  # touching its own footholds only
        n_swings += 1
        lengths.append(L)
        heights.append(H)
    assert n_swings == 30
    # the front tripod got onto the stairs: MF on the landing (three steps up), RF and LF on a tread
    # (the rear tripod's climb is not reached: docs/stairs_gait.md, limitations)
    assert final_feet["mf_foot"][2] == pytest.approx(0.39)
    assert min(final_feet["lf_foot"][2], final_feet["rf_foot"][2]) >= 0.13 - 1e-9
    assert final_T[0, 3] > 1.0
    # the parameters adapted: several step lengths and step heights were used
    assert len(set(np.round(lengths, 3))) >= 3 and len(set(np.round(heights, 3))) >= 2


def test_naive_fixed_parameters_collide(robot, info, seq, truth):
    """The same walk with a fixed step (0.15 m long, 3 cm high) hits the stairs."""
    from graphcal.planning.gait import _body_after

    steps = seq.terrain.stairs
    hd = np.array([1.0, 0.0, 0.0])

    def plan(T, stance, feet):
        swing = info.gait_groups[1] if stance == "A" else info.gait_groups[0]
        land = {f: feet[f] + 0.15 * hd for f in swing}
        for f in land:
            land[f][2] = stairs_height(steps, [land[f][0]])[0]
        names = list(feet)
        T_end = _body_after(T, np.array([feet[f] for f in names]), np.array([land.get(f, feet[f]) for f in names]),
                            0.15, hd, np.radians(30.0))
        return 0.15, 0.03, T_end, land

    hits_own, hits_phys = 0, 0
    for k, f, T, T_end, p0, p1, H, L in _walk(robot, info, steps, plan, 10):
        if k is None:
            break
        hits_own += swing_collides(robot, f, T, T_end, p0, p1, H, truth).collides
        phys, ok = _true_clearance(robot, f, T, T_end, p0, p1, H, steps)
        hits_phys += phys < -1e-3
    assert hits_own >= 2 and hits_phys >= 1


def test_feet_from_joint_angles_and_bad_input(robot, info, truth):
    T, feet = _stance(info, 0.2)
    q = {}
    for f in robot.feet:
        leg = robot.leg(f)
        q[f], ok = ik_leg(leg, info.nominal_stance[f], np.zeros(leg.n_joints))
        assert bool(ok)
    back = feet_from_joint_angles(robot, T, q)
    assert all(np.allclose(back[f], feet[f], atol=1e-6) for f in robot.feet)
    assert np.allclose(foot_positions(robot.leg("mf_foot"), q["mf_foot"]), info.nominal_stance["mf_foot"], atol=1e-6)
    with pytest.raises(GaitError, match="stance_group"):
        gait_parameters(robot, T, "C", truth, feet)
    with pytest.raises(GaitError, match="no position for foot 'mf_foot'"):
        gait_parameters(robot, T, "A", truth, {f: p for f, p in feet.items() if f != "mf_foot"})
    with pytest.raises(GaitError, match="cannot reach"):
        gait_parameters(robot, T, "A", truth, {**feet, "mf_foot": feet["mf_foot"] + [1.0, 0.0, 0.0]})
    with pytest.raises(GaitError, match="4x4"):
        gait_parameters(robot, T[:3], "A", truth, feet)
    assert issubclass(GaitError, GraphcalError)
