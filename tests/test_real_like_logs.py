"""Logs written the way real robots write them (issue 42): raw foot counts with per-foot offsets and
gains, a stand-up and a lie-down, the IMU off the base link, a 400 Hz log and noise levels none of
graphcal's defaults has (graphcal.simulation.real_like). Each must track within 1 % drift with a
verdict that is not inconsistent and a plausible trajectory, with nothing set by hand: the noise
learned from the log, the contacts from each foot's own signal, the phases found.

Development was against the a1 trot of seed 1 (and seed 5 by hand); the walk of seed 2, the
hexapod's tripod walk of seed 3 and the trot of seed 4 were held out of the tuning and first run
once, blind (their figures are in the commit message and docs/state_estimation.md)."""

from __future__ import annotations

import json

import pytest

from graphcal.cli import main

CASES = [("trot", 1), ("walk", 2), ("tripod-walk", 3), ("trot", 4)]


@pytest.fixture(scope="module", params=CASES, ids=[f"{p}-{s}" for p, s in CASES])
def tracked(request, tmp_path_factory):
    from graphcal.simulation.real_like import real_like_log
    from graphcal.simulation.write import write_real_like

    program, seed = request.param
    root = tmp_path_factory.mktemp(f"real_like_{program}_{seed}")
    log = real_like_log(program, seed)
    write_real_like(log, root / "ds")
    assert main(["track", str(root / "ds"), "--out", str(root / "track"), "--quiet"]) == 0
    return log, json.loads((root / "track" / "metrics.json").read_text())


@pytest.mark.slow
def test_real_like_log_tracks_within_1_percent_consistent_and_plausible(tracked):
    log, m = tracked
    assert m["drift_percent"] <= 1.0
    assert m["consistency"]["verdict"] != "inconsistent"
    assert m["plausibility"]["verdict"] == "plausible", m["plausibility"]["reason"]
    assert m["nees_fraction_above_band"] <= 0.05  # not over-confident
    assert m["innovation_bias"]["verdict"] == "unbiased"


@pytest.mark.slow
def test_real_like_noise_is_learned_not_the_defaults(tracked):
    """The IMU and encoder noise come from the still windows, within 10 % of the log's true values
    (which none of graphcal's defaults is)."""
    log, m = tracked
    c, v, src = log.config, m["noise"]["values"], m["noise"]["sources"]
    for key, true in (("gyro_noise_density", c.gyro_noise_density), ("accel_noise_density", c.accel_noise_density),
                      ("encoder_sigma_rad", c.encoder_sigma_rad)):
        assert src[key].startswith("learned: still windows"), (key, src[key])
        assert v[key] == pytest.approx(true, rel=0.10), key


@pytest.mark.slow
def test_real_like_contacts_and_phases_are_found(tracked):
    """Each foot's thresholds are its own (the raw counts' offsets and gains differ); the log is
    segmented into lying, standing up, walking, lying down -- in that order."""
    log, m = tracked
    phases = [s["phase"] for s in m["phases"]["segments"]]
    order = [p for p in phases if p in ("lying", "standing_up", "walking", "lying_down")]
    assert order[:3] == ["lying", "standing_up", "walking"] and order[-2:] == ["lying_down", "lying"]
    assert m["floor"]["zero_velocity_updates"] > 0
    if log.force_counts is not None:
        feet = m["contacts"]["feet"]
        assert {r["source"] for r in feet.values()} == {"learned"}
        for f, (offset, gain) in log.force_counts.items():  # the swing mode near the foot's own offset
            assert abs(feet[f]["low_mode"] - offset) < 10.0 / gain + 5.0, f
        assert all(0.3 < r["duty_factor"] < 0.95 for r in feet.values())


def _scaled_legs_urdf(robot, scale: float, feet: tuple) -> str:
    """The robot's URDF with the thigh and shank of ``feet`` ``scale`` times as long (graphcal.models.perturb)."""
    import numpy as np

    from graphcal.models.perturb import LegPerturbation, apply_perturbation, link_length_delta

    deltas = {}
    for f in feet:
        leg = robot.leg(f)
        knee, foot_joint = leg.joint_names[2], f.replace("_foot", "_foot_joint")
        deltas[knee] = tuple(link_length_delta(robot, knee, (scale - 1) * np.linalg.norm(leg.T_parent_joint[2][:3, 3])))
        deltas[foot_joint] = tuple(link_length_delta(robot, foot_joint,
                                                     (scale - 1) * np.linalg.norm(leg.T_lastjoint_foot[:3, 3])))
    return apply_perturbation(robot.urdf_xml, LegPerturbation(origin_deltas_m=deltas))


@pytest.mark.slow
def test_a_wrong_leg_model_is_implausible_and_named_with_its_time(tmp_path, capsys):
    """The real-like trot given front legs 0.75x as long as the robot's (a robot.urdf in the dataset:
    the URDF of another variant): the body seems pitched on level ground, the console warns that
    the trajectory is physically implausible and names when and how much, the report says it at the
    top; with the robot's own legs the same log is plausible (above). (All four legs scaled alike
    are not caught: docs/state_estimation.md, "A leg model off by a constant".)"""
    import shutil

    import yaml

    from graphcal.io.dataset import load_dataset_robot, read_dataset
    from graphcal.simulation.real_like import real_like_log
    from graphcal.simulation.write import write_real_like

    ds = tmp_path / "ds"
    write_real_like(real_like_log("trot", 1), ds)
    robot = load_dataset_robot(read_dataset(ds))
    (ds / "robot.urdf").write_text(_scaled_legs_urdf(robot, 0.75, ("fl_foot", "fr_foot")))
    doc = yaml.safe_load((ds / "dataset.yaml").read_text())
    doc["robot"] = {"urdf": "robot.urdf", "base_frame": doc["robot"]["base_frame"], "feet": doc["robot"]["feet"]}
    (ds / "dataset.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    capsys.readouterr()
    assert main(["track", str(ds), "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert "WARNING: the trajectory is physically implausible: " in err
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    p = m["plausibility"]
    assert p["verdict"] == "implausible" and p["failures"]
    first = p["failures"][0]
    assert first["message"] in err and f"at {first['peak_s']:.1f} s" in first["message"]
    assert 2.0 < first["time_s"] < 23.0  # inside the log, after the stand-up began
    report = (tmp_path / "out" / "report.html").read_text()
    assert "Physical plausibility: implausible" in report and 'class="warn"' in report
    shutil.rmtree(ds)


@pytest.mark.slow
def test_joint_zero_offsets_bias_the_innovations_and_are_named(tmp_path, capsys):
    """The real-like trot with 5 mrad zero offsets on every joint encoder (what a real robot's joint
    calibration leaves): drift and NEES grow while the NIS level stays matched; the innovations'
    mean per foot says the leg model is off by a constant, on the console and in metrics.json."""
    from dataclasses import replace

    from graphcal.simulation.real_like import RealLikeLog, real_like_log
    from graphcal.simulation.write import write_real_like

    log = real_like_log("trot", 1)
    write_real_like(RealLikeLog(replace(log.config, joint_offset_sigma_rad=0.005), log.force_counts), tmp_path / "ds")
    capsys.readouterr()
    assert main(["track", str(tmp_path / "ds"), "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    ib = m["innovation_bias"]
    assert ib["verdict"] == "biased" and abs(ib["worst"]["t"]) >= 5.0 and abs(ib["worst"]["mean_sigma"]) >= 0.3
    assert f"the stance innovations of {ib['worst']['slot']} are biased" in err and "identify-legs" in err


def _docs_map() -> str:
    """The Unitree-style column map of docs/state_estimation.md (the block marked docs-example)."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "state_estimation.md").read_text()
    block = text.split("# docs-example: unitree-csv-map\n", 1)[1].split("```", 1)[0]
    return block


@pytest.mark.slow
def test_the_docs_unitree_csv_example_imports_and_tracks(tmp_path):
    """docs/state_estimation.md's worked example as written: a real-like trot exported as a Unitree
    CSV (raw counts), imported with the docs' map (no offsets, scales or thresholds), tracked with the
    defaults: within 1 % drift, consistent, plausible, every foot's thresholds learned."""
    import shutil
    from dataclasses import replace

    from graphcal.simulation.real_like import RealLikeLog, real_like_log
    from graphcal.simulation.ros_log import write_walk_csv
    from graphcal.simulation.write import write_real_like

    log = real_like_log("trot", 1)  # the built-in a1's URDF has no IMU link: the IMU at the base origin
    write_real_like(RealLikeLog(replace(log.config, imu_xyz_m=(0.0, 0.0, 0.0)), log.force_counts), tmp_path / "sim")
    write_walk_csv(tmp_path / "sim", tmp_path / "go1.csv")
    (tmp_path / "go1_map.yaml").write_text(_docs_map())
    assert main(["import", str(tmp_path / "go1.csv"), "--map", str(tmp_path / "go1_map.yaml"), "--timeseries",
                 "--out", str(tmp_path / "go1"), "--quiet"]) == 0
    for name in ("truth.yaml", "truth_trajectory.csv"):  # the simulator's truth, for the accuracy only
        shutil.copy(tmp_path / "sim" / name, tmp_path / "go1" / name)
    assert main(["track", str(tmp_path / "go1"), "--out", str(tmp_path / "go1_track"), "--quiet"]) == 0
    m = json.loads((tmp_path / "go1_track" / "metrics.json").read_text())
    assert m["drift_percent"] <= 1.0 and m["consistency"]["verdict"] == "consistent"
    assert m["plausibility"]["verdict"] == "plausible" and m["innovation_bias"]["verdict"] == "unbiased"
    assert {r["source"] for r in m["contacts"]["feet"].values()} == {"learned"}


@pytest.mark.slow
def test_stairs_declared_level_are_implausible_and_the_warning_says_declare_the_ground(tmp_path, capsys):
    """A stairs walk whose dataset.yaml says the ground is level (a user's mistake): the floor updates
    cannot fit it; the verdict is implausible (touchdowns far above the floor) and the warning says
    to declare the ground, not only that the model does not fit."""
    import yaml

    ds = tmp_path / "ds"
    assert main(["simulate", "--robot", "qingzhui", "--program", "tripod-stairs", "--cloud-rate", "0", "--out",
                 str(ds), "--quiet"]) == 0
    doc = yaml.safe_load((ds / "dataset.yaml").read_text())
    doc["ground"] = {"type": "level"}
    (ds / "dataset.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    capsys.readouterr()
    assert main(["track", str(ds), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    err = capsys.readouterr().err
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert m["plausibility"]["verdict"] == "implausible"
    assert any(f["kind"] == "touchdown" and f["size"] > 0.1 for f in m["plausibility"]["failures"])
    assert "if the ground is not level, declare it" in err
