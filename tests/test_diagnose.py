"""graphcal diagnose: the hidden-effect battery (examples/diagnosis_battery.py), the command and its files.

The battery simulates 50 datasets (5 per cause of the ten), each hiding one catalogued effect drawn
from its seed at a realistic magnitude and location on two robots, plus 6 clean datasets; ``diagnose`` reads only the
dataset folder, never truth.yaml. Each case asserts the named cause, its location and that its
parameters lie within 3 sigma of the truth; the battery asserts >= 95 % top-1 and <= 5 % false alarms.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))

import diagnosis_battery  # noqa: E402

PER_CAUSE = 5
CLEAN = 6
CASES = diagnosis_battery.cases(PER_CAUSE, CLEAN)


@pytest.fixture(scope="module")
def battery():
    out = diagnosis_battery.main(per_cause=PER_CAUSE, clean=CLEAN, jobs=2, verbose=True)
    return out


def test_battery_covers_the_catalogue_on_two_robots():
    effect = [c for c in CASES if c[2] != "clean"]
    assert len(effect) >= 50
    assert {c[2] for c in effect} == set(diagnosis_battery.CAUSES)
    assert len({c[1] for c in CASES}) >= 2
    assert sum(c[2] == "clean" for c in CASES) >= 5


#: battery cases diagnose is known to get wrong (docs/diagnosis.md): strict, so a fix shows up
KNOWN_MISSES = {(147, "qingzhui", "outlier_stations"):
                "three outlier stations: an extrinsic change is named first, then the outliers, with no "
                "warning (outlier findings are exempt from the held-out test; measured 49/50 on the battery)"}


@pytest.mark.battery
@pytest.mark.slow
@pytest.mark.parametrize("k", range(len(CASES)), ids=[f"{s}-{r}-{c}" for s, r, c in CASES])
def test_battery_case(battery, k, request):
    if CASES[k] in KNOWN_MISSES:
        request.applymarker(pytest.mark.xfail(reason=KNOWN_MISSES[CASES[k]], strict=True))
    r = battery["results"][k]
    assert (r.seed, r.robot, r.hidden) == CASES[k]
    assert r.passed, f"{r.hidden} on {r.robot} (seed {r.seed}): named {r.named or 'nothing'}; {r.detail}"


@pytest.mark.battery
@pytest.mark.slow
def test_battery_targets(battery):
    print(f"\nbattery: top-1 {battery['top1']:.1%}, all checks {battery['passed']:.1%}, "
          f"false alarms {battery['false_alarm']:.1%}")
    assert battery["top1"] >= 0.95
    assert battery["false_alarm"] <= 0.05
    # the final model of a right diagnosis fits when judged as calibrate judges (measured 55 of 55)
    assert battery["final_fits"] >= 0.98


@pytest.mark.battery
@pytest.mark.slow
def test_clean_data_leave_no_unexplained_structure(battery):
    clean = [r for r in battery["results"] if r.hidden == "clean"]
    assert clean and not any(r.unexplained for r in clean)


# ----------------------------------------------------------------------------- command and files
@pytest.fixture(scope="module")
def knocked(tmp_path_factory):
    from graphcal.commands.simulate import run as simulate_to_folder

    out = tmp_path_factory.mktemp("diag") / "knocked"
    simulate_to_folder(robot="octopus", program="random", ground="level", out_dir=out, seed=7, n_stations=30,
                       n_sessions=2, output="planes", cloud_stride=8, progress=False,
                       effects=[("extrinsic_change", {"sensor": "depth", "station": "16", "angle_rad": "0.035"})])
    return out


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "graphcal.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=ROOT)


@pytest.mark.slow
def test_cli_writes_the_diagnosis(knocked, tmp_path):
    out = tmp_path / "dg"
    p = _cli("diagnose", knocked, "--out", out, "--quiet")
    assert p.returncode == 0, p.stderr
    assert "found extrinsic_change" in p.stdout
    doc = json.loads((out / "diagnosis.json").read_text())
    assert doc["format"] == "graphcal-diagnosis/1"
    assert set(doc["nominal"]) >= {"normal_rms_deg", "distance_rms_mm", "chi2_per_dof"}
    f = doc["findings"][0]
    assert f["cause"] == "extrinsic_change" and f["where"] == {"sensor": "depth", "station": 16}
    assert abs(f["parameters"]["angle_rad"] - 0.035) < 3 * f["sigma"]["angle_rad"] + 1e-9
    assert set(f["evidence"]) >= {"test", "statistic", "dof", "p_value", "delta_bic"}
    assert f["evidence"]["dof"] == 6 and f["evidence"]["p_value"] < 1e-6
    assert f["gain"]["heldout_rms_after"] < f["gain"]["heldout_rms_before"]
    assert f["gain"]["relative"] == pytest.approx(f["gain"]["heldout_rms_after"] / f["gain"]["heldout_rms_before"])
    assert doc["unexplained_structure"] is False
    assert "depth" in doc["extended_calibration"]["sensors"]
    page = (out / "report.html").read_text()
    assert "extrinsic_change" in page and page.count("data:image/png;base64,") >= 1
    from graphcal.report.page import CSS

    assert CSS in page  # the one page template and style sheet of every report
    # a previous diagnosis is replaced; anything else is refused and left alone
    assert _cli("diagnose", knocked, "--out", out, "--quiet").returncode == 0
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    p = _cli("diagnose", knocked, "--out", foreign, "--quiet")
    assert p.returncode == 2 and "holds no graphcal diagnosis" in p.stderr
    assert (foreign / "notes.txt").read_text() == "keep me" and len(list(foreign.iterdir())) == 1


def test_cli_bad_dataset_is_one_line(tmp_path):
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "dataset.yaml").write_text("format: graphcal-dataset/1\nrobot: {model: octopus}\n")
    p = _cli("diagnose", bad, "--out", tmp_path / "o")
    assert p.returncode == 2
    assert p.stderr.startswith("graphcal diagnose: error:") and "Traceback" not in p.stderr
    assert not (tmp_path / "o").exists()


def test_the_last_progress_line_of_a_finding_gives_its_final_estimate(knocked, caplog):
    """A finding is re-read in the final model (later findings and the noise re-learned move it);
    progress (logged, INFO) ends with the numbers the report gives, not those of the moment it was found."""
    import logging

    from graphcal.diagnosis.diagnose import _params_text, diagnose

    with caplog.at_level(logging.INFO, logger="graphcal"):
        result = diagnose(knocked, progress=True, heldout=False)
    lines = [r.getMessage() for r in caplog.records]
    for f in result.findings:
        said = [ln for ln in lines if f.candidate.label() in ln and "sigma" in ln]
        assert said and said[-1].endswith(f"{_params_text(f.parameters)} (sigma {_params_text(f.sigma)})")


@pytest.fixture(scope="module")
def knee_flipped(tmp_path_factory):
    """One knee column of the wrong sign (an audit's mistake with its own hexapod)."""
    import csv
    import shutil

    from graphcal.commands.simulate import run as simulate_to_folder

    root = tmp_path_factory.mktemp("diagflip")
    clean = root / "clean"
    simulate_to_folder(robot="octopus", program="random", ground="level", out_dir=clean, seed=7, n_stations=30,
                       n_sessions=2, output="planes", cloud_stride=8, progress=False)
    out = root / "flipped"
    shutil.copytree(clean, out)
    rows = list(csv.reader((out / "stations.csv").open(newline="")))
    c = rows[0].index("q_rf_tibia_joint")
    for r in rows[1:]:
        r[c] = repr(-float(r[c]))
    with (out / "stations.csv").open("w", newline="") as f:
        csv.writer(f).writerows(rows)
    return out


def test_wrong_data_are_not_named_as_a_kinematic_error(knee_flipped):
    """A sign-flipped knee fits best as the femur 229 mm shorter (a 100 mm link): that is wrong data,
    not a link length; it is not named, the diagnosis says structure remains, and a finding that
    does not predict held-out stations better carries a note saying so."""
    from graphcal.diagnosis.diagnose import MAX_LINK_CHANGE_SHARE, diagnose, implausible_size

    result = diagnose(knee_flipped)
    for f in result.findings:
        assert not implausible_size(f.candidate, f.parameters, result.model.robot), f.candidate.label()
    assert any(f"more than {MAX_LINK_CHANGE_SHARE:.0%} of the" in n for n in result.notes)
    assert result.unexplained_structure
    weak = [f for f in result.findings if f.gain is not None and f.gain.heldout_rms_after >= f.gain.heldout_rms_before]
    for f in weak:
        assert any(f.candidate.label() in n and "does not predict held-out" in n for n in result.notes)


@pytest.fixture(scope="module")
def outliers(tmp_path_factory):
    """bench/diagnose_speed.py's outlier dataset: three outlier stations (14, 44, 48; statistics
    ~3400, ~1500 and ~250 at the nominal fit), 48 stations in 3 sessions."""
    return _outlier_dataset(tmp_path_factory, 206)


def _outlier_dataset(tmp_path_factory, seed: int) -> Path:
    from graphcal.commands.simulate import run as simulate_to_folder

    out = tmp_path_factory.mktemp("outliers") / f"outliers_{seed}"
    simulate_to_folder(robot="octopus", program="random", ground="level", out_dir=out, seed=seed, n_stations=48,
                       n_sessions=3, output="planes", cloud_stride=8, progress=False,
                       effects=[("outlier_stations", {})], session_heading_step_deg=40.0)
    return out


def test_once_outlier_stations_are_named_the_noise_is_learned_again_and_the_final_model_fits(outliers):
    """The nominal noise was learned with three outlier stations in (the stance contact sigma at tens
    of mm): one bounded update after naming them drove the joints' noise to its floor (1e-6 rad) and
    the final model read x2.0-2.2 its physical stance noise ("does not fit"). Learned again from the
    defaults once they are named, the final model fits at the search's own noise (stance feet x0.6),
    with no re-check."""
    from graphcal.calibration.noise_estimation import VCE_FLOOR
    from graphcal.diagnosis import diagnose
    from graphcal.report.diagnosis_json import diagnosis_to_dict

    d = diagnose(outliers)
    assert [f.candidate.cause for f in d.findings] == ["outlier_stations"]
    assert d.model.options.sigma_joint_rad > 100 * VCE_FLOOR["sigma_joint_rad"]
    a = diagnosis_to_dict(d)["adequacy"]
    assert a["verdict"] == "fits", a
    assert a["model"] == "final (extended)"  # judged at the search's noise: no re-check was needed
    assert a["groups"]["stance_foot"]["ratio"] < 1.0


@pytest.fixture(scope="module")
def outliers_imu(tmp_path_factory):
    """Outlier stations (30, 43, 45) on a dataset whose IMU reads x1.6 its physical noise with its
    mounting held at the prior, as the search holds it (octopus seed 230)."""
    return _outlier_dataset(tmp_path_factory, 230)


def test_a_final_model_that_fails_at_the_search_noise_is_judged_again_as_calibrate_judges(outliers_imu):
    """The search holds the IMU's noise and mounting: there the final model's IMU group fails (x1.6).
    Judged again with every noise group learned from the defaults and the IMU mounting estimated,
    as calibrate does, it fits; diagnosis.json says which model was judged."""
    from graphcal.calibration.calibrate import adequacy_at
    from graphcal.diagnosis import diagnose
    from graphcal.report.diagnosis_json import diagnosis_to_dict

    d = diagnose(outliers_imu)
    assert [f.candidate.cause for f in d.findings] == ["outlier_stations"]
    held = adequacy_at(d.model.ds, d.model.options, d.problem, d.values)
    assert held.verdict == "does not fit"
    assert [g.group for g in held.groups if g.misfit] == ["imu"]
    a = diagnosis_to_dict(d)["adequacy"]
    assert a["verdict"] == "fits", a
    assert "learned from graphcal's defaults and the IMU mounting estimated" in a["model"]
    assert a["groups"]["imu"]["ratio"] < 1.5


def test_the_diagnosis_fits_end_within_a_twentieth_of_the_smallest_chi2_difference_read(outliers):
    """The nominal model at physical noise with the three outliers in, from the final model's
    solution (chi-square 4.5e5: the fit the joint-column finder and the verdicts read): diagnose's
    solve, which stops on SOLVE_CHI2_TOL or SOLVE_REL_TOL of the chi-square, ends within a
    twentieth of the smallest chi-square difference a decision reads (the segments finder's 2) of
    the fit taken on to calibrate's relative 1e-9; and a step's tolerance there is within a
    twentieth of the joint-column finder's margin (25)."""
    import dataclasses

    from graphcal.diagnosis import diagnose
    from graphcal.diagnosis.joint_columns import MIN_CONFIDENCE as JC_MARGIN
    from graphcal.diagnosis.model import SOLVE_CHI2_TOL, SOLVE_REL_TOL, chi2_of, model_options
    from graphcal.diagnosis.segments import MIN_CONFIDENCE
    from graphcal.solvers.batch import solve_lm

    d = diagnose(outliers)
    phys = dataclasses.replace(d.model, options=model_options(d.model.ds), findings=())
    problem, values = phys.solve(initial=d.values)
    full = solve_lm(problem.graph, values, check_determined=False).values
    chi2 = chi2_of(problem, values)[0]
    gap = chi2 - chi2_of(problem, full)[0]
    assert SOLVE_CHI2_TOL <= MIN_CONFIDENCE / 100
    assert 1e5 < chi2 and SOLVE_REL_TOL * chi2 <= JC_MARGIN / 20
    # measured 0.043 (2.6 with an absolute tolerance of 50, 2.56 with a relative one of 1e-4)
    assert -1e-6 <= gap <= MIN_CONFIDENCE / 20


def test_three_outlier_stations_are_named_in_one_round_and_no_knock_is_fitted(outliers, monkeypatch, caplog):
    """The outliers' statistics differ by 14x (~3400 to ~250): with the gross one free, the others
    are tested given it (forward selection in one linearisation), so one round names all three
    (three rounds before); and the segments finder, whose strongest knock scores 0.19 of the
    outliers' statistic linearly, fits no knock: even raised by segments.KNOCK_GAIN_BOUND it loses."""
    import logging

    import yaml

    import graphcal.diagnosis.segments as segments
    from graphcal.diagnosis import diagnose

    def no_fit(*args, **kwargs):
        raise AssertionError("a knock was fitted")

    monkeypatch.setattr(segments, "_refit_knocks", no_fit)
    truth = yaml.safe_load((outliers / "truth.yaml").read_text())["effects"]["outlier_stations"]["stations"]
    with caplog.at_level(logging.INFO, logger="graphcal.diagnosis.diagnose"):
        d = diagnose(outliers, progress=True)
    assert [f.candidate.label() for f in d.findings] == [f"outlier_stations(stations={sorted(truth)})"]
    assert len(d.screening) == 2  # the round that names them and the one that finds nothing more
    assert any("is explained better by outlier_measurement" in r.getMessage() and "no knock can win" in r.getMessage()
               for r in caplog.records)


def test_no_grid_of_knocks_is_fitted_when_even_its_bound_loses_to_the_outliers(tmp_path_factory, monkeypatch):
    """Outliers at stations 15, 26 and the last, 48 (octopus seed 228): the strongest knocks fitted
    (a knock at the last station is the outlier there) explain over half of what the outliers do, so
    the grid of places was fitted too (25 knock fits, 1.2 s); raised by GRID_GAIN_BOUND, as far as
    the grid ever raised a knock, the best still loses by BIC, so the grid is skipped. The answer is
    the same: one station at the end cannot tell a knock from an outlier, and the loop names the
    three outliers."""
    import graphcal.diagnosis.model as model_module
    from graphcal.diagnosis import diagnose
    from graphcal.diagnosis.segments import REFIT_KNOCKS

    path = _outlier_dataset(tmp_path_factory, 228)
    knocks = []
    with_finding = model_module.DiagnosisModel.with_finding

    def counted(self, candidate):
        if candidate.cause == "extrinsic_change":
            knocks.append(candidate)
        return with_finding(self, candidate)

    monkeypatch.setattr(model_module.DiagnosisModel, "with_finding", counted)
    d = diagnose(path)
    assert [f.candidate.label() for f in d.findings] == ["outlier_stations(stations=[15, 26, 48])"]
    assert any("station 48: an outlier measurement of depth, or depth knocked at it" in n for n in d.notes)
    assert 0 < len(knocks) <= REFIT_KNOCKS + 3  # the strongest and the best's neighbours; no grid of 16


def test_a_knock_fit_that_does_not_converge_is_said_and_its_chi_square_was_an_upper_bound(tmp_path_factory,
                                                                                         monkeypatch, caplog):
    """Octopus seed 228 (outliers at 15, 26 and the last station, 48): the knock fitted at station 47,
    whose extrinsic after it only two stations' planes see, still lowers its chi-square after
    model.SOLVE_MAX_STEPS Levenberg-Marquardt steps. That fit is marked stalled, said in a progress
    line, and the diagnosis notes say its chi-square is an upper bound; taken on from where it
    stopped, the fit does lower its chi-square (the mark is not a false alarm). The knock at 48,
    which converges, is not named in that note."""
    import logging

    import graphcal.diagnosis.model as model_module
    from graphcal.diagnosis import diagnose
    from graphcal.solvers.batch import solve_lm

    path = _outlier_dataset(tmp_path_factory, 228)
    fits = []
    fit = model_module.DiagnosisModel.fit

    def kept(self, **kwargs):
        out = fit(self, **kwargs)
        fits.append(out)
        return out

    monkeypatch.setattr(model_module.DiagnosisModel, "fit", kept)
    with caplog.at_level(logging.INFO, logger="graphcal.diagnosis.model"):
        d = diagnose(path)
    said = [n for n in d.notes if "without converging" in n]
    assert len(said) == 1 and "extrinsic_knock(sensor=depth, from_station=47)" in said[0], d.notes
    assert "from_station=48)" not in said[0].split("(best")[0]
    assert sum("without converging" in r.getMessage() for r in caplog.records) == 1
    stalled = [f for f in fits if f.stalled]
    assert len(stalled) == 1 and stalled[0].steps == model_module.SOLVE_MAX_STEPS
    graph = stalled[0].problem.graph
    on = solve_lm(graph, stalled[0].values, check_determined=False, absolute_tol=model_module.SOLVE_CHI2_TOL / 2)
    # gtsam's error is chi2 / 2: the fit taken on lowers the chi-square by more than 10 tolerances
    assert 2 * (graph.error(stalled[0].values) - on.error_final) > 10 * model_module.SOLVE_CHI2_TOL
    assert not any(f.stalled for f in fits if f is not stalled[0])


def test_forward_selection_tests_a_station_given_the_gross_outlier():
    """A mean fitted to ten rows, one of them 100 sigma off: alone, every other row fails its test
    (the outlier pulls the mean by 10 sigma); given the outlier freed, none does."""
    import numpy as np

    from graphcal.diagnosis.scores import LinearSystem, freed_rows_test

    b = np.zeros(10)
    b[0] = 100.0
    b -= b.mean()  # the whitened residual at the fitted mean (the score test's linearisation point)
    system = LinearSystem(np.ones((10, 1)), b, {0: (0, 1)}, np.arange(10), np.arange(10), {}, {},
                          np.array([], dtype=int))
    test = freed_rows_test(system, [])
    alone, dof = test([3])
    assert dof == 1 and alone > 100.0  # (10 sigma)^2 / (1 - 1/10): far beyond any threshold
    gross, _ = test([0])
    both, dof2 = test([0, 3])
    assert dof2 == 2 and gross > 8000.0 and abs(both - gross) < 1e-6


def test_outlier_stations_do_not_open_the_joint_column_search(tmp_path_factory, monkeypatch):
    """Octopus seed 218: at physical noise the three outliers pull every station's stance feet, and
    the plain gate opens (the middle legs 2.0x the third's chi-square, 75th percentile 1 128 >= 1 000):
    17 exchanged-leg refits (2.5 s) that corrected nothing. With the sensors' rows weighted out the
    stance feet fit (percentile below 0.5): two solves, no hypothesis refitted, the outliers named."""
    import graphcal.diagnosis.joint_columns as jc
    from graphcal.diagnosis import diagnose

    fits = []
    fit = jc._fit

    def counted(phys, data, legs=(), *args, **kwargs):
        fits.append(tuple(legs))
        return fit(phys, data, legs, *args, **kwargs)

    monkeypatch.setattr(jc, "_fit", counted)
    gate = []
    percentile = jc._kinematic_percentile
    monkeypatch.setattr(jc, "_kinematic_percentile", lambda *a: gate.append(percentile(*a)) or gate[-1])
    d = diagnose(_outlier_dataset(tmp_path_factory, 218))
    assert [f.candidate.cause for f in d.findings] == ["outlier_stations"]
    assert d.corrections == ()
    assert len(gate) == 1 and gate[0] < 1.0 < jc.MIN_LEG_CHI2
    assert fits == [(), ()]  # the data as given, and with the sensors weighted out: no exchange tried
