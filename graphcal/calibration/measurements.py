"""A dataset's stations as the arrays the calibration graph needs.

Everything is read from a :class:`graphcal.io.dataset.Dataset` (never from ``truth.yaml``):
joint angles per leg, commanded body poses, IMU specific force, the ground plane each camera saw
(``planes.csv``, or fitted here from the clouds) and laser-scanner points.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from graphcal.errors import DatasetError
from graphcal.geometry import pose_from_xyz_quat_wxyz
from graphcal.io.dataset import FEET_REPLANTED_AT_EACH_STATION
from graphcal.models.sensors import sensor_type


@dataclass(frozen=True, eq=False)
class PlaneMeasurement:
    """The ground plane seen by ``sensor`` at ``station``: (n, d) in the sensor frame (canonical,
    n points towards the sensor), its 4x4 covariance of (nx, ny, nz, d), inlier count and rms (m)."""

    station: int
    sensor: str
    n: np.ndarray
    d: float
    cov: np.ndarray
    n_points: int


@dataclass(frozen=True, eq=False)
class StationMeasurements:
    """What one static station measured.

    Attributes:
        station: id; session: stance label (feet planted within it).
        q_by_foot: foot -> (n,) measured joint angles of that leg (rad / m), Leg order.
        T_world_body_cmd: (4, 4) commanded pose, or None.
        imu_accel: (3,) specific force in the IMU frame (m/s^2), or None.
        stances: foot -> label of the stance it stands in (a walk: one per foot and touchdown), or
            None: every foot of ``q_by_foot`` stands in the session's stance.
        T_world_body_start: (4, 4) a start guess of the body pose carrying no information (a
            walk's leg odometry: its x, y and yaw start the solve), or None.
        time_s: log time of the joint angles (s; a walk's stations), or None.
    """

    station: int
    session: str
    q_by_foot: dict
    T_world_body_cmd: np.ndarray | None
    imu_accel: np.ndarray | None
    stances: dict | None = None
    T_world_body_start: np.ndarray | None = None
    time_s: float | None = None

    def stance_of(self, foot: str) -> str:
        """The label of the stance ``foot`` stands in (its planted point's)."""
        return self.stances[foot] if self.stances is not None else self.session


@dataclass(frozen=True, eq=False)
class CalibrationData:
    """Stations in file order, the planes per (station, sensor), and scan points per (station,
    sensor) for laser scanners (sensor frame, m)."""

    stations: tuple[StationMeasurements, ...]
    planes: dict
    scan_points: dict
    sensor_types: dict
    #: laser scanner -> ((cloud file, 90th percentile of |z|, m), ...) for its clouds that lie off
    #: its scan plane z = 0 (:data:`~graphcal.io.dataset.SCAN_PLANE_MAX_Z_M`), and its cloud count
    scans_off_plane: dict = field(default_factory=dict)
    #: (station, sensor) -> how many planes the camera saw there, where the floor taken (the plane
    #: the kinematics predict) is not the largest of them (stairs, a wall, a table)
    ground_not_largest: dict = field(default_factory=dict)


def station_measurements(ds, robot) -> tuple[StationMeasurements, ...]:
    """Per-station joint angles, commanded poses and IMU readings of ``ds`` (stations.csv)."""
    t = ds.stations
    if t is None:
        raise DatasetError(ds.root or "dataset", "stations.csv", "a stations.csv for a static calibration")
    n = len(t)
    sessions = t["session"] if t.has("session") else np.array(["default"] * n)
    if str(ds.stance.get("feet_fixed_within", "session")) in FEET_REPLANTED_AT_EACH_STATION:
        # dataset.yaml: the feet are re-planted at every station, so each is a stance of its own
        sessions = np.array([f"station {int(s)}" for s in t["station"]])
    has_cmd = t.has("body_x")
    has_imu = t.has("imu_ax")
    legs = {f: robot.leg(f) for f in robot.feet}
    out = []
    for i in range(n):
        q_by_foot = {}
        for f, leg in legs.items():
            if all(t.has(f"q_{j}") for j in leg.joint_names):
                q_by_foot[f] = np.array([t[f"q_{j}"][i] for j in leg.joint_names])
        T_cmd = None
        if has_cmd:
            T_cmd = pose_from_xyz_quat_wxyz(
                [t["body_x"][i], t["body_y"][i], t["body_z"][i]],
                np.array([t["body_qw"][i], t["body_qx"][i], t["body_qy"][i], t["body_qz"][i]])
                / np.linalg.norm([t["body_qw"][i], t["body_qx"][i], t["body_qy"][i], t["body_qz"][i]]),
            )
        accel = np.array([t["imu_ax"][i], t["imu_ay"][i], t["imu_az"][i]]) if has_imu else None
        out.append(StationMeasurements(int(t["station"][i]), str(sessions[i]), q_by_foot, T_cmd, accel))
    return tuple(out)


def plane_measurements_from_rows(rows: dict) -> dict:
    """(station, sensor) -> [:class:`PlaneMeasurement`, ...] largest first, from a planes table
    (planes.csv's columns, e.g. :func:`graphcal.clouds.plane_table.planes_rows`)."""
    out: dict = {}
    _plane_rows_to_measurements(rows, len(rows["station"]), out)
    for key in out:
        out[key].sort(key=lambda p: -p.n_points)
    return out


def _plane_rows_to_measurements(rows: dict, count: int, out: dict) -> None:
    """Append the first ``count`` rows of a planes table (planes.csv's columns) to ``out``:
    (station, sensor) -> [:class:`PlaneMeasurement`, ...] (sensor frame, m)."""
    for k in range(count):
        key = (int(rows["station"][k]), str(rows["sensor"][k]))
        npts = int(rows["n_points"][k]) if "n_points" in rows else 0
        if all(f"cov_{i}{j}" in rows for i in range(4) for j in range(4)):
            cov = np.array([[float(rows[f"cov_{i}{j}"][k]) for j in range(4)] for i in range(4)])
        else:
            cov = None
        n = np.array([float(rows["nx"][k]), float(rows["ny"][k]), float(rows["nz"][k])])
        out.setdefault(key, []).append(PlaneMeasurement(key[0], key[1], n, float(rows["d"][k]), cov, npts))


def plane_candidates(ds, *, progress: bool = False, plane_max_points: int | None = None) -> tuple[dict, object]:
    """The planes every camera saw: ((station, sensor) -> [:class:`PlaneMeasurement`, ...] largest
    first, ``refit``): from planes.csv when the dataset has it (every row; ``refit`` None),
    otherwise fitted to the clouds (the largest plane of each, on at most ``plane_max_points`` of its
    points, see :func:`graphcal.clouds.plane_table.planes_rows`; None: all) with ``refit(key)`` fitting up
    to ``ground_selection.REFIT_MAX_PLANES`` planes to that station's cloud."""
    from graphcal.clouds.plane_table import planes_rows

    types = {name: spec.type for name, spec in ds.sensors.items()}
    if ds.planes is not None:
        p = ds.planes
        rows = {c: p[c] for c in p.columns}
        count = len(p)
        if count == 0 and ds.root is not None:
            from graphcal.errors import DatasetError
            from graphcal.io.dataset import cloud_paths

            if cloud_paths(ds):
                raise DatasetError(ds.root / "planes.csv", "rows", "at least one plane: when planes.csv exists the "
                                   "clouds are not read (delete it to fit the clouds)", "a header only")
    else:
        from graphcal.io.dataset import cloud_paths, load_cloud

        cams = {k: v for k, v in cloud_paths(ds).items() if k[0] in types and sensor_type(types[k[0]]).fits_planes}
        pairs = [(key, functools.partial(load_cloud, ds, *key)) for key in sorted(cams)]  # read by the workers
        rows = planes_rows(pairs, types, progress=progress, total=len(cams), max_points=plane_max_points)
        count = len(rows["station"])
    out: dict = {}
    _plane_rows_to_measurements(rows, count, out)
    for key in out:
        out[key].sort(key=lambda p: -p.n_points)  # stable: planes.csv's order among equal counts
    refit = None
    if ds.planes is None:
        def refit(key):
            from graphcal.calibration.ground_selection import REFIT_MAX_PLANES

            station, sensor = key
            more = planes_rows([((sensor, station), functools.partial(load_cloud, ds, sensor, station))], types,
                               max_planes=REFIT_MAX_PLANES, max_points=plane_max_points, processes=False, workers=1)
            found: dict = {}
            _plane_rows_to_measurements(more, len(more["station"]), found)
            return sorted(found.get(key, []), key=lambda p: -p.n_points)
    return out, refit


def ground_line_inliers(points_sensor: np.ndarray, *, distance_m: float = 0.03, iterations: int = 200,
                        seed: int = 0) -> np.ndarray:
    """Boolean mask of the points of one laser scan that lie on its dominant straight line.

    A 2D scanner's scan plane cuts flat ground in a straight line; points on the robot's legs or on
    obstacles do not lie on it. RANSAC over point pairs (``distance_m`` ~ 3 sigma of the range
    noise), then the largest inlier set is refined once by a least-squares line.
    """
    P = np.asarray(points_sensor, dtype=float)[:, :2]
    n = len(P)
    if n < 3:
        return np.ones(n, dtype=bool)
    rng = np.random.default_rng(seed)
    best = np.zeros(n, dtype=bool)
    for _ in range(iterations):
        i, j = rng.choice(n, 2, replace=False)
        d = P[j] - P[i]
        norm = np.linalg.norm(d)
        if norm < 1e-6:
            continue
        normal = np.array([-d[1], d[0]]) / norm
        mask = np.abs((P - P[i]) @ normal) < distance_m
        if mask.sum() > best.sum():
            best = mask
    c = P[best].mean(axis=0)
    _, _, Vt = np.linalg.svd(P[best] - c)
    return np.abs((P - c) @ Vt[1]) < distance_m


#: laser points farther than this are not used for calibration (m). The default keeps the whole
#: range of a URG-04LX: with the range residual (factors/range_to_plane.py) the far, grazing beams
#: are the most informative (measured on the simulated Messor: 0.11 deg error with 1.5 m, 0.035 deg
#: with 4 m). Lower it when the floor is flat only near the robot (Łabęcki & Belter kept ~0.5 m).
SCAN_MAX_RANGE_M = 4.0


def scan_points(ds, *, max_points: int = 200, seed: int = 0, max_range_m: float = SCAN_MAX_RANGE_M,
                off_plane: dict | None = None) -> dict:
    """(station, sensor) -> (M, 3) ground points of every laser scanner cloud: the points on the
    scan's ground line (:func:`ground_line_inliers`; legs and obstacles dropped), evenly subsampled
    to at most ``max_points`` (the dense point-to-plane factors do not need every beam).

    ``off_plane``: filled with sensor -> ([(cloud file, 90th percentile of |z| in m), ...] of its
    clouds off the scan plane z = 0, number of its clouds) (see :class:`CalibrationData`)."""
    from graphcal.io.dataset import SCAN_PLANE_MAX_Z_M, cloud_paths, load_cloud, scan_off_plane_m, shown_path

    out = {}
    for (sensor, station), path in sorted(cloud_paths(ds).items()):
        if sensor_type(ds.sensors[sensor].type).fits_planes:
            continue
        pts = load_cloud(ds, sensor, station)
        if off_plane is not None:
            off, n = off_plane.get(sensor, ([], 0))
            z90 = scan_off_plane_m(pts)
            if z90 > SCAN_PLANE_MAX_Z_M:
                off.append((shown_path(ds.root, path), z90))
            off_plane[sensor] = (off, n + 1)
        pts = pts[np.linalg.norm(pts, axis=1) <= max_range_m]
        if len(pts) < 10:
            continue
        pts = pts[ground_line_inliers(pts, seed=seed)]
        if len(pts) > max_points:
            pts = pts[np.linspace(0, len(pts) - 1, max_points).round().astype(int)]
        out[(station, sensor)] = pts
    return out


def require_sensors(ds, command: str) -> None:
    """DatasetError naming dataset.yaml's ``sensors`` when the dataset has none (a motion-capture
    dataset: its legs are identified by ``graphcal identify-legs``); ``command`` names what needs them."""
    if ds.sensors:
        return
    where = ds.root / "dataset.yaml" if ds.root is not None else "dataset.yaml"
    hint = " (its motion capture identifies the legs: graphcal identify-legs)" if ds.mocap is not None else ""
    raise DatasetError(where, "sensors", f"at least one sensor for {command}{hint}", "none")


def calibration_data(ds, robot, *, progress: bool = False, plane_max_points: int | None = None) -> CalibrationData:
    """Everything the calibration graph reads from a dataset (``plane_max_points``: see
    :func:`plane_candidates`; where a camera saw several planes the floor is the one the stance
    feet and the extrinsic predict, :mod:`graphcal.calibration.ground_selection`)."""
    from graphcal.clouds.plane_table import check_max_points

    plane_max_points = check_max_points(plane_max_points, "plane_max_points")
    off_plane: dict = {}
    scans = scan_points(ds, off_plane=off_plane)
    candidates, refit = plane_candidates(ds, progress=progress, plane_max_points=plane_max_points)
    data = CalibrationData(
        stations=station_measurements(ds, robot),
        planes={k: v[0] for k, v in candidates.items()},
        scan_points=scans,
        sensor_types={name: spec.type for name, spec in ds.sensors.items()},
        scans_off_plane={s: (tuple(off), n) for s, (off, n) in off_plane.items() if off},
    )
    if data.planes:
        # the floor among each station's planes: the one the stance feet and the extrinsic predict
        from graphcal.calibration.ground_selection import choose_ground_planes
        from graphcal.calibration.kinematic_pose import kinematic_bodies

        u_body, height, _ = kinematic_bodies(data, robot)  # cached on data: the graph reuses it
        priors = {name: (spec.T_body_sensor_prior.matrix, spec.T_body_sensor_prior.sigma_m,
                         spec.T_body_sensor_prior.sigma_rad) for name, spec in ds.sensors.items()}
        chosen, moved = choose_ground_planes(candidates, u_body, height, priors, refit)
        data.planes.update(chosen)
        data.ground_not_largest.update(moved)
    return data


def plane_source_warnings(plane_max_points: int | None, planes_given: bool, ds, fitted=None) -> list[str]:
    """The warnings about where the planes came from: that ``plane_max_points`` did nothing (the
    planes were passed in, ``planes_given``, or the dataset ``ds`` has planes.csv, so no cloud was
    fitted), and which stations with a camera cloud have no plane: planes.csv has none for them (the
    clouds are not read when planes.csv exists: a planes.csv cut short or out of date silently drops
    them), or, when the clouds were fitted, no plane was found in theirs (``fitted``: the
    ``(station, sensor)`` keys of the fitted planes; too few points, collinear points, no plane)."""
    out = []
    if plane_max_points is not None and (planes_given or ds.planes is not None):
        out.append(f"--plane-points {plane_max_points} (plane_max_points) had no effect: the planes were "
                   + ("given" if planes_given else "read from planes.csv, not fitted to the clouds"))
    if planes_given or ds.root is None or (ds.planes is None and fitted is None):
        return out
    from graphcal.clouds.plane_table import camera_clouds_without_planes, no_plane_found_warning, stations_text

    if ds.planes is not None:
        have = zip(ds.planes["sensor"].tolist(), ds.planes["station"].tolist())
    else:
        have = ((sensor, station) for station, sensor in fitted)
    for sensor, (missing, total) in camera_clouds_without_planes(ds, have).items():
        if ds.planes is not None:
            out.append(f"{sensor}: planes.csv has no plane for {len(missing)} of the {total} stations with a "
                       f"cloud ({stations_text(missing)}); they are not used: when planes.csv exists the clouds are not read "
                       "(if it is out of date, delete it or refit it with graphcal extract-planes --out NEW)")
        else:
            out.append(no_plane_found_warning(sensor, missing, total, "those stations are not used"))
    return out
