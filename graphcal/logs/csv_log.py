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


def read_csv_map(path: Path) -> dict:
    """The column map: checked keys, units as factors to SI (``time.factor`` etc.)."""
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
    r = m.get("robot") or {}
    if not (r.get("model") or r.get("urdf")):
        raise DatasetError(path, "robot", "robot.model (a built-in robot) or robot.urdf (a file)", None)
    return m


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
    """``graphcal import`` of a CSV log with a column map; returns (folder, summary)."""
    m = read_csv_map(map_path)
    th = thresholds_of(m, str(map_path))
    joints = tuple(m["joints"]["columns"])
    feet = m.get("feet") or {}
    learn = [f for f, spec in feet.items() if "threshold_raw" not in spec and "threshold_n" not in spec]
    thresholds = foot_thresholds(_foot_samples(path, m, learn) if learn else {}, feet, th.force_threshold_n)
    finder = StationFinder(joints, tuple(feet), bool(m.get("imu")), th)
    sink = SampleSink(finder, thresholds, timeseries)
    stamps = StampCheck(path)
    first: list = []
    try:
        f = path.open(newline="", encoding="utf-8")
    except OSError as exc:
        raise DatasetError(path, "file", "a readable CSV log", exc.strerror or str(exc)) from None
    with f:
        reader = csv.reader(f)
        header = next(reader, None)
        if not header:
            raise DatasetError(path, "header (row 0)", "a header row of column names", "an empty file")
        idx = _columns(header, m, path)
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
    finder.finish()
    r = m["robot"]
    urdf_xml = None
    if urdf_file is not None or r.get("urdf"):
        p = Path(urdf_file or r["urdf"])
        try:
            urdf_xml = p.read_text(encoding="utf-8")
        except OSError as exc:
            raise DatasetError(p, "file", "a readable URDF", exc.strerror or str(exc)) from None
    base, feet_frames = r.get("base_frame"), r.get("feet")
    if r.get("model") and not (base and feet_frames):
        from graphcal.models.builtin import builtin_info

        info = builtin_info(r["model"])
        base, feet_frames = base or info.base_frame, feet_frames or list(info.feet)
    if not base or not feet_frames:
        raise DatasetError(map_path, "robot.base_frame / robot.feet", "the base frame and the foot frames", None)
    robot = RobotSpec("robot.urdf" if urdf_xml else None, None if urdf_xml else r["model"], base, feet_frames)
    imu = ImuSpec(PosePrior(np.zeros(3), np.zeros(3), 0.0, np.radians(1.0))) if m.get("imu") else None
    parts = DatasetParts(robot, urdf_xml, joints, {}, imu, finder, sink, source=str(path),
                         map_text=map_path.read_text(encoding="utf-8"))
    return write_imported(parts, Path(out_dir), overwrite=overwrite, jumps=stamps.jumps)


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
