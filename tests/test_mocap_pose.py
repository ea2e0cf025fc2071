"""The 6-D motion-capture pose kind: factor (error, analytic Jacobians against central differences),
contract (mocap_poses.csv read, validated, written), simulation and identification from it."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from graphcal.factors.mocap_pose import mocap_pose_error, so3_log, so3_right_jacobian_inverse
from graphcal.geometry import pose_from_xyz_rpy
from graphcal.models.legs import leg_model
from graphcal.models.robot import load_robot

DEG = np.pi / 180.0
FOOT = "fl_foot"


def _setup(seed=3, n=4):
    robot = load_robot(model="a1", base_frame="body", feet=(FOOT,))
    leg = robot.leg(FOOT)
    model = leg_model(robot, FOOT, origins="first")
    rng = np.random.default_rng(seed)
    q = rng.uniform(-0.5, 0.5, size=(n, leg.n_joints))
    theta = rng.normal(0, 0.01, model.dim)
    T = pose_from_xyz_rpy([0.3, -0.1, 0.2], [0.1, -0.2, 0.4])
    Tm = np.array([pose_from_xyz_rpy(rng.normal(0, 0.3, 3), rng.normal(0, 0.5, 3)) for _ in range(n)])
    return leg, model, q, theta, T, Tm


def test_so3_helpers():
    x = np.array([[0.3, -0.2, 0.5], [1e-9, 0, 0]])
    R = np.array([gtsam.Rot3.Expmap(v).matrix() for v in x])
    assert np.allclose(so3_log(R), x, atol=1e-12)
    # Jr^-1 inverts the right Jacobian: Log(Exp(x) Exp(d)) ~ x + Jr^-1 d
    d = 1e-6 * np.array([0.2, 0.7, -0.4])
    y = gtsam.Rot3.Logmap(gtsam.Rot3.Expmap(x[0]) * gtsam.Rot3.Expmap(d))
    assert np.allclose((y - x[0]) / 1e-6, so3_right_jacobian_inverse(x[:1])[0] @ d / 1e-6, atol=1e-5)


def test_pose_error_jacobians_match_central_differences():
    leg, model, q, theta, T, Tm = _setup()
    e, (HV, HL) = mocap_pose_error(T, theta, q, Tm, leg, model, True)
    h = 1e-6
    num_V = np.zeros_like(HV)
    for i in range(6):
        dx = np.zeros(6)
        dx[i] = h
        ep = mocap_pose_error(gtsam.Pose3(T).retract(dx).matrix(), theta, q, Tm, leg, model, False)[0]
        em = mocap_pose_error(gtsam.Pose3(T).retract(-dx).matrix(), theta, q, Tm, leg, model, False)[0]
        num_V[:, :, i] = (ep - em) / (2 * h)
    num_L = np.zeros_like(HL)
    for i in range(model.dim):
        dt = np.zeros(model.dim)
        dt[i] = h
        ep = mocap_pose_error(T, theta + dt, q, Tm, leg, model, False)[0]
        em = mocap_pose_error(T, theta - dt, q, Tm, leg, model, False)[0]
        num_L[:, :, i] = (ep - em) / (2 * h)
    assert np.max(np.abs(HV - num_V)) < 1e-6, np.max(np.abs(HV - num_V))
    assert np.max(np.abs(HL - num_L)) < 1e-6, np.max(np.abs(HL - num_L))
    # a wrong sign in any block would miss: the Jacobians are not small
    assert np.max(np.abs(HV)) > 0.1 and np.max(np.abs(HL)) > 0.1
