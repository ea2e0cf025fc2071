"""Dataset write -> read round trips (exact floats), atomic writes, and the YAML the writer produces."""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from graphcal.errors import DatasetError
from graphcal.geometry import matrix_from_rpy, quat_wxyz_from_matrix
from graphcal.io import (
    Dataset,
    ImuSpec,
    MarkerSpec,
    OutputExistsError,
    PosePrior,
    RobotSpec,
    SensorSpec,
    Table,
    atomic_directory,
    atomic_write_text,
    cloud_paths,
    load_cloud,
    read_dataset,
    read_ply,
    validate_dataset,
    write_dataset,
    write_ply,
)
from graphcal.models.builtin import builtin_info
from graphcal.models.robot import load_robot

FIXTURE = Path(__file__).parent / "data" / "octopus_small"


def make_dataset(seed: int = 0) -> tuple[Dataset, dict]:
    """An octopus dataset with every kind of content, full-precision random floats, and its clouds."""
    rng = np.random.default_rng(seed)
    info = builtin_info("octopus")
    robot = load_robot(model="octopus")
    n = 9
    stations: dict[str, object] = {
        "station": np.arange(1, n + 1) * 10,
        "session": np.array(["s1"] * 3 + ["s2"] * 3 + ["s 3"] * 3),
        "time": np.cumsum(rng.uniform(0.5, 2.0, n)),
    }
    for j in robot.joint_names:
        stations[f"q_{j}"] = rng.uniform(-0.5, 0.5, n)
    stations["tau_lf_femur_joint"] = rng.normal(0.0, 3.0, n)
    quats = np.array([quat_wxyz_from_matrix(matrix_from_rpy(rng.normal(0, 0.1, 3))) for _ in range(n)])
    for k, c in enumerate(("body_x", "body_y", "body_z")):
        stations[c] = rng.normal(0.0, 0.05, n) + (0.68 if c == "body_z" else 0.0)
    for k, c in enumerate(("body_qw", "body_qx", "body_qy", "body_qz")):
        stations[c] = quats[:, k]
    for c in ("imu_ax", "imu_ay"):
        stations[c] = rng.normal(0.0, 0.3, n)
    stations["imu_az"] = 9.81 + rng.normal(0.0, 0.01, n)
    for c in ("imu_gx", "imu_gy", "imu_gz"):
        stations[c] = rng.normal(0.0, 1e-3, n)

    m = 15
    ts: dict[str, object] = {"time": 100.0 + np.sort(rng.uniform(0, 3, m)), "session": np.array(["walk"] * m)}
    for j in robot.joint_names:
        ts[f"q_{j}"] = rng.uniform(-0.5, 0.5, m)
    for c in ("imu_ax", "imu_ay", "imu_az", "imu_gx", "imu_gy", "imu_gz"):
        ts[c] = rng.normal(0.0, 1.0, m)
    ts["contact_lf_foot"] = rng.integers(0, 2, m).astype(float)
    ts["contact_rr_foot"] = np.ones(m)

    k = 6
    normals = rng.normal(size=(k, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    A = rng.normal(size=(k, 4, 4)) * 1e-3
    cov = A @ np.swapaxes(A, 1, 2)
    planes: dict[str, object] = {
        "station": stations["station"][:k],
        "sensor": np.array(["depth"] * k),
        "nx": normals[:, 0],
        "ny": normals[:, 1],
        "nz": normals[:, 2],
        "d": rng.uniform(0.2, 2.0, k),
        "n_points": rng.integers(100, 10000, k).astype(float),
        "rms": rng.uniform(0.001, 0.01, k),
    }
    for i in range(4):
        for j in range(4):
            planes[f"cov_{i}{j}"] = cov[:, i, j]

    times, markers, xyz = [], [], []
    for t in stations["time"][:4]:
        for name in ("body.1", "body.2", "body.3", "body.4", "lf_foot", "rr_foot.2", "tool"):
            times.append(t)
            markers.append(name)
            xyz.append(rng.normal(0.0, 1.0, 3))
    xyz = np.array(xyz)
    mocap = {"time": np.array(times), "marker": np.array(markers), "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}

    cad = info.sensors["depth"]
    ds = Dataset(
        robot=RobotSpec(urdf=None, model="octopus", base_frame=info.base_frame, feet=info.feet),
        sensors={
            "depth": SensorSpec(
                "depth",
                cad.type,
                PosePrior(np.array([0.3, 0.0, 0.4]), np.radians([-90.0, 0.0, -120.0]), 0.05, math.radians(5.0)),
                {"resolution": [640, 480], "model": "kinect v1"},
            ),
            "laser": SensorSpec(
                "laser", "laser_scanner", PosePrior([0.25, 0.0, 0.1], [0.0, 0.0, 0.0], 0.02, math.radians(2.0))
            ),
        },
        imu=ImuSpec(PosePrior([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], 0.0, math.radians(1.0)), {"rate_hz": 400}),
        ground={"type": "level"},
        stance={"feet_fixed_within": "session"},
        extra={"notes": "round trip", "x_vendor": {"a": 1, "b": [1.5, "x"]}},
        stations=Table.from_columns(stations),
        timeseries=Table.from_columns(ts),
        planes=Table.from_columns(planes),
        mocap=Table.from_columns(mocap),
        mocap_markers={"tool": MarkerSpec("lf_tibia", [0.0, 0.01, -0.02]), "lf_foot": MarkerSpec("lf_foot")},
    )
    clouds = {
        ("depth", 10): rng.normal(0.0, 1.0, (50, 3)) + [0, 0, 2],
        ("depth", 20): rng.normal(0.0, 1.0, (7, 3)),
        ("laser", 10): rng.uniform(-3, 3, (30, 3)),
    }
    return ds, clouds


def test_round_trip_exact(tmp_path):
    ds, clouds = make_dataset()
    out = write_dataset(ds, tmp_path / "ds", clouds=clouds)
    back = read_dataset(out)
    assert back.root == tmp_path / "ds"
    assert dataclasses.replace(back, root=None) == ds
    # the tables, field by field, bit for bit (the equality above already says so; be explicit)
    for name in ("stations", "timeseries", "planes", "mocap"):
        a, b = getattr(ds, name), getattr(back, name)
        assert a.columns == b.columns
        for c in a.columns:
            assert a[c].dtype.kind == b[c].dtype.kind
            assert np.array_equal(a[c], b[c]), (name, c)
    assert back.stations["station"].dtype == np.int64
    assert back.stations["session"].tolist()[-1] == "s 3"
    assert back.sensors["depth"].extra == {"resolution": [640, 480], "model": "kinect v1"}
    assert back.imu.extra == {"rate_hz": 400}
    assert back.extra == ds.extra
    assert back.mocap_markers["lf_foot"].xyz is None
    # clouds: binary PLY, exact float64
    assert set(cloud_paths(back)) == set(clouds)
    for (sensor, station), pts in clouds.items():
        assert np.array_equal(load_cloud(back, sensor, station), pts)
    report = validate_dataset(out)
    assert (report.n_stations, report.n_sessions, report.n_clouds, report.n_planes) == (9, 4, 3, 6)
    assert report.n_mocap_rows == 28 and report.n_timeseries_rows == 15
    assert report.sensors == ("depth", "laser") and report.n_sensors == 2
    assert report.time_start_s == float(ds.stations["time"][0])
    assert "valid graphcal-dataset/1" in report.summary()


def test_yaml_uses_contract_keys_and_units(tmp_path):
    ds, clouds = make_dataset()
    write_dataset(ds, tmp_path / "ds", clouds=clouds)
    doc = yaml.safe_load((tmp_path / "ds" / "dataset.yaml").read_text())
    assert doc["format"] == "graphcal-dataset/1"
    assert doc["robot"] == {"model": "octopus", "base_frame": "body", "feet": list(ds.robot.feet)}
    prior = doc["sensors"]["depth"]["T_body_sensor_prior"]
    assert prior == {"xyz": [0.3, 0.0, 0.4], "rpy_deg": [-90.0, 0.0, -120.0], "sigma_mm": 50.0, "sigma_rpy_deg": 5.0}
    assert doc["sensors"]["depth"]["type"] == "depth_camera"
    assert doc["imu"]["T_body_imu_prior"]["sigma_rpy_deg"] == 1.0
    assert doc["mocap"] == {"markers": {"tool": {"link": "lf_tibia", "xyz": [0.0, 0.01, -0.02]}, "lf_foot": {"link": "lf_foot"}}}
    assert doc["notes"] == "round trip"
    text = (tmp_path / "ds" / "stations.csv").read_text()
    assert text.splitlines()[0].startswith("station,session,time,q_")
    assert text.splitlines()[1].startswith("10,s1,")
    assert read_ply(tmp_path / "ds" / "clouds" / "depth" / "10.ply").shape == (50, 3)
    assert (tmp_path / "ds" / "clouds" / "depth" / "10.ply").read_bytes().startswith(b"ply\nformat binary_little_endian")


def test_priors_from_arbitrary_radians_within_one_ulp(tmp_path):
    ds, _ = make_dataset()
    rng = np.random.default_rng(5)
    priors = [PosePrior(rng.normal(0, 0.3, 3), rng.uniform(-3.1, 3.1, 3), rng.uniform(0, 0.1), rng.uniform(0, 0.2))
              for _ in range(20)]  # fmt: skip
    sensors = {f"s{i}": SensorSpec(f"s{i}", "depth_camera", p) for i, p in enumerate(priors)}
    out = write_dataset(dataclasses.replace(ds, sensors=sensors, planes=None, timeseries=None), tmp_path / "ds")
    back = read_dataset(out)
    exact = 0
    for name, s in sensors.items():
        a, b = s.T_body_sensor_prior, back.sensors[name].T_body_sensor_prior
        assert np.array_equal(a.xyz, b.xyz)
        np.testing.assert_array_max_ulp(a.rpy_rad, b.rpy_rad, maxulp=1)
        np.testing.assert_array_max_ulp(np.array([a.sigma_m, a.sigma_rad]), np.array([b.sigma_m, b.sigma_rad]), maxulp=1)
        exact += a == b
    assert exact >= 10  # most of them are exact (the writer searches for a decimal that reads back exactly)


def test_rewrite_a_read_dataset_copies_clouds(tmp_path):
    """Reading the hand-made fixture and writing it elsewhere keeps everything, clouds included."""
    ds = read_dataset(FIXTURE)
    out = write_dataset(ds, tmp_path / "copy")
    back = read_dataset(out)
    assert dataclasses.replace(back, root=None) == dataclasses.replace(ds, root=None)
    assert np.array_equal(load_cloud(back, "depth", 1), load_cloud(ds, "depth", 1))
    assert (out / "clouds" / "depth" / "t10.01.ply").read_bytes() == (FIXTURE / "clouds/depth/t10.01.ply").read_bytes()
    assert validate_dataset(out).n_clouds == 2


def test_urdf_is_written_and_read(tmp_path):
    ds, _ = make_dataset()
    from graphcal.models.builtin import builtin_urdf

    spec = dataclasses.replace(ds.robot, urdf="model/robot.urdf", model=None)
    out = write_dataset(dataclasses.replace(ds, robot=spec), tmp_path / "ds", robot_urdf_xml=builtin_urdf("octopus"))
    assert (out / "model" / "robot.urdf").read_text() == builtin_urdf("octopus")
    assert read_dataset(out).robot.urdf == "model/robot.urdf"
    with pytest.raises(DatasetError, match="robot.urdf"):
        write_dataset(dataclasses.replace(ds, robot=spec), tmp_path / "ds2")
    assert not (tmp_path / "ds2").exists()


# ------------------------------------------------------------------ atomicity
def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def test_existing_folder_is_never_replaced_without_overwrite(tmp_path):
    ds, clouds = make_dataset()
    out = tmp_path / "ds"
    out.mkdir()
    (out / "precious.txt").write_text("user data")
    with pytest.raises(OutputExistsError):
        write_dataset(ds, out, clouds=clouds)
    assert sorted(p.name for p in out.iterdir()) == ["precious.txt"]
    assert (out / "precious.txt").read_text() == "user data"
    assert _leftovers(tmp_path) == []
    write_dataset(ds, out, clouds=clouds, overwrite=True)
    assert not (out / "precious.txt").exists() and (out / "dataset.yaml").exists()
    assert _leftovers(tmp_path) == []
    # an empty folder is fine without overwrite
    (tmp_path / "empty").mkdir()
    write_dataset(ds, tmp_path / "empty")
    assert (tmp_path / "empty" / "stations.csv").exists()


def test_failed_write_leaves_nothing_behind(tmp_path):
    ds, clouds = make_dataset()
    bad = dict(ds.stations.data)
    bad["time"] = bad["time"].copy()
    bad["time"][3] = np.nan
    bad_ds = dataclasses.replace(ds, stations=Table(ds.stations.columns, bad))
    with pytest.raises(DatasetError) as info:
        write_dataset(bad_ds, tmp_path / "ds", clouds=clouds)
    msg = str(info.value)
    assert "stations.csv (not written)" in msg and "row 4" in msg and "column time" in msg
    assert list(tmp_path.iterdir()) == []
    # the same failure over an existing dataset with overwrite=True keeps the old one intact
    write_dataset(ds, tmp_path / "ds", clouds=clouds)
    before = {p.relative_to(tmp_path): p.read_bytes() for p in (tmp_path / "ds").rglob("*") if p.is_file()}
    with pytest.raises(DatasetError):
        write_dataset(bad_ds, tmp_path / "ds", clouds=clouds, overwrite=True)
    after = {p.relative_to(tmp_path): p.read_bytes() for p in (tmp_path / "ds").rglob("*") if p.is_file()}
    assert before == after
    assert _leftovers(tmp_path) == []


def test_bad_clouds_are_refused_before_writing(tmp_path):
    ds, clouds = make_dataset()
    for key, pts, where in [
        (("depth", 10), np.full((3, 3), np.nan), "finite"),
        (("depth", 10), np.zeros((0, 3)), "non-empty"),
        (("nope", 10), np.zeros((3, 3)), "sensor"),
        (("depth", 11), np.zeros((3, 3)), "station"),
    ]:
        with pytest.raises(DatasetError, match=where) as info:
            write_dataset(ds, tmp_path / "ds", clouds={key: pts})
        assert f"clouds/{key[0]}/{key[1]}.ply" in str(info.value)
    assert list(tmp_path.iterdir()) == []


def test_atomic_directory_exception_and_refusals(tmp_path):
    target = tmp_path / "out"
    with pytest.raises(RuntimeError):
        with atomic_directory(target) as tmp:
            (tmp / "a.txt").write_text("half")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    with atomic_directory(target) as tmp:
        (tmp / "a.txt").write_text("done")
    assert (target / "a.txt").read_text() == "done"
    with pytest.raises(OutputExistsError):
        with atomic_directory(target) as tmp:
            pass
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputExistsError):
        with atomic_directory(tmp_path / "file", overwrite=True):
            pass
    assert (tmp_path / "file").read_text() == "x"
    with atomic_directory(target, overwrite=True) as tmp:
        (tmp / "b.txt").write_text("new")
    assert sorted(p.name for p in target.iterdir()) == ["b.txt"]
    assert _leftovers(tmp_path) == []


def _old_and_new(tmp_path):
    target = tmp_path / "out"
    with atomic_directory(target) as tmp:
        (tmp / "a.txt").write_text("old")
    return target


@pytest.fixture
def python_sigint_handler():
    """Python's own Ctrl-C handler for the test (a process started in the background by a
    non-interactive shell, as CI may be, inherits SIGINT ignored, and graphcal leaves an ignored
    SIGINT ignored)."""
    import signal

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


@pytest.mark.parametrize("exchange", [True, False], ids=["one-call-exchange", "two-renames"])
def test_ctrl_c_during_the_swap_leaves_the_new_folder_complete(tmp_path, monkeypatch, exchange,
                                                               python_sigint_handler):
    """A SIGINT right after the old folder was moved aside (the moment an audit hit: the folder then
    vanished and the CLI said nothing was written) is held back until the new folder is in place,
    then raised as InterruptedAfterWrite; nothing hidden is left."""
    import signal

    from graphcal.io import atomic

    target = _old_and_new(tmp_path)
    if not exchange:
        monkeypatch.setattr(atomic, "_exchange", lambda a, b: False)
    real_rename, real_exchange = os.rename, atomic._exchange

    def rename(a, b):
        real_rename(a, b)
        if Path(a) == target:  # the old folder moved aside: Ctrl-C now
            os.kill(os.getpid(), signal.SIGINT)

    def exchange_then_sigint(a, b):
        done = real_exchange(a, b)
        os.kill(os.getpid(), signal.SIGINT)
        return done

    monkeypatch.setattr(atomic.os, "rename", rename)
    if exchange:
        monkeypatch.setattr(atomic, "_exchange", exchange_then_sigint)
    with pytest.raises(atomic.InterruptedAfterWrite, match="was written"):
        with atomic_directory(target, overwrite=True) as tmp:
            (tmp / "b.txt").write_text("new")
    monkeypatch.undo()
    assert sorted(p.name for p in target.iterdir()) == ["b.txt"]
    assert _leftovers(tmp_path) == []


def test_folders_left_by_a_killed_writer_are_cleaned_or_put_back(tmp_path):
    """SIGKILL leaves hidden siblings named after the writer's process id. The next write to the same
    folder removes a dead writer's temporary folder and puts a previous output it had moved aside
    back (never deleting it); a live writer's folders are left alone."""
    import subprocess
    import sys

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True, check=True).stdout.strip()
    target = tmp_path / "out"
    (tmp_path / f".out.tmp-{dead}-abc123").mkdir()
    (tmp_path / f".out.tmp-{dead}-abc123" / "calibration.yaml").write_text("half")
    (tmp_path / f".out.old-{dead}-xyz789").mkdir()
    (tmp_path / f".out.old-{dead}-xyz789" / "a.txt").write_text("previous")
    live = tmp_path / f".out.tmp-{os.getppid()}-live01"  # the test runner's parent: alive
    live.mkdir()
    with pytest.raises(OutputExistsError):  # the previous output is back: not replaced unasked
        with atomic_directory(target) as tmp:
            (tmp / "b.txt").write_text("new")
    assert (target / "a.txt").read_text() == "previous"
    assert _leftovers(tmp_path) == [live.name]
    with atomic_directory(target, overwrite=True) as tmp:
        (tmp / "b.txt").write_text("new")
    assert sorted(p.name for p in target.iterdir()) == ["b.txt"]
    assert _leftovers(tmp_path) == [live.name]


def test_the_cli_says_when_an_interrupt_came_after_the_output_was_written(monkeypatch, capsys):
    from graphcal import cli
    from graphcal.io.atomic import InterruptedAfterWrite

    def interrupted(args):
        raise InterruptedAfterWrite(Path("somewhere/out"))

    monkeypatch.setattr(cli, "_cmd_validate", interrupted)
    assert cli.main(["validate", "x"]) == 130
    assert capsys.readouterr().err.strip() == "graphcal validate: interrupted after somewhere/out was written (complete)"


def test_atomic_write_text_and_failures(tmp_path, monkeypatch):
    f = tmp_path / "x.txt"
    atomic_write_text(f, "one")
    atomic_write_text(f, "two")
    assert f.read_text() == "two"
    with pytest.raises(OutputExistsError):
        atomic_write_text(f, "three", overwrite=False)

    def fail(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        atomic_write_text(f, "four")
    with pytest.raises(OSError, match="disk full"):
        write_ply(tmp_path / "c.ply", np.zeros((2, 3)))
    monkeypatch.undo()
    assert f.read_text() == "two"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.txt"]


def test_write_ply_read_ply(tmp_path):
    pts = np.random.default_rng(3).normal(size=(100, 3))
    write_ply(tmp_path / "a.ply", pts)
    assert np.array_equal(read_ply(tmp_path / "a.ply"), pts)
    write_ply(tmp_path / "b.ply", pts, binary=False)
    assert np.allclose(read_ply(tmp_path / "b.ply"), pts, atol=1e-5)
    with pytest.raises(ValueError):
        write_ply(tmp_path / "c.ply", np.zeros((0, 3)))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.ply", "b.ply"]


def test_table_basics():
    t = Table.from_columns({"station": [3.0, 1.0], "session": ["a", "b"], "q_x": [0.5, 1]})
    assert len(t) == 2 and t.has("q_x") and not t.has("q_y") and "session" in t
    assert t["station"].dtype == np.int64 and t["q_x"].dtype == np.float64 and t["session"].dtype.kind == "U"
    assert t.suffixes("q_") == ("x",)
    assert t.row(1) == {"station": 1, "session": "b", "q_x": 1.0}
    assert len(t.select(t["station"] > 2)) == 1
    with pytest.raises(KeyError, match="q_x"):
        t["q_xx"]
    with pytest.raises(ValueError):
        Table.from_columns({"station": [1.5]})
    with pytest.raises(ValueError):
        Table.from_columns({"a": [1, 2], "b": [1]})
    assert not t["q_x"].flags.writeable


def test_pose_prior_matrix():
    p = PosePrior([0.3, 0.0, 0.4], np.radians([-90.0, 0.0, -120.0]), 0.05, 0.1)
    T = p.matrix
    assert np.allclose(T[:3, 3], [0.3, 0.0, 0.4])
    assert np.allclose(T[:3, :3], matrix_from_rpy(np.radians([-90.0, 0.0, -120.0])))
    q = PosePrior.from_matrix(T, 0.05, 0.1)
    assert np.allclose(q.matrix, T)


def test_read_accepts_dataset_yaml_path(tmp_path):
    shutil.copytree(FIXTURE, tmp_path / "d")
    assert read_dataset(tmp_path / "d" / "dataset.yaml").root == tmp_path / "d"
