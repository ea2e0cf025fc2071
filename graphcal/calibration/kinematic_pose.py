"""The body pose from the stance feet (Chai 2015 section 4.2; Łabęcki's "kinematic height").

With every foot planted on level ground, the feet seen from the body (forward kinematics of the
measured joint angles) lie on the ground plane. A plane through them gives, in the body frame, the
ground's up direction ``u_body = R_world_bodyᵀ e_z`` and the body height above the ground; together
they fix roll, pitch and height. x, y and yaw are not seen by the feet of a single stance (they are
the gauge of the problem) and come from the commanded pose when the dataset has one.
"""

from __future__ import annotations

import numpy as np

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
