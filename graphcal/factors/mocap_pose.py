"""Motion-capture pose factor: a measured 6-D pose of a robot frame (a tracker or camera measuring a
tool, hand or foot frame) against the leg's kinematics.

Variables: ``V`` = T_body_mocap (Pose3: the measurement frame in the body frame), optional ``L`` =
theta_leg (Vector: the leg's parameters of :mod:`graphcal.models.legs`, or a subset). The measured
frame is the leg's end frame (the "foot" of :class:`~graphcal.models.robot.Leg`: a foot, hand or
tool frame), its pose measured in the measurement frame: ``T_mocap_frame`` (4, 4).

One factor holds N samples (one Python callback per batch). Prediction per sample i:

    T_pred_i = T_body_mocap^-1 T_body_frame(q_i; theta)

Error (6N: per sample ``[e_r (rad), e_t (m)]``, GTSAM's tangent order, in the MEASURED frame's axes):

    e_r = Log(R_meas^T R_pred),   e_t = R_meas^T (p_pred - p_meas)

(the right-perturbation error of SO(3) x R^3: to first order the tangent ``xi`` of
``T_meas = T_pred Exp(xi)`` with the sign flipped, so a 6x6 covariance of the measured pose in its
own axes, GTSAM order [rx, ry, rz, x, y, z], is the covariance of this error).

Jacobians (right perturbations, ``Jr^-1`` the inverse right Jacobian of SO(3) at ``e_r``,
``R = R_body_frame``, ``J_w``, ``J_p`` its angular and linear Jacobians in the body frame):

* ``T_body_mocap Exp([phi, rho])``: ``R_pred -> R_pred Exp(-R_pred^T phi)``, ``p_pred -> p_pred +
  [p_pred]x phi - rho``: ``H_V = [[-Jr^-1 R_pred^T, 0], [R_meas^T [p_pred]x, -R_meas^T]]``;
* theta: ``R -> R Exp(R^T J_w dtheta)``: ``H_L = [[Jr^-1 R^T J_w], [R_meas^T R_body_mocap^T J_p]]``.

Noise: a per-sample covariance ``cov`` (N, 6, 6) (rad^2, m^2; the factor whitens inside and uses a
unit noise model, so ``graph.error`` is half the sum of squared Mahalanobis distances), optionally
inside a robust loss (``robust``: a gtsam mEstimator, applied per factor).
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from graphcal.factors.checked import checked_custom_factor
from graphcal.geometry import skew_batch, so3_log_batch, so3_right_jacobian_inverse_batch
from graphcal.models.legs import LegModel, point_kinematics
from graphcal.models.robot import Leg

__all__ = ["DEFAULT_SIGMA_POSE", "frame_kinematics", "mocap_pose_error", "mocap_pose_factor", "pose_covariance",
           "sqrt_information6"]

#: default per-axis sigma of a measured pose [rx, ry, rz (rad), x, y, z (m)]: 0.1 deg and 1 mm
DEFAULT_SIGMA_POSE = (np.radians(0.1),) * 3 + (0.001,) * 3


def _angular(J0: np.ndarray, Jk: list[np.ndarray], R: np.ndarray) -> np.ndarray:
    """Angular Jacobian (N, 3, k) from the point Jacobians of the frame origin ``J0`` and of its
    unit points ``Jk[a]`` (all (N, 3, k)): ``dR/dx = [w]x R``, so ``[w]x = sum_a d(R e_a) (R e_a)^T``."""
    D = np.stack([J - J0 for J in Jk], axis=2)  # (N, 3 rows, 3 a, k)
    S = np.einsum("nrak,nca->nrck", D, R)
    return 0.5 * np.stack([S[:, 2, 1] - S[:, 1, 2], S[:, 0, 2] - S[:, 2, 0], S[:, 1, 0] - S[:, 0, 1]], axis=1)


def frame_kinematics(leg: Leg, model: LegModel, q, theta):
    """Pose of the leg's end frame and its Jacobians, body frame.

    Returns:
        ``(R (N, 3, 3), p (N, 3) m, J_w_theta (N, 3, k), J_p_theta (N, 3, k), J_w_q (N, 3, n), J_p_q (N, 3, n))``.
    """
    pk0 = point_kinematics(leg, model, q, theta, np.zeros(3))
    pks = [point_kinematics(leg, model, q, theta, e) for e in np.eye(3)]
    R = pk0.R_base_foot
    Jw_th = _angular(pk0.J_theta, [p.J_theta for p in pks], R)
    Jw_q = _angular(pk0.J_q, [p.J_q for p in pks], R)
    return R, pk0.p_base_foot, Jw_th, pk0.J_theta, Jw_q, pk0.J_q


def mocap_pose_error(T_body_mocap, theta, q, T_mocap_meas, leg: Leg, model: LegModel, want_jacobians: bool = True):
    """Errors (N, 6) and analytic Jacobians ``[H_V (N, 6, 6), H_L (N, 6, k)]`` (or None) of N
    measured poses (module docstring). ``q``: (N, n) joint values (rad / m); ``T_mocap_meas``:
    (N, 4, 4) measured poses of the leg's end frame in the measurement frame (m)."""
    T = np.asarray(T_body_mocap, dtype=float)
    R_bm, t_bm = T[:3, :3], T[:3, 3]
    Tm = np.asarray(T_mocap_meas, dtype=float)
    Rm, pm = Tm[:, :3, :3], Tm[:, :3, 3]
    R, p, Jw_th, Jp_th, _, _ = frame_kinematics(leg, model, q, theta)
    R_pred = np.einsum("ji,njk->nik", R_bm, R)
    p_pred = (p - t_bm) @ R_bm
    RmT = np.swapaxes(Rm, 1, 2)
    e_r = so3_log_batch(RmT @ R_pred)
    e_t = np.einsum("nij,nj->ni", RmT, p_pred - pm)
    e = np.concatenate([e_r, e_t], axis=1)
    if not want_jacobians:
        return e, None
    N = e.shape[0]
    Jri = so3_right_jacobian_inverse_batch(e_r)
    H_V = np.zeros((N, 6, 6))
    H_V[:, :3, :3] = -Jri @ np.swapaxes(R_pred, 1, 2)
    H_V[:, 3:, :3] = RmT @ skew_batch(p_pred)
    H_V[:, 3:, 3:] = -RmT
    H_L = np.concatenate([Jri @ np.swapaxes(R, 1, 2) @ Jw_th, RmT @ np.einsum("ji,njk->nik", R_bm, Jp_th)], axis=1)
    return e, [H_V, H_L]


def pose_covariance(cov_meas, R_body_frame=None, J_w_q=None, J_p_q=None, sigma_joint_rad: float = 0.0) -> np.ndarray:
    """(N, 6, 6) covariance of the pose error: the measurement's ``cov_meas`` (N, 6, 6) plus, when
    ``sigma_joint_rad > 0``, the encoder noise through the leg, ``sigma^2 G G^T`` with
    ``G = [R^T J_w_q; R^T J_p_q]`` (the end frame's axes, evaluated at the nominal legs)."""
    C = np.array(cov_meas, dtype=float)
    if sigma_joint_rad:
        Rt = np.swapaxes(np.asarray(R_body_frame, dtype=float), 1, 2)
        G = np.concatenate([Rt @ J_w_q, Rt @ J_p_q], axis=1)
        C = C + float(sigma_joint_rad) ** 2 * (G @ np.swapaxes(G, 1, 2))
    return C


def sqrt_information6(cov) -> np.ndarray:
    """(N, d, d) ``L_i`` with ``L_i^T L_i = cov_i^-1``. ValueError unless finite symmetric positive definite."""
    C = np.asarray(cov, dtype=float)
    if C.ndim != 3 or C.shape[1] != C.shape[2] or not np.all(np.isfinite(C)):
        raise ValueError(f"cov must be finite (N, d, d), got shape {C.shape}")
    C = 0.5 * (C + np.swapaxes(C, 1, 2))
    try:
        Lc = np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        raise ValueError("cov: a covariance is not positive definite") from None
    return np.linalg.inv(Lc)


def mocap_pose_factor(
    v_key: int,
    q,
    T_mocap_meas,
    leg: Leg,
    model: LegModel,
    *,
    cov,
    l_key: int | None = None,
    free: Sequence[int] | None = None,
    theta=None,
    robust=None,
) -> gtsam.NonlinearFactor:
    """Factor on (V[, L]) for N measured poses of the end frame of ``leg``.

    Args:
        v_key: key of T_body_mocap (Pose3).
        q: (N, n) measured joint values of the leg (rad / m).
        T_mocap_meas: (N, 4, 4) measured poses of the leg's end frame in the measurement frame (m).
        leg, model: the leg and its :class:`~graphcal.models.legs.LegModel`.
        cov: (N, 6, 6) covariance of each error (rad^2 / m^2, [rx, ry, rz, x, y, z], measured frame's axes).
        l_key, free, theta: as :func:`graphcal.factors.mocap_marker.mocap_marker_factor`.
        robust: a ``gtsam.noiseModel.mEstimator`` (Huber, Cauchy) or None.

    Raises:
        ValueError: inconsistent shapes, non-finite input, a bad covariance.
    """
    q = np.array(q, dtype=float).reshape(-1, leg.n_joints) if leg.n_joints else np.zeros((len(T_mocap_meas), 0))
    Tm = np.array(T_mocap_meas, dtype=float)
    if Tm.ndim == 2:
        Tm = Tm[None]
    N = q.shape[0]
    if Tm.shape != (N, 4, 4) or not np.all(np.isfinite(Tm)) or not np.all(np.isfinite(q)):
        raise ValueError(f"T_mocap_meas must be finite ({N}, 4, 4) with finite q, got shape {Tm.shape}")
    model.check_leg(leg)
    L = sqrt_information6(cov)
    if L.shape != (N, 6, 6):
        raise ValueError(f"cov must have shape ({N}, 6, 6), got {np.shape(cov)}")
    m = 6 * N
    theta0 = np.zeros(model.dim) if theta is None else model.check_theta(theta).copy()
    free_idx = np.arange(model.dim) if free is None else np.asarray(list(free), dtype=int)
    if l_key is None and free is not None:
        raise ValueError("free needs l_key (the variable that holds those parameters)")
    if l_key is not None and free_idx.size == 0:
        raise ValueError("l_key given but no free parameter")
    noise = gtsam.noiseModel.Unit.Create(m)
    if robust is not None:
        noise = gtsam.noiseModel.Robust.Create(robust, noise)
    for a in (q, Tm, theta0, free_idx, L):
        a.setflags(write=False)
    keys, dims, kinds = [v_key], [6], ["Pose3"]
    if l_key is not None:
        keys.append(l_key)
        dims.append(int(free_idx.size))
        kinds.append("Vector")

    def error_fn(*args):
        want = args[-1]
        th = theta0
        if l_key is not None:
            th = theta0.copy()
            th[free_idx] = args[1]
        e, H = mocap_pose_error(args[0], th, q, Tm, leg, model, want)
        e = np.einsum("nij,nj->ni", L, e).reshape(m)
        if not want:
            return e, None
        blocks = [H[0]] + ([H[1][:, :, free_idx]] if l_key is not None else [])
        return e, [np.ascontiguousarray((L @ B).reshape(m, B.shape[2])) for B in blocks]

    return checked_custom_factor(noise, keys, error_fn, dims, m, kinds=kinds, name="mocap_pose")
