"""The ground plane each station predicts for a sensor, without that sensor's planes, and the
chi-square of any measured plane (or a sign / convention / unit variant of it) at any station.

Used by :mod:`graphcal.diagnosis.association` (issue 29). Frames: a station's body frame, the
sensor frame of ``T_body_sensor = (R, t)`` (4x4, m); the ground is the world plane z = 0.

Prediction. A station gives the ground's up direction ``u`` in its body frame and the body
origin's height ``z`` above it -- from its stance feet (the plane through >= 3 feet on the nominal
legs) or, without joint angles, from its commanded pose -- never from the sensor's own planes.
The sensor then sees ``n = R^T u``, ``d = z + u . t`` (n towards the sensor, d >= 0).

Uncertainty of the prediction, at physical noise (dataset.yaml ``physical_noise:``): a tilt ``a``
(2, rad, along a basis ``W`` orthogonal to ``u``) and a height ``b`` (m) of the station's ground,
covariance ``sigma_f^2 (A^T A)^-1`` with rows ``A_i = [W^T p_i, 1]`` over the stance feet ``p_i``
(``sigma_f``: the feet's height on the ground, their contact and the encoders through the foot's
lever), or ``diag(commanded_deg^2, commanded_deg^2, commanded_mm^2)`` from a commanded pose; and the
extrinsic's own covariance (``[phi, rho]``, right perturbation of ``T_body_sensor``).

Error of a plane ``(n_m, d_m)`` with basis ``B`` orthogonal to ``n_m``: ``e = [B^T n theta / sin
theta, d - d_m]`` (rad, rad, m; ``theta`` the angle between measured and predicted normal, so a
normal off by more than 90 deg is not read as small), its covariance ``Gm^T cov4 Gm`` (the plane
fit's, plane_observation.plane_cov3) ``+ J_X Sigma_ab J_X^T + J_S Sigma_S J_S^T``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graphcal.factors.plane_observation import plane_cov3, tangent_basis
from graphcal.geometry import so3_exp, so3_log

__all__ = ["StationGrounds", "station_grounds", "PLANE_VARIANTS", "plane_variant", "plane_rows", "chi2_rows",
           "fit_extrinsic", "prior_information", "prior_residual", "retract_extrinsic",
           "DEFAULT_PLANE_COV4"]

#: a plane without a covariance in planes.csv: 1 mm and ~0.06 deg (calibration/graph.py's default)
DEFAULT_PLANE_COV4 = np.diag([1e-6, 1e-6, 1e-6, 1e-6])

#: the variants of a measured plane tried as bookkeeping errors: (cause, detail)
PLANE_VARIANTS = (
    ("", ""),  # as given
    ("normal_sign", "x"), ("normal_sign", "y"), ("normal_sign", "z"),
    ("plane_convention", "n -> -n"),
    ("distance_unit", "mm"), ("distance_unit", "cm"),
)


def plane_variant(n: np.ndarray, d: float, variant: tuple) -> tuple[np.ndarray, float]:
    """(n, d) corrected as ``variant`` (an entry of :data:`PLANE_VARIANTS`) says the data were
    written: a component's sign flipped back, the normal negated, d from mm / cm to m."""
    cause, detail = variant
    n = np.array(n, dtype=float)
    if cause == "normal_sign":
        n["xyz".index(detail)] *= -1.0
    elif cause == "plane_convention":
        n = -n
    elif cause == "distance_unit":
        d = d / (1000.0 if detail == "mm" else 100.0)
    return n, float(d)


@dataclass(frozen=True, eq=False)
class StationGrounds:
    """Per station (in data order): ``ids`` (M,), ``u`` (M, 3) up in the body frame, ``z`` (M,)
    body height (m), ``W`` (M, 3, 2) tilt basis, ``cov`` (M, 3, 3) covariance of (tilt rad x2,
    height m), ``source`` (M,) "feet" or "commanded"."""

    ids: np.ndarray
    u: np.ndarray
    z: np.ndarray
    W: np.ndarray
    cov: np.ndarray
    source: tuple


def station_grounds(data, robot, physical: dict) -> StationGrounds:
    """The ground each station of ``data`` predicts (module docstring); ``physical`` is
    dataset.yaml's physical noise (key -> deg / mm, calibration.adequacy.physical_noise)."""
    from graphcal.calibration.kinematic_pose import kinematic_bodies, leg_kinematics

    u_body, height, _ = kinematic_bodies(data, robot)
    kin = leg_kinematics(data, robot) if any(len(st.q_by_foot) >= 3 for st in data.stations) else {}
    ground = 1e-3 * physical["ground_mm"]
    contact = 1e-3 * physical["contact_mm"]
    joint = np.radians(physical["joint_deg"])
    ids, us, zs, Ws, covs, src = [], [], [], [], [], []
    for st in data.stations:
        u = np.asarray(u_body[st.station], dtype=float)
        W = tangent_basis(u)
        if len(st.q_by_foot) >= 3:
            P = np.array([kin[(st.station, f)][0] for f in st.q_by_foot])
            sig2 = ground**2 + contact**2 + 2.0 * (joint * np.linalg.norm(P, axis=1)) ** 2
            A = np.column_stack([P @ W, np.ones(len(P))])
            cov = np.linalg.inv(A.T @ (A / sig2[:, None]))
            src.append("feet")
        else:
            cov = np.diag([np.radians(physical["commanded_deg"]) ** 2] * 2 + [(1e-3 * physical["commanded_mm"]) ** 2])
            src.append("commanded")
        ids.append(st.station)
        us.append(u)
        zs.append(float(height[st.station]))
        Ws.append(W)
        covs.append(cov)
    return StationGrounds(np.array(ids), np.array(us), np.array(zs), np.array(Ws), np.array(covs), tuple(src))


def plane_rows(n_m: np.ndarray, d_m: np.ndarray, cov4: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n (K, 3) unit, d (K,), cov3 (K, 3, 3)) of K planes (normals (K, 3), distances m, 4x4
    covariances or None each), cov3 the plane fit's covariance of ``[B^T n, d]``."""
    n_m = np.asarray(n_m, dtype=float)
    n_m = n_m / np.linalg.norm(n_m, axis=1, keepdims=True)
    cov3 = np.array([plane_cov3(n, DEFAULT_PLANE_COV4 if c is None else np.asarray(c)) for n, c in zip(n_m, cov4)])
    return n_m, np.asarray(d_m, dtype=float), cov3


def _errors(n_m, d_m, u, z, W, R, t, B=None, with_S: bool = True):
    """(e (K, 3), J_X (K, 3, 3), J_S (K, 3, 6), or None without ``with_S``) of K planes (n_m (K, 3),
    d_m (K,); B (K, 3, 2) their tangent bases, or None) at K stations (u (K, 3), z (K,), W (K, 3, 2))."""
    k = len(d_m)
    B = np.array([tangent_basis(n) for n in n_m]) if B is None else B  # (K, 3, 2)
    Bt = np.swapaxes(B, 1, 2)  # (K, 2, 3)
    n_p = u @ R  # (K, 3): R^T u
    d_p = z + u @ t
    v = (Bt @ n_p[:, :, None])[:, :, 0]  # (K, 2)
    c = np.clip(np.sum(n_p * n_m, axis=1), -1.0, 1.0)
    theta = np.arccos(c)
    s = np.linalg.norm(v, axis=1)
    scale = np.where(s > 1e-12, theta / np.maximum(s, 1e-12), 1.0)
    e = np.empty((k, 3))
    e[:, :2] = v * scale[:, None]
    e[:, 2] = d_p - d_m
    J_X = np.zeros((k, 3, 3))
    J_X[:, :2, :2] = (Bt @ R.T) @ W  # B^T R^T W
    J_X[:, 2, :2] = (t @ W)  # (K, 2)
    J_X[:, 2, 2] = 1.0
    if not with_S:
        return e, J_X, None
    nx = np.zeros((k, 3, 3))  # [n_p]x
    nx[:, 0, 1], nx[:, 0, 2], nx[:, 1, 2] = -n_p[:, 2], n_p[:, 1], -n_p[:, 0]
    nx[:, 1, 0], nx[:, 2, 0], nx[:, 2, 1] = n_p[:, 2], -n_p[:, 1], n_p[:, 0]
    J_S = np.zeros((k, 3, 6))
    J_S[:, :2, :3] = Bt @ nx
    J_S[:, 2, 3:] = n_p
    return e, J_X, J_S


def _inverse3(C: np.ndarray) -> np.ndarray:
    """(K, 3, 3) inverses of K 3x3 matrices by their adjugates (elementwise over K: a tenth of
    numpy.linalg.inv's time on the small stacks the association evaluates ~100 times)."""
    a, b, c = C[:, 0, 0], C[:, 0, 1], C[:, 0, 2]
    d, e, f = C[:, 1, 0], C[:, 1, 1], C[:, 1, 2]
    g, h, i = C[:, 2, 0], C[:, 2, 1], C[:, 2, 2]
    adj = np.empty_like(C)
    adj[:, 0, 0], adj[:, 0, 1], adj[:, 0, 2] = e * i - f * h, c * h - b * i, b * f - c * e
    adj[:, 1, 0], adj[:, 1, 1], adj[:, 1, 2] = f * g - d * i, a * i - c * g, c * d - a * f
    adj[:, 2, 0], adj[:, 2, 1], adj[:, 2, 2] = d * h - e * g, b * g - a * h, a * e - b * d
    det = a * adj[:, 0, 0] + b * adj[:, 1, 0] + c * adj[:, 2, 0]
    return adj / det[:, None, None]


def chi2_rows(n_m, d_m, cov3, u, z, W, cov_ab, T_body_sensor, cov_S=None, *, jacobian: bool = False, B=None):
    """(K,) chi-square (3 dof) of K planes (n_m (K, 3) unit, d_m (K,) m, cov3 (K, 3, 3)) each at
    its station (u (K, 3), z (K,), W (K, 3, 2), cov_ab (K, 3, 3)) for the extrinsic
    ``T_body_sensor`` (4x4) with covariance ``cov_S`` (6x6, [phi rad, rho m]; None: exact); with
    ``jacobian`` also (e (K, 3), C^-1 (K, 3, 3), J_S (K, 3, 6)); ``B`` (K, 3, 2): the planes'
    tangent bases (plane_observation.tangent_basis) when known."""
    R, t = T_body_sensor[:3, :3], T_body_sensor[:3, 3]
    e, J_X, J_S = _errors(n_m, d_m, u, z, W, R, t, B, with_S=jacobian or cov_S is not None)
    C = cov3 + J_X @ cov_ab @ np.swapaxes(J_X, 1, 2)
    if cov_S is not None:
        C = C + J_S @ cov_S @ np.swapaxes(J_S, 1, 2)
    Ci = _inverse3(C)
    chi = np.sum((Ci @ e[:, :, None])[:, :, 0] * e, axis=1)
    return (chi, e, Ci, J_S) if jacobian else chi


def prior_information(prior: tuple) -> np.ndarray:
    """6x6 information [phi, rho] of the CAD ``prior`` (T, sigma_m, sigma_rad) of an extrinsic,
    each sigma floored at 1e-4."""
    _, sig_m, sig_rad = prior
    return np.diag([max(sig_rad, 1e-4) ** -2] * 3 + [max(sig_m, 1e-4) ** -2] * 3)


def prior_residual(T: np.ndarray, T_cad: np.ndarray) -> np.ndarray:
    """[phi, rho] of T_body_sensor ``T`` (4x4) from the CAD extrinsic ``T_cad``: the rotation
    vector of R_cad^T R (rad) and the translation difference t - t_cad in T's sensor frame (m)."""
    R, t = T[:3, :3], T[:3, 3]
    return np.concatenate([so3_log(T_cad[:3, :3].T @ R), R.T @ (t - T_cad[:3, 3])])


def retract_extrinsic(T: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """T_body_sensor (4x4) moved by ``delta`` = [phi (rad), rho (m)], both in the sensor frame."""
    out = np.eye(4)
    out[:3, :3] = T[:3, :3] @ so3_exp(delta[:3])
    out[:3, 3] = T[:3, 3] + T[:3, :3] @ delta[3:]
    return out


def fit_extrinsic(n_m, d_m, cov3, g: StationGrounds, rows: np.ndarray, T0: np.ndarray, prior: tuple,
                  *, huber: float = 3.0, iterations: int = 10, B=None) -> tuple[np.ndarray, np.ndarray, float]:
    """(T_body_sensor (4x4), its 6x6 covariance [phi, rho], the cost: the planes' Huber-weighted
    chi-square + the prior's) that best explains K planes (n_m (K, 3), d_m (K,), cov3 (K, 3, 3), as
    :func:`plane_rows`) at the stations ``rows`` (K indices into ``g``), from ``T0``, with the CAD
    ``prior`` (T (4x4), sigma_m, sigma_rad); Gauss-Newton, Huber weight ``huber`` on the square root
    of each plane's chi-square."""
    P = prior_information(prior)
    rows = np.asarray(rows, dtype=int)
    u, z, W, cab = g.u[rows], g.z[rows], g.W[rows], g.cov[rows]
    T = np.array(T0, dtype=float)
    H, cost = P, 0.0
    B = np.array([tangent_basis(n) for n in n_m]) if B is None else B
    for _ in range(iterations):
        chi, e, Ci, J = chi2_rows(n_m, d_m, cov3, u, z, W, cab, T, jacobian=True, B=B)
        w = np.where(chi <= huber**2, 1.0, huber / np.sqrt(np.maximum(chi, 1e-300)))
        r_p = prior_residual(T, prior[0])
        cost = float(np.sum(np.where(chi <= huber**2, chi, 2 * huber * np.sqrt(chi) - huber**2)) + r_p @ P @ r_p)
        H = np.einsum("k,kji,kjl,klm->im", w, J, Ci, J) + P
        b = np.einsum("k,kji,kjl,kl->i", w, J, Ci, e) + P @ r_p
        delta = -np.linalg.solve(H, b)
        T = retract_extrinsic(T, delta)
        if np.linalg.norm(delta) < 1e-10:
            break
    return T, np.linalg.inv(H), cost
