"""Undeclared segment boundaries (graphcal/diagnosis/segments.py, issue 29 item 3): height steps and
knocks nobody declared, found by change-point segmentation over the station sequence, ends included.

Two robots (octopus, 30 stations; qingzhui, 24 stations), one session each, planes only. A height
step: every plane's distance from a station on shortened by 20 mm (the feet sank: the ground the
sensor sees came closer); a knock: the simulator's extrinsic change (2 deg) from a station on. Each
case asserts the cause, the station, and what the finder did with the data; a knock with one
station on a side (an outlier measurement reads the same) must be a note naming the station and no
correction.
"""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import numpy as np
import pytest

#: robot -> (seed, stations)
ROBOTS = {"octopus": (1, 30), "qingzhui": (2, 24)}
STEP_M = 0.02


def _simulate(folder: Path, robot: str, effects=()) -> Path:
    from graphcal.commands.simulate import run as simulate_to_folder

    seed, n = ROBOTS[robot]
    simulate_to_folder(robot=robot, program="random", ground="level", out_dir=folder, seed=seed, n_stations=n,
                       n_sessions=1, output="planes", cloud_stride=8, progress=False, effects=list(effects))
    return folder


def _height_step(src: Path, dst: Path, from_station: int, h: float) -> Path:
    """``src`` with every plane's d shortened by ``h`` from ``from_station`` on (the feet sank by h)."""
    shutil.copytree(src, dst)
    with open(dst / "planes.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        if int(r["station"]) >= from_station:
            r["d"] = repr(float(r["d"]) - h)
    with open(dst / "planes.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return dst


def _find(folder: Path):
    from graphcal.calibration.measurements import calibration_data
    from graphcal.diagnosis.model import DiagnosisModel, model_options
    from graphcal.diagnosis.segments import find_segments
    from graphcal.io.dataset import load_dataset_robot, read_dataset

    ds = read_dataset(folder)
    robot = load_dataset_robot(ds)
    model, _, _ = DiagnosisModel(ds, robot, calibration_data(ds, robot), model_options(ds)).learn_noise()
    corrections, data, notes = find_segments(model, lambda msg: None)
    return model, corrections, data, notes


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    root = tmp_path_factory.mktemp("segments")
    return {r: _simulate(root / f"clean_{r}", r) for r in ROBOTS}


@pytest.mark.parametrize("robot", list(ROBOTS))
def test_clean_data_find_nothing(clean, robot):
    model, corrections, data, notes = _find(clean[robot])
    assert corrections == () and notes == ()
    assert data is model.data


@pytest.mark.parametrize("robot", list(ROBOTS))
@pytest.mark.parametrize("where", ["mid", "second", "last"])
def test_an_undeclared_height_step_is_found_at_its_station(clean, robot, where, tmp_path):
    n = ROBOTS[robot][1]
    k = {"mid": n // 2, "second": 2, "last": n}[where]
    model, corrections, data, notes = _find(_height_step(clean[robot], tmp_path / "step", k, STEP_M))
    assert [c.cause for c in corrections] == ["height_step"], notes
    c = corrections[0]
    assert c.get("from_station") == k and c.get("session") == "s1"
    got = dict(c.corrected)
    assert abs(got["ground_distance_change_m"] + STEP_M) < 3 * got["sigma_m"] + 1e-3
    assert got["boundary_interval"][0] <= k <= got["boundary_interval"][1]
    assert c.p_value < 1e-6 and c.confidence > 2.0
    # the stations from the boundary on carry a new session label; nothing else changed
    new = dict(c.corrected)["new_session"]
    assert [st.session for st in data.stations] == ["s1" if st.station < k else new for st in data.stations]
    assert data.planes is model.data.planes
    if where != "mid":  # one station on a side: the note and the alternatives say what else it could be
        odd = 1 if where == "second" else n
        assert "one station" in c.note and f"outlier_stations(stations=[{odd}])" in c.alternatives
    else:
        assert c.alternatives == ()


@pytest.mark.parametrize("robot", list(ROBOTS))
@pytest.mark.parametrize("where", ["mid", "2 before", "2 after", "1 before", "1 after"])
def test_a_knock_is_found_or_said_ambiguous_at_the_ends(clean, robot, where, tmp_path):
    n = ROBOTS[robot][1]
    k = {"mid": n // 2, "2 before": 3, "2 after": n - 1, "1 before": 2, "1 after": n}[where]
    folder = _simulate(tmp_path / "knock", robot, [("extrinsic_change", {"sensor": "depth", "station": str(k),
                                                                         "angle_rad": "0.035"})])
    model, corrections, data, notes = _find(folder)
    assert data is model.data  # a knock changes no data
    if where.startswith("1"):
        # one station on a side: a knock or an outlier measurement -- said, not picked
        assert corrections == ()
        one = k - 1 if where == "1 before" else k
        assert len(notes) == 1 and notes[0].startswith(f"station {one}:") and "cannot tell" in notes[0]
        return
    assert [c.cause for c in corrections] == ["extrinsic_knock"], notes
    c = corrections[0]
    assert c.get("sensor") == "depth" and c.get("from_station") == k
    lo, hi = dict(c.corrected)["boundary_interval"]
    assert lo <= k <= hi and hi - lo <= 2
    assert c.confidence > 2.0


def test_diagnose_names_the_session_offset_of_a_height_step(clean, tmp_path):
    from graphcal.diagnosis import diagnose
    from graphcal.report.diagnosis_json import diagnosis_to_dict

    folder = _height_step(clean["octopus"], tmp_path / "step", 15, STEP_M)
    d = diagnose(folder, heldout=False)
    assert [c.label() for c in d.corrections] == ["height_step(from_station=15, session=s1)"]
    f = d.findings[0]
    assert f.candidate.cause == "session_offset" and f.candidate.get("session") in ("s1", "s1@15")
    sign = -1.0 if f.candidate.get("session") == "s1" else 1.0  # offset_m > 0: the feet of the session sank
    assert abs(sign * f.parameters["offset_m"] - STEP_M) < 3 * f.sigma["offset_m"] + 1e-3
    assert diagnosis_to_dict(d)["corrections"][0]["where"] == {"from_station": 15, "session": "s1"}


def test_diagnose_names_a_knock_two_stations_from_the_end(tmp_path):
    """The loop tests extrinsic_change with 3 stations on each side; a knock the segmentation found
    is tested with 2 (diagnose.MIN_KNOCK_STATIONS), so it is named at its station."""
    from graphcal.diagnosis import diagnose

    n = ROBOTS["qingzhui"][1]
    folder = _simulate(tmp_path / "knock", "qingzhui", [("extrinsic_change", {"sensor": "depth", "station": str(n - 1),
                                                                             "angle_rad": "0.035"})])
    d = diagnose(folder, heldout=False)
    assert [c.label() for c in d.corrections] == [f"extrinsic_knock(from_station={n - 1}, sensor=depth)"]
    f = d.findings[0]
    assert f.candidate.label() == f"extrinsic_change(sensor=depth, station={n - 1})"
    assert np.isfinite(f.parameters["angle_rad"]) and abs(f.parameters["angle_rad"] - 0.035) < 3 * f.sigma["angle_rad"] + 0.005


@pytest.mark.parametrize("block", [(1, 2), (22, 32), (48, 48)], ids=["first two", "mid-session", "last"])
def test_a_height_step_among_declared_sessions_relabels_the_stations_at_the_other_height(block, tmp_path):
    """Three declared sessions (16 stations each) share one ground: the stations of ``block`` (m, inclusive)
    sank 15 mm; the stations at the other height, and only they, get the new session."""
    from graphcal.commands.simulate import run as simulate_to_folder

    base = tmp_path / "base"
    simulate_to_folder(robot="octopus", program="random", ground="level", out_dir=base, seed=100, n_stations=48,
                       n_sessions=3, output="planes", cloud_stride=8, progress=False, session_heading_step_deg=40.0)
    lo, hi = block
    folder = tmp_path / "step"
    shutil.copytree(base, folder)
    with open(folder / "planes.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        if lo <= int(r["station"]) <= hi:
            r["d"] = repr(float(r["d"]) - 0.015)
    with open(folder / "planes.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    model, corrections, data, notes = _find(folder)
    assert [c.cause for c in corrections] == ["height_step"], notes
    boundary = hi + 1 if lo == 1 else lo
    assert corrections[0].get("from_station") == boundary
    new = dict(corrections[0].corrected)["new_session"]
    assert {st.station for st in data.stations if st.session == new} == set(range(lo, hi + 1))


@pytest.mark.parametrize("sensor, station", [("stereo", 29), ("laser", 15)])
def test_two_sensors_the_knocked_one_is_named(sensor, station, tmp_path):
    """The Messor (2D laser scanner + stereo camera), 30 stations: a knock of one sensor puts the
    two in conflict; which one moved is decided by fitting each (the linear scores put a 2.3 deg knock
    of the stereo 2 stations from the end on the laser: 9979 against 9627)."""
    from graphcal.commands.simulate import run as simulate_to_folder

    folder = tmp_path / "messor"
    simulate_to_folder(robot="messor", program="random", ground="level", out_dir=folder, seed=5, n_stations=30,
                       n_sessions=1, output="planes", cloud_stride=8, progress=False,
                       effects=[("extrinsic_change", {"sensor": sensor, "station": str(station), "angle_rad": "0.04"})])
    model, corrections, data, notes = _find(folder)
    assert [c.label() for c in corrections] == [f"extrinsic_knock(from_station={station}, sensor={sensor})"], notes
    assert corrections[0].confidence > 2.0
