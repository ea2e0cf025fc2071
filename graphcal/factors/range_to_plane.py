"""Range-to-plane factor: the measured range of each beam against the range at which that beam meets
the ground, for range sensors whose noise is along the beam (2D laser scanners; dense mode).

Why not the point's height above the plane (point_to_plane.py)? With noise along the beam, a point's
height error is ``eps * (n . R d)``: it depends on the unknown rotation R. Least squares on heights
then prefers rotations that flatten the beams (a smaller ``n . R d`` hides the noise): an
errors-in-variables bias, measured at 3.5 deg on a simulated Hokuyo on the Messor (clean data: exact).
The range residual has constant noise ``sigma_range`` and is the maximum-likelihood criterion.

Variables: X = T_world_body (Pose3), S = T_body_sensor (Pose3). Ground (world): ``n . x + c = 0``
(default z = 0). Measurement: for each beam, its unit direction ``d_i`` and range ``rho_i`` in the
sensor frame (``p_i = rho_i d_i``).

With T_ws = X S = (R, t):  a = n . t + c  (sensor height above the plane),  b_i = n . (R d_i)
(< 0 for a beam going down), predicted range ``r_i = -a / b_i`` and error ``e_i = rho_i - r_i``.

Jacobians for a right perturbation [phi, rho_t] of T_ws: ``da/drho_t = n^T R``,
``db_i/dphi = (d_i x R^T n)^T``; ``de_i/dphi = -a/b_i^2 db_i/dphi``, ``de_i/drho_t = n^T R / b_i``.
X's perturbation reaches T_ws through ``Ad(S^-1)``, S's directly.
"""

from __future__ import annotations

import gtsam
import numpy as np

from graphcal.factors.checked import checked_custom_factor, with_robust, world_plane
from graphcal.geometry import pose_adjoint

__all__ = ["range_to_plane_error", "range_to_plane_factor", "checked_scan_points", "MIN_GRAZING_COS"]

#: beams whose direction is within this cosine of parallel to the ground are not used (their
#: predicted range is unbounded)
MIN_GRAZING_COS = 0.02


def range_to_plane_error(T_world_body, T_body_sensor, points_sensor, plane_world=None, want_jacobians: bool = True):
    """Range residuals (m) of each beam, and analytic Jacobians (pure numpy).

    Args:
        T_world_body: 4x4 body pose X.
        T_body_sensor: 4x4 extrinsic S.
        points_sensor: (N, 3) measured points in the sensor frame (m); the beam is the direction
            from the sensor origin to the point, the range its norm.
        plane_world: (4,) ``[nx, ny, nz, c]``; None for the ground z = 0.

    Returns:
        e (N,) m, and ``[H_X (N, 6), H_S (N, 6)]`` or None. A beam that does not go towards the
        plane (``b_i >= -MIN_GRAZING_COS``) gets error 0 and zero Jacobian rows (it carries no
        information at this estimate).
    """
    X = np.asarray(T_world_body, dtype=float)
    S = np.asarray(T_body_sensor, dtype=float)
    P = np.asarray(points_sensor, dtype=float)
    n, c = world_plane(plane_world)
    T_ws = X @ S
    R, t = T_ws[:3, :3], T_ws[:3, 3]
    rho = np.linalg.norm(P, axis=1)
    D = P / rho[:, None]
    a = float(n @ t + c)
    n_s = R.T @ n
    b = D @ n_s
    ok = b < -MIN_GRAZING_COS
    b_safe = np.where(ok, b, -1.0)
    e = np.where(ok, rho + a / b_safe, 0.0)
    if not want_jacobians:
        return e, None
    N = len(P)
    H_T = np.zeros((N, 6))
    db_dphi = np.cross(D, n_s)  # (d x R^T n)
    H_T[:, :3] = (-a / b_safe**2)[:, None] * db_dphi
    H_T[:, 3:] = (n @ R)[None, :] / b_safe[:, None]
    H_T[~ok] = 0.0
    S_inv = np.eye(4)
    S_inv[:3, :3] = S[:3, :3].T
    S_inv[:3, 3] = -S[:3, :3].T @ S[:3, 3]
    return e, [H_T @ pose_adjoint(S_inv), H_T]


def checked_scan_points(points_sensor, sigma_range_m: float) -> np.ndarray:
    """A scan's points (N, 3) (sensor frame, m) as a read-only float array, after checking them and
    the range sigma (m); ValueError naming what is wrong."""
    P = np.array(points_sensor, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) == 0 or not np.all(np.isfinite(P)):
        raise ValueError(f"points_sensor must be a non-empty finite (N, 3) array, got shape {P.shape}")
    if np.any(np.linalg.norm(P, axis=1) <= 0):
        raise ValueError("points_sensor: a point at the sensor origin has no beam direction")
    if not np.isfinite(sigma_range_m) or sigma_range_m <= 0:
        raise ValueError(f"sigma_range_m must be > 0, got {sigma_range_m}")
    P.setflags(write=False)
    return P


def range_to_plane_factor(x_key: int, s_key: int, points_sensor, sigma_range_m: float, *, plane_world=None,
                          robust=None) -> gtsam.NonlinearFactor:
    """One factor on (X, S) for every ground point of one scan (noise ``sigma_range_m`` per beam)."""
    P = checked_scan_points(points_sensor, sigma_range_m)
    plane = None if plane_world is None else np.array(plane_world, dtype=float)
    noise = with_robust(gtsam.noiseModel.Isotropic.Sigma(len(P), float(sigma_range_m)), robust)

    def error_fn(Xm, Sm, want):
        return range_to_plane_error(Xm, Sm, P, plane, want)

    return checked_custom_factor(noise, [x_key, s_key], error_fn, [6, 6], len(P), kinds=["Pose3", "Pose3"],
                                 name="range_to_plane")
