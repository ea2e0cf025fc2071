"""The command line as a user meets it: exit codes, one-line errors without tracebacks, outputs that
never overwrite what the user has, and the example scripts."""

from __future__ import annotations

import csv
import subprocess
import sys

import numpy as np
import pytest
import yaml


def run(*args, check_rc=None):
    proc = subprocess.run([sys.executable, "-m", "graphcal", *map(str, args)], capture_output=True, text=True,
                          timeout=600)
    if check_rc is not None:
        assert proc.returncode == check_rc, proc.stderr + proc.stdout
    return proc


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "octopus"
    run("simulate", "--robot", "octopus", "--program", "random", "--stations", "8", "--sessions", "2",
        "--cloud-stride", "8", "--out", out, "--quiet", "--effect", "link_length:joint=rm_foot_joint,delta_m=0.015",
        check_rc=0)
    return out


def test_simulate_writes_a_valid_dataset_with_truth_beside_it(small_dataset):
    assert (small_dataset / "dataset.yaml").is_file()
    assert len(list((small_dataset / "clouds" / "depth").glob("*.ply"))) == 8
    truth = yaml.safe_load((small_dataset / "truth.yaml").read_text())
    assert truth["effects"]["link_length"]["rm_foot_joint"]["delta_m"] == pytest.approx(0.015)
    proc = run("validate", small_dataset, check_rc=0)
    assert "8 in 2 session(s)" in proc.stdout


def test_simulate_refuses_to_overwrite_a_users_folder(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("precious")
    proc = run("simulate", "--robot", "octopus", "--program", "random", "--stations", "3", "--out", out, "--quiet")
    assert proc.returncode == 2
    assert "not empty" in proc.stderr and "Traceback" not in proc.stderr
    assert (out / "notes.txt").read_text() == "precious"


@pytest.mark.parametrize(
    "effect, words",
    [("volcano", "unknown cause"), ("link_length:joint=rm_foot_joint", "missing parameter delta_m"),
     ("ground_tilt:tilt_rad=abc", "not a number"), ("joint_offset:joint=nope_joint,offset_rad=0.03", "nope_joint")],
)
def test_bad_effect_is_one_line_exit_2(tmp_path, effect, words):
    proc = run("simulate", "--program", "random", "--stations", "3", "--out", tmp_path / "x", "--quiet",
               "--effect", effect)
    assert proc.returncode == 2, proc.stderr
    assert words in proc.stderr
    assert "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()


def test_validate_malformed_dataset_exit_2_names_file_and_row(small_dataset, tmp_path):
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(small_dataset, broken)
    lines = (broken / "stations.csv").read_text().splitlines()
    header = lines[0].split(",")
    row = lines[3].split(",")
    row[header.index("body_qw")] = "0.5"  # no longer a unit quaternion
    lines[3] = ",".join(row)
    (broken / "stations.csv").write_text("\n".join(lines) + "\n")
    proc = run("validate", broken)
    assert proc.returncode == 2
    assert "stations.csv" in proc.stderr and "row 3" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_extract_planes_writes_once_and_never_overwrites(small_dataset, tmp_path):
    out = tmp_path / "planes.csv"
    run("extract-planes", small_dataset, "--out", out, "--quiet", check_rc=0)
    rows = out.read_text().splitlines()
    assert rows[0].startswith("station,sensor,nx,ny,nz,d")
    assert len(rows) == 1 + 8
    before = out.read_bytes()
    proc = run("extract-planes", small_dataset, "--out", out, "--quiet")
    assert proc.returncode == 2 and "never overwrites" in proc.stderr
    assert out.read_bytes() == before
    # --plane-points: each plane fitted on at most N points of its cloud, as calibrate's option
    thin = tmp_path / "planes_thin.csv"
    run("extract-planes", small_dataset, "--out", thin, "--plane-points", "2000", "--quiet", check_rc=0)
    col = rows[0].split(",").index("n_points")
    full_n = [float(r.split(",")[col]) for r in rows[1:]]
    thin_n = [float(r.split(",")[col]) for r in thin.read_text().splitlines()[1:]]
    assert len(thin_n) == 8 and max(thin_n) <= 2000 < min(full_n)
    proc = run("extract-planes", small_dataset, "--out", tmp_path / "bad.csv", "--plane-points", "5", "--quiet")
    assert proc.returncode == 2 and "--plane-points" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "bad.csv").exists()
    # no plane asked for: refused (it wrote a header-only planes.csv, which then hid the clouds)
    proc = run("extract-planes", small_dataset, "--out", tmp_path / "none.csv", "--max-planes", "0", "--quiet")
    assert proc.returncode == 2 and "--max-planes" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "none.csv").exists()


def test_example_simulate_and_validate(load_example, tmp_path):
    mod = load_example("simulate_and_validate.py", "example")
    result = mod.main(tmp_path / "octopus")
    assert result["stations"] == 52
    # Kinect noise over ~16k points per frame: the fitted ground is within hundredths of a degree
    # and a fraction of a millimetre of the truth (a frame error would show up as degrees / cm)
    assert result["plane_angle_err_deg"][1] < 0.05
    assert result["plane_dist_err_mm"][1] < 1.0


def test_calibrate_writes_the_outputs_and_never_into_the_dataset(small_dataset, tmp_path):
    from graphcal.io.calibration_yaml import read_calibration_yaml

    out = tmp_path / "cal"
    proc = run("calibrate", small_dataset, "--out", out, "--quiet", check_rc=0)
    assert "depth:" in proc.stdout
    doc = read_calibration_yaml(out / "calibration.yaml")
    assert doc["format"] == "graphcal-calibration/1"
    assert set(doc["sensors"]["depth"]) >= {"T_body_sensor", "covariance", "sigma", "unobservable"}
    assert len(doc["sensors"]["depth"]["covariance"]) == 6
    # how each noise group's sigma was set: the values are those of the noise model, every group of
    # the graph is there, and the held ones are named on stdout
    groups = doc["noise_estimation"]
    assert {"stance_foot/joint", "stance_foot/contact", "imu", "plane:depth"} <= set(groups)
    for g in groups.values():
        assert g["status"] in {"learned", "too few dof", "at floor", "not converged"}
        assert all(doc["noise_model"][k] == v for k, v in g["values"].items())
    assert "implausibly" not in proc.stdout and "outside the URDF" not in proc.stdout  # clean data: no alarm
    held = [k for k, g in groups.items() if g["status"] != "learned"]
    assert ("noise not learned:" in proc.stdout) == bool(held)
    assert all(k in proc.stdout for k in held)
    for name in ("robot_calibrated.urdf", "static_transforms.sh", "report.html", "scene.mcap"):
        assert (out / name).stat().st_size > 0
    before = sorted(p.name for p in small_dataset.iterdir())
    proc = run("calibrate", small_dataset, "--out", small_dataset, "--quiet")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert sorted(p.name for p in small_dataset.iterdir()) == before


def test_an_output_that_cannot_be_written_is_refused_before_the_work(small_dataset, tmp_path):
    """--out under a regular file, in every writing command: one line naming --out, exit 2, before
    the work (the file is left as it was)."""
    notes = tmp_path / "notes.txt"
    notes.write_text("user data")
    for args in (("calibrate", small_dataset, "--out", notes / "cal"),  # no --quiet: no solve may start
                 ("suggest-poses", small_dataset, "-k", "2", "--out", notes / "poses.csv"),
                 ("extract-planes", small_dataset, "--out", notes / "planes.csv"),
                 ("diagnose", small_dataset, "--out", notes / "diag", "--quiet"),
                 ("simulate", "--robot", "octopus", "--program", "chai2015", "--output", "planes",
                  "--out", notes / "sim", "--quiet")):
        proc = run(*args)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, (args[0], proc.stderr)
        assert f"{notes}/" in proc.stderr and "is a file, not a folder" in proc.stderr, proc.stderr
        assert "LM iterations" not in proc.stderr  # refused before the work, not after it
    assert notes.read_text() == "user data"


def test_noise_from_inside_the_output_folder_is_refused_not_lost(small_dataset, tmp_path):
    out = tmp_path / "cal"
    run("calibrate", small_dataset, "--out", out, "--quiet", check_rc=0)
    before = (out / "calibration.yaml").read_bytes()
    proc = run("calibrate", small_dataset, "--out", out, "--noise-from", out / "calibration.yaml", "--quiet")
    assert proc.returncode == 2 and "is inside --out" in proc.stderr, proc.stderr
    assert (out / "calibration.yaml").read_bytes() == before


def test_calibrate_legs_writes_them_and_shows_progress(small_dataset, tmp_path):
    """``--legs`` end to end: the legs block of calibration.yaml (every foot, every parameter with
    value and sigma), the same values written into robot_calibrated.urdf, and progress on stderr
    (no --quiet: one line per solve)."""
    import xml.etree.ElementTree as ET

    from graphcal.io.calibration_yaml import read_calibration_yaml
    from graphcal.models.builtin import builtin_urdf

    out = tmp_path / "cal_legs"
    proc = run("calibrate", small_dataset, "--out", out, "--legs", check_rc=0)
    assert "calibrate: first solve (closed-form start, default noise):" in proc.stderr
    assert proc.stderr.count("LM iterations") >= 2, proc.stderr
    legs = read_calibration_yaml(out / "calibration.yaml")["legs"]
    assert set(legs) == {f"{leg}_foot" for leg in ("lf", "lm", "lr", "rf", "rm", "rr")}
    assert all(len(p) == 6 and all(set(v) == {"value", "sigma"} for v in p.values()) for p in legs.values())
    tibia = legs["rm_foot"]["rm_foot_joint.delta_m"]
    assert abs(tibia["value"] - 0.015) < 3 * tibia["sigma"]  # the injected 15 mm (8 stations: a wide sigma)

    def foot_z(text):
        j = next(e for e in ET.fromstring(text).iter("joint") if e.get("name") == "rm_foot_joint")
        return float(j.find("origin").get("xyz").split()[2])

    written = foot_z((out / "robot_calibrated.urdf").read_text())
    assert written == pytest.approx(foot_z(builtin_urdf("octopus")) - tibia["value"], abs=1e-9)


def test_suggest_poses_prints_and_writes_reachable_poses(small_dataset, tmp_path):
    out = tmp_path / "poses.csv"
    proc = run("suggest-poses", small_dataset, "-k", "4", "--out", out, check_rc=0)
    assert "rank" in proc.stdout
    rows = out.read_text().splitlines()
    assert len(rows) == 1 + 4 and rows[0].startswith("station,session,body_x")
    # predicted sigma never grows as stations are added (the 4 data rows of the table)
    table = [line.split() for line in proc.stdout.splitlines() if line.strip()[:1].isdigit()]
    sig_rot_x = [float(r[7]) for r in table]
    assert all(b <= a + 1e-9 for a, b in zip(sig_rot_x, sig_rot_x[1:]))
    # an existing file (here the user's poses; it could be the dataset's stations.csv) is never replaced
    before = out.read_bytes()
    proc = run("suggest-poses", small_dataset, "-k", "2", "--out", out)
    assert proc.returncode == 2 and "never overwrites" in proc.stderr and "Traceback" not in proc.stderr
    assert out.read_bytes() == before


def test_a_planes_csv_cut_short_is_reported_not_silently_used(small_dataset, tmp_path):
    """When planes.csv exists the clouds are not read: stations it lacks are named, and a header-only
    planes.csv is refused (it read as "nothing to calibrate")."""
    import shutil

    ds = tmp_path / "ds"
    shutil.copytree(small_dataset, ds)
    lines = (ds / "planes.csv").read_text().splitlines()
    stations = sorted(int(line.split(",")[0]) for line in lines[1:])
    (ds / "planes.csv").write_text("\n".join(lines[:5]) + "\n")  # the first 4 of 8 planes
    kept = sorted(int(line.split(",")[0]) for line in lines[1:5])
    proc = run("calibrate", ds, "--out", tmp_path / "cal", "--quiet", check_rc=0)
    dropped = ", ".join(str(s) for s in stations if s not in kept)
    assert f"depth: planes.csv has no plane for 4 of the 8 stations with a cloud ({dropped})" in proc.stdout
    (ds / "planes.csv").write_text(lines[0] + "\n")
    proc = run("calibrate", ds, "--out", tmp_path / "cal2", "--quiet")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "planes.csv: rows: expected at least one plane: when planes.csv exists the clouds are not read" in proc.stderr
    assert not (tmp_path / "cal2").exists()


def test_joint_columns_swapped_are_warned_about(small_dataset, tmp_path):
    """Two joint columns swapped on one leg: calibrate still answers (the sensors and the IMU
    determine the extrinsic) but says the legs' data are wrong. (Angles in degrees are an error:
    test_joint_angles_in_degrees_are_an_error_naming_the_column.)"""
    import csv
    import shutil

    ds = tmp_path / "ds"
    shutil.copytree(small_dataset, ds)
    rows = list(csv.reader((ds / "stations.csv").open(newline="")))
    a, b = rows[0].index("q_lf_coxa_joint"), rows[0].index("q_lf_femur_joint")
    rows[0][a], rows[0][b] = rows[0][b], rows[0][a]
    with (ds / "stations.csv").open("w", newline="") as f:
        csv.writer(f).writerows(rows)
    proc = run("calibrate", ds, "--out", tmp_path / "cal", "--quiet", check_rc=0)
    assert "the stance feet fit their kinematics implausibly badly" in proc.stdout
    assert "stations have joint angles outside the URDF's limits" not in proc.stdout


def _edit_stations(src, dst, edit):
    import csv
    import shutil

    shutil.copytree(src, dst)
    rows = list(csv.reader((dst / "stations.csv").open(newline="")))
    edit(rows[0], rows[1:])
    with (dst / "stations.csv").open("w", newline="") as f:
        csv.writer(f).writerows(rows)
    return dst


def _flip_knee(header, rows):
    c = header.index("q_rf_tibia_joint")
    for r in rows:
        r[c] = repr(-float(r[c]))


def _quaternion_xyzw(header, rows):
    cols = [header.index(f"body_q{a}") for a in "wxyz"]
    for r in rows:
        w, x, y, z = (r[c] for c in cols)
        for c, v in zip(cols, (x, y, z, w)):
            r[c] = v


@pytest.mark.parametrize("edit, words", [
    (_flip_knee, "the stance feet fit their kinematics implausibly badly"),
    (_quaternion_xyzw, "a quaternion in x, y, z, w order"),
], ids=["knee-sign-flipped", "body-quaternion-xyzw"])
def test_leg_and_commanded_pose_mistakes_are_warned_about(small_dataset, tmp_path, edit, words):
    """Mistakes an audit made with its own hexapod's data that calibrate answered without a word: one
    knee column of the wrong sign (contact learned 9-15 mm, under the old 20 mm threshold) and the
    commanded body quaternion written x, y, z, w (commanded pose learned ~7 deg / 70 mm)."""
    ds = _edit_stations(small_dataset, tmp_path / "ds", edit)
    proc = run("calibrate", ds, "--out", tmp_path / "cal", "--quiet", check_rc=0)
    assert words in proc.stdout, proc.stdout


@pytest.mark.parametrize("learned, warned", [
    ({}, False),  # the defaults
    ({"sigma_joint_rad": np.radians(0.05), "sigma_contact_m": 0.0092, "sigma_ground_m": 0.001}, True),  # audit, seed 1
    ({"sigma_joint_rad": np.radians(0.05), "sigma_contact_m": 0.0005, "sigma_ground_m": 0.0217}, True),
    ({"sigma_joint_rad": np.radians(0.05), "sigma_contact_m": 0.0005, "sigma_ground_m": 0.0217,
      "ground_unevenness_m": 0.01}, False),  # --ground-roughness-mm given: bumps may hold the feet
    ({"sigma_joint_rad": np.radians(0.3), "sigma_contact_m": 0.001, "sigma_ground_m": 0.010}, False),  # 0.3 deg flex, big bumps
    ({"sigma_commanded_rad": np.radians(6.8), "sigma_commanded_m": 0.068}, True),
    ({"sigma_commanded_rad": np.radians(3.0), "sigma_commanded_m": 0.03}, False),
])
def test_implausible_learned_noise_thresholds(small_dataset, learned, warned):
    import dataclasses

    from graphcal.calibration.calibrate import implausible_leg_data_warnings
    from graphcal.calibration.graph import CalibrationOptions
    from graphcal.calibration.measurements import calibration_data
    from graphcal.io.dataset import load_dataset_robot, read_dataset

    ds = read_dataset(small_dataset)
    robot = load_dataset_robot(ds)
    options = dataclasses.replace(CalibrationOptions(), **learned)
    assert bool(implausible_leg_data_warnings(calibration_data(ds, robot), robot, options)) is warned


def test_a_closed_pipe_and_a_garbage_cloud_give_no_traceback_nor_warnings(small_dataset, tmp_path):
    import os
    import shutil

    # `graphcal validate D | head -1`: the reader is gone before graphcal prints
    proc = subprocess.Popen([sys.executable, "-m", "graphcal", "validate", str(small_dataset)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    proc.wait(timeout=300)
    assert "Traceback" not in err and "BrokenPipeError" not in err, err
    assert proc.returncode == 141
    # random bytes after a valid header: one line naming the file and the point, no numpy warnings
    ds = tmp_path / "ds"
    shutil.copytree(small_dataset, ds)
    (ds / "planes.csv").unlink()
    cloud = sorted((ds / "clouds" / "depth").glob("*.ply"))[0]
    data = bytearray(cloud.read_bytes())
    start = data.index(b"end_header\n") + len(b"end_header\n")
    data[start:] = os.urandom(len(data) - start)
    cloud.write_bytes(bytes(data))
    proc = run("validate", ds)
    assert proc.returncode == 2 and f"{cloud.name}: point" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr


def test_a_sensor_prior_known_exactly_is_held_and_said_so(small_dataset, tmp_path):
    """sigma_mm: 0 (the contract allows sigmas >= 0) holds the translation at the CAD value; it is
    not reported as undetermined by the data."""
    import shutil

    from graphcal.io.calibration_yaml import read_calibration_yaml

    ds = tmp_path / "ds"
    shutil.copytree(small_dataset, ds)
    doc = yaml.safe_load((ds / "dataset.yaml").read_text())
    prior = doc["sensors"]["depth"]["T_body_sensor_prior"]
    prior["sigma_mm"] = 0
    (ds / "dataset.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    proc = run("calibrate", ds, "--out", tmp_path / "cal", "--quiet", check_rc=0)
    assert "depth: translation held at the CAD value (sigma_mm: 0 in dataset.yaml" in proc.stdout
    cal = read_calibration_yaml(tmp_path / "cal" / "calibration.yaml")
    assert np.allclose(cal["sensors"]["depth"]["T_body_sensor"]["xyz"], prior["xyz"], atol=1e-5)
    assert not [u for u in cal["sensors"]["depth"]["unobservable"] if "translation" in u or "height" in u]


@pytest.mark.parametrize("extra, words", [(["--ground-roughness-mm", "-3"], "must be a number >= 0 (mm), got -3"),
                                          (["--ground-roughness-mm", "nan"], "must be a number >= 0"),
                                          (["--plane-points", "50"], "--plane-points must be a whole number of points >= 100"),
                                          (["--noise-from", "nowhere/calibration.yaml"],
                                           "nowhere/calibration.yaml: file: expected a readable calibration.yaml")])
def test_calibrate_ground_roughness_bad_use_is_one_line_exit_2(small_dataset, tmp_path, extra, words):
    proc = run("calibrate", small_dataset, "--out", tmp_path / "out", "--quiet", *extra)
    assert proc.returncode == 2, proc.stderr
    assert words in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_simulate_mocap_then_identify_legs_finds_yuans_errors_from_the_command_line(tmp_path):
    """A user without a motion-capture room: `simulate --program mocap` writes Yuan's Table I session
    (the A1's front-left leg, its errors hidden in truth.yaml) and `identify-legs` finds them."""
    ds, out = tmp_path / "a1-mocap", tmp_path / "a1-legs"
    proc = run("simulate", "--robot", "a1", "--program", "mocap", "--stations", "400", "--seed", "5", "--out", ds,
               check_rc=0)
    assert "400 motion-capture samples" in proc.stdout and "Table I" in proc.stdout
    # its own output warns about nothing: no session column (the leg is in the air) and no encoder
    # reading beyond a joint limit (the true angles are drawn within the limits less the noise)
    assert "warning" not in run("validate", ds, check_rc=0).stdout
    run("identify-legs", ds, "--out", out, "--mocap-free", "rz,z", "--origins", "none", "--quiet", check_rc=0)
    from graphcal.models.legs import leg_model, theta_from_perturbation
    from graphcal.models.perturb import LegPerturbation
    from graphcal.models.robot import load_robot

    truth = yaml.safe_load((ds / "truth.yaml").read_text())["legs"]
    legs = yaml.safe_load((out / "legs.yaml").read_text())
    found = legs["legs"]["fl_foot"]
    model = leg_model(load_robot(model="a1"), "fl_foot", origins="none")  # the parameters identified
    theta = theta_from_perturbation(model, LegPerturbation(truth["joint_offsets_rad"], truth["origin_deltas_m"]))
    expected = dict(zip(model.names, theta.tolist()))
    assert set(found) == set(expected)
    z = [(found[k]["value"] - v) / found[k]["sigma"] for k, v in expected.items()]
    assert max(abs(x) for x in z) < 4.0, dict(zip(expected, z))
    rmse = legs["foot_error_mm"]["fl_foot"]
    assert rmse["rmse_after"] < 0.3 * rmse["rmse_before"]


def _freeze_marker(folder):
    """The fl_foot marker held at its first position (a marker the motion capture lost)."""
    rows = list(csv.reader(open(folder / "mocap.csv", newline="")))
    first = next(r[2:] for r in rows[1:] if r[1] == "fl_foot")
    rows = [rows[0]] + [r[:2] + first if r[1] == "fl_foot" else r for r in rows[1:]]
    csv.writer(open(folder / "mocap.csv", "w", newline=""), lineterminator="\n").writerows(rows)


def _freeze_joints(folder):
    rows = list(csv.reader(open(folder / "stations.csv", newline="")))
    qi = [i for i, c in enumerate(rows[0]) if c.startswith("q_")]
    for r in rows[2:]:
        for i in qi:
            r[i] = rows[1][i]
    csv.writer(open(folder / "stations.csv", "w", newline=""), lineterminator="\n").writerows(rows)


@pytest.mark.parametrize("edit, words", [
    # identified before as a leg shrunk to a point, +- 0.000 mm, sigma nan, and a URDF written
    (_freeze_marker, ["mocap.csv: marker 'fl_foot'", "a foot marker that moves", "spread 0 mm"]),
    (_freeze_joints, ["stations.csv: columns q_fl_hip_joint", "joint values that vary"]),
])
def test_identify_legs_refuses_motion_capture_that_cannot_identify(tmp_path, edit, words):
    folder = tmp_path / "mocap"
    run("simulate", "--robot", "a1", "--program", "mocap", "--stations", "60", "--out", folder, "--quiet",
        check_rc=0)
    edit(folder)
    proc = run("identify-legs", folder, "--out", tmp_path / "legs", "--quiet")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert all(w in proc.stderr for w in words), proc.stderr
    assert not (tmp_path / "legs").exists()


def test_simulate_mocap_refuses_the_station_program_options(tmp_path):
    proc = run("simulate", "--program", "mocap", "--out", tmp_path / "x", "--sessions", "2", "--quiet")
    assert proc.returncode == 2
    assert "--sessions" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "x").exists()


def test_simulate_overwrite_replaces_a_simulation_never_a_users_folder(tmp_path):
    """--overwrite (which scripts/demo passes) replaces a previous simulation; a measured dataset (no
    graphcal truth.yaml) or a simulation the user put notes in is refused and left as it was."""
    from graphcal.simulation.write import SIMULATION_FILES, TRUTH_TRAJECTORY_FILE

    assert TRUTH_TRAJECTORY_FILE in SIMULATION_FILES
    sim = tmp_path / "sim"
    args = ("simulate", "--program", "random", "--stations", "3", "--output", "planes", "--quiet", "--out", sim)
    run(*args, check_rc=0)
    first = (sim / "planes.csv").read_text()
    run(*args, "--seed", "1", "--overwrite", check_rc=0)
    assert (sim / "planes.csv").read_text() != first  # replaced
    (sim / "notes.txt").write_text("mine")
    proc = run(*args, "--overwrite")
    assert proc.returncode == 2 and "notes.txt" in proc.stderr and "Traceback" not in proc.stderr
    assert (sim / "notes.txt").read_text() == "mine"
    measured = tmp_path / "measured"
    measured.mkdir()
    for name in ("dataset.yaml", "stations.csv", "planes.csv"):
        (measured / name).write_text((sim / name).read_text())
    proc = run("simulate", "--program", "random", "--stations", "3", "--quiet", "--out", measured, "--overwrite")
    assert proc.returncode == 2 and "not a previous graphcal simulation" in proc.stderr
    assert sorted(p.name for p in measured.iterdir()) == ["dataset.yaml", "planes.csv", "stations.csv"]


def test_a_cloud_without_a_plane_is_named_not_dropped_silently(small_dataset, tmp_path):
    """A cloud of collinear points gives no plane: calibrate and extract-planes name its station
    (they dropped it without a word); extract-planes creates a missing parent folder of --out."""
    import shutil

    from graphcal.io.ply import write_ply

    ds = tmp_path / "ds"
    shutil.copytree(small_dataset, ds)
    (ds / "planes.csv").unlink()
    write_ply(ds / "clouds" / "depth" / "3.ply", np.c_[np.linspace(0, 1, 50), np.zeros(50), np.full(50, 2.0)])
    proc = run("extract-planes", ds, "--out", tmp_path / "new" / "planes.csv", "--quiet", check_rc=0)
    assert "no plane found in the clouds of 1 of the 8 stations (3;" in proc.stdout
    assert (tmp_path / "new" / "planes.csv").is_file()
    run("calibrate", ds, "--out", tmp_path / "out", "--quiet", check_rc=0)
    doc = yaml.safe_load((tmp_path / "out" / "calibration.yaml").read_text())
    assert any("no plane found in the clouds of 1 of the 8 stations (3;" in w for w in doc["warnings"])


@pytest.mark.parametrize("args, words", [
    (("simulate", "--seed", "-1"), "--seed must be a whole number >= 0"),
    (("simulate", "--program", "random", "--stations", "0"), "--stations must be >= 1"),
    (("simulate", "--program", "chai2015", "--stations", "5"), "--stations applies to the random and mocap"),
    (("simulate", "--program", "mocap", "--ground", "bumpy-big"), "--ground"),
])
def test_bad_simulate_values_are_one_line_exit_2(tmp_path, args, words):
    proc = run(*args, "--out", tmp_path / "x", "--quiet")
    assert proc.returncode == 2 and words in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("option, value, words", [
    ("--sigma-joint-deg", "inf", "--sigma-joint-deg must be a number from 0 to 360"),
    ("--sigma-joint-deg", "nan", "--sigma-joint-deg must be a number from 0 to 360"),
    ("--sigma-joint-deg", "1e308", "--sigma-joint-deg must be a number from 0 to 360 (deg), got 1e+308"),
    ("--sigma-marker-mm", "0", "--sigma-marker-mm must be a finite number > 0"),
    ("--sigma-marker-mm", "1e308", "--sigma-marker-mm must be at most 1e6"),
])
def test_bad_identify_legs_sigmas_are_one_line_exit_2(tmp_path, option, value, words):
    ds = tmp_path / "mocap"
    run("simulate", "--robot", "a1", "--program", "mocap", "--stations", "20", "--out", ds, "--quiet", check_rc=0)
    proc = run("identify-legs", ds, "--out", tmp_path / "o", option, value, "--quiet")
    assert proc.returncode == 2 and words in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_commands_needing_a_sensor_name_dataset_yaml_on_a_mocap_dataset(tmp_path):
    """calibrate said "station 0: fewer than 3 legs" and diagnose "run graphcal extract-planes?" on
    a motion-capture dataset; now each names dataset.yaml's sensors and identify-legs."""
    ds = tmp_path / "mocap"
    run("simulate", "--robot", "a1", "--program", "mocap", "--stations", "20", "--out", ds, "--quiet", check_rc=0)
    for words in (("calibrate",), ("calibrate", "--incremental"), ("diagnose",)):
        proc = run(words[0], ds, "--out", tmp_path / "o", *words[1:], "--quiet")
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
        assert "dataset.yaml: sensors: expected at least one sensor for " + " ".join(words) in proc.stderr, proc.stderr
        assert "graphcal identify-legs" in proc.stderr
        assert not (tmp_path / "o").exists()


def test_dataset_yaml_ground_and_stance_values_are_used_or_warned_about(small_dataset, tmp_path):
    """ground.type other than level and an unknown stance.feet_fixed_within are warned about by
    validate (they were read and ignored); feet_fixed_within: station makes every station a stance."""
    import shutil

    from graphcal.calibration.measurements import station_measurements
    from graphcal.io.dataset import load_dataset_robot, read_dataset

    ds = tmp_path / "ds"
    shutil.copytree(small_dataset, ds)
    doc = yaml.safe_load((ds / "dataset.yaml").read_text())
    doc["ground"], doc["stance"] = {"type": "tilted"}, {"feet_fixed_within": "leg"}
    (ds / "dataset.yaml").write_text(yaml.safe_dump(doc))
    out = run("validate", ds, check_rc=0).stdout
    assert "ground.type 'tilted'" in out and "feet_fixed_within 'leg'" in out
    doc["stance"] = {"feet_fixed_within": "station"}
    (ds / "dataset.yaml").write_text(yaml.safe_dump(doc))
    d = read_dataset(ds)
    sessions = {st.session for st in station_measurements(d, load_dataset_robot(d))}
    assert len(sessions) == 8  # 2 sessions in stations.csv, 8 stations each re-planted
    doc["stance"] = {"feet_fixed_within": "step"}  # what simulate writes for a walk
    (ds / "dataset.yaml").write_text(yaml.safe_dump(doc))
    out = run("validate", ds, check_rc=0).stdout
    assert "feet_fixed_within" not in out
    d = read_dataset(ds)
    assert len({st.session for st in station_measurements(d, load_dataset_robot(d))}) == 8


def test_joint_angles_in_degrees_are_an_error_naming_the_column(small_dataset, tmp_path):
    import shutil

    ds = tmp_path / "ds"
    shutil.copytree(small_dataset, ds)
    lines = (ds / "stations.csv").read_text().splitlines()
    head = lines[0].split(",")
    rows = [ln.split(",") for ln in lines[1:]]
    for r in rows:
        for i, c in enumerate(head):
            if c.startswith("q_"):
                r[i] = repr(float(r[i]) * 180.0 / np.pi)
    (ds / "stations.csv").write_text("\n".join([lines[0]] + [",".join(r) for r in rows]) + "\n")
    for cmd in (("validate", ds), ("calibrate", ds, "--out", tmp_path / "o", "--quiet")):
        proc = run(*cmd)
        assert proc.returncode == 2, proc.stdout + proc.stderr
        assert "stations.csv: column q_" in proc.stderr and "degrees?" in proc.stderr
        assert "Traceback" not in proc.stderr


def test_every_command_has_quiet_verbose_and_documented_arguments(capsys):
    """--quiet / --verbose on every command (log levels), help for every positional DATASET and for
    --seed, simulate --help shows its defaults; --quiet hides the INFO messages, --verbose shows DEBUG."""
    import argparse
    import logging

    from graphcal.cli import _build_parser, configure_logging

    parser = _build_parser()
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    assert set(subs) == {"simulate", "validate", "calibrate", "suggest-poses", "extract-planes", "diagnose",
                         "identify-legs", "track", "import", "batch", "study", "plan-gait"}
    for name, sp in subs.items():
        opts = {o for a in sp._actions for o in a.option_strings}
        assert {"--quiet", "--verbose"} <= opts, name
        for a in sp._actions:
            if a.dest in ("dataset", "seed"):
                assert a.help, (name, a.dest)
    subs["simulate"].print_help()
    text = capsys.readouterr().out
    # --robot: a walking program's own robot (tripod-walk: the qingzhui), otherwise the Octopus
    assert "walking program's own robot, otherwise" in " ".join(text.split()) and "(default: 0)" in text
    log = logging.getLogger("graphcal.calibration.calibrate")
    for quiet, verbose, shown in ((True, False, logging.WARNING), (False, False, logging.INFO),
                                  (False, True, logging.DEBUG)):
        configure_logging(quiet, verbose)
        assert log.getEffectiveLevel() == shown
    configure_logging()
    mine = [h for h in logging.getLogger("graphcal").handlers if getattr(h, "_graphcal_cli_handler", False)]
    assert len(mine) == 1
    log.info("calibrate: a message")
    assert capsys.readouterr().err == "calibrate: a message\n"
    logging.getLogger("graphcal").removeHandler(mine[0])
    logging.getLogger("graphcal").setLevel(logging.NOTSET)


def test_calibrate_compares_with_truth_yaml_when_it_is_there(small_dataset, tmp_path):
    """On simulated data calibrate says how far each sensor is from the hidden truth (issue 46 item
    6), with the extrinsic NEES; without a truth.yaml beside the dataset, nothing is said."""
    import shutil

    import numpy as np

    from graphcal.commands import calibrate
    from graphcal.io.calibration_yaml import pose_from_dict
    from graphcal.solvers.covariance import extrinsic_errors

    res = calibrate.run(small_dataset, tmp_path / "cal", progress=False)
    t = res.truth["depth"]
    truth = yaml.safe_load((small_dataset / "truth.yaml").read_text())["sensors"]["depth"]["T_body_sensor"]
    s = res.calibration.sensors["depth"]
    e = extrinsic_errors(s.T_body_sensor, pose_from_dict(truth), s.covariance)
    assert t["rotation_error_deg"] == pytest.approx(e["angle_deg"]) and t["nees"] == pytest.approx(e["nees"])
    assert np.isfinite(t["translation_error_mm"]) and t["translation_error_mm"] > 0
    assert f"against the truth (truth.yaml beside the dataset): depth {t['rotation_error_deg']:.4f} deg" in res.summary_text()
    bare = tmp_path / "bare"
    shutil.copytree(small_dataset, bare, ignore=shutil.ignore_patterns("truth*"))
    res2 = calibrate.run(bare, tmp_path / "cal2", progress=False)
    assert res2.truth is None and "against the truth" not in res2.summary_text()
