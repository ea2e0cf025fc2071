"""The simulator's dataset writers, each folder written atomically: a station session
(:class:`~graphcal.simulation.session.SimulationResult`: the contract's files and ``truth.yaml``) and a
walk (:class:`~graphcal.simulation.walking.WalkingResult`: ``timeseries.csv`` with time, q_*, tau_*,
imu_*, cloud_depth, contact_* and force_* with force sensors, the clouds, ``truth.yaml`` and
``truth_trajectory.csv`` -- time, T_world_body, world velocity, IMU biases at ``truth_rate_hz`` --
which only evaluations read). SI units (m, rad, s, N, N m, m/s^2, rad/s)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.io.calibration_yaml import pose_to_dict
from graphcal.simulation.session import SimulationResult
from graphcal.simulation.walking import WalkingConfig, WalkingResult, simulate_walking

__all__ = ["SIMULATION_FILES", "TRUTH_TRAJECTORY_FILE", "result_to_dataset", "clouds_written", "write_simulation",
           "truth_table", "force_counts_of", "walking_dataset", "truth_dict", "write_walking", "simulate_walking_to_folder",
           "write_real_like"]

#: a walk's true trajectory, beside its dataset.yaml
TRUTH_TRAJECTORY_FILE = "truth_trajectory.csv"
#: what a simulation writes at the top of its folder (the contract's files and truth.yaml)
SIMULATION_FILES = frozenset({"dataset.yaml", "stations.csv", "timeseries.csv", "planes.csv", "mocap.csv",
                              "robot.urdf", "clouds", "truth.yaml", TRUTH_TRAJECTORY_FILE})


def result_to_dataset(result: SimulationResult, *, with_planes: bool, progress: bool = False):
    """The simulated data as a contract :class:`~graphcal.io.dataset.Dataset` (planes fitted from
    the clouds when ``with_planes``)."""
    from graphcal.clouds.plane_table import planes_rows
    from graphcal.geometry import xyz_quat_wxyz_from_pose
    from graphcal.io.dataset import Dataset, ImuSpec, PosePrior, RobotSpec, SensorSpec, Table
    from graphcal.simulation.session import robot_and_info

    _, info = robot_and_info(result.config)
    sensors = {
        name: SensorSpec(name, cad.type, PosePrior.from_matrix(cad.T_body_sensor, cad.sigma_m, cad.sigma_rad))
        for name, cad in result.sensor_cad.items()
    }
    imu = ImuSpec(PosePrior.from_matrix(info.T_body_imu, 0.0, float(np.radians(1.0))))
    recs = result.stations
    cols: dict[str, list] = {"station": [r.station for r in recs], "session": [r.session for r in recs],
                             "time": [r.time_s for r in recs]}
    for joint in recs[0].q_measured:
        cols[f"q_{joint}"] = [r.q_measured[joint] for r in recs]
    poses = [xyz_quat_wxyz_from_pose(r.T_world_body_cmd) for r in recs]
    for k, c in enumerate("xyz"):
        cols[f"body_{c}"] = [p[0][k] for p in poses]
    for k, c in enumerate(("qw", "qx", "qy", "qz")):
        cols[f"body_{c}"] = [p[1][k] for p in poses]
    for k, c in enumerate("xyz"):
        cols[f"imu_a{c}"] = [r.imu_accel[k] for r in recs]
    for k, c in enumerate("xyz"):
        cols[f"imu_g{c}"] = [r.imu_gyro[k] for r in recs]
    planes = None
    if with_planes:
        types = {n: s.type for n, s in sensors.items()}
        max_planes = 4 if result.config.ground == "stairs" else 1
        rows = planes_rows(result.clouds, types, max_planes=max_planes, seed=result.config.seed, progress=progress)
        if rows["station"]:
            planes = Table.from_columns(rows)
    return Dataset(
        robot=RobotSpec(
            urdf="robot.urdf" if result.config.custom_robot is not None else None,
            model=None if result.config.custom_robot is not None else result.robot_name,
            base_frame=info.base_frame,
            feet=info.feet,
        ),
        sensors=sensors,
        imu=imu,
        ground={"type": "level"},
        stance={"feet_fixed_within": "session"},
        stations=Table.from_columns(cols),
        planes=planes,
        extra={"physical_noise": physical_noise_declared(result.config)},
    )


def physical_noise_declared(config) -> dict:
    """What the simulator declares in dataset.yaml's ``physical_noise:`` (deg, mm), as a producer
    declares its hardware's noise (docs/calibration.md, "Does the model fit?"): its encoder noise
    (and unseen joint flex), point feet (contact 0), the ground's bump RMS, the IMU's accelerometer
    bias and noise as an attitude, the body's scatter about its set pose from the servos' tracking
    error (about half the per-joint tracking sigma, 3 mm; measured 1-2 mm and ~0.1 deg, docs/simulation.md)."""
    g = 9.81
    return {
        "joint_deg": float(np.degrees(np.hypot(config.encoder_sigma_rad, config.joint_flex_sigma_rad))),
        "contact_mm": 0.0,
        "ground_mm": {"bumpy-little": 3.0, "bumpy-big": 10.0}.get(config.ground, 0.0),  # terrain.py's RMS
        "imu_deg": float(np.degrees(np.hypot(config.imu_accel_bias_sigma_m_s2, config.imu_accel_sigma_m_s2) / g)),
        "commanded_deg": float(np.degrees(config.tracking_sigma_rad) / 2.0),
        "commanded_mm": 3.0,
    }


def clouds_written(result: SimulationResult, output: str) -> dict:
    """(sensor, station) -> points of the clouds :func:`write_simulation` writes for ``output``:
    every non-empty one with ``clouds`` or ``both``; with ``planes`` only the laser scanners' (a
    scanner's data are its scan points, a 2D scan has no plane to fit: ``--output planes`` would
    otherwise leave it without data)."""
    from graphcal.models.sensors import sensor_type

    scans = {n for n, cad in result.sensor_cad.items() if not sensor_type(cad.type).fits_planes}
    return {k: v for k, v in result.clouds.items() if len(v) and (output in ("clouds", "both") or k[0] in scans)}


def write_simulation(result: SimulationResult, out_dir: str | Path, *, output: str = "both",
                     overwrite: bool = False, progress: bool = False):
    """Write a simulation as a dataset folder: the contract's files (clouds and/or planes) and
    ``truth.yaml`` beside ``dataset.yaml``; a custom robot's URDF as ``robot.urdf``. Returns the
    written :class:`~graphcal.io.dataset.Dataset` (in memory).

    A station where a sensor saw nothing (every ray missed or fell outside the sensor's range: a
    depth camera mounted low, tilted towards the floor closer than its minimum range) has no cloud
    file for that sensor, as a real recording would have none; ``truth.yaml`` lists these under
    ``config: empty_clouds`` as ``[sensor, station]`` pairs. A laser scanner's scans are written as
    clouds with every ``output`` (its data are the scan points; it has no planes)."""
    import yaml

    from graphcal.io.dataset import write_dataset

    if output not in ("clouds", "planes", "both"):
        raise GraphcalError(f"output must be clouds, planes or both, got {output!r}")
    ds = result_to_dataset(result, with_planes=output in ("planes", "both"), progress=progress)
    clouds = clouds_written(result, output)
    empty = sorted([str(s), int(st)] for (s, st), v in result.clouds.items() if not len(v))
    truth = dict(result.truth)
    c = result.config
    truth["config"] = {
        "robot": c.robot, "program": c.program, "ground": c.ground, "seed": int(c.seed),
        "n_sessions": int(c.n_sessions), "output": output, "cloud_stride": int(c.cloud_stride),
        "leg_error_sigma_rad": float(c.leg_error_sigma_rad), "leg_error_sigma_m": float(c.leg_error_sigma_m),
        "empty_clouds": empty,
    }
    urdf = c.custom_robot.urdf_xml if c.custom_robot is not None else None
    write_dataset(ds, out_dir, clouds=clouds, robot_urdf_xml=urdf, overwrite=overwrite,
                  extra_files={"truth.yaml": yaml.safe_dump(truth, sort_keys=False)})
    return ds


# ----------------------------------------------------------------------------- walks
def truth_table(result: WalkingResult):
    """The truth trajectory at ``truth_rate_hz``: a :class:`~graphcal.io.dataset.Table`-like dict of
    columns time, x, y, z, qw, qx, qy, qz (T_world_body), vx, vy, vz (world), gyro/accel biases."""
    c = result.config
    step = max(1, int(round(c.rate_hz / c.truth_rate_hz)))
    idx = np.arange(0, len(result.times), step)
    T = result.T_world_body[idx]
    from graphcal.geometry import quat_wxyz_from_matrix_batch

    q = quat_wxyz_from_matrix_batch(T[:, :3, :3])
    cols = {"time": result.times[idx]}
    for k, n in enumerate("xyz"):
        cols[n] = T[:, k, 3]
    for k, n in enumerate(("qw", "qx", "qy", "qz")):
        cols[n] = q[:, k]
    for k, n in enumerate(("vx", "vy", "vz")):
        cols[n] = result.v_world_body[idx, k]
    for k, n in enumerate(("bgx", "bgy", "bgz")):
        cols[n] = result.gyro_bias[idx, k]
    for k, n in enumerate(("bax", "bay", "baz")):
        cols[n] = result.accel_bias[idx, k]
    return cols


def _truth_csv_text(cols: dict) -> str:
    """``truth_trajectory.csv``: a header line and the columns at 10 significant digits."""
    names = list(cols)
    A = np.column_stack([cols[n] for n in names])
    import io

    buf = io.StringIO()
    buf.write(",".join(names) + "\n")
    np.savetxt(buf, A, delimiter=",", fmt="%.10g")
    return buf.getvalue()


def force_counts_of(force_n: np.ndarray, feet, force_counts: dict) -> np.ndarray:
    """Foot loads (N, n_feet) in N as a real sensor's raw counts: ``round(offset + force / gain)``
    with ``force_counts`` foot -> (offset counts, gain N per count) (the import map's ``offset`` and
    ``scale``: force_N = (raw - offset) * scale)."""
    missing = [f for f in feet if f not in force_counts]
    if missing:
        raise GraphcalError(f"force_counts: expected (offset, gain) for every foot, missing {', '.join(missing)}")
    offset = np.array([float(force_counts[f][0]) for f in feet])
    gain = np.array([float(force_counts[f][1]) for f in feet])
    if not np.all(gain > 0):
        raise GraphcalError(f"force_counts: expected gains > 0 (N per count), got {gain.tolist()}")
    return np.round(offset + np.asarray(force_n, dtype=float) / gain)


def walking_dataset(result: WalkingResult, cloud_names: list[str] | None = None, *, force_counts: dict | None = None):
    """The walk as a contract :class:`~graphcal.io.dataset.Dataset` (timeseries only).
    ``cloud_names``: relative PLY path per cloud (default ``clouds/depth/<frame>.ply``).
    ``force_counts``: foot -> (offset, gain N/count): ``force_<foot>`` written as raw counts of a
    real sensor (:func:`force_counts_of`) instead of N."""
    from graphcal.io.dataset import Dataset, ImuSpec, PosePrior, RobotSpec, SensorSpec, Table

    info = result.info
    N = len(result.times)
    cols: dict[str, object] = {"time": np.round(result.times, 9)}
    for f in result.feet:
        for name in result.robot.leg(f).joint_names:
            cols[f"q_{name}"] = result.q_measured[name]
    for f in result.feet:
        for name in result.robot.leg(f).joint_names:
            cols[f"tau_{name}"] = result.tau_measured[name]
    for k, n in enumerate("xyz"):
        cols[f"imu_a{n}"] = result.imu_accel[:, k]
    for k, n in enumerate("xyz"):
        cols[f"imu_g{n}"] = result.imu_gyro[:, k]
    sensors = {}
    if len(result.cloud_indices):
        names = cloud_names or [f"clouds/depth/{j:05d}.ply" for j in range(len(result.cloud_indices))]
        col = np.full(N, "", dtype=object)
        delay = int(round(result.config.camera_delay_s * result.config.rate_hz))  # stamped late
        rows = result.cloud_indices + delay
        keep = rows < N
        col[rows[keep]] = np.asarray(names, dtype=object)[keep]
        cols["cloud_depth"] = col.astype(str)
        cad = info.sensors["depth"]
        T_cad = result.T_body_sensor_cad if result.T_body_sensor_cad is not None else cad.T_body_sensor
        sensors["depth"] = SensorSpec("depth", cad.type, PosePrior.from_matrix(T_cad, cad.sigma_m, cad.sigma_rad))
    for i, f in enumerate(result.feet):
        cols[f"contact_{f}"] = result.contact[:, i].astype(float)
    if result.foot_force is not None:
        force = result.foot_force if force_counts is None else force_counts_of(result.foot_force, result.feet,
                                                                               force_counts)
        for i, f in enumerate(result.feet):
            cols[f"force_{f}"] = force[:, i]
    ground = {"type": "stairs"} if result.config.stairs else {"type": "level"}
    return Dataset(
        robot=RobotSpec(urdf=None, model=result.config.robot, base_frame=info.base_frame, feet=tuple(result.feet)),
        sensors=sensors,
        imu=ImuSpec(PosePrior.from_matrix(result.T_body_imu, 0.0, float(np.radians(1.0)))),
        ground=ground,
        stance={"feet_fixed_within": "step"},
        timeseries=Table.from_columns(cols),
    )


def truth_dict(result: WalkingResult) -> dict:
    """Plain dict for ``truth.yaml`` (what the walk hides)."""
    c = result.config
    stairs = [
        {"x_start_m": s.x_start_m, "depth_m": s.depth_m, "height_m": s.height_m, "width_m": s.width_m}
        for s in (result.terrain.stairs if result.terrain is not None else ())
    ]
    cfg = {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in c.__dict__.items()}
    return {
        "format": "graphcal-truth/1",
        "note": "hidden simulation truth; only evaluations read this file",
        "robot": c.robot,
        "program": c.program,
        "seed": int(c.seed),
        "ground": {"type": "stairs" if c.stairs else "level", "stairs": stairs},
        "trajectory": {"file": TRUTH_TRAJECTORY_FILE, "frame": "T_world_body",
                       "columns": "time, x, y, z, qw, qx, qy, qz (T_world_body), vx, vy, vz (world, m/s), "
                                  "bgx..bgz (gyro bias, rad/s), bax..baz (accel bias, m/s^2)"},
        "distance_m": result.distance_m,
        "gait": {"groups": [list(g) for g in result.groups], "cycle_s": c.cycle_s, "duty_factor": c.duty_factor,
                 **({"phase_offsets": dict(c.gait.phase_offsets)} if c.gait.phase_offsets else {})},
        "sensors": {"depth": {"type": "depth_camera", "T_body_sensor": pose_to_dict(result.T_body_sensor),
                              # the cloud stamp minus its capture time (s)
                              "time_offset_s": float(round(c.camera_delay_s * c.rate_hz) / c.rate_hz)}},
        "imu": {"T_body_imu": pose_to_dict(result.T_body_imu),
                "accel_bias_start_m_s2": [float(v) for v in result.accel_bias[0]],
                "gyro_bias_start_rad_s": [float(v) for v in result.gyro_bias[0]]},
        "body_mass_kg": c.body_mass_kg,
        "noise": {
            "encoder_sigma_rad": c.encoder_sigma_rad, "torque_sigma_nm": c.torque_sigma_nm,
            "gyro_noise_density": c.gyro_noise_density, "accel_noise_density": c.accel_noise_density,
            "gyro_bias_rw": c.gyro_bias_rw, "accel_bias_rw": c.accel_bias_rw,
        },
        "config": cfg,
    }


def write_walking(result: WalkingResult, out_dir: str | Path, *, overwrite: bool = False,
                  force_counts: dict | None = None) -> Path:
    """Write the walk as a dataset folder (contract files, clouds) with ``truth.yaml`` and
    ``truth_trajectory.csv`` beside it, atomically (:func:`graphcal.io.dataset.write_dataset`);
    ``force_counts`` as in :func:`walking_dataset` (raw counts in ``force_<foot>``)."""
    import yaml

    from graphcal.io.dataset import write_dataset

    out = Path(out_dir)
    c = result.config
    last = len(result.times) - 1 - int(round(c.camera_delay_s * c.rate_hz))  # a late stamp past the log's end: dropped
    names = [f"clouds/depth/{j:05d}.ply" if len(cl) and k <= last else ""
             for j, (k, cl) in enumerate(zip(result.cloud_indices, result.clouds))]
    ds = walking_dataset(result, names, force_counts=force_counts)  # a frame that saw nothing has no file
    extra = {
        "truth.yaml": yaml.safe_dump(truth_dict(result), sort_keys=False),
        TRUTH_TRAJECTORY_FILE: _truth_csv_text(truth_table(result)),
    }
    clouds = {n: cl for n, cl in zip(names, result.clouds) if n}
    write_dataset(ds, out, overwrite=overwrite, extra_files=extra, timeseries_clouds=clouds)
    return out


def simulate_walking_to_folder(
    *,
    program: str,
    out_dir: str | Path,
    robot: str | None = None,
    seed: int = 0,
    distance_m: float | None = None,
    duration_s: float | None = None,
    cloud_rate_hz: float | None = None,
    cloud_stride: int | None = None,
    overwrite: bool = False,
    progress: bool = True,
    real_like: bool = False,
    walk: dict | None = None,
) -> str:
    """``graphcal simulate --program tripod-walk|tripod-stairs|trot|walk``: simulate and write the folder
    (``real_like``: as a real robot's log, :mod:`graphcal.simulation.real_like`; ``walk``: more
    :class:`~graphcal.simulation.walking.WalkingConfig` fields). Returns a one-paragraph summary."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise GraphcalError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise GraphcalError(f"{out}: folder exists and is not empty; choose another --out or pass --overwrite")
    kw = dict(walk or {})
    if cloud_rate_hz is not None:
        kw["cloud_rate_hz"] = float(cloud_rate_hz)
    if cloud_stride is not None:
        kw["cloud_stride"] = int(cloud_stride)
    counts = None
    if real_like:
        from graphcal.simulation.real_like import real_like_log

        if distance_m is not None or kw:
            raise GraphcalError("--real-like takes --duration only (a 25 s log at 400 Hz by default, no clouds)")
        log = real_like_log(program, seed, **({"duration_s": duration_s} if duration_s is not None else {}))
        cfg, counts = log.config, log.force_counts
    else:
        cfg = WalkingConfig(program=program, robot=robot, seed=seed, distance_m=distance_m, duration_s=duration_s, **kw)
    result = simulate_walking(cfg, progress=progress)
    write_walking(result, out, overwrite=overwrite, force_counts=counts)
    c = result.config
    if real_like:
        return (f"wrote {out}: a real-like log of the {c.robot}'s {c.program}, {result.distance_m:.2f} m in "
                f"{result.times[-1]:.1f} s at {c.rate_hz:g} Hz: lying {c.lying_s:.1f} s, standing up, walking, "
                f"lying down; IMU at {tuple(round(v, 3) for v in c.imu_xyz_m)} m off the base; "
                f"{'raw foot counts with per-foot offsets and gains; ' if counts else 'joint torques; '}"
                f"noise drawn away from graphcal's defaults (truth.yaml); truth in {out / 'truth.yaml'}")
    return (
        f"wrote {out}: {c.program} of the {c.robot}, {result.distance_m:.2f} m in {result.times[-1]:.1f} s; "
        f"{len(result.times)} samples at {c.rate_hz:g} Hz (joints, torques, IMU), {len(result.cloud_indices)} depth "
        f"clouds at {c.cloud_rate_hz:g} Hz (stride {c.cloud_stride}){_hidden_camera_errors(result)}; truth in "
        f"{out / 'truth.yaml'} and {out / TRUTH_TRAJECTORY_FILE}"
    )


def _hidden_camera_errors(result: WalkingResult) -> str:
    """``, hidden: ...`` naming the camera's CAD error and stamp delay when the walk has them."""
    from graphcal.geometry import rotation_angle_between

    c, out = result.config, []
    if result.T_body_sensor_cad is not None and (c.cad_error_m > 0 or c.cad_error_rad > 0):
        dT = result.T_body_sensor_cad
        out.append(f"the CAD prior {1e3 * np.linalg.norm(dT[:3, 3] - result.T_body_sensor[:3, 3]):.1f} mm and "
                   f"{np.degrees(rotation_angle_between(dT[:3, :3], result.T_body_sensor[:3, :3])):.2f} deg off the truth")
    if c.camera_delay_s > 0:
        out.append(f"clouds stamped {1e3 * c.camera_delay_s:g} ms late")
    return f"; hidden: {', '.join(out)}" if out else ""


def write_real_like(log, out_dir: str | Path, *, overwrite: bool = False) -> Path:
    """Simulate a :class:`~graphcal.simulation.real_like.RealLikeLog` and write it as a dataset folder
    with its truth (raw counts when the robot has foot-force sensors; :func:`write_walking`)."""
    result = simulate_walking(log.config)
    return write_walking(result, out_dir, overwrite=overwrite, force_counts=log.force_counts)
