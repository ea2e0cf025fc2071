"""The Gauss-Newton step of point-to-plane ICP, taken only along the directions the data constrains.

Both of graphcal's registrations use it: :mod:`graphcal.clouds.icp` (a new frame onto a keyframe,
for the EKF) and :mod:`graphcal.clouds.stitch` (a cloud onto the map of the others; the stairs model). They
differ in how correspondences are found and weighted; the linear algebra is this module's.

Coordinates: the right perturbation ``T = T_hat Exp(xi)``, ``xi = [omega, v]`` (rad, m;
docs/conventions.md). A correspondence of source point ``s`` (source frame) with a target plane of
normal ``n`` (target frame) has the residual ``n . (T s - q)`` and the Jacobian
``[(s x m)^T, m^T]``, ``m = R^T n``.

Degenerate directions (Zhang, Kaess & Singh, ICRA 2016, "On degeneracy of optimization-based state
estimation problems"): the Hessian of the data is compared in scaled coordinates
``xi_s = xi * scale`` (a rotation in rad counts as ``scale`` metres); an eigen-direction is kept when
its eigenvalue is at least ``degeneracy_ratio`` times the largest. A flat floor constrains one
translation and two rotations: without this, noise in the normals lets the cloud slide along it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ConstrainedStep", "point_to_plane_jacobian", "constrained_step"]


@dataclass(frozen=True, eq=False)
class ConstrainedStep:
    """A Gauss-Newton step restricted to the well-constrained directions.

    Attributes:
        step: (6,) the update ``[omega (rad), v (m)]`` of the right perturbation.
        eigenvalues: (k,) the kept eigenvalues of the data Hessian in scaled coordinates.
        basis: (6, k) their eigenvectors (orthonormal in scaled coordinates).
    """

    step: np.ndarray
    eigenvalues: np.ndarray
    basis: np.ndarray

    @property
    def n_degenerate(self) -> int:
        """How many of the 6 directions got no update."""
        return 6 - self.basis.shape[1]


def point_to_plane_jacobian(points_source: np.ndarray, normals_target: np.ndarray, R_target_source: np.ndarray) -> np.ndarray:
    """(N, 6) rows ``[(s x m)^T, m^T]``, ``m = R^T n``: the derivative of the residuals
    ``n . (T Exp(xi) s - q)`` in ``xi = [omega, v]`` at ``xi = 0``.

    Args:
        points_source: (N, 3) source points ``s``, source frame, m.
        normals_target: (N, 3) unit normals ``n`` of their target planes, target frame.
        R_target_source: (3, 3) rotation of the current ``T_target_source``.
    """
    m = normals_target @ R_target_source
    return np.hstack([np.cross(points_source, m), m])


def constrained_step(H_data: np.ndarray, g: np.ndarray, *, scale: np.ndarray, degeneracy_ratio: float,
                     prior_information: np.ndarray | None = None) -> ConstrainedStep:
    """The Gauss-Newton step of ``0.5 xi^T H xi + g^T xi`` along the well-constrained directions of
    ``H_data`` (module docstring).

    Args:
        H_data: (6, 6) ``sum w J^T J`` of the correspondences (1/rad^2, 1/m^2).
        g: (6,) the gradient, ``sum w J^T r`` plus the prior's part if there is one.
        scale: (6,) metres per unit of each coordinate (1 for translations; the length scale for
            rotations) in which eigenvalues are compared.
        degeneracy_ratio: the smallest kept eigenvalue relative to the largest.
        prior_information: (6,) diagonal of a prior on ``xi`` (None: none). Without a prior the
            step is the pseudo-inverse on the kept directions; with one, the step of the
            regularised system ``H_data + diag(prior)``, projected on them.
    """
    scale = np.asarray(scale, dtype=float)
    lam, V = np.linalg.eigh(H_data / np.outer(scale, scale))
    keep = lam >= degeneracy_ratio * lam[-1]
    Vk = V[:, keep]
    if prior_information is None:
        step_scaled = -Vk @ ((Vk.T @ (g / scale)) / lam[keep])
    else:
        full = -np.linalg.solve(H_data + np.diag(prior_information), g)
        step_scaled = Vk @ (Vk.T @ (full * scale))
    return ConstrainedStep(step_scaled / scale, lam[keep], Vk)
