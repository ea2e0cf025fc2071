"""The stance-contact factor (a round foot and joint compliance, graphcal/factors/stance_contact.py):
analytic Jacobians against numerical ones, the nominal case equal to the plain stance-foot factor,
and the foot radius's geometry (a vertical lower leg: no offset)."""

from __future__ import annotations

import numpy as np
import pytest

from graphcal.factors.keys import F, L, Q, R, X
from graphcal.factors.stance_contact import lower_leg_direction, lower_leg_directions, stance_contact_factor
from graphcal.factors.stance_foot import stance_foot_factor
from graphcal.models.builtin import builtin_info
from graphcal.models.kinematics import foot_positions
from graphcal.models.legs import leg_model
from graphcal.models.robot import load_robot
from graphcal.testing import assert_jacobians, gtsam_values, random_pose


@pytest.fixture(scope="module")
def leg():
    info = builtin_info("octopus")
    robot = load_robot(model="octopus", feet=info.feet) if False else load_robot(model="octopus")
    return robot, robot.leg(robot.feet[0])


@pytest.mark.parametrize("with_legs", [False, True])
@pytest.mark.parametrize("which", ["radius", "compliance", "both"])
def test_jacobians_match_numerical(leg, which, with_legs):
    robot, lg = leg
    rng = np.random.default_rng(3)
    q = np.array([0.1, 0.4, -0.9])[: lg.n_joints]
    T = random_pose(rng, 0.3)
    p = T[:3, :3] @ foot_positions(lg, q) + T[:3, 3] + rng.normal(0, 0.01, 3)
    a_b = lower_leg_direction(lg, q)
    R_lever = T[:3, :3]
    param = leg_model(robot, lg.foot, origins="none") if with_legs else None
    kw = dict(r_key=R(0) if which in ("radius", "both") else None, a_b=a_b,
              k_key=Q(1) if which in ("compliance", "both") else None, joint_index=1, R_lever=R_lever,
              l_key=L(0) if with_legs else None, param=param)
    fac = stance_contact_factor(X(0), F(0), q, lg, np.eye(3) * 1e-6, **kw)
    items = dict(x=(X(0), T), f=(F(0), ("point3", p)))
    dims = [6, 3]
    if with_legs:
        items["l"] = (L(0), rng.normal(0, 0.01, param.dim))
        dims.append(param.dim)
    if kw["r_key"] is not None:
        items["r"] = (R(0), np.array([0.025]))
        dims.append(1)
    if kw["k_key"] is not None:
        items["k"] = (Q(1), np.array([0.3]))
        dims.append(1)
    values = gtsam_values(**items)
    from graphcal.factors.stance_contact import stance_contact_error

    vals = [T, p] + ([values.atVector(L(0))] if with_legs else [])
    e, H = stance_contact_error(T, p, q, lg, radius=0.025 if kw["r_key"] else None, a_b=a_b,
                                compliance=0.3 if kw["k_key"] else None, joint_index=1, R_lever=R_lever,
                                param=param, theta=vals[2] if with_legs else None)
    np.testing.assert_allclose(fac.unwhitenedError(values), e, atol=1e-12)
    assert_jacobians(fac, values, dims, H, atol=2e-6, what=which)


def test_nominal_equals_stance_foot(leg):
    robot, lg = leg
    q = np.array([0.0, 0.5, -1.0])[: lg.n_joints]
    T = random_pose(np.random.default_rng(1), 0.2)
    p = T[:3, 3] + np.array([0.2, 0.1, -0.1])
    values = gtsam_values(x=(X(0), T), f=(F(0), ("point3", p)), r=(R(0), np.array([0.0])), k=(Q(1), np.array([0.0])))
    plain = stance_foot_factor(X(0), F(0), q, lg, cov_m2=np.eye(3) * 1e-6)
    ext = stance_contact_factor(X(0), F(0), q, lg, np.eye(3) * 1e-6, r_key=R(0), a_b=lower_leg_direction(lg, q),
                                k_key=Q(1), joint_index=1, R_lever=np.eye(3))
    np.testing.assert_allclose(ext.unwhitenedError(values), plain.unwhitenedError(values), atol=1e-12)
    # a 25 mm radius moves the seen foot by r (a_b - n_b): 0 only where the lower leg is vertical
    v2 = gtsam_values(x=(X(0), T), f=(F(0), ("point3", p)), r=(R(0), np.array([0.025])), k=(Q(1), np.array([0.0])))
    d = ext.unwhitenedError(v2) - plain.unwhitenedError(values)
    n_b = T[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(d, 0.025 * (lower_leg_direction(lg, q) - n_b), atol=1e-12)
    assert np.linalg.norm(d) > 1e-3


def _lower_leg_reference(lg, q) -> np.ndarray:
    """The lower leg's direction by its definition, one configuration at a time: from the foot to
    the last joint origin that is not the foot's (independent of the batched code)."""
    from graphcal.models.kinematics import joint_frames

    _, origins, _, p_foot = joint_frames(lg, np.asarray(q, dtype=float)[None, :])
    for o in origins[0][::-1]:
        d = o - p_foot[0]
        if np.linalg.norm(d) > 1e-6:
            return d / np.linalg.norm(d)
    return np.array([0.0, 0.0, 1.0])


def test_lower_leg_directions_batch_is_the_definition(leg):
    robot, _ = leg
    rng = np.random.default_rng(5)
    for foot in robot.feet:
        lg = robot.leg(foot)
        Q = rng.uniform(-1.2, 1.2, (7, lg.n_joints))
        got = lower_leg_directions(lg, Q)
        assert got.shape == (7, 3)
        np.testing.assert_allclose(got, [_lower_leg_reference(lg, q) for q in Q], atol=1e-15)
        np.testing.assert_allclose([lower_leg_direction(lg, q) for q in Q], got, atol=1e-15)
