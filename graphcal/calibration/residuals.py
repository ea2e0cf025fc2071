"""Plane residuals of a calibration: every station and sensor, before and after.

Chai 2015's theta (angle between the measured and the predicted ground, deg) and e_d (distance
error, mm), each against the model before calibration (CAD extrinsic, body poses from the
kinematics) and after (the solution), and the chi-square of the plane factor at the solution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class StationResidual:
    """Plane residual of one station and sensor, against the model before (CAD prior, body poses
    from kinematics) and after calibration. Chai 2015's theta (angle between measured and predicted
    ground, deg) and e_d (distance error, mm)."""

    station: int
    sensor: str
    angle_before_deg: float
    distance_before_mm: float
    angle_after_deg: float
    distance_after_mm: float
    chi2_after: float
    outlier: bool = False


def plane_residuals(data, problem, values, T_world_body: dict, sensors: dict, outliers) -> list[StationResidual]:
    """The :class:`StationResidual` of every plane of ``data`` seen by a sensor of ``sensors``, in
    (station, sensor) order.

    Args:
        data: the :class:`~graphcal.calibration.measurements.CalibrationData` (planes in the sensor
            frame: unit normal towards the sensor, distance m).
        problem, values: the :class:`~graphcal.calibration.graph.CalibrationProblem` solved and its
            solution (gtsam.Values): "before" is its kinematic body pose and CAD extrinsic, the
            chi-square is its plane factor's whitened error at ``values`` (nan for a measurement
            left out of the graph).
        T_world_body: station id -> (4, 4) body pose after (m).
        sensors: sensor name -> its estimate (``T_body_sensor`` (4, 4), m) after.
        outliers: the (station, sensor) measurements left out as outliers.
    """
    from graphcal.calibration.graph import predicted_plane_errors
    from graphcal.solvers.batch import whitened_errors

    index_of = {m: i for i, m in problem.plane_factors.items()}
    out = []
    for (station, sensor), p in sorted(data.planes.items()):
        if sensor not in sensors:
            continue
        T_cad = problem.sensor_priors[sensor][0]
        a0, d0 = predicted_plane_errors(problem.initial_body[station], T_cad, p.n, p.d)
        a1, d1 = predicted_plane_errors(T_world_body[station], sensors[sensor].T_body_sensor, p.n, p.d)
        i = index_of.get((station, sensor))
        chi2 = float(whitened_errors(problem.graph, values, [i])[0]) if i is not None else float("nan")
        out.append(StationResidual(station, sensor, a0, d0, a1, d1, chi2, (station, sensor) in outliers))
    return out


def flipped_normal_warnings(residuals) -> list[str]:
    """A warning per sensor with planes answered at more than 90 deg: their normals point away from
    the sensor, against the contract (n from the plane towards the sensor, d >= 0). The plane factor
    does not use the normal's sign, so the estimate stands, but the residual statistics read ~180 deg
    and the exporter has a sign error (an audit's flipped normals went unsaid; so did a few rows
    printed with the wrong sign, which left a 56 deg RMS normal residual without a word). The
    stations are named (numbered as in stations.csv), ten at most."""
    out = []
    for sensor in dict.fromkeys(r.sensor for r in residuals):
        rows = [r for r in residuals if r.sensor == sensor and not r.outlier and np.isfinite(r.angle_after_deg)]
        flipped = [int(r.station) for r in rows if r.angle_after_deg > 90.0]
        if not flipped:
            continue
        shown = ", ".join(map(str, flipped[:10])) + (f" and {len(flipped) - 10} more" if len(flipped) > 10 else "")
        out.append(f"{sensor}: {len(flipped)} of {len(rows)} plane normals point away from the sensor (answered at "
                   f"~180 deg; station {shown}): the contract's n points from the plane towards the sensor with "
                   "d >= 0; the estimate does not depend on that sign, but the residual angles do (their RMS "
                   "includes these rows) and the plane exporter has a sign error")
    return out
