"""Robot loading, built-in models (dimensions from the papers), sensor frames and perturbations."""

from __future__ import annotations

import numpy as np
import pytest

from graphcal.errors import ModelError
from graphcal.geometry import invert_pose, matrix_from_rpy, pose_matrix, rot_x, rot_y, rot_z, transform_points
from graphcal.models.builtin import (
    BUILTIN_MODELS,
    R_BODY_OPTICAL,
    R_HIP_ZHAO,
    BuiltinInfo,
    builtin_info,
    builtin_urdf,
    zhao_toe_position,
)
from graphcal.models.kinematics import fk_leg, foot_positions, ik_leg
from graphcal.models.perturb import (
    LegPerturbation,
    apply_perturbation,
    hip_offset_delta,
    joint_origin,
    link_length_delta,
)
from graphcal.models.robot import load_robot

# Chai et al. 2015, Table A1 (all 52 poses): beta' (deg), gamma' (deg), p_y' (mm); alpha' = p_x' = p_z' = 0.
CHAI_TABLE_A1 = [
    (2, 20, 615), (8, 18, 619), (11, 16, 623), (13, 14, 627), (15, 12, 631), (17, 10, 635),
    (19, 8, 639), (19, 6, 643), (19, 4, 647), (20, 2, 651), (-2, -20, 617), (-8, -18, 621),
    (-11, -16, 625), (-13, -14, 629), (-15, -12, 633), (-17, -10, 637), (-19, -8, 641),
    (-19, -6, 645), (-19, -4, 649), (-20, -2, 653), (3, 19, 690), (9, 17, 694), (12, 15, 698),
    (15, 13, 698), (17, 11, 694), (17, 9, 690), (17, 7, 686), (18, 5, 682), (18, 3, 678),
    (19, 1, 674), (-3, -19, 692), (-9, -17, 696), (-12, -15, 700), (-15, -13, 696),
    (-17, -11, 692), (-17, -9, 688), (-17, -7, 684), (-18, -5, 680), (-18, -3, 676),
    (-19, -1, 672), (1, 13, 730), (7, 11, 734), (9, 9, 738), (11, 7, 742), (11, 5, 746),
    (12, 3, 749), (-1, -13, 732), (-7, -11, 736), (-9, -9, 740), (-11, -7, 744), (-11, -5, 748),
    (-12, -3, 750),
]

# Hand-written URDF for the perturbation tests: rotated origins, an unaligned axis, a prismatic
# joint, a continuous joint and a base frame below the root.
CUSTOM_URDF = """<?xml version="1.0"?>
<robot name="custom">
  <link name="root"/><link name="body"/><link name="a"/><link name="b"/><link name="c"/><link name="foot"/>
  <joint name="mount" type="fixed"><parent link="root"/><child link="body"/>
    <origin xyz="0.1 0.2 0.3" rpy="0.3 0.2 -0.5"/></joint>
  <joint name="ja" type="revolute"><parent link="body"/><child link="a"/>
    <origin xyz="0.1 -0.05 0.02" rpy="0.4 -0.3 0.9"/><axis xyz="0.2 0.6 -0.7"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <joint name="jb" type="prismatic"><parent link="a"/><child link="b"/>
    <origin xyz="0.2 0.0 0.0" rpy="0.0 0.3 0.0"/><axis xyz="1 0 1"/>
    <limit lower="-0.1" upper="0.1" effort="1" velocity="1"/></joint>
  <joint name="jc" type="continuous"><parent link="b"/><child link="c"/>
    <origin xyz="0.3 0.01 -0.02" rpy="-0.2 0.1 0.3"/><axis xyz="0 1 0"/></joint>
  <joint name="foot_joint" type="fixed"><parent link="c"/><child link="foot"/>
    <origin xyz="0.0 0.0 -0.4"/></joint>
</robot>
"""


@pytest.fixture(scope="module")
def robots():
    return {name: load_robot(model=name) for name in BUILTIN_MODELS}


# ----------------------------------------------------------------------------- loading
def test_builtin_models_load_with_default_feet(robots):
    expected_feet = {
        "octopus": ("lf_foot", "lm_foot", "lr_foot", "rf_foot", "rm_foot", "rr_foot"),
        "qingzhui": ("lf_foot", "lb_foot", "rf_foot", "rb_foot", "mf_foot", "mb_foot"),
        "messor": ("lf_foot", "lm_foot", "lr_foot", "rf_foot", "rm_foot", "rr_foot"),
        "a1": ("fl_foot", "fr_foot", "rl_foot", "rr_foot"),
        "a1cam": ("fl_foot", "fr_foot", "rl_foot", "rr_foot"),
    }
    for name, robot in robots.items():
        info = builtin_info(name)
        assert isinstance(info, BuiltinInfo)
        assert robot.name == name and robot.base_frame == "body" == info.base_frame
        assert robot.feet == info.feet == expected_feet[name]
        assert len(robot.joint_names) == 3 * len(robot.feet)
        assert set(robot.neutral_q()) == set(robot.joint_names)
        assert all(v == 0.0 for v in robot.neutral_q().values())
        for foot in robot.feet:
            leg = robot.leg(foot)
            leg_name = foot[: -len("_foot")]
            assert leg.n_joints == 3 and leg.joint_types == ("revolute",) * 3
            assert all(j.startswith(leg_name + "_") for j in leg.joint_names)
            assert np.all(leg.lower < leg.upper)
            assert f"{leg_name}_foot_joint" in robot.frame_names
        assert "imu" in robot.frame_names
        np.testing.assert_allclose(info.T_body_imu, np.eye(4))


def test_explicit_feet_and_sensor_frames_via_zero_joint_legs(robots):
    """Sensor and IMU links sit exactly at the CAD poses of builtin_info (URDF <-> info agree)."""
    for name in BUILTIN_MODELS:
        info = builtin_info(name)
        frames = tuple(info.sensors) + ("imu",)
        robot = load_robot(model=name, feet=frames)
        for s, cad in info.sensors.items():
            assert robot.leg(s).n_joints == 0
            np.testing.assert_allclose(robot.fk_pinocchio(s, []), cad.T_body_sensor, atol=1e-12)
            np.testing.assert_allclose(fk_leg(robot.leg(s), np.zeros((1, 0)))[0], cad.T_body_sensor, atol=1e-12)
            assert cad.type in ("depth_camera", "laser_scanner", "stereo_camera")
            assert cad.sigma_m == pytest.approx(0.05) and cad.sigma_rad == pytest.approx(np.deg2rad(5.0))
            R = cad.T_body_sensor[:3, :3]
            np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
            assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(robot.fk_pinocchio("imu", []), info.T_body_imu, atol=1e-15)


def _down_angle_deg(v):
    """Angle of direction v below the horizontal plane (deg)."""
    return float(np.rad2deg(np.arcsin(-v[2] / np.linalg.norm(v))))


def test_octopus_camera_is_chai_eq32():
    cad = builtin_info("octopus").sensors["depth"]
    T = cad.T_body_sensor
    np.testing.assert_allclose(T[:3, 3], [0.528, 0.033, 0.365])
    z, x = T[:3, 2], T[:3, 0]
    assert _down_angle_deg(z) == pytest.approx(37.4)
    assert z[0] > 0 and abs(z[1]) < 1e-12  # looking forward, pitched down
    np.testing.assert_allclose(x, [0, -1, 0], atol=1e-12)  # image x = robot right
    np.testing.assert_allclose(T[:3, :3], rot_y(np.deg2rad(37.4)) @ R_BODY_OPTICAL, atol=1e-15)


def test_qingzhui_camera_front_tilted_down():
    T = builtin_info("qingzhui").sensors["depth"].T_body_sensor
    assert T[0, 3] > 0.25 and abs(T[1, 3]) < 1e-12
    assert _down_angle_deg(T[:3, 2]) == pytest.approx(30.0)
    np.testing.assert_allclose(T[:3, 0], [0, -1, 0], atol=1e-12)


def test_messor_sensors_from_labecki_tables():
    info = builtin_info("messor")
    laser = info.sensors["laser"]
    stereo = info.sensors["stereo"]
    assert laser.type == "laser_scanner" and stereo.type == "stereo_camera"
    # positions: their (x right, y forward, z up) -> ours (y, -x, z)
    np.testing.assert_allclose(laser.T_body_sensor[:3, 3], [0.202, 0.0, 0.175], atol=1e-15)
    np.testing.assert_allclose(stereo.T_body_sensor[:3, 3], [0.180, 0.030, 0.230], atol=1e-15)
    # laser: centre beam (x) forward and 45 deg down; scan plane normal (z) in the x-z plane
    R_l = laser.T_body_sensor[:3, :3]
    assert _down_angle_deg(R_l[:, 0]) == pytest.approx(45.0)
    assert R_l[0, 0] > 0
    np.testing.assert_allclose(R_l[:, 1], [0, 1, 0], atol=1e-12)  # scan plane spans the robot's y
    np.testing.assert_allclose(R_l, rot_z(-np.pi / 2) @ rot_x(np.deg2rad(-45)) @ rot_z(np.pi / 2), atol=1e-15)
    # stereo: optical axis forward and 25 deg down, x = robot right, y down (and slightly back)
    R_c = stereo.T_body_sensor[:3, :3]
    assert _down_angle_deg(R_c[:, 2]) == pytest.approx(25.0)
    assert R_c[0, 2] > 0
    np.testing.assert_allclose(R_c[:, 0], [0, -1, 0], atol=1e-12)
    assert R_c[2, 1] < -0.9
    np.testing.assert_allclose(R_c, rot_z(-np.pi / 2) @ rot_x(np.deg2rad(-115)), atol=1e-15)


def test_a1_dimensions_match_yuan_table_1(robots):
    """l_b = 0.361, omega_b = 0.094, |omega| = 0.08, l1 = l2 = 0.2 read back from the URDF."""
    robot = robots["a1"]
    hips = {f: robot.leg(f).T_parent_joint[0][:3, 3] for f in robot.feet}
    assert hips["fl_foot"][0] - hips["rl_foot"][0] == pytest.approx(0.361, abs=1e-12)
    assert hips["fr_foot"][0] - hips["rr_foot"][0] == pytest.approx(0.361, abs=1e-12)
    assert hips["fl_foot"][1] - hips["fr_foot"][1] == pytest.approx(0.094, abs=1e-12)
    assert hips["rl_foot"][1] - hips["rr_foot"][1] == pytest.approx(0.094, abs=1e-12)
    for foot in robot.feet:
        leg = robot.leg(foot)
        side = 1.0 if foot in ("fl_foot", "rl_foot") else -1.0
        np.testing.assert_allclose(leg.axes, [[1, 0, 0], [0, 1, 0], [0, 1, 0]], atol=1e-15)
        np.testing.assert_allclose(leg.T_parent_joint[1][:3, 3], [0, side * 0.08, 0], atol=1e-15)
        assert np.linalg.norm(leg.T_parent_joint[2][:3, 3]) == pytest.approx(0.2, abs=1e-15)
        assert np.linalg.norm(leg.T_lastjoint_foot[:3, 3]) == pytest.approx(0.2, abs=1e-15)
        # at zero angles the leg hangs straight down: foot 0.4 m below the hip, offset outward
        np.testing.assert_allclose(
            foot_positions(leg, np.zeros(3)), hips[foot] + [0, side * 0.08, -0.4], atol=1e-15
        )


def test_nominal_stances_reachable_within_limits(robots):
    for name, robot in robots.items():
        info = builtin_info(name)
        for foot in robot.feet:
            leg = robot.leg(foot)
            p = np.asarray(info.nominal_stance[foot])
            assert p[2] == pytest.approx(-info.default_body_height_m)
            q, ok = ik_leg(leg, p[None], np.clip(np.full(3, 0.3), leg.lower, leg.upper))
            assert ok[0], f"{name} {foot}"
            assert np.all(q[0] >= leg.lower) and np.all(q[0] <= leg.upper), f"{name} {foot}: {q[0]}"


def test_octopus_reaches_all_52_chai_poses(robots):
    """Feet planted at the nominal stance; body pose roll = gamma', pitch = -beta', z = p_y'."""
    robot = robots["octopus"]
    info = builtin_info("octopus")
    assert len(CHAI_TABLE_A1) == 52
    table = np.array(CHAI_TABLE_A1, dtype=float)
    T_world_body = np.array(
        [
            pose_matrix(matrix_from_rpy(np.deg2rad([gamma, -beta, 0.0])), [0.0, 0.0, py / 1000.0])
            for beta, gamma, py in table
        ]
    )
    T_body_world = invert_pose(T_world_body)
    for foot in robot.feet:
        leg = robot.leg(foot)
        p_world_foot = info.nominal_stance[foot] + np.array([0, 0, info.default_body_height_m])
        assert p_world_foot[2] == pytest.approx(0.0)
        p_body = np.einsum("nij,j->ni", T_body_world[:, :3, :3], p_world_foot) + T_body_world[:, :3, 3]
        q_nom, ok_nom = ik_leg(leg, info.nominal_stance[foot][None], np.array([0.0, 0.3, 0.3]))
        assert ok_nom[0]
        q, ok = ik_leg(leg, p_body, np.repeat(q_nom, len(p_body), axis=0))
        assert ok.all(), f"{foot}: unreachable poses {np.flatnonzero(~ok) + 1}"
        assert np.all(q >= leg.lower) and np.all(q <= leg.upper), foot
        np.testing.assert_allclose(foot_positions(leg, q), p_body, atol=1e-8)


def test_zhao_toe_position_matches_urdf_leg(robots):
    """Zhao Eqs. 1-3 (absolute shank angle) = URDF FK with knee = theta_s - theta_t, in the hip frame."""
    robot = robots["qingzhui"]
    rng = np.random.default_rng(7)
    n = 30
    for foot in robot.feet:
        leg = robot.leg(foot)
        ta = rng.uniform(-0.6, 0.6, n)
        tt = rng.uniform(-1.0, 1.0, n)
        ts = tt + rng.uniform(-0.4, 2.5, n)
        p_body = foot_positions(leg, np.stack([ta, tt, ts - tt], axis=1))
        T_body_hip = leg.T_parent_joint[0]
        p_hip = transform_points(invert_pose(T_body_hip), p_body)
        p_zhao = zhao_toe_position(ta, tt, ts, 0.30, 0.45)
        np.testing.assert_allclose(p_hip, p_zhao @ R_HIP_ZHAO.T, atol=1e-12)
    # the hip frame's x axis is horizontal and radial (abduction axis), z is up
    for foot in robot.feet:
        T = robot.leg(foot).T_parent_joint[0]
        radial = T[:2, 3] / np.linalg.norm(T[:2, 3])
        np.testing.assert_allclose(T[:3, 0], [radial[0], radial[1], 0.0], atol=1e-12)
        np.testing.assert_allclose(T[:3, 2], [0, 0, 1], atol=1e-12)


def test_qingzhui_layout_and_gait_groups(robots):
    robot = robots["qingzhui"]
    info = builtin_info("qingzhui")
    hip = {f: robot.leg(f).T_parent_joint[0][:3, 3] for f in robot.feet}
    assert hip["mf_foot"][0] > 0 and abs(hip["mf_foot"][1]) < 1e-12
    assert hip["mb_foot"][0] < 0 and abs(hip["mb_foot"][1]) < 1e-12
    assert hip["mf_foot"][0] - hip["mb_foot"][0] == pytest.approx(0.70)
    assert hip["lf_foot"][1] > 0 and hip["rf_foot"][1] < 0 and hip["lb_foot"][0] < 0
    assert info.gait_groups == (("mf_foot", "rb_foot", "lb_foot"), ("mb_foot", "rf_foot", "lf_foot"))


# ----------------------------------------------------------------------------- errors
def test_unknown_model_suggests_close_name():
    with pytest.raises(ModelError, match="octopus"):
        load_robot(model="octopos")
    with pytest.raises(ModelError, match="unknown built-in"):
        builtin_urdf("hexapod9000")
    with pytest.raises(ModelError):
        builtin_info("A1 ")


def test_missing_foot_frame_suggests_alternatives():
    with pytest.raises(ModelError, match=r"'fl_fot'.*did you mean 'fl_foot'"):
        load_robot(model="a1", feet=["fl_fot"])


def test_missing_base_frame():
    with pytest.raises(ModelError, match=r"base frame 'bodi'.*'body'"):
        load_robot(model="messor", base_frame="bodi")


def test_foot_not_below_base():
    with pytest.raises(ModelError, match="not below base frame"):
        load_robot(model="a1", base_frame="fl_thigh", feet=["fr_foot"])
    with pytest.raises(ModelError, match="not below base frame"):
        load_robot(model="octopus", base_frame="depth", feet=["lf_foot"])


def test_bad_urdf_inputs(tmp_path):
    with pytest.raises(ModelError, match="not valid XML"):
        load_robot(urdf_xml="<robot name='x'><link name='a'>")
    with pytest.raises(ModelError, match="not a URDF"):
        load_robot(urdf_xml="<model name='x'/>")
    with pytest.raises(ModelError, match="not a valid URDF"):
        load_robot(urdf_xml="<robot name='x'></robot>")
    with pytest.raises(ModelError, match="cannot read URDF file"):
        load_robot(tmp_path / "missing.urdf")
    bad = tmp_path / "bad.urdf"
    bad.write_text("this is not xml <")
    with pytest.raises(ModelError, match="not valid XML"):
        load_robot(bad)
    with pytest.raises(ModelError, match="exactly one"):
        load_robot(model="a1", urdf_xml=builtin_urdf("a1"))
    with pytest.raises(ModelError, match="exactly one"):
        load_robot()


@pytest.mark.parametrize("old, new, words", [
    ('<axis xyz="0 1.0 0"/>', '<axis xyz="0 0 0"/>', r"joint '\w+_joint': <axis xyz>: expected a nonzero axis"),
    ('<origin xyz="0.1 0 0"', '<origin xyz="a b c"', r"joint '\w+_joint': <origin xyz>: expected three finite numbers, got 'a b c'"),
    ('<axis xyz="0 1.0 0"/>', '<axis xyz="nan 1 0"/>', r"<axis xyz>: expected three finite numbers, got 'nan 1 0'"),
])
def test_bad_urdf_numbers_name_the_joint(old, new, words):
    """A zero axis became NaN (then an SVD that did not converge in calibrate); a non-number origin
    gave a page of urdfdom C++ errors and a message naming no joint."""
    text = builtin_urdf("octopus")
    assert old in text
    with pytest.raises(ModelError, match=words):
        load_robot(urdf_xml=text.replace(old, new, 1), base_frame="body", feet=("lf_foot",))


def test_load_from_file_and_string_equal_builtin(tmp_path, robots):
    path = tmp_path / "a1.urdf"
    path.write_text(builtin_urdf("a1"))
    feet = builtin_info("a1").feet
    r_file = load_robot(path, feet=feet)
    r_str = load_robot(urdf_xml=builtin_urdf("a1"), feet=feet)
    assert r_file.name == "a1" and r_file.joint_names == robots["a1"].joint_names
    q = np.array([0.1, 0.8, -1.5])
    for r in (r_file, r_str):
        np.testing.assert_allclose(fk_leg(r.leg("rr_foot"), q), fk_leg(robots["a1"].leg("rr_foot"), q), atol=1e-15)
    assert load_robot(urdf_xml=builtin_urdf("a1")).legs == {}
    with pytest.raises(ModelError, match="not a foot"):
        r_file.leg("nose")


# ----------------------------------------------------------------------------- perturbations
def _fk(urdf_xml, foot, q, base="body"):
    return fk_leg(load_robot(urdf_xml=urdf_xml, base_frame=base, feet=[foot]).leg(foot), q)


def test_joint_offset_equals_shifted_angle_builtin():
    rng = np.random.default_rng(3)
    for name in BUILTIN_MODELS:
        xml = builtin_urdf(name)
        foot = builtin_info(name).feet[0]
        leg = load_robot(urdf_xml=xml, feet=[foot]).leg(foot)
        offsets = dict(zip(leg.joint_names, (0.03, -0.05, 0.02)))
        pert = LegPerturbation(joint_offsets_rad=offsets)
        q = rng.uniform(-1.0, 1.0, (10, 3))
        T_true = _fk(apply_perturbation(xml, pert), foot, q)
        T_nom_shifted = _fk(xml, foot, q + np.array([offsets[j] for j in leg.joint_names]))
        np.testing.assert_allclose(T_true, T_nom_shifted, atol=1e-12)
        assert np.abs(T_true - _fk(xml, foot, q)).max() > 1e-3  # the perturbation does something


def test_joint_offset_equals_shifted_angle_custom():
    """Unaligned axis, rotated origins, a prismatic and a continuous joint, base below the root."""
    rng = np.random.default_rng(4)
    pert = LegPerturbation(joint_offsets_rad={"ja": 0.07, "jb": 0.004, "jc": -0.09})
    q = rng.uniform(-1.0, 1.0, (10, 3)) * [1.0, 0.1, 1.0]
    T_true = _fk(apply_perturbation(CUSTOM_URDF, pert), "foot", q)
    T_shift = _fk(CUSTOM_URDF, "foot", q + [0.07, 0.004, -0.09])
    np.testing.assert_allclose(T_true, T_shift, atol=1e-12)


def test_origin_delta_and_link_length():
    xml = builtin_urdf("octopus")
    d = link_length_delta(xml, "lf_foot_joint", 0.012)
    np.testing.assert_allclose(d, [0, 0, -0.012], atol=1e-15)  # the tibia points down at zero
    d_femur = link_length_delta(load_robot(model="octopus"), "lf_tibia_joint", -0.01)
    np.testing.assert_allclose(d_femur, [-0.01, 0, 0], atol=1e-15)
    pert = LegPerturbation(origin_deltas_m={"lf_foot_joint": d, "lf_tibia_joint": d_femur})
    true_xml = apply_perturbation(xml, pert)
    leg = load_robot(urdf_xml=true_xml, feet=["lf_foot"]).leg("lf_foot")
    assert np.linalg.norm(leg.T_lastjoint_foot[:3, 3]) == pytest.approx(0.75 + 0.012, abs=1e-15)
    assert np.linalg.norm(leg.T_parent_joint[2][:3, 3]) == pytest.approx(0.45 - 0.01, abs=1e-15)
    # zero configuration: foot moved by exactly the two deltas (both axes aligned with the body there)
    p0 = _fk(xml, "lf_foot", np.zeros((1, 3)))[0, :3, 3]
    p1 = _fk(true_xml, "lf_foot", np.zeros((1, 3)))[0, :3, 3]
    az = np.deg2rad(30)
    np.testing.assert_allclose(p1 - p0, [-0.01 * np.cos(az), -0.01 * np.sin(az), -0.012], atol=1e-14)
    # other legs untouched
    np.testing.assert_allclose(_fk(true_xml, "rr_foot", np.ones((1, 3))), _fk(xml, "rr_foot", np.ones((1, 3))))


def test_origin_delta_custom_in_parent_frame():
    pert = LegPerturbation(origin_deltas_m={"jc": (0.01, -0.02, 0.005)})
    xyz0, R0 = joint_origin(CUSTOM_URDF, "jc")
    xyz1, R1 = joint_origin(apply_perturbation(CUSTOM_URDF, pert), "jc")
    np.testing.assert_allclose(xyz1 - xyz0, [0.01, -0.02, 0.005], atol=1e-15)
    np.testing.assert_allclose(R1, R0, atol=1e-15)


def test_hip_offset_delta_a1_both_sides():
    xml = builtin_urdf("a1")
    for leg_name, side in (("fl", 1.0), ("fr", -1.0), ("rl", 1.0), ("rr", -1.0)):
        d = hip_offset_delta(xml, f"{leg_name}_thigh_joint", 0.0038)
        np.testing.assert_allclose(d, [0, side * 0.0038, 0], atol=1e-15)
        true_xml = apply_perturbation(xml, LegPerturbation(origin_deltas_m={f"{leg_name}_thigh_joint": d}))
        leg = load_robot(urdf_xml=true_xml, feet=[f"{leg_name}_foot"]).leg(f"{leg_name}_foot")
        assert abs(leg.T_parent_joint[1][1, 3]) == pytest.approx(0.0838, abs=1e-15)  # Yuan's actual |omega|
    with pytest.raises(ModelError, match="no origin offset along its axis"):
        hip_offset_delta(xml, "fl_calf_joint", 0.01)
    with pytest.raises(ModelError, match="no axis"):
        hip_offset_delta(xml, "fl_foot_joint", 0.01)


def test_perturbation_errors():
    xml = builtin_urdf("a1")
    with pytest.raises(ModelError, match=r"'fl_thigh_jiont'.*did you mean 'fl_thigh_joint'"):
        apply_perturbation(xml, LegPerturbation(joint_offsets_rad={"fl_thigh_jiont": 0.1}))
    with pytest.raises(ModelError, match="not in the URDF"):
        apply_perturbation(xml, LegPerturbation(origin_deltas_m={"nope": (0, 0, 0.1)}))
    with pytest.raises(ModelError, match="only revolute"):
        apply_perturbation(xml, LegPerturbation(joint_offsets_rad={"fl_foot_joint": 0.1}))
    with pytest.raises(ModelError, match="not in the URDF"):
        link_length_delta(xml, "fl_knee_joint", 0.01)
    with pytest.raises(ModelError, match="3 finite numbers"):
        LegPerturbation(origin_deltas_m={"fl_thigh_joint": (0.0, 0.1)})


def test_leg_perturbation_is_frozen_and_hashable():
    a = LegPerturbation({"j": 0.1}, {"k": (0.0, 0.0, 0.01)})
    b = LegPerturbation(joint_offsets_rad={"j": 0.1}, origin_deltas_m={"k": np.array([0.0, 0.0, 0.01])})
    assert a == b and hash(a) == hash(b)
    assert a != LegPerturbation({"j": 0.2})
    assert a.joint_offsets_rad["j"] == 0.1 and a.origin_deltas_m["k"] == (0.0, 0.0, 0.01)
    with pytest.raises(TypeError):
        a.joint_offsets_rad["j"] = 0.3  # type: ignore[index]
    with pytest.raises(AttributeError):
        a.joint_offsets_rad = {}  # type: ignore[misc]
    empty = LegPerturbation()
    assert len(empty.joint_offsets_rad) == 0 and len(empty.origin_deltas_m) == 0
    assert apply_perturbation(builtin_urdf("a1"), empty)  # no-op still valid URDF
    s = a + LegPerturbation({"j": 0.05})
    assert s.joint_offsets_rad["j"] == pytest.approx(0.15)


def test_outside_limits_skips_joints_without_usable_limits():
    """A URDF joint without <limit> can come back as lower == upper: never 'outside' (validate and
    calibrate's joint-angle warnings share this rule)."""
    from dataclasses import replace

    leg = load_robot(model="octopus").leg("lf_foot")
    lo, hi = np.array(leg.lower), np.array(leg.upper)
    q = np.vstack([0.5 * (lo + hi), hi + 0.01, lo - 0.0005])
    assert leg.outside_limits(q).tolist() == [[False] * 3, [True] * 3, [False] * 3]
    no_limits = replace(leg, lower=np.zeros(3), upper=np.zeros(3))
    assert not no_limits.outside_limits(q).any()


def test_each_sensor_type_is_one_record_read_by_import_plane_fitting_and_the_range_check():
    """models/sensors.py's SensorType records are what the import map, the plane fitting and the
    range-scale check read (no second list of types elsewhere)."""
    from graphcal.calibration.range_observability import range_scale_limits
    from graphcal.clouds.plane_table import range_noise_for
    from graphcal.errors import GraphcalError
    from graphcal.logs import mapping
    from graphcal.models.sensors import SENSOR_TYPE_RECORDS, SENSOR_TYPES, StereoCamera, sensor_type

    assert SENSOR_TYPES == ("depth_camera", "laser_scanner", "stereo_camera")
    assert mapping.LOG_SENSOR_TYPES == ("depth_camera", "laser_scanner")  # a stereo pair is not imported
    assert mapping.TYPES["laser_scanner"] == SENSOR_TYPE_RECORDS["laser_scanner"].log_messages
    assert range_noise_for("laser_scanner") is None
    pts = np.array([[0.0, 0.0, 1.0], [0.3, -0.2, 2.0], [0.1, 0.4, 3.0]])  # points on rays, optical frame
    n = np.array([0.0, 0.0, 1.0])  # a fronto-parallel plane: distance noise = depth noise
    noise = range_noise_for("stereo_camera")
    assert noise is not None and np.allclose(noise(pts, n), StereoCamera().sigma_along_axis(pts[:, 2]))
    assert [sensor_type(t).fits_planes for t in SENSOR_TYPES] == [True, False, True]
    with pytest.raises(GraphcalError, match="unknown sensor type 'lidar'; expected one of depth_camera, laser_scanner"):
        sensor_type("lidar")
    class _Ds:  # the two sensors of a dataset.yaml
        sensors = {"laser": type("S", (), {"type": "laser_scanner"}), "cam": type("S", (), {"type": "stereo_camera"})}

    limits = range_scale_limits(_Ds, None)
    assert limits["laser"][0] == SENSOR_TYPE_RECORDS["laser_scanner"].range_scale_check_pct
    assert limits["cam"][1] == "default for a stereo_camera (graphcal/models/sensors.py)"


def test_each_cause_is_one_record_with_its_parameters_and_minimum_size():
    from graphcal.diagnosis.catalogue import relevant
    from graphcal.models.effects import CAUSE_RECORDS, CAUSES, cause_record

    assert CAUSES == tuple(CAUSE_RECORDS) and len(CAUSES) == 10
    assert all(c.parameter.endswith(("_m", "_rad", "_per_m")) or c.name == "sensor_range_scale"
               for c in CAUSE_RECORDS.values() if c.parameters)
    assert [c for c in CAUSES if cause_record(c).kinematic] == ["joint_offset", "link_length", "foot_radius",
                                                               "joint_compliance"]
    # the minimum sizes, either side of them
    assert not relevant("sensor_range_scale", {"scale": 0.9975}) and relevant("sensor_range_scale", {"scale": 1.0031})
    assert not relevant("extrinsic_change", {"angle_rad": np.radians(0.49), "translation_m": 0.0049})
    assert relevant("extrinsic_change", {"angle_rad": np.radians(0.1), "translation_m": -0.0051})
    assert relevant("joint_offset", {"offset_rad": -np.radians(0.51)})
    assert not relevant("joint_compliance", {"k_rad_per_m": 0.079})
    assert relevant("outlier_stations", {})
    with pytest.raises(KeyError, match="unknown cause 'wobble'"):
        cause_record("wobble")
