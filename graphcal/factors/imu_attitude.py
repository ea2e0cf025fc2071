"""IMU attitude factors: the accelerometer at rest measures "up", which fixes roll and pitch.

At rest the accelerometer measures the specific force ``f = R_world_imu^T (0, 0, +g)``: it points
UP (away from the ground) in the sensor frame, not along gravity. Its direction therefore gives
the world's up direction in the IMU frame; yaw is unobservable from it.

1. :func:`imu_attitude_factor` -- IMU rigidly at a KNOWN rotation ``R_body_imu`` (identity for the
   built-in models): GTSAM's built-in ``AttitudeFactorPose3(X, nRef = up (0, 0, 1) in the world,
   bMeasured = Unit3(R_body_imu f / |f|))``, whose error is ``B_ref^T (R_x b_meas)`` (2) with
   ``B_ref`` the Unit3 basis of ``(0, 0, 1)``. :func:`imu_attitude_error` is its numpy twin (for
   reports and tests): ``H_X = [-B_ref^T R_x [b]x, 0]``.

2. :func:`imu_attitude_misaligned_factor` -- the IMU mounting rotation is a variable
   ``M = R_body_imu`` (Rot3). Predicted up in the IMU frame ``u_i = (R_x R_bi)^T e_z``; error (2)
   ``e = B_m^T u_i`` with ``B_m = tangent_basis(f / |f|)`` (rad, to first order). Jacobians: a
   right perturbation ``phi`` of ``R_wi = R_x R_bi`` gives ``d u_i = [u_i]x phi``; X's rotation
   perturbation ``omega`` is ``R_bi^T omega`` for ``R_wi`` (``R_x Exp(omega) R_bi =
   R_wi Exp(R_bi^T omega)``) and M's is ``phi`` itself, so ``H_X = [B_m^T [u_i]x R_bi^T, 0]``
   (translation columns zero) and ``H_M = B_m^T [u_i]x``. ``u_i = -f/|f|`` also zeroes the
   error: start within 90 deg of the truth.

Noise: isotropic on the 2 error components, default ``sigma_rad = 0.5 deg``: the static accuracy
of an AHRS's roll/pitch as used by Łabęcki et al.; with a station-averaged accelerometer the
white noise averages out and the residual accelerometer bias (~0.01 g, i.e. ~0.5 deg of tilt)
dominates, so averaging longer does not help below that.
"""

from __future__ import annotations

import gtsam
import numpy as np

from graphcal.factors.checked import checked_custom_factor, tangent_basis, with_robust
from graphcal.geometry import is_rotation, skew

__all__ = [
    "DEFAULT_SIGMA_RAD",
    "attitude_noise_model",
    "imu_up_direction",
    "imu_attitude_error",
    "imu_attitude_factor",
    "imu_attitude_misaligned_error",
    "imu_attitude_misaligned_factor",
]

#: default sigma of each attitude error component (rad): 0.5 deg, an AHRS's static roll/pitch accuracy
DEFAULT_SIGMA_RAD = float(np.deg2rad(0.5))

_UP_W = np.array([0.0, 0.0, 1.0])


def imu_up_direction(f_imu) -> np.ndarray:
    """Unit "up" direction in the IMU frame from a (station-averaged) specific force f (3,), m/s^2.

    Raises:
        ValueError: f is not 3 finite numbers, or is (near) zero (free fall, a bad average).
    """
    f = np.asarray(f_imu, dtype=float).reshape(-1)
    if f.shape != (3,) or not np.all(np.isfinite(f)):
        raise ValueError(f"f_imu must be 3 finite numbers (m/s^2), got {f_imu!r}")
    n = np.linalg.norm(f)
    if n < 1e-6:
        raise ValueError(f"f_imu is (near) zero, |f| = {n}: no up direction")
    return f / n


def _check_rotation(R, what: str) -> np.ndarray:
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError(f"{what} must be a finite 3x3 rotation, got shape {R.shape}")
    if not is_rotation(R):
        raise ValueError(f"{what} is not a rotation matrix")
    return R


def attitude_noise_model(sigma_rad: float, robust):
    """Isotropic 2-D noise model (rad) of an attitude error (the two tilt angles), optionally robust.

    Args:
        sigma_rad: sigma of each tilt angle, rad (> 0).
        robust: optional gtsam mEstimator (None: Gaussian).
    """
    if not np.isfinite(sigma_rad) or sigma_rad <= 0:
        raise ValueError(f"sigma_rad must be > 0, got {sigma_rad}")
    return with_robust(gtsam.noiseModel.Isotropic.Sigma(2, float(sigma_rad)), robust)


def imu_attitude_error(T_world_body, f_imu, R_body_imu=None, want_jacobians: bool = True):
    """Error of GTSAM's ``AttitudeFactorPose3`` as built by :func:`imu_attitude_factor` (pure numpy).

    Returns:
        e (2,) = ``B_ref^T R_x b`` with ``b = R_body_imu f/|f|`` (rad, first order), and ``[H_X (2,6)]``.
    """
    X = np.asarray(T_world_body, dtype=float)
    R_bi = np.eye(3) if R_body_imu is None else np.asarray(R_body_imu, dtype=float)
    b = R_bi @ imu_up_direction(f_imu)
    B = tangent_basis(_UP_W)
    R_x = X[:3, :3]
    e = B.T @ (R_x @ b)
    if not want_jacobians:
        return e, None
    H_X = np.zeros((2, 6))
    H_X[:, :3] = -B.T @ R_x @ skew(b)
    return e, [H_X]


def imu_attitude_factor(
    x_key: int,
    f_imu,
    sigma_rad: float = DEFAULT_SIGMA_RAD,
    *,
    R_body_imu=None,
    robust=None,
) -> gtsam.NonlinearFactor:
    """Built-in ``gtsam.AttitudeFactorPose3`` on X from an accelerometer at rest.

    Args:
        x_key: key of T_world_body (Pose3).
        f_imu: (3,) specific force measured in the IMU frame (station average), m/s^2; points up.
        sigma_rad: sigma of each of the 2 error components (default 0.5 deg).
        R_body_imu: known 3x3 IMU mounting rotation (default identity).
        robust: optional gtsam mEstimator.
    """
    R_bi = np.eye(3) if R_body_imu is None else _check_rotation(R_body_imu, "R_body_imu")
    b = R_bi @ imu_up_direction(f_imu)
    return gtsam.AttitudeFactorPose3(x_key, gtsam.Unit3(_UP_W.copy()), attitude_noise_model(sigma_rad, robust), gtsam.Unit3(b))


def imu_attitude_misaligned_error(T_world_body, R_body_imu, f_imu, want_jacobians: bool = True):
    """Attitude error with an unknown IMU mounting rotation, and analytic Jacobians (pure numpy).

    Args:
        T_world_body: 4x4 body pose X.
        R_body_imu: 3x3 IMU mounting rotation M.
        f_imu: (3,) specific force in the IMU frame (any scale; only its direction is used).

    Returns:
        e (2,) = ``B_m^T (R_x R_bi)^T e_z`` (rad, first order), and ``[H_X (2,6), H_M (2,3)]`` or None.
    """
    return _misaligned_error(np.asarray(T_world_body, dtype=float), np.asarray(R_body_imu, dtype=float),
                             tangent_basis(imu_up_direction(f_imu)).T, want_jacobians)


def _misaligned_error(X: np.ndarray, R_bi: np.ndarray, BT: np.ndarray, want_jacobians: bool):
    """:func:`imu_attitude_misaligned_error` given ``BT`` (2, 3), the transposed tangent basis of the
    measured up direction (a constant of the factor, computed once)."""
    R_wi = X[:3, :3] @ R_bi
    u = R_wi.T @ _UP_W
    e = BT @ u
    if not want_jacobians:
        return e, None
    H_M = BT @ skew(u)
    H_X = np.zeros((2, 6))
    H_X[:, :3] = H_M @ R_bi.T
    return e, [H_X, H_M]


def imu_attitude_misaligned_factor(
    x_key: int,
    m_key: int,
    f_imu,
    sigma_rad: float = DEFAULT_SIGMA_RAD,
    *,
    robust=None,
) -> gtsam.NonlinearFactor:
    """Custom factor on (X, M = R_body_imu) from an accelerometer at rest.

    Args:
        x_key: key of T_world_body (Pose3).
        m_key: key of R_body_imu (Rot3).
        f_imu: (3,) specific force in the IMU frame (station average), m/s^2; points up.
        sigma_rad: sigma of each of the 2 error components (default 0.5 deg).
        robust: optional gtsam mEstimator.
    """
    BT = np.ascontiguousarray(tangent_basis(imu_up_direction(f_imu)).T)
    BT.setflags(write=False)

    def error_fn(X, M, want):
        return _misaligned_error(X, M, BT, want)

    return checked_custom_factor(
        attitude_noise_model(sigma_rad, robust), [x_key, m_key], error_fn, [6, 3], 2, kinds=["Pose3", "Rot3"],
        name="imu_attitude_misaligned",
    )
