"""Range-scale factors: a plane observation or a laser scan whose ranges read ``scale`` times too long.

A depth camera or laser scanner with a range (depth) scale error measures every point at ``scale``
times its true distance from the sensor origin (``p_measured = scale * p_true``). A plane
``n . p + d = 0`` then keeps its normal and measures ``d_m = scale * d_true``; a beam measures
``rho_m = scale * rho_true``. These factors add the scale as a variable (the diagnosis catalogue's
``sensor_range_scale``, graphcal/diagnosis): one ``Vector`` of length 1 per sensor, 1 when the
sensor is right.

Variables: X = T_world_body (Pose3), S = T_body_sensor (Pose3), C = [scale] (Vector, 1), and for the
plane factor optionally G = the world plane (OrientedPlane3).

Errors (same rows and noise as the unscaled factors, plane_observation.py and range_to_plane.py):

* plane: ``e = [B^T n_s, scale * d_s - d_m]`` (rad, rad, m): ``scale`` times the unscaled error at
  the measurement ``d_m / scale`` in the distance row. ``H_C = [0, 0, d_s]``.
* laser: ``e_i = rho_i - scale * r_i`` (m), ``r_i`` the predicted range of beam i: ``scale`` times
  the unscaled error at ``rho_i / scale``. ``H_C = -r_i``.

The Jacobians with respect to X, S (and G) are the unscaled ones with the scaled rows multiplied by
``scale``; all are exact.
"""

from __future__ import annotations

import gtsam
import numpy as np

from graphcal.factors.checked import checked_custom_factor, with_robust, world_plane
from graphcal.factors.plane_observation import check_plane_measurement, plane_noise_model, plane_observation_error
from graphcal.factors.range_to_plane import MIN_GRAZING_COS, checked_scan_points, range_to_plane_error

__all__ = ["scaled_plane_error", "scaled_plane_factor", "scaled_range_error", "scaled_range_factor"]


def _scale(c) -> float:
    s = float(np.asarray(c, dtype=float).reshape(-1)[0])
    if not np.isfinite(s) or s <= 0.0:
        raise ValueError(f"range scale must be a finite positive number, got {s}")
    return s


def scaled_plane_error(T_world_body, T_body_sensor, scale, n_m, d_m, plane_world=None, want_jacobians: bool = True):
    """Plane-observation error with a range scale, and analytic Jacobians (pure numpy).

    Args:
        T_world_body, T_body_sensor: 4x4 poses X and S.
        scale: (1,) or float, measured range / true range.
        n_m, d_m: measured plane in the sensor frame (unit normal; d_m >= 0, m).
        plane_world: (4,) world plane ``[nx, ny, nz, d]``; None for the ground z = 0.

    Returns:
        e (3,) and ``[H_X (3,6), H_S (3,6), H_C (3,1), H_G (3,3)]`` or None.
    """
    s = _scale(scale)
    e, H = plane_observation_error(T_world_body, T_body_sensor, n_m, float(d_m) / s, plane_world, want_jacobians)
    d_s = e[2] + float(d_m) / s
    e = e.copy()
    e[2] *= s
    if H is None:
        return e, None
    H_X, H_S, H_G = (h.copy() for h in H)
    for h in (H_X, H_S, H_G):
        h[2] *= s
    H_C = np.zeros((3, 1))
    H_C[2, 0] = d_s
    return e, [H_X, H_S, H_C, H_G]


def scaled_plane_factor(x_key: int, s_key: int, c_key: int, n_m, d_m, cov4=None, *, g_key: int | None = None,
                        noise_model=None, robust=None) -> gtsam.NonlinearFactor:
    """Factor on (X, S, C[, G]) for one plane measured by a sensor with a range scale.

    Args:
        x_key, s_key, c_key: keys of T_world_body, T_body_sensor (Pose3) and the scale (Vector, 1).
        n_m, d_m: measured plane in the sensor frame.
        cov4: 4x4 covariance of ``(nx, ny, nz, d)``, or give ``noise_model`` (3-dim).
        g_key: key of the world plane (OrientedPlane3) when it is estimated; else the ground z = 0.
        robust: optional gtsam mEstimator.
    """
    n_m, d_m = check_plane_measurement(n_m, d_m)
    if (cov4 is None) == (noise_model is None):
        raise ValueError("give exactly one of cov4 and noise_model")
    if noise_model is None:
        noise_model = plane_noise_model(n_m, cov4, robust=robust)
    if g_key is None:

        def error_fn(X, S, C, want):
            e, H = scaled_plane_error(X, S, C, n_m, d_m, None, want)
            return e, (None if H is None else H[:3])

        return checked_custom_factor(noise_model, [x_key, s_key, c_key], error_fn, [6, 6, 1], 3,
                                     kinds=["Pose3", "Pose3", "Vector"], name="scaled_plane_observation")

    def error_fn_g(X, S, C, G, want):
        return scaled_plane_error(X, S, C, n_m, d_m, G, want)

    return checked_custom_factor(noise_model, [x_key, s_key, c_key, g_key], error_fn_g, [6, 6, 1, 3], 3,
                                 kinds=["Pose3", "Pose3", "Vector", "OrientedPlane3"],
                                 name="scaled_plane_observation")


def scaled_range_error(T_world_body, T_body_sensor, scale, points_sensor, plane_world=None,
                       want_jacobians: bool = True):
    """Range residuals (m) of a scan with a range scale, and analytic Jacobians (pure numpy).

    Args:
        T_world_body, T_body_sensor: 4x4 poses X and S.
        scale: (1,) or float, measured range / true range.
        points_sensor: (N, 3) measured points in the sensor frame (m).
        plane_world: (4,) world plane; None for the ground z = 0.

    Returns:
        e (N,) and ``[H_X (N,6), H_S (N,6), H_C (N,1)]`` or None. Beams that do not go towards the
        plane get error 0 and zero rows (as in range_to_plane.py).
    """
    s = _scale(scale)
    P = np.asarray(points_sensor, dtype=float)
    e, H = range_to_plane_error(T_world_body, T_body_sensor, P / s, plane_world, want_jacobians)
    rho = np.linalg.norm(P, axis=1)
    n, c = world_plane(plane_world)
    T_ws = np.asarray(T_world_body, dtype=float) @ np.asarray(T_body_sensor, dtype=float)
    b = (P / rho[:, None]) @ (T_ws[:3, :3].T @ n)
    ok = b < -MIN_GRAZING_COS
    r_pred = np.where(ok, rho / s - e, 0.0)
    e = s * e
    if H is None:
        return e, None
    return e, [s * H[0], s * H[1], -r_pred.reshape(-1, 1)]


def scaled_range_factor(x_key: int, s_key: int, c_key: int, points_sensor, sigma_range_m: float, *,
                        robust=None) -> gtsam.NonlinearFactor:
    """One factor on (X, S, C) for every ground point of one scan of a sensor with a range scale."""
    P = checked_scan_points(points_sensor, sigma_range_m)
    noise = with_robust(gtsam.noiseModel.Isotropic.Sigma(len(P), float(sigma_range_m)), robust)

    def error_fn(Xm, Sm, C, want):
        return scaled_range_error(Xm, Sm, C, P, None, want)

    return checked_custom_factor(noise, [x_key, s_key, c_key], error_fn, [6, 6, 1], len(P),
                                 kinds=["Pose3", "Pose3", "Vector"], name="scaled_range_to_plane")
