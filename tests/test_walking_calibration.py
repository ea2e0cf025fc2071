"""Calibration from ordinary walking (issue 43, graphcal/calibration/walking.py, time_offset.py,
walk_calibration.py): a simulated hexapod walks with a depth camera whose CAD prior is off the
truth and whose clouds are stamped late; ``graphcal calibrate`` finds the extrinsic and the time
offset from the walk alone, with the stance read from the joint torques (the log's contact
columns removed, as a real log has none).

Development cases: seed 0 (sway 1 deg, 30 ms) and the swayless walk. The held-out case (seed 11,
sway 1.5 deg, 17 ms, other CAD errors) was run once, blind, after the bounds below were written.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import yaml

from graphcal.calibration.time_offset import _parabola
from graphcal.calibration.walking import stance_runs
from graphcal.errors import DatasetError
from graphcal.stats import ppf

#: NEES of the 6-dof extrinsic: one run inside chi2(6) 0.999
NEES_999 = float(ppf(0.999, 6))


def _strip_columns(ts: Path, prefixes: tuple[str, ...]) -> None:
    rows = list(csv.reader(ts.open()))
    keep = [i for i, h in enumerate(rows[0]) if not h.startswith(prefixes)]
    with ts.open("w", newline="") as f:
        w = csv.writer(f)
        for r in rows:
            w.writerow([r[i] for i in keep])


def _walk(tmp: Path, *, seed: int, delay_s: float, sway_deg: float, duration_s: float = 15.0,
          cad_mm: float = 15.0, cad_deg: float = 1.5) -> Path:
    from graphcal.simulation.walking import WalkingConfig, simulate_walking
    from graphcal.simulation.write import write_walking

    cfg = WalkingConfig(program="tripod-walk", seed=seed, duration_s=duration_s, cloud_rate_hz=15.0,
                        cad_error_m=1e-3 * cad_mm, cad_error_rad=np.radians(cad_deg), camera_delay_s=delay_s,
                        sway_rad=np.radians(sway_deg), nod_rad=np.radians(sway_deg / 2))
    out = write_walking(simulate_walking(cfg), tmp / f"walk{seed}")
    _strip_columns(out / "timeseries.csv", ("contact_",))  # the stance from the torques, as on a real log
    return out


def _calibrated(walk: Path, out: Path, **kw):
    from graphcal.commands import calibrate

    return calibrate.run(walk, out, progress=False, **kw)


@pytest.fixture(scope="module")
def swaying(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("walkcal")
    walk = _walk(tmp, seed=0, delay_s=0.030, sway_deg=1.0)
    return walk, _calibrated(walk, tmp / "out")


def test_stance_runs_number_each_touchdown():
    c = np.array([[1, 0], [1, 0], [0, 1], [1, 1], [1, 0]], bool)
    assert stance_runs(c).tolist() == [[0, -1], [0, -1], [-1, 0], [1, 0], [1, -1]]


def test_the_parabola_vertex_and_curvature():
    x = np.linspace(-0.01, 0.01, 9)
    x0, a = _parabola(x, 4e6 * (x - 0.003) ** 2 + 17.0)
    assert x0 == pytest.approx(0.003, abs=1e-9) and a == pytest.approx(4e6, rel=1e-9)


@pytest.mark.slow
def test_a_walk_calibrates_the_camera_and_its_time_offset(swaying):
    walk, r = swaying
    t = r.truth["depth"]
    s = r.calibration.sensors["depth"]
    assert r.verdict == "fits"
    assert t["nees"] < NEES_999
    assert t["rotation_error_deg"] < 0.1 and t["translation_error_mm"] < 3.0
    # the CAD prior was 1.5 deg / 15 mm per axis off: the walk moved the estimate away from it
    prior = yaml.safe_load((walk / "dataset.yaml").read_text())["sensors"]["depth"]["T_body_sensor_prior"]
    assert np.linalg.norm(np.array(prior["xyz"]) - s.T_body_sensor[:3, 3]) > 0.01
    assert s.time_offset_source == "estimated"
    assert abs(t["time_offset_error_ms"]) < 2.0
    assert abs(t["time_offset_error_ms"]) < 3 * 1e3 * s.time_offset_sigma_s
    doc = yaml.safe_load((r.out / "calibration.yaml").read_text())
    entry = doc["sensors"]["depth"]
    assert entry["time_offset_s"] == pytest.approx(s.time_offset_s)
    assert entry["time_offset_sigma_s"] == pytest.approx(s.time_offset_sigma_s)
    assert doc["walk"]["frames"]["depth"] >= 200 and doc["walk"]["duration_s"] == pytest.approx(15.0, abs=1.0)
    text = r.summary_text()
    assert "time offset +" in text and "walk: " in text and "time offset " in text.split("against the truth")[1]


@pytest.mark.slow
def test_a_swayless_walk_names_what_it_does_not_determine(tmp_path):
    """Without sway or nod the floor is seen from one tilt: the yaw about the vertical and the
    horizontal position are the prior's, and the calibration says so instead of a tight number."""
    walk = _walk(tmp_path, seed=3, delay_s=0.020, sway_deg=0.0)
    r = _calibrated(walk, tmp_path / "out", time_offsets_s={"depth": 0.020})
    s = r.calibration.sensors["depth"]
    assert s.time_offset_source == "given" and s.time_offset_sigma_s is None
    assert s.unobservable, "a swayless walk reported every direction determined"
    assert r.truth["depth"]["nees"] < NEES_999
    assert max(s.sigma_xyz_mm[:2]) > 10.0  # not a confident horizontal position


@pytest.mark.slow
def test_held_out_walk_blind(tmp_path):
    """Held out of the tuning; run once, blind (issue 43's targets for 15 s instead of 60 s)."""
    walk = _walk(tmp_path, seed=11, delay_s=0.017, sway_deg=1.5, cad_mm=20.0, cad_deg=2.0)
    r = _calibrated(walk, tmp_path / "out")
    t = r.truth["depth"]
    s = r.calibration.sensors["depth"]
    assert t["nees"] < NEES_999
    assert t["rotation_error_deg"] < 0.1 and t["translation_error_mm"] < 3.0
    assert abs(t["time_offset_error_ms"]) < 2.0
    assert abs(t["time_offset_error_ms"]) < 3 * 1e3 * s.time_offset_sigma_s


def test_a_walk_without_stance_information_is_refused_in_one_line(tmp_path):
    from graphcal.simulation.walking import WalkingConfig, simulate_walking
    from graphcal.simulation.write import write_walking

    walk = write_walking(simulate_walking(WalkingConfig(program="tripod-walk", duration_s=6.0, cloud_rate_hz=2.0)),
                         tmp_path / "w")
    _strip_columns(walk / "timeseries.csv", ("contact_", "tau_"))
    with pytest.raises(DatasetError) as e:
        _calibrated(walk, tmp_path / "out")
    assert "timeseries.csv" in str(e.value) and "force_<foot>" in str(e.value) and "\n" not in str(e.value)
    assert not (tmp_path / "out").exists()


def test_the_simulator_hides_a_cad_error_and_a_late_stamp(tmp_path):
    from graphcal.simulation.walking import WalkingConfig, simulate_walking
    from graphcal.simulation.write import walking_dataset

    base = dict(program="tripod-walk", duration_s=6.0, cloud_rate_hz=5.0)
    a = simulate_walking(WalkingConfig(**base))
    b = simulate_walking(WalkingConfig(**base, cad_error_m=0.02, cad_error_rad=0.03, camera_delay_s=0.025))
    assert np.allclose(a.T_body_sensor, b.T_body_sensor)  # the truth is the same walk's
    assert np.allclose(a.T_body_sensor_cad, a.T_body_sensor)
    assert np.linalg.norm(b.T_body_sensor_cad[:3, 3] - b.T_body_sensor[:3, 3]) > 0.005
    rows_a = np.flatnonzero(walking_dataset(a).timeseries["cloud_depth"] != "")
    rows_b = np.flatnonzero(walking_dataset(b).timeseries["cloud_depth"] != "")
    assert len(rows_b) >= len(rows_a) - 1 and (rows_b - rows_a[: len(rows_b)] == 25).all()  # 25 ms at 1 kHz


def test_a_walking_program_simulates_its_own_robot_when_none_is_named(tmp_path):
    from graphcal.cli import main

    out = tmp_path / "w"
    assert main(["simulate", "--program", "tripod-walk", "--duration", "6", "--cloud-rate", "0", "--out", str(out),
                 "--quiet"]) == 0
    assert yaml.safe_load((out / "dataset.yaml").read_text())["robot"]["model"] == "qingzhui"


def test_the_offsets_sigma_widens_the_extrinsic_and_an_undetermined_offset_is_warned():
    from graphcal.calibration.result import CalibrationResult, SensorEstimate
    from graphcal.calibration.time_offset import TimeOffsetEstimate
    from graphcal.calibration.walk_calibration import with_time_offsets

    cov = np.diag([1e-8] * 3 + [1e-8] * 3)
    s = SensorEstimate("depth", "depth_camera", np.eye(4), cov, np.eye(4), np.zeros(3), np.zeros(3), np.eye(6))
    res = CalibrationResult("ds", "", "body", {"depth": s})
    J = np.array([0.0, 0.0, 0.5, 0.1, 0.0, 0.0])  # rad/s, m/s
    out = with_time_offsets(res, (TimeOffsetEstimate("depth", 0.03, 1e-3, "estimated", (), J),))
    got = out.sensors["depth"]
    np.testing.assert_allclose(got.covariance, cov + np.outer(J, J) * 1e-6)
    assert got.sigma_rot_deg[2] == pytest.approx(np.degrees(np.sqrt(1e-8 + 0.25e-6)), rel=1e-6)
    assert got.time_offset_s == 0.03 and got.time_offset_sigma_s == 1e-3 and not out.warnings
    vague = with_time_offsets(res, (TimeOffsetEstimate("depth", 0.01, 0.02, "not determined", (), J),))
    assert vague.sensors["depth"].time_offset_sigma_s is None
    assert vague.sensors["depth"].covariance[2, 2] == pytest.approx(1e-8 + 0.25 * 4e-4)
    assert len(vague.warnings) == 1 and "does not determine the camera's time offset" in vague.warnings[0]


def test_a_walk_on_ground_that_is_not_level_is_refused_in_one_line(tmp_path):
    from graphcal.errors import GraphcalError
    from graphcal.simulation.walking import WalkingConfig, simulate_walking
    from graphcal.simulation.write import write_walking

    walk = write_walking(simulate_walking(WalkingConfig(program="tripod-walk", duration_s=6.0, cloud_rate_hz=2.0)),
                         tmp_path / "w")
    text = (walk / "dataset.yaml").read_text().replace("ground: {type: level}", "ground: {type: stairs}")
    assert "stairs" in text
    (walk / "dataset.yaml").write_text(text)
    with pytest.raises(GraphcalError) as e:
        _calibrated(walk, tmp_path / "out")
    assert "ground.type 'stairs'" in str(e.value) and "\n" not in str(e.value)
    assert not (tmp_path / "out").exists()
