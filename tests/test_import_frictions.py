"""graphcal import's frictions with a real log (issue 42, item 5): the IMU mount from the URDF link
the map names, ``--urdf`` making the map's ``robot.urdf`` optional, map paths relative to the map,
bad maps refused before the log is read, the ``--timeseries`` hint for a walking log."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import yaml

from graphcal.cli import main
from graphcal.commands import import_log, simulate
from graphcal.geometry import pose_from_xyz_rpy
from graphcal.io.dataset import read_dataset
from graphcal.models.builtin import builtin_urdf
from graphcal.simulation.ros_log import LogPlan, write_station_log

A1_JOINTS = [f"{leg}_{j}_joint" for leg in ("fl", "fr", "rl", "rr") for j in ("hip", "thigh", "calf")]
A1_FEET = ["fl_foot", "fr_foot", "rl_foot", "rr_foot"]
#: the IMU board of the test URDF: body -> imu_board -> imu_link, two fixed joints
BOARD_XYZ, BOARD_RPY = (-0.016, -0.067, 0.0), (0.0, 0.0, 0.0)
IMU_XYZ, IMU_RPY = (0.0, 0.0, -0.006), (0.0, 0.0, np.pi / 2)
T_BODY_IMU = pose_from_xyz_rpy(BOARD_XYZ, BOARD_RPY) @ pose_from_xyz_rpy(IMU_XYZ, IMU_RPY)


def _with_imu_board(urdf: str, base: str = "body") -> str:
    """``urdf`` with an IMU on a board: ``base`` -> imu_board -> imu_link (fixed joints)."""
    v = lambda a: " ".join(repr(float(x)) for x in a)  # noqa: E731
    extra = (f'  <link name="imu_board"/>\n  <link name="imu_link"/>\n'
             f'  <joint name="imu_board_joint" type="fixed"><parent link="{base}"/><child link="imu_board"/>'
             f'<origin xyz="{v(BOARD_XYZ)}" rpy="{v(BOARD_RPY)}"/></joint>\n'
             f'  <joint name="imu_link_joint" type="fixed"><parent link="imu_board"/><child link="imu_link"/>'
             f'<origin xyz="{v(IMU_XYZ)}" rpy="{v(IMU_RPY)}"/></joint>\n')
    return urdf.replace("</robot>", extra + "</robot>")


def _write_csv(path: Path, *, seconds: float = 3.0, rate_hz: float = 100.0, gyro_z: float = 0.0,
               bad_row: int | None = None) -> None:
    """A Unitree-style export of the a1 standing (``gyro_z`` 0) or turning all along (``gyro_z``
    0.5 rad/s: never still): time_ms, acc in g, gyro rad/s, q0..q11 rad, four raw foot counts;
    ``bad_row``: that row's time cell is ``x``."""
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["time_ms", "acc_x", "acc_y", "acc_z", "gyro_x", "gyro_y", "gyro_z",
                    *[f"q{i}" for i in range(12)], *[f"foot_force_{i}" for i in range(4)]])
        for k in range(int(seconds * rate_hz)):
            t = "x" if bad_row == k + 1 else repr(1e3 * k / rate_hz)
            q = [0.0, 0.8, -1.6] * 4
            w.writerow([t, 0.0, 0.0, 1.0, 0.0, 0.0, gyro_z, *q, 300, 300, 300, 300])


def _csv_map(**robot) -> dict:
    return {"format": "graphcal-csv-map/1", "time": {"column": "time_ms", "unit": "ms"},
            **({"robot": robot} if robot else {}),
            "joints": {"unit": "rad", "columns": {j: f"q{i}" for i, j in enumerate(A1_JOINTS)}},
            "imu": {"accel": ["acc_x", "acc_y", "acc_z"], "accel_unit": "g", "gyro": ["gyro_x", "gyro_y", "gyro_z"],
                    "gyro_unit": "rad/s"},
            "feet": {f: {"column": f"foot_force_{i}", "threshold_n": 20.0} for i, f in enumerate(A1_FEET)}}


@pytest.fixture
def robot_dir(tmp_path) -> Path:
    """A folder with the map's files: robot.urdf (the a1 with its IMU on a board) beside the map."""
    d = tmp_path / "robot"
    d.mkdir()
    (d / "robot.urdf").write_text(_with_imu_board(builtin_urdf("a1")))
    return d


def _write_map(folder: Path, m: dict) -> Path:
    p = folder / "map.yaml"
    p.write_text(yaml.safe_dump(m, sort_keys=False))
    return p


def _fails(capsys, out: Path, args, *words) -> str:
    """graphcal import ... exits 2 with one line naming ``words``; nothing written."""
    rc = main(["import", *map(str, args), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert len(err.splitlines()) == 1, err
    for w in words:
        assert w in err, (w, err)
    assert not out.exists()
    return err


def _imu_pose(ds: Path) -> np.ndarray:
    return read_dataset(ds).imu.T_body_imu_prior.matrix


# ----------------------------------------------------------------------------- 1. the IMU's link
def test_csv_imu_mount_from_the_urdf_link(robot_dir, tmp_path, capsys):
    """imu.link names the URDF link: T_body_imu_prior is the URDF's fixed transform (two fixed
    joints composed), sigma 2 mm / 1 deg (or the map's); an unknown link is one line naming the
    key and the links."""
    log = tmp_path / "log.csv"
    _write_csv(log)
    m = _csv_map(urdf="robot.urdf")
    m["imu"]["link"] = "imu_link"
    result = import_log.run(log, tmp_path / "ds", map_path=_write_map(robot_dir, m), progress=False)
    assert result.n_stations == 1
    np.testing.assert_allclose(_imu_pose(tmp_path / "ds"), T_BODY_IMU, atol=1e-12)
    prior = read_dataset(tmp_path / "ds").imu.T_body_imu_prior
    assert prior.sigma_m == pytest.approx(2e-3) and prior.sigma_rad == pytest.approx(np.radians(1.0))
    m["imu"].update(sigma_mm=0.5, sigma_rpy_deg=0.2)
    import_log.run(log, tmp_path / "ds2", map_path=_write_map(robot_dir, m), progress=False)
    assert read_dataset(tmp_path / "ds2").imu.T_body_imu_prior.sigma_m == pytest.approx(5e-4)
    m["imu"]["link"] = "imu_lnk"
    _fails(capsys, tmp_path / "ds3", [log, "--map", _write_map(robot_dir, m)], "map.yaml", "imu.link",
           "a link of the URDF", "imu_board, imu_link", "got imu_lnk")
    m["imu"]["link"] = "fl_foot"  # behind moving joints
    _fails(capsys, tmp_path / "ds3", [log, "--map", _write_map(robot_dir, m)], "imu.link", "fixed joints only",
           "revolute joint")


@pytest.fixture(scope="module")
def station_bag(tmp_path_factory):
    """A short ROS 1 bag of a simulated octopus session (/tf_static body -> imu_link: identity)."""
    d = tmp_path_factory.mktemp("bag")
    simulate.run(robot="octopus", program="random", ground="level", out_dir=d / "sim", seed=5, n_stations=2,
                 n_sessions=1, cloud_stride=8, progress=False)
    write_station_log(d / "sim", d / "log.bag", LogPlan(fmt="ros1", rate_hz=50.0, cloud_rate_hz=2.0, still_s=1.5,
                                                        move_s=0.5, decoys=False))
    return d / "log.bag"


def _bag_map(log: Path, **changes) -> dict:
    from graphcal.logs.mapping import detect_map
    from graphcal.logs.reader import LogReader

    with LogReader(log) as r:
        m = detect_map(r.topics)
    m["robot"].update(base_frame="body", feet=[f"{leg}_foot" for leg in ("lf", "lm", "lr", "rf", "rm", "rr")])
    for k, v in changes.items():
        m[k].update(v)
    return m


def test_bag_imu_mount_from_the_urdf_link(station_bag, tmp_path, capsys):
    """In a bag's map imu.link (a URDF link) wins over /tf_static; an unknown one is refused before
    the log is read, naming imu.link and the URDF's links; the map's robot.urdf is relative to the
    map's folder."""
    d = tmp_path / "maps"
    d.mkdir()
    (d / "robot.urdf").write_text(_with_imu_board(builtin_urdf("octopus")))
    m = _bag_map(station_bag, imu={"link": "imu_link"}, robot={"urdf": "robot.urdf"})
    result = import_log.run(station_bag, tmp_path / "ds", map_path=_write_map(d, m), progress=False)
    assert result.n_stations == 2
    np.testing.assert_allclose(_imu_pose(tmp_path / "ds"), T_BODY_IMU, atol=1e-12)
    m["imu"]["link"] = "imu_lnk"
    _fails(capsys, tmp_path / "ds2", [station_bag, "--map", _write_map(d, m)], "map.yaml", "imu.link",
           "a link of the URDF", "imu_link", "got imu_lnk")


# ----------------------------------------------------------------------------- 2. --urdf, no robot.urdf
def test_csv_urdf_flag_makes_the_map_robot_optional(robot_dir, tmp_path):
    """No robot entry in the column map: --urdf gives the URDF, its root the base, its leaves named
    *foot* the feet; the URDF's one *imu* link... is ambiguous here (imu, imu_board, imu_link) so
    the map names it."""
    log = tmp_path / "log.csv"
    _write_csv(log)
    m = _csv_map()
    m["imu"]["link"] = "imu_link"
    rc = main(["import", str(log), "--map", str(_write_map(tmp_path, m)), "--urdf", str(robot_dir / "robot.urdf"),
               "--out", str(tmp_path / "ds"), "--quiet"])
    assert rc == 0
    ds = read_dataset(tmp_path / "ds")
    assert ds.robot.base_frame == "body" and tuple(ds.robot.feet) == tuple(A1_FEET)
    assert (tmp_path / "ds" / "robot.urdf").read_text() == (robot_dir / "robot.urdf").read_text()


# ----------------------------------------------------------------------------- 3. paths relative to the map
def test_csv_map_paths_relative_to_the_map_folder(robot_dir, tmp_path, monkeypatch):
    """robot.urdf: relative to the map's folder whatever the current directory; absolute as given."""
    log = tmp_path / "log.csv"
    _write_csv(log)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    m = _csv_map(urdf="robot.urdf")
    import_log.run(log, tmp_path / "ds", map_path=_write_map(robot_dir, m), progress=False)
    assert (tmp_path / "ds" / "robot.urdf").read_text() == (robot_dir / "robot.urdf").read_text()
    m["robot"]["urdf"] = str(robot_dir / "robot.urdf")
    import_log.run(log, tmp_path / "ds2", map_path=_write_map(tmp_path, m), progress=False)
    assert (tmp_path / "ds2" / "robot.urdf").is_file()


# ----------------------------------------------------------------------------- 4. bad maps before the log
@pytest.mark.parametrize("change, words", [
    (lambda m: m["robot"].update(urdf="missing.urdf"), ["missing.urdf", "robot.urdf of", "a readable URDF"]),
    (lambda m: m["robot"].update(feet=["fl_foot", "nose"]), ["robot.feet", "a link of the URDF", "got nose"]),
    (lambda m: m["robot"].update(base_frame="trunk"), ["robot.base_frame", "got trunk"]),
    (lambda m: m["joints"]["columns"].update(fl_knee_joint="q0"),
     ["joints.columns.fl_knee_joint", "a moving joint of the URDF"]),
    (lambda m: m["imu"].update(link="nope"), ["imu.link", "got nope"]),
    (lambda m: m["imu"].update(gyro=["gyro_x", "gyro_y", "gyro_q"]), ["column 'gyro_q' (imu.gyro[2]"]),
])
def test_csv_bad_map_refused_before_the_first_row(change, words, robot_dir, tmp_path, capsys, monkeypatch):
    """The log's row 1 is bad (a time 'x'), so an error found while reading rows would name row 1:
    the map's error comes first. And no row is parsed at all."""
    import graphcal.logs.csv_log as csv_log

    log = tmp_path / "log.csv"
    _write_csv(log, bad_row=1)
    m = _csv_map(urdf="robot.urdf")
    change(m)

    def no_rows(*a, **k):
        raise AssertionError("a row was read before the map was checked")

    monkeypatch.setattr(csv_log, "_parse_row", no_rows)
    err = _fails(capsys, tmp_path / "ds", [log, "--map", _write_map(robot_dir, m)], *words)
    assert "row 1" not in err


def test_csv_robot_without_base_or_feet_refused_first(tmp_path, capsys):
    """A URDF without a link named like a foot and no robot.feet: refused before the rows."""
    d = tmp_path / "r"
    d.mkdir()
    (d / "robot.urdf").write_text(builtin_urdf("a1").replace("_foot", "_tip"))
    log = tmp_path / "log.csv"
    _write_csv(log, bad_row=1)
    _fails(capsys, tmp_path / "ds", [log, "--map", _write_map(d, _csv_map(urdf="robot.urdf"))],
           "robot.base_frame / robot.feet", "the base frame and the foot frames")


# ----------------------------------------------------------------------------- 5. the --timeseries hint
def test_walking_csv_without_timeseries_says_so(robot_dir, tmp_path, capsys):
    """Never still: without --timeseries one line that names --timeseries; with it, the import works."""
    log = tmp_path / "walk.csv"
    _write_csv(log, gyro_z=0.5)
    m = _write_map(robot_dir, _csv_map(urdf="robot.urdf"))
    _fails(capsys, tmp_path / "ds", [log, "--map", m], "walk.csv", "at least one still window", "--timeseries",
           "graphcal track")
    assert main(["import", str(log), "--map", str(m), "--out", str(tmp_path / "ds"), "--timeseries", "--quiet"]) == 0
    assert read_dataset(tmp_path / "ds").timeseries is not None
