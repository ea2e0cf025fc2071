"""graphcal diagnose in the open world (issue 28): verdicts judged at physical noise, findings that
must predict held-out stations significantly better, the two shared-parameter causes (a foot
radius, a joint compliance) and effects outside the catalogue reported as structure, never as a
confident wrong cause. The batteries (examples/diagnosis_openworld.py) are the slow part."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))


def _simulate(folder: Path, robot: str, seed: int, *, effects=(), open_world=None) -> Path:
    from dataclasses import replace

    from graphcal.commands.simulate import run as simulate_to_folder

    if open_world is None:
        simulate_to_folder(robot=robot, program="random", ground="level", out_dir=folder, seed=seed, n_stations=48,
                           n_sessions=3, output="planes", cloud_stride=8, effects=list(effects), progress=False,
                           session_heading_step_deg=40.0, overwrite=True)
        return folder
    from graphcal.simulation.effects import Effects
    from graphcal.simulation.session import SimulationConfig, simulate
    from graphcal.simulation.write import write_simulation

    cfg = SimulationConfig(robot=robot, program="random", ground="level", seed=seed, n_stations=48, n_sessions=3,
                           cloud_stride=8, session_heading_step_deg=40.0)
    write_simulation(simulate(replace(cfg, effects=Effects(open_world=open_world))), folder, output="planes",
                     overwrite=True)
    return folder


def test_open_world_generators_change_what_they_say():
    """The open-world generators (outside the catalogue): a plate raises the named feet of its
    session, a range^2 error lengthens every point by k r^2, sinking lowers the feet through the
    session, a drifting IMU mount rotates gravity in the IMU by the drift's angle at the last station."""
    from dataclasses import replace

    import numpy as np

    from graphcal.simulation.effects import Effects, OpenWorld
    from graphcal.simulation.session import SimulationConfig, simulate

    cfg = SimulationConfig(robot="octopus", program="random", ground="level", seed=4, n_stations=6, n_sessions=2,
                           cloud_stride=16, imu_accel_sigma_m_s2=0.0, imu_accel_bias_sigma_m_s2=0.0)
    base = simulate(cfg)
    feet = base.truth["sessions"]["s1"]["feet_world"]
    plate = simulate(replace(cfg, effects=Effects(open_world=OpenWorld(plate=("s1", ("lf_foot",), 0.02)))))
    z = {f: p[2] for f, p in plate.truth["sessions"]["s1"]["feet_world"].items()}
    assert z["lf_foot"] - feet["lf_foot"][2] == pytest.approx(0.02)
    assert all(z[f] == pytest.approx(feet[f][2]) for f in z if f != "lf_foot")
    quad = simulate(replace(cfg, effects=Effects(open_world=OpenWorld(range_quadratic={"depth": 0.01}))))
    for key, pts in base.clouds.items():
        r0, r1 = np.linalg.norm(pts, axis=1), np.linalg.norm(quad.clouds[key], axis=1)
        np.testing.assert_allclose(r1, r0 * (1 + 0.01 * r0), rtol=1e-12)
    drift = simulate(replace(cfg, effects=Effects(open_world=OpenWorld(imu_drift=(0.03, 0.0)))))
    a0, a1 = base.stations[-1].imu_accel, drift.stations[-1].imu_accel
    angle = np.arccos(np.clip(a0 @ a1 / np.linalg.norm(a0) / np.linalg.norm(a1), -1, 1))
    assert 0.01 < angle <= 0.03 + 1e-9  # the drift's axis is horizontal in the body: gravity turns by up to 0.03 rad
    assert np.allclose(base.stations[0].imu_accel, drift.stations[0].imu_accel)
    sink = simulate(replace(cfg, effects=Effects(open_world=OpenWorld(sinking={"s2": 0.02}))))
    st2 = [r for r in sink.stations if r.session == "s2"]
    b2 = {r.station: r for r in base.stations}
    dz = [r.T_world_body_real[2, 3] - b2[r.station].T_world_body_real[2, 3] for r in st2]
    assert dz[0] == pytest.approx(0.0, abs=1e-9) and dz[-1] == pytest.approx(-0.02, abs=2e-3)


def test_clean_data_pass_every_group_at_physical_noise(tmp_path):
    from graphcal.diagnosis import diagnose
    from graphcal.report.diagnosis_json import diagnosis_to_dict

    doc = diagnosis_to_dict(diagnose(_simulate(tmp_path / "clean", "octopus", 3)))
    assert doc["findings"] == [] and not doc["unexplained_structure"] and doc["answer"] == "nominal"
    groups = {g["group"]: g for g in doc["physical_noise_tests"]["final"]}
    # every group covered, planes included; the documented defaults are conservative (chi2/dof < 0.5)
    assert {"stance_foot", "foot_on_ground", "imu", "commanded", "plane:depth"} <= set(groups)
    assert all(g["chi2_per_dof"] < 0.5 and not g["structure"] for g in groups.values())


def test_a_plate_under_two_feet_is_structure_not_a_session_offset(tmp_path):
    """A 20 mm plate under two feet of one session: before, diagnose named a 6.7 mm session offset with
    no note. Now the foot-height group fails at physical noise, the offset is at most tentative, the
    answer is neither model, and calibrate-style warnings name the group."""
    from graphcal.diagnosis import diagnose
    from graphcal.models.robot import load_robot
    from graphcal.report.diagnosis_json import diagnosis_to_dict
    from graphcal.simulation.effects import OpenWorld

    feet = load_robot(model="octopus").feet
    folder = _simulate(tmp_path / "plate", "octopus", 3, open_world=OpenWorld(plate=("s1", tuple(feet[:2]), 0.02)))
    doc = diagnosis_to_dict(diagnose(folder))
    assert doc["unexplained_structure"] and doc["answer"] == "neither"
    assert "foot_on_ground" in doc["structure_remains_in"]
    assert all(not f["supported"] for f in doc["findings"])
    assert any("foot_on_ground" in w for w in doc["warnings"])


@pytest.mark.slow
@pytest.mark.parametrize("cause,param", [("foot_radius", "radius_m"), ("joint_compliance", "k_rad_per_m")])
def test_shared_parameter_causes_are_named_once_within_3_sigma(tmp_path, cause, param):
    """One foot radius (not per-leg offsets), one compliance constant (not four femur offsets)."""
    import yaml

    from graphcal.diagnosis import diagnose
    from graphcal.report.diagnosis_json import diagnosis_to_dict

    folder = _simulate(tmp_path / cause, "octopus", 5, effects=[(cause, {})])
    doc = diagnosis_to_dict(diagnose(folder))
    truth = yaml.safe_load((folder / "truth.yaml").read_text())["effects"][cause]
    assert [f["cause"] for f in doc["findings"]] == [cause]
    f = doc["findings"][0]
    assert f["supported"] and f["gain"]["p_value"] < 0.01
    assert abs(f["parameters"][param] - truth[param]) <= 3 * f["sigma"][param]
    assert doc["answer"] == "extended" and not doc["unexplained_structure"]
    if cause == "joint_compliance":
        assert f["where"]["joint_index"] == truth["joint_index"]


# ----------------------------------------------------------------------------- the open-world battery
@pytest.fixture(scope="module")
def developed():
    import diagnosis_openworld

    return diagnosis_openworld.main(diagnosis_openworld.DEVELOPED, per=5, jobs=2, verbose=True)


@pytest.mark.battery
@pytest.mark.slow
def test_open_world_developed_generators(developed):
    """A plate under two feet and a depth error growing with range^2 (the generators developed
    against): reported as structure (named correctly is impossible: no catalogued cause fits) in
    at least 90 % of the cases, a confident wrong cause in at most 5 %."""
    assert developed["error"] == 0.0
    assert developed["honest"] >= 0.9
    assert developed["wrong"] <= 0.05


@pytest.fixture(scope="module")
def blind():
    import diagnosis_openworld

    return diagnosis_openworld.main(diagnosis_openworld.BLIND, per=5, jobs=2, first_seed=700, verbose=True)


@pytest.mark.battery
@pytest.mark.slow
def test_open_world_blind_generators(blind):
    """Feet sinking during a session and an IMU mount drifting over the run: kept out of development
    and run once at its end (docs/diagnosis.md, the BLIND row); the same targets."""
    assert blind["error"] == 0.0
    assert blind["honest"] >= 0.9
    assert blind["wrong"] <= 0.05
