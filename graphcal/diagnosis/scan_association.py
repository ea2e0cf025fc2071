"""The chi-square of a 2D laser scan of the ground at any station, and the extrinsic fitted to scans
(used by :mod:`graphcal.diagnosis.association` for laser scanners; issue 29).

A scan is its points ``p_k`` (sensor frame, m) = range ``rho_k`` along the unit beam ``D_k``. At a
station with the ground's up direction ``u`` (body frame) and body height ``z`` (plane_corrections.py)
and the extrinsic ``(R, t)``: ``n = R^T u``, ``a = z + u . t`` (the sensor's height), ``b_k = n .
D_k`` (< 0 for a beam going down), predicted range ``-a / b_k`` and error ``e_k = rho_k + a / b_k``
(range noise ``sigma``, as factors/range_to_plane.py; a beam that would not meet the ground has
error ``rho_k``). The station's (tilt, height) covariance and the extrinsic's enter through their
Jacobians, ``C = sigma^2 I + J Sigma J^T``, inverted by the Woodbury identity:
``chi2 = (e.e - (J^T e)^T (sigma^2 Sigma^-1 + J^T J)^-1 J^T e) / sigma^2``.
"""

from __future__ import annotations

import numpy as np

from graphcal.diagnosis.plane_corrections import StationGrounds, prior_information, prior_residual, retract_extrinsic

__all__ = ["scan_beams", "scan_chi2", "fit_scan_extrinsic", "MIN_GRAZING_COS"]

#: beams closer than this cosine to parallel to the ground are not predicted (factors/range_to_plane.py)
MIN_GRAZING_COS = 0.02


def scan_beams(points) -> tuple[np.ndarray, np.ndarray]:
    """(D (K, 3) unit beams, rho (K,) ranges m) of scan points (K, 3) in the sensor frame."""
    P = np.asarray(points, dtype=float)
    rho = np.linalg.norm(P, axis=1)
    keep = rho > 1e-9
    return P[keep] / rho[keep, None], rho[keep]


def _scan_errors(D, rho, u, z, W, R, t):
    """(e (M, K), J_X (M, K, 3), J_S (M, K, 6)) of one scan at M stations."""
    n_p = u @ R  # (M, 3)
    a = z + u @ t  # (M,)
    b = n_p @ D.T  # (M, K)
    ok = b < -MIN_GRAZING_COS
    bb = np.where(ok, b, -1.0)
    e = np.where(ok, rho[None] + a[:, None] / bb, rho[None])
    RDW = np.einsum("ki,mil->mkl", D @ R.T, W)  # (R D_k)^T W
    tW = np.einsum("i,mil->ml", t, W)
    J_X = np.zeros(b.shape + (3,))
    J_X[..., :2] = tW[:, None, :] / bb[..., None] - (a[:, None] / bb**2)[..., None] * RDW
    J_X[..., 2] = 1.0 / bb
    J_S = np.zeros(b.shape + (6,))
    J_S[..., :3] = -(a[:, None] / bb**2)[..., None] * np.cross(D[None], n_p[:, None, :])
    J_S[..., 3:] = n_p[:, None, :] / bb[..., None]
    J_X[~ok] = 0.0
    J_S[~ok] = 0.0
    return e, J_X, J_S


def scan_chi2(D, rho, g: StationGrounds, T_body_sensor, sigma: float, cov_S=None) -> np.ndarray:
    """(M,) chi-square (K dof) of one scan (D, rho: :func:`scan_beams`) at every station of ``g``,
    range noise ``sigma`` (m), extrinsic ``T_body_sensor`` (4x4) with covariance ``cov_S`` (6x6,
    [phi rad, rho m]; None: exact)."""
    R, t = T_body_sensor[:3, :3], T_body_sensor[:3, 3]
    e, J_X, J_S = _scan_errors(D, rho, g.u, g.z, g.W, R, t)
    if cov_S is None:
        J, Sinv = J_X, np.linalg.inv(g.cov)
    else:
        J = np.concatenate([J_X, J_S], axis=2)
        Sinv = np.zeros((len(g.z), 9, 9))
        Sinv[:, :3, :3] = np.linalg.inv(g.cov)
        Sinv[:, 3:, 3:] = np.linalg.inv(cov_S)
    A = sigma**2 * Sinv + np.einsum("mki,mkj->mij", J, J)
    Jte = np.einsum("mki,mk->mi", J, e)
    return (np.einsum("mk,mk->m", e, e) - np.einsum("mi,mi->m", Jte, np.linalg.solve(A, Jte[..., None])[..., 0])) \
        / sigma**2


def fit_scan_extrinsic(scans: list, rows, g: StationGrounds, T0, prior: tuple, sigma: float, *,
                       huber: float = 3.0, iterations: int = 10) -> np.ndarray:
    """T_body_sensor (4x4) fitted from ``T0`` to ``scans`` ((D, rho) each) at the stations ``rows``
    (indices into ``g``) and the CAD ``prior`` (T, sigma_m, sigma_rad): Gauss-Newton on the range
    errors, Huber weight at ``huber`` sigma per beam (the stations' uncertainty left out)."""
    P = prior_information(prior)
    T = np.array(T0, dtype=float)
    for _ in range(iterations):
        R, t = T[:3, :3], T[:3, 3]
        H, bvec = P.copy(), np.zeros(6)
        for (D, rho), j in zip(scans, rows):
            sub = StationGrounds(g.ids[j:j + 1], g.u[j:j + 1], g.z[j:j + 1], g.W[j:j + 1], g.cov[j:j + 1], ())
            e, _, J = _scan_errors(D, rho, sub.u, sub.z, sub.W, R, t)
            e, J = e[0], J[0]
            w = np.where(np.abs(e) <= huber * sigma, 1.0, huber * sigma / np.maximum(np.abs(e), 1e-300)) / sigma**2
            H += np.einsum("k,ki,kj->ij", w, J, J)
            bvec += np.einsum("k,ki,k->i", w, J, e)
        delta = -np.linalg.solve(H, bvec + P @ prior_residual(T, prior[0]))
        T = retract_extrinsic(T, delta)
        if np.linalg.norm(delta) < 1e-10:
            break
    return T
