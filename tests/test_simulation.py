"""The simulator: frames, noise models, tracking error, IMU, and every catalogued effect leaves the
signature it should (each test compares against the same seed without the effect)."""

from __future__ import annotations

import numpy as np
import pytest

from graphcal.clouds.planes import fit_ground_plane
from graphcal.errors import GraphcalError
from graphcal.geometry import (
    invert_pose,
    pose_from_xyz_quat_wxyz,
    rotation_angle_between,
    transform_points,
)
from graphcal.models.effects import CAUSES
from graphcal.models.sensors import DepthCamera, LaserScanner, StereoCamera
from graphcal.simulation.effects import Effects, ExtrinsicChange, draw_effect
from graphcal.simulation.programs import CHAI2015_TABLE_A1, station_program
from graphcal.simulation.session import GRAVITY_M_S2, SimulationConfig, leg_link_joints, simulate
from graphcal.simulation.terrain import LABEL_GROUND

FAST = dict(cloud_stride=8)


def _truth_extrinsic(result, sensor, after_change=False):
    key = "T_body_sensor_after_change" if after_change else "T_body_sensor"
    t = result.truth["sensors"][sensor][key]
    return pose_from_xyz_quat_wxyz(t["xyz"], t["quaternion_wxyz"])


@pytest.fixture(scope="module")
def octopus():
    return simulate(SimulationConfig(robot="octopus", program="chai2015", seed=3, **FAST))


def test_chai_program_is_table_a1():
    cmds = station_program("chai2015", default_height_m=0.6825)
    assert len(cmds) == 52 == len(CHAI2015_TABLE_A1)
    heights = np.array([c.T_stance_body[2, 3] for c in cmds])
    assert heights.min() == pytest.approx(0.615) and heights.max() == pytest.approx(0.750)
    # pose 1: gamma' = 20 deg about X_G is our roll; beta' = 2 deg about Z_G is our pitch, sign flipped
    R = cmds[0].T_stance_body[:3, :3]
    assert np.degrees(np.arctan2(R[2, 1], R[2, 2])) == pytest.approx(20.0)
    assert np.degrees(np.arcsin(-R[2, 0])) == pytest.approx(-2.0)


def test_depth_noise_matches_kinect_model_within_10_percent(octopus):
    """World z of ground points / predicted sigma along world z has unit spread: checks the frames
    (true pose and extrinsic) and the noise model sigma_z = 1.425e-3 z^2 at once."""
    cam = DepthCamera()
    T_body_sensor = _truth_extrinsic(octopus, "depth")
    ratios = []
    for rec in octopus.stations:
        pts = octopus.clouds[("depth", rec.station)]
        ground = octopus.cloud_labels[("depth", rec.station)] == LABEL_GROUND
        T_world_sensor = rec.T_world_body_real @ T_body_sensor
        p = pts[ground]
        z_world = transform_points(T_world_sensor, p)[:, 2]
        dirs = p / np.linalg.norm(p, axis=1, keepdims=True)
        # a depth error e_z moves the point along its ray by e_z / dir_z
        dir_world_z = (dirs @ T_world_sensor[:3, :3].T)[:, 2]
        sigma = cam.sigma_along_axis(p[:, 2]) * np.abs(dir_world_z) / dirs[:, 2]
        ratios.append(z_world / sigma)
    spread = np.std(np.concatenate(ratios))
    assert spread == pytest.approx(1.0, rel=0.10)


def test_laser_and_stereo_noise_models():
    res = simulate(SimulationConfig(robot="messor", program="labecki2012", seed=1, **FAST))
    for sensor, model in (("laser", LaserScanner()), ("stereo", StereoCamera())):
        T_bs = _truth_extrinsic(res, sensor)
        ratios = []
        for rec in res.stations:
            pts = res.clouds[(sensor, rec.station)]
            p = pts[res.cloud_labels[(sensor, rec.station)] == LABEL_GROUND]
            T_ws = rec.T_world_body_real @ T_bs
            z_world = transform_points(T_ws, p)[:, 2]
            r = np.linalg.norm(p, axis=1)
            dirs = p / r[:, None]
            dz = np.abs((dirs @ T_ws[:3, :3].T)[:, 2])
            if sensor == "laser":
                sigma = model.sigma_m * dz
            else:
                sigma = model.sigma_along_axis(p[:, 2]) * dz / dirs[:, 2]
            ratios.append(z_world / sigma)
        assert np.std(np.concatenate(ratios)) == pytest.approx(1.0, rel=0.10), sensor


def test_real_pose_differs_from_commanded_like_a_real_robot(octopus):
    d_pos, d_ang = [], []
    for rec in octopus.stations:
        D = invert_pose(rec.T_world_body_cmd) @ rec.T_world_body_real
        d_pos.append(np.linalg.norm(D[:3, 3]))
        d_ang.append(np.degrees(rotation_angle_between(np.eye(3), D[:3, :3])))
    # servo tracking error of 0.2 deg per joint: millimetres and tenths of a degree, never zero
    assert 0.3e-3 < np.mean(d_pos) < 5e-3
    assert 0.02 < np.mean(d_ang) < 0.5
    # the stored truth is the real pose
    T = octopus.truth["stations"][1]["T_world_body"]
    assert np.allclose(pose_from_xyz_quat_wxyz(T["xyz"], T["quaternion_wxyz"]), octopus.stations[0].T_world_body_real)


def test_imu_measures_gravity_in_the_real_body_frame(octopus):
    for rec in octopus.stations:
        g_body = rec.T_world_body_real[:3, :3].T @ np.array([0, 0, GRAVITY_M_S2])
        # bias (0.02 m/s^2 per axis) + noise: far below what a wrong frame would give (> 1 m/s^2)
        assert np.linalg.norm(rec.imu_accel - g_body) < 0.15


def test_same_seed_same_data_other_seed_other_data():
    a = simulate(SimulationConfig(robot="octopus", program="labecki2012", seed=5, **FAST))
    b = simulate(SimulationConfig(robot="octopus", program="labecki2012", seed=5, **FAST))
    c = simulate(SimulationConfig(robot="octopus", program="labecki2012", seed=6, **FAST))
    assert np.array_equal(a.clouds[("depth", 3)], b.clouds[("depth", 3)])
    assert a.stations[2].q_measured == b.stations[2].q_measured
    assert not np.allclose(_truth_extrinsic(a, "depth"), _truth_extrinsic(c, "depth"))


def test_leg_errors_move_the_real_pose():
    clean = simulate(SimulationConfig(robot="octopus", program="labecki2012", seed=2, **FAST))
    legs = simulate(SimulationConfig(robot="octopus", program="labecki2012", seed=2,
                                     effects=Effects(link_length={"rm_foot_joint": 0.02}), **FAST))
    dz = [b.T_world_body_real[2, 3] - a.T_world_body_real[2, 3] for a, b in zip(clean.stations, legs.stations)]
    # one tibia 20 mm longer, six feet planted: the body rises and tilts by a fraction of that
    assert 2e-3 < np.mean(dz) < 20e-3


def _ground_d(result, sensor="depth"):
    return np.array([fit_ground_plane(result.clouds[(sensor, r.station)], rng=0).d for r in result.stations])


def test_effect_sensor_range_scale():
    base = simulate(SimulationConfig(robot="octopus", program="labecki2012", seed=4, **FAST))
    scaled = simulate(SimulationConfig(robot="octopus", program="labecki2012", seed=4,
                                       effects=Effects(sensor_range_scale={"depth": 1.03}), **FAST))
    ratio = _ground_d(scaled) / _ground_d(base)
    assert np.median(ratio) == pytest.approx(1.03, abs=0.002)


def test_effect_session_offset_sinks_the_body():
    base = simulate(SimulationConfig(robot="octopus", program="random", n_stations=12, n_sessions=2, seed=4, **FAST))
    sunk = simulate(SimulationConfig(robot="octopus", program="random", n_stations=12, n_sessions=2, seed=4,
                                     effects=Effects(session_offset={"s2": 0.025}), **FAST))
    for a, b in zip(base.stations, sunk.stations):
        expected = -0.025 if a.session == "s2" else 0.0
        assert b.T_world_body_real[2, 3] - a.T_world_body_real[2, 3] == pytest.approx(expected, abs=1e-3)


def test_effect_ground_tilt_tilts_the_real_body():
    tilt = np.radians(2.0)
    res = simulate(SimulationConfig(robot="octopus", program="labecki2012", seed=4,
                                    effects=Effects(ground_tilt=(tilt, 0.7)), **FAST))
    angles = [rotation_angle_between(r.T_world_body_cmd[:3, :3], r.T_world_body_real[:3, :3]) for r in res.stations]
    assert np.mean(angles) == pytest.approx(tilt, abs=np.radians(0.25))
    assert res.truth["effects"]["ground_tilt"]["tilt_rad"] == pytest.approx(tilt)


def test_effect_imu_misalignment():
    ang = np.radians(2.5)
    res = simulate(SimulationConfig(robot="octopus", program="labecki2012", seed=4,
                                    effects=Effects(imu_misalignment=(ang, 1.0)), **FAST))
    errs = []
    for r in res.stations:
        g_body = r.T_world_body_real[:3, :3].T @ np.array([0, 0, 1.0])
        a = r.imu_accel / np.linalg.norm(r.imu_accel)
        errs.append(np.arccos(np.clip(a @ g_body, -1, 1)))
    # a horizontal-axis misalignment turns gravity by ~the angle while the body is near level
    assert np.mean(errs) == pytest.approx(ang, abs=np.radians(0.4))


def test_effect_joint_offset_changes_where_the_body_ends_up():
    base = simulate(SimulationConfig(robot="octopus", program="labecki2012", seed=4, **FAST))
    off = simulate(SimulationConfig(robot="octopus", program="labecki2012", seed=4,
                                    effects=Effects(joint_offset={"lf_femur_joint": np.radians(3.0)}), **FAST))
    d = [np.linalg.norm(b.T_world_body_real[:3, 3] - a.T_world_body_real[:3, 3]) for a, b in zip(base.stations, off.stations)]
    assert np.mean(d) > 3e-3
    assert off.truth["legs"]["joint_offsets_rad"]["lf_femur_joint"] == pytest.approx(np.radians(3.0))


def test_effect_extrinsic_change_from_its_station_on():
    change = ExtrinsicChange("depth", station=20, angle_rad=np.radians(2.0), axis=(0.0, 1.0, 0.0))
    res = simulate(SimulationConfig(robot="octopus", program="chai2015", seed=4,
                                    effects=Effects(extrinsic_change=change), **FAST))
    before, after = _truth_extrinsic(res, "depth"), _truth_extrinsic(res, "depth", after_change=True)
    assert np.degrees(rotation_angle_between(before[:3, :3], after[:3, :3])) == pytest.approx(2.0, abs=1e-6)
    for r in res.stations:
        pts = res.clouds[("depth", r.station)]
        T_right = before if r.station < 20 else after
        T_wrong = after if r.station < 20 else before

        def rms(T):
            return np.sqrt(np.mean(transform_points(r.T_world_body_real @ T, pts)[:, 2] ** 2))

        assert rms(T_right) < rms(T_wrong)


def test_effect_outlier_stations_carry_another_stations_data():
    res = simulate(SimulationConfig(robot="octopus", program="chai2015", seed=4,
                                    effects=Effects(outlier_stations=(5, 30, 44)), **FAST))
    swapped = res.truth["outliers"]
    assert sorted(swapped) == [5, 30, 44]
    for st, src in swapped.items():
        assert src != st
        assert np.array_equal(res.clouds[("depth", st)], res.clouds[("depth", src)])


@pytest.mark.parametrize("cause", CAUSES)
def test_draw_effect_is_within_the_catalogue_magnitudes(cause):
    from graphcal.models.robot import load_robot

    robot = load_robot(model="octopus")
    leg_joints = {f: robot.leg(f).joint_names for f in robot.feet}
    eff, where = draw_effect(cause, np.random.default_rng(11), sensors=("depth",), sessions=("s1", "s2"),
                             stations=tuple(range(1, 53)), leg_joints=leg_joints,
                             link_joints=leg_link_joints(robot))
    assert eff.active() == (cause,)
    d = eff.to_dict()[cause]
    if cause == "sensor_range_scale":
        assert 0.01 <= abs(d["depth"]["scale"] - 1) <= 0.03
    elif cause == "link_length":
        assert where["joint"] in leg_link_joints(robot)[where["leg"]]
        assert 0.010 <= abs(d[where["joint"]]["delta_m"]) <= 0.025
    elif cause == "joint_offset":
        assert np.radians(1.5) <= abs(d[where["joint"]]["offset_rad"]) <= np.radians(4.0)
    elif cause == "outlier_stations":
        assert len(where["stations"]) == 3


@pytest.mark.parametrize(
    "kwargs, words",
    [
        (dict(robot="hexapod9000"), "hexapod9000"),
        (dict(program="zigzag"), "zigzag"),
        (dict(ground="lava"), "lava"),
        (dict(sensors=("lidar",)), "lidar"),
        (dict(effects=Effects(session_offset={"s7": 0.02})), "s7"),
        (dict(effects=Effects(sensor_range_scale={"laser": 1.02})), "laser"),
    ],
)
def test_bad_simulation_requests_are_named(kwargs, words):
    with pytest.raises(GraphcalError, match=words):
        simulate(SimulationConfig(**{**dict(robot="octopus", program="chai2015", **FAST), **kwargs}))


def test_a_users_own_hexapod_urdf_is_simulated_and_written_in_the_contract(tmp_path):
    from graphcal.io.dataset import read_dataset, validate_dataset
    from graphcal.simulation.write import write_simulation
    from graphcal.testing import HEXAPOD_T_BODY_IMU, custom_hexapod

    config = SimulationConfig(robot="sidewinder", program="random", n_stations=10, n_sessions=3, seed=8,
                              custom_robot=custom_hexapod(),
                              tilt_scale=0.6, **FAST)
    res = simulate(config)
    # the IMU is mounted turned by 90 deg: gravity must appear in the IMU frame, not the body's
    R_body_imu = HEXAPOD_T_BODY_IMU[:3, :3]
    for r in res.stations:
        g_imu = (r.T_world_body_real[:3, :3] @ R_body_imu).T @ np.array([0, 0, GRAVITY_M_S2])
        assert np.linalg.norm(r.imu_accel - g_imu) < 0.15
    out = tmp_path / "sidewinder"
    write_simulation(res, out)
    ds = read_dataset(out)
    assert ds.robot.urdf == "robot.urdf" and ds.robot.model is None
    assert "q_front_left_knee" in ds.stations.columns
    assert len(set(ds.stations["session"].tolist())) == 3
    assert validate_dataset(out).n_clouds == 10


def test_a_station_where_the_camera_saw_nothing_has_no_cloud_file(tmp_path):
    """The custom hexapod's camera sits 0.42 m above the floor, pitched 32 deg down; with the body
    pitched down 11.6 deg (seed 604, station 23) every floor point is closer than the Kinect's 0.8 m
    minimum range: an empty cloud. Before: write_simulation refused the whole dataset ("points:
    expected a non-empty (N, 3) array", 2 of the first 8 seeds of bench/calibration_nees.py
    --scenario unseen). Now the station has no cloud file, as a real recording would have none."""
    import yaml

    from graphcal.calibration.calibrate import calibrate
    from graphcal.io.dataset import read_dataset
    from graphcal.simulation.write import write_simulation
    from graphcal.testing import custom_hexapod

    res = simulate(SimulationConfig(robot="sidewinder", program="random", n_stations=45, n_sessions=3, seed=604,
                                    tilt_scale=0.8, cloud_stride=8,
                                    custom_robot=custom_hexapod()))
    empty = sorted(k for k, v in res.clouds.items() if len(v) == 0)
    assert empty == [("front_cam", 23)]
    out = tmp_path / "ds"
    write_simulation(res, out, output="both")
    assert not (out / "clouds" / "front_cam" / "23.ply").exists()
    assert (out / "clouds" / "front_cam" / "22.ply").exists() and (out / "clouds" / "front_cam" / "24.ply").exists()
    assert yaml.safe_load((out / "truth.yaml").read_text())["config"]["empty_clouds"] == [["front_cam", 23]]
    ds = read_dataset(out)
    assert 23 not in set(ds.planes["station"].tolist()) and len(ds.planes["station"]) == 44
    assert 23 in set(ds.stations["station"].tolist())  # the station itself stays: its joints, IMU
    result = calibrate(out)
    assert ("front_cam" not in {r.sensor for r in result.residuals if r.station == 23})
    assert len([r for r in result.residuals if r.sensor == "front_cam"]) == 44


def test_output_planes_keeps_the_laser_scans(tmp_path):
    """A laser scanner's data are its scan points (a 2D scan has no plane): with --output planes they
    are still written as clouds. Before, `simulate --sensor laser --output planes` wrote a dataset
    with no sensor data ("0 clouds, 0 planes", exit 0) and calibrate found nothing to calibrate."""
    from graphcal.commands.simulate import run as simulate_to_folder

    out = tmp_path / "ds"
    result = simulate_to_folder(robot="messor", program="labecki2012", ground="level", out_dir=out, output="planes",
                                cloud_stride=8, progress=False)
    assert (result.n_clouds, result.n_planes) == (44, 44) and set(result.sensors) == {"stereo", "laser"}
    assert result.out == out and out / "truth.yaml" in result.files and out / "planes.csv" in result.files
    assert "44 clouds, 44 planes" in result.summary_text()  # the console's words
    assert len(list((out / "clouds" / "laser").glob("*.ply"))) == 44
    assert not (out / "clouds" / "stereo").exists()
    assert set(np.unique(np.loadtxt(out / "planes.csv", delimiter=",", skiprows=1, usecols=1, dtype=str))) == {"stereo"}


@pytest.mark.parametrize("robot, seed", [("octopus", 1), ("qingzhui", 2), ("qingzhui", 3)])
def test_random_stations_stay_within_the_joint_limits(tmp_path, robot, seed):
    """The random program's stations are poses the robot can take: every written joint angle lies
    within the URDF's limits, so calibrate does not warn about the simulator's own data. Before:
    octopus seed 1 wrote q_rf_coxa 6.087 rad (an IK that walked a full turn) and a flipped right
    front knee on 21 of 60 stations; qingzhui seeds 2 and 3 hip angles up to 0.694 rad against
    limits of +-0.6 (poses out of reach)."""
    from graphcal.io.dataset import validate_dataset
    from graphcal.simulation.write import write_simulation

    res = simulate(SimulationConfig(robot=robot, program="random", n_stations=60, seed=seed, cloud_stride=16))
    write_simulation(res, tmp_path / "ds", output="planes")
    report = validate_dataset(tmp_path / "ds")
    assert report.n_stations == 60
    assert not [w for w in report.warnings if "outside the URDF limits" in w], report.warnings


def test_wrap_revolute_turns_by_whole_turns_towards_the_middle_of_the_limits():
    from graphcal.models.robot import load_robot
    from graphcal.simulation.session import wrap_revolute

    leg = load_robot(model="octopus").leg("rf_foot")
    q = np.array([6.087, -0.3, 2.0 - 4 * np.pi])
    w = wrap_revolute(leg, q)
    np.testing.assert_allclose(w, [6.087 - 2 * np.pi, -0.3, 2.0], atol=1e-12)
    assert not leg.outside_limits(w).any()
