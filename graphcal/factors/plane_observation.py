"""Plane observation factor: a sensor sees the ground (or a known/estimated world plane).

Variables: ``X`` = T_world_body (Pose3), ``S`` = T_body_sensor (Pose3), optional ``G`` = the world
plane (OrientedPlane3); without ``G`` the ground ``n_w = (0, 0, 1)``, ``d_w = 0`` (or a fixed
``plane_world``). Measurement: the plane ``(n_m, d_m)`` in the sensor frame (unit ``n_m``,
canonical ``d_m >= 0`` m, ``n_m . x + d_m = 0``) and the 4x4 covariance ``cov4`` of
``(nx, ny, nz, d)``. Error (3): ``e = [B^T n_s (2, rad) ; d_s - d_m (1, m)]``, the world plane
predicted in the sensor frame (``T_ws = X S``) against the measured one, ``B`` the tangent basis
of ``n_m``; analytic Jacobians for right perturbations ``[omega, v]``. The initial normal must be
within 90 deg of the truth (``n_s = -n_m`` also zeroes the angular rows).

Prediction, Jacobians, noise and floors: docs/factors.md, "1. plane_observation".
"""

from __future__ import annotations

import gtsam
import numpy as np

from graphcal.factors.checked import checked_custom_factor, tangent_basis, with_robust, world_plane
from graphcal.geometry import pose_adjoint, skew

__all__ = [
    "tangent_basis",
    "plane_observation_error",
    "plane_cov3",
    "plane_noise_model",
    "check_plane_measurement",
    "plane_observation_factor",
    "plane_angle_distance_error",
    "DEFAULT_SIGMA_ANGLE_FLOOR_RAD",
    "DEFAULT_SIGMA_DISTANCE_FLOOR_M",
]

#: default additive floor on the normal's angular sigma (rad): 0, the fit covariance is trusted
DEFAULT_SIGMA_ANGLE_FLOOR_RAD = 0.0
#: default additive floor on the distance sigma (m): 0, the fit covariance is trusted
DEFAULT_SIGMA_DISTANCE_FLOOR_M = 0.0

_UNIT_TOL = 1e-6


def check_plane_measurement(n_m, d_m) -> tuple[np.ndarray, float]:
    """A measured plane ``n_m . x = d_m`` (sensor frame; unit normal, distance m >= 0) checked and
    renormalised: (n_m (3,), d_m); ValueError when it is not finite, not unit or not canonical."""
    n_m = np.asarray(n_m, dtype=float).reshape(-1)
    if n_m.shape != (3,) or not np.all(np.isfinite(n_m)):
        raise ValueError(f"plane normal n_m must be 3 finite numbers, got {n_m!r}")
    if abs(np.linalg.norm(n_m) - 1.0) > _UNIT_TOL:
        raise ValueError(f"plane normal n_m must be a unit vector, |n_m| = {np.linalg.norm(n_m)}")
    d_m = float(d_m)
    if not np.isfinite(d_m) or d_m < 0.0:
        raise ValueError(
            f"plane distance d_m must be finite and >= 0 (canonical plane, see graphcal.geometry.canonical_plane), got {d_m}"
        )
    return n_m / np.linalg.norm(n_m), d_m


#: ``tangent_basis`` of the ground's normal e_z (the default world plane), read-only
_GROUND_BASIS = tangent_basis(np.array([0.0, 0.0, 1.0]))
_GROUND_BASIS.setflags(write=False)


def plane_observation_error(
    T_world_body,
    T_body_sensor,
    n_m,
    d_m,
    plane_world=None,
    want_jacobians: bool = True,
    basis_m=None,
):
    """Error of a plane observation and its analytic Jacobians (pure numpy).

    Args:
        T_world_body: 4x4 body pose X.
        T_body_sensor: 4x4 sensor extrinsic S.
        n_m: (3,) measured unit normal in the sensor frame.
        d_m: measured distance (m), >= 0.
        plane_world: (4,) world plane ``[nx, ny, nz, d]``; None for the ground z = 0.
        want_jacobians: also return the Jacobians.
        basis_m: ``tangent_basis(n_m)`` (3, 2) when the caller has it (a factor: ``n_m`` is constant).

    Returns:
        e (3,) = ``[B^T n_s, d_s - d_m]`` (rad, rad, m) and ``[H_X (3,6), H_S (3,6), H_G (3,3)]``
        (right perturbations; ``H_G`` w.r.t. the OrientedPlane3 retract of ``plane_world``), or
        None when ``want_jacobians`` is False.
    """
    X = np.asarray(T_world_body, dtype=float)
    S = np.asarray(T_body_sensor, dtype=float)
    n_m = np.asarray(n_m, dtype=float)
    n_w, d_w = world_plane(plane_world)
    T_ws = X @ S
    R_ws, t_ws = T_ws[:3, :3], T_ws[:3, 3]
    n_s = R_ws.T @ n_w
    d_s = d_w + n_w @ t_ws
    B = tangent_basis(n_m) if basis_m is None else basis_m
    e = np.empty(3)
    e[:2] = B.T @ n_s
    e[2] = d_s - float(d_m)
    if not want_jacobians:
        return e, None
    H_T = np.zeros((3, 6))
    H_T[:2, :3] = B.T @ skew(n_s)
    H_T[2, 3:] = n_s
    S_inv = np.eye(4)
    S_inv[:3, :3] = S[:3, :3].T
    S_inv[:3, 3] = -S[:3, :3].T @ S[:3, 3]
    H_X = H_T @ pose_adjoint(S_inv)
    B_w = _GROUND_BASIS if plane_world is None else tangent_basis(n_w)
    H_G = np.zeros((3, 3))
    H_G[:2, :2] = B.T @ R_ws.T @ B_w
    H_G[2, :2] = t_ws @ B_w
    H_G[2, 2] = 1.0
    return e, [H_X, H_T, H_G]


def plane_cov3(
    n_m,
    cov4,
    sigma_angle_floor_rad: float = DEFAULT_SIGMA_ANGLE_FLOOR_RAD,
    sigma_distance_floor_m: float = DEFAULT_SIGMA_DISTANCE_FLOOR_M,
) -> np.ndarray:
    """3x3 covariance of the error ``[B^T n, d]``: ``Gm^T cov4 Gm + diag(sa^2, sa^2, sd^2)``.

    Args:
        n_m: (3,) measured unit normal (sensor frame).
        cov4: 4x4 covariance of ``(nx, ny, nz, d)`` (unitless^2 and m^2), symmetric PSD.
        sigma_angle_floor_rad, sigma_distance_floor_m: additive floors (ground roughness).

    Raises:
        ValueError: bad shapes, a non-symmetric or indefinite ``cov4``, negative floors, or a
            singular result (give floors if the fit covariance can be exactly zero).
    """
    n_m = np.asarray(n_m, dtype=float).reshape(3)
    C = np.asarray(cov4, dtype=float)
    if C.shape != (4, 4) or not np.all(np.isfinite(C)):
        raise ValueError(f"cov4 must be a finite 4x4 covariance of (nx, ny, nz, d), got shape {C.shape}")
    scale = max(float(np.abs(C).max()), 1e-300)
    if np.abs(C - C.T).max() > 1e-9 * scale:
        raise ValueError("cov4 must be symmetric")
    if np.linalg.eigvalsh(C).min() < -1e-9 * scale:
        raise ValueError("cov4 must be positive semi-definite")
    if sigma_angle_floor_rad < 0 or sigma_distance_floor_m < 0:
        raise ValueError("noise floors must be >= 0")
    Gm = np.zeros((4, 3))
    Gm[:3, :2] = tangent_basis(n_m)
    Gm[3, 2] = 1.0
    cov3 = Gm.T @ C @ Gm
    cov3 = 0.5 * (cov3 + cov3.T)
    cov3 += np.diag([sigma_angle_floor_rad**2, sigma_angle_floor_rad**2, sigma_distance_floor_m**2])
    w = np.linalg.eigvalsh(cov3)
    if w.min() <= 1e-12 * max(w.max(), 1e-300) or w.max() <= 0.0:
        raise ValueError(
            f"plane error covariance is singular (eigenvalues {w}); give sigma_angle_floor_rad / sigma_distance_floor_m > 0"
        )
    return cov3


def plane_noise_model(
    n_m,
    cov4,
    sigma_angle_floor_rad: float = DEFAULT_SIGMA_ANGLE_FLOOR_RAD,
    sigma_distance_floor_m: float = DEFAULT_SIGMA_DISTANCE_FLOOR_M,
    robust=None,
):
    """GTSAM noise model of a plane observation: Gaussian(:func:`plane_cov3`), optionally robust."""
    cov3 = plane_cov3(n_m, cov4, sigma_angle_floor_rad, sigma_distance_floor_m)
    return with_robust(gtsam.noiseModel.Gaussian.Covariance(cov3), robust)


def plane_observation_factor(
    x_key: int,
    s_key: int,
    n_m,
    d_m,
    cov4=None,
    *,
    g_key: int | None = None,
    plane_world=None,
    noise_model=None,
    sigma_angle_floor_rad: float = DEFAULT_SIGMA_ANGLE_FLOOR_RAD,
    sigma_distance_floor_m: float = DEFAULT_SIGMA_DISTANCE_FLOOR_M,
    robust=None,
) -> gtsam.NonlinearFactor:
    """Factor on (X, S[, G]) for one plane measured in the sensor frame.

    Args:
        x_key, s_key: keys of T_world_body and T_body_sensor (Pose3).
        n_m, d_m: measured plane in the sensor frame (unit normal, d >= 0, m).
        cov4: 4x4 covariance of ``(nx, ny, nz, d)``; or give ``noise_model`` (3-dim) instead.
        g_key: key of the world plane (OrientedPlane3) if it is estimated.
        plane_world: fixed world plane ``[nx, ny, nz, d]`` when ``g_key`` is None (default ground).
        noise_model: a ready 3-dim noise model (then ``cov4``, floors and ``robust`` are not used).
        sigma_angle_floor_rad, sigma_distance_floor_m: additive noise floors (default 0).
        robust: optional gtsam mEstimator (e.g. ``gtsam.noiseModel.mEstimator.Huber.Create(1.345)``).
    """
    n_m, d_m = check_plane_measurement(n_m, d_m)
    if (cov4 is None) == (noise_model is None):
        raise ValueError("give exactly one of cov4 and noise_model")
    if g_key is not None and plane_world is not None:
        raise ValueError("plane_world is fixed; it cannot be given together with g_key (an estimated plane)")
    if noise_model is None:
        noise_model = plane_noise_model(n_m, cov4, sigma_angle_floor_rad, sigma_distance_floor_m, robust)
    fixed_plane = None if plane_world is None else np.append(*world_plane(plane_world))
    B_m = tangent_basis(n_m)  # once: the measured normal is constant
    B_m.setflags(write=False)

    if g_key is None:

        def error_fn(X, S, want):
            e, H = plane_observation_error(X, S, n_m, d_m, fixed_plane, want, B_m)
            return e, (None if H is None else H[:2])

        return checked_custom_factor(
            noise_model, [x_key, s_key], error_fn, [6, 6], 3, kinds=["Pose3", "Pose3"], name="plane_observation"
        )

    def error_fn_g(X, S, G, want):
        return plane_observation_error(X, S, n_m, d_m, G, want, B_m)

    return checked_custom_factor(
        noise_model,
        [x_key, s_key, g_key],
        error_fn_g,
        [6, 6, 3],
        3,
        kinds=["Pose3", "Pose3", "OrientedPlane3"],
        name="plane_observation",
    )


def plane_angle_distance_error(T_world_sensor, n_m, d_m, plane_world=None) -> tuple[float, float]:
    """Report metrics of one plane observation (Chai et al. 2015's theta and e_d).

    Args:
        T_world_sensor: 4x4 sensor pose (X S).
        n_m, d_m: measured plane in the sensor frame.
        plane_world: (4,) world plane; None for the ground z = 0.

    Returns:
        (angle_rad, distance_m): the angle in [0, pi] between the predicted normal ``n_s`` and
        ``n_m`` (atan2 form, accurate near 0), and the signed distance error ``d_s - d_m`` (m).
    """
    T = np.asarray(T_world_sensor, dtype=float)
    n_w, d_w = world_plane(plane_world)
    n_s = T[:3, :3].T @ n_w
    d_s = d_w + n_w @ T[:3, 3]
    n_m = np.asarray(n_m, dtype=float)
    angle = float(np.arctan2(np.linalg.norm(np.cross(n_s, n_m)), n_s @ n_m))
    return angle, float(d_s - float(d_m))
