"""``calibration.yaml`` (format ``graphcal-calibration/1``): the calibration result as plain YAML.

Written by :func:`calibration_yaml_text` from a :class:`~graphcal.calibration.result.CalibrationResult`,
read back (and checked) by :func:`graphcal.io.calibration_yaml.read_calibration_yaml`. Schema:
docs/outputs.md.

Conventions (docs/conventions.md): ``T_body_sensor`` maps sensor coordinates to the body frame;
``xyz`` in metres; ``quaternion_wxyz`` unit with ``w >= 0``; ``rpy_deg`` the ROS convention
``R = Rz(yaw) Ry(pitch) Rx(roll)`` in degrees; ``covariance`` of the right perturbation
``T = T_hat * Exp(xi)``, ``xi = [rx, ry, rz, x, y, z]`` in rad and m. ``sigma`` and ``correlation``
are about/along the *body* axes (deg, mm), see :func:`body_axis_covariance`.

Every number is a plain Python ``float`` or ``int`` (no numpy scalars, no YAML tags), so
``yaml.safe_load`` reads the file back; floats are written with ``repr`` precision (exact round trip).
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np
import yaml

from graphcal.calibration.adequacy import adequacy_dict
from graphcal.io.calibration_yaml import FORMAT, plain_float, plain_floats, pose_to_dict

__all__ = [
    "calibration_to_dict",
    "calibration_yaml_text",
    "body_axis_covariance",
    "sigma_body_deg_mm",
    "residual_summary",
    "range_scale_check_dict",
]

_f = plain_float
_flist = plain_floats


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
    if getattr(s, "time_offset_s", None) is not None:
        # a walk's camera: its stamp minus its capture time (s); sigma null when given or not determined
        entry["time_offset_s"] = _f(s.time_offset_s)
        entry["time_offset_sigma_s"] = None if s.time_offset_sigma_s is None else _f(s.time_offset_sigma_s)
        entry["time_offset_source"] = str(s.time_offset_source)
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
    walk = getattr(result, "walk", None)
    if walk:
        # a walking dataset: its stations are camera frames and stance changes (station_times_s: log time, s)
        doc["walk"] = {"duration_s": _f(walk["duration_s"]), "stations": int(walk["stations"]),
                       "frames": {str(k): int(v) for k, v in walk["frames"].items()},
                       "frames_in_log": {str(k): int(v) for k, v in walk["frames_in_log"].items()}}
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
        "time_offset_s": "a walking dataset's camera: its cloud stamp minus its capture time, in s (the frame "
                         "stamped t shows the body at t - time_offset_s); time_offset_sigma_s its 1-sigma in s "
                         "(null when given or not determined); time_offset_source estimated | given | not determined",
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
