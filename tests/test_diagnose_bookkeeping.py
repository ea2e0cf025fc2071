"""The bookkeeping battery (issue 29): the generators do what they say, and ``graphcal diagnose``
finds the errors they hide (examples/diagnosis_bookkeeping.py; figures in docs/diagnosis.md,
"Bookkeeping battery").

Default suite: the generators on a small simulated dataset and a few battery cases. Slow
(``-m slow``): the DEVELOPMENT battery (in CI half of it: 2 cases of each kind, 10 clean; the
whole set, 4 and 20, by the example's command) against the issue's targets
(>= 95 % found at the right place with the right cause; <= 5 % false alarms on clean data), and the
BLIND battery (run once whole when the finders were merged, 2026-11-27 08:05: it meets them; in CI a
quarter of it, 1 case of each kind and 5 clean).
"""

from __future__ import annotations

import csv
import importlib.util
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from graphcal.io.dataset.read import read_dataset
from graphcal.simulation import bookkeeping as bk

ROOT = Path(__file__).resolve().parents[1]


def _battery():
    spec = importlib.util.spec_from_file_location("diagnosis_bookkeeping", ROOT / "examples" / "diagnosis_bookkeeping.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["diagnosis_bookkeeping"] = mod
    spec.loader.exec_module(mod)
    return mod


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _plane(folder: Path, station: int, sensor: str = "depth") -> dict:
    hits = [r for r in _rows(folder / "planes.csv") if int(r["station"]) == station and r["sensor"] == sensor]
    assert len(hits) == 1, (station, len(hits))
    return hits[0]


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """A small clean octopus dataset: 12 stations in 2 sessions, planes only."""
    cache = tmp_path_factory.mktemp("bk")
    return bk.simulate_base(bk.base_config("octopus", 3, n_stations=12, n_sessions=2), cache / "clean")


def test_exchange_stations_swaps_only_the_two_stations_planes(base, tmp_path):
    t = bk.exchange_stations(base, tmp_path / "x", 4, 9)
    assert t.cause == "stations_exchanged" and t.where == {"stations": [4, 9]}
    for a, b in ((4, 9), (9, 4)):
        got, want = _plane(tmp_path / "x", a), _plane(base, b)
        assert {k: v for k, v in got.items() if k != "station"} == {k: v for k, v in want.items() if k != "station"}
    for s in (1, 2, 3, 5, 12):
        assert _plane(tmp_path / "x", s) == _plane(base, s)
    assert (tmp_path / "x" / "stations.csv").read_text() == (base / "stations.csv").read_text()
    assert not (tmp_path / "x" / "truth.yaml").exists()
    read_dataset(tmp_path / "x")  # still a valid dataset


def test_mislabel_row_files_one_row_under_another_station(base, tmp_path):
    t = bk.mislabel_row(base, tmp_path / "x", 5, "depth", 7)
    assert t.where["station"] == 7 and t.where["stations"] == [5, 7] and t.corrected == {"belongs_to_station": 5}
    rows = _rows(tmp_path / "x" / "planes.csv")
    assert len(rows) == len(_rows(base / "planes.csv")) - 1
    assert not [r for r in rows if int(r["station"]) == 5]
    assert _plane(tmp_path / "x", 7)["d"] == _plane(base, 5)["d"]
    read_dataset(tmp_path / "x")


def test_exchange_legs_swaps_the_joint_columns(base, tmp_path):
    pairs = bk.leg_pairs(base, "neighbour")
    assert ("lf_foot", "lm_foot") in pairs and ("lf_foot", "rf_foot") not in pairs
    assert ("lf_foot", "rf_foot") in bk.leg_pairs(base, "mirror")
    bk.exchange_legs(base, tmp_path / "x", "lf_foot", "lm_foot")
    got, want = _rows(tmp_path / "x" / "stations.csv"), _rows(base / "stations.csv")
    for j in ("coxa", "femur", "tibia"):
        assert [r[f"q_lf_{j}_joint"] for r in got] == [r[f"q_lm_{j}_joint"] for r in want]
        assert [r[f"q_lm_{j}_joint"] for r in got] == [r[f"q_lf_{j}_joint"] for r in want]
    assert [r["q_rf_coxa_joint"] for r in got] == [r["q_rf_coxa_joint"] for r in want]
    read_dataset(tmp_path / "x")


def test_plane_edits_sign_convention_unit(base, tmp_path):
    n = np.array([float(_plane(base, 6)[c]) for c in ("nx", "ny", "nz")])
    d = float(_plane(base, 6)["d"])
    bk.flip_normal_sign(base, tmp_path / "s", 6, "depth", 1)
    p = _plane(tmp_path / "s", 6)
    assert np.allclose([float(p["nx"]), float(p["ny"]), float(p["nz"])], n * [1, -1, 1], atol=0)
    assert p["cov_11"] == _plane(base, 6)["cov_11"]  # the covariance is left as fitted
    bk.opposite_convention(base, tmp_path / "c", 6, "depth")
    p = _plane(tmp_path / "c", 6)
    assert np.allclose([float(p["nx"]), float(p["ny"]), float(p["nz"])], -n, atol=0) and float(p["d"]) == d
    t = bk.distance_unit(base, tmp_path / "u", 6, "depth", 100.0)
    assert float(_plane(tmp_path / "u", 6)["d"]) == pytest.approx(100.0 * d, rel=1e-15)
    assert t.corrected["d_corrected_m"] == d and _plane(tmp_path / "u", 7) == _plane(base, 7)


def test_reader_keeps_a_few_millimetre_distances_only_for_the_diagnosis(base, tmp_path):
    """A plane distance in mm is refused by every reader but diagnose's, which keeps a few such rows
    (at most 20 %) for the association finder to name and correct; a whole column in mm is refused."""
    from graphcal.errors import DatasetError

    bk.distance_unit(base, tmp_path / "one", 6, "depth", 1000.0)
    with pytest.raises(DatasetError, match="looks like millimetres"):
        read_dataset(tmp_path / "one")
    ds = read_dataset(tmp_path / "one", keep_unit_slips=True)
    assert ds.planes["d"].max() > 100.0
    folder = tmp_path / "all"
    shutil.copytree(base, folder)
    rows = _rows(folder / "planes.csv")
    for r in rows:
        r["d"] = repr(1000.0 * float(r["d"]))
    with open(folder / "planes.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    with pytest.raises(DatasetError, match="looks like millimetres"):
        read_dataset(folder, keep_unit_slips=True)


def test_a_far_plane_no_unit_explains_is_left_out_with_a_warning(base, tmp_path):
    """d times 137 is no unit slip: the diagnosis corrects nothing, leaves the plane out and warns
    first (calibrate refuses the file), rather than answering quietly without it."""
    from graphcal.diagnosis import diagnose

    bk.distance_unit(base, tmp_path / "odd", 6, "depth", 137.0)
    d = diagnose(tmp_path / "odd")
    assert not d.corrections
    assert any("station 6, depth" in w and "left out" in w for w in d.warnings), d.warnings
    assert (6, "depth") not in d.model.data.planes


def test_height_step_twin_differs_only_in_plane_distance(base, tmp_path):
    """The sunk twin has the same joints, IMU and commanded poses; its plane distances are shorter
    by the step (a floor plane seen from a body ``h`` lower); spliced, only the block changes."""
    cfg = bk.base_config("octopus", 3, n_stations=12, n_sessions=2)
    twin = bk.simulate_base(bk.height_step_config(cfg, 0.02), tmp_path / "twin")
    a, b = _rows(base / "stations.csv"), _rows(twin / "stations.csv")
    assert [r["session"] for r in a] == [r["session"] for r in b]
    num = [c for c in a[0] if c != "session"]
    assert np.allclose([[float(r[c]) for c in num] for r in a], [[float(r[c]) for c in num] for r in b], rtol=0, atol=1e-12)
    dd = [float(b["d"]) - float(a["d"]) for a, b in zip(_rows(base / "planes.csv"), _rows(twin / "planes.csv"))]
    assert np.allclose(dd, -0.02, atol=1.5e-3), dd
    bk.splice_stations(base, twin, tmp_path / "x", [11, 12])
    assert _plane(tmp_path / "x", 12) == _plane(twin, 12) and _plane(tmp_path / "x", 10) == _plane(base, 10)


def test_make_case_writes_truth_beside_the_folder_and_is_deterministic(tmp_path):
    a = bk.make_case("normal_sign", "qingzhui", 4, tmp_path / "cache", tmp_path / "a")
    b = bk.make_case("normal_sign", "qingzhui", 4, tmp_path / "cache", tmp_path / "b")
    assert a == b and a.cause == "normal_sign"
    assert (tmp_path / "a.truth.yaml").is_file() and not (tmp_path / "a" / "truth.yaml").exists()
    assert (tmp_path / "a" / "planes.csv").read_text() == (tmp_path / "b" / "planes.csv").read_text()


def test_scoring_rules():
    m = _battery()
    swap = {"cause": "stations_exchanged", "where": {"stations": [4, 9]}, "ambiguous": False}
    assert m.matches(swap, "stations_exchanged", {"stations": [9, 4]})
    assert not m.matches(swap, "stations_exchanged", {"stations": [4, 10]})
    assert not m.matches(swap, "station_mislabelled", {"stations": [4, 9]})
    legs = {"cause": "legs_exchanged", "where": {"legs": ["lf_foot", "lm_foot"]}}
    assert m.matches(legs, "legs_exchanged", {"legs": ["lm", "lf"]})
    assert not m.matches(legs, "legs_exchanged", {"legs": ["lf_foot", "rf_foot"]})
    knock = {"cause": "extrinsic_knock", "where": {"sensor": "depth", "from_station": 47}, "ambiguous": False}
    assert m.matches(knock, "extrinsic_change", {"sensor": "depth", "station": 47})
    assert not m.matches(knock, "extrinsic_change", {"sensor": "depth", "station": 46})
    end = {"cause": "extrinsic_knock", "where": {"sensor": "depth", "from_station": 2}, "ambiguous": True}
    doc = {"corrections": [], "findings": [{"cause": "outlier_stations", "where": {"stations": [1]}}], "notes": []}
    assert m.score(end, doc)[0] == "missed"  # an outlier finding alone does not say "or a knock"
    doc["notes"] = ["station 1: an outlier measurement of depth, or depth knocked after it; one station cannot tell"]
    assert m.score(end, doc)[0] == "noted"
    assert m.score({**end, "ambiguous": False}, doc)[0] == "missed"
    wrong = {"cause": "joint_offset", "where": {}, "alternatives": []}
    clean = {"cause": "", "where": {}}
    assert m.score(clean, {"corrections": [wrong]})[:2] == ("false_alarm", True)


# A few battery cases in the default suite (DEVELOPMENT seeds): each must be found (an ambiguous
# one -- a knock with one station before it -- honestly noted), with no confident wrong correction.
FAST_CASES = [
    (1000, "octopus", "stations_exchanged"),
    (1002, "octopus", "legs_exchanged"),
    (1003, "qingzhui", "normal_sign"),
    (1005, "qingzhui", "distance_unit"),
    (1006, "octopus", "height_step_mid"),
    (1009, "qingzhui", "knock_mid"),
    (1010, "octopus", "knock_first"),
    (1012, "octopus", "clean"),
]
#: cases the finders did not find at the last measurement (none: the millimetre slip, refused by the
#: reader until diagnose kept such rows for the association finder, is found since 2026-11-27 08:40)
FAST_MISSED: dict = {}


@pytest.mark.parametrize("seed,robot,kind", [
    pytest.param(*c, marks=pytest.mark.xfail(strict=True, reason=FAST_MISSED[c])) if c in FAST_MISSED else c
    for c in FAST_CASES])
def test_battery_case(seed, robot, kind, tmp_path):
    m = _battery()
    r = m.run_case(seed, robot, kind, tmp_path / "cache", tmp_path)
    assert r.right, (r.outcome, r.detail)
    assert not r.confident_wrong, r.detail


#: the issue's targets: found at the right place with the right cause (or, where no data can tell
#: the cause, an honest note naming the place), and false alarms on clean data
TARGET_FOUND = 0.95
TARGET_FALSE_ALARM = 0.05
#: why the DEVELOPMENT / BLIND batteries miss the targets at the last measurement ("" = they meet them)
DEV_MISS = ""  # 2026-11-27 08:40: 48/48 found or honestly noted (44 found strictly), 0/20 false alarms
BLIND_MISS = ""  # run once blind, 2026-11-27 08:05: 47/48 (97.9 %) found or honestly noted, 0/20 false alarms;
#   re-run (no longer blind) after the reader change at 08:40: 48/48, 0/20


def _xfail_if(reason: str):
    return pytest.mark.xfail(strict=True, reason=reason) if reason else []


@pytest.mark.battery
@pytest.mark.slow
@pytest.mark.parametrize("which,miss", [pytest.param("dev", DEV_MISS, marks=_xfail_if(DEV_MISS)),
                                        pytest.param("blind", BLIND_MISS, marks=_xfail_if(BLIND_MISS))])
def test_battery_meets_the_targets(which, miss, tmp_path):
    m = _battery()
    # CI time (docs: per 4, clean 20): half the development set; a quarter of the blind one (it was run
    # blind once, whole; here it guards against regressions)
    per, clean = {"dev": (2, 10), "blind": (1, 5)}[which]
    s = m.main(which, per=per, clean=clean, jobs=1, cache=tmp_path / "cache", verbose=False)
    assert s["errors"] == 0, [r.detail for r in s["results"] if r.outcome == "error"]
    assert s["right"] >= TARGET_FOUND, s["per_kind"]
    assert s["false_alarm"] <= TARGET_FALSE_ALARM, [r.detail for r in s["results"] if r.outcome == "false_alarm"]
