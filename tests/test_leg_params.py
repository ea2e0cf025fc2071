"""Leg kinematic parameters: names, FK with parameters against perturbed URDFs, analytic Jacobian."""

from __future__ import annotations

import numpy as np
import pytest

from graphcal.errors import ModelError
from graphcal.models.kinematics import foot_positions, leg_jacobian
from graphcal.models.legs import (
    LegModel,
    fk_and_param_jacobian,
    fk_with_params,
    leg_model,
    param_jacobian,
    perturbation_from_theta,
)
from graphcal.models.perturb import LegPerturbation, apply_perturbation, link_length_delta
from graphcal.models.robot import load_robot
from graphcal.testing import numerical_jacobian

# Fixed joints with rotations inside the chain (so link directions differ between the URDF parent
# link frame and the Leg's frame), a prismatic and a continuous joint, a joint without origin
# translation (no link), and a foot attached through two fixed joints.
CHAIN_URDF = """<?xml version="1.0"?>
<robot name="chain">
  <link name="root"/><link name="body"/>
  <joint name="mount" type="fixed">
    <parent link="root"/><child link="body"/>
    <origin xyz="0.1 0.0 0.3" rpy="0.1 0.2 0.3"/>
  </joint>
  <link name="a"/><link name="a_fix"/><link name="b"/><link name="c"/><link name="d"/>
  <link name="tip"/><link name="foot"/>
  <joint name="ja" type="revolute">
    <parent link="body"/><child link="a"/>
    <origin xyz="0.2 0.1 0.0" rpy="0.0 0.0 0.5"/>
    <axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
  <joint name="ja_fix" type="fixed">
    <parent link="a"/><child link="a_fix"/>
    <origin xyz="0.03 0.01 0.0" rpy="0.4 -0.3 0.2"/>
  </joint>
  <joint name="jb" type="prismatic">
    <parent link="a_fix"/><child link="b"/>
    <origin xyz="0.15 0.0 -0.02" rpy="0.1 0.0 0.0"/>
    <axis xyz="1 0 0"/>
    <limit lower="-0.1" upper="0.1" effort="1" velocity="1"/>
  </joint>
  <joint name="jc" type="continuous">
    <parent link="b"/><child link="c"/>
    <origin xyz="0 0 0" rpy="0.0 0.3 0.0"/>
    <axis xyz="0 1 1"/>
  </joint>
  <joint name="jd" type="revolute">
    <parent link="c"/><child link="d"/>
    <origin xyz="0.0 0.05 -0.25" rpy="0.2 0.1 -0.1"/>
    <axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/>
  </joint>
  <joint name="tip_fix" type="fixed">
    <parent link="d"/><child link="tip"/>
    <origin xyz="0.01 0.0 -0.1" rpy="0.3 0.2 0.1"/>
  </joint>
  <joint name="foot_fix" type="fixed">
    <parent link="tip"/><child link="foot"/>
    <origin xyz="0.0 0.02 -0.2" rpy="-0.1 0.0 0.4"/>
  </joint>
</robot>
"""

SEED = 31337


@pytest.fixture(scope="module")
def robots():
    return {
        "octopus": load_robot(model="octopus"),
        "a1": load_robot(model="a1"),
        "qingzhui": load_robot(model="qingzhui"),
        "messor": load_robot(model="messor"),
        "chain": load_robot(urdf_xml=CHAIN_URDF, feet=("foot",)),
    }


def _random_q(leg, rng, n):
    lo = np.where(np.isfinite(leg.lower), leg.lower, -np.pi)
    hi = np.where(np.isfinite(leg.upper), leg.upper, np.pi)
    return rng.uniform(lo, hi, size=(n, leg.n_joints))


# ----------------------------------------------------------------------------- names and layout
def test_names_octopus_and_a1(robots):
    p = leg_model(robots["octopus"], "lf_foot", origins="none")
    assert p.names == (
        "lf_coxa_joint.offset_rad",
        "lf_femur_joint.offset_rad",
        "lf_tibia_joint.offset_rad",
        "lf_femur_joint.delta_m",
        "lf_tibia_joint.delta_m",
        "lf_foot_joint.delta_m",
    )
    assert (p.dim, p.n_offsets, p.n_trans) == (6, 3, 3)
    assert p.trans_joints == (1, 2, 3)
    assert p.trans_urdf_joints == ("lf_femur_joint", "lf_tibia_joint", "lf_foot_joint")
    np.testing.assert_allclose(p.trans_dirs[2], [0.0, 0.0, -1.0])  # the tibia points down at q = 0
    a = leg_model(robots["a1"], "rr_foot", origins="none")
    assert a.names[3:] == ("rr_thigh_joint.delta_m", "rr_calf_joint.delta_m", "rr_foot_joint.delta_m")
    assert a.index("rr_calf_joint.delta_m") == 4


def test_joint_without_link_gets_no_delta(robots):
    p = leg_model(robots["qingzhui"], "lf_foot", origins="none")
    # the thigh joint sits at the hip joint's origin (no translation): no link ends there
    assert "lf_thigh_joint.delta_m" not in p.names
    assert "lf_knee_joint.delta_m" in p.names and "lf_foot_joint.delta_m" in p.names


def test_chain_names_and_directions(robots):
    r = robots["chain"]
    p = leg_model(r, "foot", origins="none")
    assert p.names == (
        "ja.offset_rad",
        "jb.offset_m",
        "jc.offset_rad",
        "jd.offset_rad",
        "jb.delta_m",
        "jd.delta_m",
        "foot_fix.delta_m",
    )
    # directions in the URDF parent link frame are the unit origin translations
    np.testing.assert_allclose(p.trans_dirs_urdf[0], np.array([0.15, 0.0, -0.02]) / np.hypot(0.15, 0.02))
    # ... and differ from the Leg-frame directions because of the rotated fixed joints
    assert np.abs(p.trans_dirs[0] - p.trans_dirs_urdf[0]).max() > 1e-3
    np.testing.assert_allclose(np.linalg.norm(p.trans_dirs, axis=1), 1.0)


def test_flags_and_sigmas(robots):
    r = robots["octopus"]
    only_off = leg_model(r, "lf_foot", link_lengths=False, origins="none")
    only_len = leg_model(r, "lf_foot", joint_offsets=False, origins="none")
    assert only_off.names == leg_model(r, "lf_foot", origins="none").names[:3]
    assert only_len.names == leg_model(r, "lf_foot", origins="none").names[3:]
    np.testing.assert_allclose(leg_model(r, "lf_foot", origins="none").prior_sigmas(0.1, 0.01), [0.1] * 3 + [0.01] * 3)
    chain = leg_model(robots["chain"], "foot", origins="none")
    np.testing.assert_allclose(chain.prior_sigmas(0.1, 0.01), [0.1, 0.01, 0.1, 0.1, 0.01, 0.01, 0.01])
    assert isinstance(only_off, LegModel)


# ----------------------------------------------------------------------------- FK and Jacobian
@pytest.mark.parametrize("name", ["octopus", "a1", "qingzhui", "messor", "chain"])
def test_zero_theta_is_nominal_fk(robots, name):
    r = robots[name]
    rng = np.random.default_rng(SEED)
    for foot in r.feet:
        leg = r.leg(foot)
        p = leg_model(r, foot, origins="none")
        q = _random_q(leg, rng, 50)
        np.testing.assert_allclose(fk_with_params(leg, p, q, p.zeros()), foot_positions(leg, q), atol=1e-14)
        # offset columns are the joint Jacobian at theta = 0
        J = param_jacobian(leg, p, q, p.zeros())
        np.testing.assert_allclose(J[:, :, : p.n_offsets], leg_jacobian(leg, q), atol=1e-14)


@pytest.mark.parametrize("name", ["octopus", "a1", "qingzhui", "messor", "chain"])
def test_param_jacobian_matches_central_differences(robots, name):
    r = robots[name]
    rng = np.random.default_rng(SEED + 1)
    for foot in r.feet[:2]:
        leg = r.leg(foot)
        p = leg_model(r, foot, origins="none")
        q = _random_q(leg, rng, 25)
        theta = rng.normal(scale=[0.05] * p.n_offsets + [0.01] * p.n_trans)
        J = param_jacobian(leg, p, q, theta)
        np.testing.assert_allclose(J, numerical_jacobian(lambda t: fk_with_params(leg, p, q, t), theta), atol=1e-8)
        p1, J1 = fk_and_param_jacobian(leg, p, q, theta)
        np.testing.assert_allclose(p1, fk_with_params(leg, p, q, theta), atol=0)
        np.testing.assert_allclose(J1, J, atol=0)


def test_single_configuration_shapes(robots):
    r = robots["a1"]
    leg = r.leg("fl_foot")
    p = leg_model(r, "fl_foot", origins="none")
    q = np.array([0.1, 0.7, -1.4])
    assert fk_with_params(leg, p, q, p.zeros()).shape == (3,)
    assert param_jacobian(leg, p, q, p.zeros()).shape == (3, p.dim)
    # a straight leg (a singular configuration for IK) still has finite, correct parameter columns
    q0 = np.zeros(3)
    np.testing.assert_allclose(
        param_jacobian(leg, p, q0, p.zeros()),
        numerical_jacobian(lambda t: fk_with_params(leg, p, q0[None], t), p.zeros())[0], atol=1e-8,
    )


# ----------------------------------------------------------------------------- against perturbed URDFs
def _perturbed_fk(robot, foot, pert, q):
    true = load_robot(urdf_xml=apply_perturbation(robot.urdf_xml, pert), feet=(foot,), base_frame=robot.base_frame)
    return foot_positions(true.leg(foot), q), true


@pytest.mark.parametrize("name", ["octopus", "a1", "chain"])
@pytest.mark.parametrize("which", ["offsets", "links", "both"])
def test_equivalent_to_apply_perturbation(robots, name, which):
    r = robots[name]
    rng = np.random.default_rng(SEED + 2)
    for foot in r.feet[:3]:
        leg = r.leg(foot)
        p = leg_model(r, foot, joint_offsets=which != "links", link_lengths=which != "offsets", origins="none")
        theta = rng.normal(scale=0.03, size=p.dim)
        pert = perturbation_from_theta(p, theta)
        q = _random_q(leg, rng, 20)
        expected, true = _perturbed_fk(r, foot, pert, q)
        np.testing.assert_allclose(fk_with_params(leg, p, q, theta), expected, atol=1e-12)
        # and the Pinocchio reference on one configuration
        np.testing.assert_allclose(fk_with_params(leg, p, q[0], theta), true.fk_pinocchio(foot, q[0])[:3, 3], atol=1e-12)


def test_link_delta_is_link_length_delta(robots):
    """A ``<joint>.delta_m`` parameter is exactly perturb.link_length_delta of that joint."""
    r = robots["a1"]
    p = leg_model(r, "fl_foot", joint_offsets=False, origins="none")
    theta = np.array([0.004, -0.003, 0.006])
    pert = LegPerturbation(
        origin_deltas_m={j: tuple(link_length_delta(r, j, v)) for j, v in zip(p.trans_urdf_joints, theta)}
    )
    leg = r.leg("fl_foot")
    q = _random_q(leg, np.random.default_rng(SEED + 3), 10)
    np.testing.assert_allclose(fk_with_params(leg, p, q, theta), _perturbed_fk(r, "fl_foot", pert, q)[0], atol=1e-12)


def test_perturbation_round_trip(robots):
    p = leg_model(robots["octopus"], "rm_foot", origins="none")
    theta = np.arange(p.dim) * 0.01
    pert = perturbation_from_theta(p, theta)
    assert pert.joint_offsets_rad["rm_femur_joint"] == pytest.approx(0.01)
    assert np.linalg.norm(pert.origin_deltas_m["rm_foot_joint"]) == pytest.approx(0.05)
    assert p.as_dict(theta)["rm_tibia_joint.delta_m"] == pytest.approx(0.04)


# ----------------------------------------------------------------------------- errors
def test_errors(robots):
    r = robots["a1"]
    p = leg_model(r, "fl_foot", origins="none")
    with pytest.raises(ModelError, match="theta must have shape"):
        fk_with_params(r.leg("fl_foot"), p, np.zeros(3), np.zeros(2))
    with pytest.raises(ModelError, match="used with the leg"):
        fk_with_params(r.leg("fr_foot"), p, np.zeros(3), p.zeros())
    with pytest.raises(ModelError, match="q must have shape"):
        param_jacobian(r.leg("fl_foot"), p, np.zeros((4, 2)), p.zeros())
    with pytest.raises(ModelError, match="not a parameter"):
        p.index("fl_knee.offset_rad")
    with pytest.raises(ModelError):
        leg_model(r, "no_such_foot", origins="none")
