"""A walking log as calibration stations (docs/calibration.md, "Calibrating from a walk").

While a legged robot walks, the feet in stance stand still on the floor and the camera sees that
floor in every frame: each depth frame taken while at least three feet stand is a station whose
stance feet are the planted points of their own stance (one point per foot and touchdown, not per
session), and one station without a cloud at the middle of every interval of constant stance
(the double-support moments among them) links the stances, so that one graph holds the whole walk.
Time is the log's (s); a sensor's ``time_offset_s`` is its stamp minus its capture time, so its
frame stamped t is matched with the joints at t - time_offset_s.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from graphcal.calibration.measurements import CalibrationData, StationMeasurements
from graphcal.errors import DatasetError

__all__ = ["WALK_SESSION", "MIN_STANCE_FEET", "WalkingFrames", "is_walking_dataset", "walking_frames",
           "walking_data", "stance_runs"]

#: the session label of every station of a walk (the feet's own stances link them)
WALK_SESSION = "walk"
#: a frame is a station when at least this many feet stand (three points fix the body on the floor)
MIN_STANCE_FEET = 3


@dataclass(frozen=True, eq=False)
class WalkingFrames:
    """What a walk gives the calibration before any time offset is chosen.

    Attributes:
        times: (N,) log time of every timeseries row (s).
        q: joint name -> (N,) measured joint angle (rad / m).
        contact: (N, n_feet) bool, foot in stance (``robot.feet`` order).
        cloud_rows: sensor -> (rows with a cloud of that sensor, relative PLY paths).
        planes: (sensor, cloud row) -> [PlaneMeasurement, ...] the planes of that frame, largest first.
        refit: (sensor, cloud row) -> more planes of that frame (up to 4), or None (planes.csv given).
    """

    times: np.ndarray
    q: dict
    contact: np.ndarray
    feet: tuple
    cloud_rows: dict
    planes: dict
    refit: object = None
    sensor_types: dict = field(default_factory=dict)


def is_walking_dataset(ds) -> bool:
    """True for a dataset whose clouds are along a walk: a timeseries with ``cloud_<sensor>``
    columns and no stations.csv."""
    t = ds.timeseries
    return ds.stations is None and t is not None and any(t.suffixes("cloud_"))


def stance_runs(contact: np.ndarray) -> np.ndarray:
    """(N, n_feet) int: the index of each foot's stance (0, 1, ... in time order; -1 in swing)."""
    c = np.asarray(contact, dtype=bool)
    starts = c & ~np.vstack([np.zeros((1, c.shape[1]), bool), c[:-1]])
    runs = np.cumsum(starts, axis=0) - 1
    return np.where(c, runs, -1)


def walking_frames(ds, robot, contact: np.ndarray, *, progress: bool = False,
                   plane_max_points: int | None = None) -> WalkingFrames:
    """The walk of ``ds`` (a walking dataset, :func:`is_walking_dataset`) with ``contact`` (N, n_feet)
    bool stance per row; every camera frame's planes fitted once (clouds in the sensor frame, m)."""
    import functools

    from graphcal.calibration.measurements import plane_measurements_from_rows
    from graphcal.clouds.plane_table import planes_rows
    from graphcal.io.dataset.cloud_files import read_cloud
    from graphcal.models.sensors import sensor_type

    t = ds.timeseries
    times = np.asarray(t["time"], dtype=float)  # never decreasing: the dataset's validation
    q = {}
    for f in robot.feet:
        for j in robot.leg(f).joint_names:
            if not t.has(f"q_{j}"):
                raise DatasetError(ds.root / "timeseries.csv", f"column q_{j}",
                                   "the joint angles of every leg (a walk is calibrated from its stance feet)", "none")
            q[j] = np.asarray(t[f"q_{j}"], dtype=float)
    types = {name: spec.type for name, spec in ds.sensors.items()}
    cloud_rows = {}
    for s in t.suffixes("cloud_"):
        if s in types and sensor_type(types[s]).fits_planes:
            paths = np.asarray(t[f"cloud_{s}"])
            rows = np.flatnonzero(paths != "")
            cloud_rows[s] = (rows, tuple(str(p) for p in paths[rows]))
    pairs = [((s, int(r)), functools.partial(read_cloud, ds.root / p))
             for s, (rows, paths) in sorted(cloud_rows.items()) for r, p in zip(rows, paths)]
    fitted = planes_rows(pairs, types, progress=progress, total=len(pairs), max_points=plane_max_points)
    planes = {(s, r): v for (r, s), v in plane_measurements_from_rows(fitted).items()}

    def refit(key):
        from graphcal.calibration.ground_selection import REFIT_MAX_PLANES

        sensor, row = key
        path = ds.root / dict(zip(*cloud_rows[sensor]))[row]
        more = planes_rows([(key, functools.partial(read_cloud, path))], types, max_planes=REFIT_MAX_PLANES,
                           max_points=plane_max_points, processes=False, workers=1)
        return plane_measurements_from_rows(more).get((row, sensor), [])

    return WalkingFrames(times, q, np.asarray(contact, dtype=bool), tuple(robot.feet), cloud_rows, planes, refit, types)


def _station_rows(frames: WalkingFrames, offsets: dict, steady: tuple | None) -> list[tuple[float, dict]]:
    """(time of the joints (s), {sensor: cloud row}) of every station in time order: the frames
    (at stamp - offset) and the middle of every interval of constant stance. ``steady`` (lo, hi) s:
    only the frames whose stance does not change between stamp - hi and stamp - lo."""
    at: dict = {}
    for s, (rows, _) in frames.cloud_rows.items():
        for r in rows:
            if steady is not None and not _stance_constant(frames, float(frames.times[r]), steady):
                continue
            tk = float(frames.times[r]) - float(offsets.get(s, 0.0))
            at.setdefault(round(tk, 9), {})[s] = int(r)
    out = list(at.items())
    change = np.flatnonzero(np.any(frames.contact[1:] != frames.contact[:-1], axis=1)) + 1
    edges = np.concatenate([[0], change, [len(frames.times)]])
    for a, b in zip(edges[:-1], edges[1:]):
        mid = (a + b - 1) // 2
        if frames.contact[mid].sum() >= MIN_STANCE_FEET:
            out.append((float(frames.times[mid]), {}))
    return sorted(out, key=lambda x: (x[0], len(x[1])))


def _stance_constant(frames: WalkingFrames, stamp: float, steady: tuple) -> bool:
    """True when no foot touches down or lifts off between ``stamp - steady[1]`` and ``stamp - steady[0]``."""
    a, b = np.searchsorted(frames.times, [stamp - steady[1], stamp - steady[0]])
    block = frames.contact[max(0, a - 1):min(len(frames.times), b + 1)]
    return bool(len(block) == 0 or (block == block[0]).all())


def walking_data(frames: WalkingFrames, robot, priors: dict, *, offsets: dict | None = None,
                 steady: tuple | None = None) -> tuple[CalibrationData, dict]:
    """The walk as :class:`CalibrationData` with the cameras' time offsets ``offsets`` (sensor -> s,
    stamp minus capture; absent: 0), stations in time order with ids 0, 1, ..., the floor among
    each frame's planes chosen as for stations (``priors``: sensor -> (T_body_sensor CAD (4, 4),
    sigma m, sigma rad); :mod:`graphcal.calibration.ground_selection`). Returns it and station ->
    (log time of its joints (s), {sensor: cloud row}). Frames with fewer than
    :data:`MIN_STANCE_FEET` feet in stance are left out; with ``steady`` (lo, hi) s also those whose
    stance changes between stamp - hi and stamp - lo (the same stations for every offset in it)."""
    import dataclasses

    from graphcal.calibration.ground_selection import choose_ground_planes
    from graphcal.calibration.kinematic_pose import kinematic_bodies

    stations, where = _stations(frames, robot, offsets or {}, steady)
    candidates = {(sid, s): [dataclasses.replace(p, station=sid) for p in frames.planes[(s, r)]]
                  for sid, (_, clouds) in where.items() for s, r in clouds.items() if frames.planes.get((s, r))}
    if not candidates:
        raise DatasetError("timeseries.csv", "cloud_* rows",
                           f"camera frames with a plane, taken while at least {MIN_STANCE_FEET} feet stand", "none")
    data = CalibrationData(stations=tuple(stations), planes={k: v[0] for k, v in candidates.items()}, scan_points={},
                           sensor_types=dict(frames.sensor_types))

    def refit(key):
        sid, sensor = key
        return [dataclasses.replace(p, station=sid) for p in frames.refit((sensor, where[sid][1][sensor]))]

    u_body, height, _ = kinematic_bodies(data, robot)
    chosen, moved = choose_ground_planes(candidates, u_body, height, priors, refit)
    data.planes.update(chosen)
    data.ground_not_largest.update(moved)
    return data, where


def _stations(frames: WalkingFrames, robot, offsets: dict, steady: tuple | None) -> tuple[list, dict]:
    """The stations of :func:`walking_data` (start poses chained through the shared stance feet)
    and station -> (joint time (s), {sensor: cloud row})."""
    from graphcal.calibration.kinematic_pose import feet_in_body, ground_from_feet, initial_body_pose
    from graphcal.geometry import fit_rigid_transform

    runs = stance_runs(frames.contact)
    times = frames.times
    rows = _station_rows(frames, offsets, steady)
    tks = np.array([tk for tk, _ in rows])
    q_at = {j: np.interp(tks, times, v) for j, v in frames.q.items()}  # every joint at every station time
    i_near = np.clip(np.searchsorted(times, tks), 1, len(times) - 1)
    i_near = np.where(tks - times[i_near - 1] < times[i_near] - tks, i_near - 1, i_near)  # the nearest row
    stations: list = []
    where: dict = {}
    known: dict = {}  # stance label -> p_world_foot of the start guess
    T_prev = None
    for n, (tk, clouds) in enumerate(rows):
        i = int(i_near[n])
        feet = [f for k, f in enumerate(frames.feet) if frames.contact[i, k]]
        if len(feet) < MIN_STANCE_FEET:
            continue
        q_by_foot = {f: np.array([q_at[j][n] for j in robot.leg(f).joint_names]) for f in feet}
        labels = {f: f"{f}#{runs[i, frames.feet.index(f)]}" for f in feet}
        P = feet_in_body(robot, q_by_foot)
        shared = [k for k, f in enumerate(feet) if labels[f] in known]
        if len(shared) >= MIN_STANCE_FEET:
            T = fit_rigid_transform(P[shared], np.array([known[labels[feet[k]]] for k in shared]))
        elif T_prev is None:
            T = initial_body_pose(*ground_from_feet(P))
        else:
            T = T_prev
        for k, f in enumerate(feet):
            known.setdefault(labels[f], T[:3, :3] @ P[k] + T[:3, 3])
        sid = len(stations)
        stations.append(StationMeasurements(sid, WALK_SESSION, q_by_foot, None, None, stances=labels,
                                            T_world_body_start=T, time_s=float(tk)))
        where[sid] = (float(tk), clouds)
        T_prev = T
    return stations, where
