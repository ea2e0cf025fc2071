"""Prior on an estimated ground plane (OrientedPlane3): its tilt and its offset, separately.

The diagnosis catalogue's ``ground_tilt`` estimates the world ground plane G (graphcal/diagnosis).
Its offset along the normal is a gauge (moving the ground, the feet and the bodies together changes
nothing the sensors see), so it is pinned; its tilt gets a prior that is tight in the nominal model
(the floor is level) and loose when the tilt is estimated.

Variable: G = plane ``[nx, ny, nz, d]`` (OrientedPlane3; tangent: 2 along ``n.basis()``, then d).
Error (3,): ``[B_0^T n, d - d_0]`` with ``B_0`` the tangent basis of the prior normal ``n_0``
(rad, rad, m). Jacobian: ``[[B_0^T B_n, 0], [0, 1]]``.
"""

from __future__ import annotations

import gtsam
import numpy as np

from graphcal.factors.checked import checked_custom_factor, tangent_basis, world_plane

__all__ = ["plane_prior_error", "plane_prior_factor"]


def plane_prior_error(plane_world, plane_prior, want_jacobians: bool = True):
    """Error of a plane against its prior, and the Jacobian.

    Args:
        plane_world: (4,) current plane ``[nx, ny, nz, d]`` (world frame, unit normal, m).
        plane_prior: (4,) prior plane.

    Returns:
        e (3,) and ``[H_G (3,3)]`` or None.
    """
    n, d = world_plane(plane_world)
    n0, d0 = world_plane(plane_prior)
    B0 = tangent_basis(n0)
    e = np.empty(3)
    e[:2] = B0.T @ n
    e[2] = d - d0
    if not want_jacobians:
        return e, None
    H = np.zeros((3, 3))
    H[:2, :2] = B0.T @ tangent_basis(n)
    H[2, 2] = 1.0
    return e, [H]


def plane_prior_factor(g_key: int, plane_prior, sigma_tilt_rad: float, sigma_offset_m: float) -> gtsam.NonlinearFactor:
    """Prior on G: tilt ``sigma_tilt_rad`` (each of the two tangent directions), offset ``sigma_offset_m``."""
    for name, v in (("sigma_tilt_rad", sigma_tilt_rad), ("sigma_offset_m", sigma_offset_m)):
        if not np.isfinite(v) or v <= 0:
            raise ValueError(f"{name} must be > 0, got {v}")
    prior = np.append(*world_plane(plane_prior))
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_tilt_rad, sigma_tilt_rad, sigma_offset_m]))

    def error_fn(G, want):
        return plane_prior_error(G, prior, want)

    return checked_custom_factor(noise, [g_key], error_fn, [3], 3, kinds=["OrientedPlane3"], name="plane_prior")
