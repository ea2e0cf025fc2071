"""CSV logs (a robot SDK's export, e.g. Unitree's: time, IMU, 12 joint positions, four raw foot-force
counts) read row by row through a column map YAML (docs/import.md): the time column and its unit,
joint columns and unit, IMU columns and units, raw force counts with offset and scale (or a raw
threshold), foot names. Wrong units are caught by plausibility (a time step, |specific force| at
rest about 9.81 m/s², joint angles within ±2π rad, rates under 35 rad/s)."""

from __future__ import annotations

import csv
import logging
from array import array
from pathlib import Path

import numpy as np

from graphcal.errors import DatasetError
from graphcal.io.dataset.model import ImuSpec, PosePrior, RobotSpec
from graphcal.logs.assemble import DatasetParts, SampleSink, StampCheck, foot_thresholds, write_imported
from graphcal.logs.mapping import load_yaml, thresholds_of
from graphcal.logs.stations import StationFinder
from graphcal.logs.urdf_frames import UrdfFrames, check_robot, resolve_map_path
from graphcal.progress import ProgressBar

__all__ = ["CSV_MAP_FORMAT", "import_csv", "read_csv_map"]

log = logging.getLogger(__name__)

CSV_MAP_FORMAT = "graphcal-csv-map/1"
_TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
_ACCEL_UNITS = {"m/s^2": 1.0, "m/s2": 1.0, "g": 9.80665}
_GYRO_UNITS = {"rad/s": 1.0, "deg/s": np.pi / 180.0}
_ANGLE_UNITS = {"rad": 1.0, "deg": np.pi / 180.0}
_KEYS = ("format", "time", "robot", "joints", "imu", "feet", "stations")


def _unit(table: dict, value, source, key: str) -> float:
    if value not in table:
        raise DatasetError(source, key, f"one of {', '.join(table)}", value)
    return table[value]


def read_csv_map(path: Path, *, urdf_given: bool = False) -> dict:
    """The column map: checked keys, units as factors to SI (``time.factor`` etc.); ``robot`` may
    be left out when the URDF is given (``--urdf``, ``urdf_given``)."""
    try:
        m = load_yaml(path.read_text(encoding="utf-8"), path)
    except OSError as exc:
        raise DatasetError(path, "file", "a readable column map (YAML)", exc.strerror or str(exc)) from None
    if not isinstance(m, dict) or m.get("format") != CSV_MAP_FORMAT:
        raise DatasetError(path, "format", CSV_MAP_FORMAT, m.get("format") if isinstance(m, dict) else m)
    for k in m:
        if k not in _KEYS:
            raise DatasetError(path, k, f"one of the keys {', '.join(_KEYS)}", k)
    t = m.get("time") or {}
    if "column" not in t:
        raise DatasetError(path, "time.column", "the name of the time column", None)
    t["factor"] = _unit(_TIME_UNITS, t.get("unit", "s"), path, "time.unit")
    j = m.get("joints") or {}
    if not isinstance(j.get("columns"), dict) or not j["columns"]:
        raise DatasetError(path, "joints.columns", "a mapping URDF joint -> column", j.get("columns"))
    j["factor"] = _unit(_ANGLE_UNITS, j.get("unit", "rad"), path, "joints.unit")
    imu = m.get("imu")
    if imu:
        for k in ("accel", "gyro"):
            if not (isinstance(imu.get(k), list) and len(imu[k]) == 3):
                raise DatasetError(path, f"imu.{k}", "three column names (x, y, z of the IMU frame)", imu.get(k))
        imu["accel_factor"] = _unit(_ACCEL_UNITS, imu.get("accel_unit", "m/s^2"), path, "imu.accel_unit")
        imu["gyro_factor"] = _unit(_GYRO_UNITS, imu.get("gyro_unit", "rad/s"), path, "imu.gyro_unit")
    if m.get("robot") is None:
        m["robot"] = {}
    r = m["robot"]
    if not isinstance(r, dict):
        raise DatasetError(path, "robot", "a mapping (model or urdf, base_frame, feet)", r)
    if not (r.get("model") or r.get("urdf") or urdf_given):
        raise DatasetError(path, "robot", "robot.model (a built-in robot) or robot.urdf (a file), or --urdf", None)
    return m


def _csv_robot(m: dict, map_path: Path, urdf_file: Path | None) -> tuple[RobotSpec, str | None, UrdfFrames]:
    """(robot, URDF text to write or None for a built-in model, its link tree): ``--urdf``, else
    the map's ``robot.urdf`` (relative to the map's folder), else ``robot.model``; the base frame
    (default: the URDF's root), the feet (default: its leaves named like feet) and the mapped
    joints checked against it, all before the log is read."""
    r = m["robot"]
    urdf_xml = None
    if urdf_file is not None or r.get("urdf"):
        p = Path(urdf_file) if urdf_file is not None else resolve_map_path(str(r["urdf"]), map_path)
        try:
            urdf_xml = p.read_text(encoding="utf-8")
        except OSError as exc:
            where = "file (--urdf)" if urdf_file is not None else f"file (robot.urdf of {map_path})"
            raise DatasetError(p, where, "a readable URDF", exc.strerror or str(exc)) from None
        frames = UrdfFrames(urdf_xml, str(p))
        base, feet = r.get("base_frame") or frames.root, r.get("feet") or list(frames.feet_guess)
    else:
        from graphcal.models.builtin import builtin_info, builtin_urdf

        info = builtin_info(r["model"])  # ModelError (one line) for an unknown name
        frames = UrdfFrames(builtin_urdf(r["model"]), f"of the built-in model {r['model']}")
        base, feet = r.get("base_frame") or info.base_frame, r.get("feet") or list(info.feet)
    if not base or not feet:
        raise DatasetError(map_path, "robot.base_frame / robot.feet", "the base frame and the foot frames", None)
    check_robot(frames, base, feet, m["joints"]["columns"], map_path)
    robot = RobotSpec("robot.urdf" if urdf_xml else None, None if urdf_xml else r["model"], base, list(feet))
    return robot, urdf_xml, frames


def _csv_imu(m: dict, frames: UrdfFrames, base: str, map_path: Path, notes: list[str]) -> ImuSpec | None:
    """``T_body_imu`` prior: the URDF's fixed transform base -> ``imu.link`` (2 mm, 1 deg unless
    ``imu.sigma_mm`` / ``imu.sigma_rpy_deg``); without ``imu.link``, the URDF's one link named
    ``*imu*`` (with a note), else identity (0 mm, 1 deg, with a note)."""
    imu = m.get("imu")
    if not imu:
        return None
    if imu.get("link") is not None:
        return ImuSpec(frames.imu_prior(base, imu, map_path))
    guess = frames.imu_guess()
    if guess is not None and guess != base:
        notes.append(f"IMU mount from the URDF link {guess} (imu.link not in the column map)")
        return ImuSpec(frames.imu_prior(base, {**imu, "link": guess}, map_path))
    notes.append("IMU mount unknown (no imu.link in the column map): T_body_imu identity, 1 deg")
    return ImuSpec(PosePrior(np.zeros(3), np.zeros(3), 0.0, np.radians(1.0)))


def _columns(header: list[str], m: dict, source: Path) -> dict[str, int]:
    """Every column the map names -> its index; DatasetError for a missing one."""
    names = {"time.column": m["time"]["column"]}
    names.update({f"joints.columns.{j}": c for j, c in m["joints"]["columns"].items()})
    if m.get("imu"):
        names.update({f"imu.{k}[{i}]": c for k in ("accel", "gyro") for i, c in enumerate(m["imu"][k])})
    names.update({f"feet.{f}.column": spec.get("column") for f, spec in (m.get("feet") or {}).items()})
    index = {c.strip(): i for i, c in enumerate(header)}
    out = {}
    for key, col in names.items():
        if col not in index:
            raise DatasetError(source, "header (row 0)", f"a column {col!r} ({key} in the column map)",
                               f"columns {', '.join(header[:12])}{', ...' if len(header) > 12 else ''}")
        out[key] = index[col]
    return out


def _plausible(source: Path, m: dict, first: list[tuple[int, float, np.ndarray, np.ndarray]]) -> None:
    """Unit checks on the first rows: the time step, |specific force| of the IMU."""
    if len(first) >= 2:
        dt = float(np.median(np.diff([r[1] for r in first])))
        if not 1e-5 <= dt <= 1.0:
            raise DatasetError(source, f"column {m['time']['column']} (rows 1-{len(first)})",
                               f"a time step between 0.01 ms and 1 s with time.unit {m['time'].get('unit', 's')}",
                               f"median step {dt:.3g} s (another unit?)")
    if m.get("imu") and first:
        a = float(np.median([np.linalg.norm(r[2]) for r in first]))
        if not 4.0 <= a <= 20.0:
            cols = ", ".join(m["imu"]["accel"])
            raise DatasetError(source, f"columns {cols} (rows 1-{len(first)})",
                               f"|specific force| about 9.81 m/s² with imu.accel_unit "
                               f"{m['imu'].get('accel_unit', 'm/s^2')}", f"median {a:.3g} m/s² (another unit?)")


def import_csv(path: Path, out_dir: Path, *, map_path: Path, urdf_file: Path | None = None, timeseries: bool = False,
               progress: bool = True, overwrite: bool = False) -> tuple[Path, str]:
    """``graphcal import`` of a CSV log with a column map; returns (folder, summary). Everything the
    map says that can be checked (the robot, its URDF, the IMU link, the header's columns) is
    checked before the first row is read."""
    m = read_csv_map(map_path, urdf_given=urdf_file is not None)
    th = thresholds_of(m, str(map_path))
    robot, urdf_xml, frames = _csv_robot(m, map_path, urdf_file)
    notes: list[str] = []
    imu = _csv_imu(m, frames, robot.base_frame, map_path, notes)
    header = _header(path)
    idx = _columns(header, m, path)
    joints = tuple(m["joints"]["columns"])
    feet = m.get("feet") or {}
    learn = [f for f, spec in feet.items() if "threshold_raw" not in spec and "threshold_n" not in spec]
    thresholds = foot_thresholds(_foot_samples(path, m, learn) if learn else {}, feet, th.force_threshold_n)
    finder = StationFinder(joints, tuple(feet), bool(m.get("imu")), th)
    sink = SampleSink(finder, thresholds, timeseries)
    stamps = _read_rows(path, m, idx, header, sink, progress)
    finder.finish()
    parts = DatasetParts(robot, urdf_xml, joints, {}, imu, finder, sink, notes=notes, source=str(path),
                         map_text=map_path.read_text(encoding="utf-8"))
    return write_imported(parts, Path(out_dir), overwrite=overwrite, jumps=stamps.jumps)


def _header(path: Path) -> list[str]:
    """The CSV's header row; DatasetError for an unreadable or empty file."""
    try:
        with path.open(newline="", encoding="utf-8") as f:
            header = next(csv.reader(f), None)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise DatasetError(path, "file", "a readable CSV log", getattr(exc, "strerror", None) or str(exc)) from None
    if not header:
        raise DatasetError(path, "header (row 0)", "a header row of column names", "an empty file")
    return header


def _read_rows(path: Path, m: dict, idx: dict, header: list[str], sink: SampleSink, progress: bool) -> StampCheck:
    """Every row into ``sink`` (stamps checked, units checked on the first 200 rows)."""
    stamps = StampCheck(path)
    first: list = []
    with path.open(newline="", encoding="utf-8") as f:
        reader = csv.reader(f)
        next(reader, None)
        for row_no, row in enumerate(ProgressBar(reader, desc="import: rows", unit="row", disable=not progress,
                                                 mininterval=0.5), start=1):
            t, q, acc, gyr, forces = _parse_row(path, m, idx, row, row_no, header)
            stamps(f"column {m['time']['column']}", t, f"row {row_no}")
            if len(first) < 200:
                first.append((row_no, t, acc, gyr))
                if len(first) == 200:
                    _plausible(path, m, first)
            if m.get("imu"):
                sink.imu(t, acc, gyr)
            if forces:
                sink.feet(t, forces)
            sink.joints(t, q)
    if len(first) < 200:
        _plausible(path, m, first)
    return stamps


def _foot_samples(path: Path, m: dict, feet: list[str]) -> dict[str, np.ndarray]:
    """A first pass over the CSV: foot -> its loads in the map's unit (N after offset and scale), to
    learn its contact thresholds from; rows that do not parse are skipped (the main pass names them)."""
    specs = m["feet"]
    try:
        with path.open(newline="", encoding="utf-8") as f:
            reader = csv.reader(f)
            index = {c.strip(): i for i, c in enumerate(next(reader, None) or [])}
            cols = [index.get(specs[foot].get("column")) for foot in feet]
            if any(c is None for c in cols):
                return {}  # the main pass names the missing column
            values = [array("d") for _ in feet]
            for row in reader:
                try:
                    v = [float(row[c]) for c in cols]
                except (ValueError, IndexError):
                    continue
                for out, x in zip(values, v):
                    out.append(x)
    except OSError:
        return {}  # the main pass says why
    return {foot: (np.frombuffer(v, dtype=np.float64) - float(specs[foot].get("offset", 0.0)))
            * float(specs[foot].get("scale", 1.0)) for foot, v in zip(feet, values)}


def _number(source: Path, row: list[str], i: int, row_no: int, header: list[str]) -> float:
    try:
        v = float(row[i])
    except (ValueError, IndexError):
        got = row[i] if i < len(row) else "nothing (short row)"
        raise DatasetError(source, f"row {row_no}, column {header[i]}", "a number", got) from None
    if not np.isfinite(v):
        raise DatasetError(source, f"row {row_no}, column {header[i]}", "a finite number", row[i])
    return v


def _parse_row(source: Path, m: dict, idx: dict, row: list[str], row_no: int, header: list[str]):
    """One row -> (t s, q rad, specific force m/s², rate rad/s, foot -> force N (or raw counts))."""
    num = lambda key: _number(source, row, idx[key], row_no, header)  # noqa: E731
    t = num("time.column") * m["time"]["factor"]
    jf = m["joints"]["factor"]
    q = np.array([num(f"joints.columns.{j}") * jf for j in m["joints"]["columns"]])
    bad = np.flatnonzero(np.abs(q) > 2 * np.pi)
    if bad.size:
        j = list(m["joints"]["columns"])[bad[0]]
        raise DatasetError(source, f"row {row_no}, column {m['joints']['columns'][j]}",
                           f"a joint angle within ±2π rad with joints.unit {m['joints'].get('unit', 'rad')}",
                           f"{q[bad[0]]:.4g} rad (another unit?)")
    acc = gyr = None
    if m.get("imu"):
        acc = np.array([num(f"imu.accel[{i}]") for i in range(3)]) * m["imu"]["accel_factor"]
        gyr = np.array([num(f"imu.gyro[{i}]") for i in range(3)]) * m["imu"]["gyro_factor"]
        if np.max(np.abs(gyr)) > 35.0:
            i = int(np.argmax(np.abs(gyr)))
            raise DatasetError(source, f"row {row_no}, column {m['imu']['gyro'][i]}",
                               f"an angular rate under 35 rad/s with imu.gyro_unit {m['imu'].get('gyro_unit', 'rad/s')}",
                               f"{gyr[i]:.4g} rad/s (another unit?)")
    forces = {}
    for foot, spec in (m.get("feet") or {}).items():
        raw = num(f"feet.{foot}.column")
        forces[foot] = raw if "threshold_raw" in spec else (raw - float(spec.get("offset", 0.0))) * float(
            spec.get("scale", 1.0))
    return t, q, acc, gyr, forces
