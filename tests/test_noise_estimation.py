"""Variance-component estimation: the dense and the factor-by-factor (gtsam.Marginals) paths give
the same group scales, and a noise model that fits gives scales near 1."""

from __future__ import annotations

import numpy as np
import pytest

import graphcal.calibration.noise_estimation as ne
from graphcal.calibration.calibrate import solve_problem
from graphcal.calibration.graph import CalibrationOptions, build_problem
from graphcal.calibration.measurements import calibration_data
from graphcal.io.dataset import load_dataset_robot, read_dataset
from graphcal.simulation.run import write_simulation
from graphcal.simulation.session import SimulationConfig, simulate


@pytest.fixture(scope="module")
def problem(tmp_path_factory):
    res = simulate(SimulationConfig(robot="octopus", program="random", n_stations=15, seed=71, cloud_stride=8))
    folder = tmp_path_factory.mktemp("vce") / "ds"
    write_simulation(res, folder, output="planes")
    ds = read_dataset(folder)
    robot = load_dataset_robot(ds)
    pb = build_problem(ds, robot, calibration_data(ds, robot), CalibrationOptions())
    return pb, solve_problem(pb).values


def test_dense_and_marginals_paths_agree(problem, monkeypatch):
    pb, values = problem
    dense = ne.group_variances(pb.graph, values, pb.factor_groups, pb.factor_components)
    monkeypatch.setattr(ne, "DENSE_MAX_DIM", 0)
    sparse = ne.group_variances(pb.graph, values, pb.factor_groups, pb.factor_components)
    assert dense.keys() == sparse.keys()
    for g in dense:
        assert dense[g].scale == pytest.approx(sparse[g].scale, rel=1e-6)
        assert dense[g].redundancy == pytest.approx(sparse[g].redundancy, rel=1e-6)


def test_default_noise_is_far_too_large_for_the_simulator(problem):
    """The defaults (0.1 deg joints, 1 mm contact, 0.5 deg IMU) are 5-15x the simulator's noise:
    every well-determined group's scale says so (and redundancies are positive, below the rows)."""
    pb, values = problem
    stats = ne.group_variances(pb.graph, values, pb.factor_groups, pb.factor_components)
    for g in ("stance_foot/joint", "imu"):
        assert 0.0 < stats[g].redundancy < stats[g].rows
        assert stats[g].scale < 0.5
