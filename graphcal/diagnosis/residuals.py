"""Per-measurement residual records of a fitted model, with the covariates that reveal causes.

Each sensor measurement (plane or scan) gives one :class:`ResidualRecord`: its station, session,
sensor, Chai's angle error theta (deg) and distance error e_d (mm) for planes (the RMS range residual
for scans), the measured range (plane distance d, m) and the body tilt (deg). The diagnosis plots
draw these against the covariate of each finding (station index for a knock, session for an offset,
range for a scale, body tilt for a tilt or an IMU misalignment), before and after.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import from_gtsam_pose

__all__ = ["ResidualRecord", "StanceRecord", "residual_records", "stance_records"]


@dataclass(frozen=True)
class ResidualRecord:
    station: int
    index: int
    session: str
    sensor: str
    angle_deg: float
    distance_mm: float
    range_m: float
    tilt_deg: float
    whitened: float


def residual_records(model, problem, values) -> tuple[ResidualRecord, ...]:
    from factors.plane_observation import plane_angle_distance_error

    from ..solvers.batch import whitened_errors

    order = {st.station: (j, st.session) for j, st in enumerate(model.data.stations)}
    idx = list(problem.plane_factors)
    chi = whitened_errors(problem.graph, values, idx)
    out = []
    for i, c in zip(idx, chi):
        st, s = problem.plane_factors[i]
        T_wb = from_gtsam_pose(values.atPose3(problem.station_keys[st]))
        T_bs = from_gtsam_pose(values.atPose3(problem.measurement_keys[(st, s)]))
        tilt = float(np.degrees(np.arccos(np.clip(T_wb[2, 2], -1.0, 1.0))))
        if (st, s) in model.data.planes:
            p = model.data.planes[(st, s)]
            a, d = plane_angle_distance_error(T_wb @ T_bs, p.n, p.d)
            ang, dist, rng = float(np.degrees(a)), float(1e3 * d), float(p.d)
        else:
            e = np.asarray(problem.graph.at(i).unwhitenedError(values))
            pts = model.data.scan_points[(st, s)]
            ang, dist, rng = float("nan"), float(1e3 * np.sqrt(np.mean(e**2))), float(np.median(np.linalg.norm(pts, axis=1)))
        j, session = order[st]
        out.append(ResidualRecord(int(st), j, session, s, ang, dist, rng, tilt, float(np.sqrt(c / problem.graph.at(i).dim()))))
    return tuple(out)


@dataclass(frozen=True)
class StanceRecord:
    """Whitened RMS of one stance-foot factor (a leg's kinematics against its planted foot)."""

    station: int
    index: int
    leg: str
    whitened: float


def stance_records(model, problem, values) -> tuple[StanceRecord, ...]:
    from ..solvers.batch import whitened_errors

    order = {st.station: j for j, st in enumerate(model.data.stations)}
    x_station = {int(k): st for st, k in problem.station_keys.items()}
    from factors.keys import F

    foot_of = {}
    sessions = list(dict.fromkeys(st.session for st in model.data.stations))
    j = 0
    for s in sessions:
        for f in model.robot.feet:
            foot_of[int(F(j))] = f
            j += 1
    idx = [i for i, g in problem.factor_groups.items() if g == "stance_foot"]
    chi = whitened_errors(problem.graph, values, idx)
    out = []
    for i, c in zip(idx, chi):
        keys = [int(k) for k in problem.graph.at(i).keys()]
        st = next((x_station[k] for k in keys if k in x_station), None)
        leg = next((foot_of[k] for k in keys if k in foot_of), "?")
        if st is not None:
            out.append(StanceRecord(int(st), order[st], leg, float(np.sqrt(c / 3.0))))
    return tuple(out)
