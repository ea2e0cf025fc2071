"""Is the reported covariance honest? Monte Carlo NEES of the extrinsic, and noise learned from data.

The NEES test follows the standard consistency test: the estimator's noise model is the one the
simulator used; over N runs the mean NEES of a 6-dof estimate must lie in the 95 % interval of
chi2(6N)/N. (bench/calibration_nees.py runs it with more runs.)
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from graphcal.calibration.calibrate import calibrate
from graphcal.simulation.session import SimulationConfig, simulate
from graphcal.simulation.write import write_simulation
from graphcal.solvers.covariance import nees
from graphcal.testing import SIMULATOR_NOISE, custom_hexapod, true_extrinsic


def _dataset(tmp_path, seed):
    res = simulate(SimulationConfig(robot="octopus", program="chai2015", seed=seed, cloud_stride=8))
    write_simulation(res, tmp_path / f"s{seed}", output="planes")
    return tmp_path / f"s{seed}", true_extrinsic(res.truth, "depth")


@pytest.mark.battery
@pytest.mark.slow
def test_monte_carlo_nees_of_the_extrinsic_is_in_its_95_percent_interval(tmp_path):
    n_runs = 24
    values = []
    for seed in range(300, 300 + n_runs):
        path, T_true = _dataset(tmp_path, seed)
        est = calibrate(path, options=SIMULATOR_NOISE).sensors["depth"]
        values.append(nees(T_true, est.T_body_sensor, est.covariance))
    lo, hi = chi2.ppf([0.025, 0.975], 6 * n_runs) / n_runs
    print(f"mean NEES over {n_runs} runs: {np.mean(values):.2f} (95 % interval {lo:.2f} .. {hi:.2f})")
    assert lo <= np.mean(values) <= hi


@pytest.mark.battery
@pytest.mark.slow
def test_unseen_hexapod_nees_with_the_noise_learned_is_in_its_95_percent_interval(tmp_path):
    """Issue 3's acceptance case with the product's defaults (noise learned from the data), over 10
    seeds: a hexapod graphcal does not ship (graphcal/testing.py), 45 random stations in three
    sessions, IMU, clouds (calibrate fits the planes). Every run within the goal (0.1 deg, 2 mm) and
    the mean NEES inside its 95 % interval. bench/calibration_nees.py --scenario unseen runs 200
    seeds (600-799; these 10 are its first): learned 5.30 (just below [5.53, 6.49]: conservative),
    the simulator's noise model 5.83 (inside); every run within the goal."""
    from graphcal.geometry import rotation_angle_between

    n_runs = 10
    values = []
    for seed in range(600, 600 + n_runs):
        res = simulate(SimulationConfig(robot="sidewinder", program="random", n_stations=45, n_sessions=3, seed=seed,
                                        tilt_scale=0.8, cloud_stride=8,
                                        custom_robot=custom_hexapod()))
        write_simulation(res, tmp_path / f"u{seed}", output="clouds")
        T_true = true_extrinsic(res.truth, "front_cam")
        est = calibrate(tmp_path / f"u{seed}").sensors["front_cam"]
        T = est.T_body_sensor
        assert np.degrees(rotation_angle_between(T[:3, :3], T_true[:3, :3])) < 0.1, seed
        assert 1e3 * np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 2.0, seed
        values.append(nees(T_true, T, est.covariance))
    lo, hi = chi2.ppf([0.025, 0.975], 6 * n_runs) / n_runs
    print(f"unseen hexapod, mean NEES over {n_runs} runs: {np.mean(values):.2f} (95 % interval {lo:.2f} .. {hi:.2f})")
    assert lo <= np.mean(values) <= hi


def test_noise_is_learned_from_the_data(tmp_path):
    """Variance-component estimation recovers the encoder noise the simulator used (0.02 deg) from
    the default guess (0.1 deg), and finds no contact noise."""
    path, _ = _dataset(tmp_path, 401)
    result = calibrate(path)  # defaults: estimate_noise=True
    assert np.degrees(result.noise["sigma_joint_rad"]) == pytest.approx(0.02, rel=0.25)
    assert result.noise["sigma_contact_m"] < 2e-4


def test_learned_noise_holds_the_ground_term_and_that_term_sets_the_rotation_sigma(tmp_path):
    """Why the learned noise model is conservative on the simulator's flat floor (docs/calibration.md).

    The feet's height above the ground has one row per planted foot (6 in one stance). The variance
    estimation lowers its sigma from 3 mm to 0.06 mm, where the rows carry under 3 dof and it is
    held ("too few dof"), while the simulated floor is exact (the simulator's model: 1e-6 m). That
    term alone doubles the sigma about the sensor's x axis: the simulator's model with only the
    ground sigma swapped for the learned one gave 1.97-2.51x on 12 seeds (100-111); the IMU's
    learned sigma changes it by under 1 %."""
    import dataclasses

    path, _ = _dataset(tmp_path, 100)
    learned = calibrate(path)
    groups = {g.group: g for g in learned.noise_groups}
    ground = groups["foot_on_ground"]
    assert ground.status == "too few dof" and ground.dof < 3.0 and ground.data_scale < 1.0
    assert groups["stance_foot/joint"].status == "learned" and groups["stance_foot/joint"].dof > 100

    def sigma(**swap):
        opts = dataclasses.replace(SIMULATOR_NOISE, **swap)
        return np.sqrt(np.diag(calibrate(path, options=opts).sensors["depth"].covariance))

    base = sigma()
    with_ground = sigma(sigma_ground_m=learned.noise["sigma_ground_m"])
    with_imu = sigma(sigma_imu_rad=learned.noise["sigma_imu_rad"])
    assert with_ground[0] / base[0] > 1.6
    assert abs(with_imu[0] / base[0] - 1.0) < 0.05
