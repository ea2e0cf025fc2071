"""Point-to-plane factor (dense mode): raw ground points must lie on the world plane.

Łabęcki et al.'s criterion ``z_M = 0``: every point the sensor returns from the ground, mapped
into the world, has zero signed distance to the ground plane. One factor holds all the points of
one station and one sensor (vectorised; N can be thousands), which amortises GTSAM's Python
callback cost.

Variables: ``X`` = T_world_body (Pose3), ``S`` = T_body_sensor (Pose3), optional ``G`` = world
plane (OrientedPlane3); without ``G`` the plane is the ground ``n_w = (0, 0, 1)``, ``d_w = 0``
(or a fixed ``plane_world``).

Measurement: points ``p_i`` (N, 3) in the sensor frame (m), per-point sigma (N,) or one sigma (m).

Error (N): ``e_i = n_w . (R_ws p_i + t_ws) + d_w`` with ``T_ws = X S``.

Jacobians (right perturbations ``[omega, v]``): for ``T_ws Exp([phi, rho])``,
``d e_i = n_w . R_ws (phi x p_i + rho)``, i.e. row ``[(p_i x n_s)^T, n_s^T]`` with
``n_s = R_ws^T n_w``; ``H_S = H_T``, ``H_X = H_T Ad(S^-1)``. For ``G`` (retract
``n_w <- Unit3 retract along B_w``, ``d_w + dd``): row ``[(R_ws p_i + t_ws)^T B_w, 1]``.

Noise: diagonal with the given sigmas (no default: it is the sensor's range noise plus the
ground's roughness at the working distance); ``robust=`` wraps it in a GTSAM mEstimator, which is
advisable when the points come from a RANSAC segmentation that may keep a few outliers.
"""

from __future__ import annotations

import gtsam
import numpy as np

from graphcal.factors.checked import checked_custom_factor, tangent_basis, with_robust, world_plane
from graphcal.geometry import pose_adjoint

__all__ = ["point_to_plane_error", "point_to_plane_noise_model", "point_to_plane_factor"]


def point_to_plane_error(
    T_world_body,
    T_body_sensor,
    points_sensor,
    plane_world=None,
    want_jacobians: bool = True,
):
    """Signed distances of sensor points to the world plane, and analytic Jacobians (pure numpy).

    Args:
        T_world_body: 4x4 body pose X.
        T_body_sensor: 4x4 sensor extrinsic S.
        points_sensor: (N, 3) points in the sensor frame, m.
        plane_world: (4,) world plane ``[nx, ny, nz, d]``; None for the ground z = 0.
        want_jacobians: also return the Jacobians.

    Returns:
        e (N,) in m, and ``[H_X (N,6), H_S (N,6), H_G (N,3)]`` or None.
    """
    X = np.asarray(T_world_body, dtype=float)
    S = np.asarray(T_body_sensor, dtype=float)
    P = np.asarray(points_sensor, dtype=float)
    n_w, d_w = world_plane(plane_world)
    T_ws = X @ S
    R_ws, t_ws = T_ws[:3, :3], T_ws[:3, 3]
    P_w = P @ R_ws.T + t_ws
    e = P_w @ n_w + d_w
    if not want_jacobians:
        return e, None
    n_s = R_ws.T @ n_w
    N = P.shape[0]
    H_T = np.empty((N, 6))
    H_T[:, :3] = np.cross(P, n_s)
    H_T[:, 3:] = n_s
    S_inv = np.eye(4)
    S_inv[:3, :3] = S[:3, :3].T
    S_inv[:3, 3] = -S[:3, :3].T @ S[:3, 3]
    H_X = H_T @ pose_adjoint(S_inv)
    H_G = np.empty((N, 3))
    H_G[:, :2] = P_w @ tangent_basis(n_w)
    H_G[:, 2] = 1.0
    return e, [H_X, H_T, H_G]


def point_to_plane_noise_model(sigma_m, n_points: int, robust=None):
    """Isotropic (scalar sigma) or diagonal ((N,) sigmas) noise model, m; optionally robust."""
    sigma = np.asarray(sigma_m, dtype=float)
    if sigma.ndim == 0:
        if not np.isfinite(sigma) or sigma <= 0:
            raise ValueError(f"sigma_m must be > 0, got {float(sigma)}")
        model = gtsam.noiseModel.Isotropic.Sigma(int(n_points), float(sigma))
    else:
        if sigma.shape != (n_points,):
            raise ValueError(f"sigma_m must be a scalar or have shape ({n_points},), got {sigma.shape}")
        if not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
            raise ValueError("every sigma_m must be finite and > 0")
        model = gtsam.noiseModel.Diagonal.Sigmas(sigma.copy())
    return with_robust(model, robust)


def point_to_plane_factor(
    x_key: int,
    s_key: int,
    points_sensor,
    sigma_m,
    *,
    g_key: int | None = None,
    plane_world=None,
    robust=None,
) -> gtsam.NonlinearFactor:
    """One factor on (X, S[, G]) for all ground points of one station and one sensor.

    Args:
        x_key, s_key: keys of T_world_body and T_body_sensor (Pose3).
        points_sensor: (N, 3) ground points in the sensor frame, m (N >= 1).
        sigma_m: point-to-plane sigma, scalar or (N,), m.
        g_key: key of the world plane (OrientedPlane3) if estimated.
        plane_world: fixed world plane ``[nx, ny, nz, d]`` when ``g_key`` is None (default ground).
        robust: optional gtsam mEstimator.
    """
    P = np.array(points_sensor, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3 or P.shape[0] < 1:
        raise ValueError(f"points_sensor must have shape (N, 3) with N >= 1, got {np.shape(points_sensor)}")
    if not np.all(np.isfinite(P)):
        raise ValueError("points_sensor contains NaN or inf")
    P.setflags(write=False)
    N = P.shape[0]
    if g_key is not None and plane_world is not None:
        raise ValueError("plane_world is fixed; it cannot be given together with g_key (an estimated plane)")
    fixed_plane = None if plane_world is None else np.append(*world_plane(plane_world))
    noise = point_to_plane_noise_model(sigma_m, N, robust)

    if g_key is None:

        def error_fn(X, S, want):
            e, H = point_to_plane_error(X, S, P, fixed_plane, want)
            return e, (None if H is None else H[:2])

        return checked_custom_factor(noise, [x_key, s_key], error_fn, [6, 6], N, kinds=["Pose3", "Pose3"], name="point_to_plane")

    def error_fn_g(X, S, G, want):
        return point_to_plane_error(X, S, P, G, want)

    return checked_custom_factor(
        noise,
        [x_key, s_key, g_key],
        error_fn_g,
        [6, 6, 3],
        N,
        kinds=["Pose3", "Pose3", "OrientedPlane3"],
        name="point_to_plane",
    )
