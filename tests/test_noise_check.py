"""A given noise model checked against the run's residuals (graphcal/calibration/noise_check.py).

The data hide a plane noise model that understates the planes' scatter (the given plane scale is
0.25 where the fits' own noise is about right): the run must see it in its residuals, say so, and
widen the sensor's covariance by exactly the variance factor it reports; a noise model that
overstates the scatter must leave the covariance alone. ``judge=False``: the noise check's own
covariance, without the adequacy verdict's robust one (tests/test_adequacy.py)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from graphcal.calibration.calibrate import calibrate
from graphcal.calibration.graph import CalibrationOptions
from graphcal.calibration.incremental import calibrate_incremental
from graphcal.commands.calibrate import run as run_calibrate
from graphcal.io.calibration_yaml import read_calibration_yaml
from graphcal.io.dataset import read_dataset
from graphcal.simulation.session import SimulationConfig, simulate
from graphcal.simulation.write import write_simulation


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    sim = simulate(SimulationConfig(robot="octopus", program="chai2015", seed=21, cloud_stride=16, extrinsic_seed=7))
    out = tmp_path_factory.mktemp("noise_check") / "session"
    write_simulation(sim, out, output="planes")
    return read_dataset(out)


def _given(plane_scale: float, scale: bool) -> CalibrationOptions:
    return CalibrationOptions(estimate_noise=False, scale_to_plane_residuals=scale,
                              plane_sigma_scales=(("depth", plane_scale),))


def _plane_group(result):
    return next(g for g in result.noise_groups if g.group == "plane:depth")


def test_understated_plane_noise_widens_the_covariance_by_the_variance_factor(dataset):
    on = calibrate(dataset, options=_given(0.25, True), judge=False)
    off = calibrate(dataset, options=_given(0.25, False), judge=False)
    right = calibrate(dataset, options=_given(1.0, False), judge=False)  # the fits' own noise: what the planes point to
    s_on, s_off = on.sensors["depth"], off.sensors["depth"]
    g = _plane_group(on)
    assert g.status == "given" and g.data_scale > 1.5 and g.p_high < 0.01
    # the factor is the one the planes point to with their own noise model, for a model scaled by 0.25
    # (one update at the solution reads only 1.8^2: the body poses absorb most of understated planes)
    implied = (_plane_group(right).data_scale / 0.25) ** 2
    assert s_on.covariance_scale == pytest.approx(implied, rel=0.15)
    np.testing.assert_allclose(s_on.covariance, s_off.covariance * s_on.covariance_scale, rtol=1e-12)
    root = np.sqrt(s_on.covariance_scale)
    np.testing.assert_allclose(s_on.sigma_xyz_mm, s_off.sigma_xyz_mm * root, rtol=1e-12)
    np.testing.assert_allclose(s_on.sigma_rot_deg, s_off.sigma_rot_deg * root, rtol=1e-12)
    np.testing.assert_allclose(s_on.segments[-1].covariance, s_off.segments[-1].covariance * s_on.covariance_scale,
                               rtol=1e-12)
    np.testing.assert_array_equal(s_on.T_body_sensor, s_off.T_body_sensor)  # the estimate is not touched
    assert any(w.startswith("depth: the plane residuals are") for w in on.warnings)
    # without the switch (the defaults' case): reported, not scaled, not warned about
    assert s_off.covariance_scale == 1.0 and _plane_group(off).status == "given"
    assert not any("plane residuals" in w for w in off.warnings)
    assert {g.status for g in off.noise_groups} == {"given"} and len(off.noise_groups) >= 5


@pytest.mark.parametrize("plane_scale, warned", [(0.45, True), (0.6, False)])
def test_a_large_factor_is_warned_about_even_when_the_test_is_not_significant(dataset, plane_scale, warned):
    r = calibrate(dataset, options=_given(plane_scale, True), judge=False)
    f = r.sensors["depth"].covariance_scale
    assert _plane_group(r).p_high > 0.01 and f > 1.2
    assert (f > 2.0) == warned
    assert any(w.startswith("depth: the plane residuals are") for w in r.warnings) == warned


def test_planes_with_too_little_redundancy_are_warned_about_not_scaled(dataset):
    r = calibrate(dataset, options=_given(0.1, True), judge=False)
    assert _plane_group(r).dof < 3.0
    assert r.sensors["depth"].covariance_scale == 1.0
    assert any("too few to check the given noise model" in w for w in r.warnings)


def test_overstated_plane_noise_leaves_the_covariance_alone(dataset):
    on = calibrate(dataset, options=_given(3.0, True), judge=False)
    off = calibrate(dataset, options=_given(3.0, False), judge=False)
    assert _plane_group(on).data_scale < 1.0
    assert on.sensors["depth"].covariance_scale == 1.0
    np.testing.assert_array_equal(on.sensors["depth"].covariance, off.sensors["depth"].covariance)
    assert not any("plane residuals" in w for w in on.warnings)


def test_incremental_scales_its_final_covariance_not_its_history(dataset):
    on = calibrate_incremental(dataset, options=_given(0.25, True), judge=False)
    off = calibrate_incremental(dataset, options=_given(0.25, False), judge=False)
    batch = calibrate(dataset, options=_given(0.25, True), judge=False)
    assert [g.group for g in on.noise_groups] == ["plane:depth"]  # the iSAM2 graph names its planes only
    f = on.sensors["depth"].covariance_scale
    assert f > 4 and f == pytest.approx(batch.sensors["depth"].covariance_scale, rel=1e-3)  # the same graph
    np.testing.assert_allclose(on.sensors["depth"].covariance, off.sensors["depth"].covariance * f, rtol=1e-9)
    # the per-station sigmas (the stop rule's) are the solver's own
    np.testing.assert_array_equal(on.history[-1].sigma_xyz_mm, off.history[-1].sigma_xyz_mm)


def test_noise_from_an_understating_file_is_written_and_said(dataset, tmp_path):
    noise = {"sigma_joint_rad": 0.0017, "sigma_contact_m": 0.001, "sigma_ground_m": 0.0003, "sigma_imu_rad": 0.0006,
             "sigma_commanded_rad": 0.0009, "sigma_commanded_m": 0.0005, "plane_scale:depth": 0.25}
    src = tmp_path / "earlier.yaml"
    earlier = {"format": "graphcal-calibration/1", "outliers": [],
               "sensors": {"depth": {"T_body_sensor": {"xyz": [0.0, 0.0, 0.0], "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0],
                                                       "rpy_deg": [0.0, 0.0, 0.0]},
                                     "covariance": np.eye(6).tolist(),
                                     "sigma": {"rot_deg": [1.0] * 3, "xyz_mm": [1.0] * 3},
                                     "unobservable": []}},
               "residuals": {"normal_rms_deg": 0.01, "distance_rms_mm": 0.3}, "noise_model": noise}
    src.write_text(yaml.safe_dump(earlier), encoding="utf-8")
    result = run_calibrate(dataset.root, tmp_path / "out", progress=False, noise_from=src)
    doc = read_calibration_yaml(tmp_path / "out" / "calibration.yaml")
    f = doc["sensors"]["depth"]["covariance_scale"]
    plane = doc["noise_estimation"]["plane:depth"]
    assert plane["status"] == "given" and plane["data_scale"] > 1.3 and f > 2
    assert result.calibration.sensors["depth"].covariance_scale == pytest.approx(f, rel=1e-12)
    assert result.noise_from == str(src) and result.calibration.noise_source == str(src)
    assert f"depth: covariance x{f:.3g}" in result.summary_text()  # the console's words
    assert "includes a factor of" in (tmp_path / "out" / "report.html").read_text(encoding="utf-8")
