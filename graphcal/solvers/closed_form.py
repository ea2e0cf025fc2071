"""Closed-form initial values of a sensor extrinsic ``T_body_sensor`` from ground observations.

Pure numpy, no iteration except an optional Gauss–Newton polish of the laser-scanner case. The
results seed the factor graph (graphcal/solvers/batch.py); they do not depend on the CAD prior
except along directions the data does not determine, so a prior that is wrong by 180 deg of yaw
still gives the right answer when the stations tilt the body (Łabęcki 2012, Sec. 3.2: a gradient
method started far from the answer lands in a local minimum; a closed form has no start).

Setting (frames and signs as in graphcal/geometry.py): at station ``i``

* ``u_i = R_world_body^T e_z`` is the world "up" direction in the body frame (unit, from
  kinematics or the IMU), ``z_i`` the height of the body origin above the ground ``z = 0`` (m);
* the ground plane measured in the sensor frame is ``(n_i, d_i)``, canonical (``d_i >= 0``,
  ``n_i`` points from the plane towards the sensor);
* the true extrinsic ``T_body_sensor = (R, t)`` satisfies ``R n_i = u_i`` and
  ``d_i = z_i + u_i . t``  (the ground is ``u_i . x + z_i = 0`` in body coordinates).

Every function returns a ``rank``: the number of directions the data determines (3 for a rotation
or a translation, 6 for a pose). Directions below ``min_spread_deg`` of tilt variation count as
undetermined; those are taken from the prior (never the others).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.geometry import nearest_rotation, pose_matrix, skew, so3_exp

__all__ = [
    "rotation_from_normals",
    "translation_from_distances",
    "extrinsic_from_scan_points",
    "project_to_so3",
    "robust_closed_form_extrinsic",
]

#: Default threshold of "tilt variation": directions whose spread (RMS angle of the up vectors
#: about their mean, in that direction) is below this count as undetermined.
DEFAULT_MIN_SPREAD_DEG = 0.5


# ----------------------------------------------------------------------------- helpers
def _unit_rows(a, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.ndim == 1:
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != 3:
        raise GraphcalError(f"{name}: expected an (N, 3) array, got shape {np.shape(a)}")
    if not np.all(np.isfinite(a)):
        raise GraphcalError(f"{name}: contains NaN or inf")
    norms = np.linalg.norm(a, axis=1)
    if np.any(norms < 1e-12):
        raise GraphcalError(f"{name}: contains a zero vector")
    return a / norms[:, None]


def _weights(weights, n: int, name: str = "weights") -> np.ndarray:
    if weights is None:
        return np.ones(n)
    w = np.asarray(weights, dtype=float).reshape(-1)
    if w.shape != (n,):
        raise GraphcalError(f"{name}: expected {n} values, got shape {np.shape(weights)}")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise GraphcalError(f"{name}: must be finite and non-negative")
    return w


#: the rotation closest to a 3x3 matrix (Frobenius norm, det +1): :func:`graphcal.geometry.nearest_rotation`
project_to_so3 = nearest_rotation


def _min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector a to unit vector b."""
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(a @ b)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # antiparallel: half turn about any axis perpendicular to a
        p = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(p) < 1e-6:
            p = np.cross(a, [0.0, 1.0, 0.0])
        return so3_exp(p / np.linalg.norm(p) * np.pi)
    return so3_exp(axis / s * np.arctan2(s, c))


def _lstsq_with_prior(A: np.ndarray, y: np.ndarray, x_prior: np.ndarray | None, rcond: float,
                      ridge: float) -> tuple[np.ndarray, int]:
    """Least squares ``A x ~ y``; directions with singular value below ``rcond * s_max`` are
    undetermined: along them a ridge of weight ``ridge`` pulls x to ``x_prior`` (0 without a prior).
    The determined directions are pure data. Returns (x, number of determined directions)."""
    n = A.shape[1]
    xp = np.zeros(n) if x_prior is None else np.asarray(x_prior, dtype=float)
    if A.shape[0] == 0:
        return xp.copy(), 0
    A_pad = A if A.shape[0] >= n else np.vstack([A, np.zeros((n - A.shape[0], n))])
    _, S, Vt = np.linalg.svd(A_pad, full_matrices=False)
    s_max = S[0]
    determined = S > rcond * s_max if s_max > 0 else np.zeros(n, dtype=bool)
    # coefficients in the right-singular basis: c_k = v_k . x
    proj = Vt @ (A.T @ y)  # = s_k * (u_k . y)
    c = np.empty(n)
    c[determined] = proj[determined] / S[determined] ** 2
    und = ~determined
    denom = S[und] ** 2 + ridge
    num = proj[und] + ridge * (Vt[und] @ xp)
    c[und] = np.where(denom > 0, num / np.where(denom > 0, denom, 1.0), Vt[und] @ xp)
    return Vt.T @ c, int(determined.sum())


# ----------------------------------------------------------------------------- rotation
def rotation_from_normals(
    u_body,
    n_sensor,
    weights=None,
    *,
    R_prior=None,
    prior_weight: float = 1e-3,
    min_spread_deg: float = DEFAULT_MIN_SPREAD_DEG,
) -> tuple[np.ndarray, int]:
    """Rotation R = R_body_sensor with ``R n_i ~ u_i`` (Wahba's problem, solved by SVD).

    Args:
        u_body: (N, 3) up direction in the body frame per station (normalised here).
        n_sensor: (N, 3) ground normal in the sensor frame (canonical: towards the sensor).
        weights: optional (N,) non-negative weights (e.g. 1 / sigma_angle^2).
        R_prior: (3, 3) prior rotation (CAD); used ONLY for the rotation about the common up
            direction when the data does not determine it (rank 2).
        prior_weight: weight of the prior's three axis pseudo-observations, relative to the total
            data weight, when resolving that undetermined rotation against whatever weak
            information the data still has about it. Irrelevant when rank is 3.
        min_spread_deg: below this RMS spread of the directions the rotation about their mean
            counts as undetermined.

    Returns:
        (R (3, 3) proper rotation, rank): rank 3 when the up directions vary (roll/pitch
        variation), 2 when they are (nearly) parallel: the rotation about that direction then
        comes from ``R_prior`` (identity yaw without a prior), 0 with no data (R_prior or I).

    With ``B = sum_i w_i u_i n_i^T = U S V^T``, ``R = U diag(1, 1, det(U V^T)) V^T``. For exactly
    parallel data ``B`` has rank 1 and ``S_1 / S_0`` is the squared spread; rank 2 is reported when
    ``S_1 / S_0 < sin(min_spread)^2``. In that case ``R = Rot(u_bar, phi) R0`` where ``R0`` is the
    smallest rotation taking the mean normal to the mean up direction and ``phi`` maximises
    ``tr(Rot(u_bar, phi) R0 (B^T + prior_weight * sum(w) * R_prior^T))`` (a 1-D closed form).
    """
    U = _unit_rows(u_body, "u_body")
    N = _unit_rows(n_sensor, "n_sensor")
    if len(U) != len(N):
        raise GraphcalError(f"u_body has {len(U)} rows but n_sensor has {len(N)}")
    w = _weights(weights, len(U))
    Rp = None if R_prior is None else nearest_rotation(R_prior)
    W = float(w.sum())
    if len(U) == 0 or W <= 0:
        return (np.eye(3) if Rp is None else Rp.copy()), 0
    B = (U * w[:, None]).T @ N
    Us, S, Vt = np.linalg.svd(B)
    if S[0] <= 1e-15 * W:
        return (np.eye(3) if Rp is None else Rp.copy()), 0
    tol = np.sin(np.radians(min_spread_deg)) ** 2
    if S[1] >= tol * S[0]:
        return nearest_rotation(B), 3
    # one DOF undetermined: rotation about the mean up direction
    u_bar, n_bar = Us[:, 0], Vt[0]
    R0 = _min_rotation(n_bar, u_bar)
    M = R0 @ B.T
    if Rp is not None:
        M = M + prior_weight * W * (R0 @ Rp.T)
    K = skew(u_bar)
    a = np.trace(M) - u_bar @ M @ u_bar
    b = np.trace(K @ M)
    phi = float(np.arctan2(b, a)) if (abs(a) + abs(b)) > 0 else 0.0
    return so3_exp(u_bar * phi) @ R0, 2


# ----------------------------------------------------------------------------- translation
def translation_from_distances(
    u_body,
    d_sensor,
    z_body,
    weights=None,
    *,
    t_prior=None,
    prior_weight: float = 1e-6,
    min_spread_deg: float = DEFAULT_MIN_SPREAD_DEG,
) -> tuple[np.ndarray, int]:
    """Translation t = t_body_sensor from ``d_i - z_i = u_i . t`` (linear least squares).

    Args:
        u_body: (N, 3) up direction in the body frame per station.
        d_sensor: (N,) ground distance measured by the sensor (m, canonical d >= 0).
        z_body: (N,) body height above the ground (m).
        weights: optional (N,) weights (e.g. 1 / sigma_d^2).
        t_prior: (3,) prior translation; used only along undetermined directions (0 without).
        prior_weight: ridge weight towards ``t_prior`` along undetermined directions, relative to
            the total data weight.
        min_spread_deg: a direction with less tilt spread than this counts as undetermined.

    Returns:
        (t (3,), rank): rank 3 needs roll and pitch variation; level stations give rank 1 (only
        the component along up, i.e. the height, is determined; x and y come from the prior).
    """
    U = _unit_rows(u_body, "u_body")
    d = np.asarray(d_sensor, dtype=float).reshape(-1)
    z = np.asarray(z_body, dtype=float).reshape(-1)
    if d.shape != (len(U),) or z.shape != (len(U),):
        raise GraphcalError(f"d_sensor and z_body need {len(U)} values, got {d.shape} and {z.shape}")
    if not (np.all(np.isfinite(d)) and np.all(np.isfinite(z))):
        raise GraphcalError("d_sensor / z_body contain NaN or inf")
    w = _weights(weights, len(U))
    sw = np.sqrt(w)
    A = U * sw[:, None]
    y = (d - z) * sw
    tp = None if t_prior is None else np.asarray(t_prior, dtype=float).reshape(3)
    return _lstsq_with_prior(A, y, tp, np.sin(np.radians(min_spread_deg)), prior_weight * max(w.sum(), 1e-300))


# ----------------------------------------------------------------------------- laser scanner / points
def _point_residuals_and_jacobian(U: np.ndarray, z: np.ndarray, P: np.ndarray, R: np.ndarray, t: np.ndarray):
    """Residual ``u . (R p + t) + z`` per point and its Jacobian w.r.t. the right perturbation
    [omega, v] of (R, t): row = [p x (R^T u), R^T u]."""
    a = U @ R  # rows: R^T u
    r = np.einsum("ij,ij->i", U, P @ R.T + t) + z
    J = np.hstack([np.cross(P, a), a])
    return r, J


def _tilt_rank(U_st: np.ndarray, min_spread_deg: float) -> int:
    """How many directions the station up vectors span (1 = level, 2 = tilt about one axis, 3 = roll
    and pitch variation), with ``min_spread_deg`` as the threshold of a spread."""
    if len(U_st) == 0:
        return 0
    ev = np.linalg.eigvalsh(U_st.T @ U_st / len(U_st))[::-1]
    tol = np.sin(np.radians(min_spread_deg)) ** 2
    return int(np.sum(ev > tol * ev[0]))


def _plane_per_station(P: np.ndarray):
    """(n, d) canonical plane through a station's 3D points, or None when they do not span a plane."""
    if len(P) < 3:
        return None
    c = P.mean(axis=0)
    w, V = np.linalg.eigh((P - c).T @ (P - c) / len(P))
    if w[1] <= 1e-12 * max(w[2], 1e-300):
        return None
    n = V[:, 0]
    d = -float(n @ c)
    return (-n, -d) if d < 0 else (n, d)


def _gauss_newton_points(U, z, P, R, t, scale, rcond, iterations, robust=False):
    """Gauss–Newton on the point heights over the right perturbation of (R, t); undetermined
    directions (relative singular value below rcond) are not moved. With ``robust``, each step is
    reweighted (IRLS, Cauchy weights at 2.385 robust standard deviations of the current residuals) so that
    points off the floor (boxes, legs) do not bias the answer. Returns (R, t, cost, rank), cost the
    (weighted) sum of squares."""

    def weights(r):
        if not robust:
            return np.ones_like(r)
        c = 2.385 * max(1.4826 * float(np.median(np.abs(r))), 1e-9)
        return 1.0 / (1.0 + (r / c) ** 2)

    def svd_scaled(J, w):
        _, S, Vt = np.linalg.svd(J * scale * np.sqrt(w)[:, None], full_matrices=False)
        keep = S > rcond * S[0] if S[0] > 0 else np.zeros_like(S, dtype=bool)
        return S, Vt, keep

    r, J = _point_residuals_and_jacobian(U, z, P, R, t)
    w = weights(r)
    for _ in range(max(0, int(iterations))):
        S, Vt, keep = svd_scaled(J, w)
        if not keep.any():
            break
        g = (J * scale).T @ (w * r)
        step_s = -(Vt[keep].T @ ((Vt[keep] @ g) / S[keep] ** 2))
        xi = step_s * scale
        for _halving in range(8):  # backtracking: far from the answer a full step can overshoot
            R_new = R @ so3_exp(xi[:3])
            t_new = t + R @ xi[3:]
            r_new, J_new = _point_residuals_and_jacobian(U, z, P, R_new, t_new)
            if r_new @ (w * r_new) <= r @ (w * r):
                break
            xi = 0.5 * xi
        else:
            break
        R, t, r, J = R_new, t_new, r_new, J_new
        w = weights(r)
        if np.linalg.norm(step_s) < 1e-14 * float(np.max(scale)):
            break
    S, _, keep = svd_scaled(J, w)
    return R, t, float(r @ (w * r)), int(keep.sum())


def _ground_symmetric_starts(R: np.ndarray, t: np.ndarray, U_st: np.ndarray, z_st: np.ndarray, n_yaw: int):
    """Starting points related to (R, t) by the symmetries of a level floor, which only the body tilts
    (and anything off the floor) break: turns of the sensor about the vertical through the point
    of the ground under the body origin (``n_yaw`` evenly spaced angles, 0 included), each also
    reflected through the ground with its scan mirrored (under the floor, looking up; the rotation
    stays proper). A 2D scan fits a level floor equally well from all of them."""
    u0 = U_st.mean(axis=0)
    u0 /= np.linalg.norm(u0)
    c = -float(np.mean(z_st)) * u0  # the ground under the body origin, body frame
    H = np.eye(3) - 2.0 * np.outer(u0, u0)
    starts = []
    for k in range(n_yaw):
        Ry = so3_exp(u0 * (2.0 * np.pi * k / n_yaw))
        Rk, tk = Ry @ R, Ry @ (t - c) + c
        starts.append((Rk, tk))
        starts.append((H @ Rk @ np.diag([1.0, 1.0, -1.0]), H @ (tk - c) + c))
    return starts


def _stacked_points(U_st: np.ndarray, z_st: np.ndarray, points_sensor_list: Sequence) -> tuple:
    """The scan points of :func:`extrinsic_from_scan_points` checked and stacked: (per station the
    finite points (N_i, 3) in the sensor frame (m; 2D scans get z = 0), all points P (N, 3), each
    point's station up direction U (N, 3) in the body frame and body height z (N,), m)."""
    Ps, Us, zs = [], [], []
    for i, pts in enumerate(points_sensor_list):
        P = np.asarray(pts, dtype=float)
        if P.ndim != 2 or P.shape[1] not in (2, 3):
            raise GraphcalError(f"points_sensor_list[{i}]: expected (N, 2) or (N, 3), got shape {P.shape}")
        if P.shape[1] == 2:
            P = np.hstack([P, np.zeros((len(P), 1))])
        P = P[np.all(np.isfinite(P), axis=1)]
        Ps.append(P)
        Us.append(np.repeat(U_st[i : i + 1], len(P), axis=0))
        zs.append(np.full(len(P), z_st[i]))
    P = np.vstack(Ps) if Ps else np.zeros((0, 3))
    U = np.vstack(Us) if Us else np.zeros((0, 3))
    z = np.concatenate(zs) if zs else np.zeros(0)
    return Ps, P, U, z


def _best_solution(solutions: list, U_st: np.ndarray, z_st: np.ndarray, U: np.ndarray, z: np.ndarray,
                   P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of the solution (R, t, _, rank) whose sensor origin is above the ground (median over
    the stations: up directions ``U_st``, body heights ``z_st``, m) with the lowest median absolute
    point height (points ``P`` in the sensor frame with their ``U``, ``z``)."""
    best = None
    for R, t, _, rank in solutions:
        above = bool(np.median(U_st @ t + z_st) > 0.0)  # the sensor origin's height above the ground
        r, _ = _point_residuals_and_jacobian(U, z, P, R, t)
        key = (not above, float(np.median(np.abs(r))))
        # earlier candidates win ties: a level floor's turned copies fit exactly as well, and the
        # first solutions keep the prior's value along the directions the data do not determine
        if best is None or key[0] < best[2][0] or (key[0] == best[2][0] and key[1] < best[2][1] * (1 - 1e-9)):
            best = (R, t, key, rank)
    return best[0], best[1]


def extrinsic_from_scan_points(
    u_body_list,
    z_body_list,
    points_sensor_list: Sequence,
    *,
    T_prior=None,
    min_spread_deg: float = DEFAULT_MIN_SPREAD_DEG,
    gauss_newton_iterations: int = 10,
) -> tuple[np.ndarray, int]:
    """Extrinsic from ground points seen by the sensor (Łabęcki 2012: every point on z_world = 0).

    For every point ``p`` of station ``i``: ``u_i . (R p + t) + z_i = 0``. This is linear in the
    entries of R and t:

    * 2D laser scanner (all points have ``p_z = 0``, or (N, 2) arrays): unknowns are the first two
      columns of R and t (9); the third column is ``r1 x r2``;
    * 3D points (not all in the sensor's x-y plane): all 12 unknowns (R and t). A second candidate
      comes from a plane fitted to each station's points (:func:`rotation_from_normals`,
      :func:`translation_from_distances`); the one with the lower point residual wins.
    * with ``T_prior`` given, the prior is one more starting point for the Gauss–Newton polish: with
      little tilt variation the linear system has a degenerate near-solution (the scan plane lying
      on the ground) that only a start near the truth avoids.
    * a 2D scan fits a level floor exactly as well from the scanner turned about the vertical or
      reflected through the ground (under the floor, looking up, its scan mirrored); every
      candidate's copies (8 turns, each also reflected) are refined too, and candidates whose origin
      lies below the ground (median over the stations) lose.

    Among the rest the lowest median absolute point height wins (robust to points off the floor:
    boxes, legs), and its Gauss–Newton polish is reweighted (Cauchy).

    The linear least-squares solution is projected to SO(3) (polar decomposition), then t is
    solved again by linear least squares given R, then (``gauss_newton_iterations`` > 0) a few
    Gauss–Newton steps on the 6-DOF pose minimise the same point heights exactly (the linear
    solution ignores the orthonormality of R, which matters with noisy points).

    The prior enters only along directions the data does not determine: when the station up
    vectors span all three directions (roll and pitch variation) the linear solve is pure data;
    otherwise directions with a relative singular value below ``sin(min_spread_deg)`` are taken
    from ``T_prior``.

    Args:
        u_body_list: (M, 3) up direction in the body frame per station.
        z_body_list: (M,) body height per station (m).
        points_sensor_list: M arrays (N_i, 3) or (N_i, 2) of ground points in the sensor frame (m).
        T_prior: (4, 4) prior extrinsic (CAD); identity without one.

    Returns:
        (T_body_sensor (4, 4), rank): rank = number of pose directions (of 6) the points
        determine; 6 needs roll and pitch variation. A scanner at a level body gives 3 (its roll,
        pitch and height); the others then come from ``T_prior``.
    """
    U_st = _unit_rows(u_body_list, "u_body_list")
    z_st = np.asarray(z_body_list, dtype=float).reshape(-1)
    if z_st.shape != (len(U_st),) or len(points_sensor_list) != len(U_st):
        raise GraphcalError(
            f"u_body_list ({len(U_st)}), z_body_list ({z_st.size}) and points_sensor_list "
            f"({len(points_sensor_list)}) need one entry per station"
        )
    if not np.all(np.isfinite(z_st)):
        raise GraphcalError("z_body_list contains NaN or inf")
    Ps, P, U, z = _stacked_points(U_st, z_st, points_sensor_list)
    Tp = np.eye(4) if T_prior is None else np.asarray(T_prior, dtype=float)
    if Tp.shape != (4, 4) or not np.all(np.isfinite(Tp)):
        raise GraphcalError(f"T_prior: expected a finite 4x4 pose, got shape {Tp.shape}")
    Rp = nearest_rotation(Tp[:3, :3])
    tp = Tp[:3, 3].copy()
    if len(P) == 0:
        return pose_matrix(Rp, tp), 0

    # characteristic length so that the columns u*p/L and u have comparable scale
    L = float(np.sqrt(np.mean(np.sum(P**2, axis=1)))) or 1.0
    planar = bool(np.max(np.abs(P[:, 2])) <= 1e-9 * L)
    spread_rcond = np.sin(np.radians(min_spread_deg))
    full_tilt = _tilt_rank(U_st, min_spread_deg) == 3
    lin_rcond = 1e-10 if full_tilt else spread_rcond
    ridge = 1e-6 * len(z)

    candidates = []
    if planar:
        A = np.hstack([U * (P[:, 0:1] / L), U * (P[:, 1:2] / L), U])
        x_prior = np.concatenate([Rp[:, 0] * L, Rp[:, 1] * L, tp])
        x, _ = _lstsq_with_prior(A, -z, x_prior, lin_rcond, ridge)
        r1, r2 = x[0:3] / L, x[3:6] / L
        s = 0.5 * (np.linalg.norm(r1) + np.linalg.norm(r2))
        M = np.column_stack([r1, r2, np.cross(r1, r2) / s if s > 0 else np.zeros(3)])
        candidates.append(M)
    else:
        A = np.hstack([U * (P[:, 0:1] / L), U * (P[:, 1:2] / L), U * (P[:, 2:3] / L), U])
        x_prior = np.concatenate([Rp[:, 0] * L, Rp[:, 1] * L, Rp[:, 2] * L, tp])
        x, _ = _lstsq_with_prior(A, -z, x_prior, lin_rcond, ridge)
        candidates.append(np.column_stack([x[0:3], x[3:6], x[6:9]]) / L)
        planes = [(i, _plane_per_station(Pi)) for i, Pi in enumerate(Ps)]
        planes = [(i, pl) for i, pl in planes if pl is not None]
        if planes:
            idx = [i for i, _ in planes]
            R_pl, _ = rotation_from_normals(U_st[idx], np.array([pl[0] for _, pl in planes]), R_prior=Rp,
                                            min_spread_deg=min_spread_deg)
            candidates.append(R_pl)

    # The prior as one more start: with little tilt variation the linear system has a degenerate
    # near-solution (the scan plane lying on the ground: r1, r2 -> 0, every point "on" it), which
    # Gauss-Newton from the linear answer cannot leave; the lower point residual decides.
    if T_prior is not None:
        candidates.append(Rp)
    scale = np.array([L, L, L, 1.0, 1.0, 1.0])  # rotation columns in metres at the point range
    solutions = []
    for M in candidates:
        if not np.all(np.isfinite(M)) or np.linalg.norm(M) < 1e-12:
            M = Rp
        R = nearest_rotation(M)
        # t given R: u . t = -z - u . R p  (translation_from_distances with d = -u . R p)
        d_eff = -np.einsum("ij,ij->i", U, P @ R.T)
        t, _ = translation_from_distances(U, d_eff, z, t_prior=tp, min_spread_deg=min_spread_deg)
        solutions.append(_gauss_newton_points(U, z, P, R, t, scale, spread_rcond, gauss_newton_iterations))
    if planar:
        # A 2D scan fits a level floor as well turned about the vertical or reflected through the
        # ground (under it, looking up); only the tilts and points off the floor tell these apart,
        # and least squares can settle in the wrong one (the linear solution is often the point
        # reflection). Every solution's symmetric copies are refined too (on a subsample of at most
        # 2000 points), the physical rule "the scanner is above the ground" removes the reflections,
        # and the lowest median absolute point height picks among the rest.
        # The search also moves directions that small tilts determine only weakly (relative singular
        # value down to 1e-3, not sin(min_spread_deg)): stopping short along them leaves the start's
        # (wrong) value there. Directions with no information at all (level body) stay truncated.
        search_rcond = min(spread_rcond, 1e-3)
        sub = np.linspace(0, len(P) - 1, min(len(P), 2000)).astype(int)
        for R0, t0, _, _ in list(solutions):
            for R, t in _ground_symmetric_starts(R0, t0, U_st, z_st, n_yaw=8):
                solutions.append(_gauss_newton_points(U[sub], z[sub], P[sub], R, t, scale, search_rcond,
                                                      gauss_newton_iterations, robust=True))
    R, t = _best_solution(solutions, U_st, z_st, U, z, P)
    best = _gauss_newton_points(U, z, P, R, t, scale, spread_rcond, gauss_newton_iterations, robust=True)
    R, t, _, rank = best
    return pose_matrix(R, t), rank


def robust_closed_form_extrinsic(u: np.ndarray, n: np.ndarray, d: np.ndarray, z: np.ndarray, T_prior: np.ndarray):
    """Closed-form extrinsic ``T_body_sensor`` (4x4, m) from planes, with stations whose residual is
    far off the rest trimmed (outlier stations would otherwise pull the closed form).

    Args: per station, ``u`` (N, 3) the ground's up direction in the body frame, ``n`` (N, 3) and
    ``d`` (N,) the plane measured in the sensor frame (unit normal towards the sensor, distance m),
    ``z`` (N,) the body origin's height above the ground (m); ``T_prior`` (4x4) the CAD extrinsic
    (it fixes directions the planes do not determine).
    """
    keep = np.ones(len(u), dtype=bool)
    for _ in range(4):
        R, _ = rotation_from_normals(u[keep], n[keep], R_prior=T_prior[:3, :3])
        ang = np.arccos(np.clip(np.einsum("ij,ij->i", (n @ R.T), u), -1.0, 1.0))
        t, _ = translation_from_distances(u[keep], d[keep], z[keep], t_prior=T_prior[:3, 3])
        res = d - z - u @ t
        a_med = np.median(ang[keep])
        r_mad = np.median(np.abs(res[keep] - np.median(res[keep]))) + 1e-6
        new_keep = (ang < max(6 * a_med, np.radians(0.3))) & (np.abs(res - np.median(res[keep])) < max(8 * r_mad, 0.005))
        if new_keep.sum() < 3 or np.array_equal(new_keep, keep):
            break
        keep = new_keep
    return pose_matrix(R, t)
