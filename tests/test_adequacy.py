"""calibrate's model-adequacy verdict (issue 27): judged against physical noise, robust sigma when
the model does not fit, gross stations flagged; the hidden-effect battery (reduced, slow)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from graphcal import stats
from graphcal.calibration.adequacy import ALPHA, RATIO_LIMIT, adequacy_verdict, gross_stations, group_check, physical_noise
from graphcal.errors import DatasetError

REPO = Path(__file__).resolve().parents[1]
NEES_LIMIT = float(stats.ppf(0.997, 6))


def _bench():
    spec = importlib.util.spec_from_file_location("adequacy_battery", REPO / "bench" / "adequacy_battery.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["adequacy_battery"] = mod
    spec.loader.exec_module(mod)
    return mod


# ----------------------------------------------------------------------------- statistics
def test_group_statistic_is_chi2_at_the_physical_sigma():
    phys, src = physical_noise({"joint_deg": 0.02, "contact_mm": 0.0})
    assert phys["joint_deg"] == 0.02 and phys["contact_mm"] == 0.1  # a declared 0 is judged at its floor
    assert "at its floor" in src["contact_mm"] and src["imu_deg"].startswith("default")
    # learned 0.239 deg over 675 dof against 0.02 deg: ratio 12, T = 675 * 12^2
    g = group_check("stance_foot/joint", (("sigma_joint_rad", np.radians(0.239)),), 1.0, 675.0, phys, src, 6)
    assert g.ratio == pytest.approx(11.95, abs=0.01)
    assert g.statistic == pytest.approx(675.0 * g.ratio**2)
    assert g.misfit
    # below the ratio limit: not a misfit however many dof (1.2 x over 675 dof has p ~ 1e-9)
    g = group_check("stance_foot/joint", (("sigma_joint_rad", np.radians(0.024)),), 1.0, 675.0, phys, src, 6)
    assert g.p_value < ALPHA / 6 and g.ratio < RATIO_LIMIT and not g.misfit
    # above the ratio but not significant (1 dof): not a misfit either (default ground 2 mm)
    g = group_check("foot_on_ground", (("sigma_ground_m", 0.007),), 1.0, 1.0, phys, src, 6)
    assert g.ratio == pytest.approx(3.5) and g.p_value > ALPHA / 6 and not g.misfit
    # under 1 dof: nothing to judge
    assert group_check("plane:depth", (("plane_scale:depth", 9.0),), 1.0, 0.4, phys, src, 6) is None
    # a held group is judged at the factor its residuals point to
    g = group_check("plane:depth", (("plane_scale:depth", 1.0),), 3.0, 30.0, phys, src, 6)
    assert g.ratio == pytest.approx(3.0) and g.misfit
    v = adequacy_verdict((g,))
    assert v.verdict == "does not fit" and v.worst_group == "plane:depth" and v.reference == "chi2(30.0)"
    assert v.p_value == pytest.approx(g.p_value)
    assert any("diagnose" in s for s in v.next_steps)


def test_physical_noise_in_dataset_yaml_is_checked():
    with pytest.raises(DatasetError, match=r"physical_noise.joint_rad: expected one of joint_deg"):
        physical_noise({"joint_rad": 0.001})
    with pytest.raises(DatasetError, match=r"physical_noise.contact_mm: expected a number >= 0"):
        physical_noise({"contact_mm": -1})
    phys, src = physical_noise(None, ground_roughness_m=0.01)
    assert phys["ground_mm"] == 10.0 and src["ground_mm"] == "--ground-roughness-mm"


def test_gross_station_against_a_median_that_does_not_fit_either():
    rng = np.random.default_rng(1)
    # every station 4x its chi-square (the rest does not fit well), station 7 60x
    chi = {s: (4.0 * float(rng.chisquare(20)), 20.0) for s in range(30)}
    chi[7] = (60.0 * 20, 20.0)
    gross = gross_stations(chi)
    assert [g.station for g in gross] == [7]
    assert gross[0].factor == pytest.approx(15, rel=0.3)
    chi[7] = (4.0 * 45, 20.0)  # a station at the tail of the others is not gross
    assert gross_stations(chi) == ()


# ----------------------------------------------------------------------------- the cases
@pytest.fixture(scope="module")
def joint_offset_run(tmp_path_factory):
    from graphcal.commands.simulate import run as simulate

    out = tmp_path_factory.mktemp("octeff") / "octeff"
    simulate(robot="octopus", program="chai2015", ground="level", out_dir=out, seed=5, output="planes",
             effects=[("joint_offset", {"joint": "lf_femur_joint", "offset_rad": "0.05"})], progress=False)
    return out


def test_joint_offset_warns_and_its_governing_sigma_covers_the_error(joint_offset_run, tmp_path):
    """Issue 27: the Octopus with a hidden 0.05 rad femur offset was 0.39 deg / 7.6 mm off with
    sigma 0.008 deg / 0.11 mm (NEES 5181) and no warning."""
    from graphcal.commands.calibrate import run
    from graphcal.geometry import pose_from_xyz_quat_wxyz, pose_log_between
    from graphcal.solvers.covariance import nees

    result = run(joint_offset_run, tmp_path / "cal", progress=False)
    assert result.verdict == "does not fit" and result.calibration.adequacy.worst_group == "stance_foot"
    assert result.warnings[0].startswith("the model does not fit") and "calibrate --legs" in result.warnings[0]
    lines = result.summary_text().splitlines()  # the verdict and its warning first on the console
    assert lines[0].startswith("model DOES NOT FIT: worst group stance_foot,")
    assert lines[1] == f"warning: {result.warnings[0]}"
    doc = yaml.safe_load((tmp_path / "cal" / "calibration.yaml").read_text())
    a = doc["adequacy"]
    assert a["verdict"] == "does not fit" and a["sigma_from"] == "robust" and a["p_value"] < 1e-10
    assert {g for g, v in a["groups"].items() if v["misfit"]} == {"foot_on_ground", "stance_foot"}
    assert a["groups"]["imu"]["misfit"] is False
    assert doc["warnings"][0].startswith("the model does not fit")
    s = doc["sensors"]["depth"]
    assert s["sigma_from"] == "robust" and s["sigma"] == s["sigma_robust"]
    # widened along the largest axis (measured 7.9 mm against 0.49 mm), not to hundreds of mm: the model term is the
    # model's covariance at the learned noise, not scaled again by the misfit (measured 2.2-7.9 mm; 4.6-8.0 before)
    assert max(s["sigma"]["xyz_mm"]) > 5 * max(s["sigma_model"]["xyz_mm"])
    t = yaml.safe_load((joint_offset_run / "truth.yaml").read_text())["sensors"]["depth"]["T_body_sensor"]
    T_true = pose_from_xyz_quat_wxyz(t["xyz"], t["quaternion_wxyz"])
    T = pose_from_xyz_quat_wxyz(s["T_body_sensor"]["xyz"], s["T_body_sensor"]["quaternion_wxyz"])
    nees_model = nees(T_true, T, np.asarray(s["covariance_model"]))
    nees_gov = nees(T_true, T, np.asarray(s["covariance"]))
    assert nees_model > 1000  # measured 5181: the model's sigma does not cover the error
    assert nees_gov < NEES_LIMIT  # measured 1.0: the governing one does
    err_mm = 1e3 * np.linalg.norm(np.asarray(pose_log_between(T, T_true))[3:])
    assert max(s["sigma"]["xyz_mm"]) < 3 * err_mm  # and not absurdly wider than the error (measured 7.9 / 7.6 mm)
    assert "robust (the model does not fit)" in (tmp_path / "cal" / "static_transforms.sh").read_text()
    from graphcal.io.calibration_yaml import read_calibration_yaml, validate_calibration_dict

    assert read_calibration_yaml(tmp_path / "cal" / "calibration.yaml")["adequacy"]["verdict"] == "does not fit"
    doc["adequacy"]["verdict"] = "maybe"
    with pytest.raises(DatasetError, match=r"adequacy.verdict: expected fits or does not fit"):
        validate_calibration_dict(doc)
    html = (tmp_path / "cal" / "report.html").read_text()
    assert html.index("Does the model fit?") < html.index("Sensor <code>depth</code>")
    assert "1-σ model (the model does not fit)" in html


def test_clean_run_fits_and_keeps_the_model_covariance(tmp_path):
    from graphcal.calibration.calibrate import calibrate
    from graphcal.commands.simulate import run as simulate

    simulate(robot="octopus", program="chai2015", ground="level", out_dir=tmp_path / "d", seed=7, output="planes",
             cloud_stride=8, progress=False)
    r = calibrate(tmp_path / "d")
    assert r.adequacy.verdict == "fits" and r.adequacy.gross == ()
    assert r.sensors["depth"].covariance_model is None  # the model's covariance governs
    assert r.sensors["depth"].robust_terms == ()  # no --legs or range-scale solve paid for
    assert not any("does not fit" in w for w in r.warnings)
    # every group judged against what the simulator declares, below the limit
    assert {g.group for g in r.adequacy.groups} >= {"stance_foot", "imu", "commanded"}
    assert max(g.ratio for g in r.adequacy.groups) < RATIO_LIMIT
    # Chai's tilts vary the Kinect's distance to the floor: the data determine its range scale
    # (measured 0.032-0.041 % on seeds 0-4, 12 mm per 1 %), so no range-scale warning
    c = r.sensors["depth"].range_scale_check
    assert c.determined and c.sigma_from_data < 1e-3 and 10.0 < c.translation_mm < 14.0
    assert not any("range scale" in w for w in r.warnings)


def test_range_scale_the_data_cannot_see_is_said(tmp_path, monkeypatch):
    """The Messor on Łabęcki's program sees the floor from nearly the same range at every station:
    a 2 % laser range scale fits (``model fits``) and leaves the laser 7.6 mm off with sigma under
    1 mm. No verdict can see it; calibrate says that these data cannot check the range scale and
    what 1 % of scale would do, and that prediction matches the error (measured: 3.63 mm per 1 %,
    a predicted shift of 7.27 mm against an error of 7.61 mm, 0.79 mm apart)."""
    from graphcal.calibration.calibrate import calibrate
    from graphcal.commands.calibrate import verdict_lines
    from graphcal.commands.simulate import run as simulate
    from graphcal.geometry import pose_from_xyz_quat_wxyz
    from graphcal.report.calibration_yaml import calibration_to_dict

    simulate(robot="messor", program="labecki2012", ground="level", out_dir=tmp_path / "d", seed=24, output="planes",
             effects=[("sensor_range_scale", {"sensor": "laser", "scale": "1.02"})], progress=False)
    r = calibrate(tmp_path / "d")
    assert r.adequacy.fits  # what no verdict can see
    s = r.sensors["laser"]
    t = yaml.safe_load((tmp_path / "d" / "truth.yaml").read_text())["sensors"]["laser"]["T_body_sensor"]
    err_mm = 1e3 * (s.T_body_sensor[:3, 3] - pose_from_xyz_quat_wxyz(t["xyz"], t["quaternion_wxyz"])[:3, 3])
    assert np.linalg.norm(err_mm) > 6.0 and max(s.sigma_xyz_mm) < 1.0  # confident and wrong
    c = s.range_scale_check
    assert not c.determined and c.sigma_from_data > 0.04  # measured 7.8 %: the data say nothing
    # the true scale is 1.02 and calibrate takes 1: its estimate is off by -2 x the shift per 1 %
    predicted = -2.0 * c.translation_mm_per_percent
    assert np.linalg.norm(err_mm - predicted) < 1.5  # the error's noise is sigma 0.15-0.72 mm
    assert c.translation_mm == pytest.approx(np.linalg.norm(err_mm) / 2.0, rel=0.15)
    w = next(x for x in r.warnings if x.startswith("laser: these data do not determine its range scale (± 7."))
    assert "the sigma assume" in w
    assert verdict_lines(r)[1] == f"warning: {w}"  # with the verdict, first on the console
    # the stereo camera sees the floor from a constant range too: untested there as well
    assert not r.sensors["stereo"].range_scale_check.determined
    doc = calibration_to_dict(r)["sensors"]["laser"]["range_scale_check"]
    assert doc["determined"] is False and doc["sigma_from_data_pct"] > 4.0 and doc["limit_pct"] == 0.5
    assert doc["translation_mm_per_percent"] == pytest.approx(c.translation_mm)
    from graphcal.report import calibration_page

    monkeypatch.setattr(calibration_page, "report_figures", lambda result: [])  # the figures take seconds
    html = calibration_page.report_html(r)
    assert html.index("laser: these data do not determine its range scale") < html.index("Sensor <code>laser</code>")


def test_range_scale_run_governing_sigma_covers_its_error(tmp_path):
    """A depth scale of 0.98 moves the extrinsic ~2 % of the distance to the floor (~20 mm) alike at
    every station: the model's sigma (0.1 mm) and the jackknife do not see it (governing NEES 254
    over 10 runs before the range-scale term); with the shift to the same data solved with a range
    scale the governing sigma covers the error without being much wider than it."""
    import re

    from graphcal.calibration.calibrate import calibrate
    from graphcal.commands.simulate import run as simulate
    from graphcal.geometry import pose_from_xyz_quat_wxyz, pose_log_between
    from graphcal.report.calibration_yaml import calibration_to_dict
    from graphcal.solvers.covariance import nees

    simulate(robot="octopus", program="chai2015", ground="level", out_dir=tmp_path / "d", seed=11, output="planes",
             cloud_stride=8, effects=[("sensor_range_scale", {"sensor": "depth", "scale": "0.98"})], progress=False)
    r = calibrate(tmp_path / "d")
    assert "plane:depth" in {g.group for g in r.adequacy.misfit_groups}
    s = r.sensors["depth"]
    t = yaml.safe_load((tmp_path / "d" / "truth.yaml").read_text())["sensors"]["depth"]["T_body_sensor"]
    T_true = pose_from_xyz_quat_wxyz(t["xyz"], t["quaternion_wxyz"])
    assert nees(T_true, s.T_body_sensor, s.covariance_model) > 1000  # the model's sigma is confident and wrong
    assert nees(T_true, s.T_body_sensor, s.covariance) < NEES_LIMIT  # the governing one covers the error
    err_mm = 1e3 * np.linalg.norm(pose_log_between(s.T_body_sensor, T_true)[3:])
    assert err_mm > 10 and max(s.sigma_xyz_mm) < 2 * err_mm  # not absurdly wide
    terms = dict(s.robust_terms)
    assert "range_scale_shift" in terms and list(terms)[:2] == ["model", "jackknife"]
    scale = float(re.search(r"depth ([0-9.]+) ± ", terms["range_scale_shift"]).group(1))
    assert scale == pytest.approx(0.98, abs=0.002)  # the scale that explains the planes
    doc = calibration_to_dict(r)["sensors"]["depth"]
    assert doc["sigma_from"] == "robust" and set(doc["robust_terms"]) == set(terms)


def test_variance_factor_is_relative_to_the_noise_the_model_used():
    """The model term of the robust covariance scales C_model by the residuals' variance factor
    relative to the noise the solve used: ~1 for noise learned from the residuals (C_model is then
    already at the inflated sigma; scaling it again by learned / physical counted the misfit twice:
    34 deg / 822 mm for a 1.6 deg / 12 mm knock), the given noise's misfit when the noise was given."""
    from graphcal.calibration.robust import variance_factor

    phys, src = physical_noise(None)
    # learned: plane scale 3.5 (x3.5 the physical), the residuals point to it (data_scale 1)
    learned = (group_check("plane:depth", (("plane_scale:depth", 3.5),), 1.0, 100.0, phys, src, 2),
               group_check("stance_foot/joint", (("sigma_joint_rad", np.radians(0.3)),), 1.0, 300.0, phys, src, 2))
    assert learned[0].misfit and learned[0].statistic == pytest.approx(100 * 3.5 ** 2)
    assert variance_factor(learned) == pytest.approx(1.0)
    # given: the solve used plane scale 1 and joint 0.1 deg, the residuals converge to 3.5 and 0.3 deg
    used = {"plane_scale:depth": 1.0, "sigma_joint_rad": np.radians(0.1)}
    given = (group_check("plane:depth", (("plane_scale:depth", 3.5),), 1.0, 100.0, phys, src, 2, used),
             group_check("stance_foot/joint", (("sigma_joint_rad", np.radians(0.3)),), 1.0, 300.0, phys, src, 2, used))
    assert [g.model_ratio for g in given] == pytest.approx([3.5, 3.0])
    assert variance_factor(given) == pytest.approx((100 * 3.5 ** 2 + 300 * 9.0) / 400)
    # residuals below the noise used never shrink the model's covariance
    assert variance_factor((group_check("plane:depth", (("plane_scale:depth", 0.5),), 1.0, 100.0, phys, src, 1,
                                        {"plane_scale:depth": 1.0}),)) == 1.0


@pytest.mark.slow
def test_knocked_sensor_governing_sigma_covers_its_error_not_absurdly(tmp_path):
    """A camera knocked by 2.8 deg at station 26 of 52 (the battery's extrinsic_change, seed 2004):
    the one extrinsic estimated lies between the two, 1.6 deg / 12 mm from the first. Before,
    the governing sigma was 34 deg / 822 mm (C_model at the learned plane noise, times the
    variance factor at the physical noise: the misfit counted twice); without that, the model term,
    jackknife and legs shift gave 0.97 deg / 24 mm and NEES 21.5. The extrinsic-change term (the
    same data with a second extrinsic from the station a score test picks) covers it. Slow: 10 s
    alone (three extra solves: --legs, range scale, the split), 28 s under load."""
    import re

    from graphcal.calibration.calibrate import calibrate
    from graphcal.commands.simulate import run as simulate
    from graphcal.geometry import pose_from_xyz_quat_wxyz, pose_log_between
    from graphcal.solvers.covariance import nees

    simulate(robot="octopus", program="chai2015", ground="level", out_dir=tmp_path / "d", seed=2004, output="planes",
             cloud_stride=8, effects=[("extrinsic_change", {})], progress=False)
    truth = yaml.safe_load((tmp_path / "d" / "truth.yaml").read_text())
    assert truth["effects"]["extrinsic_change"]["station"] == 26
    r = calibrate(tmp_path / "d")
    assert "plane:depth" in {g.group for g in r.adequacy.misfit_groups}
    s = r.sensors["depth"]
    t = truth["sensors"]["depth"]["T_body_sensor"]
    T_true = pose_from_xyz_quat_wxyz(t["xyz"], t["quaternion_wxyz"])
    assert nees(T_true, s.T_body_sensor, s.covariance_model) > NEES_LIMIT  # measured 184
    assert nees(T_true, s.T_body_sensor, s.covariance) < NEES_LIMIT  # measured 0.89
    err = np.asarray(pose_log_between(s.T_body_sensor, T_true))
    err_deg, err_mm = np.degrees(np.linalg.norm(err[:3])), 1e3 * np.linalg.norm(err[3:])
    # measured 1.83 deg / 27.8 mm for 1.56 deg / 11.7 mm (34.4 deg / 822 mm with the double count)
    assert max(s.sigma_rot_deg) < 3 * err_deg and max(s.sigma_xyz_mm) < 5 * err_mm
    terms = dict(s.robust_terms)
    assert terms["model"].startswith("the model covariance x 1 ")  # noise learned: no second factor
    assert int(re.search(r"before and after station (\d+)", terms["extrinsic_change_shift"]).group(1)) == 26


def test_implausible_range_scale_is_no_term():
    from graphcal.calibration.robust import PLAUSIBLE_RANGE_SCALE_ERROR, misfit_sensors, plausible_range_scales

    assert plausible_range_scales({"depth": (0.97, 5e-4), "laser": (1.02, 1e-3)})
    # a sensor knocked mid-session read as a scale of 1.26 (extrinsic_change, seed 2004)
    assert not plausible_range_scales({"depth": (1.26, 0.027)})
    assert not plausible_range_scales({"depth": (1.0 - 1.01 * PLAUSIBLE_RANGE_SCALE_ERROR, 1e-3)})
    phys, src = physical_noise(None)
    groups = (group_check("plane:depth", (("plane_scale:depth", 3.5),), 1.0, 100.0, phys, src, 3),
              group_check("plane:laser", (("plane_scale:laser", 1.1),), 1.0, 100.0, phys, src, 3),
              group_check("stance_foot/joint", (("sigma_joint_rad", np.radians(0.3)),), 1.0, 500.0, phys, src, 3))
    assert misfit_sensors(groups) == ("depth",)


def test_chai_table3_flags_the_sign_error_row(tmp_path):
    """Chai's Table 3 association: the plane of station 15 (label 10, c printed with the wrong sign)
    is ~27 deg from the others; calibrate was 18.4 deg from Eq. 32 and flagged nothing."""
    sys.path.insert(0, str(REPO / "examples" / "octopus_chai2015"))
    import make_dataset

    from graphcal.calibration.calibrate import calibrate
    from graphcal.geometry import rotation_angle_between

    path = make_dataset.build_dataset(tmp_path / "t3", association="table3")
    r = calibrate(path)
    assert [g.station for g in r.adequacy.gross] == [15]
    assert r.adequacy.gross[0].p_value < 1e-5
    assert 15 in r.outliers and r.warnings[0].startswith("gross station(s) left out: 15")
    err = np.degrees(rotation_angle_between(r.sensors["depth"].T_body_sensor[:3, :3],
                                            make_dataset.paper_T_body_sensor()[:3, :3]))
    assert err < 1.0  # measured 0.36 deg (18.4 deg with station 15 in)


# ----------------------------------------------------------------------------- reduced battery
@pytest.mark.battery
@pytest.mark.slow
def test_reduced_hidden_effect_battery(tmp_path):
    """bench/adequacy_battery.py, reduced (18 runs, ~40 s): one drawn run of each catalogued effect
    (seed 2003), four more (seed 2000) and six clean runs (seeds 2000-2005), runs of the full battery
    (docs/calibration.md: 0 of 80 confident-wrong, 0 of 20 clean runs called misfits). No
    confident-wrong run, no false alarm, the effects that bias the extrinsic called misfits."""
    bench = _bench()
    specs = [("clean", 2000 + i, str(tmp_path)) for i in range(6)]
    specs += [(eff, 2003, str(tmp_path)) for eff in bench.CATALOGUE]
    specs += [(eff, 2000, str(tmp_path)) for eff in ("joint_offset", "link_length", "session_offset",
                                                      "sensor_range_scale")]
    records = [bench.run_one(s) for s in specs]
    clean = [r for r in records if r["effect"] == "clean"]
    assert all(r["verdict"] == "fits" for r in clean)
    assert np.mean([r["nees_model"] for r in clean]) < stats.ppf(0.975, 6 * len(clean)) / len(clean)
    assert not any(r["confident_wrong"] for r in records), [r for r in records if r["confident_wrong"]]
    for r in records:
        if r["effect"] in ("joint_offset", "link_length", "sensor_range_scale", "extrinsic_change", "session_offset"):
            assert r["verdict"] == "does not fit", r
            assert r["nees_model"] > NEES_LIMIT, r  # the model's sigma alone would be confident and wrong
        if r["effect"] in ("joint_offset", "link_length", "session_offset", "extrinsic_change", "sensor_range_scale"):
            assert r["nees_governing"] < NEES_LIMIT, r  # the robust sigma covers the error


def test_range_scale_limit_per_type_and_declared():
    """The limit is the sensor type's default unless dataset.yaml's physical_noise declares one."""
    from types import SimpleNamespace

    from graphcal.calibration.range_observability import RangeScaleCheck, range_scale_limits, range_scale_warning
    from graphcal.models.sensors import RANGE_SCALE_CHECK_PCT

    ds = SimpleNamespace(sensors={"laser": SimpleNamespace(type="laser_scanner"),
                                  "cam": SimpleNamespace(type="depth_camera")})
    lim = range_scale_limits(ds, None)
    assert lim["laser"][0] == RANGE_SCALE_CHECK_PCT["laser_scanner"] and lim["laser"][1].startswith("default")
    assert range_scale_limits(ds, {"range_scale_pct": 2.0})["cam"] == (2.0, "dataset.yaml physical_noise range_scale_pct")
    physical_noise({"range_scale_pct": 2.0})  # a key of the contract
    with pytest.raises(DatasetError, match=r"physical_noise.range_scale_pct"):
        physical_noise({"range_scale_pct": -1.0})
    c = RangeScaleCheck("laser", 0.0049, np.array([0.0, 0.0, 3.0]), np.zeros(3), 0.5, "x")
    assert c.determined and range_scale_warning(c) == ""
    c = RangeScaleCheck("laser", 0.0051, np.array([0.0, 0.0, 3.0]), np.zeros(3), 0.5, "x")
    assert not c.determined and "1 % would move its translation by 3 mm" in range_scale_warning(c)
