"""An "independent tool" writes a dataset following only the contract (docs/dataset.md), without any
graphcal code: its own hexapod URDF, YAML written as text, CSV with Python's csv module (CRLF line
ends, its own column order), clouds written with Open3D directly (binary and ASCII), clouds of the
timeseries in a folder of its choosing. graphcal must read and validate it, values intact."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from graphcal.errors import DatasetError
from graphcal.io import cloud_paths, load_cloud, load_dataset_robot, read_dataset, validate_dataset

LEGS = {  # leg name -> (hip position in base_link, m; yaw of the leg, deg)
    "L1": ((0.20, 0.10, 0.0), 45.0),
    "L2": ((0.00, 0.14, 0.0), 90.0),
    "L3": ((-0.20, 0.10, 0.0), 135.0),
    "R1": ((0.20, -0.10, 0.0), -45.0),
    "R2": ((0.00, -0.14, 0.0), -90.0),
    "R3": ((-0.20, -0.10, 0.0), -135.0),
}
LEG_XML = """
  <link name="{n}_coxa_link"><inertial><mass value="0.1"/><inertia ixx="1e-4" iyy="1e-4" izz="1e-4" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="{n}_thigh_link"><inertial><mass value="0.2"/><inertia ixx="1e-4" iyy="1e-4" izz="1e-4" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="{n}_shin_link"><inertial><mass value="0.1"/><inertia ixx="1e-4" iyy="1e-4" izz="1e-4" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <link name="{n}_toe"/>
  <joint name="{n}_yaw" type="revolute">
    <parent link="base_link"/><child link="{n}_coxa_link"/>
    <origin xyz="{x} {y} {z}" rpy="0 0 {yaw}"/><axis xyz="0 0 1"/>
    <limit lower="-0.8" upper="0.8" effort="10" velocity="5"/>
  </joint>
  <joint name="{n}_hip" type="revolute">
    <parent link="{n}_coxa_link"/><child link="{n}_thigh_link"/>
    <origin xyz="0.05 0 0" rpy="0 0 0"/><axis xyz="0 -1 0"/>
    <limit lower="-1.5" upper="1.5" effort="10" velocity="5"/>
  </joint>
  <joint name="{n}_knee" type="revolute">
    <parent link="{n}_thigh_link"/><child link="{n}_shin_link"/>
    <origin xyz="0.12 0 0" rpy="0 0 0"/><axis xyz="0 -1 0"/>
    <limit lower="-2.5" upper="2.5" effort="10" velocity="5"/>
  </joint>
  <joint name="{n}_toe_fixed" type="fixed">
    <parent link="{n}_shin_link"/><child link="{n}_toe"/>
    <origin xyz="0.16 0 0" rpy="0 0 0"/>
  </joint>
"""
URDF = (
    '<?xml version="1.0"?>\n<robot name="indie_hexapod">\n'
    '  <link name="base_link"><inertial><mass value="2.0"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial></link>\n'
    '  <link name="cam_optical"/>\n'
    '  <joint name="cam_fixed" type="fixed"><parent link="base_link"/><child link="cam_optical"/>'
    '<origin xyz="0.25 0 0.05" rpy="-1.5707963 0 -1.5707963"/></joint>\n'
    + "".join(
        LEG_XML.format(n=n, x=p[0], y=p[1], z=p[2], yaw=math.radians(yaw)) for n, (p, yaw) in LEGS.items()
    )
    + "</robot>\n"
)
FEET = [f"{n}_toe" for n in LEGS]
JOINTS = [f"{n}_{j}" for n in LEGS for j in ("yaw", "hip", "knee")]

DATASET_YAML = """\
# written by indie-tool 3.1, not by graphcal
format: graphcal-dataset/1
producer: {name: indie-tool, version: 3.1}      # not in the contract: kept, ignored
robot:
  urdf: robot.urdf
  base_frame: base_link
  feet:
""" + "".join(f"    - {f}\n" for f in FEET) + """\
sensors:
  front_cam:
    type: stereo_camera
    baseline_m: 0.12
    T_body_sensor_prior:
      xyz: [0.25, 0, 0.05]
      rpy_deg: [-90, 0, -90]
      sigma_mm: 2.5e1
      sigma_rpy_deg: 3
  rear_lidar:
    type: laser_scanner
    T_body_sensor_prior: {xyz: [-0.22, 0.0, 0.08], rpy_deg: [0.0, 0.0, 180.0], sigma_mm: 10, sigma_rpy_deg: 2.0}
imu:
  T_body_imu_prior:
    xyz: [0.0, 0.0, 0.02]
    rpy_deg: [0, 0, 0]
    sigma_mm: 0
    sigma_rpy_deg: 0.5
  noise_density: 0.0002
ground:
  type: level
stance:
  feet_fixed_within: session
"""


def g17(v: float) -> str:
    return format(float(v), ".17g")


def write_csv(path: Path, header, rows) -> None:
    with open(path, "w", newline="") as f:  # csv's default line end is CRLF
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)


def write_independent_dataset(root: Path) -> dict:
    rng = np.random.default_rng(42)
    root.mkdir()
    (root / "robot.urdf").write_text(URDF)
    (root / "dataset.yaml").write_text(DATASET_YAML)

    n = 8
    station = np.arange(n)  # ids from 0
    session = ["1", "1", "1", "1", "2", "2", "2", "2"]
    time = 12.0 + 2.0 * np.arange(n) + rng.uniform(0, 0.5, n)
    q = rng.uniform(-0.4, 0.4, (n, len(JOINTS)))
    tau = rng.normal(0, 1, (n, 3))
    body_xyz = np.column_stack([rng.normal(0, 0.02, n), rng.normal(0, 0.02, n), 0.15 + rng.normal(0, 0.01, n)])
    quat = rng.normal(size=(n, 4)) * [0.05, 1, 1, 1]  # arbitrary sign of w too
    quat[:, 0] += np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    acc = np.column_stack([rng.normal(0, 0.2, n), rng.normal(0, 0.2, n), 9.81 + rng.normal(0, 0.01, n)])
    gyr = rng.normal(0, 1e-3, (n, 3))
    header = (["session", "time"] + ["imu_gx", "imu_gy", "imu_gz"] + ["station"] + [f"q_{j}" for j in JOINTS]
              + ["body_qw", "body_qx", "body_qy", "body_qz", "body_x", "body_y", "body_z"]
              + ["imu_ax", "imu_ay", "imu_az"] + ["tau_L1_yaw", "tau_L1_hip", "tau_L1_knee"])  # fmt: skip
    rows = []
    for i in range(n):
        rows.append([session[i], g17(time[i])] + [g17(v) for v in gyr[i]] + [str(station[i])]
                    + [g17(v) for v in q[i]] + [g17(v) for v in quat[i]] + [g17(v) for v in body_xyz[i]]
                    + [g17(v) for v in acc[i]] + [g17(v) for v in tau[i]])  # fmt: skip
    write_csv(root / "stations.csv", header, rows)

    # clouds: binary for the camera (every station), ASCII for the lidar (one station)
    clouds = {}
    for s in station:
        pts = rng.normal(0, 0.3, (200, 3)) + [0, 0, 1.2]
        (root / "clouds" / "front_cam").mkdir(parents=True, exist_ok=True)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        assert o3d.io.write_point_cloud(str(root / "clouds" / "front_cam" / f"{s}.ply"), pcd)
        clouds[("front_cam", int(s))] = pts
    (root / "clouds" / "rear_lidar").mkdir(parents=True)
    lidar = rng.uniform(-4, 4, (90, 3)) * [1, 1, 0.001]  # a 2-D scan: within 4 mm of its plane z = 0
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(lidar))
    assert o3d.io.write_point_cloud(str(root / "clouds" / "rear_lidar" / "2.ply"), pcd, write_ascii=True)
    clouds[("rear_lidar", 2)] = lidar

    # planes, own column order, no covariance
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    d = rng.uniform(0.5, 1.5, n)
    write_csv(root / "planes.csv", ["sensor", "station", "d", "nx", "ny", "nz", "rms"],
              [["front_cam", str(s), g17(d[i]), *map(g17, normals[i]), "0.003"] for i, s in enumerate(station)])

    # motion capture at the station times: body markers and feet (two markers on L1_toe)
    mrows = []
    for i in range(n):
        for name in ["body.1", "body.2", "body.3", "body.4", "L1_toe.1", "L1_toe.2", "R3_toe"]:
            mrows.append([g17(time[i]), name, *map(g17, rng.normal(0, 0.5, 3))])
    write_csv(root / "mocap.csv", ["time", "marker", "x", "y", "z"], mrows)

    # a short timeseries with its clouds stored in a folder of the tool's choosing
    m = 5
    ts_time = 100.0 + 0.01 * np.arange(m)
    ts_q = rng.uniform(-0.3, 0.3, (m, len(JOINTS)))
    (root / "scans" / "front").mkdir(parents=True)
    ts_rows = []
    for k in range(m):
        cloud = ""
        if k % 2 == 0:
            cloud = f"scans/front/{k:06d}.ply"
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rng.normal(0, 1, (40, 3)) + [0, 0, 2]))
            assert o3d.io.write_point_cloud(str(root / cloud), pcd)
        ts_rows.append([g17(ts_time[k])] + [g17(v) for v in ts_q[k]] + [cloud, "1", str(k % 2)])
    write_csv(root / "timeseries.csv", ["time"] + [f"q_{j}" for j in JOINTS] + ["cloud_front_cam", "contact_L1_toe",
                                                                                 "contact_R1_toe"], ts_rows)
    return dict(station=station, session=session, time=time, q=q, tau=tau, body_xyz=body_xyz, quat=quat, acc=acc,
                gyr=gyr, clouds=clouds, normals=normals, d=d, ts_time=ts_time, ts_q=ts_q, n_mocap=len(mrows))


def test_independent_dataset_reads_and_validates(tmp_path):
    root = tmp_path / "indie"
    truth = write_independent_dataset(root)
    assert b"\r\n" in (root / "stations.csv").read_bytes()

    report = validate_dataset(root)
    assert report.warnings == ()
    assert report.robot == "URDF robot.urdf"
    assert (report.n_stations, report.n_sessions, report.n_planes) == (8, 2, 8)
    assert report.n_clouds == 8 + 1 + 3 and report.n_mocap_rows == truth["n_mocap"]
    assert report.sensors == ("front_cam", "rear_lidar")

    ds = read_dataset(root)
    assert ds.robot.urdf == "robot.urdf" and ds.robot.base_frame == "base_link" and ds.robot.feet == tuple(FEET)
    assert ds.extra == {"producer": {"name": "indie-tool", "version": 3.1}}
    assert ds.sensors["front_cam"].type == "stereo_camera"
    assert ds.sensors["front_cam"].extra == {"baseline_m": 0.12}
    prior = ds.sensors["front_cam"].T_body_sensor_prior
    assert prior.xyz.tolist() == [0.25, 0.0, 0.05]
    assert prior.rpy_rad.tolist() == [math.radians(-90), 0.0, math.radians(-90)]
    assert prior.sigma_m == 0.025 and prior.sigma_rad == math.radians(3)
    # the optical frame as the tool's URDF places it (z forward, x right)
    assert np.allclose(prior.matrix[:3, :3] @ [0, 0, 1], [1, 0, 0], atol=1e-12)
    assert np.allclose(prior.matrix[:3, :3] @ [1, 0, 0], [0, -1, 0], atol=1e-12)
    assert ds.imu.T_body_imu_prior.sigma_m == 0.0 and ds.imu.extra == {"noise_density": 0.0002}

    st = ds.stations
    assert st["station"].tolist() == truth["station"].tolist()
    assert st["session"].tolist() == truth["session"]
    assert np.array_equal(st["time"], truth["time"])
    for k, j in enumerate(JOINTS):
        assert np.array_equal(st[f"q_{j}"], truth["q"][:, k])
    assert np.array_equal(np.column_stack([st[f"tau_L1_{j}"] for j in ("yaw", "hip", "knee")]), truth["tau"])
    assert np.array_equal(np.column_stack([st[c] for c in ("body_qw", "body_qx", "body_qy", "body_qz")]), truth["quat"])
    assert np.array_equal(np.column_stack([st[c] for c in ("body_x", "body_y", "body_z")]), truth["body_xyz"])
    assert np.array_equal(np.column_stack([st[c] for c in ("imu_ax", "imu_ay", "imu_az")]), truth["acc"])
    assert np.array_equal(np.column_stack([st[c] for c in ("imu_gx", "imu_gy", "imu_gz")]), truth["gyr"])

    assert ds.planes.columns == ("sensor", "station", "d", "nx", "ny", "nz", "rms")
    assert np.array_equal(ds.planes["d"], truth["d"])
    assert np.array_equal(np.column_stack([ds.planes[c] for c in ("nx", "ny", "nz")]), truth["normals"])
    assert np.array_equal(ds.timeseries["time"], truth["ts_time"])
    assert ds.timeseries["cloud_front_cam"].tolist() == ["scans/front/000000.ply", "", "scans/front/000002.ply", "",
                                                         "scans/front/000004.ply"]  # fmt: skip
    assert ds.timeseries["contact_R1_toe"].tolist() == [0.0, 1.0, 0.0, 1.0, 0.0]

    assert set(cloud_paths(ds)) == set(truth["clouds"])
    for (sensor, station), pts in truth["clouds"].items():
        got = load_cloud(ds, sensor, station)
        if sensor == "front_cam":
            assert np.array_equal(got, pts)  # binary PLY: exact
        else:
            assert np.allclose(got, pts, rtol=1e-5, atol=1e-5)  # Open3D's ASCII writer: 6 digits

    robot = load_dataset_robot(ds)
    assert robot.base_frame == "base_link" and set(robot.feet) == set(FEET)
    for n in LEGS:
        assert robot.legs[f"{n}_toe"].joint_names == (f"{n}_yaw", f"{n}_hip", f"{n}_knee")


def test_independent_dataset_with_only_a_timeseries(tmp_path):
    root = tmp_path / "indie"
    write_independent_dataset(root)
    for f in ("stations.csv", "planes.csv", "mocap.csv"):
        (root / f).unlink()
    for p in sorted((root / "clouds").rglob("*.ply")):
        p.unlink()
    report = validate_dataset(root)
    assert report.n_stations == 0 and report.n_timeseries_rows == 5 and report.n_clouds == 3
    assert report.warnings == ("sensor 'rear_lidar' has no cloud and no plane",)
    # a cloud no row names (the file cut short): the message says so, not "a station id of stations.csv"
    stray = root / "clouds" / "front_cam" / "00006.ply"
    stray.parent.mkdir(parents=True, exist_ok=True)
    stray.write_bytes((root / "scans" / "front" / "000000.ply").read_bytes())
    with pytest.raises(DatasetError, match=r"00006\.ply: file name: .*cloud_front_cam cell of timeseries\.csv, got "
                                           r"00006\.ply \(no stations\.csv, and no row of timeseries\.csv names it\)"):
        validate_dataset(root)


@pytest.mark.parametrize("fmt", ["binary_big_endian", "ascii_float_xyz_with_normals"])
def test_other_ply_flavours(tmp_path, fmt):
    """Big-endian binary and float32 ASCII with extra properties (as other tools write them)."""
    root = tmp_path / "indie"
    write_independent_dataset(root)
    pts = np.array([[0.5, -0.25, 1.0], [0.125, 0.0, 2.0]])
    if fmt == "binary_big_endian":
        head = (b"ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty double x\nproperty double y\n"
                b"property double z\nend_header\n")  # fmt: skip
        (root / "clouds/front_cam/3.ply").write_bytes(head + pts.astype(">f8").tobytes())
    else:
        text = ("ply\nformat ascii 1.0\ncomment from another tool\nelement vertex 2\nproperty float x\nproperty float y\n"
                "property float z\nproperty float nx\nproperty float ny\nproperty float nz\nend_header\n"
                "0.5 -0.25 1.0 0 0 1\n0.125 0 2 0 0 1\n")  # fmt: skip
        (root / "clouds/front_cam/3.ply").write_text(text)
    validate_dataset(root)
    assert np.array_equal(load_cloud(read_dataset(root), "front_cam", 3), pts)


@pytest.mark.parametrize("layout", ["f8_le", "f4_le_rgb", "f4_be_normals_intensity", "camera_element_first", "face_list_after"])
def test_binary_ply_decoded_like_open3d(tmp_path, layout):
    """The binary fast path of read_ply (a structured view of the bytes) gives exactly what Open3D's
    reader gives, for layouts other tools write: float32 with colours, big-endian with extra
    properties, a fixed-size element before the vertices, and a face list after them."""
    import open3d as o3d

    from graphcal.io.ply import read_ply

    rng = np.random.default_rng(7)
    n = 257
    pts = rng.normal(0.0, 2.0, (n, 3))
    if layout == "f8_le":
        head, props = b"format binary_little_endian 1.0\n", [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    elif layout == "f4_le_rgb":
        head = b"format binary_little_endian 1.0\n"
        props = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    else:
        head = b"format binary_big_endian 1.0\n" if layout.startswith("f4_be") else b"format binary_little_endian 1.0\n"
        e = ">" if layout.startswith("f4_be") else "<"
        props = [("nx", e + "f4"), ("x", e + "f4"), ("y", e + "f4"), ("intensity", e + "u2"), ("z", e + "f4"),
                 ("ny", e + "f4"), ("nz", e + "f4")]
    names = {"<f8": "double", "<f4": "float", ">f4": "float", "u1": "uchar", "<u2": "ushort", ">u2": "ushort"}
    rec = np.zeros(n, dtype=props)
    for j, a in enumerate("xyz"):
        rec[a] = pts[:, j]
    for name, dt in props:
        if name not in "xyz":
            rec[name] = rng.integers(0, 200, n) if dt.endswith(("u1", "u2")) else rng.normal(size=n)
    header = b"ply\n" + head
    pre = post = b""
    if layout == "camera_element_first":
        header += b"element camera 1\nproperty float view_px\nproperty float view_py\n"
        pre = np.array([1.5, -2.5], dtype="<f4").tobytes()
    header += b"element vertex %d\n" % n + b"".join(b"property %s %s\n" % (names[dt].encode(), nm.encode()) for nm, dt in props)
    if layout == "face_list_after":
        header += b"element face 1\nproperty list uchar int vertex_indices\n"
        post = np.array([3], dtype="u1").tobytes() + np.array([0, 1, 2], dtype="<i4").tobytes()
    path = tmp_path / "cloud.ply"
    path.write_bytes(header + b"end_header\n" + pre + rec.tobytes() + post)

    got = read_ply(path)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        ref = np.asarray(o3d.io.read_point_cloud(str(path), format="ply").points)
    expected = np.column_stack([rec[a].astype(np.float64) for a in "xyz"])
    assert got.dtype == np.float64 and got.shape == (n, 3)
    assert np.array_equal(got, expected)
    assert np.array_equal(got, ref)


def test_ascii_ply_read_by_property_position_and_checked_line_by_line(tmp_path):
    """ASCII PLY as other tools may write it: x, y, z in any order among other properties, a list
    property, a face element after the vertices. Open3D's reader gave uninitialised memory for a
    z, y, x order and shifted every point after a line with one value too many."""
    from graphcal.io.ply import read_ply

    pts = np.array([[0.5, -0.25, 1.0], [0.125, 0.0, 2.0], [-1.5, 3.25, 0.75]])
    zyx = "".join(f"{z!r} {y!r} {x!r}\n" for x, y, z in pts.tolist())
    head = "ply\nformat ascii 1.0\nelement vertex 3\nproperty double z\nproperty double y\nproperty double x\n"
    (tmp_path / "zyx.ply").write_text(head + "end_header\n" + zyx)
    assert np.array_equal(read_ply(tmp_path / "zyx.ply"), pts)
    # a list property inside the vertex element, and a face element after it
    rows = "".join(f"2 {k} {k + 1} {z!r} 7 {x!r} {y!r}\n" for k, (x, y, z) in enumerate(pts.tolist()))
    text = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty list uchar int idx\nproperty double z\n"
            "property uchar label\nproperty double x\nproperty double y\nelement face 1\n"
            "property list uchar int vertex_indices\nend_header\n" + rows + "3 0 1 2\n")
    (tmp_path / "list.ply").write_text(text)
    assert np.array_equal(read_ply(tmp_path / "list.ply"), pts)
    # one value too many on line 2 and one too few on line 3: the same number of values in all
    bad = "ply\nformat ascii 1.0\nelement vertex 3\nproperty double x\nproperty double y\nproperty double z\n"
    (tmp_path / "shifted.ply").write_text(bad + "end_header\n0.5 -0.25 1.0\n0.125 0.0 2.0 -1.5\n3.25 0.75\n")
    with pytest.raises(DatasetError, match=r"shifted\.ply: line 2 after the header \(vertex 2\): expected 3 values"):
        read_ply(tmp_path / "shifted.ply")


def test_binary_ply_with_a_list_property_needs_x_y_z_first(tmp_path):
    """Binary files with list properties go to Open3D, whose reader needs x, y, z first: read
    right when they are, refused (not read as uninitialised memory) when they are not."""
    from graphcal.io.ply import read_ply

    pts = np.array([[0.5, -0.25, 1.0], [0.125, 0.0, 2.0]])
    for order, name in (("xyz", "ok.ply"), ("zyx", "zyx.ply")):
        head = b"ply\nformat binary_little_endian 1.0\nelement vertex 2\n" + b"".join(
            b"property double %s\n" % a.encode() for a in order) + b"property list uchar int idx\nend_header\n"
        body = b"".join(np.array([p["xyz".index(a)] for a in order], "<f8").tobytes()
                        + np.array([1], "u1").tobytes() + np.array([k], "<i4").tobytes() for k, p in enumerate(pts))
        (tmp_path / name).write_bytes(head + body)
    assert np.array_equal(read_ply(tmp_path / "ok.ply"), pts)
    with pytest.raises(DatasetError, match=r"zyx\.ply: header: expected vertex properties that begin x, y, z"):
        read_ply(tmp_path / "zyx.ply")
