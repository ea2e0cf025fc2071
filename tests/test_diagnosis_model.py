"""graphcal/diagnosis/model.py: when the variance components count as moved, and the memo of solves
(the same model from the same start, or from its own solution, is not solved again)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

import graphcal.diagnosis.model as model_module
from graphcal.diagnosis.model import DiagnosisModel, model_options, noise_moved

DATA = Path(__file__).parent / "data" / "octopus_small"


def test_noise_moved_reads_every_sigma_and_plane_scale_against_the_tolerance():
    o = model_options(type("ds", (), {"imu": None})())
    assert not noise_moved(o, o)
    assert noise_moved(o, dataclasses.replace(o, sigma_joint_rad=o.sigma_joint_rad * 1.03))
    assert not noise_moved(o, dataclasses.replace(o, sigma_joint_rad=o.sigma_joint_rad * 1.01))
    assert noise_moved(o, dataclasses.replace(o, sigma_commanded_m=o.sigma_commanded_m / 1.05))
    assert noise_moved(o, dataclasses.replace(o, plane_sigma_scales=(("depth", 1.05),)))
    assert not noise_moved(o, dataclasses.replace(o, plane_sigma_scales=(("depth", 1.005),)))


@pytest.fixture()
def model():
    from graphcal.calibration.measurements import calibration_data
    from graphcal.io.dataset import load_dataset_robot, read_dataset

    ds = read_dataset(DATA)
    robot = load_dataset_robot(ds)
    return DiagnosisModel(ds, robot, calibration_data(ds, robot), model_options(ds))


def test_a_model_is_not_solved_again_from_the_same_start_or_from_its_solution(model, monkeypatch):
    calls = []
    solve_lm = model_module.solve_lm
    monkeypatch.setattr(model_module, "solve_lm", lambda *a, **k: calls.append(1) or solve_lm(*a, **k))
    problem, values = model.solve()
    assert len(calls) == 1
    assert model.solve() == (problem, values)  # the same start (none): the same objects
    assert dataclasses.replace(model).solve(initial=values) == (problem, values)  # from its own solution
    assert len(calls) == 1
    noisier = dataclasses.replace(model, options=dataclasses.replace(model.options, sigma_joint_rad=0.01))
    assert noisier.solve(initial=values)[1] is not values  # other noise: solved
    assert len(calls) == 2
    model.solve(initial=problem.initial)  # another start object: solved
    assert len(calls) == 3


def test_the_legs_parameter_kinematics_come_in_one_batch_equal_to_each_station_alone(model):
    """calibration/kinematic_pose.leg_parameter_kinematics (what every stance factor estimating a leg
    reads at its first linearisation, a screening graph's): per station, the forward kinematics and
    parameter Jacobian of that station's joint angles at the nominal parameters."""
    import numpy as np

    from graphcal.calibration.kinematic_pose import leg_parameter_kinematics
    from graphcal.models.legs import fk_and_param_jacobian, leg_model

    for foot in model.robot.feet[:2]:
        param = leg_model(model.robot, foot, origins="none")
        table = leg_parameter_kinematics(model.data, model.robot, foot, param)
        stations = [st for st in model.data.stations if foot in st.q_by_foot]
        assert sorted(table) == sorted(st.station for st in stations) and stations
        for st in stations:
            theta0, p, J = table[st.station]
            p1, J1 = fk_and_param_jacobian(model.robot.leg(foot), param, np.asarray(st.q_by_foot[foot], float),
                                           param.zeros())
            assert not theta0.any()
            np.testing.assert_allclose(p, p1, atol=1e-12)
            np.testing.assert_allclose(J, J1, atol=1e-12)
        assert leg_parameter_kinematics(model.data, model.robot, foot, param) is table  # cached
