"""graphcal import: logs written with rosbags' own writers (ROS 1 bag, ROS 2 sqlite3, bare MCAP) and
a Unitree-style CSV from simulated station sessions -> import -> validate -> calibrate; the stations
found are exactly the simulated ones; every kind of bad input is one line, exit 2, nothing written."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from graphcal.cli import main
from graphcal.commands import calibrate, import_log, simulate
from graphcal.geometry import matrix_from_quat_wxyz, rotation_angle_between
from graphcal.io.dataset import read_dataset, validate_dataset
from graphcal.simulation.ros_log import LogPlan, write_station_csv, write_station_log

N_STATIONS = 6
OCTOPUS_JOINTS = [f"{leg}_{j}_joint" for leg in ("lf", "lm", "lr", "rf", "rm", "rr") for j in ("coxa", "femur", "tibia")]


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    out = tmp_path_factory.mktemp("imp") / "sim"
    simulate.run(robot="octopus", program="random", ground="level", out_dir=out, seed=3, n_stations=N_STATIONS,
                 n_sessions=1, cloud_stride=8, progress=False)
    return out


def _pose_error(cal_dir: Path, truth_dir: Path) -> tuple[float, float]:
    """(rotation error deg, translation error mm) of the one calibrated sensor against truth.yaml."""
    cal = yaml.safe_load((cal_dir / "calibration.yaml").read_text())
    truth = yaml.safe_load((truth_dir / "truth.yaml").read_text())
    (s,) = cal["sensors"].values()
    (t,) = truth["sensors"].values()
    R = matrix_from_quat_wxyz(s["T_body_sensor"]["quaternion_wxyz"])
    Rt = matrix_from_quat_wxyz(t["T_body_sensor"]["quaternion_wxyz"])
    dt = np.subtract(s["T_body_sensor"]["xyz"], t["T_body_sensor"]["xyz"])
    return np.degrees(rotation_angle_between(R, Rt)), 1e3 * float(np.linalg.norm(dt))


@pytest.fixture(scope="module")
def reference_error(sim, tmp_path_factory):
    """The simulation's own accuracy: calibrate on the simulated dataset itself."""
    out = tmp_path_factory.mktemp("cal0") / "cal"
    calibrate.run(sim, out, progress=False)
    return _pose_error(out, sim)


def _check_stations(ds_dir: Path, sim: Path, windows, t_offset: float = 0.0) -> None:
    """Exactly the simulated stations: one per still window (its centre inside), in order, joints
    and IMU equal to the simulated station's, and every rejected window one of the two decoys."""
    got = read_dataset(ds_dir).stations
    want = read_dataset(sim).stations
    assert len(got.data["station"]) == len(windows)
    for k, (a, b) in enumerate(windows):
        assert a + t_offset < got.data["time"][k] < b + t_offset
    for c in want.columns:
        if c.startswith(("q_", "imu_a", "imu_g")):
            np.testing.assert_allclose(got.data[c], want.data[c], rtol=0, atol=1e-9, err_msg=c)
    report = yaml.safe_load((ds_dir / "import_report.yaml").read_text())
    reasons = [r["reason"] for r in report["rejected"]]
    assert len(reasons) == 2 and "only" in reasons[0] and "not loaded" in reasons[1], reasons
    assert len(set(got.data["session"])) == 1  # no foot lifted between the stations


@pytest.mark.slow
@pytest.mark.parametrize("fmt", ["ros1", "sqlite3", "mcap"])
def test_bag_import_validate_calibrate(fmt, sim, reference_error, tmp_path):
    """ros1: PointCloud2 and one WrenchStamped per foot; sqlite3: depth Image + CameraInfo and a
    Float32MultiArray of raw foot counts whose offset and scale are set in the edited map; mcap: a
    bare .mcap file."""
    plan = LogPlan(fmt=fmt, feet="array" if fmt == "sqlite3" else "wrench",
                   points="depth" if fmt == "sqlite3" else "cloud")
    log = tmp_path / ("log.bag" if fmt == "ros1" else "log")
    windows = write_station_log(sim, log, plan)
    if fmt == "mcap":
        log = next(log.glob("*.mcap"))
    ds = tmp_path / "ds"
    result = import_log.run(log, ds, progress=False)
    if fmt == "sqlite3":
        # raw counts read as newtons (offset 0, scale 1): each foot's thresholds are learned from its
        # own counts (issue 42), so the decoy with a foot in the air is rejected already (with one
        # threshold of 20 "N" on counts it was a station); the map the user edits gives the same
        assert (result.n_stations, result.n_rejected) == (N_STATIONS, 2)
        m = yaml.safe_load((ds / "import_map.yaml").read_text())
        for f in m["feet"].values():
            f.update(offset=plan.raw_offset, scale=plan.raw_scale)
        (tmp_path / "map.yaml").write_text(yaml.safe_dump(m))
        result = import_log.run(log, ds, map_path=tmp_path / "map.yaml", progress=False, overwrite=True)
    assert (result.n_stations, result.n_rejected) == (N_STATIONS, 2) and result.out == ds
    assert "valid" in validate_dataset(ds).summary()
    _check_stations(ds, sim, windows)
    cal = tmp_path / "cal"
    calibrate.run(ds, cal, progress=False)
    rot, trans = _pose_error(cal, sim)
    rot0, trans0 = reference_error
    # the simulation's accuracy: as good as calibrating the simulated dataset itself, within a little:
    # a log has no commanded body pose (the simulated stations.csv has body_*, a prior the solver
    # uses); PointCloud2 and the depth images (the simulated camera's pixels) carry the same points
    # (float32), so all three formats calibrate alike
    slack_deg, slack_mm = 0.005, 0.2
    print(f"{fmt}: error {rot:.4f} deg {trans:.3f} mm; simulated dataset itself {rot0:.4f} deg {trans0:.3f} mm")
    assert rot <= rot0 + slack_deg and trans <= trans0 + slack_mm, (rot, trans, rot0, trans0)


def _sensorless_stations(out, *, seed, n_stations):
    """Stations of the a1 (no camera or laser: `graphcal simulate` refuses that combination, since
    there is nothing to calibrate; a CSV log of joints, IMU and foot forces only needs the poses)."""
    from graphcal.simulation.session import SimulationConfig
    from graphcal.simulation.session import simulate as simulate_session
    from graphcal.simulation.write import write_simulation

    res = simulate_session(SimulationConfig(robot="a1", program="random", ground="level", seed=seed,
                                            n_stations=n_stations, n_sessions=1))
    write_simulation(res, out, output="both")


def test_csv_import_with_raw_foot_counts(tmp_path):
    sim_a1 = tmp_path / "a1"
    _sensorless_stations(sim_a1, seed=1, n_stations=4)
    windows, cmap = write_station_csv(sim_a1, tmp_path / "log.csv", LogPlan(decoys=True))
    cmap = yaml.safe_load(cmap)
    # fl_foot (the one lifted in the decoy) by a threshold on its raw count instead of offset and scale
    cmap["feet"]["fl_foot"] = {"column": "foot_force_0", "threshold_raw": 250}
    (tmp_path / "map.yaml").write_text(yaml.safe_dump(cmap))
    ds = tmp_path / "ds"
    result = import_log.run(tmp_path / "log.csv", ds, map_path=tmp_path / "map.yaml", timeseries=True, progress=False)
    assert (result.n_stations, result.n_rejected) == (4, 2)
    assert {ds / "dataset.yaml", ds / "import_report.yaml", ds / "timeseries.csv"} <= set(result.files)
    _check_stations(ds, sim_a1, windows)
    ts = read_dataset(ds).timeseries
    assert ts is not None and {"contact_fl_foot", "imu_az", "q_fr_calf_joint"} <= set(ts.columns)
    # the decoy with fl_foot in the air: contact 0 there, 1 elsewhere
    assert 0.0 in set(ts.data["contact_fl_foot"]) and set(ts.data["contact_fr_foot"]) == {1.0}
    assert "valid" in validate_dataset(ds).summary()


# ----------------------------------------------------------------------------- bad input


def _tiny_bag(path: Path, stamps, *, fmt: str = "ros1", imu_only: bool = False, version: int = 9,
              custom: bool = False) -> Path:
    """A small log written with rosbags: JointState (or only Imu) at ``stamps`` (s); ``custom``: a
    foot-force message of a type no store knows (``my_msgs/msg/FootForce``)."""
    from rosbags.typesys import get_types_from_msg

    from graphcal.logs.reader import default_typestore

    ts = default_typestore("ros1" if fmt == "ros1" else "ros2")
    foot_def = "std_msgs/Header header\nfloat32[4] force\n"
    if custom:
        ts.register(get_types_from_msg(foot_def, "my_msgs/msg/FootForce"))
    T = ts.types
    if fmt == "ros1":
        from rosbags.rosbag1 import Writer

        w = Writer(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        w = Writer(path, version=version, storage_plugin=StoragePlugin.SQLITE3)
    ser = ts.serialize_ros1 if fmt == "ros1" else ts.serialize_cdr

    def header(t):
        stamp = T["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t % 1) * 1e9)))
        return T["std_msgs/msg/Header"](**({"seq": 0} if fmt == "ros1" else {}), stamp=stamp, frame_id="")

    with w:
        typ = "sensor_msgs/msg/Imu" if imu_only else "sensor_msgs/msg/JointState"
        c = w.add_connection("/imu" if imu_only else "/joint_states", typ, typestore=ts)
        cf = w.add_connection("/foot_force", "my_msgs/msg/FootForce", typestore=ts) if custom else None
        v = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=9.81)
        for i, t in enumerate(stamps):
            if imu_only:
                msg = T[typ](header=header(t), orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                             orientation_covariance=np.zeros(9), angular_velocity=v,
                             angular_velocity_covariance=np.zeros(9), linear_acceleration=v,
                             linear_acceleration_covariance=np.zeros(9))
            else:
                msg = T[typ](header=header(t), name=OCTOPUS_JOINTS, position=np.zeros(len(OCTOPUS_JOINTS)),
                             velocity=np.zeros(0), effort=np.zeros(0))
            w.write(c, int(1e9 * (100 + 0.01 * i)), ser(msg, typ))
            if cf is not None:
                foot = T["my_msgs/msg/FootForce"](header=header(t), force=np.full(4, 100.0, dtype=np.float32))
                w.write(cf, int(1e9 * (100 + 0.01 * i)) + 1, ser(foot, "my_msgs/msg/FootForce"))
    return path


@pytest.fixture(scope="module")
def urdf_file(tmp_path_factory):
    from graphcal.models.builtin import builtin_urdf

    p = tmp_path_factory.mktemp("urdf") / "robot.urdf"
    p.write_text(builtin_urdf("octopus"))
    return p


@pytest.fixture(scope="module")
def small_logs(sim, tmp_path_factory):
    """A short ROS 1 bag and a ROS 2 MCAP bag of the simulated session."""
    d = tmp_path_factory.mktemp("logs")
    plan = dict(rate_hz=50.0, cloud_rate_hz=2.0, still_s=1.5, move_s=0.5, decoys=False)
    write_station_log(sim, d / "log.bag", LogPlan(fmt="ros1", **plan))
    write_station_log(sim, d / "mcap", LogPlan(fmt="mcap", **plan))
    write_station_log(sim, d / "sqlite", LogPlan(fmt="sqlite3", **plan))
    return d


def _fails(capsys, tmp_path, args, *words):
    """graphcal import ... exits 2 with one line naming ``words`` and leaves no dataset behind."""
    out = tmp_path / "ds"
    rc = main(["import", *map(str, args), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert len(err.splitlines()) == 1, err
    for w in words:
        assert w in err, (w, err)
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".ds")]
    return err


def _map_with(tmp_path, log, **changes) -> Path:
    """The detected map of ``log`` with top-level entries replaced."""
    from graphcal.logs.mapping import detect_map, map_yaml_text
    from graphcal.logs.reader import LogReader

    with LogReader(log) as r:
        m = detect_map(r.topics, ("lf_foot",))
    m["robot"].update(base_frame="body", feet=[f"{leg}_foot" for leg in ("lf", "lm", "lr", "rf", "rm", "rr")])
    m.update(changes)
    p = tmp_path / "map.yaml"
    p.write_text(map_yaml_text(m))
    return p


def test_topic_missing_or_of_the_wrong_type(small_logs, tmp_path, capsys):
    log = small_logs / "log.bag"
    _fails(capsys, tmp_path, [log, "--map", _map_with(tmp_path, log, joints={"topic": "/nope"})],
           "topic /nope (joints.topic)", "expected a topic of the log")
    _fails(capsys, tmp_path, [log, "--map", _map_with(tmp_path, log, imu={"topic": "/joint_states"})],
           "topic /joint_states (imu.topic)", "sensor_msgs/msg/Imu", "got sensor_msgs/msg/JointState")
    imu_only = _tiny_bag(tmp_path / "imu.bag", [100.0, 100.01], imu_only=True)
    _fails(capsys, tmp_path, [imu_only], "joints.topic", "sensor_msgs/msg/JointState", "none in the log")


@pytest.mark.parametrize("stamps, words", [([100.0, 100.01, 100.01], "a duplicated stamp"),
                                           ([100.0, 100.02, 100.01], "a stamp 0.010000 s before the previous one")])
def test_duplicated_or_backwards_stamps(stamps, words, urdf_file, tmp_path, capsys):
    log = _tiny_bag(tmp_path / "j.bag", stamps)
    err = _fails(capsys, tmp_path, [log, "--urdf", urdf_file], "/joint_states", words, "strictly increasing")
    assert f"t = {stamps[2]:.6f} s" in err


def test_truncated_or_corrupt_logs(small_logs, tmp_path, capsys):
    bag = small_logs / "log.bag"
    cut = tmp_path / "cut.bag"
    cut.write_bytes(bag.read_bytes()[: bag.stat().st_size // 2])
    _fails(capsys, tmp_path, [cut], "cut.bag", "expected a readable ROS 1 bag")
    mcap = next((small_logs / "mcap").glob("*.mcap"))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(mcap.read_bytes()[: mcap.stat().st_size * 2 // 3])
    _fails(capsys, tmp_path, [cut], "cut.mcap", "MCAP")
    bad = tmp_path / "sqlite"
    shutil.copytree(small_logs / "sqlite", bad)
    db = next(bad.glob("*.db3"))
    data = bytearray(db.read_bytes())
    data[4096: 4096 + 20000] = b"\xff" * 20000
    db.write_bytes(bytes(data))
    _fails(capsys, tmp_path, [bad], "sqlite", "ROS 2 bag")


def test_unknown_message_type_needs_its_definition(urdf_file, tmp_path, capsys):
    """A ROS 2 bag without message definitions (as older recorders wrote them): the custom foot-force
    type is unknown until --msg-dir gives its .msg."""
    import sqlite3

    log = _tiny_bag(tmp_path / "custom", [100 + 0.01 * i for i in range(300)], fmt="sqlite3", custom=True)
    with sqlite3.connect(next(log.glob("*.db3"))) as db:
        db.execute("DELETE FROM message_definitions")
    m = _map_with(tmp_path, log, feet={"lf_foot": {"topic": "/foot_force", "kind": "array", "field": "force",
                                                  "index": 0}}, imu=None, sensors={})
    _fails(capsys, tmp_path, [log, "--map", m, "--urdf", urdf_file], "topic /foot_force",
           "expected a known message type", "--msg-dir", "my_msgs/msg/FootForce")
    msg = tmp_path / "msgs" / "my_msgs" / "msg"
    msg.mkdir(parents=True)
    (msg / "FootForce.msg").write_text("std_msgs/Header header\nfloat32[4] force\n")
    result = import_log.run(log, tmp_path / "ok", map_path=m, urdf=urdf_file, msg_dir=tmp_path / "msgs",
                            progress=False)
    assert result.n_stations == 1


@pytest.fixture(scope="module")
def csv_log(tmp_path_factory):
    d = tmp_path_factory.mktemp("csv")
    _sensorless_stations(d / "a1", seed=2, n_stations=2)
    _, cmap = write_station_csv(d / "a1", d / "log.csv", LogPlan(rate_hz=100.0, still_s=1.5, move_s=0.5, decoys=False))
    return d / "log.csv", yaml.safe_load(cmap)


@pytest.mark.parametrize("change, words", [
    (lambda m: m["imu"].update(gyro=["gyro_x", "gyro_y", "gyro_q"]), ["column 'gyro_q' (imu.gyro[2]"]),
    (lambda m: m["time"].update(unit="s"), ["column time_ms", "median step 10 s", "another unit"]),
    (lambda m: m["imu"].update(accel_unit="m/s^2"), ["columns acc_x, acc_y, acc_z", "median 1 m/s²"]),
    (lambda m: m["feet"]["fl_foot"].pop("column"), ["feet.fl_foot.column", "a column None"]),
])
def test_csv_columns_missing_or_in_the_wrong_unit(csv_log, change, words, tmp_path, capsys):
    log, cmap = csv_log
    cmap = yaml.safe_load(yaml.safe_dump(cmap))
    change(cmap)
    (tmp_path / "map.yaml").write_text(yaml.safe_dump(cmap))
    _fails(capsys, tmp_path, [log, "--map", tmp_path / "map.yaml"], "log.csv", *words)


def test_csv_joint_column_in_degrees(csv_log, tmp_path, capsys):
    log, cmap = csv_log
    rows = log.read_text().splitlines()
    header = rows[0].split(",")
    j = header.index("q2")
    bad = []
    for r in rows[1:]:
        cells = r.split(",")
        cells[j] = repr(float(np.degrees(float(cells[j]))))
        bad.append(",".join(cells))
    p = tmp_path / "deg.csv"
    p.write_text("\n".join([rows[0], *bad]) + "\n")
    (tmp_path / "map.yaml").write_text(yaml.safe_dump(cmap))
    _fails(capsys, tmp_path, [p, "--map", tmp_path / "map.yaml"], "row 1, column q2", "within ±2π rad",
           "another unit")
    rows[4] = "x" + rows[4][rows[4].index(","):]
    p.write_text("\n".join(rows) + "\n")
    _fails(capsys, tmp_path, [p, "--map", tmp_path / "map.yaml"], "row 4, column time_ms", "expected a number", "got x")


def test_receive_time_and_clock_jumps(sim, small_logs, urdf_file, tmp_path):
    """--receive-time finds the same stations (receive times are the header stamps plus < 1 ms
    here); a 5 s gap in the stamps is reported as a clock jump, not refused."""
    by_header = import_log.run(small_logs / "log.bag", tmp_path / "a", progress=False)
    by_receive = import_log.run(small_logs / "log.bag", tmp_path / "b", receive_time=True, progress=False)
    assert by_header.n_stations == N_STATIONS and by_receive.n_stations == N_STATIONS
    assert "stamps: receive" in (tmp_path / "b" / "import_map.yaml").read_text()
    # a recorder whose clock is 100 s ahead of the robot's: the stations by header stamps still find
    # their clouds (looked for at the receive times the offset predicts)
    plan = LogPlan(fmt="ros1", rate_hz=50.0, cloud_rate_hz=2.0, still_s=1.5, move_s=0.5, decoys=False,
                   receive_offset_s=100.0)
    write_station_log(sim, tmp_path / "late.bag", plan)
    assert import_log.run(tmp_path / "late.bag", tmp_path / "d", progress=False).n_stations == N_STATIONS
    stamps = [100 + 0.01 * i for i in range(50)] + [106 + 0.01 * i for i in range(50)]
    log = _tiny_bag(tmp_path / "gap.bag", stamps)
    result = import_log.run(log, tmp_path / "c", urdf=urdf_file, timeseries=True, progress=False)
    report = yaml.safe_load((tmp_path / "c" / "import_report.yaml").read_text())
    assert len(report["clock"]) == 1 and "clock jump of 5.510 s at t = 100.490000 s" in report["clock"][0]
    assert result.report == report and result.warnings == tuple(report["clock"])
    assert result.warnings[0].startswith("/joint_states: clock jump")
    assert "warning: /joint_states: clock jump" in result.summary_text()  # said on the console


def test_points_from_messages():
    """PointCloud2 with an extra field and row padding, LaserScan with out-of-range beams, a 16UC1
    depth image: the points (m) each message type means, exactly."""
    from graphcal.logs import messages as M
    from graphcal.logs.reader import default_typestore

    T = default_typestore("ros2").types
    hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=5, nanosec=250_000_000), frame_id="s")
    # x y z float32, intensity float32 first: point_step 16, 2 x 2 points, each row padded by 8 bytes
    pts = np.array([[1, 2, 3], [4, 5, np.nan], [7, 8, 9], [-1, -2, -3]], dtype=np.float32)
    rows = []
    for r in range(2):
        rec = b"".join(np.float32(0.5).tobytes() + pts[2 * r + c].tobytes() for c in range(2))
        rows.append(rec + b"\0" * 8)
    fields = [T["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=7, count=1)
              for n, o in (("intensity", 0), ("x", 4), ("y", 8), ("z", 12))]
    cloud = T["sensor_msgs/msg/PointCloud2"](header=hdr, height=2, width=2, fields=fields, is_bigendian=False,
                                             point_step=16, row_step=40, data=np.frombuffer(b"".join(rows), np.uint8),
                                             is_dense=False)
    np.testing.assert_array_equal(M.cloud_points(cloud), [[1, 2, 3], [7, 8, 9], [-1, -2, -3]])
    scan = T["sensor_msgs/msg/LaserScan"](header=hdr, angle_min=0.0, angle_max=np.pi, angle_increment=np.pi / 2,
                                          time_increment=0.0, scan_time=0.0, range_min=0.1, range_max=10.0,
                                          ranges=np.array([1.0, 20.0, 2.0], np.float32), intensities=np.zeros(0, np.float32))
    np.testing.assert_allclose(M.laser_scan_points(scan), [[1, 0, 0], [-2, 0, 0]], atol=1e-12)
    depth = np.zeros((3, 4), "<u2")
    depth[2, 3] = 1500  # 1.5 m at pixel (u=3, v=2)
    img = T["sensor_msgs/msg/Image"](header=hdr, height=3, width=4, encoding="16UC1", is_bigendian=0, step=8,
                                     data=np.frombuffer(depth.tobytes(), np.uint8))
    fx, fy, cx, cy = 100.0, 50.0, 1.0, 0.5
    np.testing.assert_allclose(M.depth_image_points(img, np.array([fx, fy, cx, cy])),
                               [[(3 - cx) * 1.5 / fx, (2 - cy) * 1.5 / fy, 1.5]])
    assert M.header_stamp(img) == 5.25
