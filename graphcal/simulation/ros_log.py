"""A continuous robot log (ROS 1 bag, ROS 2 bag in sqlite3 or MCAP) written with rosbags' own
writers from a simulated station dataset: the robot stands still at each station (joints, IMU and
clouds as the dataset has them) and moves between them (joints interpolated, the body turning), feet
loaded throughout; optional extra still periods that must be rejected (too short, a foot unloaded).
For the tests and the benchmark of ``graphcal import``. Times in s, SI units."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["LogPlan", "write_station_log", "write_station_csv", "write_walk_csv", "still_windows", "depth_image",
           "simulated_camera_intrinsics", "cloud_depth_image"]


@dataclass(frozen=True)
class LogPlan:
    """How the log is laid out.

    Attributes:
        fmt: ``ros1``, ``sqlite3`` or ``mcap`` (ROS 2 storages).
        rate_hz: joints, IMU and feet rate.
        cloud_rate_hz: points rate while still (Hz).
        still_s, move_s: time still at a station and moving between stations (s).
        t0: stamp of the first message (s).
        feet: ``wrench`` (one WrenchStamped topic per foot, N) or ``array`` (one Float32MultiArray
            of raw counts: raw = force / scale + offset).
        points: ``cloud`` (PointCloud2 from the station's cloud) or ``depth`` (32FC1 depth Image +
            CameraInfo of the simulated camera: each point of the station's cloud in its pixel, so
            the image carries the cloud's points, noise included; a dataset without clouds: the
            image is rendered noise-free from the station's plane in planes.csv, see
            :func:`depth_image`).
        decoys: append a 0.4 s still period and a 2 s still with one foot unloaded (both rejected).
        raw_offset, raw_scale: the ``array`` feet's count offset and N per count.
        embed_robot: publish the URDF on /robot_description.
        receive_offset_s: the recorder's clock minus the robot's (receive time = stamp + this).
    """

    fmt: str = "ros1"
    rate_hz: float = 200.0
    cloud_rate_hz: float = 5.0
    still_s: float = 2.0
    move_s: float = 1.0
    t0: float = 1000.0
    feet: str = "wrench"
    points: str = "cloud"
    decoys: bool = True
    raw_offset: float = 100.0
    raw_scale: float = 0.5
    embed_robot: bool = True
    receive_offset_s: float = 0.0
    extra: dict = field(default_factory=dict)


def still_windows(n_stations: int, plan: LogPlan) -> list[tuple[float, float]]:
    """The (start, end) of the simulated still windows of the stations (s)."""
    step = plan.still_s + plan.move_s
    return [(plan.t0 + k * step, plan.t0 + k * step + plan.still_s) for k in range(n_stations)]


class _Out:
    """rosbags writer + serialiser for one format."""

    def __init__(self, path: Path, fmt: str):
        from graphcal.logs.reader import default_typestore

        self.fmt = fmt
        self.ts = default_typestore("ros1" if fmt == "ros1" else "ros2")
        if fmt == "ros1":
            from rosbags.rosbag1 import Writer

            self.w = Writer(path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
            self.w = Writer(path, version=9, storage_plugin=plugin)
        self.conns: dict = {}
        self.T = self.ts.types
        self.shift = 0.0

    def __enter__(self):
        self.w.open()
        return self

    def __exit__(self, *a):
        self.w.close()

    def write(self, topic: str, msgtype: str, msg, t: float) -> None:
        if topic not in self.conns:
            kw = {"typestore": self.ts}
            self.conns[topic] = self.w.add_connection(topic, msgtype, **kw)
        ser = self.ts.serialize_ros1 if self.fmt == "ros1" else self.ts.serialize_cdr
        self.w.write(self.conns[topic], int(round((t + self.shift) * 1e9)), ser(msg, msgtype))

    def header(self, t: float, frame: str):
        T = self.T
        stamp = T["builtin_interfaces/msg/Time"](sec=int(np.floor(t)), nanosec=int(round((t - np.floor(t)) * 1e9)) % 10**9)
        if self.fmt == "ros1":
            return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)


def _vec(T, v):
    return T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _cloud_msg(o: _Out, t: float, frame: str, pts: np.ndarray):
    T = o.T
    data = np.ascontiguousarray(pts, dtype="<f4").tobytes()
    fields = [T["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
    return T["sensor_msgs/msg/PointCloud2"](header=o.header(t, frame), height=1, width=len(pts), fields=fields,
                                            is_bigendian=False, point_step=12, row_step=12 * len(pts),
                                            data=np.frombuffer(data, dtype=np.uint8), is_dense=True)


def depth_image(plane_nd: np.ndarray, K=(100.0, 100.0, 80.0, 60.0), shape=(120, 160)) -> np.ndarray:
    """(h, w) float32 depth (m, along z) of the plane n·p + d = 0 seen by a pinhole camera (optical
    frame, fx fy cx cy in pixels); 0 where the ray misses or is beyond 10 m."""
    fx, fy, cx, cy = K
    v, u = np.mgrid[0:shape[0], 0:shape[1]]
    n, d = plane_nd[:3], plane_nd[3]
    denom = n[0] * (u - cx) / fx + n[1] * (v - cy) / fy + n[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        z = -d / denom
    z[~np.isfinite(z) | (z <= 0.05) | (z > 10.0)] = 0.0
    return z.astype(np.float32)


def simulated_camera_intrinsics(sensor_type: str, stride: int = 1) -> tuple[tuple[float, float, float, float], tuple[int, int]]:
    """((fx, fy, cx, cy) px, (h, w)) of the camera the simulator casts its rays from
    (:func:`graphcal.models.sensors.sensor_for_type`, every ``stride``-th pixel row and column, same
    field of view), in the ROS convention: pixel centres at integer coordinates, so ``cx = w/2 - 0.5``
    (the simulator's rays go through ``u + 0.5 - w/2``)."""
    from graphcal.models.sensors import sensor_for_type
    from graphcal.simulation.session import strided

    cam = strided(sensor_for_type(sensor_type), int(stride))
    w, h = int(cam.width_px), int(cam.height_px)
    fx = w / 2.0 / np.tan(np.radians(cam.hfov_deg) / 2.0)
    fy = h / 2.0 / np.tan(np.radians(cam.vfov_deg) / 2.0)
    return (fx, fy, w / 2.0 - 0.5, h / 2.0 - 0.5), (h, w)


def cloud_depth_image(points: np.ndarray, K, shape) -> np.ndarray:
    """(h, w) float32 depth (m, along z) holding each point of a simulated camera cloud (N, 3),
    optical frame, in the pixel its ray went through (0 elsewhere). The simulator moves a point
    along its ray only (depth noise, range scale), so its pixel ``fx x / z + cx`` is an integer;
    ValueError for a point that is not on the pixel grid of ``K`` (another camera, a wrong stride)."""
    fx, fy, cx, cy = K
    h, w = shape
    P = np.asarray(points, dtype=np.float64)
    u = fx * P[:, 0] / P[:, 2] + cx
    v = fy * P[:, 1] / P[:, 2] + cy
    iu, iv = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
    off = (np.abs(u - iu) > 1e-3) | (np.abs(v - iv) > 1e-3) | (iu < 0) | (iu >= w) | (iv < 0) | (iv >= h)
    if off.any() or len(np.unique(iv * w + iu)) != len(P):
        raise ValueError(f"cloud_depth_image: {int(off.sum())} of {len(P)} points off the {w}x{h} pixel grid "
                         f"of K = {tuple(map(float, K))} (or two points in one pixel)")
    z = np.zeros((h, w), dtype=np.float32)
    z[iv, iu] = P[:, 2]
    return z


def _image_msgs(o: _Out, t: float, frame: str, z: np.ndarray, K):
    T = o.T
    h, w = z.shape
    img = T["sensor_msgs/msg/Image"](header=o.header(t, frame), height=h, width=w, encoding="32FC1",
                                     is_bigendian=0, step=4 * w,
                                     data=np.frombuffer(z.astype("<f4").tobytes(), dtype=np.uint8))
    k = np.array([K[0], 0, K[2], 0, K[1], K[3], 0, 0, 1], dtype=np.float64)
    kw = dict(header=o.header(t, frame), height=h, width=w, distortion_model="plumb_bob",
              binning_x=0, binning_y=0, roi=T["sensor_msgs/msg/RegionOfInterest"](
                  x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
    if o.fmt == "ros1":
        info = T["sensor_msgs/msg/CameraInfo"](D=np.zeros(5), K=k, R=np.eye(3).ravel(),
                                               P=np.zeros(12), **kw)
    else:
        info = T["sensor_msgs/msg/CameraInfo"](d=np.zeros(5), k=k, r=np.eye(3).ravel(), p=np.zeros(12), **kw)
    return img, info


def _static_tf(o: _Out, t: float, items):
    from graphcal.geometry import xyz_quat_wxyz_from_pose

    T = o.T
    tfs = []
    for parent, child, pose in items:
        xyz, q = xyz_quat_wxyz_from_pose(pose)
        tfs.append(T["geometry_msgs/msg/TransformStamped"](
            header=o.header(t, parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](translation=_vec(T, xyz), rotation=T[
                "geometry_msgs/msg/Quaternion"](x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])))))
    return T["tf2_msgs/msg/TFMessage"](transforms=tfs)


def _timeline(q_st: np.ndarray, plan: LogPlan):
    """Yield (t, q, phase, station index or -1, foot_unloaded_index or -1) at ``rate_hz``."""
    n = len(q_st)
    segments = []  # (duration, q_from, q_to, still, station, unloaded foot)
    for k in range(n):
        segments.append((plan.still_s, q_st[k], q_st[k], True, k, -1))
        if k + 1 < n:
            segments.append((plan.move_s, q_st[k], q_st[k + 1], False, -1, -1))
    if plan.decoys:
        away = q_st[-1] + 0.2
        segments += [(plan.move_s, q_st[-1], away, False, -1, -1), (0.4, away, away, True, -1, -1),
                     (plan.move_s, away, q_st[-1], False, -1, -1), (2.0, q_st[-1], q_st[-1], True, -1, 0),
                     (plan.move_s, q_st[-1], away, False, -1, -1)]
    else:
        segments.append((plan.move_s, q_st[-1], q_st[-1] + 0.2, False, -1, -1))
    dt = 1.0 / plan.rate_hz
    t_start = plan.t0
    for dur, qa, qb, still, station, unloaded in segments:
        m = int(round(dur * plan.rate_hz))
        for i in range(m):
            s = i / m
            yield t_start + i * dt, qa + (qb - qa) * s, still, station, unloaded
        t_start += m * dt


def write_station_log(dataset: str | Path, out: str | Path, plan: LogPlan = LogPlan()) -> list[tuple[float, float]]:
    """Write the log of a simulated station dataset (see the module docstring) to ``out`` (a
    ``.bag`` file for ros1, a folder otherwise); returns the true still windows (s)."""
    from graphcal.io.dataset import read_dataset
    from graphcal.io.ply import read_ply
    from graphcal.models.builtin import builtin_urdf

    ds = read_dataset(dataset)
    st = ds.stations.data
    joints = [c[2:] for c in ds.stations.columns if c.startswith("q_")]
    q_st = np.stack([st[f"q_{j}"] for j in joints], axis=1)
    acc = np.stack([st[f"imu_a{a}"] for a in "xyz"], axis=1)
    gyr = np.stack([st[f"imu_g{a}"] for a in "xyz"], axis=1)
    sensor = next(iter(ds.sensors))
    base, feet = ds.robot.base_frame, ds.robot.feet
    ids = st["station"]
    planes = {}
    depth_from_cloud = plan.points == "depth" and (Path(dataset) / "clouds" / sensor).is_dir()
    if plan.points == "depth" and not depth_from_cloud:
        p = ds.planes.data
        planes = {int(s): np.array([p["nx"][i], p["ny"][i], p["nz"][i], p["d"][i]])
                  for i, s in enumerate(p["station"]) if p["sensor"][i] == sensor}
    K, shape = (100.0, 100.0, 80.0, 60.0), (120, 160)
    if depth_from_cloud:
        # the camera the simulator cast its rays from: the image carries the station's cloud
        import yaml

        truth = Path(dataset) / "truth.yaml"
        stride = (yaml.safe_load(truth.read_text()).get("config") or {}).get("cloud_stride", 1) if truth.is_file() else 1
        K, shape = simulated_camera_intrinsics(ds.sensors[sensor].type, stride)
    with _Out(Path(out), plan.fmt) as o:
        T = o.T
        o.shift = plan.receive_offset_s
        if plan.embed_robot:
            o.write("/robot_description", "std_msgs/msg/String", T["std_msgs/msg/String"](data=builtin_urdf(ds.robot.model)),
                    plan.t0 - 0.5)
        o.write("/tf_static", "tf2_msgs/msg/TFMessage",
                _static_tf(o, plan.t0 - 0.5, [(base, sensor, ds.sensors[sensor].T_body_sensor_prior.matrix),
                                             (base, "imu_link", ds.imu.T_body_imu_prior.matrix)]), plan.t0 - 0.5)
        cloud_every = max(1, int(round(plan.rate_hz / plan.cloud_rate_hz)))
        cache: dict = {}
        for n, (t, q, still, k, unloaded) in enumerate(_timeline(q_st, plan)):
            js = T["sensor_msgs/msg/JointState"](header=o.header(t, ""), name=list(joints), position=q,
                                                 velocity=np.zeros(0), effort=np.zeros(0))
            o.write("/joint_states", "sensor_msgs/msg/JointState", js, t)
            kk = k if k >= 0 else len(q_st) - 1
            g = gyr[kk] if still else np.array([0.0, 0.0, 0.3])
            imu = T["sensor_msgs/msg/Imu"](header=o.header(t, "imu_link"),
                                           orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                                           orientation_covariance=np.full(9, -1.0), angular_velocity=_vec(T, g),
                                           angular_velocity_covariance=np.zeros(9),
                                           linear_acceleration=_vec(T, acc[kk]), linear_acceleration_covariance=np.zeros(9))
            o.write("/imu", "sensor_msgs/msg/Imu", imu, t + 1e-4)
            force = np.array([0.0 if i == unloaded else 150.0 for i in range(len(feet))])
            if plan.feet == "wrench":
                for i, f in enumerate(feet):
                    w = T["geometry_msgs/msg/WrenchStamped"](header=o.header(t, f), wrench=T["geometry_msgs/msg/Wrench"](
                        force=_vec(T, [0.0, 0.0, force[i]]), torque=_vec(T, [0.0, 0.0, 0.0])))
                    o.write(f"/foot_force/{f}", "geometry_msgs/msg/WrenchStamped", w, t + 2e-4)
            else:
                raw = (force / plan.raw_scale + plan.raw_offset).astype(np.float32)
                arr = T["std_msgs/msg/Float32MultiArray"](layout=T["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0),
                                                          data=raw)
                o.write("/foot_force", "std_msgs/msg/Float32MultiArray", arr, t + 2e-4)
            if still and n % cloud_every == cloud_every // 2:  # the decoys see the last station's view
                tc = t + 3e-4
                if kk not in cache:  # the station's cloud, or its depth image
                    if plan.points == "cloud" or depth_from_cloud:
                        pts = read_ply(Path(dataset) / "clouds" / sensor / f"{ids[kk]}.ply")
                        cache = {kk: pts if plan.points == "cloud" else cloud_depth_image(pts, K, shape)}
                    else:
                        cache = {kk: depth_image(planes[int(ids[kk])], K, shape)}
                if plan.points == "cloud":
                    o.write("/camera/points", "sensor_msgs/msg/PointCloud2", _cloud_msg(o, tc, sensor, cache[kk]), tc)
                else:
                    img, info = _image_msgs(o, tc, sensor, cache[kk], K)
                    o.write("/camera/depth/camera_info", "sensor_msgs/msg/CameraInfo", info, tc)
                    o.write("/camera/depth/image_raw", "sensor_msgs/msg/Image", img, tc)
    return still_windows(len(q_st), plan)


def write_station_csv(dataset: str | Path, out: str | Path, plan: LogPlan = LogPlan()) -> tuple[list, str]:
    """The same session as :func:`write_station_log` as a Unitree-style CSV export (``time_ms``,
    ``acc_x..z`` in g, ``gyro_x..z`` in rad/s, ``q0..q<n-1>`` in rad, ``foot_force_<i>`` raw counts:
    raw = force / raw_scale + raw_offset); returns (the true still windows in s, the column map YAML)."""
    import csv

    from graphcal.io.dataset import read_dataset

    ds = read_dataset(dataset)
    st = ds.stations.data
    joints = [c[2:] for c in ds.stations.columns if c.startswith("q_")]
    q_st = np.stack([st[f"q_{j}"] for j in joints], axis=1)
    acc = np.stack([st[f"imu_a{a}"] for a in "xyz"], axis=1)
    gyr = np.stack([st[f"imu_g{a}"] for a in "xyz"], axis=1)
    feet = ds.robot.feet
    g0 = 9.80665
    with open(out, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["time_ms", "acc_x", "acc_y", "acc_z", "gyro_x", "gyro_y", "gyro_z",
                    *[f"q{i}" for i in range(len(joints))], *[f"foot_force_{i}" for i in range(len(feet))]])
        for t, q, still, k, unloaded in _timeline(q_st, plan):
            kk = k if k >= 0 else len(q_st) - 1
            g = gyr[kk] if still else np.array([0.0, 0.0, 0.3])
            force = np.array([0.0 if i == unloaded else 150.0 for i in range(len(feet))])
            raw = np.round(force / plan.raw_scale + plan.raw_offset).astype(int)
            w.writerow([repr(float((t - plan.t0) * 1e3)), *[repr(float(x)) for x in (*(acc[kk] / g0), *g, *q)], *raw.tolist()])
    cmap = {"format": "graphcal-csv-map/1", "time": {"column": "time_ms", "unit": "ms"},
            "robot": {"model": ds.robot.model},
            "joints": {"unit": "rad", "columns": {j: f"q{i}" for i, j in enumerate(joints)}},
            "imu": {"accel": ["acc_x", "acc_y", "acc_z"], "accel_unit": "g", "gyro": ["gyro_x", "gyro_y", "gyro_z"],
                    "gyro_unit": "rad/s"},
            "feet": {foot: {"column": f"foot_force_{i}", "offset": plan.raw_offset, "scale": plan.raw_scale,
                            "threshold_n": 20.0} for i, foot in enumerate(feet)}}
    import yaml

    return [(a - plan.t0, b - plan.t0) for a, b in still_windows(len(q_st), plan)], yaml.safe_dump(cmap, sort_keys=False)


def write_walk_csv(dataset: str | Path, out: str | Path, *, raw_scale: float = 0.25, raw_offset: float = 40.0) -> str:
    """A simulated walk's ``timeseries.csv`` (with ``force_<foot>`` columns, e.g. ``graphcal simulate
    --robot a1 --program trot``) as a Unitree-style CSV export: ``time_ms``, ``acc_x..z`` in g,
    ``gyro_x..z`` in rad/s, ``q0..q<n-1>`` in rad and ``foot_force_<i>`` raw counts (raw = force N /
    ``raw_scale`` + ``raw_offset``, rounded); returns the column map YAML for ``graphcal import``."""
    import csv

    import yaml

    from graphcal.io.dataset import read_dataset

    ds = read_dataset(dataset)
    data = ds.timeseries.data
    joints = [c[2:] for c in ds.timeseries.columns if c.startswith("q_")]
    feet = list(ds.robot.feet)
    g0 = 9.80665
    acc = np.stack([data[f"imu_a{a}"] for a in "xyz"], axis=1) / g0
    gyr = np.stack([data[f"imu_g{a}"] for a in "xyz"], axis=1)
    q = np.stack([data[f"q_{j}"] for j in joints], axis=1)
    raw = np.round(np.stack([data[f"force_{f}"] for f in feet], axis=1) / raw_scale + raw_offset).astype(int)
    with open(out, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["time_ms", "acc_x", "acc_y", "acc_z", "gyro_x", "gyro_y", "gyro_z",
                    *[f"q{i}" for i in range(len(joints))], *[f"foot_force_{i}" for i in range(len(feet))]])
        for k, t in enumerate(data["time"]):
            w.writerow([repr(1e3 * float(t)), *map(repr, map(float, (*acc[k], *gyr[k], *q[k]))), *raw[k].tolist()])
    cmap = {"format": "graphcal-csv-map/1", "time": {"column": "time_ms", "unit": "ms"}, "robot": {"model": ds.robot.model},
            "joints": {"unit": "rad", "columns": {j: f"q{i}" for i, j in enumerate(joints)}},
            "imu": {"accel": ["acc_x", "acc_y", "acc_z"], "accel_unit": "g", "gyro": ["gyro_x", "gyro_y", "gyro_z"],
                    "gyro_unit": "rad/s"},
            "feet": {foot: {"column": f"foot_force_{i}", "offset": raw_offset, "scale": raw_scale, "threshold_n": 20.0}
                     for i, foot in enumerate(feet)}}
    return yaml.safe_dump(cmap, sort_keys=False)
