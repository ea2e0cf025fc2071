"""Batch calibration on simulated datasets it has never seen: accuracy against the hidden truth,
the reported sigma covering the error, convergence from bad priors, outliers, and directions the
data cannot determine."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from graphcal.calibration.calibrate import _passing_again, calibrate, solve_problem
from graphcal.calibration.graph import CalibrationOptions, build_problem
from graphcal.calibration.measurements import calibration_data
from graphcal.geometry import rotation_angle_between, se3_exp
from graphcal.io.dataset import load_dataset_robot, read_dataset
from graphcal.simulation.effects import Effects
from graphcal.testing import custom_hexapod, extrinsic_error_scores, simulated_dataset, true_extrinsic


@pytest.fixture(scope="module")
def octopus(tmp_path_factory):
    path, truth = simulated_dataset(tmp_path_factory.mktemp("oct"), "octopus", robot="octopus", program="chai2015", seed=21)
    return path, truth, calibrate(path)


def test_octopus_chai_program_recovers_the_extrinsic(octopus):
    path, truth, result = octopus
    est = result.sensors["depth"]
    ang, dist, z = extrinsic_error_scores(est, true_extrinsic(truth, "depth"))
    # CAD is off by ~1 deg / 10 mm (simulator default); the calibration gets within hundredths
    assert ang < 0.02 and dist < 1.0
    assert np.all(np.abs(z) < 4.0), z  # the reported sigma covers the error on every body axis
    assert est.unobservable == ()
    before = np.sqrt(np.mean([r.angle_before_deg**2 for r in result.residuals]))
    assert result.normal_rms_deg < 0.2 * before
    assert result.outliers == ()


def test_converges_from_any_cad_prior(octopus):
    """Łabęcki's LM failed from sigma_d = 0.2 m, sigma_a = 50 deg; the closed-form start does not care."""
    path, truth, reference = octopus
    ds = read_dataset(path)
    rng = np.random.default_rng(5)
    T_ref = reference.sensors["depth"].T_body_sensor
    spec = ds.sensors["depth"]
    starts = [se3_exp(np.r_[rng.normal(0, np.radians(50), 3), rng.normal(0, 0.2, 3)]) for _ in range(4)]
    starts.append(se3_exp(np.r_[0.0, 0.0, np.pi, 0.0, 0.0, 0.0]))  # 180 deg about the sensor's z
    yaw180 = np.eye(4)
    yaw180[:3, :3] = np.diag([-1.0, -1.0, 1.0])  # 180 deg yaw about the body's z
    for k, D in enumerate(starts + [None]):
        T_bad = yaw180 @ spec.T_body_sensor_prior.matrix if D is None else spec.T_body_sensor_prior.matrix @ D
        prior = dataclasses.replace(spec.T_body_sensor_prior).from_matrix(
            T_bad, spec.T_body_sensor_prior.sigma_m, spec.T_body_sensor_prior.sigma_rad)
        ds_bad = dataclasses.replace(ds, sensors={"depth": dataclasses.replace(spec, T_body_sensor_prior=prior)})
        res = calibrate(ds_bad)
        T = res.sensors["depth"].T_body_sensor
        assert np.degrees(rotation_angle_between(T[:3, :3], T_ref[:3, :3])) < 1e-3, k
        assert 1e3 * np.linalg.norm(T[:3, 3] - T_ref[:3, 3]) < 0.05, k
        # a prior this far off its own stated sigma is reported as wrong, naming the sensor
        assert any(w.startswith("depth: the CAD prior in dataset.yaml is") for w in res.warnings), (k, res.warnings)
    # the dataset's own prior (about 1 deg / 10 mm off, sigma as stated) is not
    assert not any("CAD prior" in w for w in reference.warnings), reference.warnings


def test_fixed_legs_use_the_builtin_stance_factor_and_agree_with_the_python_one(octopus, monkeypatch):
    """With the legs held fixed the stance feet are GTSAM's C++ bearing-range factors (the Python
    factor with --legs); the whole calibration, noise learned, equals the one with the Python factor
    everywhere to a small share of the reported sigma (the two agree to first order)."""
    import graphcal.factors.stance_foot_builtin as sfb
    from graphcal.calibration.graph import CalibrationOptions, build_problem
    from graphcal.calibration.measurements import calibration_data
    from graphcal.io.dataset import load_dataset_robot

    path, truth, builtin = octopus
    ds = read_dataset(path)
    robot = load_dataset_robot(ds)
    data = calibration_data(ds, robot)

    def stance_types(options):
        pb = build_problem(ds, robot, data, options)
        return {type(pb.graph.at(i)).__name__ for i, g in pb.factor_groups.items() if g == "stance_foot"}

    assert stance_types(CalibrationOptions()) == {"BearingRangeFactor3D"}
    assert stance_types(CalibrationOptions(legs=True)) == {"CustomFactor"}
    monkeypatch.setattr(sfb, "MIN_RANGE_M", 1e9)  # every foot "too close": the Python factor throughout
    assert stance_types(CalibrationOptions()) == {"CustomFactor"}
    python = calibrate(ds, data=data)
    a, b = builtin.sensors["depth"], python.sensors["depth"]
    D = a.T_body_sensor[:3, :3] @ b.T_body_sensor[:3, :3].T
    dphi = np.degrees(0.5 * np.array([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]]))
    dt = 1e3 * (a.T_body_sensor[:3, 3] - b.T_body_sensor[:3, 3])
    assert np.all(np.abs(dphi) < 0.01 * b.sigma_rot_deg), (dphi, b.sigma_rot_deg)
    assert np.all(np.abs(dt) < 0.01 * b.sigma_xyz_mm), (dt, b.sigma_xyz_mm)
    np.testing.assert_allclose(a.sigma_rot_deg, b.sigma_rot_deg, rtol=0.01)
    np.testing.assert_allclose(a.sigma_xyz_mm, b.sigma_xyz_mm, rtol=0.01)
    for name, value in python.noise.items():  # the learned noise model
        assert builtin.noise[name] == pytest.approx(value, rel=0.01), name


def test_outlier_stations_are_found_and_do_not_hurt(tmp_path):
    path, truth = simulated_dataset(tmp_path, "outliers", robot="octopus", program="chai2015", seed=22,
                                    effects=Effects(outlier_stations=(5, 30, 44)))
    result = calibrate(path)
    assert set(result.outliers) == {5, 30, 44}
    assert not any("plane_max_points" in w for w in result.warnings)
    # planes.csv given: a cap on the cloud points cannot apply, and the result says so
    assert any("--plane-points 5000 (plane_max_points) had no effect" in w
               for w in calibrate(path, plane_max_points=5000).warnings)
    ang, dist, _ = extrinsic_error_scores(result.sensors["depth"], true_extrinsic(truth, "depth"))
    assert ang < 0.03 and dist < 1.5


def test_outliers_are_left_out_before_the_noise_is_learned(tmp_path):
    # qingzhui, planes only: learned with the two outliers in, the noise absorbed them (contact
    # 11 mm, joints 0.27 deg; no outlier found, the extrinsic 0.4-1.4 deg and 20-36 mm off). Screened
    # at the default noise first, they are found and the learned noise is the simulator's.
    path, truth = simulated_dataset(tmp_path, "outliers_q", robot="qingzhui", program="random", seed=201,
                                    n_stations=48, n_sessions=3, session_heading_step_deg=40.0,
                                    effects=Effects(outlier_stations=(4, 29)))
    result = calibrate(path)
    replaced = set(truth["outliers"])  # the stations whose clouds are another station's
    assert {4, 29} <= replaced and set(result.outliers) == replaced
    noise = {g.group: g for g in result.noise_groups}
    assert dict(noise["stance_foot/contact"].fields)["sigma_contact_m"] < 0.5e-3
    ang, dist, z = extrinsic_error_scores(result.sensors["depth"], true_extrinsic(truth, "depth"))
    assert ang < 0.03 and dist < 1.0 and np.all(np.abs(z) < 4.0)

    # the re-test of what the screen left out: a good station left out with the two outliers is
    # put back, the outliers are not
    ds = read_dataset(path)
    robot = load_dataset_robot(ds)
    data = calibration_data(ds, robot)
    excluded = frozenset({(4, "depth"), (29, "depth"), (10, "depth")})
    problem = build_problem(ds, robot, data, CalibrationOptions(), exclude=excluded)
    values = solve_problem(problem).values
    assert _passing_again(ds, robot, data, CalibrationOptions(), problem, values, excluded) == {(10, "depth")}


def test_unseen_hexapod_three_sessions_from_clouds(tmp_path):
    """The issue's acceptance case: a hexapod URDF graphcal never saw, clouds (planes fitted by
    calibrate itself), IMU, three sessions: within 0.1 deg and 2 mm, sigma covering the error."""
    path, truth = simulated_dataset(
        tmp_path, "sidewinder", output="clouds", robot="sidewinder", program="random", n_stations=45,
        n_sessions=3, seed=23, tilt_scale=0.8,
        custom_robot=custom_hexapod())
    assert not (path / "planes.csv").exists()
    result = calibrate(path)
    ang, dist, z = extrinsic_error_scores(result.sensors["front_cam"], true_extrinsic(truth, "front_cam"))
    assert ang < 0.1 and dist < 2.0
    assert np.all(np.abs(z) < 4.0), z
    # the clouds thinned to every k-th point: the planes are fitted on fewer points (the sigma
    # grows), the extrinsic still within the goal and covered
    thin = calibrate(path, plane_max_points=1000)  # its clouds have 1.7k-3.3k points
    ang, dist, z = extrinsic_error_scores(thin.sensors["front_cam"], true_extrinsic(truth, "front_cam"))
    assert ang < 0.1 and dist < 2.0
    assert np.all(np.abs(z) < 4.0), z
    assert not thin.warnings
    assert np.all(np.diag(thin.sensors["front_cam"].covariance) > np.diag(result.sensors["front_cam"].covariance))


@pytest.mark.slow
def test_laser_scanner_and_stereo_camera_in_one_graph(tmp_path):
    """Łabęcki's Messor: a 2D laser scanner (dense point-to-plane) and a stereo camera (planes)."""
    path, truth = simulated_dataset(tmp_path, "messor", output="both", robot="messor", program="labecki2012", seed=24)
    result = calibrate(path)
    ang_l, dist_l, z_l = extrinsic_error_scores(result.sensors["laser"], true_extrinsic(truth, "laser"))
    ang_s, dist_s, z_s = extrinsic_error_scores(result.sensors["stereo"], true_extrinsic(truth, "stereo"))
    # the Messor tilts only +-5 deg: yaw about the ground normal is known to ~0.03 deg (1 sigma)
    assert ang_l < 0.1 and dist_l < 2.0
    assert ang_s < 0.1 and dist_s < 1.0
    assert np.all(np.abs(z_l) < 4.0) and np.all(np.abs(z_s) < 4.0), (z_l, z_s)
    assert not [w for w in result.warnings if "scan plane" in w]  # the simulated scans lie in z = 0


def test_a_depth_cloud_declared_laser_scanner_is_the_first_warning(tmp_path):
    """The stereo camera's 3-D clouds declared ``laser_scanner``: calibrate reads them as scan lines,
    and its first warning says why that is wrong, naming a cloud file."""
    path, _ = simulated_dataset(tmp_path, "messor", output="clouds", robot="messor", program="random", n_stations=8,
                                seed=24)
    text = (path / "dataset.yaml").read_text()
    (path / "dataset.yaml").write_text(text.replace("type: stereo_camera", "type: laser_scanner"))
    result = calibrate(path)
    assert result.warnings[0].startswith(
        "sensor 'stereo' is a laser_scanner, but 8 of its 8 clouds do not lie in its scan plane z = 0")
    assert "clouds/stereo/" in result.warnings[0]
    assert not [w for w in result.warnings if "sensor 'laser' is a laser_scanner" in w]


def test_directions_without_data_are_named_not_guessed(tmp_path):
    """No roll or pitch variation: yaw about the ground normal and the horizontal lever arm are not
    determined; the result says so in words instead of reporting a tight sigma."""
    path, truth = simulated_dataset(tmp_path, "flat", robot="octopus", program="random", n_stations=12, seed=25,
                                    tilt_scale=0.0)
    result = calibrate(path)
    est = result.sensors["depth"]
    text = " ".join(est.unobservable)
    assert est.unobservable, "expected undetermined directions"
    assert "roll and pitch" in text or "pitch" in text
    # what IS determined (the height above the ground) stays accurate
    T_true = true_extrinsic(truth, "depth")
    assert abs(est.T_body_sensor[2, 3] - T_true[2, 3]) < 0.002


@pytest.mark.slow
def test_bumpy_ground_roughness_puts_the_bumps_into_sigma(tmp_path):
    """On Chai's little bumpiness (3 mm RMS smooth bumps, one stance) the feet stand on bumps: an
    offset between the feet's plane and the ground the camera sees that one stance cannot tell from
    the extrinsic. With the flat-floor defaults the error is many of its reported sigma (measured:
    up to 14); with the ground's roughness given the sigma covers it."""
    from graphcal.calibration.graph import CalibrationOptions, options_for_ground_roughness

    path, truth = simulated_dataset(tmp_path, "bumpy", robot="octopus", program="chai2015", ground="bumpy-little",
                                    seed=0, cloud_stride=4)
    T_true = true_extrinsic(truth, "depth")
    flat = calibrate(path)
    import dataclasses

    from graphcal.solvers.covariance import body_axis_sigmas

    s = flat.sensors["depth"]
    rot_m, xyz_m, _, _ = body_axis_sigmas(s.T_body_sensor, s.model_covariance)
    _, _, z_flat = extrinsic_error_scores(dataclasses.replace(s, sigma_rot_deg=rot_m, sigma_xyz_mm=xyz_m), T_true)
    assert np.max(np.abs(z_flat)) > 6.0, z_flat  # the model's sigma: overconfident without the roughness
    # ... which the adequacy verdict sees (issue 27): the robust sigma governs and covers the error
    assert flat.adequacy.verdict == "does not fit"
    _, _, z_gov = extrinsic_error_scores(s, T_true)
    assert np.max(np.abs(z_gov)) < 3.0, z_gov  # measured 1.85
    # ... and calibrate says so: the planes scatter more than their point noise predicts
    assert [w for w in flat.warnings if "the planes scatter" in w and "--ground-roughness-mm" in w], flat.warnings
    rough = calibrate(path, options=options_for_ground_roughness(CalibrationOptions(), 0.003))
    assert not [w for w in rough.warnings if "the planes scatter" in w], rough.warnings
    est = rough.sensors["depth"]
    ang, dist, z = extrinsic_error_scores(est, T_true)
    # measured: largest |error| / sigma 1.2 (NEES 1.8); with the roughness terms at a third of the
    # bump height (until the eighteenth stop) 3.57 (NEES 15.8; mean NEES 82 over 12 seeds)
    assert np.all(np.abs(z) < 2.5), z
    assert ang < 0.3 and dist < 6.0  # the estimate itself is as before: the bumps are not removed
    from graphcal.errors import GraphcalError

    with pytest.raises(GraphcalError, match="roughness"):
        options_for_ground_roughness(CalibrationOptions(), -0.001)


def test_an_estimate_far_from_its_wide_prior_points_to_a_frame_mistake():
    """Planes in the body frame fit a sensor at the body origin: an audit's 60 deg / 500 mm prior let
    the estimate sit 137 deg / 395 mm away without a word. Beyond 30 deg or 250 mm the warning names
    the frames, whatever the prior's sigma; a 10 deg / 100 mm mounting error inside it says nothing."""
    from graphcal.calibration.result import prior_conflict
    from graphcal.geometry import matrix_from_rpy

    T_prior = np.eye(4)
    T_prior[:3, :3] = matrix_from_rpy(np.radians([-120.0, 0.0, -90.0]))
    T_prior[:3, 3] = [0.25, 0.0, 0.3]
    wide = (0.5, np.radians(60.0))
    identity = np.eye(4)
    said = prior_conflict(identity, T_prior, *wide)
    assert "seldom a mounting error" in said and "sensor frame" in said and "times its stated sigma" not in said
    near = T_prior.copy()
    near[:3, :3] = T_prior[:3, :3] @ matrix_from_rpy(np.radians([10.0, 0.0, 0.0]))
    near[:3, 3] += [0.1, 0.0, 0.0]
    assert prior_conflict(near, T_prior, *wide) == ""
    far_xyz = T_prior.copy()
    far_xyz[:3, 3] += [0.3, 0.0, 0.0]
    assert "seldom a mounting error" in prior_conflict(far_xyz, T_prior, *wide)
    tight = prior_conflict(identity, T_prior, 0.05, np.radians(5.0))  # both: the conflict and the hint
    assert "times its stated sigma" in tight and "seldom a mounting error" in tight


def test_plane_normals_pointing_away_from_the_sensor_are_named():
    from graphcal.calibration.residuals import StationResidual, flipped_normal_warnings

    def rows(sensor, angles, outlier=False):
        return [StationResidual(i, sensor, 1.0, 5.0, a, 0.3, 2.0, outlier) for i, a in enumerate(angles)]

    flipped = rows("depth", [179.9, 179.95, 0.05, 179.8]) + rows("laser", [0.1, 0.2, 179.0])
    said = flipped_normal_warnings(flipped)
    assert len(said) == 2 and said[0].startswith("depth: 3 of 4 plane normals point away from the sensor")
    assert "station 0, 1, 3)" in said[0]
    # a few rows printed with the wrong sign are named too (issue 32: 5 of 52 left a 56 deg RMS unsaid)
    assert said[1].startswith("laser: 1 of 3 plane normals") and "station 2)" in said[1]
    few = flipped_normal_warnings(rows("depth", [0.1, 179.0, 0.2, 179.0]))
    assert len(few) == 1 and few[0].startswith("depth: 2 of 4") and "station 1, 3)" in few[0]
    assert flipped_normal_warnings(rows("depth", [0.1, 0.2, 89.0])) == []  # none beyond 90 deg
    assert flipped_normal_warnings(rows("depth", [179.0, 179.0], outlier=True) + rows("depth", [0.1])) == []
