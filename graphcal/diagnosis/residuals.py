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

from graphcal.geometry import from_gtsam_pose

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


def _kinematic_body(model, problem, values, st) -> np.ndarray | None:
    """T_world_body the model predicts from proprioception alone: the plane through the feet (forward
    kinematics with the model's leg parameters) gives roll, pitch and height; x, y, yaw come from the
    commanded pose. None without three legs."""
    from graphcal.calibration.kinematic_pose import ground_from_feet, initial_body_pose, leg_kinematics
    from graphcal.models.legs import fk_with_params

    if len(st.q_by_foot) < 3:
        return None
    kin = leg_kinematics(model.data, model.robot)
    feet = []
    for f, q in st.q_by_foot.items():
        if f in problem.leg_keys:
            key, param = problem.leg_keys[f]
            feet.append(fk_with_params(model.robot.leg(f), param, q, np.asarray(values.atVector(key))))
        else:
            feet.append(kin[(st.station, f)][0])
    u, h = ground_from_feet(np.array(feet))
    return initial_body_pose(u, h, st.T_world_body_cmd)


def residual_records(model, problem, values) -> tuple[ResidualRecord, ...]:
    """One record per sensor measurement. Planes: theta and e_d of the plane the model PREDICTS from
    the legs alone (the kinematic body pose, the model's extrinsic, range scale and the ground that
    station's session sees) against the measured one -- the fitted body poses would absorb most of a
    discrepancy. Scans: the fitted range residual's RMS."""
    from graphcal.factors.plane_observation import plane_angle_distance_error
    from graphcal.solvers.batch import whitened_errors

    order = {st.station: (j, st.session) for j, st in enumerate(model.data.stations)}
    by_station = {st.station: st for st in model.data.stations}
    idx = list(problem.plane_factors)
    chi = whitened_errors(problem.graph, values, idx)
    ek = problem.extension_keys
    out = []
    for i, c in zip(idx, chi):
        st, s = problem.plane_factors[i]
        j, session = order[st]
        T_fit = from_gtsam_pose(values.atPose3(problem.station_keys[st]))
        T_kin = _kinematic_body(model, problem, values, by_station[st])
        T_wb = T_kin if T_kin is not None else T_fit
        T_bs = from_gtsam_pose(values.atPose3(problem.measurement_keys[(st, s)]))
        tilt = float(np.degrees(np.arccos(np.clip(T_fit[2, 2], -1.0, 1.0))))
        if (st, s) in model.data.planes:
            p = model.data.planes[(st, s)]
            g = ek.get(f"session_offset:{session}")
            plane_w = np.asarray(values.atOrientedPlane3(g).planeCoefficients()) if g is not None else None
            scale = float(values.atVector(ek[f"range_scale:{s}"])[0]) if f"range_scale:{s}" in ek else 1.0
            a, d = plane_angle_distance_error(T_wb @ T_bs, p.n, p.d / scale, plane_w)
            ang, dist, rng = float(np.degrees(a)), float(1e3 * d * scale), float(p.d)
        else:
            from graphcal.factors.range_scale import scaled_range_error

            pts = model.data.scan_points[(st, s)]
            scale = float(values.atVector(ek[f"range_scale:{s}"])[0]) if f"range_scale:{s}" in ek else 1.0
            e, _ = scaled_range_error(T_wb, T_bs, scale, pts, want_jacobians=False)
            ang, dist, rng = float("nan"), float(1e3 * np.sqrt(np.mean(e**2))), float(np.median(np.linalg.norm(pts, axis=1)))
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
    from graphcal.solvers.batch import whitened_errors

    order = {st.station: j for j, st in enumerate(model.data.stations)}
    x_station = {int(k): st for st, k in problem.station_keys.items()}
    from graphcal.calibration.graph import planted_foot_index
    from graphcal.factors.keys import F

    foot_of = {int(F(j)): f for (_, f), j in planted_foot_index(model.data, model.robot).items()}
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
