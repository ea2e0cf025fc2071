"""Motion-capture data of a dataset as arrays for leg identification (``mocap.csv`` + joint values).

:func:`mocap_data_from_dataset` reads a ``graphcal-dataset/1`` folder (``read_dataset``), pairs
each marker row of ``mocap.csv`` with the joint values of the station (``stations.csv``, by
``time``) or sample (``timeseries.csv``) at the same time, and returns one :class:`MarkerTrack`
per marker fixed to a foot:

* a marker is on foot ``f`` when it is named ``f`` or ``f.<k>``, or when ``mocap.markers`` in
  ``dataset.yaml`` gives it ``link: f`` (a foot frame of ``robot.feet``); its position on the foot
  is known when ``mocap.markers.<name>.xyz`` is given (foot frame, m), else it is estimated;
* when the four body markers ``body.1 ... body.4`` are present, every sample is expressed in
  Yuan's virtual base (:mod:`graphcal.legs.virtual_base`) and the identification estimates
  ``T_body_vbase``; samples without all four body markers are dropped (with a warning). The
  nominal ``T_body_vbase`` is known when ``mocap.markers`` gives the four body markers' ``xyz`` on
  the base frame. Without body markers the motion-capture frame is fixed to the base and
  ``T_body_mocap`` is estimated from scratch.

Measured 6-D poses of robot frames (``mocap_poses.csv``, docs/dataset.md) become one
:class:`PoseTrack` per frame (:func:`pose_tracks_from_table`), beside the marker tracks.

Bad input raises :class:`~graphcal.errors.DatasetError` naming the file and the field.
Units: metres, radians.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from graphcal.errors import DatasetError, GraphcalError
from graphcal.legs.virtual_base import (
    BODY_MARKERS,
    point_covariance_in_vbase,
    vbase_points,
    virtual_base,
    virtual_base_covariance,
)

__all__ = ["MarkerTrack", "PoseTrack", "MocapData", "mocap_data_from_dataset", "marker_foot", "pose_tracks_from_table"]

#: fewest samples of a marker for it to be used
MIN_SAMPLES = 3


@dataclass(frozen=True, eq=False)
class MarkerTrack:
    """The samples of one marker on one foot.

    Attributes:
        marker: marker name (mocap.csv).
        foot: the foot frame it is fixed to (the leg).
        time: (N,) sample times, s.
        q: (N, n) measured joint values of the leg (rad / m), ``Leg.joint_names`` order.
        p_meas: (N, 3) marker positions in the measurement frame (the motion-capture frame, or the
            virtual base when the dataset has body markers), m.
        p_foot_marker: (3,) known marker position in the foot frame (m), or None (estimated).
        cov_extra: (N, 3, 3) covariance (m^2, measurement frame) the virtual base adds, or None.
    """

    marker: str
    foot: str
    time: np.ndarray
    q: np.ndarray
    p_meas: np.ndarray
    p_foot_marker: np.ndarray | None = None
    cov_extra: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.time.shape[0])

    def select(self, rows) -> "MarkerTrack":
        """A track with the chosen rows (boolean mask or index array)."""
        ce = None if self.cov_extra is None else self.cov_extra[rows]
        return MarkerTrack(self.marker, self.foot, self.time[rows], self.q[rows], self.p_meas[rows],
                           self.p_foot_marker, ce)


@dataclass(frozen=True, eq=False)
class PoseTrack:
    """The measured 6-D poses of one robot frame (the end frame of a leg: a foot, hand or tool).

    Attributes:
        marker: name of the track (``pose:<frame>`` when read from mocap_poses.csv: distinct from a
            marker named after the frame).
        foot: the leg's end frame that is measured (a frame of ``robot.feet``).
        time: (N,) sample times, s.
        q: (N, n) measured joint values of the leg (rad / m), ``Leg.joint_names`` order.
        T_meas: (N, 4, 4) measured pose of the frame in the measurement frame (m).
        cov: (N, 6, 6) covariance of each measurement, [rx, ry, rz (rad), x, y, z (m)] in the
            measured frame's own axes (right perturbation, GTSAM order).
    """

    marker: str
    foot: str
    time: np.ndarray
    q: np.ndarray
    T_meas: np.ndarray
    cov: np.ndarray
    cov_extra = None

    @property
    def p_foot_marker(self) -> np.ndarray:
        """The measured point on the frame: its origin (used by the rigid-fit start)."""
        return np.zeros(3)

    @property
    def p_meas(self) -> np.ndarray:
        """(N, 3) measured origins (m)."""
        return self.T_meas[:, :3, 3]

    def __len__(self) -> int:
        return int(self.time.shape[0])

    def select(self, rows) -> "PoseTrack":
        """A track with the chosen rows (boolean mask or index array)."""
        return PoseTrack(self.marker, self.foot, self.time[rows], self.q[rows], self.T_meas[rows], self.cov[rows])


@dataclass(frozen=True, eq=False)
class MocapData:
    """Everything leg identification needs from a dataset.

    Attributes:
        robot: the :class:`~graphcal.models.robot.RobotModel`.
        tracks: one :class:`MarkerTrack` per foot marker.
        frame: ``"mocap"`` (frame fixed to the base) or ``"vbase"`` (Yuan's virtual base).
        T_body_mocap_nominal: (4, 4) nominal pose of the measurement frame in the body frame
            (``T_body_vbase`` from the body markers' ``xyz`` in dataset.yaml), or None (unknown).
        source: the dataset path, for reports.
        warnings: what was dropped and why.
        noise: the declared noise of dataset.yaml (``mocap.sigma_mm`` -> ``sigma_m``,
            ``mocap.sigma_joint_deg`` -> ``sigma_joint_rad``, SI), empty when not declared.
    """

    robot: object
    tracks: tuple[MarkerTrack, ...]
    frame: str = "mocap"
    T_body_mocap_nominal: np.ndarray | None = None
    source: str = ""
    warnings: tuple[str, ...] = field(default_factory=tuple)
    noise: dict = field(default_factory=dict)

    @property
    def feet(self) -> tuple[str, ...]:
        """Feet with at least one track, in robot.feet order."""
        have = {t.foot for t in self.tracks}
        return tuple(f for f in self.robot.feet if f in have)


#: a leg whose joints all vary less than this over a marker's samples identifies nothing
MIN_JOINT_SPREAD_RAD = 1e-6
#: a foot marker that spreads less than this over its samples (in the frame its points are used in)
#: did not follow the foot (measured: a frozen marker made the identification shrink the leg to a
#: point, "+- 0.000 mm", sigma nan, and write that URDF)
MIN_MARKER_SPREAD_M = 1e-3


def marker_foot(name: str, feet, markers) -> str | None:
    """The foot a marker is fixed to (by its name or ``mocap.markers.<name>.link``), or None."""
    if name in markers:
        link = markers[name].link
        return link if link in feet else None
    if name in feet:
        return name
    base, dot, k = name.rpartition(".")
    if dot and k.isdigit() and base in feet:
        return base
    return None


def _joint_table(ds):
    """(file name, Table) of the joint values with a time column: stations.csv, else timeseries.csv."""
    root = ds.root if ds.root is not None else Path(".")
    for name, t in (("stations.csv", ds.stations), ("timeseries.csv", ds.timeseries)):
        if t is not None and t.has("time") and len(t):
            return root / name, t
    raise DatasetError(root / "stations.csv", "column time",
                       "joint values at the times of mocap.csv (stations.csv or timeseries.csv with a time column)",
                       "no table with times")  # fmt: skip


def mocap_data_from_dataset(dataset, *, sigma_body_marker_m: float | None = None) -> MocapData:
    """The motion-capture tracks of a dataset (see module docstring).

    Args:
        dataset: a dataset folder (path) or a :class:`~graphcal.io.dataset.Dataset`.
        sigma_body_marker_m: noise of the body markers (m); when given, the virtual base's
            uncertainty is propagated into each sample's covariance (``MarkerTrack.cov_extra``).

    Raises:
        DatasetError: no robot, no mocap.csv, no marker on a foot, too few samples, body markers
            incomplete or degenerate, non-finite joint values (file and field named).
    """
    from graphcal.io.dataset import Dataset, load_dataset_robot, read_dataset

    ds = dataset if isinstance(dataset, Dataset) else read_dataset(dataset)
    root = ds.root if ds.root is not None else Path(".")
    if ds.robot is None:
        raise DatasetError(root / "dataset.yaml", "robot", "a robot (urdf or model, base_frame, feet) whose legs to identify",
                           "none")  # fmt: skip
    if ds.mocap is None and ds.mocap_poses is None:
        raise DatasetError(root / "mocap.csv", "file", "motion-capture markers (mocap.csv: time, marker, x, y, z) "
                           "or measured poses (mocap_poses.csv)", "missing")  # fmt: skip
    mocap_file = root / "mocap.csv"
    robot = load_dataset_robot(ds)
    feet = tuple(robot.feet)
    jfile, jt = _joint_table(ds)
    row_of_time = {}
    for i, t in enumerate(jt["time"].tolist()):
        row_of_time.setdefault(t, i)

    by_marker: dict[str, dict[float, np.ndarray]] = {}
    if ds.mocap is not None:
        m = ds.mocap
        xyz = np.column_stack([m["x"], m["y"], m["z"]])
        for i, (name, t) in enumerate(zip(m["marker"].tolist(), m["time"].tolist())):
            by_marker.setdefault(name, {})[t] = xyz[i]
    warnings: list[str] = []

    present = [b for b in BODY_MARKERS if b in by_marker]
    use_vbase = bool(present)
    if use_vbase and len(present) != 4:
        raise DatasetError(mocap_file, "column marker", "all four body markers body.1 ... body.4 (Yuan's virtual base) or none",
                           f"only {', '.join(present)}")  # fmt: skip
    extra_body = sorted(n for n in by_marker if n.startswith("body.") and n not in BODY_MARKERS)
    if extra_body:
        warnings.append(f"body markers {', '.join(extra_body)} ignored (the virtual base uses body.1 ... body.4)")

    T_nominal = None
    if use_vbase:
        specs = [ds.mocap_markers.get(b) for b in BODY_MARKERS]
        if all(s is not None and s.xyz is not None for s in specs):
            links = {s.link for s in specs}
            if links == {robot.base_frame}:
                try:
                    T_nominal = virtual_base(np.array([s.xyz for s in specs]))
                except GraphcalError as exc:
                    raise DatasetError(root / "dataset.yaml", "mocap.markers.body.1 ... body.4.xyz",
                                       "four body marker positions spanning a quadrilateral", str(exc)) from None
            else:
                warnings.append(f"body markers are on links {sorted(links)}, not on the base frame "
                                f"{robot.base_frame!r}: their nominal layout is not used")
        body_times = set.intersection(*(set(by_marker[b]) for b in BODY_MARKERS))

    tracks: list[MarkerTrack] = []
    too_few: dict[str, int] = {}  # foot marker -> its samples, where fewer than MIN_SAMPLES
    for name in sorted(by_marker):
        if name.startswith("body."):
            continue
        foot = marker_foot(name, feet, ds.mocap_markers)
        if foot is None:
            link = ds.mocap_markers[name].link if name in ds.mocap_markers else "?"
            warnings.append(f"marker {name!r} (link {link!r}) is not on a foot of robot.feet: not used")
            continue
        leg = robot.leg(foot)
        samples = by_marker[name]
        ts = sorted(samples)
        if use_vbase:
            kept = [t for t in ts if t in body_times]
            if len(kept) < len(ts):
                warnings.append(f"marker {name!r}: {len(ts) - len(kept)} sample(s) without all four body markers dropped")
            ts = kept
        rows = [row_of_time.get(t) for t in ts]
        if any(r is None for r in rows):  # read_dataset matched every time already; kept for safety
            t_bad = ts[[r is None for r in rows].index(True)]
            raise DatasetError(mocap_file, "column time", f"a time of {jfile.name}", t_bad)
        rows = np.asarray(rows, dtype=int)
        cols = []
        for j in leg.joint_names:
            c = f"q_{j}"
            if not jt.has(c):
                raise DatasetError(jfile, f"header, column {c}", f"joint values of every joint of the leg of {foot!r}",
                                   "missing")  # fmt: skip
            cols.append(np.asarray(jt[c], dtype=float)[rows])
        q = np.column_stack(cols) if cols else np.zeros((len(rows), 0))
        P = np.array([samples[t] for t in ts], dtype=float).reshape(-1, 3)
        ok = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(P), axis=1)
        if not ok.all():
            i = int(np.argmax(~ok))
            raise DatasetError(jfile if not np.all(np.isfinite(q[i])) else mocap_file,
                               f"time {ts[i]!r}", f"finite joint values and marker coordinates for marker {name!r}",
                               "nan or inf")  # fmt: skip
        t_arr = np.asarray(ts, dtype=float)
        cov_extra = None
        if use_vbase and len(ts):
            B = np.array([[by_marker[b][t] for b in BODY_MARKERS] for t in ts], dtype=float)
            try:
                T_mv = virtual_base(B)
            except GraphcalError as exc:
                raise DatasetError(mocap_file, "markers body.1 ... body.4", "four body markers spanning a quadrilateral, "
                                   "counter-clockwise from the left front", str(exc)) from None  # fmt: skip
            P = vbase_points(T_mv, P)
            if sigma_body_marker_m:
                cov_extra = point_covariance_in_vbase(P, virtual_base_covariance(B, sigma_body_marker_m))
        if len(ts) < MIN_SAMPLES:
            warnings.append(f"marker {name!r}: only {len(ts)} sample(s), not used (at least {MIN_SAMPLES})")
            too_few[name] = len(ts)
            continue
        joint_spread = np.ptp(q, axis=0) if q.size else np.zeros(0)
        if q.shape[1] and not np.any(joint_spread > MIN_JOINT_SPREAD_RAD):
            raise DatasetError(jfile, f"columns {', '.join(f'q_{j}' for j in leg.joint_names)}",
                               f"joint values that vary over the samples of marker {name!r} (the leg's parameters "
                               "are identified from its motion)", "the same values in every sample")
        if float(np.max(np.ptp(P, axis=0))) < MIN_MARKER_SPREAD_M:
            raise DatasetError(mocap_file, f"marker {name!r}",
                               f"a foot marker that moves as the joints move (it spreads less than "
                               f"{MIN_MARKER_SPREAD_M * 1e3:g} mm{' in the virtual base' if use_vbase else ''}: "
                               "a marker the motion capture lost and held, or the wrong marker)",
                               f"spread {float(np.max(np.ptp(P, axis=0))) * 1e3:.3g} mm while the joints move "
                               f"{float(np.degrees(joint_spread.max())):.3g} deg")
        spec = ds.mocap_markers.get(name)
        pfm = None if spec is None or spec.xyz is None else np.array(spec.xyz, dtype=float)
        tracks.append(MarkerTrack(name, foot, t_arr, q, P, pfm, cov_extra))
    if ds.mocap_poses is not None:
        T_mv = None
        if use_vbase:
            T_mv = {t: virtual_base(np.array([by_marker[b][t] for b in BODY_MARKERS], dtype=float)) for t in body_times}
        tracks += pose_tracks_from_table(root / "mocap_poses.csv", ds.mocap_poses, robot, jfile, jt, row_of_time,
                                         T_mv, warnings)
    if not tracks:
        raise DatasetError(mocap_file, "column marker",
                           f"samples of at least one marker on a foot of robot.feet ({', '.join(feet) or 'none'}): "
                           f"named after the foot (lf_foot, lf_foot.1) or with mocap.markers.<name>.link a foot, "
                           f"at least {MIN_SAMPLES} samples",
                           ("foot markers with too few samples: " + ", ".join(f"{m} ({k})" for m, k in sorted(too_few.items()))
                            if too_few else ", ".join(sorted(by_marker)) or "no markers"))  # fmt: skip
    source = str(root if isinstance(dataset, Dataset) else dataset)
    return MocapData(robot, tuple(tracks), "vbase" if use_vbase else "mocap", T_nominal, source, tuple(warnings),
                     dict(ds.mocap_noise))


def _unit(q) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    return q / np.linalg.norm(q)


def pose_tracks_from_table(pfile: Path, table, robot, jfile: Path, jt, row_of_time: dict, T_mocap_vbase,
                           warnings: list) -> list[PoseTrack]:
    """One :class:`PoseTrack` per frame of ``mocap_poses.csv`` (``table``, checked by the reader).

    Args:
        pfile: the file, for messages. table: its :class:`~graphcal.io.dataset.Table`.
        robot: the robot; jfile, jt: the joint table (file, Table); row_of_time: time -> its row.
        T_mocap_vbase: time -> (4, 4) virtual base in the mocap frame (poses are re-expressed in
            it; times without it are dropped), or None (mocap frame fixed to the base).
        warnings: appended to.

    Without sigma columns each pose gets :data:`~graphcal.factors.mocap_pose.DEFAULT_SIGMA_POSE`
    (0.1 deg, 1 mm per axis).
    """
    from graphcal.factors.mocap_pose import DEFAULT_SIGMA_POSE
    from graphcal.geometry import pose_from_xyz_quat_wxyz

    out = []
    frames = table["frame"].tolist()
    if not table.has("sigma_x") and not table.has("cov_00"):
        warnings.append(f"{pfile.name}: no sigma columns; every pose has the default sigma of 0.1 deg and 1 mm per axis")
    for name in dict.fromkeys(frames):
        idx = [i for i, f in enumerate(frames) if f == name]
        ts = table["time"][idx]
        if T_mocap_vbase is not None:
            keep = [k for k, t in enumerate(ts.tolist()) if t in T_mocap_vbase]
            if len(keep) < len(idx):
                warnings.append(f"pose {name!r}: {len(idx) - len(keep)} sample(s) without all four body markers dropped")
            idx, ts = [idx[k] for k in keep], ts[keep]
        if len(idx) < MIN_SAMPLES:
            warnings.append(f"pose {name!r}: only {len(idx)} sample(s), not used (at least {MIN_SAMPLES})")
            continue
        leg = robot.leg(name)
        rows = np.asarray([row_of_time[t] for t in ts.tolist()], dtype=int)
        for j in leg.joint_names:
            if not jt.has(f"q_{j}"):
                raise DatasetError(jfile, f"header, column q_{j}", f"joint values of every joint of the leg of {name!r}",
                                   "missing")  # fmt: skip
        q = np.column_stack([np.asarray(jt[f"q_{j}"], dtype=float)[rows] for j in leg.joint_names])
        T = np.array([pose_from_xyz_quat_wxyz([table[c][i] for c in "xyz"], _unit([table[c][i] for c in ("qw", "qx", "qy", "qz")]))
                      for i in idx])
        if T_mocap_vbase is not None:
            T = np.array([np.linalg.inv(T_mocap_vbase[t]) @ Ti for t, Ti in zip(ts.tolist(), T)])
        if table.has("cov_00"):
            cov = np.stack([table[f"cov_{i}{j}"][idx] for i in range(6) for j in range(6)], axis=1).reshape(-1, 6, 6)
            cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
        else:
            s = (np.column_stack([table[c][idx] for c in ("sigma_rx", "sigma_ry", "sigma_rz", "sigma_x", "sigma_y", "sigma_z")])
                 if table.has("sigma_x") else np.tile(np.asarray(DEFAULT_SIGMA_POSE, dtype=float), (len(idx), 1)))
            cov = np.einsum("ni,ij->nij", s**2, np.eye(6))
        out.append(PoseTrack(f"pose:{name}", name, np.asarray(ts, dtype=float), q, T, cov))
    return out
