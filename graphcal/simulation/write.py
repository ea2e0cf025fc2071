"""The simulator's dataset writer: a :class:`~graphcal.simulation.session.SimulationResult` as a
dataset folder (the contract's files and ``truth.yaml``), written atomically."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.simulation.session import SimulationResult

__all__ = ["SIMULATION_FILES", "result_to_dataset", "clouds_written", "write_simulation"]

#: what a simulation writes at the top of its folder (the contract's files and truth.yaml)
SIMULATION_FILES = frozenset({"dataset.yaml", "stations.csv", "timeseries.csv", "planes.csv", "mocap.csv",
                              "robot.urdf", "clouds", "truth.yaml", "truth_trajectory.csv"})



def result_to_dataset(result: SimulationResult, *, with_planes: bool, progress: bool = False):
    """The simulated data as a contract :class:`~graphcal.io.dataset.Dataset` (planes fitted from
    the clouds when ``with_planes``)."""
    from graphcal.geometry import xyz_quat_wxyz_from_pose
    from graphcal.io.dataset import Dataset, ImuSpec, PosePrior, RobotSpec, SensorSpec, Table
    from graphcal.clouds.plane_table import planes_rows
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
