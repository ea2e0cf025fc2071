"""The value checks of each CSV file once read (units, unit quaternions and normals, covariances,
ids, times, markers, joint columns against the robot); each raises one
:class:`~graphcal.errors.DatasetError` naming the file, row and column."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from graphcal.errors import DatasetError
from graphcal.io.dataset.model import (
    BODY_POSE_COLUMNS,
    IMU_ACCEL_COLUMNS,
    IMU_GYRO_COLUMNS,
    MAX_ABS_ACCEL_MPS2,
    MAX_ABS_BODY_M,
    MAX_ABS_EFFORT,
    MAX_ABS_GYRO_RADPS,
    MAX_ABS_JOINT,
    MAX_ABS_PLANE_COV,
    MAX_ABS_TIME_S,
    MAX_PLANE_POINTS,
    MAX_PLANE_RMS_M,
    MIN_PLANE_COV_EIG,
    MIN_PLANE_D_M,
    MM_LIMIT_BODY_M,
    MM_LIMIT_MOCAP_M,
    MM_LIMIT_PLANE_D_M,
    PLANE_COV_COLUMNS,
    UNIT_NORM_TOL,
    MarkerSpec,
)
from graphcal.io.dataset.paths import path_inside
from graphcal.io.dataset.schema import YamlHeader
from graphcal.io.dataset.tables import ParsedCsv
from graphcal.io.dataset.text import MILLIMETRES_HINT, did_you_mean

#: (columns, largest magnitude, what it is) of the values a robot can have, checked first
log = logging.getLogger(__name__)

_MAGNITUDES = (
    (("time",), MAX_ABS_TIME_S, "seconds"),
    (BODY_POSE_COLUMNS[:3], MAX_ABS_BODY_M, "a body position in metres"),
    (BODY_POSE_COLUMNS[3:], 2.0, "a quaternion component"),
    (IMU_ACCEL_COLUMNS, MAX_ABS_ACCEL_MPS2, "a specific force in m/s² (an IMU saturates far below)"),
    (IMU_GYRO_COLUMNS, MAX_ABS_GYRO_RADPS, "a rate in rad/s (an IMU saturates far below)"),
    (("nx", "ny", "nz"), 2.0, "a unit-normal component"),
    (("n_points",), MAX_PLANE_POINTS, "a number of points"),
    (("rms",), MAX_PLANE_RMS_M, "an rms distance in metres"),
    (PLANE_COV_COLUMNS, MAX_ABS_PLANE_COV, "a plane covariance entry (rad², rad m, m²)"),
)


def check_magnitudes(p: ParsedCsv) -> None:
    """Every number of a CSV file within what a robot can have (:data:`_MAGNITUDES`; the joint
    values and efforts are checked with the robot, :func:`check_joint_columns`): a value such as
    1e300 is refused here, naming its row, before it reaches a solver (where it overflowed)."""
    t = p.table
    for columns, limit, what in _MAGNITUDES:
        for c in columns:
            if not t.has(c) or not len(t):
                continue
            bad = ~(np.abs(t[c]) <= limit)
            if bad.any():
                i = int(np.argmax(bad))
                raise p.err(i, c, f"{what} (|{c}| <= {limit:g})", float(t[c][i]))


def _check_body_imu(p: ParsedCsv, stations: bool) -> None:
    t = p.table
    if t.has("body_qw"):
        q = np.stack([t[c] for c in BODY_POSE_COLUMNS[3:]], axis=1)
        norm = np.linalg.norm(q, axis=1)
        bad = np.abs(norm - 1.0) > UNIT_NORM_TOL
        if bad.any():
            i = int(np.argmax(bad))
            raise p.err(i, "body_qw..body_qz", f"a unit quaternion (norm within {UNIT_NORM_TOL:g} of 1)",
                        f"norm {norm[i]:.6g}")
        for c in BODY_POSE_COLUMNS[:3] if stations else ("body_z",):
            bad = np.abs(t[c]) > MM_LIMIT_BODY_M
            if bad.any():
                i = int(np.argmax(bad))
                raise p.err(i, c, f"metres (|{c}| <= {MM_LIMIT_BODY_M:g}); {MILLIMETRES_HINT}", float(t[c][i]))
    if t.has("imu_ax") and len(t):
        # the median specific force of a static station, and of a walking robot, is ~9.81 m/s²
        f = np.linalg.norm(np.stack([t[c] for c in IMU_ACCEL_COLUMNS], axis=1), axis=1)
        med = float(np.median(f))
        if 0.5 <= med <= 1.5:
            where = "at a static station" if stations else "over a walk"
            raise p.err(int(np.argmin(np.abs(f - med))), "imu_ax..imu_az",
                        f"specific force in m/s² (a median norm of about 9.81 {where}); this looks like units of g",
                        f"median norm {med:.4g}")  # fmt: skip


def check_stations(p: ParsedCsv) -> None:
    """stations.csv: unique station ids, unit body quaternions, body positions and IMU specific
    force in SI units."""
    st = p.table["station"]
    first: dict[int, int] = {}
    if len(np.unique(st)) != len(st):
        for i, s in enumerate(st.tolist()):
            if s in first:
                raise p.err(i, "station", f"unique station ids (station {s} is already on row {first[s] + 1})", s)
            first[s] = i
    _check_body_imu(p, stations=True)


def check_timeseries(p: ParsedCsv, header: YamlHeader, root: Path) -> set[Path]:
    """Checks timeseries.csv (times in s that never decrease, contacts 0/1 (or probabilities) and
    foot loads (N) of feet of ``header``, cloud
    cells naming PLY files inside the dataset folder ``root``); returns the cloud files it references."""
    t = p.table
    time = t["time"]
    if len(time) > 1:
        back = np.diff(time) < 0
        if back.any():
            i = int(np.argmax(back)) + 1
            raise p.err(i, "time", f"times that never decrease (row {i} has {float(time[i - 1])!r})", float(time[i]))
    _check_body_imu(p, stations=False)
    feet = header.robot.feet if header.robot else ()
    for foot in t.suffixes("contact_"):
        col = f"contact_{foot}"
        if foot not in feet:
            raise DatasetError(p.file, f"header, column {col}", f"contact_<foot> with a foot of robot.feet in "
                               f"dataset.yaml ({', '.join(feet) or 'none'})", col)  # fmt: skip
        bad = ~((t[col] >= 0.0) & (t[col] <= 1.0))
        if bad.any():
            i = int(np.argmax(bad))
            raise p.err(i, col, "0 or 1 (or a contact probability in [0, 1])", float(t[col][i]))
    for foot in t.suffixes("force_"):
        col = f"force_{foot}"
        if foot not in feet:
            raise DatasetError(p.file, f"header, column {col}", f"force_<foot> with a foot of robot.feet in "
                               f"dataset.yaml ({', '.join(feet) or 'none'})", col)  # fmt: skip
        bad = ~np.isfinite(np.asarray(t[col], dtype=float))
        if bad.any():
            i = int(np.argmax(bad))
            raise p.err(i, col, "a finite foot load in newtons", t[col][i])
    referenced: set[Path] = set()
    for sensor in t.suffixes("cloud_"):
        col = f"cloud_{sensor}"
        if sensor not in header.sensors:
            raise DatasetError(p.file, f"header, column {col}", "cloud_<sensor> with a sensor of dataset.yaml "
                               f"({', '.join(header.sensors) or 'none'})", col)  # fmt: skip
        values = t[col]
        seen: dict[str, Path] = {}
        for i, rel in enumerate(values.tolist()):
            if not rel or rel in seen:
                continue
            full = path_inside(root, rel, p.file, p.where(i, col))
            if full.suffix.lower() != ".ply":
                raise p.err(i, col, "the relative path of a .ply cloud", rel)
            if not full.is_file():
                raise p.err(i, col, "the relative path of an existing cloud file", f"{rel} (no such file)")
            seen[rel] = full
        referenced.update(seen.values())
    return referenced


#: at most this share of planes.csv's rows may hold a distance in millimetres when the reader is
#: asked to keep them (``graphcal diagnose``: a unit slip in a few rows is a bookkeeping error it
#: names and corrects); more, and the column is in the wrong unit: refused
MAX_UNIT_SLIP_SHARE = 0.2


def check_planes(p: ParsedCsv, header: YamlHeader, station_ids: np.ndarray | None, *,
                 keep_unit_slips: bool = False) -> None:
    """planes.csv: unit normals, ``d >= 0`` in metres, counts, rms, covariances (symmetric, PSD, of
    full rank across the plane), sensors of ``header`` and stations among ``station_ids`` (the ids
    of stations.csv, None without it). ``keep_unit_slips``: a few rows (at most
    :data:`MAX_UNIT_SLIP_SHARE`) whose d looks like millimetres are kept, with a warning, for the
    diagnosis to name and correct (graphcal/diagnosis/association.py); otherwise refused."""
    t = p.table
    n = np.stack([t["nx"], t["ny"], t["nz"]], axis=1)
    norm = np.linalg.norm(n, axis=1)
    bad = np.abs(norm - 1.0) > UNIT_NORM_TOL
    if bad.any():
        i = int(np.argmax(bad))
        raise p.err(i, "nx..nz", f"a unit normal (norm within {UNIT_NORM_TOL:g} of 1)", f"norm {norm[i]:.6g}")
    d = t["d"]
    bad = d < 0
    if bad.any():
        i = int(np.argmax(bad))
        raise p.err(i, "d", "d >= 0 (the contract orients n from the plane towards the sensor origin: "
                    "flip the signs of nx, ny, nz and d)", float(d[i]))  # fmt: skip
    bad = d > MM_LIMIT_PLANE_D_M
    if bad.any():
        i = int(np.argmax(bad))
        if not keep_unit_slips or bad.mean() > MAX_UNIT_SLIP_SHARE:
            raise p.err(i, "d", f"metres (d <= {MM_LIMIT_PLANE_D_M:g}); {MILLIMETRES_HINT}", float(d[i]))
        log.warning(f"{p.err(i, 'd', f'metres (d <= {MM_LIMIT_PLANE_D_M:g}); {MILLIMETRES_HINT}', float(d[i]))} "
                    f"({int(bad.sum())} of {len(d)} rows): kept for the diagnosis to test as a unit slip")
    bad = d < MIN_PLANE_D_M
    if bad.any():
        i = int(np.argmax(bad))
        raise p.err(i, "d", f"d >= {MIN_PLANE_D_M:g} m (the distance from the sensor to the plane: a sensor does not "
                    "see a plane through its own origin)", float(d[i]))  # fmt: skip
    if t.has("n_points"):
        npts = t["n_points"]
        bad = (npts < 0) | (npts != np.round(npts))
        if bad.any():
            i = int(np.argmax(bad))
            raise p.err(i, "n_points", "a whole number of points >= 0", float(npts[i]))
    if t.has("rms"):
        bad = t["rms"] < 0
        if bad.any():
            i = int(np.argmax(bad))
            raise p.err(i, "rms", "an rms distance >= 0 (m)", float(t["rms"][i]))
    if t.has("cov_00") and len(t):
        C = np.stack([t[c] for c in PLANE_COV_COLUMNS], axis=1).reshape(-1, 4, 4)
        scale = np.abs(C).max(axis=(1, 2))
        asym = np.abs(C - np.swapaxes(C, 1, 2)).max(axis=(1, 2))
        bad = asym > 1e-6 * scale
        if bad.any():
            i = int(np.argmax(bad))
            raise p.err(i, "cov_00..cov_33", "a symmetric covariance (cov_ij = cov_ji)", f"asymmetry {asym[i]:.3g}")
        diag = np.diagonal(C, axis1=1, axis2=2)
        bad = (diag < 0).any(axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            raise p.err(i, "cov_00..cov_33", "variances >= 0 on the diagonal", diag[i].tolist())
        Cs = 0.5 * (C + np.swapaxes(C, 1, 2))
        low = np.linalg.eigvalsh(Cs)[:, 0]
        bad = low < -1e-9 * np.maximum(scale, 1e-300)
        if bad.any():
            i = int(np.argmax(bad))
            raise p.err(i, "cov_00..cov_33", "a positive semi-definite covariance", f"an eigenvalue of {low[i]:.3g}")
        # the plane factor needs it across the plane: tilt about two in-plane axes and the offset d
        helper = np.eye(3)[np.argmin(np.abs(n), axis=1)]
        t1 = np.cross(helper, n)
        t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
        t2 = np.cross(n / norm[:, None], t1)
        G = np.zeros((len(t), 4, 3))
        G[:, :3, 0], G[:, :3, 1], G[:, 3, 2] = t1, t2, 1.0
        w = np.linalg.eigvalsh(np.swapaxes(G, 1, 2) @ Cs @ G)
        bad = (w[:, 0] <= 1e-12 * w[:, 2]) | (w[:, 2] <= 0.0)
        if bad.any():
            i = int(np.argmax(bad))
            raise p.err(i, "cov_00..cov_33", "a covariance of full rank 3 across the plane (two tilts and d); "
                        "without a covariance leave out the cov_ columns (a default is used), never zeros",
                        f"eigenvalues {np.array2string(w[i], precision=3)}")
        bad = w[:, 0] < MIN_PLANE_COV_EIG
        if bad.any():
            i = int(np.argmax(bad))
            raise p.err(i, "cov_00..cov_33", f"a covariance whose eigenvalues across the plane are >= "
                        f"{MIN_PLANE_COV_EIG:g} (a sigma of a picometre or a nanoradian: smaller ones overflow "
                        "the solver's whitening)", f"eigenvalues {np.array2string(w[i], precision=3)}")
    for i, s in enumerate(t["sensor"].tolist()):
        if s not in header.sensors:
            raise p.err(i, "sensor", f"a sensor of dataset.yaml ({', '.join(header.sensors) or 'none'})", s)
    if station_ids is None:
        if len(t):
            raise p.err(0, "station", "a station of stations.csv", "no stations.csv in the dataset")
    else:
        bad = ~np.isin(t["station"], station_ids)
        if bad.any():
            i = int(np.argmax(bad))
            empty = " (stations.csv has a header but no rows)" if len(station_ids) == 0 else ""
            raise p.err(i, "station", f"a station id of stations.csv{empty}", int(t["station"][i]))


def _marker_ok(name: str, feet: Sequence[str], markers: Mapping[str, MarkerSpec]) -> bool:
    if name in markers or name in feet:
        return True
    base, dot, k = name.rpartition(".")
    return bool(dot) and k.isdigit() and int(k) >= 1 and (base == "body" or base in feet)


def check_mocap(p: ParsedCsv, header: YamlHeader, times: np.ndarray | None) -> None:
    """mocap.csv: marker names (feet, ``body.k`` or ``mocap.markers`` of ``header``), positions in
    metres, times among ``times`` (s; those of stations.csv and timeseries.csv, None without any),
    each marker once per time."""
    t = p.table
    feet = header.robot.feet if header.robot else ()
    for i, name in enumerate(t["marker"].tolist()):
        if not _marker_ok(name, feet, header.mocap_markers):
            raise p.err(i, "marker", "a marker named after a foot of robot.feet (lf_foot or lf_foot.1), "
                        "body.1 ... body.4, or a marker of mocap.markers in dataset.yaml", name)  # fmt: skip
    _check_mocap_rows(p, times, "marker")


def _check_mocap_rows(p: ParsedCsv, times: np.ndarray | None, name_column: str) -> None:
    """mocap.csv / mocap_poses.csv: x, y, z in metres, times among ``times``, each ``name_column``
    (marker / frame) once per time."""
    t = p.table
    for c in ("x", "y", "z"):
        bad = np.abs(t[c]) > MM_LIMIT_MOCAP_M
        if bad.any():
            i = int(np.argmax(bad))
            raise p.err(i, c, f"metres (|{c}| <= {MM_LIMIT_MOCAP_M:g}); {MILLIMETRES_HINT}", float(t[c][i]))
    if not len(t):
        return
    if times is None:
        raise p.err(0, "time", "the time of a station or sample (stations.csv with a time column, "
                    "or timeseries.csv)", "no times to match")  # fmt: skip
    bad = ~np.isin(t["time"], times)
    if bad.any():
        i = int(np.argmax(bad))
        raise p.err(i, "time", "the time of a station of stations.csv or a sample of timeseries.csv (same number)",
                    float(t["time"][i]))
    seen: dict[tuple[float, str], int] = {}
    for i, key in enumerate(zip(t["time"].tolist(), t[name_column].tolist())):
        if key in seen:
            raise p.err(i, name_column, f"each {name_column} once per time (already on row {seen[key] + 1})", key[1])
        seen[key] = i


def check_mocap_poses(p: ParsedCsv, header: YamlHeader, times: np.ndarray | None) -> None:
    """mocap_poses.csv: ``frame`` a foot (end frame) of robot.feet, positions in metres, unit
    quaternions, sigmas > 0 (rotation sigmas below pi rad), times among ``times``, each frame once per time."""
    t = p.table
    feet = header.robot.feet if header.robot else ()
    for i, name in enumerate(t["frame"].tolist()):
        if name not in feet:
            raise p.err(i, "frame", "a frame of robot.feet (the measured end frame of a leg, arm or tool)", name)
    if len(t):
        norm = np.linalg.norm(np.stack([t[c] for c in ("qw", "qx", "qy", "qz")], axis=1), axis=1)
        bad = np.abs(norm - 1.0) > UNIT_NORM_TOL
        if bad.any():
            i = int(np.argmax(bad))
            raise p.err(i, "qw..qz", f"a unit quaternion (norm within {UNIT_NORM_TOL:g} of 1)", f"norm {norm[i]:.6g}")
    if t.has("sigma_x"):
        for c in ("sigma_rx", "sigma_ry", "sigma_rz", "sigma_x", "sigma_y", "sigma_z"):
            hi = np.pi if c.startswith("sigma_r") else MM_LIMIT_MOCAP_M
            bad = ~((t[c] > 0) & (t[c] < hi))
            if bad.any():
                i = int(np.argmax(bad))
                unit = "rad, below pi" if c.startswith("sigma_r") else "m"
                raise p.err(i, c, f"a standard deviation > 0 ({unit})", float(t[c][i]))
    if t.has("cov_00"):
        if t.has("sigma_x"):
            raise p.err(0, "sigma_rx ... sigma_z", "either per-axis sigmas or the covariance cov_00 ... cov_55, "
                        "not both", "both")  # fmt: skip
        C = np.stack([t[f"cov_{i}{j}"] for i in range(6) for j in range(6)], axis=1).reshape(-1, 6, 6)
        for i, c in enumerate(C):
            scale = max(float(np.max(np.abs(c))), 1e-300)
            if np.max(np.abs(c - c.T)) > 1e-6 * scale:
                raise p.err(i, "cov_00..cov_55", "a symmetric covariance (cov_ij = cov_ji)",
                            f"asymmetry {np.max(np.abs(c - c.T)):.3g}")
            ev = np.linalg.eigvalsh(0.5 * (c + c.T))
            if ev.min() <= 1e-12 * scale:
                raise p.err(i, "cov_00..cov_55", "a positive definite covariance (rad^2, m^2)",
                            f"smallest eigenvalue {ev.min():.3g}")
    _check_mocap_rows(p, times, "frame")


def check_joint_columns(robot, parsed: Mapping[str, ParsedCsv]) -> None:
    """q_/tau_ columns name moving joints of the URDF, and every leg joint has a q_ column (in
    radians). ``robot``: the loaded :class:`~graphcal.models.robot.RobotModel` or None; ``parsed``:
    the CSV files read, by kind."""
    for kind in ("stations", "timeseries"):
        if kind not in parsed:
            continue
        p = parsed[kind]
        if robot is None:
            for c in p.table.columns:
                if c.startswith(("q_", "tau_")):
                    raise DatasetError(p.file, f"header, column {c}", "a robot in dataset.yaml to name the joints",
                                       "no robot")  # fmt: skip
            continue
        joints = set(robot.joint_names)
        for prefix in ("q_", "tau_"):
            for j in p.table.suffixes(prefix):
                if j not in joints:
                    raise DatasetError(p.file, f"header, column {prefix}{j}", "a moving joint of the URDF",
                                       f"{j!r}{did_you_mean(j, joints)}")  # fmt: skip
        for foot in robot.feet:
            leg = robot.legs[foot]
            for k, j in enumerate(leg.joint_names):
                if not p.table.has(f"q_{j}"):
                    raise DatasetError(p.file, f"header, column q_{j}",
                                       f"a column for every moving joint on a leg (joint {j!r} of foot {foot!r})",
                                       "missing")  # fmt: skip
                _check_radians(p, j, leg.joint_types[k], leg.lower[k], leg.upper[k])
        for c in p.table.columns:
            if c.startswith(("q_", "tau_")) and len(p.table):
                limit = MAX_ABS_JOINT if c.startswith("q_") else MAX_ABS_EFFORT
                what = "a joint value in rad or m" if c.startswith("q_") else "a joint effort in N m or N"
                bad = ~(np.abs(p.table[c]) <= limit)
                if bad.any():
                    i = int(np.argmax(bad))
                    raise p.err(i, c, f"{what} (|{c}| <= {limit:.4g})", float(p.table[c][i]))


#: the values of dataset.yaml's stance.feet_fixed_within graphcal knows: the feet stay planted within
#: a session (the contract's default), are re-planted at every station, or within a step of a walk


def _check_radians(p: ParsedCsv, joint: str, joint_type: str, lower: float, upper: float) -> None:
    """Degrees where the contract says radians: a revolute joint whose URDF limits lie within one
    turn, with most of its rows beyond a full turn (2 pi), cannot be in radians. (A few rows beyond
    the limits are left to the limit warnings: a sign error or a wrapped encoder.)"""
    if joint_type == "prismatic" or not (np.isfinite(lower) and np.isfinite(upper)):
        return
    if max(abs(lower), abs(upper)) > 2 * np.pi or not len(p.table):
        return
    q = np.abs(np.asarray(p.table[f"q_{joint}"], dtype=float))
    beyond = int(np.count_nonzero(q > 2 * np.pi))
    if beyond > len(q) / 2:
        raise DatasetError(p.file, f"column q_{joint}",
                           f"radians (the contract's unit; its URDF limits are [{lower:.4g}, {upper:.4g}] rad)",
                           f"{beyond} of {len(q)} rows beyond a full turn, up to {q.max():.4g}: degrees?")
