"""``calibration.yaml`` (format ``graphcal-calibration/1``): the calibration result as plain YAML.

Written by :func:`calibration_yaml_text` from a :class:`~graphcal.calibration.result.CalibrationResult`,
read back (and checked) by :func:`read_calibration_yaml`. Schema: docs/outputs.md.

Conventions (docs/conventions.md): ``T_body_sensor`` maps sensor coordinates to the body frame;
``xyz`` in metres; ``quaternion_wxyz`` unit with ``w >= 0``; ``rpy_deg`` the ROS convention
``R = Rz(yaw) Ry(pitch) Rx(roll)`` in degrees; ``covariance`` of the right perturbation
``T = T_hat * Exp(xi)``, ``xi = [rx, ry, rz, x, y, z]`` in rad and m. ``sigma`` and ``correlation``
are about/along the *body* axes (deg, mm), see :func:`body_axis_covariance`.

Every number is a plain Python ``float`` or ``int`` (no numpy scalars, no YAML tags), so
``yaml.safe_load`` reads the file back; floats are written with ``repr`` precision (exact round trip).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping

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

__all__ = [
    "FORMAT",
    "calibration_to_dict",
    "calibration_yaml_text",
    "read_calibration_yaml",
    "validate_calibration_dict",
    "pose_to_dict",
    "pose_from_dict",
    "body_axis_covariance",
    "sigma_body_deg_mm",
    "residual_summary",
    "adequacy_dict",
    "range_scale_check_dict",
]

FORMAT = "graphcal-calibration/1"

#: Quaternion norm and quaternion-vs-rpy disagreement tolerated by :func:`read_calibration_yaml`.
_QUAT_NORM_TOL = 1e-3
_RPY_QUAT_TOL_RAD = 1e-4


# ----------------------------------------------------------------------------- helpers
def _f(x) -> float:
    return float(x)


def _flist(a) -> list:
    """Nested plain-float lists from an array-like."""
    a = np.asarray(a, dtype=float) + 0.0  # + 0.0 turns -0.0 into 0.0
    return a.tolist()  # tolist gives Python floats


def pose_to_dict(T) -> dict:
    """``{xyz: [m], quaternion_wxyz: [w, x, y, z], rpy_deg: [roll, pitch, yaw]}`` of a 4x4 pose."""
    T = np.asarray(T, dtype=float)
    return {
        "xyz": _flist(T[:3, 3]),
        "quaternion_wxyz": _flist(quat_wxyz_from_matrix(T[:3, :3])),
        "rpy_deg": _flist(np.rad2deg(rpy_from_matrix(T[:3, :3]))),
    }


def pose_from_dict(d: Mapping) -> np.ndarray:
    """4x4 pose from a :func:`pose_to_dict` mapping (translation and quaternion; rpy is redundant)."""
    q = np.asarray(d["quaternion_wxyz"], dtype=float)
    return pose_matrix(matrix_from_quat_wxyz(q / np.linalg.norm(q)), np.asarray(d["xyz"], dtype=float))


def body_axis_covariance(T_body_sensor, covariance) -> np.ndarray:
    """Covariance (6, 6) of [rotation about body x, y, z (rad), position along body x, y, z (m)].

    ``covariance`` is of ``xi = [omega, v]`` with ``T = T_hat Exp(xi)`` (sensor axes). To first order
    ``R_hat Exp(omega) = Exp(R_hat omega) R_hat`` and the sensor origin moves by ``R_hat v``, so the
    body-axis errors are ``blockdiag(R_hat, R_hat) xi`` (as graphcal.solvers.covariance.body_axis_sigmas).
    A sensor-axis component with infinite variance makes the body components it touches infinite
    (their variance ``inf``, their covariances 0).
    """
    R = np.asarray(T_body_sensor, dtype=float)[:3, :3]
    J = np.zeros((6, 6))
    J[:3, :3] = R
    J[3:, 3:] = R
    cov = np.asarray(covariance, dtype=float)
    bad = ~np.isfinite(np.diag(cov))
    C = np.where(np.isfinite(cov), cov, 0.0)
    C[bad, :] = 0.0
    C[:, bad] = 0.0
    C = J @ C @ J.T
    C = 0.5 * (C + C.T)
    if bad.any():
        inf_body = np.abs(J[:, bad]).sum(axis=1) > 1e-9
        C[inf_body, :] = 0.0
        C[:, inf_body] = 0.0
        C[inf_body, inf_body] = np.inf
    return C


def sigma_body_deg_mm(T_body_sensor, covariance) -> tuple[np.ndarray, np.ndarray]:
    """(sigma of the rotation about body x, y, z in deg, sigma along body x, y, z in mm)."""
    C = body_axis_covariance(T_body_sensor, covariance)
    s = np.sqrt(np.clip(np.diag(C), 0.0, None))
    return np.rad2deg(s[:3]), s[3:] * 1000.0


def _rms(x) -> float:
    x = np.asarray(x, dtype=float)
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def residual_summary(result, sensor: str | None = None) -> dict:
    """RMS, mean and max of the plane residuals before and after, over the non-outlier rows.

    Returns a dict with ``stations`` (rows used), ``outlier_rows``, ``normal_rms_deg_before/after``,
    ``distance_rms_mm_before/after``, ``angle_mean_deg_before/after``, ``angle_max_deg_before/after``,
    ``distance_mean_mm_before/after``, ``distance_max_mm_before/after`` (distances as |e_d|).
    ``sensor`` restricts to one sensor's rows.
    """
    outl = set(int(s) for s in result.outliers)
    rows = [r for r in result.residuals if sensor is None or r.sensor == sensor]
    inl = [r for r in rows if not (r.outlier or int(r.station) in outl)]
    out: dict[str, Any] = {"stations": len(inl), "outlier_rows": len(rows) - len(inl)}
    for when in ("before", "after"):
        a = np.abs([getattr(r, f"angle_{when}_deg") for r in inl])
        d = np.abs([getattr(r, f"distance_{when}_mm") for r in inl])
        out[f"normal_rms_deg_{when}"] = _rms(a)
        out[f"distance_rms_mm_{when}"] = _rms(d)
        out[f"angle_mean_deg_{when}"] = float(a.mean()) if a.size else float("nan")
        out[f"angle_max_deg_{when}"] = float(a.max()) if a.size else float("nan")
        out[f"distance_mean_mm_{when}"] = float(d.mean()) if d.size else float("nan")
        out[f"distance_max_mm_{when}"] = float(d.max()) if d.size else float("nan")
    return out


# ----------------------------------------------------------------------------- writing
def _sensor_dict(s) -> dict:
    T = np.asarray(s.T_body_sensor, dtype=float)
    entry: dict[str, Any] = {
        "type": str(s.type),
        "T_body_sensor": pose_to_dict(T),
        "covariance": _flist(s.covariance),
        "sigma": {"rot_deg": _flist(s.sigma_rot_deg), "xyz_mm": _flist(s.sigma_xyz_mm)},
        "unobservable": [str(u) for u in s.unobservable],
        "T_body_sensor_prior": pose_to_dict(s.T_body_sensor_prior),
        "correlation": _flist(s.correlation),
        "change_stations": [int(c) for c in s.change_stations],
        # the factor covariance and sigma include (> 1: the plane residuals outgrew a given noise model)
        "covariance_scale": _f(getattr(s, "covariance_scale", 1.0)),
        # which covariance governs covariance and sigma: the model's, or the robust one when the
        # model does not fit (adequacy:); both are written then
        "sigma_from": "model" if getattr(s, "covariance_model", None) is None else "robust",
    }
    if getattr(s, "covariance_model", None) is not None:
        rot_m, xyz_m = sigma_body_deg_mm(T, s.covariance_model)
        entry["covariance_model"] = _flist(s.covariance_model)
        entry["sigma_model"] = {"rot_deg": _flist(rot_m), "xyz_mm": _flist(xyz_m)}
        entry["covariance_robust"] = _flist(s.covariance)
        entry["sigma_robust"] = {"rot_deg": _flist(s.sigma_rot_deg), "xyz_mm": _flist(s.sigma_xyz_mm)}
        # the terms summed into the robust covariance, each with what it is (calibration/robust.py)
        terms = getattr(s, "robust_terms", ())
        if terms:
            entry["robust_terms"] = {str(k): str(v) for k, v in terms}
    check = getattr(s, "range_scale_check", None)
    if check is not None:
        entry["range_scale_check"] = range_scale_check_dict(check)
    if len(s.segments) > 1:
        segs = []
        for seg in s.segments:
            rot, xyz = sigma_body_deg_mm(seg.T_body_sensor, seg.covariance)
            segs.append(
                {
                    "first_station": int(seg.first_station),
                    "last_station": int(seg.last_station),
                    "T_body_sensor": pose_to_dict(seg.T_body_sensor),
                    "sigma": {"rot_deg": _flist(rot), "xyz_mm": _flist(xyz)},
                }
            )
        entry["segments"] = segs
    return entry


def calibration_to_dict(result) -> dict:
    """The ``calibration.yaml`` document of ``result`` as plain Python (str, float, int, list, dict).

    Keys (docs/outputs.md): ``format``, ``dataset``, ``base_frame``, ``frames``, ``adequacy`` (the
    verdict on the model, when judged), ``robot`` (its name, when
    known), ``sensors`` (per sensor:
    ``type``, ``T_body_sensor``, ``covariance``, ``sigma``, ``unobservable``, ``T_body_sensor_prior``,
    ``correlation``, ``change_stations``, ``covariance_scale`` and ``segments`` when the sensor moved), ``legs`` (only when
    legs were calibrated), ``outliers``, ``residuals``, ``solver``, ``warnings``.
    """
    doc: dict[str, Any] = {
        "format": FORMAT,
        "dataset": str(result.dataset),
        "base_frame": str(result.base_frame),
        "frames": frames_note(str(result.base_frame)),
    }
    if getattr(result, "adequacy", None) is not None:
        doc["adequacy"] = adequacy_dict(result.adequacy)
    if result.robot_name:
        doc["robot"] = str(result.robot_name)  # --noise-from tells another robot's file by it
    doc["sensors"] = {str(name): _sensor_dict(s) for name, s in result.sensors.items()}
    if result.legs:
        legs = {}
        for foot, leg in result.legs.items():
            legs[str(foot)] = {
                str(n): {"value": _f(v), "sigma": _f(sg)} for n, v, sg in zip(leg.names, leg.values, leg.sigmas)
            }
        doc["legs"] = legs
    doc["outliers"] = sorted({int(s) for s in result.outliers})
    summ = residual_summary(result)
    doc["residuals"] = {
        "normal_rms_deg": _f(result.normal_rms_deg),
        "distance_rms_mm": _f(result.distance_rms_mm),
        "normal_rms_deg_before": summ["normal_rms_deg_before"],
        "distance_rms_mm_before": summ["distance_rms_mm_before"],
        "stations": int(len({int(r.station) for r in result.residuals})),
    }
    doc["solver"] = {"kind": str(result.solver), "iterations": int(result.iterations)}
    doc["warnings"] = [str(w) for w in result.warnings]
    noise = getattr(result, "noise", None) or {}
    if noise:
        # the noise model of the final solve (SI units; learned by variance-component estimation)
        doc["noise_model"] = {str(k): float(v) for k, v in noise.items()}
    source = getattr(result, "noise_source", "") or ""
    if source:
        doc["noise_model_from"] = str(source)  # calibrate --noise-from: given, not learned
    groups = getattr(result, "noise_groups", ()) or ()
    if groups:
        # how each group's sigma was set: learned, held (too few dof: the data hint at data_scale), or given
        doc["noise_estimation"] = {
            str(g.group): {"status": str(g.status), "dof": _f(g.dof), "rows": int(g.rows),
                           "data_scale": _f(g.data_scale), "p_high": _f(g.p_high),
                           "values": {str(k): float(v) for k, v in g.fields},
                           # components the data did not separate: they share one scale
                           **({"scaled_with": [str(k) for k in g.shared_with]} if getattr(g, "shared_with", ()) else {})}
            for g in groups
        }
    return doc


def _group_value_dict(pairs) -> dict:
    """(name, value) pairs of a group check as a mapping in the units their names say."""
    return {str(k): float(v) for k, v in pairs}


def adequacy_dict(a) -> dict:
    """The ``adequacy:`` block (docs/outputs.md) of an :class:`~graphcal.calibration.adequacy.Adequacy`."""
    from graphcal.calibration.adequacy import ALPHA, RATIO_LIMIT

    return {
        "verdict": str(a.verdict),
        "statistic": _f(a.statistic),
        "reference": str(a.reference),
        "p_value": _f(a.p_value),
        "worst_group": str(a.worst_group),
        "test": ("each noise group's learned sigma s (the sigma of the final solve times the factor its residuals "
                 "point to) against its physical sigma p (dataset.yaml physical_noise:, else graphcal's defaults): "
                 "T = dof (s/p)^2 against chi2(dof); a group does not fit when s > "
                 f"{RATIO_LIMIT:g} p and its p-value is below {ALPHA:g} / groups; p_value is the worst group's "
                 "times the number of groups (Bonferroni)"),
        "sigma_from": str(a.covariance),
        "groups": {str(g.group): {"misfit": bool(g.misfit), "ratio": _f(g.ratio), "statistic": _f(g.statistic),
                                  "dof": _f(g.dof), "p_value": _f(g.p_value),
                                  "learned_si": _group_value_dict(g.learned),
                                  "physical": _group_value_dict(g.physical), "physical_from": str(g.source)}
                   for g in a.groups},
        "gross_stations": [{"station": int(s.station), "statistic": _f(s.statistic), "dof": _f(s.dof),
                            "p_value": _f(s.p_value), "factor_over_median": _f(s.factor)} for s in a.gross],
        "next_steps": [str(x) for x in a.next_steps],
    }


def range_scale_check_dict(c) -> dict:
    """A sensor's ``range_scale_check:`` block (docs/outputs.md) of a
    :class:`~graphcal.calibration.range_observability.RangeScaleCheck`."""
    sigma = float(c.sigma_from_data)
    return {
        "determined": bool(c.determined),
        # 1-sigma of the range scale (measured / true range) from the data alone, per cent (.inf: none)
        "sigma_from_data_pct": 100.0 * sigma,
        "limit_pct": _f(c.limit_pct),
        "limit_from": str(c.limit_from),
        # how the estimate moves for a range scale 1 % larger: norm, and along/about the body axes
        "translation_mm_per_percent": _f(c.translation_mm),
        "rotation_deg_per_percent": _f(c.rotation_deg),
        "translation_mm_per_percent_body_xyz": _flist(c.translation_mm_per_percent),
        "rotation_deg_per_percent_body_xyz": _flist(c.rotation_deg_per_percent),
    }


def frames_note(base_frame: str) -> dict[str, str]:
    """What each sensor entry's numbers mean, written into the file itself (docs/outputs.md)."""
    return {
        "T_body_sensor": f"maps sensor coordinates to {base_frame} coordinates (p_body = T_body_sensor p_sensor); "
                         "xyz in m, rpy_deg = R = Rz(yaw) Ry(pitch) Rx(roll) in deg, quaternion (w, x, y, z)",
        "covariance": "6x6 of the right perturbation T = T_hat Exp(xi), xi = [rx, ry, rz, x, y, z] about/along "
                      "the SENSOR axes, in rad and m (GTSAM's tangent order [omega, v])",
        "sigma": f"1-sigma rotation about and translation along the {base_frame.upper()} axes x, y, z, "
                 "in deg and mm (sqrt(diag(covariance)) is in sensor axes and differs)",
        "correlation": f"6x6 correlation of [rot x, y, z, trans x, y, z] in {base_frame} axes",
        "sigma_from": "model: covariance and sigma are the model's; robust: the model does not fit (adequacy:), "
                      "covariance and sigma are the robust covariance (= covariance_robust, sigma_robust), the "
                      "model's is beside it as covariance_model, sigma_model (same axes and units); robust_terms "
                      "names the terms summed into it (model, jackknife, legs_shift, range_scale_shift, "
                      "extrinsic_change_shift)",
        "range_scale_check": "the sigma assume each sensor's range is exact; range_scale_check says how well "
                             "these data determine a range scale (measured / true range) of the sensor: "
                             "sigma_from_data_pct (1-sigma, per cent, data alone), determined (at most limit_pct), "
                             "and how far a scale 1 % larger moves the estimate (mm, deg; body axes)",
    }


def _header(result) -> str:
    ds = " ".join(str(result.dataset).split())  # one line
    return (
        f"# graphcal calibration result ({FORMAT}): sensor extrinsics T_body_sensor, their covariance"
        f" and leg parameters, written by graphcal calibrate from dataset {ds}\n"
    )


def calibration_yaml_text(result, *, extra: Mapping[str, Any] | None = None) -> str:
    """``calibration.yaml`` text: a leading comment line, then :func:`calibration_to_dict` as YAML.

    ``extra`` adds top-level keys (plain values) after the standard ones (used by
    :func:`graphcal.report.write.write_calibration_outputs` for ``output_files``).
    """
    doc = calibration_to_dict(result)
    if extra:
        doc.update(extra)
    frames = doc.pop("frames", None)
    body = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, allow_unicode=True, width=200)
    if frames is not None:  # a block of sentences, one a line, after base_frame
        block = yaml.safe_dump({"frames": frames}, sort_keys=False, default_flow_style=False,
                               allow_unicode=True, width=10_000)
        at = body.index("\nbase_frame:") + 1
        at = body.index("\n", at) + 1
        body = body[:at] + block + body[at:]
    return _header(result) + body


# ----------------------------------------------------------------------------- reading
from graphcal.io.yaml_strict import StrictSafeLoader as _Loader  # noqa: E402


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
