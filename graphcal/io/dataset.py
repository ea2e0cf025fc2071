"""The graphcal dataset contract, ``graphcal-dataset/1``: dataclasses, reader, writer, validator.

The contract is documented in ``docs/dataset.md`` (layout, files, columns, units, every check
with an example message). In short: a folder with ``dataset.yaml`` (robot, sensor priors), one
or both of ``stations.csv`` (static stations) and ``timeseries.csv`` (samples), and optionally
``planes.csv``, ``mocap.csv``, ``clouds/<sensor>/<station>.ply`` and a URDF.

Inside graphcal everything is SI: metres, radians, seconds. The only non-SI values live in
``dataset.yaml`` keys whose name says so (``rpy_deg``, ``sigma_rpy_deg``, ``sigma_mm``); they are
converted on reading and writing.

* :func:`read_dataset` parses and checks a dataset (everything except the points inside the
  PLY files, whose names and locations it does check) and returns a :class:`Dataset`.
* :func:`validate_dataset` does the same, then reads every cloud, and returns counts and warnings
  (:class:`ValidationReport`).
* :func:`write_dataset` writes a :class:`Dataset` atomically (a folder appears complete or not at
  all); it reads the result back before committing it, so it never produces a dataset graphcal
  would refuse.

Every problem is one :class:`~graphcal.errors.DatasetError` naming the file, the row (``row k``
is the k-th data row, 1-based, not counting the header; ``line n`` is the line of the file as a
text editor numbers it, so ``line = row + 1`` for a file without blank or multi-line rows) or
the key (``sensors.depth.T_body_sensor_prior.xyz``), and what was expected. Nothing is unpickled
or executed: YAML is read with a subclass of ``yaml.SafeLoader``.
"""

from __future__ import annotations

import csv
import difflib
import io
import math
import re
import shutil
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
import yaml

from graphcal.errors import DatasetError, ModelError
from graphcal.geometry import pose_from_xyz_rpy
from graphcal.io.atomic import atomic_directory, atomic_write_bytes, atomic_write_text
from graphcal.io.ply import read_ply, write_ply
from graphcal.models.sensors import SENSOR_TYPES

__all__ = [
    "FORMAT",
    "SENSOR_TYPES",
    "PosePrior",
    "RobotSpec",
    "SensorSpec",
    "ImuSpec",
    "MarkerSpec",
    "Table",
    "Dataset",
    "ValidationReport",
    "read_dataset",
    "write_dataset",
    "validate_dataset",
    "load_cloud",
    "cloud_paths",
    "load_dataset_robot",
    "is_string_column",
]

FORMAT = "graphcal-dataset/1"

BODY_POSE_COLUMNS = ("body_x", "body_y", "body_z", "body_qw", "body_qx", "body_qy", "body_qz")
IMU_ACCEL_COLUMNS = ("imu_ax", "imu_ay", "imu_az")
IMU_GYRO_COLUMNS = ("imu_gx", "imu_gy", "imu_gz")
PLANE_REQUIRED_COLUMNS = ("station", "sensor", "nx", "ny", "nz", "d")
PLANE_COV_COLUMNS = tuple(f"cov_{i}{j}" for i in range(4) for j in range(4))
MOCAP_COLUMNS = ("time", "marker", "x", "y", "z")

#: Tolerances and "looks like millimetres" limits (metres) of the checks; see docs/dataset.md.
UNIT_NORM_TOL = 1e-3
MM_LIMIT_BODY_M = 50.0
MM_LIMIT_PRIOR_M = 10.0
MM_LIMIT_PLANE_D_M = 100.0
MM_LIMIT_MOCAP_M = 100.0
MM_LIMIT_CLOUD_MEDIAN_M = 100.0
#: a laser scanner's points lie in its scan plane, z = 0 of its frame (as a ROS LaserScan turned
#: into points); a cloud whose 90th percentile of |z| is above this (m) is a 3-D cloud (a depth
#: camera declared laser_scanner) or a scan written in another frame
SCAN_PLANE_MAX_Z_M = 0.02

_STRING_COLUMNS = ("session", "sensor", "marker")
_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+-]*")
_NUMBER_RE = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_MILLI = "looks like millimetres; the contract uses metres"


def is_string_column(name: str) -> bool:
    """True for the text columns of the contract: ``session``, ``sensor``, ``marker``, ``cloud_*``."""
    return name in _STRING_COLUMNS or name.startswith("cloud_")


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def _suggest(name: str, candidates: Iterable[str]) -> str:
    close = difflib.get_close_matches(name, list(candidates), n=3, cutoff=0.6)
    return f" (did you mean {', '.join(repr(c) for c in close)}?)" if close else ""


# ============================================================================ dataclasses
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
    :data:`SENSOR_TYPES`), ``T_body_sensor_prior`` and ``extra`` (the entry's other keys, kept)."""

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
            raise KeyError(f"no column {column!r}{_suggest(column, self.columns)}") from None

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


@dataclass(frozen=True)
class ValidationReport:
    """What :func:`validate_dataset` found in a valid dataset. Times in seconds.

    Attributes:
        path: the dataset folder.
        robot: ``"model octopus"``, ``"URDF robot.urdf"`` or ``"none"``.
        n_stations, n_sessions: rows of stations.csv; distinct session labels (stations and
            timeseries; 0 without a ``session`` column).
        sensors: sensor names.
        n_clouds, n_cloud_points: PLY files read (station clouds and the timeseries' clouds) and
            their total number of points.
        n_planes, n_mocap_rows, n_timeseries_rows: rows of planes.csv, mocap.csv, timeseries.csv.
        time_start_s, time_end_s: smallest and largest ``time`` over all files (None: no time).
        warnings: things that are legal but suspicious.
    """

    path: str
    robot: str
    n_stations: int
    n_sessions: int
    sensors: tuple[str, ...]
    n_clouds: int
    n_cloud_points: int
    n_planes: int
    n_mocap_rows: int
    n_timeseries_rows: int
    time_start_s: float | None
    time_end_s: float | None
    warnings: tuple[str, ...] = ()

    @property
    def n_sensors(self) -> int:
        """Number of sensors in dataset.yaml."""
        return len(self.sensors)

    @property
    def time_span_s(self) -> float | None:
        """``time_end_s - time_start_s`` (None without any time)."""
        if self.time_start_s is None or self.time_end_s is None:
            return None
        return self.time_end_s - self.time_start_s

    def summary(self) -> str:
        """A few human-readable lines."""
        span = "no time" if self.time_span_s is None else (
            f"{self.time_span_s:.3f} s ({self.time_start_s:.3f} .. {self.time_end_s:.3f} s)"
        )
        lines = [
            f"{self.path}: valid {FORMAT} dataset",
            f"  robot: {self.robot}",
            f"  sensors: {self.n_sensors} ({', '.join(self.sensors) or 'none'})",
            f"  stations: {self.n_stations} in "
            f"{self.n_sessions if self.n_sessions or not self.n_stations else 'an unknown number of'} session(s); "
            f"timeseries samples: {self.n_timeseries_rows}",
            f"  clouds: {self.n_clouds} ({self.n_cloud_points} points); planes: {self.n_planes}; "
            f"mocap rows: {self.n_mocap_rows}",
            f"  time span: {span}",
        ]
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)


# ============================================================================ YAML
from graphcal.io.yaml_strict import StrictSafeLoader as _YamlLoader  # noqa: E402


class _YamlDumper(yaml.SafeDumper):
    """``yaml.SafeDumper`` that quotes text the loader would read as a YAML 1.2 float (``1e3``)."""


_YamlDumper.yaml_implicit_resolvers = {k: list(v) for k, v in yaml.SafeDumper.yaml_implicit_resolvers.items()}
for _first, _resolvers in _YamlLoader.yaml_implicit_resolvers.items():
    for _tag, _regexp in _resolvers:
        known = _YamlDumper.yaml_implicit_resolvers.setdefault(_first, [])
        if _tag == "tag:yaml.org,2002:float" and (_tag, _regexp) not in known:
            known.append((_tag, _regexp))


def _load_yaml(path: Path) -> Any:
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DatasetError(path, "file", "a readable dataset.yaml", exc.strerror or str(exc)) from None
    text = _decode(raw, path)
    try:
        return yaml.load(text, Loader=_YamlLoader)  # noqa: S506 -- a SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark is not None else "YAML syntax"
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise DatasetError(path, where, "valid YAML", _one_line(problem)) from None
    except RecursionError:
        raise DatasetError(path, "YAML syntax", "valid YAML of reasonable nesting depth") from None
    except (ValueError, TypeError, OverflowError) as exc:  # e.g. a date such as 2024-13-45
        raise DatasetError(path, "YAML value", "valid YAML values", _one_line(str(exc))) from None


def _decode(raw: bytes, path: Path) -> str:
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise DatasetError(path, f"line {line} (byte {exc.start})", "UTF-8 text",
                           f"byte 0x{raw[exc.start]:02x}") from None  # fmt: skip


class _Y:
    """Typed access to the parsed dataset.yaml with errors naming the key."""

    def __init__(self, path: Path):
        self.path = path

    def err(self, key: str, expected: str, got: object = None) -> DatasetError:
        return DatasetError(self.path, key, expected, got)

    def mapping(self, v, key: str) -> dict:
        if not isinstance(v, dict):
            raise self.err(key or "top level", "a mapping (key: value lines)", _show(v))
        for k in v:
            if not isinstance(k, str):
                raise self.err(f"{key}.{k}" if key else str(k), "text keys", _show(k))
        return v

    def text(self, v, key: str) -> str:
        if not isinstance(v, str) or not v.strip():
            raise self.err(key, "a non-empty text", _show(v))
        return v.strip()

    def number(self, v, key: str) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.err(key, "a number", _show(v))
        try:
            x = float(v)
        except OverflowError:
            x = math.inf
        if not math.isfinite(x):
            raise self.err(key, "a finite number", _show(v))
        return x

    def vec3(self, v, key: str) -> list[float]:
        if not isinstance(v, list) or len(v) != 3:
            raise self.err(key, "a list of 3 numbers", _show(v))
        return [self.number(x, f"{key}[{i}]") for i, x in enumerate(v)]

    def keys(self, m: dict, key: str, required: Sequence[str], allowed: Sequence[str] | None) -> None:
        for r in required:
            if r not in m:
                raise self.err(f"{key}.{r}" if key else r, f"the required key '{r}'", "missing")
        if allowed is not None:
            for k in m:
                if k not in allowed:
                    raise self.err(
                        f"{key}.{k}", f"one of the keys {', '.join(allowed)}{_suggest(k, allowed)}",
                        f"unknown key {k!r}",
                    )


def _cell(text: str) -> str:
    """A cell or token for a message: verbatim if printable, else its repr (one line, visible)."""
    return text if text.isprintable() else repr(text)


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _show(v: object) -> str:
    if v is None:
        return "nothing (null)"
    text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _parse_prior(y: _Y, v, key: str) -> PosePrior:
    m = y.mapping(v, key)
    names = ("xyz", "rpy_deg", "sigma_mm", "sigma_rpy_deg")
    y.keys(m, key, names, names)
    xyz = y.vec3(m["xyz"], f"{key}.xyz")
    if math.hypot(*xyz) > MM_LIMIT_PRIOR_M:
        raise y.err(f"{key}.xyz", f"metres (norm <= {MM_LIMIT_PRIOR_M:g} m); {_MILLI}", xyz)
    rpy_deg = y.vec3(m["rpy_deg"], f"{key}.rpy_deg")
    for i, a in enumerate(rpy_deg):
        if abs(a) > 360.0:
            raise y.err(f"{key}.rpy_deg[{i}]", "degrees in [-360, 360]", a)
    sigma_mm = y.number(m["sigma_mm"], f"{key}.sigma_mm")
    sigma_deg = y.number(m["sigma_rpy_deg"], f"{key}.sigma_rpy_deg")
    for k, s in (("sigma_mm", sigma_mm), ("sigma_rpy_deg", sigma_deg)):
        if s < 0:
            raise y.err(f"{key}.{k}", "a standard deviation >= 0", s)
    return PosePrior(
        np.array(xyz), np.array([_deg_to_rad(a) for a in rpy_deg]), _mm_to_m(sigma_mm), _deg_to_rad(sigma_deg)
    )


# Unit conversions, used in both directions so that a value read from a file is written back as
# the same number (see _file_number).
def _deg_to_rad(x: float) -> float:
    return math.radians(x)


def _rad_to_deg(x: float) -> float:
    return math.degrees(x)


def _mm_to_m(x: float) -> float:
    return x / 1000.0


def _m_to_mm(x: float) -> float:
    return x * 1000.0


def _file_number(si: float, to_file, from_file) -> float:
    """The number to write in a file so that reading it back gives exactly ``si``: the shortest
    decimal that does, else the nearest float that does, else the plain conversion (1 ulp off)."""
    v = to_file(si)
    if from_file(v) == si:
        for digits in range(1, 17):
            s = float(f"{v:.{digits}g}")
            if from_file(s) == si:
                return s
        return v
    lo = hi = v
    for _ in range(64):
        lo, hi = math.nextafter(lo, -math.inf), math.nextafter(hi, math.inf)
        if from_file(lo) == si:
            return lo
        if from_file(hi) == si:
            return hi
    return v


def _prior_to_yaml(p: PosePrior) -> dict:
    return {
        "xyz": [float(x) for x in p.xyz],
        "rpy_deg": [_file_number(float(a), _rad_to_deg, _deg_to_rad) for a in p.rpy_rad],
        "sigma_mm": _file_number(p.sigma_m, _m_to_mm, _mm_to_m),
        "sigma_rpy_deg": _file_number(p.sigma_rad, _rad_to_deg, _deg_to_rad),
    }


@dataclass(frozen=True)
class _Header:
    format: str
    robot: RobotSpec | None
    sensors: dict
    imu: ImuSpec | None
    ground: dict
    stance: dict
    extra: dict
    mocap_markers: dict


_TOP_KEYS = ("format", "robot", "sensors", "imu", "ground", "stance", "mocap")


def _parse_yaml(path: Path) -> _Header:
    doc = _load_yaml(path)
    y = _Y(path)
    if doc is None:
        raise y.err("format", f"the key 'format: {FORMAT}'", "an empty file")
    doc = y.mapping(doc, "")
    if "format" not in doc:
        raise y.err("format", f"the key 'format: {FORMAT}'", "missing")
    if doc["format"] != FORMAT:
        raise y.err("format", f"'{FORMAT}' (the format this graphcal reads)", _show(doc["format"]))

    robot = None
    if doc.get("robot") is not None:
        m = y.mapping(doc["robot"], "robot")
        y.keys(m, "robot", ("base_frame", "feet"), ("urdf", "model", "base_frame", "feet"))
        n_src = ("urdf" in m) + ("model" in m)
        if n_src != 1:
            raise y.err("robot", "exactly one of the keys 'urdf' (a URDF file) or 'model' (a built-in model)",
                        "both" if n_src == 2 else "neither")
        urdf = y.text(m["urdf"], "robot.urdf") if "urdf" in m else None
        model = y.text(m["model"], "robot.model") if "model" in m else None
        base_frame = y.text(m["base_frame"], "robot.base_frame")
        if not isinstance(m["feet"], list):
            raise y.err("robot.feet", "a list of URDF frame names", _show(m["feet"]))
        feet = [y.text(f, f"robot.feet[{i}]") for i, f in enumerate(m["feet"])]
        for i, f in enumerate(feet):
            if f in feet[:i]:
                raise y.err(f"robot.feet[{i}]", "each foot frame once", f)
        robot = RobotSpec(urdf, model, base_frame, tuple(feet))

    sensors: dict[str, SensorSpec] = {}
    if doc.get("sensors") is not None:
        for name, v in y.mapping(doc["sensors"], "sensors").items():
            key = f"sensors.{name}"
            if not _NAME_RE.fullmatch(name) or name in (".", ".."):
                raise y.err(key, "a sensor name of letters, digits and _ . + - (it is used in file names)", name)
            m = y.mapping(v, key)
            y.keys(m, key, ("type", "T_body_sensor_prior"), None)
            stype = m["type"]
            if stype not in SENSOR_TYPES:
                raise y.err(f"{key}.type", f"one of {', '.join(SENSOR_TYPES)}", _show(stype))
            prior = _parse_prior(y, m["T_body_sensor_prior"], f"{key}.T_body_sensor_prior")
            extra = {k: x for k, x in m.items() if k not in ("type", "T_body_sensor_prior")}
            sensors[name] = SensorSpec(name, stype, prior, extra)

    imu = None
    if doc.get("imu") is not None:
        m = y.mapping(doc["imu"], "imu")
        y.keys(m, "imu", ("T_body_imu_prior",), None)
        prior = _parse_prior(y, m["T_body_imu_prior"], "imu.T_body_imu_prior")
        imu = ImuSpec(prior, {k: x for k, x in m.items() if k != "T_body_imu_prior"})

    ground = {"type": "level"}
    if doc.get("ground") is not None:
        ground = dict(y.mapping(doc["ground"], "ground"))
        if "type" in ground:
            y.text(ground["type"], "ground.type")
    stance = {"feet_fixed_within": "session"}
    if doc.get("stance") is not None:
        stance = dict(y.mapping(doc["stance"], "stance"))
        if "feet_fixed_within" in stance:
            y.text(stance["feet_fixed_within"], "stance.feet_fixed_within")

    markers: dict[str, MarkerSpec] = {}
    if doc.get("mocap") is not None:
        m = y.mapping(doc["mocap"], "mocap")
        y.keys(m, "mocap", (), ("markers",))
        if m.get("markers") is not None:
            for name, v in y.mapping(m["markers"], "mocap.markers").items():
                key = f"mocap.markers.{name}"
                mm = y.mapping(v, key)
                y.keys(mm, key, ("link",), ("link", "xyz"))
                xyz = None
                if mm.get("xyz") is not None:
                    xyz = y.vec3(mm["xyz"], f"{key}.xyz")
                    if math.hypot(*xyz) > MM_LIMIT_PRIOR_M:
                        raise y.err(f"{key}.xyz", f"metres (norm <= {MM_LIMIT_PRIOR_M:g} m); {_MILLI}", xyz)
                markers[name] = MarkerSpec(y.text(mm["link"], f"{key}.link"), xyz)

    extra = {k: v for k, v in doc.items() if k not in _TOP_KEYS}
    return _Header(FORMAT, robot, sensors, imu, ground, stance, extra, markers)


# ============================================================================ CSV
@dataclass(frozen=True)
class _Parsed:
    """A CSV table with the file line of each row, for messages."""

    file: Path
    table: Table
    lines: np.ndarray  # (n,) int, 1-based line numbers of the data rows

    def where(self, i: int, column: str | None = None) -> str:
        w = f"row {i + 1} (line {int(self.lines[i])})"
        return f"{w}, column {column}" if column else w

    def err(self, i: int, column: str | None, expected: str, got: object = None) -> DatasetError:
        return DatasetError(self.file, self.where(i, column), expected, got)


_KIND_FILES = {"stations": "stations.csv", "timeseries": "timeseries.csv", "planes": "planes.csv", "mocap": "mocap.csv"}


def _allowed_text(kind: str) -> str:
    if kind == "planes":
        return "station, sensor, nx, ny, nz, d, n_points, rms, cov_00 ... cov_33"
    if kind == "mocap":
        return "time, marker, x, y, z"
    base = "session, time, q_<joint>, tau_<joint>, body_x ... body_qz, imu_ax ... imu_gz"
    return "station, " + base if kind == "stations" else base + ", cloud_<sensor>, contact_<foot>"


def _column_ok(kind: str, name: str) -> bool:
    if kind == "planes":
        return name in PLANE_REQUIRED_COLUMNS or name in ("n_points", "rms") or name in PLANE_COV_COLUMNS
    if kind == "mocap":
        return name in MOCAP_COLUMNS
    if name in ("session", "time") or name in BODY_POSE_COLUMNS or name in IMU_ACCEL_COLUMNS + IMU_GYRO_COLUMNS:
        return True
    if kind == "stations" and name == "station":
        return True
    prefixes = ("q_", "tau_") + (("cloud_", "contact_") if kind == "timeseries" else ())
    return any(name.startswith(p) and len(name) > len(p) for p in prefixes)


_REQUIRED = {
    "stations": ("station",),
    "timeseries": ("time",),
    "planes": PLANE_REQUIRED_COLUMNS,
    "mocap": MOCAP_COLUMNS,
}
_GROUPS = {
    "stations": (BODY_POSE_COLUMNS, IMU_ACCEL_COLUMNS, IMU_GYRO_COLUMNS),
    "timeseries": (BODY_POSE_COLUMNS, IMU_ACCEL_COLUMNS, IMU_GYRO_COLUMNS),
    "planes": (PLANE_COV_COLUMNS,),
    "mocap": (),
}


def _read_csv(path: Path, kind: str) -> _Parsed:
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DatasetError(path, "file", f"a readable {_KIND_FILES[kind]}", exc.strerror or str(exc)) from None
    text = _decode(raw, path)
    del raw
    reader = csv.reader(io.StringIO(text, newline=""), strict=True)
    header: list[str] | None = None
    rows: list[list[str]] = []
    lines: list[int] = []
    try:
        for row in reader:
            if not row or (len(row) == 1 and not row[0].strip()):
                continue  # blank line
            if header is None:
                header = [c.strip() for c in row]
                continue
            rows.append(row)
            lines.append(reader.line_num)
    except csv.Error as exc:
        raise DatasetError(path, f"line {max(reader.line_num, 1)}", "well-formed CSV", _one_line(str(exc))) from None
    if header is None:
        raise DatasetError(path, "header", "a first line with the column names", "an empty file")
    if len(header) == 1 and (";" in header[0] or "\t" in header[0]):
        sep = "semicolons" if ";" in header[0] else "tabs"
        raise DatasetError(path, "header", f"column names separated by commas (this file uses {sep}: the "
                           "contract's CSV is comma-separated, with a point as the decimal mark)", _cell(header[0]))

    for j, name in enumerate(header):
        if not name:
            raise DatasetError(path, f"header, column {j + 1}", "a column name", "an empty name")
        if not name.isprintable():
            raise DatasetError(path, f"header, column {j + 1}", "a column name of printable characters", _cell(name))
        if name in header[:j]:
            raise DatasetError(path, f"header, column {j + 1}", "each column name once", f"{name!r} again")
        if kind == "timeseries" and name == "station":
            raise DatasetError(path, "header, column station", "no station column in timeseries.csv "
                               "(static stations go to stations.csv)", "station")  # fmt: skip
        if not _column_ok(kind, name):
            raise DatasetError(
                path, f"header, column {name}", f"a column of the contract ({_allowed_text(kind)})",
                f"unknown column {name!r}{_suggest(name, _REQUIRED[kind] + BODY_POSE_COLUMNS)}",
            )  # fmt: skip
    for r in _REQUIRED[kind]:
        if r not in header:
            raise DatasetError(path, f"header, column {r}", f"the required column '{r}'", "missing")
    for group in _GROUPS[kind]:
        present = [c for c in group if c in header]
        if present and len(present) != len(group):
            missing = [c for c in group if c not in header]
            raise DatasetError(path, f"header, column {missing[0]}",
                               f"all of {', '.join(group)} or none of them", f"missing {', '.join(missing)}")

    ncol = len(header)
    for i, row in enumerate(rows):
        if len(row) != ncol:
            raise DatasetError(path, f"row {i + 1} (line {lines[i]})",
                               f"{ncol} cells, one per column of the header", f"{len(row)} cells")
    cells = list(zip(*rows)) if rows else [()] * ncol
    lines_a = np.asarray(lines, dtype=np.int64)
    data: dict[str, np.ndarray] = {}
    for j, name in enumerate(header):
        col = cells[j]
        if is_string_column(name):
            vals = [c.strip() for c in col]
            if not name.startswith("cloud_"):
                for i, v in enumerate(vals):
                    if not v:
                        raise DatasetError(path, f"row {i + 1} (line {lines[i]}), column {name}",
                                           f"a {name} label", "an empty cell")
            data[name] = np.array(vals, dtype=np.str_) if vals else np.array([], dtype="<U1")
        else:
            data[name] = _numbers(col, path, name, lines)
    if "station" in data:
        st = data["station"]
        bad = ~((st == np.round(st)) & (np.abs(st) < 2.0**53))
        if bad.any():
            i = int(np.argmax(bad))
            raise DatasetError(path, f"row {i + 1} (line {lines[i]}), column station", "an integer station id",
                               _cell(cells[header.index("station")][i].strip()))
        data["station"] = st.astype(np.int64)
    return _Parsed(path, Table(tuple(header), data), lines_a)


def _numbers(col: Sequence[str], path: Path, name: str, lines: list[int]) -> np.ndarray:
    """Strict decimal numbers (no nan/inf/overflow, no '1_0'); fast path first."""
    try:
        vals = np.array([float(c) for c in col], dtype=np.float64)
        if np.isfinite(vals).all() and not any(("_" in c) or not c.isascii() for c in col):
            return vals
    except ValueError:
        pass
    for i, c in enumerate(col):
        s = c.strip()
        where = f"row {i + 1} (line {lines[i]}), column {name}"
        if not s:
            raise DatasetError(path, where, "a number", "an empty cell")
        if not _NUMBER_RE.fullmatch(s):
            nonfinite = s.lower().lstrip("+-") in ("nan", "inf", "infinity")
            raise DatasetError(path, where, "a finite number" if nonfinite else "a number", _cell(s))
        if not math.isfinite(float(s)):
            raise DatasetError(path, where, "a finite number (this one overflows to infinity)", _cell(s))
    # every cell is a plain ASCII decimal once stripped of whitespace: the fast path refused the column
    # only for a non-ASCII character around a number, e.g. a no-break space (found by the fuzz test)
    return np.array([float(c.strip()) for c in col], dtype=np.float64)


# ---------------------------------------------------------------------------- per-file checks
def _check_body_imu(p: _Parsed, stations: bool) -> None:
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
                raise p.err(i, c, f"metres (|{c}| <= {MM_LIMIT_BODY_M:g}); {_MILLI}", float(t[c][i]))
    if t.has("imu_ax") and len(t):
        # the median specific force of a static station, and of a walking robot, is ~9.81 m/s²
        f = np.linalg.norm(np.stack([t[c] for c in IMU_ACCEL_COLUMNS], axis=1), axis=1)
        med = float(np.median(f))
        if 0.5 <= med <= 1.5:
            where = "at a static station" if stations else "over a walk"
            raise p.err(int(np.argmin(np.abs(f - med))), "imu_ax..imu_az",
                        f"specific force in m/s² (a median norm of about 9.81 {where}); this looks like units of g",
                        f"median norm {med:.4g}")  # fmt: skip


def _check_stations(p: _Parsed) -> None:
    st = p.table["station"]
    first: dict[int, int] = {}
    if len(np.unique(st)) != len(st):
        for i, s in enumerate(st.tolist()):
            if s in first:
                raise p.err(i, "station", f"unique station ids (station {s} is already on row {first[s] + 1})", s)
            first[s] = i
    _check_body_imu(p, stations=True)


def _check_timeseries(p: _Parsed, header: _Header, root: Path) -> set[Path]:
    """Checks timeseries.csv; returns the resolved cloud files it references."""
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
        bad = (t[col] != 0.0) & (t[col] != 1.0)
        if bad.any():
            i = int(np.argmax(bad))
            raise p.err(i, col, "0 or 1", float(t[col][i]))
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
            full = _inside(root, rel, p.file, p.where(i, col))
            if full.suffix.lower() != ".ply":
                raise p.err(i, col, "the relative path of a .ply cloud", rel)
            if not full.is_file():
                raise p.err(i, col, "the relative path of an existing cloud file", f"{rel} (no such file)")
            seen[rel] = full
        referenced.update(seen.values())
    return referenced


def _check_planes(p: _Parsed, header: _Header, station_ids: np.ndarray | None) -> None:
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
        raise p.err(i, "d", f"metres (d <= {MM_LIMIT_PLANE_D_M:g}); {_MILLI}", float(d[i]))
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


def _check_mocap(p: _Parsed, header: _Header, times: np.ndarray | None) -> None:
    t = p.table
    feet = header.robot.feet if header.robot else ()
    for i, name in enumerate(t["marker"].tolist()):
        if not _marker_ok(name, feet, header.mocap_markers):
            raise p.err(i, "marker", "a marker named after a foot of robot.feet (lf_foot or lf_foot.1), "
                        "body.1 ... body.4, or a marker of mocap.markers in dataset.yaml", name)  # fmt: skip
    for c in ("x", "y", "z"):
        bad = np.abs(t[c]) > MM_LIMIT_MOCAP_M
        if bad.any():
            i = int(np.argmax(bad))
            raise p.err(i, c, f"metres (|{c}| <= {MM_LIMIT_MOCAP_M:g}); {_MILLI}", float(t[c][i]))
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
    for i, key in enumerate(zip(t["time"].tolist(), t["marker"].tolist())):
        if key in seen:
            raise p.err(i, "marker", f"each marker once per time (already on row {seen[key] + 1})", key[1])
        seen[key] = i


# ---------------------------------------------------------------------------- paths and clouds
def _inside(root: Path, rel: str, file: Path | str, where: str, *, root_resolved: Path | None = None,
            resolved: Path | None = None) -> Path:
    """Resolve a relative path written in a dataset file; it must stay inside the dataset folder.
    ``root_resolved``, ``resolved``: ``root.resolve()`` and the path's own, when the caller has them
    (a resolve costs ~0.1 ms: a dataset's clouds are listed several times a calibration)."""
    rel_norm = rel.replace("\\", "/")
    if PurePosixPath(rel_norm).is_absolute() or PureWindowsPath(rel).is_absolute() or PureWindowsPath(rel).drive:
        raise DatasetError(file, where, "a path relative to the dataset folder", f"{rel} (absolute)")
    full = root / rel_norm
    try:
        resolved = full.resolve() if resolved is None else resolved
        inside = resolved.is_relative_to(root.resolve() if root_resolved is None else root_resolved)
    except (OSError, RuntimeError, ValueError):
        inside = False
    if not inside:
        raise DatasetError(file, where, "a path inside the dataset folder (no '..', no link leading out)", rel)
    return full


def _resolved_or_none(path: Path) -> Path | None:
    """``path.resolve()``, or None where it fails (a link loop): :func:`_inside` then reports it."""
    try:
        return path.resolve()
    except (OSError, RuntimeError):
        return None


def _station_clouds(
    root: Path, sensors: Mapping[str, SensorSpec], station_ids: np.ndarray | None, referenced: set[Path]
) -> dict[tuple[str, int], Path]:
    """(sensor, station) -> path of every ``clouds/<sensor>/<station>.ply``; checks names and links."""
    cdir = root / "clouds"
    out: dict[tuple[str, int], Path] = {}
    if not cdir.exists() and not cdir.is_symlink():
        return out
    if not cdir.is_dir():
        raise DatasetError(cdir, "file", "a folder clouds/<sensor>/<station>.ply", "not a folder")
    try:
        root_res = root.resolve()
    except (OSError, RuntimeError):
        root_res = None  # _inside then reports the folder
    _inside(root, "clouds", cdir, "folder", root_resolved=root_res)
    ids = set(station_ids.tolist()) if station_ids is not None else set()
    ref_resolved = {p.resolve() for p in referenced}
    for sdir in sorted(cdir.iterdir()):
        if sdir.name.startswith(".") or not sdir.is_dir():
            continue
        plys = sorted(
            f for f in sdir.iterdir()
            if f.suffix.lower() == ".ply" and not f.name.startswith(".") and (f.is_file() or f.is_symlink())
        )  # fmt: skip
        # a file that is no link resolves within its folder: one resolve per folder, not per file
        sdir_res = sdir.resolve()
        resolved = {f: _resolved_or_none(f) if f.is_symlink() else sdir_res / f.name for f in plys}
        if sdir.name not in sensors:
            if plys and not all(resolved[f] in ref_resolved for f in plys):
                raise DatasetError(sdir, "folder", f"a folder named after a sensor of dataset.yaml "
                                   f"({', '.join(sensors) or 'none'})", sdir.name)  # fmt: skip
            continue
        for f in plys:
            rel = f"clouds/{sdir.name}/{f.name}"
            _inside(root, rel, f, "file", root_resolved=root_res, resolved=resolved[f])
            stem = f.stem
            sid = int(stem) if re.fullmatch(r"[+-]?[0-9]+", stem) else None
            if sid is not None and sid in ids:
                if (sdir.name, sid) in out:
                    other = out[(sdir.name, sid)].name
                    raise DatasetError(f, "file", "one cloud per station", f"{other} and {f.name} for station {sid}")
                out[(sdir.name, sid)] = f
            elif resolved[f] not in ref_resolved:
                expected = "<station>.ply with a station id of stations.csv"
                got = f"{f.name} ({'no stations.csv' if station_ids is None else 'no such station'})"
                if sid is None or station_ids is None:
                    expected += f", or a cloud named in a cloud_{sdir.name} cell of timeseries.csv"
                    if station_ids is None:
                        got = f"{f.name} (no stations.csv, and no row of timeseries.csv names it)"
                raise DatasetError(f, "file name", expected, got)
    return out


# ============================================================================ reading
def _dataset_root(path: str | Path) -> Path:
    root = Path(path)
    if root.name == "dataset.yaml" and root.is_file():
        root = root.parent
    if not root.exists():
        raise DatasetError(root, "folder", "a dataset folder containing dataset.yaml", "no such folder")
    if not root.is_dir():
        raise DatasetError(root, "folder", "a dataset folder containing dataset.yaml", "not a folder")
    if not (root / "dataset.yaml").is_file():
        raise DatasetError(root / "dataset.yaml", "file", f"dataset.yaml (required by {FORMAT})", "missing")
    return root


def _read(path: str | Path) -> tuple[Dataset, object | None, dict[str, _Parsed], set[Path]]:
    root = _dataset_root(path)
    header = _parse_yaml(root / "dataset.yaml")
    y = _Y(root / "dataset.yaml")
    if header.robot is not None and header.robot.urdf is not None:
        urdf = _inside(root, header.robot.urdf, y.path, "robot.urdf")
        if not urdf.is_file():
            raise y.err("robot.urdf", "an existing URDF file inside the dataset folder",
                        f"{header.robot.urdf} (no such file)")  # fmt: skip

    robot = None
    if header.robot is not None:
        robot = _load_robot_spec(root, header.robot, y.path)
        frames = set(robot.frame_names)
        for name, m in header.mocap_markers.items():
            if m.link not in frames:
                raise y.err(f"mocap.markers.{name}.link", "a frame of the URDF",
                            f"{m.link!r}{_suggest(m.link, frames)}")  # fmt: skip

    parsed: dict[str, _Parsed] = {}
    for kind, name in _KIND_FILES.items():
        f = root / name
        if f.exists() or f.is_symlink():
            parsed[kind] = _read_csv(f, kind)
    if "stations" not in parsed and "timeseries" not in parsed:
        raise DatasetError(root, "files", "stations.csv or timeseries.csv (or both)", "neither")
    _check_joint_columns(robot, parsed)

    station_ids = None
    if "stations" in parsed:
        _check_stations(parsed["stations"])
        station_ids = parsed["stations"].table["station"]
    referenced: set[Path] = set()
    if "timeseries" in parsed:
        referenced = _check_timeseries(parsed["timeseries"], header, root)
    if "planes" in parsed:
        _check_planes(parsed["planes"], header, station_ids)
    if "mocap" in parsed:
        times = [
            parsed[k].table["time"] for k in ("stations", "timeseries") if k in parsed and parsed[k].table.has("time")
        ]
        _check_mocap(parsed["mocap"], header, np.concatenate(times) if times else None)
    _station_clouds(root, header.sensors, station_ids, referenced)

    ds = Dataset(
        root=root,
        format=header.format,
        robot=header.robot,
        sensors=header.sensors,
        imu=header.imu,
        ground=header.ground,
        stance=header.stance,
        extra=header.extra,
        stations=parsed["stations"].table if "stations" in parsed else None,
        timeseries=parsed["timeseries"].table if "timeseries" in parsed else None,
        planes=parsed["planes"].table if "planes" in parsed else None,
        mocap=parsed["mocap"].table if "mocap" in parsed else None,
        mocap_markers=header.mocap_markers,
    )
    return ds, robot, parsed, referenced


def _load_robot_spec(root: Path | None, spec: RobotSpec, yaml_file: Path | str):
    from graphcal.models.robot import load_robot

    kwargs: dict[str, Any] = {"base_frame": spec.base_frame}
    if spec.urdf is not None:
        if root is None:
            raise DatasetError(yaml_file, "robot.urdf",
                               "a dataset read from a folder (the URDF file is relative to it)")  # fmt: skip
        kwargs["urdf"] = root / spec.urdf.replace("\\", "/")
    else:
        kwargs["model"] = spec.model
    def text(exc: ModelError) -> str:
        msg = str(exc)
        if spec.urdf is not None:
            msg = msg.replace(str(kwargs["urdf"]), spec.urdf)
        return _one_line(msg)

    try:
        return load_robot(feet=spec.feet, **kwargs)
    except ModelError as exc:
        first = exc
    # find which key is at fault
    src = "robot.urdf" if spec.urdf is not None else "robot.model"
    src_value = spec.urdf if spec.urdf is not None else spec.model
    try:
        if spec.model is not None:
            from graphcal.models.builtin import BUILTIN_MODELS, builtin_urdf

            if spec.model not in BUILTIN_MODELS:
                raise ModelError(str(first))
            urdf_text = builtin_urdf(spec.model)
        else:
            urdf_text = Path(kwargs["urdf"]).read_text(encoding="utf-8")
        tree = ET.fromstring(urdf_text)
        if tree.tag != "robot":  # not a URDF: load_robot's message says so, not robot.base_frame
            raise ModelError(str(first))
        names = {e.get("name") for e in tree.iter() if e.tag in ("link", "joint")} - {None}
    except (ModelError, OSError, UnicodeDecodeError, ET.ParseError):
        raise DatasetError(yaml_file, src, f"a robot graphcal can load ({text(first)})", src_value) from None
    if spec.base_frame not in names:
        raise DatasetError(yaml_file, "robot.base_frame", "a link or joint of the URDF",
                           f"{spec.base_frame!r}{_suggest(spec.base_frame, names)}") from None  # fmt: skip
    for i, foot in enumerate(spec.feet):
        if foot not in names:
            raise DatasetError(yaml_file, f"robot.feet[{i}]", "a link or joint of the URDF",
                               f"{foot!r}{_suggest(foot, names)}") from None  # fmt: skip
    try:
        load_robot(urdf_xml=urdf_text, base_frame=spec.base_frame, feet=())
    except ModelError as exc:
        raise DatasetError(yaml_file, src, f"a robot graphcal can load ({text(exc)})", src_value) from None
    raise DatasetError(yaml_file, "robot.feet", f"foot frames below the base frame, on chains of 1-DOF joints "
                       f"({text(first)})", list(spec.feet)) from None  # fmt: skip


def load_dataset_robot(ds: Dataset):
    """The :class:`~graphcal.models.robot.RobotModel` of a dataset (``ds.robot``); DatasetError if it
    cannot be loaded, ValueError if the dataset has no robot."""
    if ds.robot is None:
        raise ValueError("the dataset has no robot")
    yaml_file = ds.root / "dataset.yaml" if ds.root is not None else "dataset.yaml"
    return _load_robot_spec(ds.root, ds.robot, yaml_file)


def _check_joint_columns(robot, parsed: Mapping[str, _Parsed]) -> None:
    """q_/tau_ columns name moving joints of the URDF, and every leg joint has a q_ column."""
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
                                       f"{j!r}{_suggest(j, joints)}")  # fmt: skip
        for foot in robot.feet:
            leg = robot.legs[foot]
            for k, j in enumerate(leg.joint_names):
                if not p.table.has(f"q_{j}"):
                    raise DatasetError(p.file, f"header, column q_{j}",
                                       f"a column for every moving joint on a leg (joint {j!r} of foot {foot!r})",
                                       "missing")  # fmt: skip
                _check_radians(p, j, leg.joint_types[k], leg.lower[k], leg.upper[k])


#: the values of dataset.yaml's stance.feet_fixed_within graphcal knows: the feet stay planted within
#: a session (the contract's default), are re-planted at every station, or within a step of a walk
#: (timeseries.csv's contact_<foot> columns say when; stations of such a dataset are read as
#: "station": the robot stepped between them)
FEET_FIXED_WITHIN = ("session", "station", "step")
#: the values of it under which every station is a stance of its own
FEET_REPLANTED_AT_EACH_STATION = ("station", "step")


def _check_radians(p: _Parsed, joint: str, joint_type: str, lower: float, upper: float) -> None:
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


def read_dataset(path: str | Path) -> Dataset:
    """Read and check a ``graphcal-dataset/1`` folder (or its ``dataset.yaml``).

    Checks everything in docs/dataset.md except the points inside the PLY files (their names,
    sensors, stations and locations are checked; :func:`validate_dataset` reads them). The robot
    is loaded to check joint columns, feet and marker links.

    Returns:
        The :class:`Dataset`, SI units.

    Raises:
        DatasetError: the first problem found, naming file, row or key, and what was expected.
    """
    return _read(path)[0]


def cloud_paths(ds: Dataset) -> dict[tuple[str, int], Path]:
    """``(sensor, station) -> path`` of every station cloud ``clouds/<sensor>/<station>.ply`` of a
    dataset read from a folder (the timeseries' clouds are in its ``cloud_<sensor>`` columns)."""
    if ds.root is None:
        return {}
    ids = ds.stations["station"] if ds.stations is not None else None
    referenced: set[Path] = set()
    if ds.timeseries is not None:
        for s in ds.timeseries.suffixes("cloud_"):
            referenced.update(ds.root / r.replace("\\", "/") for r in ds.timeseries[f"cloud_{s}"].tolist() if r)
    return _station_clouds(ds.root, ds.sensors, ids, referenced)


def load_cloud(ds: Dataset, sensor: str, station: int) -> np.ndarray:
    """Points ``(N, 3)`` of station ``station`` seen by ``sensor``, in the sensor frame, metres.

    Raises:
        DatasetError: no such cloud, an unreadable or empty PLY, non-finite points, or points that
            look like millimetres (median range above 100 m).
    """
    if ds.root is None:
        raise ValueError("load_cloud needs a dataset read from a folder (ds.root is None)")
    station = int(station)
    path = ds.root / "clouds" / sensor / f"{station}.ply"
    if path.is_file():
        _inside(ds.root, f"clouds/{sensor}/{station}.ply", path, "file")
    else:  # another spelling of the id, e.g. 007.ply
        found = cloud_paths(ds).get((sensor, station))
        if found is None:
            raise DatasetError(path, "file", f"the cloud of station {station} seen by sensor {sensor!r}",
                               "no such file")  # fmt: skip
        path = found
    return _read_cloud(path)


def _read_cloud(path: Path) -> np.ndarray:
    pts = read_ply(path)
    sample = pts[:: max(1, len(pts) // 20000)]  # the unit check needs no more than ~20k points
    med = float(np.median(np.sqrt(np.einsum("ij,ij->i", sample, sample))))
    if med > MM_LIMIT_CLOUD_MEDIAN_M:
        raise DatasetError(path, "points", f"metres (median range <= {MM_LIMIT_CLOUD_MEDIAN_M:g} m); {_MILLI}",
                           f"median range {med:.4g}")
    return pts


def shown_path(root: Path, f: Path) -> str:
    """``f`` relative to the dataset folder ``root`` where it lies inside it, else in full."""
    try:
        return str(Path(f).relative_to(root))
    except ValueError:
        return str(f)


def scan_off_plane_m(points: np.ndarray) -> float:
    """How far a laser scanner's points ``(N, 3)`` (sensor frame, m) lie off its scan plane z = 0:
    the 90th percentile of |z| (m; 0 for a 2-D scan; the range noise of a 2-D scanner lies along
    its beams, in that plane)."""
    z = np.abs(np.asarray(points, dtype=float)[:, 2])
    return float(np.percentile(z, 90)) if len(z) else 0.0


def off_plane_scan_warning(sensor: str, off: Sequence[tuple[str, float]], n_clouds: int) -> str:
    """The warning for laser scanner ``sensor`` whose clouds ``off`` ((file, 90th percentile of |z|
    in m), at least one) of ``n_clouds`` lie off its scan plane (:data:`SCAN_PLANE_MAX_Z_M`)."""
    file, z90 = max(off, key=lambda x: x[1])
    return (f"sensor {sensor!r} is a laser_scanner, but {len(off)} of its {n_clouds} clouds do not lie in "
            f"its scan plane z = 0 (90% of |z| within {1e3 * SCAN_PLANE_MAX_Z_M:g} mm; {file}: "
            f"{1e3 * z90:.0f} mm): a 3-D cloud (a depth camera: type depth_camera) or a scan in another "
            "frame. A laser scanner's points are read as one scan line in the sensor's x-y plane")


def validate_dataset(path: str | Path) -> ValidationReport:
    """:func:`read_dataset` plus every cloud read; counts and warnings of a valid dataset.

    Raises:
        DatasetError: the first problem found (see docs/dataset.md for every rule).
    """
    ds, robot, parsed, referenced = _read(path)
    clouds = cloud_paths(ds)
    n_points = 0
    files = list(clouds.values()) + sorted(set(referenced) - set(clouds.values()))
    sensor_of = {f: s for (s, _), f in clouds.items()}
    off_plane: dict[str, list] = {}
    for f in files:
        pts = _read_cloud(f)
        n_points += len(pts)
        sensor = sensor_of.get(f)
        if sensor in ds.sensors and ds.sensors[sensor].type == "laser_scanner":
            z90 = scan_off_plane_m(pts)
            if z90 > SCAN_PLANE_MAX_Z_M:
                off_plane.setdefault(sensor, []).append((shown_path(ds.root, f), z90))

    warnings: list[str] = []
    times = [t["time"] for t in (ds.stations, ds.timeseries, ds.mocap) if t is not None and t.has("time") and len(t)]
    t0 = float(min(t.min() for t in times)) if times else None
    t1 = float(max(t.max() for t in times)) if times else None
    sessions: set[str] = set()
    for t in (ds.stations, ds.timeseries):
        if t is not None and t.has("session"):
            sessions.update(t["session"].tolist())
    if ds.stations is not None and not len(ds.stations):
        warnings.append("stations.csv has a header but no rows: nothing to calibrate (calibrate refuses it)")
    in_the_air = ds.mocap is not None and not ds.sensors  # a leg measured by markers: no foot is planted
    if ds.stations is not None and not ds.stations.has("session") and len(ds.stations) and not in_the_air:
        warnings.append("stations.csv has no session column (which stations share a stance is unknown)")
    if str(ds.ground.get("type", "level")) != "level":
        warnings.append(f"dataset.yaml ground.type {ds.ground['type']!r}: graphcal models a level ground (type: level) "
                        "and reads it as one; a tilted or uneven floor shows in graphcal diagnose and is "
                        "allowed for with calibrate --ground-roughness-mm")
    fixed = str(ds.stance.get("feet_fixed_within", "session"))
    if fixed not in FEET_FIXED_WITHIN:
        warnings.append(f"dataset.yaml stance.feet_fixed_within {fixed!r}: graphcal knows "
                        f"{', '.join(FEET_FIXED_WITHIN[:-1])} and {FEET_FIXED_WITHIN[-1]}; it is read as session")
    for name in ds.sensors:
        has_planes = ds.planes is not None and name in set(ds.planes["sensor"].tolist())
        has_clouds = any(s == name for s, _ in clouds) or (
            ds.timeseries is not None and ds.timeseries.has(f"cloud_{name}")
        )
        if not (has_planes or has_clouds):
            warnings.append(f"sensor {name!r} has no cloud and no plane")
        if name in off_plane:
            warnings.append(off_plane_scan_warning(name, off_plane[name], sum(s == name for s, _ in clouds)))
    if robot is not None:
        for kind in ("stations", "timeseries"):
            t = getattr(ds, kind)
            if t is None or not len(t):
                continue
            for foot in robot.feet:
                leg = robot.legs[foot]
                if not leg.n_joints:
                    continue
                outside = leg.outside_limits(np.stack([t[f"q_{j}"] for j in leg.joint_names], axis=-1))
                for j, lo, hi, out in zip(leg.joint_names, leg.lower, leg.upper, outside.sum(axis=0).tolist()):
                    if out:
                        warnings.append(
                            f"{kind}.csv: q_{j} outside the URDF limits [{lo:.4g}, {hi:.4g}] on {out} row(s)"
                        )
    if ds.robot is None:
        desc = "none"
    elif ds.robot.model is not None:
        desc = f"model {ds.robot.model}"
    else:
        desc = f"URDF {ds.robot.urdf}"
    return ValidationReport(
        path=str(ds.root),
        robot=desc,
        n_stations=len(ds.stations) if ds.stations is not None else 0,
        n_sessions=len(sessions),
        sensors=tuple(ds.sensors),
        n_clouds=len(files),
        n_cloud_points=n_points,
        n_planes=len(ds.planes) if ds.planes is not None else 0,
        n_mocap_rows=len(ds.mocap) if ds.mocap is not None else 0,
        n_timeseries_rows=len(ds.timeseries) if ds.timeseries is not None else 0,
        time_start_s=t0,
        time_end_s=t1,
        warnings=tuple(warnings),
    )


# ============================================================================ writing
def _yaml_doc(ds: Dataset) -> dict:
    doc: dict[str, Any] = {"format": FORMAT}
    if ds.robot is not None:
        r: dict[str, Any] = {}
        if ds.robot.urdf is not None:
            r["urdf"] = ds.robot.urdf
        if ds.robot.model is not None:
            r["model"] = ds.robot.model
        r["base_frame"] = ds.robot.base_frame
        r["feet"] = list(ds.robot.feet)
        doc["robot"] = r
    if ds.sensors:
        sensors = {}
        for name, s in ds.sensors.items():
            if name != s.name:
                raise ValueError(f"Dataset.sensors: key {name!r} holds SensorSpec named {s.name!r}")
            clash = {"type", "T_body_sensor_prior"} & set(s.extra)
            if clash:
                raise ValueError(f"SensorSpec {name!r}: extra must not hold {sorted(clash)}")
            sensors[name] = {"type": s.type, "T_body_sensor_prior": _prior_to_yaml(s.T_body_sensor_prior), **s.extra}
        doc["sensors"] = sensors
    if ds.imu is not None:
        if "T_body_imu_prior" in ds.imu.extra:
            raise ValueError("ImuSpec.extra must not hold 'T_body_imu_prior'")
        doc["imu"] = {"T_body_imu_prior": _prior_to_yaml(ds.imu.T_body_imu_prior), **ds.imu.extra}
    doc["ground"] = dict(ds.ground)
    doc["stance"] = dict(ds.stance)
    if ds.mocap_markers:
        markers = {}
        for name, m in ds.mocap_markers.items():
            markers[name] = {"link": m.link} if m.xyz is None else {"link": m.link, "xyz": [float(x) for x in m.xyz]}
        doc["mocap"] = {"markers": markers}
    clash = set(_TOP_KEYS) & set(ds.extra)
    if clash:
        raise ValueError(f"Dataset.extra must not hold the contract's keys {sorted(clash)}")
    doc.update(ds.extra)
    return doc


def table_csv_text(t: Table) -> str:
    """The CSV text of a table (header + rows; floats as shortest repr, an exact float64 round trip)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(t.columns)
    cols = []
    for c in t.columns:
        a = t[c]
        if a.dtype.kind == "U":
            cols.append(a.tolist())
        elif a.dtype.kind in "iu":
            cols.append([str(v) for v in a.tolist()])
        else:
            cols.append([repr(v) for v in a.tolist()])  # shortest repr: exact float64 round trip
    w.writerows(zip(*cols))
    return buf.getvalue()


def _check_table_text(t: Table, file: Path | str) -> None:
    for c in t.columns:
        if t[c].dtype.kind != "U":
            continue
        for i, v in enumerate(t[c].tolist()):
            if v != v.strip():
                raise DatasetError(file, f"row {i + 1}, column {c}", "text without leading or trailing spaces", v)


def write_dataset(
    ds: Dataset,
    out_dir: str | Path,
    *,
    clouds: Mapping[tuple[str, int], Any] | None = None,
    robot_urdf_xml: str | None = None,
    overwrite: bool = False,
    extra_files: Mapping[str, str | bytes] | None = None,
    robot_urdf: str | None = None,
    timeseries_clouds: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``ds`` as a ``graphcal-dataset/1`` folder ``out_dir``, atomically.

    Args:
        ds: the dataset (SI units). ``ds.root``, if set, is where files not given here come from:
            the URDF, the station clouds not in ``clouds`` (for stations and sensors of ``ds``) and
            the clouds named in the timeseries' ``cloud_<sensor>`` columns (copied byte for byte).
        out_dir: the folder to create. An existing non-empty folder is refused unless ``overwrite``.
        clouds: ``(sensor, station) -> (N, 3)`` points in the sensor frame (m), written as binary
            PLY ``clouds/<sensor>/<station>.ply`` (exact float64).
        robot_urdf_xml: URDF text written to ``ds.robot.urdf`` (required when ``ds.robot.urdf`` is
            set and ``ds.root`` does not hold it). ``robot_urdf`` is an alias.
        overwrite: replace an existing non-empty ``out_dir`` (the old one is deleted only after the
            new one is in place).
        extra_files: more files to put in the folder (relative name -> text or bytes), e.g.
            ``{"truth.yaml": ...}``; they must not collide with the contract's files.
        timeseries_clouds: relative PLY path (as named in a ``cloud_<sensor>`` column of the
            timeseries) -> (N, 3) points in that sensor's frame (m), written as binary PLY.

    ``dataset.yaml`` is written with ``xyz`` in metres and ``rpy_deg``, ``sigma_mm``,
    ``sigma_rpy_deg``, as the contract says; each such number is the shortest decimal that
    converts back to the exact SI value when there is one (otherwise it is 1 ulp off). CSV numbers
    are written with Python's shortest ``repr``, so they read back bit for bit.

    The folder is built next to ``out_dir`` and read back with :func:`read_dataset` before it is
    renamed into place: what cannot be read is not written.

    Returns:
        ``out_dir`` as a Path.

    Raises:
        DatasetError: ``ds`` or the clouds would make a dataset graphcal refuses (the message
            names the file, marked "(not written)").
        OutputExistsError: ``out_dir`` exists and is not empty, and ``overwrite`` is False.
    """
    out = Path(out_dir)
    if robot_urdf is not None:
        if robot_urdf_xml is not None:
            raise ValueError("give robot_urdf_xml or its alias robot_urdf, not both")
        robot_urdf_xml = robot_urdf
    if ds.format != FORMAT:
        raise ValueError(f"write_dataset writes {FORMAT}, got Dataset.format={ds.format!r}")
    if ds.stations is None and ds.timeseries is None:
        raise DatasetError(out, "files", "a dataset with stations or a timeseries (or both)", "neither")
    doc = _yaml_doc(ds)
    try:
        yaml_text = yaml.dump(
            doc, Dumper=_YamlDumper, sort_keys=False, default_flow_style=None, allow_unicode=True, width=100
        )
    except yaml.YAMLError as exc:
        raise DatasetError(out / "dataset.yaml", "extra", "plain YAML values (text, numbers, lists, mappings)",
                           str(exc)) from None  # fmt: skip

    urdf_rel = None
    urdf_bytes = None
    if ds.robot is not None and ds.robot.urdf is not None:
        urdf_rel = ds.robot.urdf.replace("\\", "/")
        if robot_urdf_xml is not None:
            urdf_bytes = robot_urdf_xml.encode("utf-8")
        elif ds.root is not None and (ds.root / urdf_rel).is_file():
            urdf_bytes = (ds.root / urdf_rel).read_bytes()
        else:
            raise DatasetError(out / urdf_rel, "robot.urdf", "the URDF text (robot_urdf_xml=...) or a dataset "
                               "root that holds the file", "none given")  # fmt: skip
    elif robot_urdf_xml is not None:
        raise ValueError("robot_urdf_xml given but the dataset's robot does not name a URDF file (robot.urdf)")

    station_ids = set(ds.stations["station"].tolist()) if ds.stations is not None else set()
    new_clouds: dict[tuple[str, int], np.ndarray] = {}
    for key, pts in (clouds or {}).items():
        sensor, station = key
        target = out / "clouds" / str(sensor) / f"{int(station)}.ply"
        if sensor not in ds.sensors:
            raise DatasetError(f"{target} (not written)", "clouds",
                               f"a sensor of the dataset ({', '.join(ds.sensors) or 'none'})", sensor)  # fmt: skip
        if int(station) not in station_ids:
            raise DatasetError(f"{target} (not written)", "clouds", "a station of stations", int(station))
        a = np.asarray(pts, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 3 or len(a) == 0:
            raise DatasetError(f"{target} (not written)", "points", "a non-empty (N, 3) array", f"shape {a.shape}")
        if not np.isfinite(a).all():
            raise DatasetError(f"{target} (not written)", "points", "finite coordinates", "nan or inf")
        new_clouds[(sensor, int(station))] = a

    new_ts_clouds: dict[str, np.ndarray] = {}
    if timeseries_clouds:
        named = set()
        if ds.timeseries is not None:
            for s in ds.timeseries.suffixes("cloud_"):
                named |= {r.replace("\\", "/") for r in ds.timeseries[f"cloud_{s}"].tolist()} - {""}
        for rel, pts in timeseries_clouds.items():
            rel = str(rel).replace("\\", "/")
            target = f"{out / rel} (not written)"
            if rel not in named:
                raise DatasetError(target, "timeseries_clouds", "a cloud named in a cloud_<sensor> column of the "
                                   "timeseries", rel)  # fmt: skip
            a = np.asarray(pts, dtype=np.float64)
            if a.ndim != 2 or a.shape[1] != 3 or len(a) == 0:
                raise DatasetError(target, "points", "a non-empty (N, 3) array", f"shape {a.shape}")
            if not np.isfinite(a).all():
                raise DatasetError(target, "points", "finite coordinates", "nan or inf")
            new_ts_clouds[rel] = a

    copies: dict[str, Path] = {}  # relative destination -> source file
    if ds.root is not None:
        for (sensor, station), src in cloud_paths(ds).items():
            if (sensor, station) not in new_clouds and station in station_ids and sensor in ds.sensors:
                copies[f"clouds/{sensor}/{station}.ply"] = src
        if ds.timeseries is not None:
            for s in ds.timeseries.suffixes("cloud_"):
                for rel in set(ds.timeseries[f"cloud_{s}"].tolist()) - {""}:
                    rel = rel.replace("\\", "/")
                    if rel not in new_ts_clouds:
                        copies[rel] = ds.root / rel

    reserved = {"dataset.yaml", "stations.csv", "timeseries.csv", "planes.csv", "mocap.csv", "clouds"}
    for name in extra_files or {}:
        top = PurePosixPath(name.replace("\\", "/")).parts[0] if name else ""
        if not name or top in reserved or (urdf_rel and name.replace("\\", "/") == urdf_rel):
            raise ValueError(f"extra_files: {name!r} collides with a file of the dataset")

    with atomic_directory(out, overwrite=overwrite) as tmp:

        def dest(rel: str) -> Path:
            p = _inside(tmp, rel, f"{out / rel} (not written)", "path")
            p.parent.mkdir(parents=True, exist_ok=True)
            return p

        atomic_write_text(tmp / "dataset.yaml", yaml_text)
        for name, t in (("stations.csv", ds.stations), ("timeseries.csv", ds.timeseries),
                        ("planes.csv", ds.planes), ("mocap.csv", ds.mocap)):  # fmt: skip
            if t is not None:
                _check_table_text(t, f"{out / name} (not written)")
                atomic_write_text(tmp / name, table_csv_text(t))
        if urdf_rel is not None:
            atomic_write_bytes(dest(urdf_rel), urdf_bytes)
        for (sensor, station), a in new_clouds.items():
            write_ply(dest(f"clouds/{sensor}/{station}.ply"), a, binary=True)
        for rel, a in new_ts_clouds.items():
            write_ply(dest(rel), a, binary=True)
        for rel, src in copies.items():
            target = dest(rel)
            if not target.exists():
                try:
                    shutil.copyfile(src, target)
                except OSError as exc:
                    raise DatasetError(f"{out / rel} (not written)", "file", f"a copy of {src}",
                                       exc.strerror or str(exc)) from None  # fmt: skip
        for name, content in (extra_files or {}).items():
            data = content.encode("utf-8") if isinstance(content, str) else bytes(content)
            atomic_write_bytes(dest(name.replace("\\", "/")), data)
        try:
            _read(tmp)
        except DatasetError as exc:
            f = str(exc.file)
            f = str(out) + f[len(str(tmp)) :] if f.startswith(str(tmp)) else f
            raise DatasetError(f"{f} (not written)", exc.where, exc.expected, exc.got) from None
    return out
