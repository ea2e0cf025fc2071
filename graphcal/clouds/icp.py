"""Point-to-plane ICP between two clouds of one sensor, aware of degenerate directions.

``icp_relative_pose(source, target, T_init, sigma_fn)`` registers the source cloud (the newer
frame) onto the target cloud (the keyframe). Correspondences come from Open3D
(``o3d.pipelines.registration.evaluate_registration``: nearest target point within
``max_correspondence_m``), target normals from Open3D's ``estimate_normals``. Each iteration is
a weighted Gauss-Newton step on the point-to-plane residuals ``n . (T s - q)`` with the solution
remapping of Zhang, Kaess & Singh (ICRA 2016, "On degeneracy of optimization-based state
estimation problems"): the step is taken only along the well-constrained eigen-directions of the
Hessian. Open3D's own ``registration_icp`` solves the full 6x6 system and slides by metres along
a flat floor, where two translations and one rotation are unconstrained; here they stay at
``T_init`` (the filter's prediction) and the result reports which directions it measured.

The Gauss-Newton step and the Jacobian are :mod:`graphcal.solvers.point_to_plane`'s (shared with
the stairs' stitching). Coordinates: the right perturbation ``T = T_hat Exp(xi)``, ``xi = [omega, v]``
(docs/conventions.md). For a correspondence (source point s, target point q, target normal n,
m = R^T n) the residual has the Jacobian ``[(s x m)^T, m^T]`` and the variance
``sigma(s)^2 (m . s_hat)^2 + sigma(q)^2 (n . q_hat)^2`` (each point's range noise along its ray,
projected on the normal). Degeneracy is judged on the Hessian in scaled coordinates
``xi_s = [L omega, v]`` (L = ``length_scale_m``): a direction is kept if its eigenvalue is at
least ``degenerate_ratio`` times the largest.

Units: m, rad.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.geometry import se3_exp
from graphcal.solvers.point_to_plane import constrained_step, point_to_plane_jacobian

__all__ = ["IcpResult", "TargetCloud", "prepare_target", "icp_relative_pose", "range_sigma_function"]


@dataclass(frozen=True, eq=False)
class IcpResult:
    """ICP result.

    Attributes:
        T_target_source: (4, 4) the registration (maps source points into the target frame).
        information: (6, 6) Hessian of the weighted residuals at the solution, in [omega, v] of
            the right perturbation of ``T_target_source`` (1/rad^2, 1/m^2).
        A: (k, 6) the measured combinations of the right perturbation: ``z = A xi`` with
            covariance ``cov`` (k, k) (the well-constrained directions, orthonormal in scaled
            coordinates).
        cov: (k, k) covariance of ``A xi`` (diagonal).
        n_correspondences: inliers used; fitness: their fraction of the source (Open3D);
        rmse: RMS residual (m); iterations: Gauss-Newton steps taken.
    """

    T_target_source: np.ndarray
    information: np.ndarray
    A: np.ndarray
    cov: np.ndarray
    n_correspondences: int
    fitness: float
    rmse: float
    iterations: int


def range_sigma_function(sensor_type: str) -> Callable[[np.ndarray], np.ndarray]:
    """Range-noise standard deviation (m) of each point (N, 3) in the sensor frame, for the sensor
    models of :mod:`graphcal.models.sensors` (depth/stereo: along the optical axis, as a
    function of z; laser: constant)."""
    from graphcal.models.sensors import sensor_for_type

    sensor = sensor_for_type(sensor_type)
    if hasattr(sensor, "sigma_along_axis"):
        return lambda pts: sensor.sigma_along_axis(np.abs(pts[:, 2]))
    return lambda pts: np.full(len(pts), sensor.sigma_m)


@dataclass(frozen=True, eq=False)
class TargetCloud:
    """A keyframe cloud ready for point-to-plane ICP: local planes from its k nearest neighbours.

    Attributes:
        points: (M, 3) the points (sensor frame, m). pcd: the same as an Open3D cloud.
        centroids: (M, 3) mean of each point's neighbourhood (the plane point).
        normals: (M, 3) unit plane normals (smallest principal axis), towards the sensor.
        var_offset: (M,) variance of the plane's offset along its normal (m^2).
        var_normal: (M,) variance of the normal's tilt (rad^2).
        valid: (M,) the neighbourhood is planar within its noise (edges and corners are not).
    """

    points: np.ndarray
    pcd: object
    centroids: np.ndarray
    normals: np.ndarray
    var_offset: np.ndarray
    var_normal: np.ndarray
    valid: np.ndarray


def prepare_target(points: np.ndarray, sigma_fn: Callable[[np.ndarray], np.ndarray], *, k: int = 15,
                   planarity_chi2: float = 9.0, min_spread_m: float = 0.02) -> TargetCloud:
    """Local planes of a cloud (N, 3) (sensor frame, m) from each point's ``k`` nearest neighbours
    (PCA, vectorised). The normal of a neighbourhood of n points with in-plane spread lambda_1
    (the middle eigenvalue of its covariance) and noise sigma_perp along the normal has a tilt
    variance sigma_perp^2 / (n lambda_1); a neighbourhood whose smallest eigenvalue exceeds
    ``planarity_chi2`` times sigma_perp^2 (plus 1 mm^2) is not planar (an edge), and one whose
    in-plane spread sqrt(lambda_1) is below ``min_spread_m`` (a row of points) has no plane: neither
    is used."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    P = np.ascontiguousarray(points, dtype=np.float64)
    M = len(P)
    if M < k:
        raise GraphcalError(f"ICP target has {M} points (need >= {k})")
    _, idx = cKDTree(P).query(P, k=k)
    nb = P[idx]  # (M, k, 3)
    c = nb.mean(axis=1)
    d = nb - c[:, None, :]
    C = np.einsum("mki,mkj->mij", d, d) / k
    lam, V = np.linalg.eigh(C)
    n = V[:, :, 0]
    flip = np.einsum("ij,ij->i", n, c) > 0  # towards the sensor origin: n . c < 0
    n[flip] *= -1.0
    sig = sigma_fn(P)[idx]  # (M, k)
    rhat = nb / np.linalg.norm(nb, axis=2, keepdims=True)
    perp2 = (sig * np.einsum("mkj,mj->mk", rhat, n)) ** 2  # each neighbour's noise along the normal
    s_perp2 = perp2.mean(axis=1)
    var_offset = s_perp2 / k
    var_normal = s_perp2 / (k * np.maximum(lam[:, 1], 1e-12))
    # planar within the noise, and spread in two directions (a row of points has no plane)
    valid = (lam[:, 0] <= planarity_chi2 * s_perp2 + 1e-6) & (lam[:, 1] >= min_spread_m**2)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    return TargetCloud(P, pcd, c, n, var_offset, var_normal, valid)


def icp_relative_pose(
    source_points: np.ndarray,
    target: TargetCloud,
    T_init: np.ndarray,
    sigma_fn: Callable[[np.ndarray], np.ndarray],
    *,
    max_correspondence_m: float = 0.1,
    max_iterations: int = 20,
    degenerate_ratio: float = 1e-3,
    length_scale_m: float = 1.0,
    gate_chi2: float | None = 9.0,
) -> IcpResult:
    """Point-to-plane ICP of ``source_points`` (N, 3, source sensor frame, m) onto ``target`` (a
    :class:`TargetCloud` from :func:`prepare_target`) from ``T_init`` (4, 4, T_target_source);
    see the module docstring. The residual of a correspondence is ``n . (T s - c)`` (c, n: the
    target's local plane) with variance ``sigma(s)^2 (m . s_hat)^2 + var_offset + |d_t|^2 var_normal``
    (d_t: the in-plane offset of T s from c); correspondences whose normalised squared residual
    exceeds ``gate_chi2`` (times the robust spread of all of them when that exceeds 1: a poor
    start) get no weight in that iteration. Raises GraphcalError when fewer than 6
    usable correspondences are found."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    src_pts = np.ascontiguousarray(source_points, dtype=np.float64)
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src_pts))
    sig_src = sigma_fn(src_pts)
    s_hat_all = src_pts / np.linalg.norm(src_pts, axis=1, keepdims=True)
    L = float(length_scale_m)
    scale = np.array([L, L, L, 1.0, 1.0, 1.0])
    T = np.asarray(T_init, dtype=float).copy()

    def linearise(T):
        ev = reg.evaluate_registration(src, target.pcd, max_correspondence_m, T)
        corr = np.asarray(ev.correspondence_set)
        if len(corr):
            corr = corr[target.valid[corr[:, 1]]]
        if len(corr) < 6:
            raise GraphcalError(f"ICP found {len(corr)} usable correspondences (need >= 6)")
        i, j = corr[:, 0], corr[:, 1]
        s, c, n = src_pts[i], target.centroids[j], target.normals[j]
        R, t = T[:3, :3], T[:3, 3]
        d = s @ R.T + t - c
        r = np.einsum("ij,ij->i", n, d)
        dt2 = np.einsum("ij,ij->i", d, d) - r * r
        m = n @ R
        J = point_to_plane_jacobian(s, n, R)
        var = ((sig_src[i] * np.einsum("ij,ij->i", m, s_hat_all[i])) ** 2 + target.var_offset[j]
               + dt2 * target.var_normal[j])
        w = 1.0 / np.maximum(var, 1e-12)
        if gate_chi2 is not None:  # outliers (e.g. across a stair edge) get no weight; the gate
            # widens with the robust spread of the normalised residuals (a poor start)
            e2 = r * r * w
            spread = max(1.0, float(np.median(e2)) / 0.455)  # 0.455: median of chi2(1)
            w = np.where(e2 <= gate_chi2 * spread, w, 0.0)
        H = (J * w[:, None]).T @ J
        g = (J * w[:, None]).T @ r
        used = w > 0
        return 0.5 * (H + H.T), g, r[used], int(used.sum()) / max(1, len(src_pts))

    it = 0
    for it in range(1, max_iterations + 1):
        H, g, r, _ = linearise(T)
        dx = constrained_step(H, g, scale=scale, degeneracy_ratio=degenerate_ratio).step
        T = T @ se3_exp(dx)
        if np.linalg.norm(dx[:3]) < 1e-7 and np.linalg.norm(dx[3:]) < 1e-6:
            break
    H, g, r, fitness = linearise(T)
    last = constrained_step(H, g, scale=scale, degeneracy_ratio=degenerate_ratio)
    A = last.basis.T * scale  # rows v_s^T S: A xi = v_s^T xi_s
    cov = np.diag(1.0 / last.eigenvalues)
    return IcpResult(T, H, A, cov, int(len(r)), float(fitness), float(np.sqrt(np.mean(r**2))), it)
