"""Vectorised leg kinematics: forward kinematics, position Jacobian, the one batch IK for N
configurations (:func:`newton_ik`; :func:`ik_leg` its robust default) and the swing profiles'
:func:`smoothstep`.

A leg (:class:`graphcal.models.robot.Leg`) is a chain of 1-DOF joints; everything here works on a
batch of N configurations at once (numpy, one loop over the chain's joints, none over
configurations). Results are expressed in the leg's base frame (usually ``body``).

Units: metres for positions and prismatic joints, radians for revolute joints.
Agreement with Pinocchio (:meth:`graphcal.models.robot.RobotModel.fk_pinocchio`) is tested to 1e-9 m.
"""

from __future__ import annotations

import weakref
from typing import NamedTuple

import numpy as np

from graphcal.errors import ModelError
from graphcal.geometry import cross_batch, so3_exp_skew_batch
from graphcal.models.robot import Leg

__all__ = [
    "fk_leg",
    "foot_positions",
    "leg_jacobian",
    "ik_leg",
    "newton_ik",
    "LegIK",
    "joint_frames",
    "chain_frames",
    "position_jacobian",
    "as_batch",
    "smoothstep",
]


def as_batch(leg: Leg, q) -> tuple[np.ndarray, bool]:
    """(N, n) float array and whether the input was a single (n,) configuration."""
    q = np.asarray(q, dtype=float)
    single = q.ndim == 1
    if single:
        q = q[None, :]
    if q.ndim != 2 or q.shape[1] != leg.n_joints:
        raise ModelError(
            f"leg of {leg.foot!r} has {leg.n_joints} joints ({', '.join(leg.joint_names)}); "
            f"q must have shape (N, {leg.n_joints}), got {np.shape(q)}"
        )
    return q, single


def chain_frames(leg: Leg, q: np.ndarray, dt: np.ndarray | None = None):
    """The one pass over a leg's chain: joint axes and origins, the frames its placements are
    expressed in, and the foot pose, for a batch of configurations.

    Args:
        leg: the leg.
        q: (N, n) joint values (rad / m), :attr:`Leg.joint_names` order (already a batch).
        dt: optional (n + 1, 3) change of each placement's translation, m: row ``j < n`` is added
            to ``T_parent_joint[j]``'s translation, row ``n`` to ``T_lastjoint_foot``'s, each in the
            frame that placement is expressed in (a leg model's link/origin parameters).

    Returns:
        axes_base (N, n, 3): unit joint axes in the base frame;
        origins_base (N, n, 3): joint frame origins in the base frame, m (for a prismatic joint:
            the origin before its own motion);
        R_frames: list of n + 1 (N, 3, 3) rotations (base frame) of the frame each placement's
            translation is expressed in (the previous joint frame after its motion; identity for j = 0);
        R_base_foot (N, 3, 3), p_base_foot (N, 3) (m).
    """
    N = q.shape[0]
    n = leg.n_joints
    joints, (t_foot, R_foot_last) = _chain_constants(leg)
    R = np.repeat(_EYE3[None], N, axis=0)
    p = np.zeros((N, 3))
    axes_base = np.empty((N, n, 3))
    origins_base = np.empty((N, n, 3))
    R_frames = []
    for j, (t, R_pj, a, K, K2, revolute) in enumerate(joints):
        R_frames.append(R)
        p = p + R @ (t if dt is None else t + dt[j])
        R = R @ R_pj
        axes_base[:, j] = R @ a
        origins_base[:, j] = p
        if revolute:
            R = R @ so3_exp_skew_batch(K, K2, q[:, j])
        else:  # prismatic
            p = p + q[:, j, None] * axes_base[:, j]
    R_frames.append(R)
    p_foot = p + R @ (t_foot if dt is None else t_foot + dt[n])
    R_foot = R @ R_foot_last
    return axes_base, origins_base, R_frames, R_foot, p_foot


_EYE3 = np.eye(3)
_EYE3.setflags(write=False)
#: leg -> :func:`_chain_constants` (a leg's placements are read-only arrays: computed once per leg)
_CHAIN_CONSTANTS: "weakref.WeakKeyDictionary[Leg, tuple]" = weakref.WeakKeyDictionary()


def _chain_constants(leg: Leg) -> tuple:
    """What :func:`chain_frames` reads of a leg's placements, sliced once: per joint (translation
    (3,) m, rotation (3, 3), unit axis (3,), its cross-product matrix K (3, 3), K @ K, revolute?),
    and the foot's (translation (3,) m, rotation (3, 3)) in the last joint frame."""
    out = _CHAIN_CONSTANTS.get(leg)
    if out is None:
        joints = []
        for j in range(leg.n_joints):
            T, a = leg.T_parent_joint[j], leg.axes[j]
            K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
            joints.append((T[:3, 3], T[:3, :3], a, K, K @ K, leg.joint_types[j] == "revolute"))
        Tf = leg.T_lastjoint_foot
        out = _CHAIN_CONSTANTS[leg] = (tuple(joints), (Tf[:3, 3], Tf[:3, :3]))
    return out


def joint_frames(leg: Leg, q) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Joint axes and origins in the base frame, and the foot pose, for a batch of configurations.

    Args:
        leg: the leg.
        q: (N, n) joint values (rad / m), :attr:`Leg.joint_names` order.

    Returns:
        axes_base (N, n, 3): unit joint axes in the base frame;
        origins_base (N, n, 3): joint frame origins in the base frame, m (for a prismatic joint:
            the origin before its own motion);
        R_base_foot (N, 3, 3), p_base_foot (N, 3) (m).
    """
    q, _ = as_batch(leg, q)
    axes_base, origins_base, _, R_foot, p_foot = chain_frames(leg, q)
    return axes_base, origins_base, R_foot, p_foot


def position_jacobian(joint_types, axes_base: np.ndarray, origins_base: np.ndarray, p_base: np.ndarray) -> np.ndarray:
    """d p_base / d q (N, 3, n) of a point ``p_base`` (N, 3) moved by the chain, base frame.

    The one geometric Jacobian of graphcal's legs: revolute joint j contributes
    ``axis_base_j x (p - origin_j)`` (m/rad), prismatic joint j ``axis_base_j`` (m/m).

    Args:
        joint_types: ``"revolute"`` / ``"prismatic"`` per joint (n).
        axes_base: (N, n, 3) unit joint axes in the base frame (:func:`chain_frames`).
        origins_base: (N, n, 3) joint origins in the base frame, m.
        p_base: (N, 3) the point (e.g. the foot), m, base frame.
    """
    # every joint's column at once as if revolute (the same arithmetic as one cross product per joint)
    J = np.ascontiguousarray(np.swapaxes(cross_batch(axes_base, p_base[:, None, :] - origins_base), 1, 2))
    for j, jtype in enumerate(joint_types):
        if jtype != "revolute":
            J[:, :, j] = axes_base[:, j]
    return J


def fk_leg(leg: Leg, q) -> np.ndarray:
    """Forward kinematics of a leg for N configurations.

    Args:
        leg: the leg.
        q: (N, n) joint values (rad for revolute, m for prismatic), :attr:`Leg.joint_names` order.
            A single (n,) configuration gives a single (4, 4) result.

    Returns:
        T_base_foot (N, 4, 4): foot frame in the leg's base frame, m.
    """
    _, single = as_batch(leg, q)
    _, _, R, p = joint_frames(leg, q)
    T = np.zeros((R.shape[0], 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = p
    T[:, 3, 3] = 1.0
    return T[0] if single else T


def foot_positions(leg: Leg, q) -> np.ndarray:
    """p_base_foot (N, 3), m, for joint values q (N, n); (3,) for a single (n,) configuration."""
    _, single = as_batch(leg, q)
    p = joint_frames(leg, q)[3]
    return p[0] if single else p


def leg_jacobian(leg: Leg, q) -> np.ndarray:
    """Position Jacobian d p_base_foot / d q, (N, 3, n), in the base frame.

    Geometric Jacobian from the vectorised FK: revolute joint j contributes
    ``axis_base_j x (p_foot - origin_j)``, prismatic joint j ``axis_base_j``.
    Units: m/rad (revolute columns), m/m (prismatic columns). A single (n,) q gives (3, n).
    """
    _, single = as_batch(leg, q)
    axes, origins, _, p = joint_frames(leg, q)
    J = position_jacobian(leg.joint_types, axes, origins, p)
    return J[0] if single else J


class LegIK(NamedTuple):
    """A batch IK solution of :func:`newton_ik`; everything at the returned ``q`` (base frame)."""

    q: np.ndarray  #: (N, n) joint values, rad / m
    err: np.ndarray  #: (N,) residual |target - foot|, m
    p_base_foot: np.ndarray  #: (N, 3) foot positions, m
    J: np.ndarray  #: (N, 3, n) position Jacobian d p_base_foot / d q (m/rad, m/m)
    origins_base: np.ndarray  #: (N, n, 3) joint origins, m (:func:`chain_frames`)


def newton_ik(
    leg: Leg,
    p_base_foot,
    q0,
    *,
    iterations: int,
    stop_tol: float,
    damping: float | None = None,
    adaptive: bool = False,
    max_step: float | None = None,
) -> LegIK:
    """Batch position IK of a leg by Newton / Gauss-Newton steps from ``q0``, one forward-kinematics
    pass per step (:func:`joint_frames` gives the foot and its Jacobian together). Joint limits are
    not enforced.

    Args:
        leg: the leg.
        p_base_foot: (N, 3) target foot positions in the base frame, m.
        q0: (N, n) initial joint values (or (n,), broadcast over the targets).
        iterations: at most this many steps.
        stop_tol: residual (m): stop once every configuration is below it (``adaptive``: each
            configuration stops there).
        damping: None: Newton's square solve ``J dq = r`` (3 joints); else the damped Gauss-Newton step
            ``(J^T J + lam I) dq = J^T r`` with ``lam = damping``.
        adaptive: Levenberg-Marquardt: a step is kept only where it lowers the residual, then ``lam``
            is multiplied by 0.3 (down to 1e-12), else by 10 (``damping`` is the first ``lam``).
        max_step: each step is scaled down to at most this largest joint change (rad / m), or None.
    """
    P = np.asarray(p_base_foot, dtype=float)
    N, n = P.shape[0], leg.n_joints
    q = np.array(np.broadcast_to(np.asarray(q0, dtype=float), (N, n)), dtype=float)
    axes, origins, _, p = joint_frames(leg, q)
    J = position_jacobian(leg.joint_types, axes, origins, p)
    r = P - p
    err = np.linalg.norm(r, axis=1)
    lam = np.full(N, 0.0 if damping is None else float(damping))
    eye = np.eye(n)
    for _ in range(iterations):
        if adaptive:
            rows = err >= stop_tol
            if not rows.any():
                break
            if rows.all():
                rows = slice(None)  # every configuration steps: views, not copies
        elif np.all(err < stop_tol):
            break
        else:
            rows = slice(None)
        Jr, rr = J[rows], r[rows]
        if damping is None:
            dq = np.linalg.solve(Jr, rr[:, :, None])[:, :, 0]
        else:
            JT = np.swapaxes(Jr, 1, 2)
            A = JT @ Jr + (lam[rows, None, None] * eye if adaptive else damping * eye)
            dq = np.linalg.solve(A, JT @ rr[:, :, None])[:, :, 0]
        if max_step is not None:
            dq = dq * np.minimum(1.0, max_step / np.maximum(np.max(np.abs(dq), axis=1, keepdims=True), 1e-12))
        q_new = q[rows] + dq
        axes_n, origins_n, _, p_n = joint_frames(leg, q_new)
        J_n = position_jacobian(leg.joint_types, axes_n, origins_n, p_n)
        r_n = P[rows] - p_n
        err_n = np.linalg.norm(r_n, axis=1)
        if not adaptive:
            q, p, origins, J, r, err = q_new, p_n, origins_n, J_n, r_n, err_n
            continue
        better = err_n < err[rows]
        if isinstance(rows, slice) and better.all():  # every step kept: take the new arrays whole
            q, p, origins, J, r, err = q_new, p_n, origins_n, J_n, r_n, err_n
            lam = np.maximum(lam * 0.3, 1e-12)
            continue
        idx = np.arange(N) if isinstance(rows, slice) else np.flatnonzero(rows)
        acc = idx[better]
        q[acc], p[acc], origins[acc], J[acc] = q_new[better], p_n[better], origins_n[better], J_n[better]
        r[acc], err[acc] = r_n[better], err_n[better]
        lam[acc] = np.maximum(lam[acc] * 0.3, 1e-12)
        lam[idx[~better]] *= 10.0
    return LegIK(q, err, p, J, origins)


def ik_leg(
    leg: Leg,
    p_base_foot,
    q0,
    *,
    tol: float = 1e-10,
    max_iter: int = 50,
    ok_tol: float = 1e-6,
) -> tuple[np.ndarray, np.ndarray]:
    """Batch position IK of a leg: Levenberg-Marquardt (:func:`newton_ik`, ``adaptive``, first damping 1e-4).

    Joint limits are NOT enforced (check ``leg.lower``/``leg.upper`` on the result if needed).

    Args:
        leg: the leg.
        p_base_foot: (N, 3) target foot positions in the base frame, m (or (3,) for one target).
        q0: (N, n) initial joint values (or (n,), broadcast over the targets).
        tol: stop iterating a configuration once its residual norm is below ``tol`` (m).
        max_iter: maximum number of iterations.
        ok_tol: residual (m) below which a solution is flagged ok.

    Returns:
        q (N, n) joint values and ok (N,) bool (final residual < ``ok_tol``). A single (3,)
        target returns q (n,) and a 0-d bool array.
    """
    P = np.asarray(p_base_foot, dtype=float)
    single = P.ndim == 1
    P = np.atleast_2d(P)
    if P.shape[1] != 3:
        raise ModelError(f"p_base_foot must have shape (N, 3), got {np.shape(p_base_foot)}")
    sol = newton_ik(leg, P, q0, iterations=max_iter, stop_tol=tol, damping=1e-4, adaptive=True)
    ok = sol.err < ok_tol
    if single:
        return sol.q[0], np.asarray(ok[0])
    return sol.q, ok


def smoothstep(x, *, degree: int) -> np.ndarray:
    """Smoothstep of ``x`` clipped to [0, 1] (swing-foot paths, speed and load ramps): ``degree`` 3,
    ``3x^2 - 2x^3`` (zero slope at both ends), or 5, ``10x^3 - 15x^4 + 6x^5`` (zero slope and
    curvature)."""
    x = np.clip(x, 0.0, 1.0)
    if degree == 3:
        return x * x * (3.0 - 2.0 * x)
    if degree == 5:
        return x * x * x * (10.0 + x * (-15.0 + 6.0 * x))
    raise ValueError(f"smoothstep: degree must be 3 or 5, got {degree!r}")
