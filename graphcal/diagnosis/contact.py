"""Screening columns of the shared-parameter leg causes: one foot radius, one compliance per joint type.

Both change where the leg's kinematics put the foot (factors/stance_contact.py): the foot radius
``r`` by ``r (a_b - n_b)`` (the lower leg's direction minus the ground normal, body frame), the
compliance ``k`` of joint index ``j`` by ``k * lever * dFK/dq_j``. Every stance-foot factor's error
depends on the predicted foot ``FK`` against ``p_b = R_x^T (F - t_x)``, so to first order a change
``delta`` of ``FK`` acts on the factor like moving the planted foot ``F`` by ``-R_x delta``: the
candidate's column on the rows of the stance-foot factor of (station, foot) is

    K = A[rows, F's columns] @ (-R_x delta / unit parameter)

built from the screening linearisation without new variables (the builtin bearing-range form of
the factor included). One parameter explains every leg: these are the parsimonious alternatives to
a joint offset per leg or a link length per leg (docs/diagnosis.md "Parsimony").
"""

from __future__ import annotations

import numpy as np

from graphcal.diagnosis.catalogue import Candidate
from graphcal.diagnosis.scores import CandidateColumns

__all__ = ["contact_candidates"]


def _stance_rows(model, problem, system):
    """[(rows, station, foot, F key)] of every stance-foot factor in the system."""
    from graphcal.factors.keys import F

    x_station = {int(k): st for st, k in problem.station_keys.items()}
    from graphcal.calibration.graph import planted_foot_index

    foot_of = {int(F(j)): f for (_, f), j in planted_foot_index(model.data, model.robot).items()}
    rows_of: dict[int, list] = {}
    stance = {i for i, g in problem.factor_groups.items() if g == "stance_foot"}
    for r, i in enumerate(system.row_factor):
        if int(i) in stance:
            rows_of.setdefault(int(i), []).append(r)
    out = []
    for i, rows in rows_of.items():
        keys = [int(k) for k in problem.graph.at(i).keys()]
        st = next((x_station[k] for k in keys if k in x_station), None)
        fk = next((k for k in keys if k in foot_of), None)
        if st is not None and fk is not None:
            out.append((np.array(rows), st, foot_of[fk], fk))
    return out


def contact_candidates(model, problem, system, values) -> list[CandidateColumns]:
    """The ``foot_radius`` candidate and one ``joint_compliance`` candidate per joint index (every
    leg's joint at that index shares one constant), as dense columns of the screening ``system``
    (problem solved at ``values``); none once either is in the model."""
    from graphcal.calibration.kinematic_pose import leg_kinematics
    from graphcal.geometry import from_gtsam_pose

    if model.found("foot_radius") or model.found("joint_compliance"):
        return []
    table = _stance_rows(model, problem, system)
    if not table:
        return []
    station_of = {st.station: st for st in model.data.stations}
    kin = leg_kinematics(model.data, model.robot)
    a_of = _lower_legs(model.robot, station_of, table)
    n_joints = min(model.robot.leg(f).n_joints for f in model.robot.feet)
    n = len(system.b)
    K_r = np.zeros((n, 1))
    K_k = np.zeros((n, n_joints))
    for rows, st, foot, fk in table:
        o, d = system.col[fk]
        A_F = system.A[np.ix_(rows, np.arange(o, o + d))]
        R_x = from_gtsam_pose(values.atPose3(problem.station_keys[st]))[:3, :3]
        station = station_of[st]
        n_b = R_x.T @ np.array([0.0, 0.0, 1.0])
        K_r[rows, 0] = A_F @ (-R_x @ (a_of[(st, foot)] - n_b))
        J = kin[(st, foot)][1]  # the cached nominal leg Jacobian at the measured angles
        R_cmd = station.T_world_body_cmd[:3, :3] if station.T_world_body_cmd is not None else np.eye(3)
        levers = J.T @ (R_cmd.T @ np.array([0.0, 0.0, 1.0]))  # compliance_lever of every joint at once
        K_k[rows] = A_F @ (-R_x @ (J[:, :n_joints] * levers[:n_joints]))
    out = [CandidateColumns(Candidate("foot_radius", (), 1), None, None, K_r)]
    for j in range(n_joints):
        joints = sorted({model.robot.leg(f).joint_names[j] for f in model.robot.feet})
        out.append(CandidateColumns(Candidate("joint_compliance", (("joint_index", j), ("joints", _common(joints))),
                                              n_joints), None, None, K_k[:, [j]]))
    return out


def _lower_legs(robot, station_of: dict, table) -> dict:
    """(station, foot) -> the lower leg's direction (body frame) at the measured angles, for every
    stance foot of ``table`` (:func:`_stance_rows`; ``station_of``: station id -> its Station);
    one batch per leg."""
    from graphcal.factors.stance_contact import lower_leg_directions

    by_foot: dict = {}
    for _, st, foot, _ in table:
        by_foot.setdefault(foot, []).append(st)
    out = {}
    for foot, stations in by_foot.items():
        Q = np.array([np.asarray(station_of[st].q_by_foot[foot], dtype=float) for st in stations])
        out.update(zip(((st, foot) for st in stations), lower_leg_directions(robot.leg(foot), Q)))
    return out


def _common(names: list) -> str:
    """A name for the joints at one index of every leg: their common suffix after the leg prefix
    (``lf_femur_joint``, ``rr_femur_joint`` -> ``femur_joint``), else the first name."""
    tails = {n.split("_", 1)[1] if "_" in n else n for n in names}
    return tails.pop() if len(tails) == 1 else names[0]
