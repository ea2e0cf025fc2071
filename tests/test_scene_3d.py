"""The 3-D scene of the calibration report (graphcal.report.scene_3d, scene_view): the floor's
collapse measured against the simulator's truth, the numbers on the page, and the view drawn by
headless Chromium (its script ran, and the canvas is not blank)."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
import subprocess

import numpy as np
import pytest
import yaml

from graphcal.geometry import pose_from_xyz_quat_wxyz
from graphcal.io.dataset import load_dataset_robot, read_dataset
from graphcal.report.page import Section, render_page
from graphcal.report.scene_3d import GROUND_BAND_M, MAX_SCENE_POINTS, calibration_scene, floor_collapse
from graphcal.report.scene_view import scene_html


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A simulated octopus session (12 stations, depth clouds, CAD prior off the truth), calibrated."""
    from graphcal.commands.calibrate import run as calibrate
    from graphcal.commands.simulate import run as simulate

    root = tmp_path_factory.mktemp("scene3d")
    ds = root / "octopus"
    simulate(robot="octopus", program="random", ground="level", out_dir=ds, n_stations=12, cloud_stride=8,
             progress=False)
    out = root / "cal"
    res = calibrate(ds, out, progress=False)
    return ds, out, res.calibration


def _truth_extrinsic(ds) -> np.ndarray:
    t = yaml.safe_load((ds / "truth.yaml").read_text())["sensors"]["depth"]["T_body_sensor"]
    return pose_from_xyz_quat_wxyz(t["xyz"], t["quaternion_wxyz"])


def test_floor_collapse_is_the_rms_height_above_the_floor():
    prior = np.array([[0.0, 0.0, 0.003], [1.0, 0.0, -0.004], [2.0, 1.0, 0.0]])
    calibrated = prior * np.array([1.0, 1.0, 0.1])
    c = floor_collapse("depth", 2, prior, calibrated)
    assert c.points == 3 and c.stations == 2
    assert c.rms_prior_m == pytest.approx(np.sqrt((0.003**2 + 0.004**2) / 3), rel=1e-12)
    assert c.rms_calibrated_m == pytest.approx(0.1 * c.rms_prior_m, rel=1e-12)


def test_the_calibrated_floor_is_as_thin_as_the_true_extrinsic_makes_it(calibrated):
    ds_dir, _, result = calibrated
    ds = read_dataset(ds_dir)
    scene = calibration_scene(result, ds, load_dataset_robot(ds))
    (c,) = scene.collapse
    assert c.sensor == "depth" and c.stations == 12 and 12 * 50 < c.points <= MAX_SCENE_POINTS
    # the same points and body poses under the simulator's true extrinsic
    truth = dataclasses.replace(result, sensors={"depth": dataclasses.replace(
        result.sensors["depth"], T_body_sensor_prior=_truth_extrinsic(ds_dir))})
    (t,) = calibration_scene(truth, ds, None).collapse
    assert t.rms_prior_m == pytest.approx(c.rms_calibrated_m, rel=0.01)  # calibrated: as thin as the truth's
    assert c.rms_prior_m > 1.5 * c.rms_calibrated_m  # the prior's floor is visibly thicker
    assert c.rms_calibrated_m < GROUND_BAND_M / 3  # the band did not clip the calibrated floor


def test_the_scene_holds_the_robot_the_frames_and_the_floor(calibrated):
    ds_dir, _, result = calibrated
    ds = read_dataset(ds_dir)
    robot = load_dataset_robot(ds)
    scene = calibration_scene(result, ds, robot)
    groups = {g.name: g for g in scene.groups}
    station = min(result.T_world_body)
    stick = groups[f"robot at station {station}"].data
    assert stick.shape[1:] == (2, 3)
    feet = stick[:, 1][np.abs(stick[:, 1, 2]) < 0.01]  # every leg's last segment ends on the floor
    assert len(feet) == len(robot.feet)
    assert groups["body poses"].data.shape == (3 * len(result.T_world_body), 2, 3)
    T = result.T_world_body[station] @ result.sensors["depth"].T_body_sensor
    assert np.allclose(groups["depth calibrated"].data[0, 0], T[:3, 3], atol=1e-12)
    assert np.all(np.abs(groups["depth ground, calibrated"].data[:, 2]) < GROUND_BAND_M)


def test_without_clouds_the_scene_says_so(calibrated):
    _, _, result = calibrated
    scene = calibration_scene(result, None, None)
    assert not scene.collapse and "No station clouds" in scene.note
    assert any(g.name == "body poses" for g in scene.groups)


def test_the_report_prints_the_collapse_it_measured(calibrated):
    ds_dir, out, result = calibrated
    ds = read_dataset(ds_dir)
    (c,) = calibration_scene(result, ds, load_dataset_robot(ds)).collapse
    text = re.sub(r"<[^>]+>", "", (out / "report.html").read_text())
    assert (f"{c.points} ground points of 12 stations" in text
            and f"{c.rms_prior_m * 1e3:.2f} mm with the CAD prior" in text
            and f"{c.rms_calibrated_m * 1e3:.2f} mm with the calibrated extrinsic" in text)


def _chromium() -> str:
    found = shutil.which("chromium") or shutil.which("chromium-browser")
    assert found, "headless Chromium is needed (Debian: apt-get install -y chromium; scripts/bootstrap installs it)"
    return found


def _canvas_shot(scene, folder, name: str) -> tuple[int, np.ndarray]:
    """(data-drawn, RGB pixels inside the canvas) of ``scene``'s view in headless Chromium."""
    from PIL import Image

    page = folder / f"{name}.html"
    page.write_text(render_page("scene", [Section(None, scene_html(scene, width=600, height=400))], footer=""))
    args = [_chromium(), "--headless", "--no-sandbox", "--disable-gpu", f"--user-data-dir={folder / 'profile'}"]
    dom = subprocess.run(args + ["--dump-dom", page.as_uri()], capture_output=True, text=True, timeout=120).stdout
    drawn = re.search(r'data-drawn="(\d+)"', dom)
    png = folder / f"{name}.png"
    subprocess.run(args + ["--window-size=700,600", f"--screenshot={png}", page.as_uri()], capture_output=True,
                   timeout=120, check=True)
    rgb = np.asarray(Image.open(png).convert("RGB")).astype(int)
    border = np.flatnonzero((np.abs(rgb - 204).max(axis=2) < 3).sum(axis=1) > 500)  # the canvas's #ccc edges
    assert len(border) >= 2
    return (int(drawn.group(1)) if drawn else -1), rgb[border.min() + 1:border.max()]


def _count(pixels: np.ndarray, hex_color: str) -> int:
    c = [int(hex_color[i:i + 2], 16) for i in (1, 3, 5)]
    return int(np.sum(np.abs(pixels - c).sum(axis=2) < 40))


def test_chromium_draws_the_view(calibrated, tmp_path):
    ds_dir, _, result = calibrated
    ds = read_dataset(ds_dir)
    scene = calibration_scene(result, ds, load_dataset_robot(ds))
    drawn, canvas = _canvas_shot(scene, tmp_path, "all")
    assert drawn == sum(len(g.data) for g in scene.groups if g.visible)  # the script drew every point and segment
    dark = int(np.sum(canvas.sum(axis=2) < 200))  # the robot's legs
    assert _count(canvas, "#1f77b4") > 500 and dark > 50, (_count(canvas, "#1f77b4"), dark)
    # the calibrated points hidden: the prior's floor is there, no calibrated point is
    hidden = dataclasses.replace(scene, groups=tuple(
        dataclasses.replace(g, visible=False) if g.name == "depth ground, calibrated" else g for g in scene.groups))
    drawn, canvas = _canvas_shot(hidden, tmp_path, "prior")
    assert drawn == sum(len(g.data) for g in hidden.groups if g.visible)
    assert _count(canvas, "#ff7f0e") > 500 and _count(canvas, "#1f77b4") < 5


def test_the_view_carries_its_scene_as_json_without_breaking_out_of_the_script():
    from graphcal.report.scene_3d import Scene, SceneGroup

    scene = Scene((SceneGroup("</script><b>x", "#000", "points", np.zeros((2, 3))),), (), "")
    html = str(scene_html(scene))
    payload = re.search(r'<script type="application/json">(.*?)</script>', html, re.S).group(1)
    assert json.loads(payload)["groups"][0]["name"] == "</script><b>x"
    assert html.count("</script>") == 2
    assert "src=" not in html and "http" not in html  # nothing fetched: the page works offline


@pytest.mark.slow
def test_a_walks_floor_collapses_onto_the_true_extrinsics(tmp_path):
    """A walking dataset: each station's cloud is its frame's (timeseries.csv ``cloud_depth``)."""
    from graphcal.commands.calibrate import run as calibrate
    from graphcal.simulation.walking import WalkingConfig, simulate_walking
    from graphcal.simulation.write import write_walking

    cfg = WalkingConfig(program="tripod-walk", seed=5, duration_s=6.0, cloud_rate_hz=5.0, cad_error_m=0.015,
                        cad_error_rad=np.radians(1.5), sway_rad=np.radians(1.0), nod_rad=np.radians(0.5))
    walk = write_walking(simulate_walking(cfg), tmp_path / "walk")
    result = calibrate(walk, tmp_path / "cal", progress=False).calibration
    ds = read_dataset(walk)
    scene = calibration_scene(result, ds, load_dataset_robot(ds))
    (c,) = scene.collapse
    assert c.stations == result.walk["stations"] and c.stations > 20
    truth = dataclasses.replace(result, sensors={"depth": dataclasses.replace(
        result.sensors["depth"], T_body_sensor_prior=_truth_extrinsic(walk))})
    (t,) = calibration_scene(truth, ds, None).collapse
    assert t.rms_prior_m == pytest.approx(c.rms_calibrated_m, rel=0.02)
    assert c.rms_prior_m > 4 * c.rms_calibrated_m
    assert f"robot at station {min(result.T_world_body)}" in {g.name for g in scene.groups}


def _payload(report) -> dict:
    text = report.read_text()
    return json.loads(re.search(r'<script type="application/json">(.*?)</script>', text, re.S).group(1))


@pytest.mark.slow
@pytest.mark.parametrize("effect", ["joint_offset", "outlier_stations"])
def test_the_diagnosis_page_marks_the_findings_place(effect, tmp_path):
    from graphcal.commands.diagnose import run as diagnose
    from graphcal.commands.simulate import run as simulate

    ds = tmp_path / "ds"
    simulate(robot="octopus", program="chai2015", ground="level", out_dir=ds, seed=3, effects=[(effect, {})],
             progress=False)
    out = tmp_path / "diag"
    diagnose(ds, out, progress=False)
    doc = json.loads((out / "diagnosis.json").read_text())
    (finding,) = [f for f in doc["findings"] if f["cause"] == effect]
    names = {g["name"] for g in _payload(out / "report.html")["groups"]}
    if effect == "joint_offset":
        assert f"finding: leg {finding['where']['leg']}" in names
    else:
        stations = ", ".join(str(s) for s in finding["where"]["stations"])
        assert f"finding: station{'s' if len(finding['where']['stations']) > 1 else ''} {stations}" in names


def test_a_moved_sensors_stations_take_their_own_segments_extrinsic(calibrated):
    """A sensor knocked mid-session has one extrinsic per segment: each station's ground points
    are laid in with its segment's, not the last segment's."""
    from graphcal.calibration.result import ExtrinsicSegment
    from graphcal.report.scene_3d import extrinsic_at

    ds_dir, _, result = calibrated
    s = result.sensors["depth"]
    T_off = s.T_body_sensor.copy()
    T_off[2, 3] += 0.020  # the first segment's sensor 20 mm higher
    stations = sorted(result.T_world_body)
    cut = stations[len(stations) // 2]
    segs = (ExtrinsicSegment(stations[0], cut, T_off, s.covariance),
            ExtrinsicSegment(cut + 1, stations[-1], s.T_body_sensor, s.covariance))
    moved = dataclasses.replace(result, sensors={"depth": dataclasses.replace(s, segments=segs)})
    assert np.array_equal(extrinsic_at(moved.sensors["depth"], cut), T_off)
    assert np.array_equal(extrinsic_at(moved.sensors["depth"], cut + 1), s.T_body_sensor)
    ds = read_dataset(ds_dir)
    (same,) = calibration_scene(result, ds, None).collapse
    (off,) = calibration_scene(moved, ds, None).collapse
    # half the stations' floor 20 mm off under their own segment's extrinsic (a body 20 mm off)
    assert off.rms_calibrated_m > 3 * same.rms_calibrated_m


def test_a_wrong_extrinsics_floor_is_not_called_collapsed(calibrated):
    """The ground points are each station's own floor, not those that agree with the extrinsic: a
    calibration 2 deg off thickens the floor it draws, and the page says it does not collapse."""
    from graphcal.geometry import rot_x
    from graphcal.report.calibration_page import report_html

    ds_dir, _, result = calibrated
    ds = read_dataset(ds_dir)
    s = result.sensors["depth"]
    T = s.T_body_sensor.copy()
    T[:3, :3] = T[:3, :3] @ rot_x(np.radians(2.0))
    wrong = dataclasses.replace(result, sensors={"depth": dataclasses.replace(s, T_body_sensor=T, segments=())})
    (good,) = calibration_scene(result, ds, None).collapse
    scene = calibration_scene(wrong, ds, None)
    (bad,) = scene.collapse
    assert bad.rms_prior_m == pytest.approx(good.rms_prior_m, rel=0.1)  # nearly the same floor chosen
    assert bad.rms_calibrated_m > 2 * bad.rms_prior_m
    page = report_html(wrong, scene=scene)
    assert "The floor does not collapse" in page and "The floor collapses" not in page
    assert "The floor collapses" in report_html(result, scene=calibration_scene(result, ds, None))
