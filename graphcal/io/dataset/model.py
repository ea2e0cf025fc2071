"""The dataset contract in memory: its constants and frozen dataclasses (:class:`Dataset`,
:class:`Table`, :class:`PosePrior`, :class:`RobotSpec`, :class:`SensorSpec`, :class:`ImuSpec`,
:class:`MarkerSpec`). SI units: metres, radians, seconds."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from graphcal.geometry import pose_from_xyz_rpy
from graphcal.io.dataset.text import did_you_mean

FORMAT = "graphcal-dataset/1"

BODY_POSE_COLUMNS = ("body_x", "body_y", "body_z", "body_qw", "body_qx", "body_qy", "body_qz")
IMU_ACCEL_COLUMNS = ("imu_ax", "imu_ay", "imu_az")
IMU_GYRO_COLUMNS = ("imu_gx", "imu_gy", "imu_gz")
PLANE_REQUIRED_COLUMNS = ("station", "sensor", "nx", "ny", "nz", "d")
PLANE_COV_COLUMNS = tuple(f"cov_{i}{j}" for i in range(4) for j in range(4))
MOCAP_COLUMNS = ("time", "marker", "x", "y", "z")
#: mocap_poses.csv: a measured 6-D pose of a robot frame (m, unit quaternion w x y z) in the measurement frame
MOCAP_POSE_COLUMNS = ("time", "frame", "x", "y", "z", "qw", "qx", "qy", "qz")
#: its optional per-axis sigmas [rx, ry, rz (rad), x, y, z (m)], the measured frame's axes (all six or none)
MOCAP_POSE_SIGMA_COLUMNS = ("sigma_rx", "sigma_ry", "sigma_rz", "sigma_x", "sigma_y", "sigma_z")
#: or its full 6x6 covariance, row-major, same order and axes (rad^2, rad m, m^2; all 36 or none)
MOCAP_POSE_COV_COLUMNS = tuple(f"cov_{i}{j}" for i in range(6) for j in range(6))

#: Tolerances and "looks like millimetres" limits (metres) of the checks; see docs/dataset.md.
UNIT_NORM_TOL = 1e-3
MM_LIMIT_BODY_M = 50.0
MM_LIMIT_PRIOR_M = 10.0
MM_LIMIT_PLANE_D_M = 100.0
MM_LIMIT_MOCAP_M = 100.0
MM_LIMIT_CLOUD_MEDIAN_M = 100.0
#: a cloud's median range (m) is at least this: a sensor does not measure its points at its own
#: origin (a cloud scaled by 1e-12 made the plane fit's covariance singular)
MIN_CLOUD_MEDIAN_M = 0.01
#: What physics allows (the readers refuse the rest before any number reaches the solvers, where
#: 1e300 overflowed and LAPACK failed): a time (s), a body position of a walk (m, "within
#: kilometres"), IMU specific force (m/s², ~200 g) and rate (rad/s), a joint value (rad or m; up to
#: 1000 so that a few values in degrees by mistake stay a warning, outside the URDF limits, and
#: a column of them the degrees error) and effort (N m or N), a plane's distance (m; at least 1 mm: a sensor does not see a plane
#: through its own origin), fit rms (m) and point count, and a plane covariance's entries (rad², m²)
#: and its smallest eigenvalue across the plane (a sigma of a picometre).
MAX_ABS_TIME_S = 1e10
MAX_ABS_BODY_M = 1e4
MAX_ABS_ACCEL_MPS2 = 2000.0
MAX_ABS_GYRO_RADPS = 100.0
MAX_ABS_JOINT = 1e3
MAX_ABS_EFFORT = 1e5
MIN_PLANE_D_M = 1e-3
MAX_PLANE_RMS_M = 10.0
MAX_PLANE_POINTS = 1e9
MAX_ABS_PLANE_COV = 1e2
MIN_PLANE_COV_EIG = 1e-24
#: dataset.yaml's prior sigmas: at most the size of a robot (sigma_mm, like MM_LIMIT_PRIOR_M) and a
#: full turn (sigma_rpy_deg); a sigma > 0 at least a nanometre and a nano-degree (a tighter prior is
#: written 0: fixed)
MAX_PRIOR_SIGMA_MM = 1e4
MAX_PRIOR_SIGMA_DEG = 360.0
MIN_PRIOR_SIGMA = 1e-6
#: a laser scanner's points lie in its scan plane, z = 0 of its frame (as a ROS LaserScan turned
#: into points); a cloud whose 90th percentile of |z| is above this (m) is a 3-D cloud (a depth
#: camera declared laser_scanner) or a scan written in another frame
SCAN_PLANE_MAX_Z_M = 0.02

#: the values of dataset.yaml's stance.feet_fixed_within graphcal knows: the feet stay planted within
#: a session (the contract's default), are re-planted at every station, or within a step of a walk
#: (timeseries.csv's contact_<foot> columns say when; stations of such a dataset are read as
#: "station": the robot stepped between them)
FEET_FIXED_WITHIN = ("session", "station", "step")
#: the values of it under which every station is a stance of its own
FEET_REPLANTED_AT_EACH_STATION = ("station", "step")

_STRING_COLUMNS = ("session", "sensor", "marker", "frame")


def is_string_column(name: str) -> bool:
    """True for the text columns of the contract: ``session``, ``sensor``, ``marker``, ``cloud_*``."""
    return name in _STRING_COLUMNS or name.startswith("cloud_")


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class PosePrior:
    """A prior on a pose (``T_body_sensor``, ``T_body_imu``): the CAD value and how far it may be off.

    Attributes:
        xyz: (3,) translation, metres.
        rpy_rad: (3,) ROS roll, pitch, yaw, radians (R = Rz(yaw) Ry(pitch) Rx(roll)).
        sigma_m: standard deviation of each translation component, metres (>= 0).
        sigma_rad: standard deviation of each rotation component, radians (>= 0).

    In ``dataset.yaml`` the same prior is ``xyz`` (m), ``rpy_deg``, ``sigma_mm``, ``sigma_rpy_deg``.
    """

    xyz: np.ndarray
    rpy_rad: np.ndarray
    sigma_m: float
    sigma_rad: float

    def __post_init__(self):
        for name in ("xyz", "rpy_rad"):
            a = np.array(getattr(self, name), dtype=np.float64).reshape(-1)
            if a.shape != (3,):
                raise ValueError(f"PosePrior.{name} must have 3 components, got shape {a.shape}")
            object.__setattr__(self, name, _readonly(a))
        object.__setattr__(self, "sigma_m", float(self.sigma_m))
        object.__setattr__(self, "sigma_rad", float(self.sigma_rad))

    @property
    def matrix(self) -> np.ndarray:
        """The prior pose as a 4x4 matrix (``T_body_sensor``), metres."""
        return pose_from_xyz_rpy(self.xyz, self.rpy_rad)

    @classmethod
    def from_matrix(cls, T, sigma_m: float, sigma_rad: float) -> PosePrior:
        """Prior from a 4x4 pose (metres), sigmas in metres and radians."""
        from graphcal.geometry import xyz_rpy_from_pose

        xyz, rpy = xyz_rpy_from_pose(T)
        return cls(xyz, rpy, sigma_m, sigma_rad)

    def __eq__(self, other):
        if not isinstance(other, PosePrior):
            return NotImplemented
        return (
            np.array_equal(self.xyz, other.xyz)
            and np.array_equal(self.rpy_rad, other.rpy_rad)
            and self.sigma_m == other.sigma_m
            and self.sigma_rad == other.sigma_rad
        )

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self):
        return (
            f"PosePrior(xyz={self.xyz.tolist()}, rpy_rad={self.rpy_rad.tolist()}, "
            f"sigma_m={self.sigma_m!r}, sigma_rad={self.sigma_rad!r})"
        )


@dataclass(frozen=True)
class RobotSpec:
    """``robot`` of ``dataset.yaml``: exactly one of ``urdf`` (path relative to the dataset folder,
    as written in the file) or ``model`` (built-in model name); ``base_frame`` (the URDF frame that is
    the body frame) and ``feet`` (URDF frames of the foot contact points)."""

    urdf: str | None
    model: str | None
    base_frame: str
    feet: tuple[str, ...]

    def __post_init__(self):
        object.__setattr__(self, "feet", tuple(self.feet))


@dataclass(frozen=True)
class SensorSpec:
    """One entry of ``sensors``: ``name`` (used in file and column names), ``type`` (one of
    :data:`graphcal.models.sensors.SENSOR_TYPES`), ``T_body_sensor_prior`` and ``extra`` (the entry's other keys, kept)."""

    name: str
    type: str
    T_body_sensor_prior: PosePrior
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True)
class ImuSpec:
    """``imu`` of ``dataset.yaml``: ``T_body_imu_prior`` and ``extra`` (the other keys, kept)."""

    T_body_imu_prior: PosePrior
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class MarkerSpec:
    """One entry of ``mocap.markers``: the URDF ``link`` a marker is fixed to and, if known, its
    position ``xyz`` (3,) in that link's frame, metres (None: unknown, to be estimated)."""

    link: str
    xyz: np.ndarray | None = None

    def __post_init__(self):
        if self.xyz is not None:
            a = np.array(self.xyz, dtype=np.float64).reshape(-1)
            if a.shape != (3,):
                raise ValueError(f"MarkerSpec.xyz must have 3 components, got shape {a.shape}")
            object.__setattr__(self, "xyz", _readonly(a))

    def __eq__(self, other):
        if not isinstance(other, MarkerSpec):
            return NotImplemented
        if self.link != other.link or (self.xyz is None) != (other.xyz is None):
            return False
        return self.xyz is None or np.array_equal(self.xyz, other.xyz)

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True, eq=False)
class Table:
    """A CSV file in memory: ordered ``columns`` and ``data`` (column -> 1-D array, one per row).

    Arrays are read-only: float64 (SI units as the contract says), except ``station`` (int64 ids)
    and the text columns ``session``, ``sensor``, ``marker``, ``cloud_*`` (numpy ``str``).
    """

    columns: tuple[str, ...]
    data: Mapping[str, np.ndarray]

    def __post_init__(self):
        columns = tuple(self.columns)
        if len(set(columns)) != len(columns):
            raise ValueError(f"Table: duplicate column names in {columns}")
        if set(columns) != set(self.data):
            raise ValueError(f"Table: columns {columns} and data keys {tuple(self.data)} differ")
        data: dict[str, np.ndarray] = {}
        n = None
        for c in columns:
            a = _table_column(c, self.data[c])
            if a.ndim != 1:
                raise ValueError(f"Table: column {c!r} must be 1-D, got shape {a.shape}")
            if n is None:
                n = len(a)
            elif len(a) != n:
                raise ValueError(f"Table: column {c!r} has {len(a)} rows, expected {n}")
            data[c] = _readonly(a)
        object.__setattr__(self, "columns", columns)
        object.__setattr__(self, "data", data)

    @classmethod
    def from_columns(cls, columns: Mapping[str, Any]) -> Table:
        """Table from a column -> values mapping, in the mapping's order."""
        return cls(tuple(columns), dict(columns))

    def __len__(self) -> int:
        return len(self.data[self.columns[0]]) if self.columns else 0

    def __getitem__(self, column: str) -> np.ndarray:
        try:
            return self.data[column]
        except KeyError:
            raise KeyError(f"no column {column!r}{did_you_mean(column, self.columns)}") from None

    def __contains__(self, column: object) -> bool:
        return column in self.data

    def has(self, column: str) -> bool:
        """True if the table has ``column``."""
        return column in self.data

    def suffixes(self, prefix: str) -> tuple[str, ...]:
        """Names after ``prefix`` of the columns that start with it, in column order
        (``suffixes("q_")`` -> the joint names)."""
        return tuple(c[len(prefix) :] for c in self.columns if c.startswith(prefix))

    def row(self, i: int) -> dict[str, Any]:
        """Row ``i`` (0-based) as a column -> Python value dict."""
        return {c: self.data[c][i].item() for c in self.columns}

    def select(self, rows) -> Table:
        """A new table with the rows chosen by a boolean mask or index array."""
        return Table(self.columns, {c: self.data[c][rows] for c in self.columns})

    def __eq__(self, other):
        if not isinstance(other, Table):
            return NotImplemented
        return self.columns == other.columns and all(
            self.data[c].dtype.kind == other.data[c].dtype.kind and np.array_equal(self.data[c], other.data[c])
            for c in self.columns
        )

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self):
        cols = ", ".join(self.columns[:8]) + (", ..." if len(self.columns) > 8 else "")
        return f"Table({len(self)} rows: {cols})"


def _table_column(name: str, values) -> np.ndarray:
    if is_string_column(name):
        a = np.asarray(values)
        if a.dtype.kind != "U":
            a = a.astype(np.str_) if a.size else np.array([], dtype="<U1").reshape(a.shape)
        return a.copy()
    if name == "station":
        a = np.asarray(values)
        if a.size and a.dtype.kind == "f":
            if not (np.isfinite(a).all() and (a == np.round(a)).all()):
                raise ValueError("Table: column 'station' must hold integer ids")
        if a.dtype.kind not in "iuf" and a.size:
            raise ValueError(f"Table: column 'station' must hold integer ids, got dtype {a.dtype}")
        return a.astype(np.int64)
    return np.array(values, dtype=np.float64)


@dataclass(frozen=True)
class Dataset:
    """A dataset in memory (``graphcal-dataset/1``); see docs/dataset.md.

    Attributes:
        root: the dataset folder (as given to :func:`read_dataset`), None for one built in memory.
        format: ``"graphcal-dataset/1"``.
        robot: the robot, or None.
        sensors: sensor name -> :class:`SensorSpec`, in file order.
        imu: the IMU prior, or None.
        ground: ``ground`` mapping (default ``{"type": "level"}``).
        stance: ``stance`` mapping (default ``{"feet_fixed_within": "session"}``).
        extra: unknown top-level keys of ``dataset.yaml``, kept (forward compatibility).
        stations, timeseries, planes, mocap: the CSV files, or None when absent.
        mocap_markers: ``mocap.markers`` of ``dataset.yaml``: marker name -> :class:`MarkerSpec`.
        mocap_poses: ``mocap_poses.csv`` (measured 6-D poses of robot frames), or None.
        mocap_noise: the declared noise of ``mocap`` in dataset.yaml, SI: ``sigma_m`` (marker
            coordinate, from ``sigma_mm``) and ``sigma_joint_rad`` (encoders, from ``sigma_joint_deg``), when given.
    """

    root: Path | None = None
    format: str = FORMAT
    robot: RobotSpec | None = None
    sensors: dict = field(default_factory=dict)
    imu: ImuSpec | None = None
    ground: dict = field(default_factory=lambda: {"type": "level"})
    stance: dict = field(default_factory=lambda: {"feet_fixed_within": "session"})
    extra: dict = field(default_factory=dict)
    stations: Table | None = None
    timeseries: Table | None = None
    planes: Table | None = None
    mocap: Table | None = None
    mocap_markers: dict = field(default_factory=dict)
    mocap_poses: Table | None = None
    mocap_noise: dict = field(default_factory=dict)
