"""Vectorised leg kinematics against Pinocchio (the reference), finite differences and IK round trips."""

from __future__ import annotations

import numpy as np
import pytest

from graphcal.errors import ModelError
from graphcal.models.builtin import BUILTIN_MODELS
from graphcal.models.kinematics import fk_leg, foot_positions, ik_leg, leg_jacobian, newton_ik, smoothstep
from graphcal.models.robot import load_robot
from graphcal.testing import numerical_jacobian

# A hand-written URDF: the base frame ``body`` sits below the root through a rotated fixed joint,
# joint origins have non-trivial rpy, one prismatic joint, a continuous joint, axes not aligned
# with x/y/z (one negative), a fixed joint inside the chain and a second branch.
CUSTOM_URDF = """<?xml version="1.0"?>
<robot name="custom">
  <link name="world_root"/>
  <link name="body"/>
  <joint name="mount" type="fixed">
    <parent link="world_root"/><child link="body"/>
    <origin xyz="0.3 -0.2 0.5" rpy="0.1 -0.25 0.7"/>
  </joint>
  <link name="l1"/><link name="l2"/><link name="l3"/><link name="l3b"/><link name="l4"/><link name="foot"/>
  <joint name="j1" type="revolute">
    <parent link="body"/><child link="l1"/>
    <origin xyz="0.12 0.05 -0.03" rpy="0.2 -0.4 1.1"/>
    <axis xyz="0.3 -0.5 0.8"/>
    <limit lower="-1.5" upper="1.5" effort="1" velocity="1"/>
  </joint>
  <joint name="j2" type="prismatic">
    <parent link="l1"/><child link="l2"/>
    <origin xyz="0.0 0.2 0.1" rpy="-0.3 0.15 0.0"/>
    <axis xyz="0 0 1"/>
    <limit lower="-0.1" upper="0.1" effort="1" velocity="1"/>
  </joint>
  <joint name="j3" type="continuous">
    <parent link="l2"/><child link="l3"/>
    <origin xyz="0.25 0.0 -0.05" rpy="0.0 0.5 -0.2"/>
    <axis xyz="1 1 1"/>
  </joint>
  <joint name="j3_fixed" type="fixed">
    <parent link="l3"/><child link="l3b"/>
    <origin xyz="0.1 0.02 0.0" rpy="0.3 0.0 0.4"/>
  </joint>
  <joint name="j4" type="revolute">
    <parent link="l3b"/><child link="l4"/>
    <origin xyz="0.3 0.0 0.0" rpy="0.05 0.1 0.15"/>
    <axis xyz="0 -1 0"/>
    <limit lower="-2.0" upper="2.0" effort="1" velocity="1"/>
  </joint>
  <joint name="foot_joint" type="fixed">
    <parent link="l4"/><child link="foot"/>
    <origin xyz="0.02 -0.01 -0.35" rpy="0.4 -0.2 0.1"/>
  </joint>
  <link name="m1"/><link name="foot2"/>
  <joint name="k1" type="revolute">
    <parent link="body"/><child link="m1"/>
    <origin xyz="-0.1 0.0 0.0" rpy="0 0 3.0"/>
    <axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
  <joint name="foot2_joint" type="fixed">
    <parent link="m1"/><child link="foot2"/>
    <origin xyz="0.2 0.0 -0.1" rpy="0 0 0"/>
  </joint>
</robot>
"""

RNG_SEED = 20240607


@pytest.fixture(scope="module")
def robots():
    out = {name: load_robot(model=name) for name in BUILTIN_MODELS}
    out["custom"] = load_robot(urdf_xml=CUSTOM_URDF, feet=("foot", "foot2"))
    return out


def _all_legs(robots):
    for name, robot in robots.items():
        for foot in robot.feet:
            yield name, robot, robot.leg(foot)


def _random_q(rng, leg, n):
    lo = np.where(np.isfinite(leg.lower), leg.lower, -np.pi)
    hi = np.where(np.isfinite(leg.upper), leg.upper, np.pi)
    return rng.uniform(lo, hi, size=(n, leg.n_joints))


def test_custom_leg_extraction(robots):
    leg = robots["custom"].leg("foot")
    assert leg.joint_names == ("j1", "j2", "j3", "j4")
    assert leg.joint_types == ("revolute", "prismatic", "revolute", "revolute")
    np.testing.assert_allclose(leg.axes[0], np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]), atol=1e-15)
    np.testing.assert_allclose(leg.axes[2], np.ones(3) / np.sqrt(3), atol=1e-15)
    np.testing.assert_allclose(leg.axes[3], [0, -1, 0], atol=1e-15)
    assert leg.lower[2] == -np.inf and leg.upper[2] == np.inf  # continuous
    assert (leg.lower[1], leg.upper[1]) == (-0.1, 0.1)
    # first placement is in the body frame (not the URDF root): just the j1 origin
    np.testing.assert_allclose(leg.T_parent_joint[0][:3, 3], [0.12, 0.05, -0.03], atol=1e-15)
    assert robots["custom"].leg("foot2").joint_names == ("k1",)


def test_fk_matches_pinocchio_all_legs(robots):
    rng = np.random.default_rng(RNG_SEED)
    worst = 0.0
    for _, robot, leg in _all_legs(robots):
        q = _random_q(rng, leg, 8)
        q[0] = 0.0
        T = fk_leg(leg, q)
        assert T.shape == (8, 4, 4)
        for i in range(len(q)):
            T_ref = robot.fk_pinocchio(leg.foot, q[i])
            worst = max(worst, float(np.abs(T[i, :3, 3] - T_ref[:3, 3]).max()))
            np.testing.assert_allclose(T[i], T_ref, atol=1e-9, err_msg=f"{robot.name} {leg.foot} q={q[i]}")
    assert worst < 1e-9


def test_fk_custom_wide_angles_and_nonzero(robots):
    """Outside the limits too (FK does not care), and the result really depends on every joint."""
    robot = robots["custom"]
    leg = robot.leg("foot")
    rng = np.random.default_rng(1)
    q = rng.uniform(-3.0, 3.0, size=(20, 4))
    T = fk_leg(leg, q)
    for i in range(len(q)):
        np.testing.assert_allclose(T[i], robot.fk_pinocchio("foot", q[i]), atol=1e-9)
    for j in range(4):
        dq = np.zeros(4)
        dq[j] = 0.05
        assert np.linalg.norm(foot_positions(leg, q[0] + dq) - foot_positions(leg, q[0])) > 1e-4


def test_single_configuration_shapes(robots):
    leg = robots["a1"].leg("fl_foot")
    q = np.array([0.1, 0.7, -1.4])
    assert fk_leg(leg, q).shape == (4, 4)
    assert foot_positions(leg, q).shape == (3,)
    assert leg_jacobian(leg, q).shape == (3, 3)
    np.testing.assert_allclose(fk_leg(leg, q[None])[0], fk_leg(leg, q))
    with pytest.raises(ModelError, match="joints"):
        fk_leg(leg, np.zeros((2, 4)))


def test_a1_standing_pose_matches_geometry(robots):
    """Closed form: foot below the thigh joint at height 2 l cos(phi) with thigh phi, calf -2 phi."""
    leg = robots["a1"].leg("fl_foot")
    phi = 0.7
    p = foot_positions(leg, [0.0, phi, -2 * phi])
    np.testing.assert_allclose(p, [0.1805, 0.047 + 0.08, -0.4 * np.cos(phi)], atol=1e-12)


def test_jacobian_finite_differences_and_pinocchio(robots):
    rng = np.random.default_rng(RNG_SEED + 1)
    eps = 1e-6
    for _, robot, leg in _all_legs(robots):
        q = _random_q(rng, leg, 4)
        J = leg_jacobian(leg, q)
        assert J.shape == (4, 3, leg.n_joints)
        # the same step dq on every row of q: each row's foot depends on its own joint angles only
        fd = numerical_jacobian(lambda dq: foot_positions(leg, q + dq), np.zeros(leg.n_joints), eps)
        for j in range(leg.n_joints):
            np.testing.assert_allclose(J[:, :, j], fd[:, :, j], atol=1e-7, err_msg=f"{robot.name} {leg.foot} joint {j}")
        for i in range(len(q)):
            np.testing.assert_allclose(J[i], robot.jacobian_pinocchio(leg.foot, q[i]), atol=1e-10)


def test_ik_round_trip_random_reachable(robots):
    rng = np.random.default_rng(RNG_SEED + 2)
    for _, robot, leg in _all_legs(robots):
        if leg.n_joints < 3:
            continue
        q_true = _random_q(rng, leg, 40)
        p = foot_positions(leg, q_true)
        q0 = q_true + rng.normal(0.0, 0.25, size=q_true.shape)
        q, ok = ik_leg(leg, p, q0)
        assert ok.all(), f"{robot.name} {leg.foot}: {np.flatnonzero(~ok)}"
        np.testing.assert_allclose(foot_positions(leg, q), p, atol=1e-8)


def test_ik_from_neutral_start_mostly_converges(robots):
    """A generic start (clipped zero) reaches nearly every in-limit target of the built-in legs."""
    rng = np.random.default_rng(RNG_SEED + 3)
    total, good = 0, 0
    for name, robot, leg in _all_legs(robots):
        if name == "custom":
            continue
        q_true = _random_q(rng, leg, 50)
        p = foot_positions(leg, q_true)
        q0 = np.clip(np.zeros(leg.n_joints), leg.lower, leg.upper)
        q, ok = ik_leg(leg, p, q0, max_iter=100)
        np.testing.assert_array_less(np.linalg.norm(foot_positions(leg, q[ok]) - p[ok], axis=1), 1e-6)
        total += len(ok)
        good += int(ok.sum())
    assert good / total > 0.97


def test_ik_flags_unreachable_targets(robots):
    leg = robots["octopus"].leg("lf_foot")
    p = np.array([[5.0, 5.0, -5.0], [0.8, 0.5, -0.6]])
    q, ok = ik_leg(leg, p, np.zeros(3))
    assert q.shape == (2, 3)
    assert not ok[0]
    assert ok[1]


def test_ik_single_target(robots):
    leg = robots["messor"].leg("rm_foot")
    q_true = np.array([0.2, -0.3, 0.6])
    q, ok = ik_leg(leg, foot_positions(leg, q_true), q_true + 0.1)
    assert q.shape == (3,) and bool(ok)
    np.testing.assert_allclose(foot_positions(leg, q), foot_positions(leg, q_true), atol=1e-9)


def test_newton_ik_modes_converge_and_report_the_kinematics_at_q(robots):
    """Newton (square solve), damped Gauss-Newton with a step limit, and Levenberg-Marquardt (ik_leg's)."""
    rng = np.random.default_rng(RNG_SEED + 4)
    for name, robot, leg in _all_legs(robots):
        if leg.n_joints != 3 or name == "custom":
            continue
        q_true = _random_q(rng, leg, 60)
        q_true = q_true[np.linalg.svd(leg_jacobian(leg, q_true), compute_uv=False)[:, -1] > 0.02]  # not stretched
        p = foot_positions(leg, q_true)
        q0 = q_true + rng.normal(0.0, 0.02, size=q_true.shape)
        for kw in ({}, {"damping": 1e-6, "max_step": 0.3}, {"damping": 1e-4, "adaptive": True}):
            sol = newton_ik(leg, p, q0, iterations=20, stop_tol=1e-12, **kw)
            assert sol.err.max() < 1e-10, (name, leg.foot, kw)
            np.testing.assert_allclose(sol.p_base_foot, foot_positions(leg, sol.q), atol=1e-15)
            np.testing.assert_allclose(sol.err, np.linalg.norm(p - sol.p_base_foot, axis=1), atol=1e-15)
            np.testing.assert_allclose(sol.J, leg_jacobian(leg, sol.q), atol=1e-15)
    # ik_leg is the adaptive mode
    leg = robots["octopus"].leg("lf_foot")
    q_true = _random_q(rng, leg, 20)
    p = foot_positions(leg, q_true)
    p[0] = [5.0, 5.0, -5.0]  # unreachable: every step rejected towards the end
    q, ok = ik_leg(leg, p, np.zeros(3))
    sol = newton_ik(leg, p, np.zeros(3), iterations=50, stop_tol=1e-10, damping=1e-4, adaptive=True)
    assert np.array_equal(q, sol.q) and np.array_equal(ok, sol.err < 1e-6) and not ok[0]


def test_newton_ik_step_limit_and_iteration_count(robots):
    leg = robots["qingzhui"].leg(robots["qingzhui"].feet[0])
    q_true = np.array([[0.3, 0.6, -0.9]])
    p = foot_positions(leg, q_true)
    q0 = q_true + [[0.2, -0.3, 0.25]]
    one = newton_ik(leg, p, q0, iterations=1, stop_tol=0.0, damping=1e-6, max_step=0.05)
    assert np.max(np.abs(one.q - q0)) == pytest.approx(0.05)  # the step is scaled to the limit
    free = newton_ik(leg, p, q0, iterations=1, stop_tol=0.0, damping=1e-6)
    assert np.max(np.abs(free.q - q0)) > 0.05
    none = newton_ik(leg, p, q0, iterations=0, stop_tol=0.0)
    assert np.array_equal(none.q, q0) and none.err[0] == pytest.approx(np.linalg.norm(p - foot_positions(leg, q0)))
    # stop_tol: a start at the solution takes no step
    done = newton_ik(leg, p, q_true, iterations=5, stop_tol=1e-9)
    assert np.array_equal(done.q, q_true)


def test_smoothstep_polynomials():
    x = np.linspace(-0.5, 1.5, 81)
    u = np.clip(x, 0.0, 1.0)
    np.testing.assert_allclose(smoothstep(x, degree=3), np.polynomial.Polynomial([0, 0, 3, -2])(u), atol=1e-15)
    np.testing.assert_allclose(smoothstep(x, degree=5), np.polynomial.Polynomial([0, 0, 0, 10, -15, 6])(u), atol=1e-15)
    h = 1e-4  # slopes at the ends: O(h) for the cubic, O(h^2) for the quintic (zero curvature too)
    assert smoothstep(h, degree=3) / h == pytest.approx(3 * h, rel=1e-3) and 1 - smoothstep(1 - h, degree=3) < 4 * h**2
    assert smoothstep(h, degree=5) / h == pytest.approx(10 * h**2, rel=1e-3)
    assert 1 - smoothstep(1 - h, degree=5) < 11 * h**3
    assert smoothstep(0.5, degree=3) == smoothstep(0.5, degree=5) == 0.5
    with pytest.raises(ValueError):
        smoothstep(x, degree=4)
