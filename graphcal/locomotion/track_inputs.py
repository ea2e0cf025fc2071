"""What the legged EKF reads (:class:`TrackInputs`), from a contract dataset (``timeseries.csv``:
time, q_*, tau_* (or contact_* / force_*), imu_*, cloud_<sensor>) or an in-memory simulated walk.
Arrays over N samples; SI units; IMU readings in the IMU frame, clouds in the sensor frame."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from graphcal.errors import DatasetError

__all__ = ["TrackInputs", "inputs_from_dataset", "inputs_from_walking", "MAX_GAP_S", "MAX_GAP_SAMPLES"]


@dataclass(frozen=True, eq=False)
class TrackInputs:
    """What the filter reads (arrays over N samples).

    Attributes:
        times: (N,) s, increasing. gyro: (N, 3) rad/s; accel: (N, 3) m/s^2 (IMU frame).
        robot: :class:`~graphcal.models.robot.RobotModel`; groups: the two tripods (foot names) of
            a two-tripod gait, or () for any other gait (a stance mask per sample, every foot its
            own slot in the filter).
        q: joint name -> (N,) rad (every joint of the legs).
        tau: joint name -> (N,) N m, or None (then ``force`` or ``contact`` must be given).
        contact: (N, n_feet) bool in ``robot.feet`` order, or None.
        force: (N, n_feet) foot loads in ``robot.feet`` order (N, foot-force sensors), or None;
            when given, the stance of every foot is read from it (any gait, not the tripods').
        T_body_imu: (4, 4).
        clouds: sample index -> loader returning (M, 3) points in the sensor frame (m).
        T_body_sensor: (4, 4) of the cloud sensor; sensor_type: its dataset type.
        source: where the data came from (for messages).
        p_body_foot: (n_feet, N, 3) body-frame foot points (m) in ``robot.feet`` order, measured
            instead of joint angles (a robot given by its feet: legs without joints, ``q`` empty;
            timeseries.csv's ``p_body_<foot>_x/_y/_z``), or None (forward kinematics of ``q``).
        p_body_measured: (N,) bool, the samples where those points were measured (``p_body_measured``
            1; elsewhere they are interpolated for the stance's bookkeeping and not used as a
            measurement), or None (every sample).
    """

    times: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    robot: object
    groups: tuple
    q: dict
    tau: dict | None = None
    contact: np.ndarray | None = None
    T_body_imu: np.ndarray = field(default_factory=lambda: np.eye(4))
    clouds: dict = field(default_factory=dict)
    T_body_sensor: np.ndarray | None = None
    sensor_type: str = "depth_camera"
    source: str = "data"
    force: np.ndarray | None = None
    p_body_foot: np.ndarray | None = None
    p_body_measured: np.ndarray | None = None


# ----------------------------------------------------------------------------- inputs
#: the longest gap in timeseries.csv's time the filter integrates the IMU across: this, or this
#: many median sample intervals if longer (measured: a 10 s gap tilted the estimate 36 deg and
#: lifted it 0.11 m without a word; a 1 h gap made the stance update's matrix singular)
MAX_GAP_S = 0.5
MAX_GAP_SAMPLES = 100


def _gait_groups(ds, robot) -> tuple:
    """The two tripods of dataset.yaml's ``gait.groups`` or the built-in model's; () when neither
    gives any (any other gait: the stance of every foot is read from its own load)."""
    spec = ds.extra.get("gait", {}) if isinstance(ds.extra, dict) else {}
    groups = spec.get("groups") if isinstance(spec, dict) else None
    yaml_file = ds.root / "dataset.yaml" if ds.root is not None else "dataset.yaml"
    if groups is None and ds.robot is not None and ds.robot.model is not None:
        from graphcal.models.builtin import builtin_info

        groups = builtin_info(ds.robot.model).gait_groups or None
    if groups is None:
        return ()
    if (not isinstance(groups, (list, tuple)) or len(groups) != 2
            or any(not isinstance(g, (list, tuple)) or len(g) != len(groups[0]) or len(g) < 3 for g in groups)):
        raise DatasetError(yaml_file, "gait.groups", "two lists of the same number (>= 3) of foot frames", groups)
    for g in groups:
        for f in g:
            if f not in robot.feet:
                raise DatasetError(yaml_file, "gait.groups", f"foot frames of robot.feet ({', '.join(robot.feet)})", f)
    return tuple(tuple(g) for g in groups)


def inputs_from_dataset(ds, *, sensor: str | None = None) -> TrackInputs:
    """Filter inputs from a contract dataset (read with :func:`graphcal.io.dataset.read_dataset`).

    Raises DatasetError naming ``timeseries.csv`` and the column when something the filter needs is
    missing (the IMU columns; torques or contacts; at least two samples)."""
    from graphcal.io.dataset import load_dataset_robot

    root = ds.root
    ts_file = root / "timeseries.csv" if root is not None else "timeseries.csv"
    yaml_file = root / "dataset.yaml" if root is not None else "dataset.yaml"
    t = ds.timeseries
    if t is None:
        raise DatasetError(ts_file, "file", "a timeseries (state estimation reads timeseries.csv)", "none")
    if ds.robot is None:
        raise DatasetError(yaml_file, "robot", "a robot (legged state estimation needs its legs)", "none")
    for c in ("imu_ax", "imu_ay", "imu_az", "imu_gx", "imu_gy", "imu_gz"):
        if not t.has(c):
            raise DatasetError(ts_file, f"header, column {c}", "the IMU columns imu_ax..imu_az, imu_gx..imu_gz",
                               "missing")
    if len(t) < 2:
        raise DatasetError(ts_file, "rows", "at least two samples", len(t))
    times = np.asarray(t["time"], dtype=float)
    if np.any(np.diff(times) <= 0):
        i = int(np.argmax(np.diff(times) <= 0)) + 1
        raise DatasetError(ts_file, f"row {i + 1}, column time", "strictly increasing times (one sample per time)",
                           float(times[i]))
    dt = np.diff(times)
    gap_limit = max(MAX_GAP_S, MAX_GAP_SAMPLES * float(np.median(dt)))
    if np.any(dt > gap_limit):
        i = int(np.argmax(dt > gap_limit)) + 1
        raise DatasetError(ts_file, f"row {i + 1}, column time",
                           f"samples without a gap longer than {gap_limit:.3g} s (the IMU cannot be integrated "
                           f"across one; recordings joined, or samples lost: split the file there)",
                           f"{float(times[i]):.6g} s after {float(times[i - 1]):.6g} s (gap {float(dt[i - 1]):.3g} s; "
                           f"median interval {float(np.median(dt)) * 1e3:.3g} ms)")
    robot = load_dataset_robot(ds)
    groups = _gait_groups(ds, robot)
    q = {}
    tau: dict | None = {}
    for f in robot.feet:
        for j in robot.leg(f).joint_names:
            q[j] = np.asarray(t[f"q_{j}"], dtype=float)
            if tau is not None and t.has(f"tau_{j}"):
                tau[j] = np.asarray(t[f"tau_{j}"], dtype=float)
            else:
                tau = None
    contact = None
    force = None
    if all(t.has(f"force_{f}") for f in robot.feet):
        force = np.column_stack([np.asarray(t[f"force_{f}"], dtype=float) for f in robot.feet])
    if not tau:  # legs without joints (a robot given by its feet): no torques
        tau = None
    p_body_foot = _foot_points(t, robot, ts_file)
    measured = np.asarray(t["p_body_measured"], dtype=float) > 0.5 if p_body_foot is not None and t.has(
        "p_body_measured") else None
    if tau is None and force is None:
        missing = [f for f in robot.feet if not t.has(f"contact_{f}")]
        if missing:
            joint = next((j for f in robot.feet for j in robot.leg(f).joint_names if not t.has(f"tau_{j}")), None)
            if joint is None:
                raise DatasetError(ts_file, f"header, column contact_{missing[0]}", "contact_<foot> of every foot "
                                   "(a robot given by its feet has no torques)", "missing")  # fmt: skip
            raise DatasetError(ts_file, f"header, column tau_{joint}", "joint torques tau_<joint> of every leg joint "
                               "(support detection), force_<foot> or contact_<foot> of every foot", "missing")  # fmt: skip
        contact = np.column_stack([t[f"contact_{f}"] > 0.5 for f in robot.feet])
        if not contact.any():
            raise DatasetError(ts_file, f"columns contact_{robot.feet[0]}..contact_{robot.feet[-1]}",
                               "at least one foot on the ground (1) at some time (support detection reads them when "
                               "there are no joint torques)", "0 in every row")
    T_body_imu = ds.imu.T_body_imu_prior.matrix if ds.imu is not None else np.eye(4)
    clouds: dict = {}
    T_body_sensor = None
    sensor_type = "depth_camera"
    cloud_sensors = [s for s in t.suffixes("cloud_") if s in ds.sensors]
    if sensor is not None and sensor not in cloud_sensors:
        raise DatasetError(ts_file, f"header, column cloud_{sensor}", "the clouds of the requested sensor", "missing")
    name = sensor or (cloud_sensors[0] if cloud_sensors else None)
    if name is not None:
        from graphcal.io.dataset.cloud_files import read_cloud  # the same checks as validate's

        spec = ds.sensors[name]
        T_body_sensor = spec.T_body_sensor_prior.matrix
        sensor_type = spec.type
        for i, rel in enumerate(t[f"cloud_{name}"].tolist()):
            if rel:
                path = Path(root) / rel.replace("\\", "/")
                clouds[i] = (lambda p=path: read_cloud(p))
    return TrackInputs(
        times=times,
        gyro=np.column_stack([t["imu_gx"], t["imu_gy"], t["imu_gz"]]).astype(float),
        accel=np.column_stack([t["imu_ax"], t["imu_ay"], t["imu_az"]]).astype(float),
        robot=robot, groups=groups, q=q, tau=tau, contact=contact, T_body_imu=T_body_imu,
        clouds=clouds, T_body_sensor=T_body_sensor, sensor_type=sensor_type, source=str(ts_file), force=force,
        p_body_foot=p_body_foot, p_body_measured=measured,
    )


def _foot_points(t, robot, ts_file) -> np.ndarray | None:
    """(n_feet, N, 3) ``p_body_<foot>_x/_y/_z`` (m) when the legs have no joints (a robot given by
    its feet), None when they have joints; DatasetError naming the first missing column."""
    if any(robot.leg(f).n_joints for f in robot.feet):
        return None
    out = np.empty((len(robot.feet), len(t), 3))
    for i, f in enumerate(robot.feet):
        for a, ax in enumerate("xyz"):
            c = f"p_body_{f}_{ax}"
            if not t.has(c):
                raise DatasetError(ts_file, f"header, column {c}", "the body-frame foot points p_body_<foot>_x/_y/_z "
                                   "of every foot (the robot's legs have no joints)", "missing")  # fmt: skip
            out[i, :, a] = np.asarray(t[c], dtype=float)
    return out


def inputs_from_walking(result, *, clouds: bool = True) -> TrackInputs:
    """Filter inputs from a :class:`graphcal.simulation.walking.WalkingResult` (in memory; only
    what the dataset would hold: measured joints, torques, IMU, clouds, CAD extrinsics)."""
    info = result.info
    cl = {}
    if clouds:
        cl = {int(k): (lambda a=a: a) for k, a in zip(result.cloud_indices, result.clouds) if len(a)}
    T_bs = np.asarray(info.sensors["depth"].T_body_sensor) if "depth" in info.sensors else None
    return TrackInputs(
        times=result.times, gyro=result.imu_gyro, accel=result.imu_accel, robot=result.robot,
        groups=tuple(result.groups), q=result.q_measured, tau=result.tau_measured,
        T_body_imu=np.asarray(result.T_body_imu), clouds=cl, T_body_sensor=T_bs, source="simulation",
        force=result.foot_force,
    )


# ----------------------------------------------------------------------------- the loop
