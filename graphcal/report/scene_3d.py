"""The 3-D scenes of the report pages: what is drawn, in the world frame (m). A track page's
(:func:`track_scene`): the trajectory, the stance footholds, the perceived stairs; a plan-gait page's
(:func:`gait_scene`); a diagnosis page's (:func:`diagnosis_scene`). A calibration's:

* the ground points of every station laid into the world frame twice,
  ``p_world = T_world_body T_body_sensor p_sensor``, with the CAD prior ``T_body_sensor`` and with the
  calibrated one (the same body poses, the calibration's): the floor spreads, then collapses;
* :class:`FloorCollapse`: the RMS distance of each set of ground points to the floor (world z = 0);
* the body pose of every station as a small frame, each sensor's frame at one station at its prior
  and its calibrated pose with the calibrated position's 3-sigma ellipsoid, the robot's legs as a
  stick figure (joint origins from forward kinematics) at that station, and the floor.

Ground points: the points of each cloud on its own floor plane (a plane fitted in the sensor frame,
seeded by the points within :data:`GROUND_BAND_M` of the floor under the calibrated extrinsic, then
refitted to the points near it: the choice does not follow the extrinsic); the same points are shown
under both extrinsics. Subsampled evenly (every k-th
point in file order) to at most :data:`POINTS_PER_STATION` per station and
:data:`MAX_SCENE_POINTS` in all.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from graphcal.geometry import plane_from_points_pca, transform_points
from graphcal.report.calibration_yaml import body_axis_covariance
from graphcal.report.scene_mcap import thin_evenly

__all__ = ["GROUND_BAND_M", "POINTS_PER_STATION", "MAX_SCENE_POINTS", "ELLIPSOID_SCALE", "MAX_TRAJECTORY_SEGMENTS",
           "FloorCollapse", "stance_footholds", "track_scene", "PosedSensor", "PosedModel", "diagnosis_scene", "gait_scene",
           "stairs_segments", "extrinsic_at",
           "SceneGroup", "Scene", "floor_collapse", "calibration_scene"]

#: a cloud's point within this distance (m) of the floor under the calibrated extrinsic is a ground point
GROUND_BAND_M = 0.03
#: ground points kept per station and extrinsic (evenly thinned)
POINTS_PER_STATION = 300
#: ground points kept in all, per extrinsic
MAX_SCENE_POINTS = 6000
#: the 3-sigma position ellipsoids are drawn this many times their size (mm ellipsoids in a 1 m scene)
ELLIPSOID_SCALE = 10.0
_FRAME_M = 0.04  # axis length of a body-pose frame
_SENSOR_FRAME_M = 0.10


@dataclass(frozen=True)
class FloorCollapse:
    """The RMS distance (m) of all stations' ground points to the floor the feet stand on (world
    z = 0: graphcal's level ground), with the prior extrinsic and with the calibrated one, for
    ``points`` points of ``stations`` stations of ``sensor``. A plane fitted to the points instead
    would absorb an error every station shares (a tilted sensor tilts every station's floor alike)."""

    sensor: str
    stations: int
    points: int
    rms_prior_m: float
    rms_calibrated_m: float


@dataclass(frozen=True, eq=False)
class SceneGroup:
    """One toggle of the 3-D view: points (N, 3) or line segments (M, 2, 3), world frame, m."""

    name: str
    color: str
    kind: str  # "points" | "lines"
    data: np.ndarray
    visible: bool = True
    cycle: tuple[str, ...] = ()  # lines: segment i drawn in cycle[i % len(cycle)] (a frame's x, y, z)
    size: float = 2.0  # points: square side, px


@dataclass(frozen=True, eq=False)
class Scene:
    """The groups of a 3-D view, and per sensor the floor's collapse and its ground points (empty when
    no clouds)."""

    groups: tuple[SceneGroup, ...]
    collapse: tuple[FloorCollapse, ...]
    note: str
    ground: dict = field(default_factory=dict)  # sensor -> (prior (N, 3), calibrated (N, 3)) ground points


def floor_collapse(sensor: str, stations: int, prior: np.ndarray, calibrated: np.ndarray) -> FloorCollapse:
    """:class:`FloorCollapse` of the same ground points (N, 3, world frame, m) under two extrinsics."""

    def rms(p: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.asarray(p, dtype=float)[:, 2] ** 2)))

    return FloorCollapse(sensor, int(stations), len(prior), rms(prior), rms(calibrated))


def _triads(poses, length: float) -> np.ndarray:
    """Line segments (3 per pose: x red, y green, z blue in that order) of frames (4x4 each)."""
    segs = []
    for T in poses:
        o = T[:3, 3]
        segs.extend([(o, o + length * T[:3, k]) for k in range(3)])
    return np.asarray(segs, dtype=float).reshape(-1, 2, 3)


_XYZ = ("#d62728", "#2ca02c", "#3344ff")


def _axis_groups(name: str, poses, length: float, visible: bool = True) -> list[SceneGroup]:
    return [SceneGroup(name, "#2ca02c", "lines", _triads(poses, length), visible, _XYZ)]


def _ellipsoid(center: np.ndarray, cov3: np.ndarray, scale: float) -> np.ndarray:
    """Segments of the three principal ellipses of the 3-sigma ellipsoid of ``cov3`` (m^2), ×scale."""
    w, V = np.linalg.eigh(0.5 * (cov3 + cov3.T))
    axes = V * (3.0 * scale * np.sqrt(np.clip(w, 0.0, None)))
    t = np.linspace(0.0, 2.0 * np.pi, 33)
    segs = []
    for a, b in ((0, 1), (1, 2), (0, 2)):
        ring = center + np.outer(np.cos(t), axes[:, a]) + np.outer(np.sin(t), axes[:, b])
        segs.append(np.stack([ring[:-1], ring[1:]], axis=1))
    return np.concatenate(segs)


def _stick_figure(legs, q: dict, T_world_body: np.ndarray) -> np.ndarray:
    """Segments body origin -> each joint origin -> foot of each leg of ``legs``, world frame (m)."""
    from graphcal.models.kinematics import joint_frames

    segs = []
    for leg in legs:
        qs = np.array([[float(q.get(j, 0.0)) for j in leg.joint_names]])
        _, origins, _, p_foot = joint_frames(leg, qs)
        chain = np.vstack([np.zeros(3), origins[0], p_foot[0]])
        chain = transform_points(T_world_body, chain)
        segs.extend(zip(chain[:-1], chain[1:]))
    return np.asarray(segs, dtype=float).reshape(-1, 2, 3)


def _nearest(t: np.ndarray, rows: np.ndarray, ts: float) -> int:
    """The row of ``rows`` (indices into ``t``, s, ascending in time) stamped nearest ``ts``."""
    i = int(np.clip(np.searchsorted(t[rows], ts), 1, len(rows) - 1)) if len(rows) > 1 else 0
    if i and abs(t[rows[i - 1]] - ts) <= abs(t[rows[i]] - ts):
        i -= 1
    return int(rows[i])


def _walk_rows(ds, result, column: str | None = None) -> dict:
    """A walk's station -> the timeseries.csv row stamped nearest its time (among the rows with a
    ``column`` entry, when given)."""
    times = (result.walk or {}).get("station_times_s") or {}
    if ds is None or ds.timeseries is None or not times:
        return {}
    t = np.asarray(ds.timeseries["time"], dtype=float)
    rows = np.argsort(t, kind="stable")
    if column is not None:
        rows = rows[np.asarray([bool(v) for v in ds.timeseries[column].tolist()])[rows]]
    if not len(rows):
        return {}
    return {int(st): _nearest(t, rows, float(ts)) for st, ts in times.items()}


def _station_clouds(ds, result) -> dict:
    """(sensor, station) -> cloud file of every station of ``result``: clouds/<sensor>/<station>.ply,
    or for a walk the ``cloud_<sensor>`` of the frame nearest the station's time in timeseries.csv."""
    from graphcal.io.dataset import cloud_paths

    if ds is None or ds.root is None:
        return {}
    found = dict(cloud_paths(ds))
    for sensor in result.sensors:
        column = f"cloud_{sensor}"
        if ds.timeseries is None or not ds.timeseries.has(column):
            continue
        files = ds.timeseries[column].tolist()
        for station, j in _walk_rows(ds, result, column).items():
            found[(sensor, station)] = ds.root / str(files[j]).replace("\\", "/")
    return found


def _station_q(ds, result, station: int) -> dict:
    """Joint angles (rad) of a station: stations.csv's q_ columns, or a walk's frame row."""
    walk = _walk_rows(ds, result)
    table = ds.timeseries if station in walk else (ds.stations if ds is not None else None)
    if table is None:
        return {}
    if station in walk:
        row = walk[station]
    else:
        rows = np.flatnonzero(np.asarray(table["station"]).astype(int) == int(station))
        if not len(rows):
            return {}
        row = int(rows[0])
    return {c[2:]: float(table[c][row]) for c in table.columns if c.startswith("q_")}


def _ground_points(ds, result, sensor: str, clouds: dict):
    """(prior, calibrated, stations): the ground points of ``sensor``'s station clouds, world frame."""
    from graphcal.io.ply import read_ply

    s = result.sensors[sensor]
    T_pri = np.asarray(s.T_body_sensor_prior, dtype=float)
    pri, cal, used = [], [], 0
    for station in sorted(st for (name, st) in clouds if name == sensor and st in result.T_world_body):
        T_wb, T_cal = np.asarray(result.T_world_body[station], dtype=float), extrinsic_at(s, station)
        pts = np.asarray(read_ply(clouds[(sensor, station)]), dtype=float)[:, :3]
        keep = _station_floor(pts, np.abs(transform_points(T_wb @ T_cal, pts)[:, 2]) < GROUND_BAND_M)
        if keep is None:
            continue
        pts = thin_evenly(pts[keep], POINTS_PER_STATION)
        cal.append(transform_points(T_wb @ T_cal, pts))
        pri.append(transform_points(T_wb @ T_pri, pts))
        used += 1
    if not used:
        return None
    return thin_evenly(np.vstack(pri), MAX_SCENE_POINTS), thin_evenly(np.vstack(cal), MAX_SCENE_POINTS), used


def _station_floor(pts: np.ndarray, seed: np.ndarray) -> np.ndarray | None:
    """The floor's points of one cloud (sensor frame, m) as a mask: a plane fitted to the ``seed``
    points (those near the floor under the calibrated extrinsic), then twice to the points within
    3 of its rms (at least 10 mm) of it, so that the choice is the station's own floor plane and not
    the extrinsic's (a wrong extrinsic would otherwise pick the points that agree with it)."""
    keep = seed
    for _ in range(3):
        if keep.sum() < 3:
            return None
        n, d, _ = plane_from_points_pca(pts[keep])
        dist = np.abs(pts @ n + d)
        keep = dist < max(3.0 * float(np.sqrt(np.mean(dist[keep] ** 2))), 0.010)
    return keep if keep.sum() >= 3 else None


def extrinsic_at(sensor, station: int) -> np.ndarray:
    """The calibrated T_body_sensor (4x4, m) at ``station``: its extrinsic segment's when the sensor
    moved during the session (``sensor.segments``), else ``sensor.T_body_sensor``."""
    for seg in getattr(sensor, "segments", ()) or ():
        if int(seg.first_station) <= int(station) <= int(seg.last_station):
            return np.asarray(seg.T_body_sensor, dtype=float)
    return np.asarray(sensor.T_body_sensor, dtype=float)


def _sensor_groups(result, name: str, T_wb: np.ndarray) -> list[SceneGroup]:
    s = result.sensors[name]
    T_cal, T_pri = np.asarray(s.T_body_sensor, dtype=float), np.asarray(s.T_body_sensor_prior, dtype=float)
    groups = _axis_groups(f"{name} calibrated", [T_wb @ T_cal], _SENSOR_FRAME_M)
    groups += _axis_groups(f"{name} prior (CAD)", [T_wb @ T_pri], 0.6 * _SENSOR_FRAME_M)
    cov = body_axis_covariance(T_cal, s.covariance)[3:, 3:]
    if np.all(np.isfinite(cov)):
        cov_w = T_wb[:3, :3] @ cov @ T_wb[:3, :3].T
        groups.append(SceneGroup(f"{name} 3σ ×{ELLIPSOID_SCALE:g}", "#9467bd", "lines",
                                 _ellipsoid((T_wb @ T_cal)[:3, 3], cov_w, ELLIPSOID_SCALE)))
    return groups


def _floor_outline(points: np.ndarray) -> np.ndarray:
    """The rectangle (4 segments) of the floor (world z = 0) under the x-y extent of ``points``."""
    (x0, y0), (x1, y1) = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    ring = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0], [x0, y0, 0.0]])
    return np.stack([ring[:-1], ring[1:]], axis=1)


def calibration_scene(result, dataset=None, robot=None) -> Scene:
    """The 3-D :class:`Scene` of a CalibrationResult; ``dataset`` (a Dataset read from its folder)
    gives the clouds and joint angles, ``robot`` (a RobotModel) the stick figure. Without clouds the
    scene has the body poses and the sensor frames only, and ``note`` says so."""
    poses = [np.asarray(T, dtype=float) for _, T in sorted(result.T_world_body.items())]
    if not poses:
        return Scene((), (), "no body poses: nothing to draw")
    station = min(result.T_world_body)
    T_wb = np.asarray(result.T_world_body[station], dtype=float)
    groups: list[SceneGroup] = []
    collapse: list[FloorCollapse] = []
    ground: dict = {}
    clouds = _station_clouds(dataset, result)
    for name in result.sensors:
        found = _ground_points(dataset, result, name, clouds) if clouds else None
        if found is None:
            continue
        pri, cal, used = found
        collapse.append(floor_collapse(name, used, pri, cal))
        ground[name] = (pri, cal)
        groups.append(SceneGroup(f"{name} ground, prior extrinsic", "#ff7f0e", "points", pri))
        groups.append(SceneGroup(f"{name} ground, calibrated", "#1f77b4", "points", cal))
        groups.append(SceneGroup(f"{name} floor (z = 0)", "#7f7f7f", "lines", _floor_outline(cal)))
    groups += _axis_groups("body poses", poses, _FRAME_M)
    if robot is not None:
        groups.append(SceneGroup(f"robot at station {station}", "#333333", "lines",
                                 _stick_figure(robot.legs.values(), _station_q(dataset, result, station), T_wb)))
    for name in result.sensors:
        groups += _sensor_groups(result, name, T_wb)
    note = (f"Robot and sensor frames at station {station}. Ground points: those on each cloud's own floor "
            f"plane (fitted in the sensor frame, seeded by the points within {GROUND_BAND_M * 1e3:g} mm of the floor "
            "under the calibrated extrinsic), the same points under both extrinsics; at most "
            f"{POINTS_PER_STATION} per station and {MAX_SCENE_POINTS} in all (evenly thinned).")
    if not collapse:
        note += " No station clouds: the dataset has planes only, or its clouds could not be read."
    return Scene(tuple(groups), tuple(collapse), note, ground)


#: trajectory segments kept in a track scene (evenly thinned)
MAX_TRAJECTORY_SEGMENTS = 2000


def _polyline(points: np.ndarray, cap: int = MAX_TRAJECTORY_SEGMENTS) -> np.ndarray:
    p = thin_evenly(np.asarray(points, dtype=float), cap + 1)
    return np.stack([p[:-1], p[1:]], axis=1) if len(p) > 1 else np.zeros((0, 2, 3))


def stance_footholds(T_world_body: np.ndarray, stance_mask: np.ndarray, p_body_foot: np.ndarray) -> np.ndarray:
    """(K, 3) world foot points (m), one per stance run of each foot, at the run's middle sample:
    ``p_world = T_world_body p_body_foot``. ``stance_mask`` (N, n_feet), ``p_body_foot`` (n_feet, N, 3)."""
    out = []
    for f in range(stance_mask.shape[1]):
        m = np.r_[False, np.asarray(stance_mask[:, f], dtype=bool), False].astype(int)
        starts, ends = np.flatnonzero(np.diff(m) == 1), np.flatnonzero(np.diff(m) == -1)
        mid = (starts + ends - 1) // 2
        T = T_world_body[mid]
        out.append(np.einsum("kij,kj->ki", T[:, :3, :3], p_body_foot[f, mid]) + T[:, :3, 3])
    return np.vstack(out) if out else np.zeros((0, 3))


def stairs_segments(stairs_doc: dict) -> np.ndarray:
    """Each perceived tread's outline (nosing edge, depth up the stairs) and its riser below the nosing."""
    T = np.asarray(stairs_doc.get("T_world_stairs", np.eye(4)), dtype=float)
    up = T[:3, 0] - T[2, 0] * np.array([0.0, 0.0, 1.0])
    up = up / max(np.linalg.norm(up), 1e-9)
    segs, below = [], 0.0
    for t in sorted(stairs_doc.get("treads", []), key=lambda t: t["height_m"]):
        e, a = np.asarray(t["p_world_edge_m"], dtype=float), np.asarray(t["edge_direction_world"], dtype=float)
        depth, half = float(t.get("depth_m") or 0.0), 0.5 * float(t.get("width_m") or 0.0)
        ring = [e - half * a, e + half * a, e + half * a + depth * up, e - half * a + depth * up, e - half * a]
        segs.extend(zip(ring[:-1], ring[1:]))
        drop = np.array([0.0, 0.0, float(t["height_m"]) - below])
        segs.extend([(e - half * a, e - half * a - drop), (e + half * a, e + half * a - drop)])
        below = float(t["height_m"])
    return np.asarray(segs, dtype=float).reshape(-1, 2, 3)


def track_scene(T_world_body: np.ndarray, footholds: np.ndarray, *, stairs_doc: dict | None = None,
                T_world_body_true: np.ndarray | None = None) -> Scene:
    """The 3-D :class:`Scene` of a track output: the estimated trajectory (and the true one), the
    stance footholds, the perceived stairs' treads and risers (stairs.json), the floor z = 0."""
    p = np.asarray(T_world_body, dtype=float)[:, :3, 3]
    groups = []
    if T_world_body_true is not None:  # drawn first: the estimate on top
        groups.append(SceneGroup("trajectory (truth)", "#2ca02c", "lines",
                                 _polyline(np.asarray(T_world_body_true, dtype=float)[:, :3, 3])))
    groups.append(SceneGroup("trajectory (estimate)", "#1f77b4", "lines", _polyline(p)))
    if len(footholds):
        groups.append(SceneGroup("stance footholds", "#d62728", "points", np.asarray(footholds, dtype=float), size=4.0))
    if stairs_doc and stairs_doc.get("treads"):
        groups.append(SceneGroup("stairs (perceived)", "#9467bd", "lines", stairs_segments(stairs_doc)))
    every = np.vstack([p] + ([footholds] if len(footholds) else []))
    lo, hi = every[:, :2].min(axis=0) - 0.2, every[:, :2].max(axis=0) + 0.2
    ring = np.array([[lo[0], lo[1], 0.0], [hi[0], lo[1], 0.0], [hi[0], hi[1], 0.0], [lo[0], hi[1], 0.0],
                     [lo[0], lo[1], 0.0]])
    groups.append(SceneGroup("floor (z = 0)", "#7f7f7f", "lines", np.stack([ring[:-1], ring[1:]], axis=1)))
    note = (f"Trajectory evenly thinned to at most {MAX_TRAJECTORY_SEGMENTS} segments; one foothold per stance of "
            "each foot, at its middle sample, placed with the estimated body pose.")
    return Scene(tuple(groups), (), note)


@dataclass(frozen=True, eq=False)
class PosedSensor:
    """A sensor's pose on the body (4x4, m) at its prior and its estimate; ``covariance`` (6, 6) of
    ``[omega, v]`` (rad, m; right perturbation), NaN where unknown (no ellipsoid drawn)."""

    T_body_sensor: np.ndarray
    T_body_sensor_prior: np.ndarray
    covariance: np.ndarray


@dataclass(frozen=True, eq=False)
class PosedModel:
    """What :func:`calibration_scene` reads of a solved model: station -> T_world_body (4x4, m),
    sensor name -> :class:`PosedSensor`, and a walk's summary (or None)."""

    T_world_body: dict
    sensors: dict
    walk: dict | None = None


_HIGHLIGHT = "#e6007e"


def _highlight(result, dataset, robot, where: dict, stations_of: dict) -> list[SceneGroup]:
    """Groups that mark a finding's place: its stations' body frames, its leg at the first station."""
    out = []
    picked = [int(s) for s in where.get("stations", [])] + ([int(where["station"])] if "station" in where else [])
    picked += [st for st, sess in stations_of.items() if "session" in where and sess == where["session"]]
    picked = [s for s in dict.fromkeys(picked) if s in result.T_world_body]
    if picked:
        out.append(SceneGroup(f"finding: station{'s' if len(picked) > 1 else ''} {', '.join(map(str, picked[:8]))}"
                              f"{' …' if len(picked) > 8 else ''}", _HIGHLIGHT, "lines",
                              _triads([result.T_world_body[s] for s in picked], 3 * _FRAME_M)))
    if "leg" in where and robot is not None and where["leg"] in robot.legs:
        station = min(result.T_world_body)
        out.append(SceneGroup(f"finding: leg {where['leg']}", _HIGHLIGHT, "lines", _stick_figure(
            [robot.legs[where["leg"]]], _station_q(dataset, result, station), result.T_world_body[station])))
    return out


def diagnosis_scene(model: PosedModel, dataset, robot, findings: list[dict], stations_of: dict) -> Scene:
    """The calibration scene of a diagnosis model, with each finding's place (``where`` of
    diagnosis.json: stations, a station, a session, a leg) drawn in magenta. ``stations_of``:
    station -> session."""
    scene = calibration_scene(model, dataset, robot)
    extra = []
    for f in findings:
        extra += _highlight(model, dataset, robot, dict(f.get("where") or {}), stations_of)
    return dataclasses.replace(scene, groups=scene.groups + tuple(extra))


def gait_scene(doc: dict, stairs_doc: dict, p_world_track: np.ndarray | None = None) -> Scene:
    """The 3-D :class:`Scene` of a plan-gait output (``doc``: gait.yaml's document, world frame, m): the
    perceived stairs, the planned body path, each planned foothold and its swing (lift point to
    foothold), the feet at the start, and the tracked path before the plan."""
    body = [doc["start"]["T_world_body"]] + [s["body"]["T_world_body_end"] for s in doc["steps"]]
    body_p = np.asarray([np.asarray(T, dtype=float)[:3, 3] for T in body]).reshape(-1, 3)
    groups = [SceneGroup("stairs (perceived)", "#9467bd", "lines", stairs_segments(stairs_doc))]
    if p_world_track is not None and len(p_world_track) > 1:
        groups.append(SceneGroup("tracked path", "#7f7f7f", "lines", _polyline(p_world_track)))
    groups.append(SceneGroup("planned body path", "#1f77b4", "lines", _polyline(body_p)))
    land = [f["p_world_foot"] for s in doc["steps"] for f in s["footholds"].values()]
    swing = [(f["p_world_lift"], f["p_world_foot"]) for s in doc["steps"] for f in s["footholds"].values()
             if f.get("p_world_lift") is not None]
    start = [f["p_world_foot"] for f in doc["start"]["feet"].values()]
    if land:
        groups.append(SceneGroup("planned footholds", "#d62728", "points", np.asarray(land, dtype=float), size=6.0))
    if swing:
        groups.append(SceneGroup("swings (lift -> foothold)", "#ff7f0e", "lines", np.asarray(swing, dtype=float)))
    if start:
        groups.append(SceneGroup("feet at the start", "#2ca02c", "points", np.asarray(start, dtype=float), size=6.0))
    note = ("Footholds and body path as planned (gait.yaml), each swing drawn straight from its lift point to its "
            "foothold (the planned swing curves over the nosings: the clearances are in the tables).")
    return Scene(tuple(groups), (), note)
