"""Motion-capture marker factor and the leg model behind it: analytic Jacobians against central
differences through GTSAM's retract (random and near-singular points), the parameterised forward
kinematics against Pinocchio on perturbed URDFs, the URDF round trip of the new origin parameters,
shape and input checks."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from graphcal.errors import ModelError
from graphcal.factors.keys import K, L, V
from graphcal.factors.mocap_marker import marker_covariance, mocap_marker_error, mocap_marker_factor, sqrt_information
from graphcal.geometry import pose_from_xyz_rpy, se3_exp
from graphcal.models.legs import (
    ORIGIN_CHOICES,
    leg_model,
    perturbation_from_theta,
    point_kinematics,
    theta_from_perturbation,
)
from graphcal.models.perturb import LegPerturbation, apply_perturbation
from graphcal.models.robot import load_robot
from graphcal.report.urdf import calibrated_urdf
from graphcal.testing import factor_jacobians, numerical_jacobian

H_STEP = 1e-6
SEED = 77

# A chain with everything the model must handle: fixed joints with rotations between the moving
# ones, a prismatic and a continuous joint, a joint without origin translation, and a foot hung
# through two fixed joints with rotations (so R_base_foot matters for a marker off the foot origin).
CHAIN_URDF = """<?xml version="1.0"?>
<robot name="chain">
  <link name="root"/><link name="body"/>
  <joint name="mount" type="fixed"><parent link="root"/><child link="body"/>
    <origin xyz="0.1 0.0 0.3" rpy="0.1 0.2 0.3"/></joint>
  <link name="a"/><link name="a_fix"/><link name="b"/><link name="c"/><link name="d"/><link name="tip"/><link name="foot"/>
  <joint name="ja" type="revolute"><parent link="body"/><child link="a"/>
    <origin xyz="0.2 0.1 0.0" rpy="0.0 0.0 0.5"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="ja_fix" type="fixed"><parent link="a"/><child link="a_fix"/>
    <origin xyz="0.0 0.05 0.0" rpy="0.3 0.0 0.0"/></joint>
  <joint name="jb" type="revolute"><parent link="a_fix"/><child link="b"/>
    <origin xyz="0.0 0.12 -0.02" rpy="0.0 0.0 0.0"/><axis xyz="1 0 0"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="jc" type="prismatic"><parent link="b"/><child link="c"/>
    <origin xyz="0.0 0.0 -0.2" rpy="0.0 0.4 0.0"/><axis xyz="0 0 1"/>
    <limit lower="-0.05" upper="0.05" effort="1" velocity="1"/></joint>
  <joint name="jd" type="continuous"><parent link="c"/><child link="d"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 1 0"/></joint>
  <joint name="tip_joint" type="fixed"><parent link="d"/><child link="tip"/>
    <origin xyz="0.01 0.0 -0.15" rpy="0.0 0.0 0.7"/></joint>
  <joint name="foot_joint" type="fixed"><parent link="tip"/><child link="foot"/>
    <origin xyz="0.0 0.02 -0.05" rpy="0.2 -0.1 0.0"/></joint>
</robot>
"""


@pytest.fixture(scope="module")
def robots():
    return {
        "a1": load_robot(model="a1"),
        "chain": load_robot(urdf_xml=CHAIN_URDF, base_frame="body", feet=("foot",)),
    }


FEET = {"a1": "fl_foot", "chain": "foot"}


def _random_pose(rng, t_scale=1.0):
    return se3_exp(np.concatenate([rng.normal(scale=1.5, size=3), rng.normal(scale=t_scale, size=3)]))


def _analytic(factor, values, dims):
    A, _ = factor.linearize(values).jacobian()
    out, off = [], 0
    for d in dims:
        out.append(A[:, off:off + d])
        off += d
    return out


def _check(factor, values, dims, rtol=1e-6):
    for Hn, Ha in zip(factor_jacobians(factor, values, dims, H_STEP, whitened=True), _analytic(factor, values, dims)):
        scale = max(1.0, np.abs(Hn).max())
        assert np.abs(Hn - Ha).max() <= rtol * scale, np.abs(Hn - Ha).max()


# ----------------------------------------------------------------------------- leg model
@pytest.mark.parametrize("name", ["a1", "chain"])
@pytest.mark.parametrize("origins", ORIGIN_CHOICES)
def test_point_kinematics_matches_pinocchio_on_perturbed_urdf(robots, name, origins):
    robot, foot = robots[name], FEET[name]
    rng = np.random.default_rng(SEED)
    m = leg_model(robot, foot, origins=origins)
    leg = robot.leg(foot)
    theta = rng.normal(scale=0.02, size=m.dim)
    marker = np.array([0.013, -0.021, 0.034])
    true = load_robot(urdf_xml=apply_perturbation(robot.urdf_xml, perturbation_from_theta(m, theta)),
                      base_frame=robot.base_frame, feet=(foot,))
    q = rng.uniform(-1.0, 1.0, size=(6, leg.n_joints)) * np.where(np.array(leg.joint_types) == "prismatic", 0.05, 1.0)
    pk = point_kinematics(leg, m, q, theta, marker)
    ref = np.array([(true.fk_pinocchio(foot, qq) @ np.r_[marker, 1.0])[:3] for qq in q])
    assert np.abs(pk.p_base_point - ref).max() < 1e-12
    # round trip: the same theta from the perturbation
    assert np.allclose(theta_from_perturbation(m, perturbation_from_theta(m, theta)), theta, atol=1e-12)


@pytest.mark.parametrize("name", ["a1", "chain"])
def test_point_kinematics_jacobians_match_central_differences(robots, name):
    robot, foot = robots[name], FEET[name]
    rng = np.random.default_rng(SEED + 1)
    m = leg_model(robot, foot, origins="all")
    leg = robot.leg(foot)
    theta = rng.normal(scale=0.02, size=m.dim)
    marker = np.array([0.02, 0.01, -0.03])
    q = rng.uniform(-1, 1, size=(5, leg.n_joints)) * 0.5
    pk = point_kinematics(leg, m, q, theta, marker)
    num = numerical_jacobian(lambda t: point_kinematics(leg, m, q, t, marker).p_base_point, theta, H_STEP)
    for i in range(m.dim):
        assert np.abs(num[:, :, i] - pk.J_theta[:, :, i]).max() < 1e-8, m.names[i]
    # the same step dq on every row of q: each row's point depends on its own joint angles only
    num = numerical_jacobian(lambda dq: point_kinematics(leg, m, q + dq, theta, marker).p_base_point,
                             np.zeros(leg.n_joints), H_STEP)
    for j in range(leg.n_joints):
        assert np.abs(num[:, :, j] - pk.J_q[:, :, j]).max() < 1e-8
    # marker Jacobian is the foot rotation: moving the marker by dm moves the point by R dm
    dm = np.array([1e-3, -2e-3, 5e-4])
    moved = point_kinematics(leg, m, q, theta, marker + dm).p_base_point
    assert np.allclose(moved - pk.p_base_point, np.einsum("nij,j->ni", pk.R_base_foot, dm), atol=1e-14)


def test_leg_model_names_and_hip_origin(robots):
    m = leg_model(robots["a1"], "fl_foot")
    # Yuan's omega is the thigh joint's link (A1 origin (0, 0.08, 0)); the hip position is new, 3-D
    assert m.names == ("fl_hip_joint.offset_rad", "fl_thigh_joint.offset_rad", "fl_calf_joint.offset_rad",
                       "fl_hip_joint.dx_m", "fl_hip_joint.dy_m", "fl_hip_joint.dz_m",
                       "fl_thigh_joint.delta_m", "fl_calf_joint.delta_m", "fl_foot_joint.delta_m")
    assert leg_model(robots["a1"], "fl_foot", origins="none").dim == 6
    with pytest.raises(ModelError, match="origins"):
        leg_model(robots["a1"], "fl_foot", origins="most")
    # a sideways shift of a link that only has a length parameter cannot be expressed
    with pytest.raises(ModelError, match="not expressible"):
        theta_from_perturbation(m, LegPerturbation({}, {"fl_calf_joint": (0.01, 0.0, 0.0)}))


@pytest.mark.parametrize("name", ["a1", "chain"])
def test_calibrated_urdf_carries_origin_components(robots, name):
    """report/urdf.py writes <joint>.dx_m/.dy_m/.dz_m: the written URDF reproduces the model."""
    robot, foot = robots[name], FEET[name]
    rng = np.random.default_rng(SEED + 2)
    m = leg_model(robot, foot, origins="all" if name == "chain" else "first")
    theta = rng.normal(scale=0.01, size=m.dim)
    text = calibrated_urdf(robot.urdf_xml, robot.base_frame, {}, {foot: m.as_dict(theta)}, command="identify-legs")
    assert "graphcal identify-legs" in text
    written = load_robot(urdf_xml=text, base_frame=robot.base_frame, feet=(foot,))
    leg = robot.leg(foot)
    q = rng.uniform(-0.5, 0.5, size=(4, leg.n_joints)) * np.where(np.array(leg.joint_types) == "prismatic", 0.05, 1.0)
    pk = point_kinematics(leg, m, q, theta)
    ref = np.array([written.fk_pinocchio(foot, qq)[:3, 3] for qq in q])
    assert np.abs(pk.p_base_point - ref).max() < 1e-12


# ----------------------------------------------------------------------------- factor Jacobians
def _values(T, theta_free=None, marker=None):
    v = gtsam.Values()
    v.insert(V(0), gtsam.Pose3(T))
    if theta_free is not None:
        v.insert(L(0), np.asarray(theta_free, dtype=float))
    if marker is not None:
        v.insertPoint3(K(0), np.asarray(marker, dtype=float))
    return v


@pytest.mark.parametrize("name", ["a1", "chain"])
@pytest.mark.parametrize("variant", ["full", "subset_cov", "pose_only"])
def test_factor_jacobians_random(robots, name, variant):
    robot, foot = robots[name], FEET[name]
    rng = np.random.default_rng(SEED + hash(variant) % 100)
    m = leg_model(robot, foot)
    leg = robot.leg(foot)
    N = 5
    q = rng.uniform(-1, 1, size=(N, leg.n_joints)) * np.where(np.array(leg.joint_types) == "prismatic", 0.05, 1.0)
    P = rng.normal(scale=0.5, size=(N, 3))
    T = _random_pose(rng)
    theta = rng.normal(scale=0.02, size=m.dim)
    if variant == "full":
        f = mocap_marker_factor(V(0), q, P, leg, m, l_key=L(0), k_key=K(0), sigma_m=0.002)
        v, dims = _values(T, theta, [0.01, -0.02, 0.03]), [6, m.dim, 3]
    elif variant == "subset_cov":
        free = [0, 2, m.dim - 1]
        A = rng.normal(size=(N, 3, 3)) * 1e-3
        cov = A @ np.swapaxes(A, 1, 2) + 1e-6 * np.eye(3)
        f = mocap_marker_factor(V(0), q, P, leg, m, l_key=L(0), free=free, theta=theta, k_key=K(0), cov_m2=cov)
        v, dims = _values(T, theta[free], [0.0, 0.0, 0.0]), [6, len(free), 3]
    else:
        f = mocap_marker_factor(V(0), q, P, leg, m, theta=theta, p_foot_marker=[0.01, 0.0, 0.0])
        v, dims = _values(T), [6]
    assert f.dim() == 3 * N
    _check(f, v, dims)


def test_factor_jacobians_near_singular(robots):
    """Leg fully stretched (knee at 0, foot on the hip axis line), marker at the foot origin, the pose
    rotated by nearly pi, and joint angles at +-pi."""
    robot = robots["a1"]
    leg = robot.leg("fl_foot")
    m = leg_model(robot, "fl_foot", origins="all")
    q = np.array([[0.0, 0.0, 0.0], [np.pi, -np.pi, 0.0], [1e-9, np.pi / 2, -1e-9]])
    P = np.zeros((3, 3))
    for T in (se3_exp([np.pi - 1e-7, 0.0, 0.0, 0.1, 0.2, 0.3]), np.eye(4), se3_exp([1e-9, -1e-9, 0, 0, 0, 0])):
        f = mocap_marker_factor(V(0), q, P, leg, m, l_key=L(0), k_key=K(0))
        _check(f, _values(T, np.zeros(m.dim), np.zeros(3)), [6, m.dim, 3])


def test_linearize_matches_pure_function_and_whitening(robots):
    robot = robots["chain"]
    leg = robot.leg("foot")
    m = leg_model(robot, "foot")
    rng = np.random.default_rng(SEED + 5)
    N = 4
    q = rng.uniform(-0.5, 0.5, size=(N, leg.n_joints)) * np.where(np.array(leg.joint_types) == "prismatic", 0.05, 1.0)
    P = rng.normal(size=(N, 3))
    T = _random_pose(rng, 0.3)
    theta = rng.normal(scale=0.01, size=m.dim)
    marker = np.array([0.01, 0.02, 0.0])
    cov = marker_covariance(rng.normal(scale=0.2, size=(N, 3, leg.n_joints)), 0.001, 0.01)
    f = mocap_marker_factor(V(0), q, P, leg, m, l_key=L(0), k_key=K(0), cov_m2=cov)
    v = _values(T, theta, marker)
    e, H = mocap_marker_error(T, theta, marker, q, P, leg, m, True)
    Lw = sqrt_information(cov)
    for i in range(N):
        assert np.allclose(Lw[i].T @ Lw[i], np.linalg.inv(cov[i]), rtol=1e-9)
    assert np.allclose(f.unwhitenedError(v), np.einsum("nij,nj->ni", Lw, e).ravel(), atol=1e-12)
    # graph.error is half the sum of squared Mahalanobis distances
    maha = sum(e[i] @ np.linalg.solve(cov[i], e[i]) for i in range(N))
    assert f.error(v) == pytest.approx(0.5 * maha, rel=1e-10)
    A, _ = f.linearize(v).jacobian()
    assert np.allclose(A[:, :6], (Lw @ H[0]).reshape(3 * N, 6), atol=1e-9)
    # the error is measured minus predicted, in the mocap frame
    pk = point_kinematics(leg, m, q, theta, marker)
    Ti = np.linalg.inv(T)
    assert np.allclose(e, P - (pk.p_base_point @ Ti[:3, :3].T + Ti[:3, 3]), atol=1e-14)


def test_factor_input_errors(robots):
    robot = robots["a1"]
    leg = robot.leg("fl_foot")
    m = leg_model(robot, "fl_foot")
    q = np.zeros((2, 3))
    P = np.zeros((2, 3))
    with pytest.raises(ValueError, match="q must be"):
        mocap_marker_factor(V(0), np.zeros((2, 2)), P, leg, m)
    with pytest.raises(ValueError, match="p_mocap"):
        mocap_marker_factor(V(0), q, np.full((2, 3), np.nan), leg, m)
    with pytest.raises(ValueError, match="free needs l_key"):
        mocap_marker_factor(V(0), q, P, leg, m, free=[0])
    with pytest.raises(ValueError, match="distinct indices"):
        mocap_marker_factor(V(0), q, P, leg, m, l_key=L(0), free=[0, 0])
    with pytest.raises(ValueError, match="positive definite"):
        mocap_marker_factor(V(0), q, P, leg, m, cov_m2=np.zeros((2, 3, 3)))
    with pytest.raises(ValueError, match="sigma_m"):
        mocap_marker_factor(V(0), q, P, leg, m, sigma_m=0.0)
    with pytest.raises(ValueError, match="together with k_key"):
        mocap_marker_factor(V(0), q, P, leg, m, k_key=K(0), p_foot_marker=[0, 0, 0])
    # a Vector variable of the wrong length is refused at evaluation, not a crash
    f = mocap_marker_factor(V(0), q, P, leg, m, l_key=L(0), free=[0, 1])
    with pytest.raises(Exception, match="length"):
        f.error(_values(np.eye(4), np.zeros(3)))


def test_factor_recovers_pose_and_parameters_noise_free(robots):
    """A small optimisation: true pose, two leg parameters and the marker from 30 exact samples."""
    from graphcal.solvers.batch import solve_lm

    robot = robots["a1"]
    leg = robot.leg("fl_foot")
    m = leg_model(robot, "fl_foot", origins="none")
    rng = np.random.default_rng(SEED + 9)
    q = rng.uniform(leg.lower, leg.upper, size=(30, 3))
    theta_true = np.zeros(m.dim)
    theta_true[m.index("fl_thigh_joint.offset_rad")] = 0.03
    theta_true[m.index("fl_calf_joint.delta_m")] = 0.012
    marker_true = np.array([0.0, 0.01, -0.015])
    T_true = pose_from_xyz_rpy([0.3, -0.1, 0.2], [0.1, -0.2, 0.5])
    pk = point_kinematics(leg, m, q, theta_true, marker_true)
    Ti = np.linalg.inv(T_true)
    P = pk.p_base_point @ Ti[:3, :3].T + Ti[:3, 3]
    free = [m.index("fl_thigh_joint.offset_rad"), m.index("fl_calf_joint.delta_m")]
    g = gtsam.NonlinearFactorGraph()
    g.add(mocap_marker_factor(V(0), q, P, leg, m, l_key=L(0), free=free, k_key=K(0)))
    v = _values(T_true @ se3_exp([0.05, -0.03, 0.08, 0.02, 0.01, -0.03]), np.zeros(2), np.zeros(3))
    res = solve_lm(g, v)
    assert res.converged
    assert np.allclose(res.values.atVector(L(0)), theta_true[free], atol=1e-9)
    assert np.allclose(res.values.atPoint3(K(0)), marker_true, atol=1e-9)
    assert np.allclose(res.values.atPose3(V(0)).matrix(), T_true, atol=1e-9)
