"""``calibrate --noise-from``: the noise model of an earlier calibration.yaml, used as given.

The behavioural test hides a robot whose joints flex by 0.3 deg (three times the default joint
sigma) and checks that an incremental run on a second session, given the noise a batch run learned
on the first, reports the sigma the batch run learns on that second session (the defaults give a
rotation sigma ~10x too large there), and that the error stays covered."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
import yaml

from graphcal.calibration.graph import CalibrationOptions
from graphcal.calibration.noise_file import NOISE_KEYS, options_with_noise_from
from graphcal.commands.calibrate import run as run_calibrate
from graphcal.errors import DatasetError
from graphcal.geometry import invert_pose, pose_from_xyz_quat_wxyz, to_gtsam_pose
from graphcal.io.calibration_yaml import read_calibration_yaml
from graphcal.simulation.session import SimulationConfig, simulate
from graphcal.simulation.write import write_simulation

NOISE = {"sigma_joint_rad": 0.005, "sigma_contact_m": 0.0011, "sigma_ground_m": 0.0003, "sigma_imu_rad": 0.0006,
         "sigma_commanded_rad": 0.0009, "sigma_commanded_m": 0.0005, "plane_scale:depth": 0.8}


def _calibration_yaml(tmp_path, noise) -> str:
    """A minimal valid calibration.yaml with ``noise`` as its noise_model (None: no block)."""
    doc = {
        "format": "graphcal-calibration/1",
        "sensors": {"depth": {
            "T_body_sensor": {"xyz": [0.1, 0.0, 0.2], "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 0.0]},
            "covariance": np.diag([1e-8] * 3 + [1e-8] * 3).tolist(),
            "sigma": {"rot_deg": [0.01] * 3, "xyz_mm": [0.1] * 3},
            "unobservable": [],
        }},
        "outliers": [],
        "residuals": {"normal_rms_deg": 0.01, "distance_rms_mm": 0.3},
    }
    if noise is not None:
        doc["noise_model"] = noise
    p = tmp_path / "calibration.yaml"
    p.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return p


def test_the_noise_model_becomes_the_options_and_nothing_else_changes(tmp_path):
    path = _calibration_yaml(tmp_path, NOISE)
    start = CalibrationOptions(legs=True, ground_unevenness_m=0.001, sigma_scan_m=0.02)
    options, scaled = options_with_noise_from(path, start)
    for key in NOISE_KEYS:
        assert getattr(options, key) == NOISE[key]
    assert options.plane_scale("depth") == 0.8 and options.plane_scale("laser") == 1.0
    assert scaled == ("depth",)
    assert options.estimate_noise is False
    assert (options.legs, options.ground_unevenness_m, options.sigma_scan_m) == (True, 0.001, 0.02)


@pytest.mark.parametrize(
    "edit, where, words",
    [
        (lambda n: None, "noise_model", "missing"),
        (lambda n: {k: v for k, v in n.items() if k != "sigma_imu_rad"}, "noise_model.sigma_imu_rad", "required"),
        (lambda n: {**n, "sigma_ground_m": 0.0}, "noise_model.sigma_ground_m", ">= 1e-12"),
        # its information overflowed the solver: "the factor graph does not determine F5", no file named
        (lambda n: {**n, "sigma_ground_m": 1e-300}, "noise_model.sigma_ground_m", ">= 1e-12"),
        (lambda n: {**n, "sigma_joint_rad": float("nan")}, "noise_model.sigma_joint_rad", ">= 1e-12"),
        (lambda n: {**n, "sigma_contact_m": True}, "noise_model.sigma_contact_m", ">= 1e-12"),
        (lambda n: {**n, "plane_scale:depth": "big"}, "noise_model.plane_scale:depth", ">= 1e-12"),
        (lambda n: {**n, "sigma_joints_rad": 0.001}, "noise_model.sigma_joints_rad", "unknown key"),
        (lambda n: [1, 2], "noise_model", "a mapping"),
    ],
)
def test_a_bad_noise_model_names_the_file_and_the_key(tmp_path, edit, where, words):
    noise = edit(dict(NOISE))
    path = _calibration_yaml(tmp_path, noise)
    with pytest.raises(DatasetError) as exc:
        options_with_noise_from(path, CalibrationOptions())
    assert exc.value.file == str(path) and exc.value.where == where
    assert words in str(exc.value)


def test_a_missing_or_empty_file_is_a_clear_error(tmp_path):
    with pytest.raises(DatasetError, match="readable calibration.yaml"):
        options_with_noise_from(tmp_path / "nope.yaml", CalibrationOptions())
    (tmp_path / "empty.yaml").write_text("")
    with pytest.raises(DatasetError, match=r"empty\.yaml: top level: expected a calibration.yaml mapping, got an empty file"):
        options_with_noise_from(tmp_path / "empty.yaml", CalibrationOptions())


def _session(tmp_path, seed: int):
    sim = simulate(SimulationConfig(robot="octopus", program="chai2015", seed=seed, cloud_stride=16, extrinsic_seed=7,
                                    joint_flex_sigma_rad=np.radians(0.3)))  # a numpy float: truth.yaml must take it
    out = tmp_path / f"session{seed}"
    write_simulation(sim, out, output="planes")
    return out, sim


def _sigma_and_error(out_dir, sim):
    doc = read_calibration_yaml(out_dir / "calibration.yaml")
    s = doc["sensors"]["depth"]
    T_hat = pose_from_xyz_quat_wxyz(s["T_body_sensor"]["xyz"], s["T_body_sensor"]["quaternion_wxyz"])
    t = sim.truth["sensors"]["depth"]["T_body_sensor"]
    T_true = pose_from_xyz_quat_wxyz(t["xyz"], t["quaternion_wxyz"])
    xi = np.asarray(gtsam.Pose3.Logmap(to_gtsam_pose(invert_pose(T_hat) @ T_true)))
    sigma_body = np.r_[s["sigma"]["rot_deg"], s["sigma"]["xyz_mm"]]  # about / along the body axes
    return doc, np.array(s["covariance"]), sigma_body, xi


@pytest.mark.slow
def test_incremental_with_the_noise_a_batch_run_learned_reports_the_batch_sigma(tmp_path):
    session_a, _ = _session(tmp_path, 3)
    session_b, sim_b = _session(tmp_path, 103)
    run_calibrate(session_a, tmp_path / "a", progress=False)  # batch: learns the noise
    run_calibrate(session_b, tmp_path / "b_batch", progress=False)
    result = run_calibrate(session_b, tmp_path / "b_online", incremental=True, progress=False,
                           noise_from=tmp_path / "a" / "calibration.yaml")
    run_calibrate(session_b, tmp_path / "b_default", incremental=True, progress=False)
    assert result.noise_from == str(tmp_path / "a" / "calibration.yaml") and result.incremental
    assert result.calibration.noise_source == result.noise_from and result.calibration.solver == "incremental"
    summary = result.summary_text()  # the console's words
    assert "noise from" in summary and "(not learned)" in summary
    assert read_calibration_yaml(tmp_path / "a" / "calibration.yaml")["robot"] == "octopus"

    learned_a = read_calibration_yaml(tmp_path / "a" / "calibration.yaml")["noise_model"]
    assert learned_a["sigma_joint_rad"] > 2 * CalibrationOptions().sigma_joint_rad  # the flex was learned
    online, cov_online, sigma_online, xi = _sigma_and_error(tmp_path / "b_online", sim_b)
    assert online["noise_model"] == learned_a
    assert online["noise_model_from"] == str(tmp_path / "a" / "calibration.yaml")
    assert {g["status"] for g in online["noise_estimation"].values()} == {"given"}  # checked, not learned
    assert not [w for w in online["warnings"] if "robot" in w]  # the same robot: no mismatch said
    assert "read from <code>" in (tmp_path / "b_online" / "report.html").read_text(encoding="utf-8")
    sigma_batch = _sigma_and_error(tmp_path / "b_batch", sim_b)[2]
    sigma_default = _sigma_and_error(tmp_path / "b_default", sim_b)[2]
    # the sigma of the batch run that learned session B's own noise, within 25 % per axis ...
    np.testing.assert_allclose(sigma_online, sigma_batch, rtol=0.25)
    # ... where the defaults are far off (about the body's x and y ~10x)
    assert np.all(sigma_default[:2] > 4 * sigma_batch[:2])
    # and the error is covered
    assert float(xi @ np.linalg.solve(cov_online, xi)) < 16.8  # chi2(6) 99 %
    assert not online["sensors"]["depth"].get("change_stations")
    assert math.isfinite(online["residuals"]["distance_rms_mm"])


def test_a_noise_model_of_another_robot_or_sensor_is_named(tmp_path):
    """The file records the robot it calibrated; another robot's noise model, a file that records
    none, and a plane scale of a sensor the dataset lacks are each one warning; a match is none."""
    from graphcal.calibration.noise_file import noise_from_mismatch

    path = _calibration_yaml(tmp_path, NOISE)
    doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    notes = noise_from_mismatch(path, "octopus", ["depth"])
    assert len(notes) == 1 and "records no robot" in notes[0]
    path.write_text(yaml.safe_dump({**doc, "robot": "octopus"}, sort_keys=False), encoding="utf-8")
    assert noise_from_mismatch(path, "octopus", ["depth", "laser"]) == ()
    notes = noise_from_mismatch(path, "messor", ["depth"])
    assert len(notes) == 1 and "'octopus'" in notes[0] and "'messor'" in notes[0]
    notes = noise_from_mismatch(path, "octopus", ["laser"])
    assert len(notes) == 1 and "plane_scale:depth" in notes[0] and "no sensor 'depth'" in notes[0]
    path.write_text(yaml.safe_dump({**doc, "robot": ["octopus"]}, sort_keys=False), encoding="utf-8")
    with pytest.raises(DatasetError) as exc:
        noise_from_mismatch(path, "octopus", ["depth"])
    assert exc.value.where == "robot"
