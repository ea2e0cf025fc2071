"""The CSV files of a dataset (``stations.csv``, ``timeseries.csv``, ``planes.csv``, ``mocap.csv``):
read strictly (:func:`read_csv`: header, columns of the contract, numbers) and written
(:func:`table_csv_text`, the one CSV writer: shortest ``repr``, an exact float64 round trip)."""

from __future__ import annotations

import csv
import io
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from graphcal.errors import DatasetError, excerpt
from graphcal.io.dataset.model import (
    BODY_POSE_COLUMNS,
    IMU_ACCEL_COLUMNS,
    IMU_GYRO_COLUMNS,
    MOCAP_COLUMNS,
    MOCAP_POSE_COLUMNS,
    MOCAP_POSE_COV_COLUMNS,
    MOCAP_POSE_SIGMA_COLUMNS,
    PLANE_COV_COLUMNS,
    PLANE_REQUIRED_COLUMNS,
    Table,
    is_string_column,
)
from graphcal.io.dataset.text import cell_text, decode_utf8, did_you_mean, one_line
from graphcal.io.files import read_regular_file

_NUMBER_RE = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


@dataclass(frozen=True)
class ParsedCsv:
    """A CSV table with the file line of each row, for messages."""

    file: Path
    table: Table
    lines: np.ndarray  # (n,) int, 1-based line numbers of the data rows

    def where(self, i: int, column: str | None = None) -> str:
        w = f"row {i + 1} (line {int(self.lines[i])})"
        return f"{w}, column {column}" if column else w

    def err(self, i: int, column: str | None, expected: str, got: object = None) -> DatasetError:
        return DatasetError(self.file, self.where(i, column), expected, got)


#: the CSV files of the contract by kind
CSV_FILES = {"stations": "stations.csv", "timeseries": "timeseries.csv", "planes": "planes.csv", "mocap": "mocap.csv",
             "mocap_poses": "mocap_poses.csv"}


def _allowed_text(kind: str) -> str:
    if kind == "planes":
        return "station, sensor, nx, ny, nz, d, n_points, rms, cov_00 ... cov_33"
    if kind == "mocap":
        return "time, marker, x, y, z"
    if kind == "mocap_poses":
        return "time, frame, x, y, z, qw, qx, qy, qz, sigma_rx ... sigma_z or cov_00 ... cov_55"
    base = "session, time, q_<joint>, tau_<joint>, body_x ... body_qz, imu_ax ... imu_gz"
    ts = ", cloud_<sensor>, contact_<foot>, force_<foot>, p_body_<foot>_x/_y/_z"
    return "station, " + base if kind == "stations" else base + ts


def _column_ok(kind: str, name: str) -> bool:
    if kind == "planes":
        return name in PLANE_REQUIRED_COLUMNS or name in ("n_points", "rms") or name in PLANE_COV_COLUMNS
    if kind == "mocap":
        return name in MOCAP_COLUMNS
    if kind == "mocap_poses":
        return name in MOCAP_POSE_COLUMNS or name in MOCAP_POSE_SIGMA_COLUMNS or name in MOCAP_POSE_COV_COLUMNS
    if name in ("session", "time") or name in BODY_POSE_COLUMNS or name in IMU_ACCEL_COLUMNS + IMU_GYRO_COLUMNS:
        return True
    if kind == "stations" and name == "station":
        return True
    # p_body_<foot>_x/_y/_z: body-frame foot points (m) of a robot given by its feet (docs/dataset.md)
    prefixes = ("q_", "tau_") + (("cloud_", "contact_", "force_", "p_body_") if kind == "timeseries" else ())
    return any(name.startswith(p) and len(name) > len(p) for p in prefixes)


_REQUIRED = {
    "stations": ("station",),
    "timeseries": ("time",),
    "planes": PLANE_REQUIRED_COLUMNS,
    "mocap": MOCAP_COLUMNS,
    "mocap_poses": MOCAP_POSE_COLUMNS,
}
_GROUPS = {
    "stations": (BODY_POSE_COLUMNS, IMU_ACCEL_COLUMNS, IMU_GYRO_COLUMNS),
    "timeseries": (BODY_POSE_COLUMNS, IMU_ACCEL_COLUMNS, IMU_GYRO_COLUMNS),
    "planes": (PLANE_COV_COLUMNS,),
    "mocap": (),
    "mocap_poses": (MOCAP_POSE_SIGMA_COLUMNS, MOCAP_POSE_COV_COLUMNS),
}


def read_csv(path: Path, kind: str) -> ParsedCsv:
    """Read the CSV file ``path`` of kind ``kind`` (a key of :data:`CSV_FILES`): its header (the
    contract's columns, required ones and complete groups) and cells (numbers, integer station
    ids, labels). The values' checks are in :mod:`graphcal.io.dataset.checks`."""
    try:
        raw = read_regular_file(path)
    except OSError as exc:
        raise DatasetError(path, "file", f"a readable {CSV_FILES[kind]}", exc.strerror or str(exc)) from None
    text = decode_utf8(raw, path)
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
        raise DatasetError(path, f"line {max(reader.line_num, 1)}", "well-formed CSV", one_line(str(exc))) from None
    if header is None:
        raise DatasetError(path, "header", "a first line with the column names", "an empty file")
    if rows and not text.endswith(("\n", "\r")) and lines[-1] == reader.line_num:
        raise DatasetError(path, f"row {len(rows)} (line {lines[-1]})", "a line end after the last row (a file "
                           "that stops inside a row was cut off, e.g. while being copied)", "no line end")
    if len(header) == 1 and (";" in header[0] or "\t" in header[0]):
        sep = "semicolons" if ";" in header[0] else "tabs"
        raise DatasetError(path, "header", f"column names separated by commas (this file uses {sep}: the "
                           "contract's CSV is comma-separated, with a point as the decimal mark)", cell_text(header[0]))

    for j, name in enumerate(header):
        if not name:
            raise DatasetError(path, f"header, column {j + 1}", "a column name", "an empty name")
        if not name.isprintable():
            raise DatasetError(path, f"header, column {j + 1}", "a column name of printable characters", cell_text(name))
        if name in header[:j]:
            raise DatasetError(path, f"header, column {j + 1}", "each column name once", f"{excerpt(repr(name), 40)} again")
        if kind == "timeseries" and name == "station":
            raise DatasetError(path, "header, column station", "no station column in timeseries.csv "
                               "(static stations go to stations.csv)", "station")  # fmt: skip
        if not _column_ok(kind, name):
            raise DatasetError(
                path, f"header, column {excerpt(name, 40)}", f"a column of the contract ({_allowed_text(kind)})",
                f"unknown column {excerpt(repr(name), 40)}{did_you_mean(name, _REQUIRED[kind] + BODY_POSE_COLUMNS)}",
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
            for i, v in enumerate(vals):
                if not v and not name.startswith("cloud_"):
                    raise DatasetError(path, f"row {i + 1} (line {lines[i]}), column {name}",
                                       f"a {name} label", "an empty cell")
                if not v.isprintable():  # a NUL or a line break would make another label that looks the same
                    raise DatasetError(path, f"row {i + 1} (line {lines[i]}), column {name}",
                                       f"a {name} of printable characters (no control characters)", cell_text(v))
            data[name] = np.array(vals, dtype=np.str_) if vals else np.array([], dtype="<U1")
        else:
            data[name] = _numbers(col, path, name, lines)
    if "station" in data:
        st = data["station"]
        bad = ~((st == np.round(st)) & (np.abs(st) < 2.0**53))
        if bad.any():
            i = int(np.argmax(bad))
            raise DatasetError(path, f"row {i + 1} (line {lines[i]}), column station", "an integer station id",
                               cell_text(cells[header.index("station")][i].strip()))
        data["station"] = st.astype(np.int64)
    return ParsedCsv(path, Table(tuple(header), data), lines_a)


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
            raise DatasetError(path, where, "a finite number" if nonfinite else "a number", cell_text(s))
        if not math.isfinite(float(s)):
            raise DatasetError(path, where, "a finite number (this one overflows to infinity)", cell_text(s))
    # every cell is a plain ASCII decimal once stripped of whitespace: the fast path refused the column
    # only for a non-ASCII character around a number, e.g. a no-break space (found by the fuzz test)
    return np.array([float(c.strip()) for c in col], dtype=np.float64)


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


def check_table_text(t: Table, file: Path | str) -> None:
    """DatasetError (naming ``file``, the file to be written) for a text cell of ``t`` with leading
    or trailing spaces: it would not read back the same."""
    for c in t.columns:
        if t[c].dtype.kind != "U":
            continue
        for i, v in enumerate(t[c].tolist()):
            if v != v.strip():
                raise DatasetError(file, f"row {i + 1}, column {c}", "text without leading or trailing spaces", v)
