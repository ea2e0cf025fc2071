"""Stance-foot factor: a planted foot seen through the leg's kinematics from the body.

Variables: ``X`` = T_world_body (Pose3), ``F`` = p_world_foot (Point3, one per planted foot),
optional ``L`` = theta_leg (Vector, the leg's kinematic parameters, see
:mod:`graphcal.models.legs`).

Measurement: the leg's joint angles ``q`` (n,) at the station, the :class:`~graphcal.models.robot.Leg`
and optionally a :class:`~graphcal.models.legs.LegModel` (without ``L`` the
parameters are held at a fixed ``theta``, zero = nominal URDF).

Error (3, m, body frame): ``e = FK(q; theta) - R_x^T (F - t_x)`` -- the foot position predicted by
the leg minus the foot position the body pose and the foot variable imply.

Jacobians (right perturbations): with ``p_b = R_x^T (F - t_x)``, a perturbation ``[phi, rho]`` of
X (``R_x Exp(phi)``, ``t_x + R_x rho``) gives ``p_b' = Exp(-phi) (p_b - rho) = p_b + [p_b]x phi - rho``
to first order, so ``H_X = [-[p_b]x, I]``; ``H_F = -R_x^T``; ``H_L = d FK / d theta``
(:func:`graphcal.models.legs.param_jacobian`).

Noise: isotropic, default ``sigma_m = 3 mm``: joint encoder noise (~0.1-0.2 deg) through a
0.2-0.5 m leg gives ~1 mm, and the foot's compliance and rolling contact point (rubber foot pads,
slip within the contact patch) add a few mm; 3 mm is a conservative sum for the small hexapods
and quadrupeds graphcal models. Use ``robust=`` against feet that slipped.
"""

from __future__ import annotations

import gtsam
import numpy as np

from graphcal.factors.checked import checked_custom_factor, with_robust
from graphcal.models.kinematics import foot_positions
from graphcal.models.legs import LegModel, fk_and_param_jacobian, fk_with_params
from graphcal.models.robot import Leg

__all__ = ["DEFAULT_SIGMA_M", "positive_definite_3x3", "stance_foot_error", "stance_foot_factor"]

#: default isotropic sigma of the stance-foot error (m): encoder noise through the leg + foot compliance
DEFAULT_SIGMA_M = 0.003


def positive_definite_3x3(C: np.ndarray) -> bool:
    """Sylvester's criterion for a symmetric 3x3 matrix (its leading minors are positive), in
    scalars: one per stance factor built, where eigvalsh cost ~25 us."""
    a, b, c = float(C[0, 0]), float(C[0, 1]), float(C[0, 2])
    d, e, f = float(C[1, 1]), float(C[1, 2]), float(C[2, 2])
    m2 = a * d - b * b
    return a > 0.0 and m2 > 0.0 and a * (d * f - e * e) - b * (b * f - e * c) + c * (b * e - d * c) > 0.0


def _pose_jacobian(p_b) -> np.ndarray:
    """d e / d xi of ``e = p_fk - X^-1 F`` for the right perturbation ``xi = [omega, v]`` of X:
    ``[-[p_b]x, I]`` (3, 6), built from scalars (called at every evaluation)."""
    x, y, z = float(p_b[0]), float(p_b[1]), float(p_b[2])
    return np.array([[0.0, z, -y, 1.0, 0.0, 0.0], [-z, 0.0, x, 0.0, 1.0, 0.0], [y, -x, 0.0, 0.0, 0.0, 1.0]])


def stance_foot_error(
    T_world_body,
    p_world_foot,
    q,
    leg: Leg,
    param: LegModel | None = None,
    theta=None,
    want_jacobians: bool = True,
):
    """Stance-foot error and its analytic Jacobians (pure numpy).

    Args:
        T_world_body: 4x4 body pose X.
        p_world_foot: (3,) planted foot F in the world, m.
        q: (n,) joint values of the leg (rad / m).
        leg: the leg (nominal kinematics).
        param: its parameterization, or None for the nominal leg (no ``H_L``).
        theta: (k,) parameter values (default zeros) when ``param`` is given.
        want_jacobians: also return the Jacobians.

    Returns:
        e (3,) m in the body frame, and ``[H_X (3,6), H_F (3,3)]`` plus ``H_L (3,k)`` when
        ``param`` is given; or None.
    """
    q = np.asarray(q, dtype=float)
    J_L = None
    if param is None:
        p_fk = foot_positions(leg, q)
    else:
        th = param.zeros() if theta is None else np.asarray(theta, dtype=float)
        if want_jacobians:
            p_fk, J_L = fk_and_param_jacobian(leg, param, q, th)
        else:
            p_fk = fk_with_params(leg, param, q, th)
    return _error_at(T_world_body, p_world_foot, p_fk, J_L, want_jacobians)


def _error_at(T_world_body, p_world_foot, p_fk, J_L, want_jacobians: bool):
    """:func:`stance_foot_error` given the forward kinematics p_fk (3,) m, base frame, and its
    parameter Jacobian J_L (3, k) (None: no ``H_L``)."""
    X = np.asarray(T_world_body, dtype=float)
    F = np.asarray(p_world_foot, dtype=float)
    R_x, t_x = X[:3, :3], X[:3, 3]
    p_b = R_x.T @ (F - t_x)
    e = p_fk - p_b
    if not want_jacobians:
        return e, None
    Hs = [_pose_jacobian(p_b), np.ascontiguousarray(-R_x.T)]
    if J_L is not None:
        Hs.append(J_L)
    return e, Hs


def stance_foot_factor(
    x_key: int,
    f_key: int,
    q,
    leg: Leg,
    sigma_m: float = DEFAULT_SIGMA_M,
    *,
    param: LegModel | None = None,
    l_key: int | None = None,
    theta=None,
    robust=None,
    cov_m2=None,
    p_fk=None,
    kin_at=None,
) -> gtsam.NonlinearFactor:
    """Factor on (X, F[, L]) for one planted foot at one station.

    Args:
        x_key: key of T_world_body (Pose3).
        f_key: key of p_world_foot (Point3).
        q: (n,) joint values of the leg at the station (rad / m), ``leg.joint_names`` order.
        leg: the leg.
        sigma_m: isotropic sigma, m (default 3 mm, see module docstring).
        param: leg parameterization; required with ``l_key``; without ``l_key`` the parameters are
            fixed at ``theta`` (default zeros).
        l_key: key of the leg's parameter vector (Vector of ``param.dim``), if estimated.
        theta: fixed parameter values when ``l_key`` is None (default: nominal).
        robust: optional gtsam mEstimator.
        cov_m2: a full 3x3 covariance (m^2) of the foot position error in the body frame instead of
            ``sigma_m`` (e.g. :func:`joint_noise_covariance`: encoder noise through the leg).
        p_fk: FK(q; theta) (3,) when the caller has it already (without ``l_key`` only). Without
            ``l_key`` the forward kinematics is a constant and computed once, here.
        kin_at: with ``l_key``, (theta0 (k,), FK(q; theta0) (3,) m, its parameter Jacobian (3, k)) when
            the caller has them (graph.py computes them for every station of a leg in one batch); an
            evaluation at exactly theta0 (a screening graph's linearisation) uses them.
    """
    q = np.array(q, dtype=float)
    if q.shape != (leg.n_joints,) or not np.isfinite(q).all():
        raise ValueError(f"q must be {leg.n_joints} finite joint values of the leg of {leg.foot!r}, got shape {q.shape}")
    q.setflags(write=False)
    if l_key is not None and param is None:
        raise ValueError("l_key needs the leg parameterization param")
    if l_key is not None and theta is not None:
        raise ValueError("theta is the fixed parameter value; it cannot be given together with l_key (estimated)")
    if param is not None:
        param.check_leg(leg)
    if theta is not None:
        if param is None:
            raise ValueError("theta needs the leg parameterization param")
        theta = param.check_theta(theta).copy()
    if cov_m2 is not None:
        cov = np.asarray(cov_m2, dtype=float)
        if cov.shape != (3, 3) or not np.isfinite(cov).all() or not positive_definite_3x3((cov + cov.T) / 2):
            raise ValueError("cov_m2 must be a finite symmetric positive-definite 3x3 matrix")
        noise = with_robust(gtsam.noiseModel.Gaussian.Covariance((cov + cov.T) / 2), robust)
    else:
        if not np.isfinite(sigma_m) or sigma_m <= 0:
            raise ValueError(f"sigma_m must be > 0, got {sigma_m}")
        noise = with_robust(gtsam.noiseModel.Isotropic.Sigma(3, float(sigma_m)), robust)

    if l_key is None:
        if p_fk is None:
            if param is None:
                p_fk = foot_positions(leg, q)
            else:
                p_fk = fk_with_params(leg, param, q, param.zeros() if theta is None else theta)
        p_fixed = np.array(p_fk, dtype=float).reshape(3)
        p_fixed.setflags(write=False)

        def error_fn(X, F, want):
            R_x, t_x = X[:3, :3], X[:3, 3]
            p_b = R_x.T @ (F - t_x)
            e = p_fixed - p_b
            if not want:
                return e, None
            return e, [_pose_jacobian(p_b), np.ascontiguousarray(-R_x.T)]

        return checked_custom_factor(noise, [x_key, f_key], error_fn, [6, 3], 3, kinds=["Pose3", "Point3"], name="stance_foot")

    at = None if kin_at is None else tuple(np.asarray(a, dtype=float) for a in kin_at)  # no copy: read-only batches

    def error_fn_l(X, F, theta_l, want):
        if at is not None and np.array_equal(theta_l, at[0]):
            return _error_at(X, F, at[1], at[2] if want else None, want)
        return stance_foot_error(X, F, q, leg, param, theta_l, want)

    return checked_custom_factor(
        noise,
        [x_key, f_key, l_key],
        error_fn_l,
        [6, 3, param.dim],
        3,
        kinds=["Pose3", "Point3", "Vector"],
        name="stance_foot",
    )


def joint_noise_covariance(leg: Leg, q, sigma_joint: float, sigma_contact_m: float) -> np.ndarray:
    """3x3 covariance (m^2, body frame) of a foot position computed from measured joint angles:
    encoder noise ``sigma_joint`` (rad, per joint) mapped through the leg's position Jacobian, plus an
    isotropic contact/compliance term ``sigma_contact_m``: ``sigma_joint^2 J J^T + sigma_contact^2 I``."""
    from graphcal.models.kinematics import leg_jacobian

    J = leg_jacobian(leg, np.asarray(q, dtype=float))
    return sigma_joint**2 * (J @ J.T) + sigma_contact_m**2 * np.eye(3)
