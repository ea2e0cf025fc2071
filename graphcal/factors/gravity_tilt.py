"""IMU attitude on a tilted floor: gravity is not normal to the ground the robot stands on.

The diagnosis catalogue's ``ground_tilt`` (graphcal/diagnosis). The calibration graph's world is the
ground: the feet stand on z = 0, the sensors see it, and the commanded poses are set relative to it.
On a tilted floor only gravity knows: the IMU's "up" is the level frame's z, which in the ground
frame is ``W e_z`` with ``W = R_ground_level`` (Rot3; a floor tilted by ``R_tilt`` in the level world
has ``W = R_tilt^T``). Rotation of W about e_z is not observable (pin it with a prior).

Variables: X = T_world_body (Pose3, world = ground), M = R_body_imu (Rot3), W = R_ground_level (Rot3).
Error (2): that of imu_attitude.py's misaligned factor for the body attitude in the level frame,
``R'_x = W^T R_x``: ``e = B_m^T (R'_x R_bi)^T e_z``. Jacobians: X and M as there (with R'_x);
a right perturbation ``phi`` of W turns R'_x by ``Exp(-phi)`` on the left, i.e. by
``-R'_x^T phi`` on the right, so ``H_W = -H_X[:, :3] R'_x^T``.
"""

from __future__ import annotations

import gtsam
import numpy as np

from graphcal.factors.checked import checked_custom_factor
from graphcal.factors.imu_attitude import DEFAULT_SIGMA_RAD, attitude_noise_model, imu_attitude_misaligned_error, imu_up_direction

__all__ = ["imu_attitude_tilted_error", "imu_attitude_tilted_factor"]


def imu_attitude_tilted_error(T_world_body, R_body_imu, R_ground_level, f_imu, want_jacobians: bool = True):
    """Attitude error of an IMU on a tilted floor, and analytic Jacobians (pure numpy).

    Args:
        T_world_body: 4x4 body pose X (world = ground frame).
        R_body_imu: 3x3 IMU mounting rotation M.
        R_ground_level: 3x3 W, the level (gravity) frame in the ground frame.
        f_imu: (3,) specific force in the IMU frame (direction only).

    Returns:
        e (2,) rad and ``[H_X (2,6), H_M (2,3), H_W (2,3)]`` or None.
    """
    X = np.asarray(T_world_body, dtype=float)
    W = np.asarray(R_ground_level, dtype=float)
    Xl = X.copy()
    Xl[:3, :3] = W.T @ X[:3, :3]
    e, H = imu_attitude_misaligned_error(Xl, R_body_imu, f_imu, want_jacobians)
    if H is None:
        return e, None
    H_X, H_M = H
    H_W = -H_X[:, :3] @ Xl[:3, :3].T
    return e, [H_X, H_M, H_W]


def imu_attitude_tilted_factor(x_key: int, m_key: int, w_key: int, f_imu, sigma_rad: float = DEFAULT_SIGMA_RAD, *,
                               robust=None) -> gtsam.NonlinearFactor:
    """Custom factor on (X, M, W) from an accelerometer at rest on a possibly tilted floor."""
    m = imu_up_direction(f_imu)
    m.setflags(write=False)

    def error_fn(X, M, W, want):
        return imu_attitude_tilted_error(X, M, W, m, want)

    return checked_custom_factor(attitude_noise_model(sigma_rad, robust), [x_key, m_key, w_key], error_fn, [6, 3, 3], 2,
                                 kinds=["Pose3", "Rot3", "Rot3"], name="imu_attitude_tilted")
