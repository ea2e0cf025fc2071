"""Two legs' joint columns exchanged in the logger (issue 29; graphcal/diagnosis/joint_columns.py).

Datasets: two simulated hexapods (octopus, qingzhui), 30 stations in 2 sessions; the fault is made
in stations.csv (the q columns of two legs exchanged, as a logger would), never through the
finder's own code. The finder must name the two legs (adjacent and opposite), find nothing on the
clean data, and leave ``diagnose`` naming no joint offsets afterwards.
"""

from __future__ import annotations

import csv
import shutil

import numpy as np
import pytest


def _simulate(root, robot):
    from graphcal.commands.simulate import run as simulate_to_folder

    out = root / f"clean_{robot}"
    simulate_to_folder(robot=robot, program="random", ground="level", out_dir=out, seed=7, n_stations=30,
                       n_sessions=2, output="planes", cloud_stride=8, progress=False)
    return out


def _exchanged(clean, out, a, b, sign=1.0, from_row=0, to_row=None):
    """A copy of ``clean`` with the q columns of legs ``a`` and ``b`` exchanged in stations.csv
    (times ``sign``), from data row ``from_row`` on, up to (not including) ``to_row``."""
    shutil.copytree(clean, out)
    rows = list(csv.reader((out / "stations.csv").open(newline="")))
    ca = [i for i, n in enumerate(rows[0]) if n.startswith(f"q_{a}_")]
    cb = [i for i, n in enumerate(rows[0]) if n.startswith(f"q_{b}_")]
    assert len(ca) == len(cb) == 3
    for r in rows[1 + from_row:None if to_row is None else 1 + to_row]:
        va, vb = [r[i] for i in ca], [r[i] for i in cb]
        for i, v in zip(ca, vb):
            r[i] = repr(sign * float(v))
        for i, v in zip(cb, va):
            r[i] = repr(sign * float(v))
    with (out / "stations.csv").open("w", newline="") as f:
        csv.writer(f).writerows(rows)
    return out


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    root = tmp_path_factory.mktemp("legs")
    return {robot: _simulate(root, robot) for robot in ("octopus", "qingzhui")}


def _nominal(folder):
    from graphcal.calibration.measurements import calibration_data
    from graphcal.diagnosis.model import DiagnosisModel, model_options
    from graphcal.io.dataset import load_dataset_robot, read_dataset

    ds = read_dataset(folder)
    robot = load_dataset_robot(ds)
    return DiagnosisModel(ds, robot, calibration_data(ds, robot), model_options(ds)).learn_noise()[0]


def _find(folder):
    from graphcal.diagnosis.joint_columns import find_joint_columns

    model = _nominal(folder)
    corrections, data, notes = find_joint_columns(model, lambda msg: None)
    return model, corrections, data, notes


@pytest.mark.parametrize("robot", ["octopus", "qingzhui"])
def test_clean_data_cost_nothing_and_find_nothing(clean, robot):
    model, corrections, data, notes = _find(clean[robot])
    assert corrections == () and notes == ()
    assert data is model.data


@pytest.mark.parametrize("robot, a, b, sign, from_row, to_row", [
    ("octopus", "lf", "lm", 1.0, 0, None),  # adjacent legs, one side
    ("qingzhui", "lf", "rf", 1.0, 0, None),  # opposite legs
    ("octopus", "lm", "rr", 1.0, 17, None),  # from station 18 on
    ("qingzhui", "lf", "lb", 1.0, 0, 12),  # before station 13
    ("qingzhui", "mf", "rb", -1.0, 0, None),  # a mirrored convention: every exchanged angle negated
], ids=["octopus-adjacent", "qingzhui-opposite", "octopus-from-18", "qingzhui-before-13", "qingzhui-mirrored"])
def test_exchanged_legs_are_found_and_corrected(clean, tmp_path, robot, a, b, sign, from_row, to_row):
    from graphcal.diagnosis.joint_columns import MIN_CONFIDENCE

    folder = _exchanged(clean[robot], tmp_path / "x", a, b, sign, from_row, to_row)
    model, corrections, data, notes = _find(folder)
    assert len(corrections) == 1, notes
    c = corrections[0]
    assert c.cause == "legs_exchanged"
    assert set(c.get("legs")) == {f"{a}_foot", f"{b}_foot"}
    assert c.get("from_station") == (None if from_row == 0 else from_row + 1)
    assert c.get("until_station") == (None if to_row is None else to_row + 1)
    assert dict(c.corrected)["signs"] == (int(sign),) * 3
    assert c.confidence >= MIN_CONFIDENCE and c.p_value < 1e-6 and c.statistic > 1e3
    assert dict(c.corrected)["chi2_per_dof_corrected"] < 1.0
    # the corrected joint angles are the clean ones
    ref = _nominal(clean[robot]).data
    for s0, s1 in zip(ref.stations, data.stations):
        for f in s0.q_by_foot:
            np.testing.assert_allclose(s1.q_by_foot[f], s0.q_by_foot[f], atol=1e-12)
    # the model's own data are not changed: the exchanged row still holds the other leg's angles
    row = model.data.stations[from_row].q_by_foot
    assert data is not model.data and not np.allclose(row[f"{a}_foot"], ref.stations[from_row].q_by_foot[f"{a}_foot"])


def test_a_hypothesis_fit_that_runs_out_of_steps_is_said(clean, tmp_path, monkeypatch):
    """Legs lf and lm exchanged (octopus). Every hypothesis fit converges: no note. With the fits cut
    to one Levenberg-Marquardt step (model.SOLVE_MAX_STEPS), they stop before converging: their
    chi-squares are upper bounds, and one note says the hypotheses' ranking is not final."""
    import graphcal.diagnosis.model as model_module
    from graphcal.diagnosis.joint_columns import find_joint_columns

    folder = _exchanged(clean["octopus"], tmp_path / "x", "lf", "lm")
    model = _nominal(folder)
    corrections, _, notes = find_joint_columns(model, lambda msg: None)
    assert len(corrections) == 1 and not any("without converging" in n for n in notes)
    monkeypatch.setattr(model_module, "SOLVE_MAX_STEPS", 1)
    _, _, notes = find_joint_columns(_nominal(folder), lambda msg: None)
    said = [n for n in notes if "without converging" in n]
    assert len(said) == 1 and "stopped after 1 Levenberg-Marquardt steps" in said[0]
    assert "legs lf_foot and lm_foot exchanged" in said[0] and "not final" in said[0]


def test_an_exchange_beside_outlier_stations_is_judged_with_the_sensors_weighted_out(tmp_path):
    """Legs lf and lm exchanged on top of three outlier stations (octopus seed 218, 48 stations). At
    physical noise the outliers keep the exchange from fitting, and the two legs' joint offsets and
    link lengths freed explained the data as well (stop 38: not corrected, two coxa offsets named
    tentatively, answer neither). With the sensors weighted out the exchange fits and beats the
    freed legs by far: it is corrected, and the diagnosis names the outliers, nothing else."""
    import yaml

    from graphcal.commands.simulate import run as simulate_to_folder
    from graphcal.diagnosis import diagnose
    from graphcal.report.diagnosis_json import diagnosis_to_dict

    src = tmp_path / "outliers"
    simulate_to_folder(robot="octopus", program="random", ground="level", out_dir=src, seed=218, n_stations=48,
                       n_sessions=3, output="planes", cloud_stride=8, progress=False,
                       effects=[("outlier_stations", {})], session_heading_step_deg=40.0)
    truth = yaml.safe_load((src / "truth.yaml").read_text())["effects"]["outlier_stations"]["stations"]
    d = diagnose(_exchanged(src, tmp_path / "x", "lf", "lm"))
    assert [c.cause for c in d.corrections] == ["legs_exchanged"]
    c = d.corrections[0]
    assert set(c.get("legs")) == {"lf_foot", "lm_foot"} and dict(c.corrected)["signs"] == (1, 1, 1)
    assert "with the sensors weighted out it fits" in c.note
    assert [f.candidate.label() for f in d.findings] == [f"outlier_stations(stations={sorted(truth)})"]
    assert diagnosis_to_dict(d)["answer"] == "corrected"


def test_an_exchange_beside_another_cause_is_still_corrected(tmp_path):
    """An extrinsic knock left in the data: the exchange does not fit at physical noise, but it beats
    the two legs' joint offsets and link lengths freed by far, so it is corrected (without that
    comparison it was a note, and diagnose named two coxa offsets)."""
    from graphcal.commands.simulate import run as simulate_to_folder
    from graphcal.diagnosis.joint_columns import MIN_CONFIDENCE

    knocked = tmp_path / "knocked"
    simulate_to_folder(robot="octopus", program="random", ground="level", out_dir=knocked, seed=7, n_stations=30,
                       n_sessions=2, output="planes", cloud_stride=8, progress=False,
                       effects=[("extrinsic_change", {"sensor": "depth", "station": "16", "angle_rad": "0.1"})])
    _, corrections, _, notes = _find(_exchanged(knocked, tmp_path / "x", "lf", "rf"))
    assert len(corrections) == 1, notes
    c = corrections[0]
    assert c.get("legs") == ("lf_foot", "rf_foot") and c.get("from_station") is None
    got = dict(c.corrected)
    assert got["chi2_per_dof_corrected"] > 1.5  # the knock is still in the data
    assert got["chi2_legs_free"] > c.statistic / 100 + MIN_CONFIDENCE


def test_a_leg_of_another_joint_count_is_no_candidate(clean):
    from graphcal.diagnosis.joint_columns import candidate_pairs

    data = _nominal(clean["octopus"]).data
    stations = tuple(type(st)(st.station, st.session, {**st.q_by_foot, "lf_foot": st.q_by_foot["lf_foot"][:2]},
                              st.T_world_body_cmd, st.imu_accel) for st in data.stations)
    worst = {(data.stations[0].station, f): c for f, c in (("lf_foot", 9.0), ("lm_foot", 8.0), ("rr_foot", 7.0))}
    pairs = candidate_pairs(type(data)(stations, data.planes, data.scan_points, data.sensor_types), worst)
    assert pairs and all("lf_foot" not in p for p in pairs)
    assert candidate_pairs(data, worst)[0] == ("lf_foot", "lm_foot")


def test_diagnose_then_names_no_joint_offset(clean, tmp_path):
    """Without the finder the exchange became two coxa offsets of about +-66 deg (measured); with it
    the correction is reported in diagnosis.json and nothing else is found."""
    from graphcal.diagnosis.diagnose import diagnose
    from graphcal.report.diagnosis_json import diagnosis_to_dict

    folder = _exchanged(clean["octopus"], tmp_path / "x", "lf", "lm")
    result = diagnose(folder, heldout=False)
    out = diagnosis_to_dict(result)
    assert [c["cause"] for c in out["corrections"]] == ["legs_exchanged"]
    assert sorted(out["corrections"][0]["where"]["legs"]) == ["lf_foot", "lm_foot"]
    assert not [f for f in result.findings if f.candidate.cause in ("joint_offset", "link_length")]
    assert not result.findings


# ----------------------------------------------------------------------------- identify-legs: exchanged marker ids
@pytest.fixture(scope="module")
def four_feet():
    """A simulated A1 with a marker on each of its four feet, 100 samples (legs in the air)."""
    from graphcal.legs.mocap_data import mocap_data_from_dataset
    from graphcal.simulation.mocap import simulate_mocap

    sim = simulate_mocap("a1", feet=("fl_foot", "fr_foot", "rl_foot", "rr_foot"), n_samples=100,
                         joint_noise_rad=np.radians(0.1), marker_noise_m=0.0005, noise="gaussian", body_markers=False,
                         seed=8)
    return mocap_data_from_dataset(sim.dataset)


@pytest.mark.parametrize("pair", [None, ("fr_foot", "rl_foot")], ids=["clean", "fr-rl"])
def test_exchanged_marker_ids_are_found(four_feet, pair):
    """Exchanged ids of two feet's markers: identified without the finder the legs take offsets of
    0.2-1.6 rad and do not fit; with it, the exchange is named and the legs identified from the
    corrected markers fit. Clean: nothing searched, nothing said."""
    from graphcal.legs.identify import IdentifyOptions, identify_legs
    from graphcal.legs.marker_ids import MIN_CONFIDENCE, exchange_markers, find_exchanged_markers

    data = four_feet
    opts = IdentifyOptions(sigma_marker_m=0.0005, sigma_joint_rad=np.radians(0.1))

    def run(tracks):
        return identify_legs(data.robot, tracks, options=opts, T_body_mocap_nominal=data.T_body_mocap_nominal,
                             frame=data.frame)

    tracks = data.tracks if pair is None else exchange_markers(data.tracks, *pair)
    given = run(tracks)
    found, result, notes = find_exchanged_markers(given, tracks, run)
    assert not notes
    if pair is None:
        assert found is None and result is given and given.adequacy.fits
        return
    assert not given.adequacy.fits
    assert found is not None and found.markers == pair and found.feet == pair
    assert found.evidence.confidence >= MIN_CONFIDENCE and found.evidence.chi2_corrected < 1e-3 * found.evidence.chi2_given
    assert result.adequacy.fits and any("exchanged" in w for w in result.warnings)
    for foot in pair:
        assert max(abs(p.value) for p in result.legs[foot] if p.name.endswith("offset_rad")) < np.radians(1.0)


def test_identify_legs_dataset_corrects_exchanged_marker_ids(four_feet):
    import dataclasses

    from graphcal.legs.identify import IdentifyOptions, identify_legs_dataset
    from graphcal.legs.marker_ids import exchange_markers

    data = dataclasses.replace(four_feet, tracks=exchange_markers(four_feet.tracks, "fl_foot", "rl_foot"))
    options = IdentifyOptions(sigma_marker_m=0.0005, sigma_joint_rad=np.radians(0.1))
    result = identify_legs_dataset(data, options=options)
    assert result.adequacy.fits
    assert [w for w in result.warnings if "markers fl_foot (fl_foot) and rl_foot (rl_foot) are exchanged" in w]


@pytest.mark.parametrize("rows", [(3, 4), (0, 99)], ids=["neighbours", "first-last"])
def test_exchanged_postures_are_found(four_feet, rows):
    """Two postures' motion-capture samples exchanged (each posture's joint angles with the other's
    markers): flagged by the per-posture outlier test, then named and corrected through
    identify_legs_dataset."""
    import dataclasses

    from graphcal.legs.identify import IdentifyOptions, identify_legs_dataset
    from graphcal.legs.marker_ids import exchange_postures

    t = four_feet.tracks[0].time
    data = dataclasses.replace(four_feet, tracks=exchange_postures(four_feet.tracks, t[rows[0]], t[rows[1]]))
    options = IdentifyOptions(sigma_marker_m=0.0005, sigma_joint_rad=np.radians(0.1))
    result = identify_legs_dataset(data, options=options)
    assert result.adequacy.fits
    said = [w for w in result.warnings if "are exchanged (each posture's joint angles" in w]
    assert len(said) == 1 and f"{t[rows[0]]:g} s and {t[rows[1]]:g} s" in said[0]


def test_an_exchange_of_labels_is_applied_only_when_it_fits_and_wins_clearly():
    """The rule both label finders (marker ids, postures) share: the data as given best, nothing; the
    best exchange within MIN_CONFIDENCE of the runner-up, or not fitting (sigma0 above MAX_SIGMA0),
    a note and nothing applied; else the exchange, its margin and the hypotheses close to it."""
    from types import SimpleNamespace

    from graphcal.legs.marker_ids import MAX_SIGMA0, MIN_CONFIDENCE, _best_exchange

    def ident(sigma0):
        return SimpleNamespace(adequacy=SimpleNamespace(fits=False, sigma0=sigma0))

    given = ("the data as given", 5000.0, ident(40.0), None)
    assert _best_exchange([given, ("x", 6000.0, ident(45.0), ("a", "b"))], "w") == (None, None)
    close = [given, ("a-b", 100.0, ident(1.0), ("a", "b")), ("a-c", 100.0 + MIN_CONFIDENCE - 1, ident(1.0), ("a", "c"))]
    best, note = _best_exchange(close, "the markers' errors")
    assert best is None and "a-c explains the data almost as well (chi-square 24.0 apart)" in note
    assert note.startswith("a-b is the best explanation tried of the markers' errors (chi-square 5000 -> 100 ")
    best, note = _best_exchange([given, ("a-b", 900.0, ident(MAX_SIGMA0 + 1), ("a", "b"))], "w")
    assert best is None and "the legs still do not fit after it" in note
    clear = [given, ("a-b", 100.0, ident(1.0), ("a", "b")), ("a-c", 110.0 + MIN_CONFIDENCE, ident(1.0), ("a", "c"))]
    best, note = _best_exchange(clear, "w")
    assert note is None and best[2] == ("a", "b") and best[3] == MIN_CONFIDENCE + 10.0 and best[4] == ()
    assert best[5] == "a-c"
