"""``calibration.yaml`` (format ``graphcal-calibration/1``) read back and checked, and the pose
mapping it uses (``{xyz: [m], quaternion_wxyz, rpy_deg}``). Written by
:mod:`graphcal.report.calibration_yaml`; schema: docs/outputs.md."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping

import numpy as np
import yaml

from graphcal.errors import DatasetError
from graphcal.geometry import (
    matrix_from_quat_wxyz,
    matrix_from_rpy,
    pose_matrix,
    quat_wxyz_from_matrix,
    rotation_angle_between,
    rpy_from_matrix,
)
from graphcal.io.yaml_strict import StrictSafeLoader as _Loader

__all__ = ["FORMAT", "plain_float", "plain_floats", "pose_to_dict", "pose_from_dict", "read_calibration_yaml",
           "validate_calibration_dict"]

FORMAT = "graphcal-calibration/1"

#: Quaternion norm and quaternion-vs-rpy disagreement tolerated by :func:`read_calibration_yaml`.
_QUAT_NORM_TOL = 1e-3
_RPY_QUAT_TOL_RAD = 1e-4


def plain_float(x) -> float:
    """A plain Python float (no numpy scalar in a written file)."""
    return float(x)


def plain_floats(a) -> list:
    """Nested plain-float lists from an array-like (-0.0 written as 0.0)."""
    a = np.asarray(a, dtype=float) + 0.0  # + 0.0 turns -0.0 into 0.0
    return a.tolist()  # tolist gives Python floats


def pose_to_dict(T) -> dict:
    """``{xyz: [m], quaternion_wxyz: [w, x, y, z], rpy_deg: [roll, pitch, yaw]}`` of a 4x4 pose."""
    T = np.asarray(T, dtype=float)
    return {
        "xyz": plain_floats(T[:3, 3]),
        "quaternion_wxyz": plain_floats(quat_wxyz_from_matrix(T[:3, :3])),
        "rpy_deg": plain_floats(np.rad2deg(rpy_from_matrix(T[:3, :3]))),
    }


def pose_from_dict(d: Mapping) -> np.ndarray:
    """4x4 pose from a :func:`pose_to_dict` mapping (translation and quaternion; rpy is redundant)."""
    q = np.asarray(d["quaternion_wxyz"], dtype=float)
    return pose_matrix(matrix_from_quat_wxyz(q / np.linalg.norm(q)), np.asarray(d["xyz"], dtype=float))



# ----------------------------------------------------------------------------- reading


def _is_num(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


class _Checker:
    def __init__(self, path: Path):
        self.path = path

    def fail(self, where: str, expected: str, got=None):
        raise DatasetError(self.path, where, expected, got)

    def mapping(self, d, where: str, keys: tuple[str, ...] = ()) -> Mapping:
        if not isinstance(d, dict):
            self.fail(where, "a mapping", type(d).__name__ if d is not None else "nothing")
        for k in keys:
            if k not in d:
                self.fail(f"{where}.{k}" if where else k, "this key (required)", "missing")
        return d

    def numbers(self, v, where: str, n: int, what: str, *, finite: bool = True) -> list:
        if not isinstance(v, list) or len(v) != n or not all(_is_num(x) for x in v):
            self.fail(where, f"a list of {n} numbers ({what})", v)
        if finite and not all(math.isfinite(x) for x in v):
            self.fail(where, f"{n} finite numbers ({what})", v)
        return [float(x) for x in v]

    def number(self, v, where: str, what: str) -> float:
        if not _is_num(v) or not math.isfinite(v):
            self.fail(where, f"a finite number ({what})", v)
        return float(v)

    def matrix6(self, v, where: str, what: str) -> None:
        if not isinstance(v, list) or len(v) != 6:
            self.fail(where, f"a 6x6 matrix as a list of 6 rows ({what})", v)
        for i, row in enumerate(v):
            if not isinstance(row, list) or len(row) != 6 or not all(_is_num(x) for x in row):
                self.fail(f"{where}[{i}]", f"a row of 6 numbers ({what})", row)
        M = np.array(v, dtype=float)
        finite = np.isfinite(M)
        if not np.array_equal(finite, finite.T):
            self.fail(where, f"a symmetric matrix ({what})", "non-finite entries not symmetric")
        with np.errstate(invalid="ignore"):
            sym = np.where(finite & finite.T, M - M.T, 0.0)
        scale = max(1e-300, float(np.max(np.abs(np.where(finite, M, 0.0)))))
        if np.max(np.abs(sym)) > 1e-9 * scale:
            self.fail(where, f"a symmetric matrix ({what})", f"max asymmetry {float(np.max(np.abs(sym))):.3g}")

    def strings(self, v, where: str, what: str) -> None:
        if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
            self.fail(where, f"a list of text entries ({what})", v)

    def ints(self, v, where: str, what: str) -> None:
        if not isinstance(v, list) or not all(isinstance(x, int) and not isinstance(x, bool) for x in v):
            self.fail(where, f"a list of integers ({what})", v)

    def pose(self, v, where: str) -> None:
        self.mapping(v, where, ("xyz", "quaternion_wxyz", "rpy_deg"))
        self.numbers(v["xyz"], f"{where}.xyz", 3, "translation in m")
        q = np.array(self.numbers(v["quaternion_wxyz"], f"{where}.quaternion_wxyz", 4, "unit quaternion w, x, y, z"))
        nq = float(np.linalg.norm(q))
        if abs(nq - 1.0) > _QUAT_NORM_TOL:
            self.fail(f"{where}.quaternion_wxyz", "a unit quaternion (w, x, y, z)", f"norm {nq:.6g}")
        rpy = self.numbers(v["rpy_deg"], f"{where}.rpy_deg", 3, "roll, pitch, yaw in deg")
        err = rotation_angle_between(matrix_from_quat_wxyz(q / nq), matrix_from_rpy(np.deg2rad(rpy)))
        if err > _RPY_QUAT_TOL_RAD:
            self.fail(
                f"{where}.rpy_deg",
                "the same rotation as quaternion_wxyz (edit both or neither)",
                f"{np.rad2deg(err):.4g} deg apart",
            )

    def sigma(self, v, where: str) -> None:
        self.mapping(v, where, ("rot_deg", "xyz_mm"))
        self.numbers(v["rot_deg"], f"{where}.rot_deg", 3, "1-sigma rotation about body x, y, z in deg", finite=False)
        self.numbers(v["xyz_mm"], f"{where}.xyz_mm", 3, "1-sigma translation along body x, y, z in mm", finite=False)


def validate_calibration_dict(doc, path: str | Path = "calibration.yaml") -> dict:
    """Check a loaded ``calibration.yaml`` document; returns it, or raises :class:`DatasetError`."""
    c = _Checker(Path(path))
    if doc is None:
        c.fail("top level", "a calibration.yaml mapping", "an empty file")
    c.mapping(doc, "top level", ())
    if "format" not in doc:
        c.fail("format", f"the key format: {FORMAT}", "missing")
    if doc["format"] != FORMAT:
        c.fail("format", FORMAT, doc["format"])
    c.mapping(doc, "", ("sensors", "outliers", "residuals"))
    sensors = c.mapping(doc["sensors"], "sensors")
    for name, s in sensors.items():
        w = f"sensors.{name}"
        if not isinstance(name, str):
            c.fail(w, "a sensor name (text)", name)
        c.mapping(s, w, ("T_body_sensor", "covariance", "sigma", "unobservable"))
        c.pose(s["T_body_sensor"], f"{w}.T_body_sensor")
        c.matrix6(s["covariance"], f"{w}.covariance", "tangent [rx, ry, rz, x, y, z], rad and m")
        c.sigma(s["sigma"], f"{w}.sigma")
        c.strings(s["unobservable"], f"{w}.unobservable", "one entry per undetermined direction")
        if "T_body_sensor_prior" in s:
            c.pose(s["T_body_sensor_prior"], f"{w}.T_body_sensor_prior")
        if "correlation" in s:
            c.matrix6(s["correlation"], f"{w}.correlation", "correlation in body axes")
        if "change_stations" in s:
            c.ints(s["change_stations"], f"{w}.change_stations", "station ids")
        if "segments" in s:
            segs = s["segments"]
            if not isinstance(segs, list):
                c.fail(f"{w}.segments", "a list of segments", segs)
            for i, seg in enumerate(segs):
                ws = f"{w}.segments[{i}]"
                c.mapping(seg, ws, ("first_station", "last_station", "T_body_sensor", "sigma"))
                for k in ("first_station", "last_station"):
                    if not isinstance(seg[k], int) or isinstance(seg[k], bool):
                        c.fail(f"{ws}.{k}", "a station id (integer)", seg[k])
                c.pose(seg["T_body_sensor"], f"{ws}.T_body_sensor")
                c.sigma(seg["sigma"], f"{ws}.sigma")
    if "legs" in doc:
        legs = c.mapping(doc["legs"], "legs")
        for foot, params in legs.items():
            c.mapping(params, f"legs.{foot}")
            for pname, pv in params.items():
                wp = f"legs.{foot}.{pname}"
                c.mapping(pv, wp, ("value", "sigma"))
                c.number(pv["value"], f"{wp}.value", "parameter value, SI units")
                if not _is_num(pv["sigma"]):
                    c.fail(f"{wp}.sigma", "a number (1-sigma, SI units)", pv["sigma"])
    c.ints(doc["outliers"], "outliers", "station ids")
    res = c.mapping(doc["residuals"], "residuals", ("normal_rms_deg", "distance_rms_mm"))
    for k in ("normal_rms_deg", "distance_rms_mm"):
        if not _is_num(res[k]):
            c.fail(f"residuals.{k}", "a number", res[k])
    if "warnings" in doc:
        c.strings(doc["warnings"], "warnings", "warning sentences")
    if "adequacy" in doc:
        a = c.mapping(doc["adequacy"], "adequacy", ("verdict",))
        if a["verdict"] not in ("fits", "does not fit"):
            c.fail("adequacy.verdict", "fits or does not fit", a["verdict"])
    if "robot" in doc and not isinstance(doc["robot"], str):
        c.fail("robot", "the robot's name (text)", doc["robot"])
    return doc


def read_calibration_yaml(path: str | Path) -> dict:
    """Read and validate a ``calibration.yaml`` (format ``graphcal-calibration/1``).

    Returns the document as plain Python (use :func:`pose_from_dict` for a 4x4 pose).

    Raises:
        DatasetError: unreadable file, invalid YAML, wrong ``format``, a missing key, a value of the
            wrong shape (the message names the file and the key, e.g.
            ``sensors.depth.T_body_sensor.quaternion_wxyz``), or ``rpy_deg`` disagreeing with
            ``quaternion_wxyz``.
    """
    path = Path(path)
    try:
        from graphcal.io.files import read_regular_file

        raw = read_regular_file(path)  # a FIFO or device is refused, not read forever
    except OSError as exc:
        raise DatasetError(path, "file", "a readable calibration.yaml", exc.strerror or str(exc)) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise DatasetError(path, f"byte {exc.start}", "UTF-8 text") from None
    try:
        doc = yaml.load(text, Loader=_Loader)  # noqa: S506 -- a SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark is not None else "YAML syntax"
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise DatasetError(path, where, "valid YAML", " ".join(str(problem).split())) from None
    except (RecursionError, ValueError, TypeError, OverflowError) as exc:
        raise DatasetError(path, "YAML value", "valid YAML values", " ".join(str(exc).split())) from None
    return validate_calibration_dict(doc, path)
