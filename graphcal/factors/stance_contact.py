"""Stance-foot factor with a round foot (contact sphere) and/or joint compliance under load.

Two causes ``graphcal diagnose`` names (docs/diagnosis.md) change where a planted foot is seen
from the body; both enter the stance-foot error of :mod:`graphcal.factors.stance_foot`
(``e = FK(q; theta) - R_x^T (F - t_x)``, 3, m, body frame):

* **Foot radius** ``r`` (variable ``R(0)``, Vector 1, m; one for every foot): the URDF foot frame is
  the tip of the lower leg, and the real foot a sphere of radius ``r`` whose centre lies ``r`` up
  the lower leg (``a_b``: the unit vector from the foot frame towards the joint before it, body
  frame). The point on the ground ``F`` is the sphere's lowest point, ``r`` below its centre along
  the ground normal (``n_b = R_x^T e_z``): the contact rolls with the leg. The foot frame seen
  from the contact: ``FK + r (a_b - n_b)``::

      e = FK(q'; theta) + r (a_b - n_b) - R_x^T (F - t_x)

  ``H_r = a_b - n_b`` (3, 1); the rotation part of ``H_X`` gains ``-r [n_b]x`` (``n_b`` of the
  perturbed pose ``R_x Exp(phi)`` is ``Exp(-phi) n_b = n_b + [n_b]x phi`` to first order).
* **Joint compliance** ``k`` (variable ``Q(j)``, Vector 1, rad per m; one per joint index ``j`` of
  every leg, e.g. every femur): under the foot's share of the weight (a vertical force on the
  foot) joint ``j`` flexes by ``c * tau``; ``tau = load * lever`` with ``lever = (d FK / d q_j) .
  n_b`` (m per rad, the torque per newton of vertical load) taken at the station's commanded
  attitude, so that ``k = c * load`` (rad per m of lever) is what the data determine (the load
  is unknown without the robot's mass). The joint really stands at ``q'_j = q_j + k lever(q')``
  (the torque of the pose the leg is really in: Newton's method, :func:`complied_angles`)::

      H_k = (d FK / d q_j)(q') * d q'_j / d k,   d q'_j / d k = lever / (1 - k d lever / d q_j)

  (with leg parameters estimated, the parameterised leg's derivative by central differences).

Without either variable the factor equals :func:`graphcal.factors.stance_foot.stance_foot_factor`.
"""

from __future__ import annotations

import gtsam
import numpy as np

from graphcal.factors.checked import checked_custom_factor
from graphcal.factors.stance_foot import stance_foot_error
from graphcal.geometry import skew
from graphcal.models.kinematics import foot_positions, joint_frames, leg_jacobian, position_jacobian
from graphcal.models.legs import fk_with_params
from graphcal.models.robot import Leg

__all__ = ["lower_leg_direction", "lower_leg_directions", "compliance_lever", "complied_angles", "complied_kinematics",
           "stance_contact_error", "stance_contact_factor"]


#: Newton rounds of the complied angle (quadratic convergence from the measured angle: the
#: deflection is a few degrees; 3 rounds reach machine precision)
NEWTON_ROUNDS = 3
#: a Newton step below this (rad) ends the iteration (the lever's change over it is ~1e-15 m)
NEWTON_STEP_RAD = 1e-12


def lower_leg_direction(leg: Leg, q) -> np.ndarray:
    """Unit vector (3,) in the leg's base (body) frame from the foot frame towards the origin of the
    last joint whose origin differs from the foot's, at joint values ``q`` (n,): the lower leg's axis."""
    return lower_leg_directions(leg, np.asarray(q, dtype=float)[None, :])[0]


def lower_leg_directions(leg: Leg, Q) -> np.ndarray:
    """:func:`lower_leg_direction` of a batch of joint values ``Q`` (N, n): (N, 3)."""
    _, origins, _, p_foot = joint_frames(leg, np.asarray(Q, dtype=float))
    out = np.tile([0.0, 0.0, 1.0], (len(p_foot), 1))
    found = np.zeros(len(p_foot), dtype=bool)
    for j in range(origins.shape[1] - 1, -1, -1):  # the last joint whose origin is off the foot's
        d = origins[:, j] - p_foot
        norm = np.linalg.norm(d, axis=1)
        take = ~found & (norm > 1e-6)
        out[take] = d[take] / norm[take, None]
        found |= take
    return out


def compliance_lever(leg: Leg, q, joint_index: int, R_world_body: np.ndarray) -> float:
    """Torque about joint ``joint_index`` (N m) per newton of vertical load on the foot, at joint values
    ``q`` (n,) and body attitude ``R_world_body`` (3, 3): ``(d p_foot / d q_j) . R^T e_z`` (m/rad)."""
    J = leg_jacobian(leg, np.asarray(q, dtype=float))
    n_b = np.asarray(R_world_body, dtype=float).T @ np.array([0.0, 0.0, 1.0])
    return float(J[:, int(joint_index)] @ n_b)


def complied_angles(leg: Leg, q, joint_index: int, k: float, R_lever, x0: float | None = None) -> tuple[np.ndarray, float]:
    """(q' (n,), d q'_j / d k) of a leg whose joint ``joint_index`` flexes by ``k * lever(q')`` from the
    measured ``q`` (n,): ``q'_j = q_j + k lever(q')`` (the torque is that of the pose the leg is
    really in), by Newton's method; the derivative by implicit differentiation,
    ``lever / (1 - k dlever/dq_j)`` (dlever/dq_j by central differences). ``R_lever``: (3, 3) body
    attitude of the lever (:func:`compliance_lever`). ``x0``: a first guess of ``q'_j`` (rad; default
    ``q_j``), e.g. the last one extrapolated to this ``k``."""
    j = int(joint_index)
    qc = np.array(q, dtype=float)
    n_b = np.asarray(R_lever, dtype=float).T @ np.array([0.0, 0.0, 1.0])
    h = 1e-6

    def lever_and_slope(x):
        batch = np.repeat(qc[None, :], 3, axis=0)
        batch[:, j] = (x, x + h, x - h)
        lv = leg_jacobian(leg, batch)[:, :, j] @ n_b  # one batched kinematics
        return float(lv[0]), float((lv[1] - lv[2]) / (2 * h))

    x = float(q[j]) if x0 is None else float(x0)
    for _ in range(NEWTON_ROUNDS):  # x - q_j - k lever(x) = 0
        lever, dl = lever_and_slope(x)
        step = (x - q[j] - k * lever) / (1.0 - k * dl)
        x -= step
        if abs(step) < NEWTON_STEP_RAD:  # converged: lever and slope at x are those just taken
            break
    else:
        lever, dl = lever_and_slope(x)
    qc[j] = x
    return qc, float(lever / (1.0 - k * dl))


def complied_kinematics(leg: Leg, q, joint_index: int, k: float, R_lever, x0: float | None = None) -> tuple:
    """(q' (n,), d q'_j / d k, FK(q') (3,) m, d FK / d q_j at q' (3,) m/rad) of the nominal leg: what the
    stance-contact error needs of a compliance ``k`` (:func:`complied_angles`, first guess ``x0``), base
    frame."""
    qc, dq_dk = complied_angles(leg, q, joint_index, k, R_lever, x0)
    axes, origins, _, p_foot = joint_frames(leg, qc[None, :])  # one kinematics pass for FK and its Jacobian
    dp = position_jacobian(leg.joint_types, axes, origins, p_foot)[0, :, int(joint_index)]
    return qc, dq_dk, p_foot[0], dp


def _fixed_leg_error(T_world_body, p_world_foot, p_fk, want_jacobians: bool):
    """The stance-foot error ``p_fk - R_x^T (F - t_x)`` of a leg whose kinematics is a constant
    ``p_fk`` (3,) m, with ``[H_X, H_F]`` (factors/stance_foot.py, without re-running the kinematics)."""
    X = np.asarray(T_world_body, dtype=float)
    R_x, t_x = X[:3, :3], X[:3, 3]
    p_b = R_x.T @ (np.asarray(p_world_foot, dtype=float) - t_x)
    e = p_fk - p_b
    if not want_jacobians:
        return e, None
    H_X = np.zeros((3, 6))
    H_X[:, :3] = -skew(p_b)
    H_X[:, 3:] = np.eye(3)
    return e, [H_X, np.ascontiguousarray(-R_x.T)]


def stance_contact_error(T_world_body, p_world_foot, q, leg: Leg, *, radius=None, a_b=None, compliance=None,
                         joint_index: int = 0, R_lever=None, param=None, theta=None,
                         want_jacobians: bool = True, p_fk=None, complied=None):
    """Error (3,) m (body frame) and Jacobians of the stance-foot factor with a foot radius and/or a
    joint compliance (module docstring).

    Args:
        T_world_body: 4x4 body pose X; p_world_foot: (3,) contact point F in the world, m.
        q: (n,) measured joint values of the leg (rad / m); leg: the leg.
        radius: foot radius r (m) or None (no sphere); a_b: (3,) unit lower-leg direction (body frame).
        compliance: k (rad per m of lever) or None; joint_index: the compliant joint; R_lever: (3, 3)
            the body attitude its lever is taken at (:func:`compliance_lever`; the commanded one).
        param, theta: the leg's parameterization and values (or None: the nominal leg).
        p_fk: FK(q) (3,) of the nominal leg when the caller has it (used without ``param`` and
            ``compliance``: the kinematics is then a constant).
        complied: :func:`complied_kinematics` of this ``q``, ``joint_index``, ``compliance`` and
            ``R_lever`` (nominal leg) when the caller has them (a factor keeps the last one: they
            depend on k alone).
    Returns:
        (e, [H_X (3,6), H_F (3,3)] + [H_L (3,p)] + [H_r (3,1)] + [H_k (3,1)]) in that order, or (e, None).
    """
    q = np.asarray(q, dtype=float)
    qc = q.copy()
    dq_dk, dp = 0.0, None
    if compliance is not None and param is None:  # the nominal leg: FK at the complied angles, a constant for k
        qc, dq_dk, p_fk, dp = complied or complied_kinematics(leg, q, int(joint_index), float(compliance), R_lever)
    elif compliance is not None:
        qc, dq_dk = complied_angles(leg, q, int(joint_index), float(compliance), R_lever)
    if p_fk is not None and param is None:  # the nominal leg's kinematics, constant
        e, Hs = _fixed_leg_error(T_world_body, p_world_foot, np.asarray(p_fk, dtype=float), want_jacobians)
    else:
        e, Hs = stance_foot_error(T_world_body, p_world_foot, qc, leg, param, theta, want_jacobians)
    R_x = np.asarray(T_world_body, dtype=float)[:3, :3]
    n_b = R_x.T @ np.array([0.0, 0.0, 1.0])
    if radius is not None:
        e = e + float(radius) * (np.asarray(a_b, dtype=float) - n_b)
    if not want_jacobians:
        return e, None
    Hs = list(Hs)
    if radius is not None:
        H_X = Hs[0].copy()
        H_X[:, :3] += -float(radius) * skew(n_b)
        Hs[0] = H_X
        Hs.append((np.asarray(a_b, dtype=float) - n_b).reshape(3, 1))
    if compliance is not None:
        if param is not None:  # the parameterised leg's d FK / d q_j by central differences (no closed form in models.legs)
            h = 1e-6
            dq = np.zeros_like(qc)
            dq[int(joint_index)] = h
            th = param.zeros() if theta is None else np.asarray(theta, dtype=float)
            dp = (fk_with_params(leg, param, qc + dq, th) - fk_with_params(leg, param, qc - dq, th)) / (2 * h)
        Hs.append((dp * dq_dk).reshape(3, 1))
    return e, Hs


def stance_contact_factor(x_key: int, f_key: int, q, leg: Leg, cov_m2, *, r_key: int | None = None, a_b=None,
                          k_key: int | None = None, joint_index: int = 0, R_lever=None,
                          l_key: int | None = None, param=None) -> gtsam.NonlinearFactor:
    """Factor on (X, F[, L][, R][, Q]) for one planted foot at one station (module docstring).

    Args:
        x_key, f_key: keys of T_world_body (Pose3) and the contact point p_world_foot (Point3).
        q: (n,) measured joint values; leg: the leg; cov_m2: (3, 3) covariance (m^2) of the error.
        r_key: key of the foot radius [r] (Vector 1, m) and ``a_b`` (3,) its lower-leg direction at ``q``.
        k_key: key of the compliance [k] (Vector 1, rad per m of lever) of joint ``joint_index``,
            its lever taken at the body attitude ``R_lever`` (3, 3; the station's commanded one).
        l_key, param: key and parameterization of the leg's parameters (Vector), if estimated.
    """
    q = np.array(q, dtype=float)
    q.setflags(write=False)
    cov = np.asarray(cov_m2, dtype=float)
    noise = gtsam.noiseModel.Gaussian.Covariance((cov + cov.T) / 2)
    keys, dims, kinds = [x_key, f_key], [6, 3], ["Pose3", "Point3"]
    if l_key is not None:
        keys.append(l_key)
        dims.append(param.dim)
        kinds.append("Vector")
    if r_key is not None:
        keys.append(r_key)
        dims.append(1)
        kinds.append("Vector")
    if k_key is not None:
        keys.append(k_key)
        dims.append(1)
        kinds.append("Vector")
    a = None if a_b is None else np.array(a_b, dtype=float)
    p_fk = foot_positions(leg, q) if (l_key is None and k_key is None) else None
    last = {}  # k -> complied_angles(k): the solver evaluates each k several times

    def error_fn(X, F, *rest, want):
        rest = list(rest)
        theta = rest.pop(0) if l_key is not None else None
        r = float(rest.pop(0)[0]) if r_key is not None else None
        k = float(rest.pop(0)[0]) if k_key is not None else None
        if k is not None and l_key is None and k not in last:
            x0 = None
            if last:  # the last solution moved along its slope: Newton then needs one or two rounds
                (k0, (qc0, dq0, *_)), = last.items()
                x0 = qc0[joint_index] + (k - k0) * dq0
            last.clear()
            last[k] = complied_kinematics(leg, q, joint_index, k, R_lever, x0)
        return stance_contact_error(X, F, q, leg, radius=r, a_b=a, compliance=k, joint_index=joint_index, R_lever=R_lever,
                                    param=param if l_key is not None else None, theta=theta, want_jacobians=want,
                                    p_fk=p_fk, complied=last.get(k))

    def fn(*args):
        *vals, want = args
        return error_fn(*vals, want=want)

    return checked_custom_factor(noise, keys, fn, dims, 3, kinds=kinds, name="stance_contact")
