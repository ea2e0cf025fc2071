"""Prior factors (GTSAM built-ins): CAD extrinsics, commanded body poses, leg parameters.

Pose priors use GTSAM's ``PriorFactorPose3`` whose error is ``Logmap(T_prior^-1 T)`` in the
tangent order ``[omega, v]`` (right perturbation): sigmas are therefore ordered
``[rot, rot, rot, trans, trans, trans]`` (rad, rad, rad, m, m, m), rotation and translation both
expressed in the variable's own (body / sensor) frame.
"""

from __future__ import annotations

import gtsam
import numpy as np

from graphcal.geometry import is_rotation, to_gtsam_pose

__all__ = [
    "DEFAULT_CMD_SIGMA_RAD",
    "DEFAULT_CMD_SIGMA_M",
    "pose_prior_sigmas",
    "extrinsic_prior",
    "commanded_pose_prior",
    "leg_offset_prior",
]

#: default rotation sigma of a commanded body pose (rad): 1 deg
DEFAULT_CMD_SIGMA_RAD = float(np.deg2rad(1.0))
#: default translation sigma of a commanded body pose (m): 1 cm
DEFAULT_CMD_SIGMA_M = 0.01


def _as_pose3(T) -> gtsam.Pose3:
    if isinstance(T, gtsam.Pose3):
        return T
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"pose must be a finite 4x4 matrix or a gtsam.Pose3, got shape {T.shape}")
    if not is_rotation(T[:3, :3]):
        raise ValueError("pose rotation block is not a rotation matrix")
    return to_gtsam_pose(T)


def _sigmas(x, n: int, what: str) -> np.ndarray:
    s = np.asarray(x, dtype=float)
    s = np.full(n, float(s)) if s.ndim == 0 else s.reshape(-1)
    if s.shape != (n,) or not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise ValueError(f"{what} must be a positive scalar or {n} positive numbers, got {x!r}")
    return s


def pose_prior_sigmas(sigma_m, sigma_rad) -> np.ndarray:
    """(6,) sigmas ``[rot x3 (rad), trans x3 (m)]`` from scalars or 3-vectors."""
    return np.concatenate([_sigmas(sigma_rad, 3, "sigma_rad"), _sigmas(sigma_m, 3, "sigma_m")])


def extrinsic_prior(key: int, T_cad, sigma_m, sigma_rad) -> gtsam.PriorFactorPose3:
    """Prior on a sensor extrinsic T_body_sensor at its CAD value.

    Args:
        key: key of T_body_sensor (Pose3).
        T_cad: 4x4 (or gtsam.Pose3) CAD pose of the sensor in the body frame.
        sigma_m: translation sigma(s), m (scalar or 3, sensor frame axes).
        sigma_rad: rotation sigma(s), rad (scalar or 3, sensor frame axes).
    """
    return gtsam.PriorFactorPose3(key, _as_pose3(T_cad), gtsam.noiseModel.Diagonal.Sigmas(pose_prior_sigmas(sigma_m, sigma_rad)))


def commanded_pose_prior(
    key: int,
    T_cmd,
    sigma_rad=DEFAULT_CMD_SIGMA_RAD,
    sigma_m=DEFAULT_CMD_SIGMA_M,
) -> gtsam.PriorFactorPose3:
    """Prior on a body pose T_world_body at its commanded value.

    Defaults: 1 deg and 1 cm. The servos hold the set pose within their tracking error, but the
    commanded pose is computed with the nominal kinematics: joint offsets and link-length errors
    move the real body by mm to cm and tilt it by a fraction of a degree, so the command is only a
    weak prior that the sensor and leg factors must be able to override.
    """
    return gtsam.PriorFactorPose3(key, _as_pose3(T_cmd), gtsam.noiseModel.Diagonal.Sigmas(pose_prior_sigmas(sigma_m, sigma_rad)))


def leg_offset_prior(key: int, dim: int, sigmas) -> gtsam.PriorFactorVector:
    """Zero-mean prior on a leg parameter vector (Vector of ``dim``): the nominal URDF.

    Args:
        key: key of theta_leg.
        dim: number of leg parameters k.
        sigmas: scalar or (k,) sigmas in the parameters' units (rad for offsets, m for link deltas;
            :meth:`graphcal.models.legs.LegModel.prior_sigmas` builds them).
    """
    dim = int(dim)
    if dim < 1:
        raise ValueError(f"dim must be >= 1, got {dim}")
    return gtsam.PriorFactorVector(key, np.zeros(dim), gtsam.noiseModel.Diagonal.Sigmas(_sigmas(sigmas, dim, "sigmas")))
