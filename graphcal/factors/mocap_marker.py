"""Motion-capture marker factor: a marker on a foot, seen by the motion capture, against the leg's
kinematics.

Variables: ``V`` = T_body_mocap (Pose3: the motion-capture frame -- or Yuan's virtual base -- in
the body frame), optional ``L`` = theta_leg (Vector: the parameters of :mod:`graphcal.models.legs`,
or a subset), optional ``K`` = p_foot_marker (Point3, foot frame). One factor holds all N samples
of one marker: joint values ``q_i`` (rad / m) and the marker ``p_mocap_i`` (m, mocap frame).
Error (3N, m, motion-capture frame):
``e_i = p_mocap_i - T_body_mocap^-1 (p_body_foot(q_i; theta) + R_body_foot(q_i; theta) p_foot_marker)``,
with analytic Jacobians (right perturbations). Noise: isotropic ``sigma_m`` (default 1 mm) or a
per-sample covariance (:func:`marker_covariance`), whitened inside the factor.

Jacobians and noise: docs/legs.md, "The factor".
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from graphcal.factors.checked import checked_custom_factor
from graphcal.models.legs import LegModel, point_kinematics
from graphcal.models.robot import Leg

__all__ = ["DEFAULT_SIGMA_M", "mocap_marker_error", "mocap_marker_factor", "marker_covariance", "sqrt_information"]

#: default isotropic sigma of a motion-capture marker (m)
DEFAULT_SIGMA_M = 0.001


def mocap_marker_error(
    T_body_mocap,
    theta,
    p_foot_marker,
    q,
    p_mocap,
    leg: Leg,
    model: LegModel,
    want_jacobians: bool = True,
):
    """Errors and analytic Jacobians of N samples (pure numpy).

    Args:
        T_body_mocap: 4x4 pose of the motion-capture (or virtual base) frame in the body frame.
        theta: (k,) leg parameters (``model.names`` order), SI units.
        p_foot_marker: (3,) marker position in the foot frame, m.
        q: (N, n) measured joint values (rad / m), ``leg.joint_names`` order.
        p_mocap: (N, 3) measured marker positions in the motion-capture frame, m.
        leg, model: the leg and its parameterization.
        want_jacobians: also return the Jacobians.

    Returns:
        e (N, 3) in m (mocap frame), and ``[H_V (N, 3, 6), H_L (N, 3, k), H_K (N, 3, 3)]`` or None.
    """
    T = np.asarray(T_body_mocap, dtype=float)
    R, t = T[:3, :3], T[:3, 3]
    pk = point_kinematics(leg, model, q, theta, p_foot_marker)
    pred = (pk.p_base_point - t) @ R  # R^T (p - t), row-wise
    e = np.asarray(p_mocap, dtype=float) - pred
    if not want_jacobians:
        return e, None
    N = e.shape[0]
    H_V = np.zeros((N, 3, 6))
    x, y, z = pred[:, 0], pred[:, 1], pred[:, 2]
    # -[p]x
    H_V[:, 0, 1], H_V[:, 0, 2] = z, -y
    H_V[:, 1, 0], H_V[:, 1, 2] = -z, x
    H_V[:, 2, 0], H_V[:, 2, 1] = y, -x
    H_V[:, :, 3:] = np.eye(3)
    Rt = R.T
    H_L = -np.einsum("ij,njk->nik", Rt, pk.J_theta)
    H_K = -np.einsum("ij,njk->nik", Rt, pk.R_base_foot)
    return e, [H_V, H_L, H_K]


def sqrt_information(cov_m2) -> np.ndarray:
    """(N, 3, 3) ``L_i`` with ``L_i^T L_i = cov_i^-1`` (inverse of the lower Cholesky factor).

    Raises:
        ValueError: a covariance that is not finite, symmetric positive definite.
    """
    C = np.asarray(cov_m2, dtype=float)
    if C.ndim != 3 or C.shape[1:] != (3, 3) or not np.all(np.isfinite(C)):
        raise ValueError(f"cov_m2 must be finite (N, 3, 3), got shape {C.shape}")
    C = 0.5 * (C + np.swapaxes(C, 1, 2))
    try:
        Lc = np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        raise ValueError("cov_m2: a covariance is not positive definite") from None
    return np.linalg.inv(Lc)


def marker_covariance(J_q, sigma_marker_m: float, sigma_joint_rad: float = 0.0, extra=None) -> np.ndarray:
    """(N, 3, 3) covariance of a marker error: ``sigma_marker^2 I + sigma_joint^2 J_q J_q^T (+ extra)``.

    Args:
        J_q: (N, 3, n) d p_marker / d q (:attr:`graphcal.models.legs.PointKinematics.J_q`), rotated
            into the frame of the error (the mocap frame: ``R_body_mocap^T J_q``; isotropic terms
            do not care).
        sigma_marker_m: marker noise per coordinate, m.
        sigma_joint_rad: encoder noise per joint, rad (m for a prismatic joint).
        extra: optional (N, 3, 3) further covariance (e.g. the virtual base's, in the same frame).
    """
    J = np.asarray(J_q, dtype=float)
    C = float(sigma_marker_m) ** 2 * np.broadcast_to(np.eye(3), (J.shape[0], 3, 3))
    if sigma_joint_rad:
        C = C + float(sigma_joint_rad) ** 2 * (J @ np.swapaxes(J, 1, 2))
    if extra is not None:
        C = C + np.asarray(extra, dtype=float)
    return np.array(C)


def mocap_marker_factor(
    v_key: int,
    q,
    p_mocap,
    leg: Leg,
    model: LegModel,
    *,
    l_key: int | None = None,
    free: Sequence[int] | None = None,
    theta=None,
    k_key: int | None = None,
    p_foot_marker=None,
    sigma_m: float = DEFAULT_SIGMA_M,
    cov_m2=None,
    robust=None,
) -> gtsam.NonlinearFactor:
    """Factor on (V[, L][, K]) for N samples of one marker on the foot of ``leg``.

    Args:
        v_key: key of T_body_mocap (Pose3).
        q: (N, n) measured joint values of the leg (rad / m).
        p_mocap: (N, 3) measured marker positions in the motion-capture frame (m).
        leg, model: the leg and its :class:`~graphcal.models.legs.LegModel`.
        l_key: key of the leg parameter vector, if estimated: a Vector of ``len(free)``.
        free: indices (into ``model.names``) of the parameters the L variable holds (default: all);
            the others keep their value in ``theta``.
        theta: (k,) values of the parameters not in L (default zeros = nominal URDF); without
            ``l_key`` all parameters are held at it.
        k_key: key of p_foot_marker (Point3), if estimated.
        p_foot_marker: (3,) the marker in the foot frame when ``k_key`` is None (default: the foot
            frame origin).
        sigma_m: isotropic sigma per coordinate (m), when ``cov_m2`` is None.
        cov_m2: (N, 3, 3) per-sample covariance of the error (m^2, mocap frame).
        robust: a ``gtsam.noiseModel.mEstimator`` (Huber, Cauchy) wrapping the noise model (it
            weighs the factor as a whole: give one sample per factor for a per-sample loss), or None.

    Raises:
        ValueError: inconsistent shapes, non-finite input, a bad sigma or covariance.
    """
    q = np.array(q, dtype=float)
    if q.ndim == 1:
        q = q[None]
    P = np.array(p_mocap, dtype=float)
    if P.ndim == 1:
        P = P[None]
    n = leg.n_joints
    if q.ndim != 2 or q.shape[1] != n or not np.all(np.isfinite(q)):
        raise ValueError(f"q must be finite (N, {n}) joint values of the leg of {leg.foot!r}, got shape {q.shape}")
    if P.shape != (q.shape[0], 3) or not np.all(np.isfinite(P)):
        raise ValueError(f"p_mocap must be finite ({q.shape[0]}, 3), got shape {P.shape}")
    model.check_leg(leg)
    N = q.shape[0]
    m = 3 * N
    theta0 = np.zeros(model.dim) if theta is None else model.check_theta(theta).copy()
    free_idx = np.arange(model.dim) if free is None else np.asarray(list(free), dtype=int)
    if l_key is None and free is not None:
        raise ValueError("free needs l_key (the variable that holds those parameters)")
    if free_idx.size and (free_idx.min() < 0 or free_idx.max() >= model.dim or len(set(free_idx.tolist())) != free_idx.size):
        raise ValueError(f"free must be distinct indices into the {model.dim} parameters, got {free_idx.tolist()}")
    if l_key is not None and free_idx.size == 0:
        raise ValueError("l_key given but no free parameter")
    marker0 = np.zeros(3) if p_foot_marker is None else np.asarray(p_foot_marker, dtype=float).reshape(3).copy()
    if k_key is not None and p_foot_marker is not None:
        raise ValueError("p_foot_marker is the fixed marker position; it cannot be given together with k_key")
    if cov_m2 is not None:
        L = sqrt_information(cov_m2)
        if L.shape[0] != N:
            raise ValueError(f"cov_m2 must have shape ({N}, 3, 3), got {np.shape(cov_m2)}")
        noise = gtsam.noiseModel.Unit.Create(m)
    else:
        if not np.isfinite(sigma_m) or sigma_m <= 0:
            raise ValueError(f"sigma_m must be > 0, got {sigma_m}")
        L = None
        noise = gtsam.noiseModel.Isotropic.Sigma(m, float(sigma_m))
    if robust is not None:
        noise = gtsam.noiseModel.Robust.Create(robust, noise)
    for a in (q, P, theta0, marker0, free_idx):
        a.setflags(write=False)

    keys, dims, kinds = [v_key], [6], ["Pose3"]
    if l_key is not None:
        keys.append(l_key)
        dims.append(int(free_idx.size))
        kinds.append("Vector")
    if k_key is not None:
        keys.append(k_key)
        dims.append(3)
        kinds.append("Point3")
    use_l, use_k = l_key is not None, k_key is not None

    def error_fn(*args):
        want = args[-1]
        T = args[0]
        i = 1
        th = theta0
        if use_l:
            th = theta0.copy()
            th[free_idx] = args[i]
            i += 1
        mk = args[i] if use_k else marker0
        e, H = mocap_marker_error(T, th, mk, q, P, leg, model, want)
        if L is not None:
            e = np.einsum("nij,nj->ni", L, e)
        e = e.reshape(m)
        if not want:
            return e, None
        blocks = [H[0]]
        if use_l:
            blocks.append(H[1][:, :, free_idx])
        if use_k:
            blocks.append(H[2])
        out = []
        for B in blocks:
            if L is not None:
                B = L @ B
            out.append(np.ascontiguousarray(B.reshape(m, B.shape[2])))
        return e, out

    return checked_custom_factor(noise, keys, error_fn, dims, m, kinds=kinds, name="mocap_marker")
