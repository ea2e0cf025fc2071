"""The body pose from the stance feet (Chai 2015 section 4.2; Łabęcki's "kinematic height").

With every foot planted on level ground, the feet seen from the body (forward kinematics of the
measured joint angles) lie on the ground plane. A plane through them gives, in the body frame, the
ground's up direction ``u_body = R_world_bodyᵀ e_z`` and the body height above the ground; together
they fix roll, pitch and height. x, y and yaw are not seen by the feet of a single stance (they are
the gauge of the problem) and come from the commanded pose when the dataset has one.
"""

from __future__ import annotations

import weakref

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.geometry import matrix_from_axis_angle, pose_matrix, rot_z


def feet_in_body(robot, q_by_foot: dict) -> np.ndarray:
    """(F, 3) positions p_body_foot (m) of the feet that have joint angles, in ``robot.feet`` order."""
    from graphcal.models.kinematics import foot_positions

    return np.array([foot_positions(robot.leg(f), q) for f, q in q_by_foot.items()])


def ground_from_feet(p_body_foot: np.ndarray) -> tuple[np.ndarray, float]:
    """(u_body, height_m): the up direction of the plane through the feet, in the body frame, and the
    body origin's distance above it. Needs >= 3 feet not on a line."""
    P = np.asarray(p_body_foot, dtype=float)
    c = P.mean(axis=0)
    _, _, Vt = np.linalg.svd(P - c)
    u = Vt[2]
    if u @ (-c) < 0:  # up points from the feet towards the body origin
        u = -u
    return u, float(u @ (-c))


def tilt_rotation_to_up(u_body: np.ndarray) -> np.ndarray:
    """The smallest rotation R with R @ u_body = e_z (a body pose with zero yaw about world z)."""
    u = np.asarray(u_body, dtype=float) / np.linalg.norm(u_body)
    ez = np.array([0.0, 0.0, 1.0])
    axis = np.cross(u, ez)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        return np.eye(3) if u[2] > 0 else np.diag([1.0, -1.0, -1.0])
    return matrix_from_axis_angle(axis, float(np.arctan2(s, u @ ez)))


def initial_body_pose(u_body: np.ndarray, height_m: float, T_world_body_cmd: np.ndarray | None = None) -> np.ndarray:
    """T_world_body with roll/pitch from ``u_body``, height from the feet, and x, y, yaw from the
    commanded pose (0 without one)."""
    R_tilt = tilt_rotation_to_up(u_body)
    if T_world_body_cmd is not None:
        R_cmd = T_world_body_cmd[:3, :3]
        x_axis = R_cmd[:, 0]
        yaw = float(np.arctan2(x_axis[1], x_axis[0]))
        # yaw of the tilted frame's x axis, corrected so that the result's x axis has the commanded heading
        x_tilt = R_tilt[:, 0]
        yaw -= float(np.arctan2(x_tilt[1], x_tilt[0]))
        xy = T_world_body_cmd[:2, 3]
    else:
        yaw, xy = 0.0, np.zeros(2)
    return pose_matrix(rot_z(yaw) @ R_tilt, [xy[0], xy[1], height_m])


#: per CalibrationData (weakly held): the leg kinematics and the kinematic body poses, computed once
#: (graphs are rebuilt many times by the noise estimation and the diagnosis)
_LEG_CACHE: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def leg_kinematics(data, robot) -> dict:
    """(station, foot) -> (p_body_foot (3,) m, J (3, n) position Jacobian, m per joint unit) of the
    measured joint angles of ``data`` (a :class:`~graphcal.calibration.measurements.CalibrationData`)
    on the nominal legs of ``robot``, computed once per (data, robot) and cached (graphs are rebuilt
    many times by the noise estimation and the diagnosis)."""
    from graphcal.models.kinematics import foot_positions, leg_jacobian

    per_data = _LEG_CACHE.setdefault(data, {})
    out = per_data.get(id(robot))
    if out is None or out[0] is not robot:
        by_foot: dict = {}
        for st in data.stations:
            for f, q in st.q_by_foot.items():
                by_foot.setdefault(f, []).append((st.station, q))
        table = {}
        for f, items in by_foot.items():  # one batch per leg (the kinematics is vectorised)
            leg = robot.leg(f)
            Q = np.array([np.asarray(q, dtype=float) for _, q in items])
            P, J = foot_positions(leg, Q), leg_jacobian(leg, Q)
            P.flags.writeable = J.flags.writeable = False  # shared by every graph built from the cache
            for k, (station, _) in enumerate(items):
                table[(station, f)] = (P[k], J[k])
        out = (robot, table)
        per_data[id(robot)] = out
    return out[1]


def leg_parameter_kinematics(data, robot, foot: str, param) -> dict:
    """station -> (theta0 (k,) zeros, p_base_foot (3,) m, d p_base_foot / d theta (3, k)) of the
    measured joint angles of ``foot`` in ``data`` at the nominal parameters of ``param`` (its
    :class:`~graphcal.models.legs.LegModel`): what a stance factor estimating the leg evaluates at
    its first linearisation; one batch per leg, cached with :func:`leg_kinematics` (the arrays
    read-only)."""
    from graphcal.models.legs import fk_and_param_jacobian

    per_data = _LEG_CACHE.setdefault(data, {})
    # the parameters' geometry, not only their names (two parameterisations could share names)
    key = ("parameters", id(robot), foot, param.names, param.offset_joints, param.trans_joints,
           np.asarray(param.trans_dirs, float).tobytes())
    out = per_data.get(key)
    if out is None or out[0] is not robot:
        items = [(st.station, q) for st in data.stations for f, q in st.q_by_foot.items() if f == foot]
        theta0 = param.zeros()
        table = {}
        if items:
            P, J = fk_and_param_jacobian(robot.leg(foot), param, np.array([np.asarray(q, float) for _, q in items]),
                                         theta0)
            theta0.flags.writeable = P.flags.writeable = J.flags.writeable = False
            table = {station: (theta0, P[k], J[k]) for k, (station, _) in enumerate(items)}
        out = (robot, table)
        per_data[key] = out
    return out[1]


def kinematic_bodies(data, robot) -> tuple[dict, dict, dict]:
    """Three dicts keyed by station id: ``u_body`` (3,) the ground's up direction in the body frame,
    the body origin's height above the ground (m), and the initial ``T_world_body`` (4x4, m), from
    the stance feet (or the commanded pose) of ``data`` (a
    :class:`~graphcal.calibration.measurements.CalibrationData`); cached with
    :func:`leg_kinematics` (new dicts each call, the arrays read-only)."""
    per_data = _LEG_CACHE.setdefault(data, {})
    out = per_data.get(("bodies", id(robot)))
    if out is None or out[0] is not robot:
        out = (robot, _compute_kinematic_bodies(data, robot))
        per_data[("bodies", id(robot))] = out
    return tuple(dict(d) for d in out[1])


def _compute_kinematic_bodies(data, robot) -> tuple[dict, dict, dict]:
    out_u, out_h, out_T = {}, {}, {}
    kin = leg_kinematics(data, robot)
    for st in data.stations:
        if len(st.q_by_foot) >= 3:
            u, h = ground_from_feet(np.array([kin[(st.station, f)][0] for f in st.q_by_foot]))
            T = initial_body_pose(u, h, st.T_world_body_cmd if st.T_world_body_cmd is not None
                                  else st.T_world_body_start)
        elif st.T_world_body_cmd is not None:
            T = st.T_world_body_cmd
            u, h = T[:3, :3].T @ np.array([0.0, 0.0, 1.0]), float(T[2, 3])
        else:
            raise GraphcalError(
                f"station {st.station}: fewer than 3 legs with joint angles and no commanded pose; "
                "the body pose cannot be known"
            )
        u, T = np.array(u, dtype=float), np.array(T, dtype=float)
        u.flags.writeable = T.flags.writeable = False
        out_u[st.station], out_h[st.station], out_T[st.station] = u, float(h), T
    return out_u, out_h, out_T
