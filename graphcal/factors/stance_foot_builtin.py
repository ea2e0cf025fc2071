"""Stance-foot factor with the legs held fixed, as GTSAM's built-in ``BearingRangeFactor3D``.

Variables: ``X`` = T_world_body (Pose3), ``F`` = p_world_foot (Point3). Measurement: ``p`` = FK(q)
(3,), m, the planted foot in the body frame predicted by the leg with its parameters held fixed,
and its covariance ``Sigma`` (3x3, m^2, body frame). Error: GTSAM's ``[local(u, u') (2, rad),
r' - r (1, m)]`` with ``u = p / |p|``, ``r = |p|`` and ``u'``, ``r'`` those of ``X^-1 F``; to first
order ``e_br = -J e`` (:func:`stance_foot_error_map`) of the Cartesian error of
:mod:`graphcal.factors.stance_foot`, with noise ``J Sigma J^T``. C++ instead of a Python callback:
the calibration graph's stance feet become several times cheaper to linearise. A foot within
:data:`MIN_RANGE_M` of the body origin is refused (the caller keeps the Python factor).

Why, the equivalence and the tests: docs/factors.md, "3b. stance_foot_builtin".
"""

from __future__ import annotations

import gtsam
import numpy as np

from graphcal.factors.checked import with_robust
from graphcal.factors.stance_foot import positive_definite_3x3

__all__ = ["MIN_RANGE_M", "stance_foot_error_map", "stance_foot_builtin_factor", "stance_foot_builtin_factors"]

#: a foot closer than this (m) to the body origin has no well-defined bearing
MIN_RANGE_M = 0.01


def _bearings(p_body_feet) -> tuple[np.ndarray, list, np.ndarray, np.ndarray]:
    """(P (F, 3), their bearings (gtsam.Unit3), ranges (F,), error maps J (F, 3, 3)) after checking P."""
    P = np.asarray(p_body_feet, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3 or not np.isfinite(P).all():
        raise ValueError(f"p_body_foot must be finite 3-vectors (m), got shape {P.shape}")
    r = np.sqrt(np.einsum("ij,ij->i", P, P))
    if (r < MIN_RANGE_M).any():
        near = float(r.min())
        raise ValueError(f"a foot is {1e3 * near:.3g} mm from the body origin (< {1e3 * MIN_RANGE_M:g} mm): "
                         "its bearing is undefined; use factors.stance_foot.stance_foot_factor")
    us = [gtsam.Unit3(p) for p in P]
    J = np.empty((len(P), 3, 3))
    J[:, :2] = np.stack([np.asarray(u.basis(), dtype=float).T for u in us]) / r[:, None, None]
    J[:, 2] = P / r[:, None]
    return P, us, r, J


def stance_foot_error_map(p_body_foot) -> np.ndarray:
    """J (3x3): the first-order map from a body-frame foot position error (m) to the error of
    :func:`stance_foot_builtin_factor` measured at ``p_body_foot`` (3,), m: rows ``B^T / r`` (rad/m)
    and ``u^T`` (module docstring). Raises ValueError for a foot within ``MIN_RANGE_M`` of the body
    origin."""
    return _bearings(np.reshape(np.asarray(p_body_foot, dtype=float), (1, -1)))[3][0]


def stance_foot_builtin_factors(x_key: int, f_keys, p_body_feet, cov_components: dict, *,
                                robust=None) -> tuple[list, dict]:
    """``gtsam.BearingRangeFactor3D`` on (X, F_j) for the planted feet of one station whose legs are
    held fixed (vectorised over the feet).

    Args:
        x_key: key of T_world_body (Pose3).
        f_keys: (F,) keys of the feet p_world_foot (Point3).
        p_body_feet: (F, 3) FK(q) of each foot, m, body frame.
        cov_components: name -> (F, 3, 3) covariances (m^2, body frame) whose sum is the noise of
            each foot's prediction (e.g. joint noise through the leg and contact noise,
            :func:`factors.stance_foot.joint_noise_covariance`).
        robust: optional gtsam mEstimator.

    Returns:
        (the F factors, name -> (F, 3, 3) each component mapped to the factors' error, ``J C J^T``).

    Raises:
        ValueError: a foot within ``MIN_RANGE_M`` of the body origin, or a noise sum that is not
            finite, symmetric positive definite.
    """
    P, us, r, J = _bearings(p_body_feet)
    f_keys = list(f_keys)
    if len(f_keys) != len(P):
        raise ValueError(f"{len(f_keys)} foot keys for {len(P)} feet")
    JT = np.swapaxes(J, 1, 2)
    mapped = {}
    for name, C in cov_components.items():
        C = np.asarray(C, dtype=float)
        if C.shape != (len(P), 3, 3) or not np.isfinite(C).all():
            raise ValueError(f"noise component {name!r} must be {len(P)} finite 3x3 matrices (m^2), got shape {C.shape}")
        M = J @ (0.5 * (C + np.swapaxes(C, 1, 2))) @ JT
        mapped[name] = 0.5 * (M + np.swapaxes(M, 1, 2))
    total = sum(mapped.values())
    if not all(positive_definite_3x3(C) for C in total):
        raise ValueError("the stance-foot noise must be symmetric positive definite")
    factors = [gtsam.BearingRangeFactor3D(x_key, f_key, u, float(ri),
                                          with_robust(gtsam.noiseModel.Gaussian.Covariance(cov), robust))
               for f_key, u, ri, cov in zip(f_keys, us, r, total)]
    return factors, mapped


def stance_foot_builtin_factor(x_key: int, f_key: int, p_body_foot, cov_m2, *, robust=None) -> gtsam.NonlinearFactor:
    """``gtsam.BearingRangeFactor3D`` on (X, F) for a planted foot whose leg is held fixed.

    Args:
        x_key: key of T_world_body (Pose3).
        f_key: key of p_world_foot (Point3).
        p_body_foot: (3,) FK(q), m, the foot in the body frame predicted by the leg.
        cov_m2: (3, 3) covariance (m^2, body frame) of that prediction's error (e.g.
            :func:`factors.stance_foot.joint_noise_covariance`); mapped to ``J cov J^T``.
        robust: optional gtsam mEstimator.

    Raises:
        ValueError: a foot within ``MIN_RANGE_M`` of the body origin, or a covariance that is not
            finite, symmetric positive definite 3x3.
    """
    P = np.reshape(np.asarray(p_body_foot, dtype=float), (1, -1))
    C = np.asarray(cov_m2, dtype=float)
    if C.shape != (3, 3):
        raise ValueError(f"cov_m2 must be a 3x3 matrix (m^2), got shape {C.shape}")
    return stance_foot_builtin_factors(x_key, [f_key], P, {"cov": C[None]}, robust=robust)[0][0]
