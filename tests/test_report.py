"""Calibration outputs: calibration.yaml, calibrated URDF, ROS 2 static transforms, HTML report,
and the atomic writing of the set (graphcal.report)."""

from __future__ import annotations

import base64
import html.parser
import os
import stat
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml

from graphcal.calibration.result import (
    CalibrationResult,
    ExtrinsicSegment,
    IncrementalStep,
    LegEstimate,
    NoiseGroupEstimate,
    SensorEstimate,
    StationResidual,
)
from graphcal.errors import DatasetError, GraphcalError, ModelError
from graphcal.geometry import (
    invert_pose,
    matrix_from_quat_wxyz,
    matrix_from_rpy,
    pose_from_xyz_rpy,
    pose_matrix,
    rot_x,
    rot_y,
    rot_z,
    se3_exp,
)
from graphcal.io.calibration_yaml import FORMAT, pose_from_dict, read_calibration_yaml
from graphcal.models.builtin import builtin_info, builtin_urdf
from graphcal.models.perturb import LegPerturbation, apply_perturbation, link_length_delta
from graphcal.models.robot import load_robot
from graphcal.report import write as write_mod
from graphcal.report.calibration_yaml import calibration_to_dict, calibration_yaml_text
from graphcal.report.ros import static_transform_publisher_command, static_transforms_script
from graphcal.report.urdf import calibrated_urdf
from graphcal.report.write import OUTPUT_FILES, write_calibration_outputs

N_STATIONS = 52


# ----------------------------------------------------------------------------- a fake, consistent result
def _spd(rng, scales) -> np.ndarray:
    A = rng.normal(size=(6, 6))
    C = A @ A.T + 0.5 * np.eye(6)
    d = np.sqrt(np.diag(C))
    C = C / np.outer(d, d)  # a correlation matrix
    return C * np.outer(scales, scales)


def _sensor_estimate(rng, name, stype, T_prior, T_est, segments=(), change_stations=(), unobservable=()):
    cov = _spd(rng, np.array([np.deg2rad(0.05)] * 3 + [0.0008] * 3))
    R = T_est[:3, :3]
    J = np.zeros((6, 6))
    J[:3, :3] = R
    J[3:, 3:] = R
    Cb = J @ cov @ J.T
    s = np.sqrt(np.diag(Cb))
    return SensorEstimate(
        name=name,
        type=stype,
        T_body_sensor=T_est,
        covariance=cov,
        T_body_sensor_prior=T_prior,
        sigma_rot_deg=np.rad2deg(s[:3]),
        sigma_xyz_mm=s[3:] * 1000.0,
        correlation=Cb / np.outer(s, s),
        unobservable=tuple(unobservable),
        segments=tuple(segments) or (ExtrinsicSegment(1, N_STATIONS, T_est, cov),),
        change_stations=tuple(change_stations),
    )


def make_result(*, moved: bool = False, legs: bool = True, history: bool = False, seed: int = 0) -> CalibrationResult:
    rng = np.random.default_rng(seed)
    info = builtin_info("octopus")
    T_prior = np.array(info.sensors["depth"].T_body_sensor)
    T_depth = T_prior @ se3_exp([0.01, -0.02, 0.015, 0.004, -0.006, 0.003])
    T_lidar_prior = pose_from_xyz_rpy([0.30, -0.02, 0.12], [0.0, 0.1, 0.0])
    T_lidar = T_lidar_prior @ se3_exp([0.002, 0.003, -0.004, 0.001, 0.002, -0.001])
    segs, chg = (), ()
    if moved:
        T_first = T_depth @ se3_exp([0.0, 0.03, 0.0, 0.0, 0.0, 0.0])
        cov1 = _spd(rng, np.array([np.deg2rad(0.08)] * 3 + [0.001] * 3))
        cov2 = _spd(rng, np.array([np.deg2rad(0.06)] * 3 + [0.0009] * 3))
        segs = (ExtrinsicSegment(1, 29, T_first, cov1), ExtrinsicSegment(30, N_STATIONS, T_depth, cov2))
        chg = (30,)
    depth = _sensor_estimate(rng, "depth", "depth_camera", T_prior, T_depth, segs, chg)
    lidar = _sensor_estimate(
        rng, "lidar", "laser_scanner", T_lidar_prior, T_lidar,
        unobservable=("translation along the scan-plane normal: tilt the body about its x axis",),
    )  # fmt: skip
    residuals = []
    for st in range(1, N_STATIONS + 1):
        for name in ("depth", "lidar"):
            residuals.append(
                StationResidual(
                    station=st, sensor=name,
                    angle_before_deg=float(abs(rng.normal(1.5, 0.4))),
                    distance_before_mm=float(rng.normal(12.0, 3.0)),
                    angle_after_deg=float(abs(rng.normal(0.2, 0.08))),
                    distance_after_mm=float(rng.normal(0.0, 1.1)),
                    chi2_after=float(rng.chisquare(3)),
                    outlier=(st == 17),
                )
            )  # fmt: skip
    leg_est = {}
    if legs:
        leg_est = {
            "lf_foot": LegEstimate(
                "lf_foot", ("lf_femur_joint.offset_rad", "lf_foot_joint.delta_m"), np.array([0.012, 0.004]), np.array([0.001, 0.0005])
            ),
            "rm_foot": LegEstimate("rm_foot", ("rm_tibia_joint.offset_rad",), np.array([-0.02]), np.array([0.002])),
        }
    hist = ()
    if history:
        hist = tuple(
            IncrementalStep(
                station=st, sensor="depth", T_body_sensor=T_depth,
                sigma_rot_deg=np.array([1.0, 1.2, 0.8]) / np.sqrt(st), sigma_xyz_mm=np.array([10.0, 12.0, 9.0]) / np.sqrt(st),
                window_chi2=float(rng.chisquare(10)), window_dof=10, change_detected=(st == 30),
            )
            for st in range(1, N_STATIONS + 1)
        )  # fmt: skip
    return CalibrationResult(
        dataset="/data/octopus run --1",
        robot_urdf_xml=builtin_urdf("octopus"),
        base_frame="body",
        sensors={"depth": depth, "lidar": lidar},
        legs=leg_est,
        outliers=(17,),
        residuals=tuple(residuals),
        normal_rms_deg=0.21,
        distance_rms_mm=1.1,
        T_world_body={1: np.eye(4)},
        solver="incremental" if history else "batch",
        iterations=N_STATIONS if history else 7,
        history=hist,
        warnings=("lidar: one direction not determined",),
        noise_groups=(
            NoiseGroupEstimate("foot_on_ground", (("sigma_ground_m", 6e-5),), "too few dof", 2.7, 6, 0.27, 0.97),
            NoiseGroupEstimate("imu", (("sigma_imu_rad", np.deg2rad(0.038)),), "learned", 100.2, 104, 1.0, 0.48),
            NoiseGroupEstimate("plane:depth", (("plane_scale:depth", 1.006),), "learned", 80.1, 156, 1.0, 0.48),
        ),
    )


@pytest.fixture(scope="module")
def result():
    return make_result()


def _leaves(x):
    if isinstance(x, dict):
        for k, v in x.items():
            assert isinstance(k, str), k
            yield from _leaves(v)
    elif isinstance(x, list):
        for v in x:
            yield from _leaves(v)
    else:
        yield x


# ----------------------------------------------------------------------------- calibration.yaml
def test_yaml_has_exactly_the_contract_keys(result):
    text = calibration_yaml_text(result)
    assert text.startswith("# ") and "graphcal" in text.splitlines()[0]
    assert "!!" not in text and "!<" not in text  # no YAML tags
    doc = yaml.safe_load(text)
    assert doc["format"] == "graphcal-calibration/1" == FORMAT
    assert {"format", "sensors", "legs", "outliers", "residuals"} <= set(doc)
    assert list(doc["sensors"]) == ["depth", "lidar"]
    for s in doc["sensors"].values():
        assert {"T_body_sensor", "covariance", "sigma", "unobservable"} <= set(s)
        assert set(s["T_body_sensor"]) == {"xyz", "quaternion_wxyz", "rpy_deg"}
        assert set(s["T_body_sensor_prior"]) == {"xyz", "quaternion_wxyz", "rpy_deg"}
        assert set(s["sigma"]) == {"rot_deg", "xyz_mm"}
        assert len(s["sigma"]["rot_deg"]) == 3 and len(s["sigma"]["xyz_mm"]) == 3
        assert isinstance(s["unobservable"], list)
    assert doc["sensors"]["depth"]["unobservable"] == []
    assert len(doc["sensors"]["lidar"]["unobservable"]) == 1
    assert set(doc["legs"]) == {"lf_foot", "rm_foot"}
    assert set(doc["legs"]["lf_foot"]) == {"lf_femur_joint.offset_rad", "lf_foot_joint.delta_m"}
    for p in doc["legs"]["lf_foot"].values():
        assert set(p) == {"value", "sigma"}
    assert {"normal_rms_deg", "distance_rms_mm"} <= set(doc["residuals"])
    assert doc["outliers"] == [17]
    for leaf in _leaves(doc):
        assert type(leaf) in (str, int, float), type(leaf)


def test_yaml_states_the_frames_of_its_numbers(result):
    """The file says which axes each block is in (issue: sqrt(diag(covariance)) != sigma puzzled
    readers): the covariance in sensor axes, sigma in body axes, and the two agree once rotated."""
    doc = yaml.safe_load(calibration_yaml_text(result))
    frames = doc["frames"]
    assert set(frames) == {"T_body_sensor", "covariance", "sigma", "correlation", "sigma_from", "range_scale_check",
                           "time_offset_s"}
    assert "stamp minus its capture time, in s" in frames["time_offset_s"]
    assert "SENSOR axes" in frames["covariance"] and "rad and m" in frames["covariance"]
    assert "BODY axes" in frames["sigma"] and "deg and mm" in frames["sigma"]
    s = doc["sensors"]["depth"]
    T = pose_from_dict(s["T_body_sensor"])
    C = np.asarray(s["covariance"])
    R = T[:3, :3]
    rot_body = np.sqrt(np.diag(R @ C[:3, :3] @ R.T))
    xyz_body = np.sqrt(np.diag(R @ C[3:, 3:] @ R.T))
    np.testing.assert_allclose(np.degrees(rot_body), s["sigma"]["rot_deg"], rtol=1e-9)
    np.testing.assert_allclose(1e3 * xyz_body, s["sigma"]["xyz_mm"], rtol=1e-9)
    assert not np.allclose(np.degrees(np.sqrt(np.diag(C[:3, :3]))), s["sigma"]["rot_deg"], rtol=1e-3)


def test_yaml_without_legs_has_no_legs_key():
    doc = yaml.safe_load(calibration_yaml_text(make_result(legs=False)))
    assert "legs" not in doc


def test_yaml_round_trip_of_numbers(result):
    doc = yaml.safe_load(calibration_yaml_text(result))
    d = result.sensors["depth"]
    s = doc["sensors"]["depth"]
    assert s["T_body_sensor"]["xyz"] == d.T_body_sensor[:3, 3].tolist()  # exact
    assert s["covariance"] == d.covariance.tolist()
    assert s["sigma"]["rot_deg"] == d.sigma_rot_deg.tolist()
    assert s["sigma"]["xyz_mm"] == d.sigma_xyz_mm.tolist()
    assert s["correlation"] == d.correlation.tolist()
    assert doc["legs"]["lf_foot"]["lf_foot_joint.delta_m"] == {"value": 0.004, "sigma": 0.0005}
    assert doc["residuals"]["normal_rms_deg"] == 0.21 and doc["residuals"]["distance_rms_mm"] == 1.1
    np.testing.assert_allclose(pose_from_dict(s["T_body_sensor"]), d.T_body_sensor, atol=1e-14)
    np.testing.assert_allclose(pose_from_dict(s["T_body_sensor_prior"]), d.T_body_sensor_prior, atol=1e-14)


def test_yaml_rotation_representations_agree_with_the_matrix(result):
    doc = calibration_to_dict(result)
    for name, s in doc["sensors"].items():
        R = result.sensors[name].T_body_sensor[:3, :3]
        q = np.array(s["T_body_sensor"]["quaternion_wxyz"])
        assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(matrix_from_quat_wxyz(q), R, atol=1e-12)
        np.testing.assert_allclose(matrix_from_rpy(np.deg2rad(s["T_body_sensor"]["rpy_deg"])), R, atol=1e-12)


def test_yaml_rotation_known_values():
    """Independent of the helpers: yaw 30 deg about z, then a pitch of 20 deg."""
    res = make_result(legs=False)
    d = res.sensors["depth"]
    T = pose_matrix(rot_z(np.deg2rad(30.0)) @ rot_y(np.deg2rad(20.0)) @ rot_x(np.deg2rad(-10.0)), [0.1, 0.2, 0.3])
    res.sensors["depth"] = SensorEstimate(**{**d.__dict__, "T_body_sensor": T})
    s = calibration_to_dict(res)["sensors"]["depth"]["T_body_sensor"]
    np.testing.assert_allclose(s["rpy_deg"], [-10.0, 20.0, 30.0], atol=1e-12)
    T2 = pose_matrix(rot_z(np.deg2rad(30.0)), [0, 0, 0])
    res.sensors["depth"] = SensorEstimate(**{**d.__dict__, "T_body_sensor": T2})
    q = calibration_to_dict(res)["sensors"]["depth"]["T_body_sensor"]["quaternion_wxyz"]
    np.testing.assert_allclose(q, [np.cos(np.deg2rad(15)), 0, 0, np.sin(np.deg2rad(15))], atol=1e-15)


def test_yaml_covariance_is_6x6_symmetric(result):
    doc = calibration_to_dict(result)
    for s in doc["sensors"].values():
        C = np.array(s["covariance"])
        assert C.shape == (6, 6)
        np.testing.assert_array_equal(C, C.T)
        assert np.all(np.linalg.eigvalsh(C) > 0)
        K = np.array(s["correlation"])
        assert K.shape == (6, 6)
        np.testing.assert_allclose(np.diag(K), 1.0, atol=1e-12)


def test_yaml_segments_only_when_the_sensor_moved(result):
    doc = calibration_to_dict(result)
    assert "segments" not in doc["sensors"]["depth"]
    assert doc["sensors"]["depth"]["change_stations"] == []
    moved = make_result(moved=True)
    s = calibration_to_dict(moved)["sensors"]["depth"]
    assert s["change_stations"] == [30]
    assert [(g["first_station"], g["last_station"]) for g in s["segments"]] == [(1, 29), (30, N_STATIONS)]
    for g, seg in zip(s["segments"], moved.sensors["depth"].segments):
        np.testing.assert_allclose(pose_from_dict(g["T_body_sensor"]), seg.T_body_sensor, atol=1e-14)
        # sigma along the body axes: the sensor origin moves by R v, rotation about body axes is R omega
        R = seg.T_body_sensor[:3, :3]
        C_v = R @ seg.covariance[3:, 3:] @ R.T
        C_w = R @ seg.covariance[:3, :3] @ R.T
        np.testing.assert_allclose(g["sigma"]["xyz_mm"], 1000 * np.sqrt(np.diag(C_v)), rtol=1e-12)
        np.testing.assert_allclose(g["sigma"]["rot_deg"], np.rad2deg(np.sqrt(np.diag(C_w))), rtol=1e-12)


def test_undetermined_direction_gives_infinite_sigma(tmp_path):
    res = make_result(moved=True, legs=False)
    d = res.sensors["depth"]
    seg0, seg1 = d.segments
    cov = seg0.covariance.copy()
    cov[5, :] = cov[:, 5] = 0.0
    cov[5, 5] = np.inf  # sensor z (optical axis) undetermined in the first segment
    T0 = d.T_body_sensor_prior  # optical axis exactly in the body x-z plane
    res.sensors["depth"] = SensorEstimate(**{**d.__dict__, "segments": (ExtrinsicSegment(1, 29, T0, cov), seg1)})
    text = calibration_yaml_text(res)
    p = tmp_path / "calibration.yaml"
    p.write_text(text)
    g = read_calibration_yaml(p)["sensors"]["depth"]["segments"][0]["sigma"]
    # the optical axis of the octopus camera lies in the body x-z plane: x and z undetermined, y not
    R = T0[:3, :3]
    assert R[1, 2] == 0.0 and abs(R[0, 2]) > 0.5 and abs(R[2, 2]) > 0.5
    assert np.isinf(g["xyz_mm"][0]) and np.isinf(g["xyz_mm"][2]) and np.isfinite(g["xyz_mm"][1])
    assert all(np.isfinite(g["rot_deg"]))


def test_read_calibration_yaml_round_trip(tmp_path, result):
    p = tmp_path / "calibration.yaml"
    p.write_text(calibration_yaml_text(result), encoding="utf-8")
    doc = read_calibration_yaml(p)
    assert doc == yaml.safe_load(p.read_text())
    np.testing.assert_allclose(pose_from_dict(doc["sensors"]["lidar"]["T_body_sensor"]), result.sensors["lidar"].T_body_sensor, atol=1e-14)


def _mutate(doc, path, value):
    d = doc
    for k in path[:-1]:
        d = d[k]
    if value is _DELETE:
        del d[path[-1]]
    else:
        d[path[-1]] = value


_DELETE = object()


@pytest.mark.parametrize(
    "path, value, where",
    [
        (("format",), "graphcal-dataset/1", "format"),
        (("format",), _DELETE, "format"),
        (("sensors",), _DELETE, "sensors"),
        (("sensors", "depth", "T_body_sensor", "xyz"), [1.0, 2.0], "sensors.depth.T_body_sensor.xyz"),
        (("sensors", "depth", "T_body_sensor", "quaternion_wxyz"), [1.0, 1.0, 0.0, 0.0], "sensors.depth.T_body_sensor.quaternion_wxyz"),
        (("sensors", "depth", "T_body_sensor", "rpy_deg"), [0.0, 0.0, 0.0], "sensors.depth.T_body_sensor.rpy_deg"),
        (("sensors", "lidar", "covariance"), [[1.0] * 6 for _ in range(5)], "sensors.lidar.covariance"),
        (("sensors", "lidar", "sigma"), {"rot_deg": [1, 2, 3]}, "sensors.lidar.sigma.xyz_mm"),
        (("sensors", "lidar", "unobservable"), "none", "sensors.lidar.unobservable"),
        (("sensors", "depth", "T_body_sensor_prior", "xyz"), ["a", 0, 0], "sensors.depth.T_body_sensor_prior.xyz"),
        (("legs", "lf_foot", "lf_foot_joint.delta_m", "value"), "x", "legs.lf_foot.lf_foot_joint.delta_m.value"),
        (("outliers",), [1.5], "outliers"),
        (("residuals", "normal_rms_deg"), _DELETE, "residuals.normal_rms_deg"),
    ],
)
def test_read_calibration_yaml_refuses_malformed(tmp_path, result, path, value, where):
    doc = calibration_to_dict(result)
    _mutate(doc, path, value)
    p = tmp_path / "bad_calibration.yaml"
    p.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    with pytest.raises(DatasetError) as ei:
        read_calibration_yaml(p)
    assert str(p) in str(ei.value)
    assert ei.value.where == where


def test_read_calibration_yaml_refuses_bad_yaml_and_non_mapping(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("format: [unclosed\n", encoding="utf-8")
    with pytest.raises(DatasetError, match="c.yaml: line"):
        read_calibration_yaml(p)
    p.write_text("- 1\n- 2\n", encoding="utf-8")
    with pytest.raises(DatasetError, match="c.yaml"):
        read_calibration_yaml(p)
    with pytest.raises(DatasetError, match="missing.yaml"):
        read_calibration_yaml(tmp_path / "missing.yaml")


# ----------------------------------------------------------------------------- URDF
def _placement(urdf_xml: str, base: str, frame: str) -> np.ndarray:
    """T_base_frame at the neutral configuration, straight from Pinocchio."""
    import pinocchio as pin

    robot = load_robot(urdf_xml=urdf_xml, base_frame=base)
    m = robot.pin_model
    d = m.createData()
    pin.framesForwardKinematics(m, d, pin.neutral(m))
    fid = {f.name: i for i, f in enumerate(m.frames) if f.type == pin.FrameType.BODY}
    T_w_b = np.asarray(d.oMf[fid[base]].homogeneous)
    T_w_f = np.asarray(d.oMf[fid[frame]].homogeneous)
    return invert_pose(T_w_b) @ T_w_f


def test_urdf_sensor_placement_equals_calibration(result):
    sensors = {n: s.T_body_sensor for n, s in result.sensors.items()}
    text = calibrated_urdf(result.robot_urdf_xml, "body", sensors, None, dataset=result.dataset)
    assert text.startswith("<?xml")
    head = text.split("<robot", 1)[0]
    assert "graphcal calibrate" in head and "/data/octopus run - -1" in head
    assert "--" not in head.split("<!--", 1)[1].rsplit("-->", 1)[0]  # not allowed inside an XML comment
    for name, T in sensors.items():
        np.testing.assert_allclose(_placement(text, "body", name), T, atol=1e-9)
    # the added lidar link hangs from body by lidar_joint; depth_joint is still the one joint of depth
    assert text.count('name="lidar_joint"') == 1 and text.count('name="depth_joint"') == 1
    # nothing else moved: a foot at neutral configuration is where the nominal URDF has it
    np.testing.assert_allclose(
        _placement(text, "body", "lf_foot"), _placement(result.robot_urdf_xml, "body", "lf_foot"), atol=1e-12
    )


_MOUNT_URDF = """<?xml version="1.0"?>
<robot name="mounted">
  <!-- a sensor on a bracket, the body below a root link -->
  <link name="base_link"/>
  <link name="body"/>
  <joint name="body_joint" type="fixed">
    <parent link="base_link"/><child link="body"/>
    <origin xyz="0.1 -0.2 0.3" rpy="0.1 0.2 -0.3"/>
  </joint>
  <link name="bracket"/>
  <joint name="bracket_joint" type="fixed">
    <parent link="body"/><child link="bracket"/>
    <origin xyz="0.4 0.0 0.2" rpy="0.0 0.5 0.2"/>
  </joint>
  <link name="cam"/>
  <joint name="cam_joint" type="fixed">
    <parent link="bracket"/><child link="cam"/>
    <origin xyz="0.05 0 0" rpy="0 0 0"/>
  </joint>
  <link name="head"/>
  <joint name="neck" type="revolute">
    <parent link="body"/><child link="head"/>
    <origin xyz="0.2 0 0.1" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
  <link name="headcam"/>
  <joint name="headcam_joint" type="fixed">
    <parent link="head"/><child link="headcam"/>
  </joint>
</robot>
"""


def test_urdf_sensor_on_a_bracket_and_base_below_root():
    T_cam = pose_from_xyz_rpy([0.5, 0.01, 0.25], [-1.2, 0.05, -1.5])
    T_new = pose_from_xyz_rpy([-0.1, 0.02, 0.05], [0.3, -0.2, 2.9])
    text = calibrated_urdf(_MOUNT_URDF, "body", {"cam": T_cam, "rear": T_new})
    np.testing.assert_allclose(_placement(text, "body", "cam"), T_cam, atol=1e-9)
    np.testing.assert_allclose(_placement(text, "body", "rear"), T_new, atol=1e-9)
    # the bracket is untouched, the user's comment kept
    np.testing.assert_allclose(_placement(text, "body", "bracket"), _placement(_MOUNT_URDF, "body", "bracket"), atol=1e-12)
    assert "a sensor on a bracket" in text


def test_urdf_keeps_the_namespace_prefixes_of_the_input():
    """Gazebo and xacro elements keep their prefixes (ElementTree wrote ns0:camera for sensor:camera,
    which readers matching tag names literally do not see), with legs calibrated too."""
    gazebo = ('<gazebo reference="cam" xmlns:sensor="http://playerstage.sourceforge.net/gazebo/xmlschema/#sensor">'
              '<sensor:camera name="c1"/></gazebo>\n  <xacro:property name="unused" value="1"/>\n</robot>')
    src = _MOUNT_URDF.replace('<robot name="mounted">', '<robot name="mounted" xmlns:xacro="http://www.ros.org/wiki/xacro">')
    src = src.replace("</robot>", gazebo)
    text = calibrated_urdf(src, "body", {"cam": pose_from_xyz_rpy([0.5, 0.0, 0.2], [0.0, 0.3, 0.0])},
                           {"headcam": {"neck.offset_rad": 0.01}})
    assert '<sensor:camera name="c1"' in text and '<xacro:property name="unused"' in text
    assert 'xmlns:sensor="http://playerstage.sourceforge.net/gazebo/xmlschema/#sensor"' in text
    assert "ns0" not in text


def test_urdf_refuses_sensor_on_a_moving_link():
    with pytest.raises(ModelError, match="moves relative to the base frame"):
        calibrated_urdf(_MOUNT_URDF, "body", {"headcam": np.eye(4)})
    with pytest.raises(ModelError, match="base frame"):
        calibrated_urdf(_MOUNT_URDF, "chassis", {"cam": np.eye(4)})
    with pytest.raises(ModelError, match="type 'revolute'"):
        calibrated_urdf(_MOUNT_URDF, "body", {"head": np.eye(4)})


def test_urdf_legs_equal_perturb_and_kinematics(result):
    nominal = result.robot_urdf_xml
    legs = {foot: dict(zip(le.names, le.values.tolist())) for foot, le in result.legs.items()}
    text = calibrated_urdf(nominal, "body", {}, legs)
    pert = LegPerturbation(
        joint_offsets_rad={"lf_femur_joint": 0.012, "rm_tibia_joint": -0.02},
        origin_deltas_m={"lf_foot_joint": tuple(link_length_delta(nominal, "lf_foot_joint", 0.004))},
    )
    expected = apply_perturbation(nominal, pert)
    feet = builtin_info("octopus").feet
    calib = load_robot(urdf_xml=text, feet=feet)
    ref = load_robot(urdf_xml=expected, feet=feet)
    nom = load_robot(urdf_xml=nominal, feet=feet)
    rng = np.random.default_rng(3)
    for _ in range(5):
        q = rng.uniform(-0.6, 0.6, 3)
        for foot in ("lf_foot", "rm_foot", "lr_foot"):
            np.testing.assert_allclose(calib.fk_pinocchio(foot, q), ref.fk_pinocchio(foot, q), atol=1e-12)
        # independently of perturb: an encoder offset adds to the joint angle ...
        np.testing.assert_allclose(
            calib.fk_pinocchio("rm_foot", q), nom.fk_pinocchio("rm_foot", q + [0, 0, -0.02]), atol=1e-12
        )
        np.testing.assert_allclose(calib.fk_pinocchio("lr_foot", q), nom.fk_pinocchio("lr_foot", q), atol=1e-12)
    # ... and delta_m lengthens the shank (tibia joint to foot) by 4 mm
    info = builtin_info("octopus")
    leg = calib.leg("lf_foot")
    shank = np.linalg.norm(leg.T_lastjoint_foot[:3, 3])
    nominal_shank = np.linalg.norm(nom.leg("lf_foot").T_lastjoint_foot[:3, 3])
    assert abs(shank - nominal_shank - 0.004) < 1e-12
    assert info.feet  # sanity


def test_urdf_legs_reproduce_the_calibration_model():
    """The calibrated URDF's FK equals graphcal.models.legs' parameterised FK, every leg and
    every parameter (the model the calibration estimates theta in)."""
    import graphcal.models.legs as lp  # in this repository: a broken import must fail, not skip
    for model in ("octopus", "a1"):
        nom = load_robot(model=model)
        rng = np.random.default_rng(11)
        legs, thetas = {}, {}
        for foot in nom.feet:
            param = lp.leg_model(nom, foot, origins="none")
            theta = rng.normal(0.0, 0.01, param.dim)
            legs[foot] = dict(zip(param.names, theta.tolist()))
            thetas[foot] = (param, theta)
        calib = load_robot(urdf_xml=calibrated_urdf(nom.urdf_xml, "body", {}, legs), feet=nom.feet)
        for foot, (param, theta) in thetas.items():
            leg = nom.leg(foot)
            q = rng.uniform(-0.5, 0.5, (4, leg.n_joints))
            p_model = lp.fk_with_params(leg, param, q, theta)
            p_urdf = np.array([calib.fk_pinocchio(foot, qi)[:3, 3] for qi in q])
            np.testing.assert_allclose(p_urdf, p_model, atol=1e-12)


_PRISMATIC_URDF = """<robot name="p">
  <link name="body"/><link name="slider"/><link name="foot"/>
  <joint name="slide" type="prismatic"><parent link="body"/><child link="slider"/>
    <origin xyz="0.1 0 0"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="foot_joint" type="fixed"><parent link="slider"/><child link="foot"/><origin xyz="0 0 -0.3"/></joint>
</robot>
"""


def test_urdf_prismatic_offset_and_foot_delta():
    legs = {"foot": {"slide.offset_m": 0.02, "foot_joint.delta_m": 0.01, "foot.delta_m": 0.0}}
    text = calibrated_urdf(_PRISMATIC_URDF, "body", {}, legs)
    calib = load_robot(urdf_xml=text, feet=("foot",))
    nom = load_robot(urdf_xml=_PRISMATIC_URDF, feet=("foot",))
    # independently: q_true = q + 0.02 along z, and the foot link 0.31 m instead of 0.3 m
    np.testing.assert_allclose(calib.fk_pinocchio("foot", [0.1])[:3, 3], [0.1, 0.0, 0.12 - 0.31], atol=1e-12)
    np.testing.assert_allclose(nom.fk_pinocchio("foot", [0.1])[:3, 3], [0.1, 0.0, 0.1 - 0.3], atol=1e-12)
    with pytest.raises(ModelError, match="slide.offset_m"):
        calibrated_urdf(_PRISMATIC_URDF, "body", {}, {"foot": {"slide.offset_rad": 0.02}})
    with pytest.raises(ModelError, match="not a URDF joint"):
        calibrated_urdf(_PRISMATIC_URDF, "body", {}, {"foot": {"foot.delta_m": 0.01}})


def test_urdf_refuses_unknown_leg_parameter(result):
    with pytest.raises(ModelError, match="offset_rad"):
        calibrated_urdf(result.robot_urdf_xml, "body", {}, {"lf_foot": {"lf_femur_joint.scale": 1.0}})
    with pytest.raises(ModelError, match="not in the URDF"):
        calibrated_urdf(result.robot_urdf_xml, "body", {}, {"lf_foot": {"nope_joint.offset_rad": 0.1}})


# ----------------------------------------------------------------------------- ROS
def test_static_transform_publisher_line_parses():
    T = pose_from_xyz_rpy([0.528123456789, -0.033, 0.365], [-1.9, 0.02, -1.4])
    line = static_transform_publisher_command("body", "depth", T)
    tok = line.split(" ")
    assert tok[:4] == ["ros2", "run", "tf2_ros", "static_transform_publisher"]
    args = dict(zip(tok[4::2], tok[5::2]))
    assert len(tok) == 4 + 2 * 9 and set(args) == {
        "--x", "--y", "--z", "--qx", "--qy", "--qz", "--qw", "--frame-id", "--child-frame-id"
    }  # fmt: skip
    assert args["--frame-id"] == "body" and args["--child-frame-id"] == "depth"
    xyz = [float(args[k]) for k in ("--x", "--y", "--z")]
    np.testing.assert_allclose(xyz, T[:3, 3], rtol=1e-8, atol=0)
    q = [float(args[k]) for k in ("--qw", "--qx", "--qy", "--qz")]
    np.testing.assert_allclose(matrix_from_quat_wxyz(q), T[:3, :3], atol=5e-9)
    assert args["--x"] == "0.528123457"  # 9 significant digits


def test_static_transforms_script_is_valid_shell(result, tmp_path):
    text = static_transforms_script("body", {n: s.T_body_sensor for n, s in result.sensors.items()}, dataset="/d")
    assert text.startswith("#!/bin/sh\n") and "\n# " in text
    assert text.count("static_transform_publisher --x") == 2
    p = tmp_path / "s.sh"
    p.write_text(text)
    assert subprocess.run(["sh", "-n", str(p)], capture_output=True).returncode == 0


# ----------------------------------------------------------------------------- HTML
class _Checker(html.parser.HTMLParser):
    VOID = {"meta", "img", "br", "hr", "link", "input", "source", "col", "wbr", "area", "base", "embed", "param", "track"}

    def __init__(self):
        super().__init__()
        self.stack, self.imgs, self.errors, self.text = [], [], [], []
        self.external = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.imgs.append(a)
        for k in ("src", "href"):
            if k in a and not str(a[k]).startswith(("data:", "#")):
                self.external.append(a[k])
        if tag not in self.VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"unexpected </{tag}>, open: {self.stack[-3:]}")
        else:
            self.stack.pop()

    def handle_data(self, data):
        self.text.append(data)


@pytest.fixture(scope="module")
def html_page():
    from graphcal.report.calibration_page import report_html
    from graphcal.report.plots import report_figures

    res = make_result(moved=True, history=True)
    return res, report_html(res, title="Octopus <test>"), len(report_figures(res))


def test_html_report_is_self_contained_and_complete(html_page):
    res, page, n_figures = html_page
    # 2 sensors with residuals x 3 figures + 2 ellipse figures + 1 incremental history
    assert n_figures == 9
    p = _Checker()
    p.feed(page)
    p.close()
    assert not p.errors and p.stack == [], (p.errors, p.stack)
    assert len(p.imgs) == n_figures
    for img in p.imgs:
        assert img["src"].startswith("data:image/png;base64,")
        assert base64.b64decode(img["src"].split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"
    assert p.external == []
    assert "<script" not in page and "stylesheet" not in page
    text = "".join(p.text)
    for name in res.sensors:
        assert name in text
    assert "Octopus <test>" in text  # escaped in the source, readable in the text
    assert "tilt the body about its x axis" in text  # unobservable direction shown
    assert "lf_femur_joint.offset_rad" in text
    assert "static_transform_publisher \\\n    --x" in text  # over four lines, as the shell reads it
    assert "17" in text  # the outlier
    # the noise model: how each group's sigma was set, at the edge in mm / deg
    assert "too few dof" in text and "0.06 mm" in text and "0.038 deg" in text and "x1.01" in text


def test_plots_draw_into_given_axes():
    from matplotlib.figure import Figure

    from graphcal.report.plots import plot_angle_errors, plot_covariance_ellipse, plot_distance_errors

    res = make_result(legs=False)
    fig = Figure()
    ax1, ax2, ax3 = fig.subplots(1, 3)
    plot_angle_errors(ax1, res.residuals, sensor="depth", outliers=res.outliers)
    plot_distance_errors(ax2, res.residuals, sensor="depth", outliers=res.outliers)
    # mean and max lines of before and after
    assert len(ax1.lines) >= 2 + 1 + 4
    rows = [r for r in res.residuals if r.sensor == "depth" and r.station != 17]
    ys = sorted({float(ln.get_ydata()[0]) for ln in ax1.lines if len(ln.get_ydata()) == 2 and ln.get_ydata()[0] == ln.get_ydata()[1]})
    assert any(abs(y - max(r.angle_after_deg for r in rows)) < 1e-12 for y in ys)
    assert any(abs(y - np.mean([r.angle_after_deg for r in rows])) < 1e-12 for y in ys)
    assert plot_covariance_ellipse(ax3, np.array([[4.0, 0.0], [0.0, 1.0]]))
    e1, e3 = ax3.patches[:2]
    assert (e1.width, e1.height) == (4.0, 2.0) and (e3.width, e3.height) == (12.0, 6.0)
    assert not plot_covariance_ellipse(ax3, np.array([[np.inf, 0.0], [0.0, 1.0]]))


# ----------------------------------------------------------------------------- writing the set
@pytest.fixture
def fast_report(monkeypatch):
    """A cheap report.html (no figures) for the tests about the file set, not the report."""

    def _write_report(folder, result, title, ds):
        return write_mod.atomic_write_text(folder / "report.html", f"<html><body>{len(result.sensors)}</body></html>\n")

    monkeypatch.setattr(write_mod, "_write_report", _write_report)


def _snapshot(folder: Path) -> dict:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    res = make_result()
    out = tmp_path_factory.mktemp("w") / "calib"
    paths = write_calibration_outputs(res, out)
    return res, out, paths


def test_written_outputs_name_the_dataset_relative_to_the_output_folder_not_by_a_machine_path(tmp_path):
    import dataclasses

    ds = tmp_path / "runs" / "octopus-2026"
    res = dataclasses.replace(make_result(seed=2, legs=False), dataset=str(ds))
    paths = write_calibration_outputs(res, tmp_path / "out" / "calib")
    for key in ("calibration", "urdf", "static_transforms"):
        text = paths[key].read_text()
        assert str(tmp_path) not in text, key
        assert "../../runs/octopus-2026" in text, key
    assert read_calibration_yaml(paths["calibration"])["dataset"] == "../../runs/octopus-2026"
    assert res.dataset == str(ds)  # the result the caller holds is not changed


def test_write_outputs_creates_the_four_files(written):
    res, out, paths = written
    assert set(paths) == {"calibration", "urdf", "static_transforms", "report", "scene"}
    assert sorted(p.name for p in out.iterdir()) == sorted(OUTPUT_FILES.values())
    for key, p in paths.items():
        assert p == out / OUTPUT_FILES[key] and p.stat().st_size > 0
    doc = read_calibration_yaml(paths["calibration"])
    assert doc["format"] == FORMAT
    for name, s in res.sensors.items():
        np.testing.assert_allclose(_placement(paths["urdf"].read_text(), "body", name), s.T_body_sensor, atol=1e-9)
    sh = paths["static_transforms"]
    assert sh.read_text().startswith("#!/bin/sh")
    assert sh.stat().st_mode & stat.S_IXUSR
    assert "<img" in paths["report"].read_text()
    assert [p.name for p in out.parent.iterdir()] == ["calib"]  # no temporary siblings left


def test_write_outputs_replaces_a_previous_calibration(tmp_path, fast_report):
    out = tmp_path / "calib"
    write_calibration_outputs(make_result(seed=1, legs=False), out)
    first = _snapshot(out)
    res2 = make_result(seed=2, legs=False)
    write_calibration_outputs(res2, out)
    second = _snapshot(out)
    assert set(second) == set(first) and second["calibration.yaml"] != first["calibration.yaml"]
    doc = read_calibration_yaml(out / "calibration.yaml")
    assert doc["sensors"]["depth"]["covariance"] == res2.sensors["depth"].covariance.tolist()


def test_write_outputs_failure_half_way_keeps_previous_results(tmp_path, fast_report, monkeypatch):
    out = tmp_path / "calib"
    write_calibration_outputs(make_result(seed=1, legs=False), out)
    before = _snapshot(out)
    calls = []
    real_yaml = write_mod._write_yaml

    def spy_yaml(folder, result):
        calls.append("yaml")
        return real_yaml(folder, result)

    def boom(folder, result):
        assert (folder / "calibration.yaml").stat().st_size > 0  # the first file was written
        raise RuntimeError("disk full")

    monkeypatch.setattr(write_mod, "_write_yaml", spy_yaml)
    monkeypatch.setattr(write_mod, "_write_urdf", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        write_calibration_outputs(make_result(seed=2, legs=False), out)
    assert calls == ["yaml"]
    assert _snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calib"]  # the temporary folder is gone
    # and a failure on the first run leaves nothing at all
    fresh = tmp_path / "fresh"
    with pytest.raises(RuntimeError):
        write_calibration_outputs(make_result(legs=False), fresh)
    assert not fresh.exists()


def test_write_outputs_refuses_a_foreign_folder(tmp_path, fast_report):
    ds = tmp_path / "dataset"
    ds.mkdir()
    (ds / "dataset.yaml").write_text("format: graphcal-dataset/1\n")
    (ds / "stations.csv").write_text("station\n1\n")
    before = _snapshot(ds)
    with pytest.raises(GraphcalError, match="holds no graphcal calibration"):
        write_calibration_outputs(make_result(legs=False), ds)
    assert _snapshot(ds) == before
    # a calibration.yaml that is not ours does not make the folder ours
    (ds / "calibration.yaml").write_text("format: kalibr/1\n")
    with pytest.raises(GraphcalError):
        write_calibration_outputs(make_result(legs=False), ds)
    assert (ds / "dataset.yaml").exists()
    # a file (not a folder) is refused too
    f = tmp_path / "file.txt"
    f.write_text("x")
    with pytest.raises(GraphcalError):
        write_calibration_outputs(make_result(legs=False), f)
    assert f.read_text() == "x"


def test_write_outputs_refuses_previous_calibration_with_user_files(tmp_path, fast_report):
    out = tmp_path / "calib"
    write_calibration_outputs(make_result(legs=False), out)
    (out / "my_notes.txt").write_text("keep me")
    before = _snapshot(out)
    with pytest.raises(GraphcalError, match="my_notes.txt"):
        write_calibration_outputs(make_result(seed=5, legs=False), out)
    assert _snapshot(out) == before


def test_calibrate_refuses_a_folder_with_user_files_before_the_work(tmp_path):
    """The output folder is checked first: the dataset (here absent) is not even read."""
    from graphcal.commands.calibrate import run as run_calibrate

    out = tmp_path / "calib"
    out.mkdir()
    (out / "my_notes.txt").write_text("keep me")
    with pytest.raises(GraphcalError, match="my_notes.txt"):
        run_calibrate(tmp_path / "no_dataset_here", out, progress=False)
    assert (out / "my_notes.txt").read_text() == "keep me"


def test_write_outputs_overwrite_false_and_empty_folder(tmp_path, fast_report):
    out = tmp_path / "calib"
    out.mkdir()
    write_calibration_outputs(make_result(legs=False), out, overwrite=False)  # empty folder: fine
    with pytest.raises(GraphcalError, match="overwrite=False"):
        write_calibration_outputs(make_result(legs=False), out, overwrite=False)
    assert os.listdir(out)


def test_station_counts_agree_between_the_yaml_and_the_report(result):
    """calibration.yaml counts every station with residuals, outliers included; the report's total
    row splits the same number into inliers + outliers (it showed the inlier rows of all sensors)."""
    from graphcal.report.calibration_page import _residual_section

    n = calibration_to_dict(result)["residuals"]["stations"]
    assert n == N_STATIONS and result.outliers == (17,)
    total = _residual_section(result).split("all (solver)")[1]
    assert f"<td>{n - 1} (+1 outl.)</td>" in total


def test_outlier_rows_stay_out_of_the_residual_summary():
    """calibration.yaml's residual RMS and maxima are over the stations kept: a station listed in
    ``outliers`` and a row flagged ``outlier`` are counted, not averaged in."""
    from types import SimpleNamespace as NS

    from graphcal.report.calibration_yaml import residual_summary

    def row(station, angle_deg, distance_mm, outlier=False):
        return NS(station=station, sensor="depth", outlier=outlier, angle_before_deg=angle_deg,
                  angle_after_deg=angle_deg, distance_before_mm=distance_mm, distance_after_mm=distance_mm)

    res = NS(outliers=(3,), residuals=[row(1, 0.3, 4.0), row(2, 0.4, -3.0), row(3, 9.0, 80.0), row(4, 5.0, 50.0, True)])
    s = residual_summary(res)
    assert s["stations"] == 2 and s["outlier_rows"] == 2
    assert s["normal_rms_deg_after"] == pytest.approx(np.sqrt((0.3**2 + 0.4**2) / 2), rel=1e-12)
    assert s["distance_max_mm_before"] == pytest.approx(4.0)


def test_atomic_write_gives_a_new_file_the_umask_mode_and_keeps_a_replaced_files_mode(tmp_path):
    """Not mkstemp's 0600: a new output is readable as any file the user writes (umask 022: 0644),
    and a file the user chmod-ed keeps its mode when rewritten."""
    from graphcal.io.atomic import atomic_write_text

    old = os.umask(0o022)
    try:
        p = atomic_write_text(tmp_path / "a.yaml", "x")
        assert stat.S_IMODE(p.stat().st_mode) == 0o644
        os.chmod(p, 0o640)
        atomic_write_text(p, "y")
        assert stat.S_IMODE(p.stat().st_mode) == 0o640 and p.read_text() == "y"
    finally:
        os.umask(old)
