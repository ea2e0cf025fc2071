"""Foot-on-ground factor: a planted foot lies on the ground plane.

Variables: ``F`` = p_world_foot (Point3), optional ``G`` = world plane (OrientedPlane3); without
``G`` the plane is the ground ``n_w = (0, 0, 1)``, ``d_w = 0`` (or a fixed ``plane_world``).

Error (1, m): ``e = n_w . F + d_w``, the signed distance of the foot point to the plane.

Jacobians: ``H_F = n_w^T``; for ``G`` (retract ``n_w <- Unit3 retract along B_w``,
``d_w <- d_w + dd``): ``H_G = [F^T B_w, 1]``.

Noise: default ``sigma_m = 3 mm``: the foot frame is the centre of a rubber foot pad whose
contact point rolls and compresses by a few mm, and the floor itself is flat only to a few mm
over the robot's footprint. Use ``robust=`` for feet that may stand on a stone or a cable.
"""

from __future__ import annotations

import gtsam
import numpy as np

from graphcal.factors.checked import checked_custom_factor, tangent_basis, with_robust, world_plane

__all__ = ["DEFAULT_SIGMA_M", "foot_on_ground_error", "foot_on_ground_factor"]

#: default sigma of the foot-to-ground distance (m): foot pad compliance + floor flatness
DEFAULT_SIGMA_M = 0.003


def foot_on_ground_error(p_world_foot, plane_world=None, want_jacobians: bool = True):
    """Signed distance of the foot to the world plane, and analytic Jacobians (pure numpy).

    Args:
        p_world_foot: (3,) foot position F, m.
        plane_world: (4,) world plane ``[nx, ny, nz, d]``; None for the ground z = 0.

    Returns:
        e (1,) m, and ``[H_F (1,3), H_G (1,3)]`` or None.
    """
    F = np.asarray(p_world_foot, dtype=float)
    n_w, d_w = world_plane(plane_world)
    e = np.array([n_w @ F + d_w])
    if not want_jacobians:
        return e, None
    H_G = np.empty((1, 3))
    H_G[0, :2] = F @ tangent_basis(n_w)
    H_G[0, 2] = 1.0
    return e, [n_w.reshape(1, 3).copy(), H_G]


def foot_on_ground_factor(
    f_key: int,
    sigma_m: float = DEFAULT_SIGMA_M,
    *,
    g_key: int | None = None,
    plane_world=None,
    robust=None,
) -> gtsam.NonlinearFactor:
    """Factor on (F[, G]): the planted foot lies on the (ground) plane.

    Args:
        f_key: key of p_world_foot (Point3).
        sigma_m: sigma of the distance, m (default 3 mm).
        g_key: key of the world plane (OrientedPlane3) if estimated.
        plane_world: fixed world plane ``[nx, ny, nz, d]`` when ``g_key`` is None (default ground).
        robust: optional gtsam mEstimator.
    """
    if not np.isfinite(sigma_m) or sigma_m <= 0:
        raise ValueError(f"sigma_m must be > 0, got {sigma_m}")
    if g_key is not None and plane_world is not None:
        raise ValueError("plane_world is fixed; it cannot be given together with g_key (an estimated plane)")
    fixed_plane = None if plane_world is None else np.append(*world_plane(plane_world))
    noise = with_robust(gtsam.noiseModel.Isotropic.Sigma(1, float(sigma_m)), robust)

    if g_key is None:

        def error_fn(F, want):
            e, H = foot_on_ground_error(F, fixed_plane, want)
            return e, (None if H is None else H[:1])

        return checked_custom_factor(noise, [f_key], error_fn, [3], 1, kinds=["Point3"], name="foot_on_ground")

    def error_fn_g(F, G, want):
        return foot_on_ground_error(F, G, want)

    return checked_custom_factor(
        noise, [f_key, g_key], error_fn_g, [3, 3], 1, kinds=["Point3", "OrientedPlane3"], name="foot_on_ground"
    )
