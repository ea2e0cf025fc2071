"""Stitching a sequence of depth clouds into one map: regularised, degeneracy-aware point-to-plane
ICP of each cloud against the map of the others (the stairs model's, Zhao 2020 section 3.2).

Frames and units: clouds in the sensor (optical) frame, poses ``T_world_sensor`` (4x4), the map in
the world frame; corrections are right perturbations ``T_world_sensor Exp(delta)``, ``delta = [omega,
v]`` (rad, m; GTSAM order, docs/conventions.md). Metres, radians.

1. **Normals** (:func:`cloud_normals`): each cloud is voxel-downsampled (``voxel_m``) and gets PCA
   normals at two scales from one neighbour search (``normal_radius_m`` for the ICP, a smaller
   ``class_radius_m`` to tell surfaces apart up to their edges), each with its predicted tilt std
   ``sqrt(lambda_min / (m lambda_mid))``; normals above ``max_normal_tilt_rad`` (resp.
   ``class_max_normal_tilt_rad``) are unreliable (sparse far points, points on an edge).
2. **Stitching** (:func:`stitch_clouds`): each cloud is registered to the map of the clouds
   before it (pass 1), then each to its ``neighbours`` nearest others (pass 2, ``passes``):
   Gauss-Newton point-to-plane ICP on the sensor pose against the reliable map points and their
   normals, with Huber weights (per-point depth std ``hypot(coeff z^2, 2 mm)``), a weak prior on
   ``delta`` (``prior_sigma_m``, ``prior_sigma_rad``) and no update along degenerate directions
   (eigenvalues of the information below ``degeneracy_ratio`` of the largest, rotations scaled by
   1 m; the step is :func:`graphcal.solvers.point_to_plane.constrained_step`): stairs leave the
   direction along the nosings unconstrained, a view of one tread three directions. Source points
   are those with a reliable normal (``reliable_source``); each is matched to its nearest map point
   by a k-d tree, gated at each of ``gates_m`` in turn, and kept only if the two normals agree
   within ``max_normal_angle_rad`` (without this, the points of a tread seen at a grazing angle
   matched the top of the riser in front of it, where the map ends, and pulled the cloud back and
   down). A cloud whose final inlier fraction is below ``min_fitness`` keeps its pose and stays out
   of the map. The stitched poses are then moved as a whole by the rigid transform that moves them
   least onto the given ones (rotation: chordal mean; translation: mean): the map keeps the given
   world frame with the *average* of the clouds' independent errors (a joint fit over the points
   turned 1 cm translation errors into 0.5-0.9 deg of tilt: the clouds see different parts).

This is not :mod:`graphcal.clouds.icp` (one frame onto one keyframe, Open3D correspondences, local
plane variances, no prior, the information for the EKF): a map of many clouds, a prior, Huber
weights, normal compatibility and the anchoring above. Open3D's unregularised
``registration_icp`` moved stairs clouds 1-5 cm along the nosings and diverged on one-tread views.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from graphcal.geometry import nearest_rotation, pose_matrix, se3_exp, transform_points
from graphcal.solvers.point_to_plane import constrained_step, point_to_plane_jacobian

__all__ = ["StitchConfig", "CloudNormals", "StitchResult", "cloud_normals", "stitch_clouds"]


@dataclass(frozen=True)
class StitchConfig:
    """The stitching's tuning (module docstring; SI units).

    Attributes:
        voxel_m: voxel size of the downsampled clouds (m).
        normal_radius_m: neighbourhood radius of the ICP normals (m).
        max_normal_tilt_rad: ICP normals with a larger predicted tilt std are unreliable (rad).
        gates_m: correspondence distance gates, one round of ICP each (m); pass 2 uses the last two.
        prior_sigma_m, prior_sigma_rad: the prior on the correction ``delta`` (m, rad).
        min_fitness: a cloud with a smaller final inlier fraction keeps its pose.
        max_iterations: Gauss-Newton iterations per gate.
        degeneracy_ratio: directions with information below this fraction of the largest get no update.
        max_source_points: source points per cloud (randomly chosen).
        passes: 1 = each cloud to the map before it; 2 = then each to its nearest others.
        neighbours: in pass 2, each cloud is registered to the clouds with the nearest sensor positions.
        max_normal_angle_rad: a correspondence counts only if the two normals agree within this
            angle (pi / 2 or more: no test).
        reliable_source: register only the source points with a reliable normal.
    """

    voxel_m: float = 0.01
    normal_radius_m: float = 0.05
    max_normal_tilt_rad: float = 0.02
    gates_m: tuple = (0.10, 0.05, 0.025, 0.015)
    prior_sigma_m: float = 0.02
    prior_sigma_rad: float = float(np.radians(1.0))
    min_fitness: float = 0.15
    max_iterations: int = 10
    degeneracy_ratio: float = 0.001
    max_source_points: int = 3000
    passes: int = 2
    neighbours: int = 8
    max_normal_angle_rad: float = float(np.radians(30.0))
    reliable_source: bool = True


@dataclass(frozen=True, eq=False)
class CloudNormals:
    """Per cloud (sensor frame): voxel-downsampled points ``down`` (M_k, 3) m, their ICP-scale
    ``normals`` and ``reliable`` masks, and the classification-scale ``normals_class`` and
    ``reliable_class`` (module docstring, step 1)."""

    down: list
    normals: list
    reliable: list
    normals_class: list
    reliable_class: list


@dataclass(frozen=True, eq=False)
class StitchResult:
    """Per cloud: the corrected ``T_world_sensor`` (4x4), the inlier ``fitness`` of its last ICP
    round (1.0 for the first cloud) and whether the correction was ``accepted``."""

    T_world_sensor: list
    fitness: list
    accepted: list


# ----------------------------------------------------------------------------- normals
def _voxel_down(points: np.ndarray, voxel_m: float) -> np.ndarray:
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    return np.asarray(pcd.voxel_down_sample(voxel_m).points)


def _pca_normals(points: np.ndarray, idx: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """PCA normals from the neighbours ``idx`` (M, k) where ``ok``, and the predicted variance of
    each normal's tilt (rad^2), ``lambda_min / (m lambda_mid)`` (m neighbours; inf below 8)."""
    m = ok.sum(axis=1)
    Q = points[np.where(ok, idx, 0)]  # (M, k, 3)
    w = ok.astype(float)[:, :, None]
    mm = np.maximum(m, 1)
    mean = (Q * w).sum(axis=1) / mm[:, None]
    X = (Q - mean[:, None, :]) * w
    C = np.empty((len(points), 3, 3))
    for i in range(3):
        for j in range(i, 3):
            C[:, i, j] = C[:, j, i] = (X[:, :, i] * X[:, :, j]).sum(axis=1)
    C /= mm[:, None, None]
    lam, V = np.linalg.eigh(C)
    tilt_var = np.where(m >= 8, lam[:, 0] / (mm * np.maximum(lam[:, 1], 1e-12)), np.inf)
    return V[:, :, 0], tilt_var


def _map_normals(points: np.ndarray, radius_m: float, small_radius_m: float, k: int = 30):
    """Normals of points at two scales from one neighbour search: from the neighbours within
    ``radius_m`` (at most ``k``; for the ICP: smooth) and within ``small_radius_m`` (to classify
    surfaces up to their edges), each with its predicted tilt variance (:func:`_pca_normals`).
    Sparse far points and points on an edge (two planes in the neighbourhood) have a large one:
    their noisy normals would give point-to-plane ICP spurious constraints along the planes, and
    they say nothing about a surface's orientation."""
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(points).query(points, k=k, distance_upper_bound=radius_m)
    ok = np.isfinite(dist)
    n_large, v_large = _pca_normals(points, idx, ok)
    n_small, v_small = _pca_normals(points, idx, ok & (dist <= small_radius_m))
    return n_large, v_large, n_small, v_small


def cloud_normals(clouds: Sequence[np.ndarray], config: StitchConfig, *, class_radius_m: float,
                  class_max_normal_tilt_rad: float) -> CloudNormals:
    """Per cloud (N_k, 3) (sensor frame, m): voxel-downsampled points with normals and their
    reliability at the ICP scale (``config``) and at the classification scale (``class_radius_m``
    m, ``class_max_normal_tilt_rad`` rad; where the small scale lacks the neighbours, the large
    one). Clouds with fewer than 10 voxels get no reliable normal."""
    down, nrm, rel, nrm_c, rel_c = [], [], [], [], []
    for c in clouds:
        d = _voxel_down(c, config.voxel_m) if len(c) else np.zeros((0, 3))
        if len(d) >= 10:
            n, v, n_c, v_c = _map_normals(d, config.normal_radius_m, class_radius_m)
            r = v < config.max_normal_tilt_rad**2  # strict: for the ICP
            # loose: for classification; the small scale where it has the neighbours
            # (up to the edges), else the large one (sparse far points)
            small_ok = v_c < class_max_normal_tilt_rad**2
            n_c = np.where(small_ok[:, None], n_c, n)
            r_c = small_ok | (v < class_max_normal_tilt_rad**2)
        else:
            n, r = np.zeros((len(d), 3)), np.zeros(len(d), dtype=bool)
            n_c, r_c = n, r
        down.append(d)
        nrm.append(n)
        rel.append(r)
        nrm_c.append(n_c)
        rel_c.append(r_c)
    return CloudNormals(down, nrm, rel, nrm_c, rel_c)


# ----------------------------------------------------------------------------- ICP of one cloud
def _icp_to_map(
    src_sensor: np.ndarray,
    sigma_src: np.ndarray,
    T_init: np.ndarray,
    tree,
    map_points: np.ndarray,
    map_normals: np.ndarray,
    *,
    gates_m: Sequence[float],
    prior_sigma_m: float,
    prior_sigma_rad: float,
    max_iterations: int,
    degeneracy_ratio: float,
    src_normals: np.ndarray | None = None,
    normal_cos_min: float = 0.0,
) -> tuple[np.ndarray, float, int]:
    """Regularised point-to-plane ICP of one cloud against the map (module docstring, step 2).

    Minimises ``sum_i rho((n_i . (T Exp(delta) p_i - q_i)) / sigma_i) + delta^T Lambda delta`` over
    ``delta = [omega, v]`` (sensor frame, GTSAM order) by Gauss-Newton. Returns the corrected
    ``T_world_sensor``, the inlier fraction of the last round and the number of degenerate
    directions of its last iteration.
    """
    prior = np.r_[np.full(3, 1.0 / prior_sigma_rad**2), np.full(3, 1.0 / prior_sigma_m**2)]
    scale = np.r_[np.full(3, 1.0), np.full(3, 1.0)]  # rotation (rad) as metres at 1 m
    delta_total = np.zeros(6)
    T = T_init.copy()
    fitness = 0.0
    n_degenerate = 6
    for gate in gates_m:
        for _ in range(max_iterations):
            R = T[:3, :3]
            p_world = src_sensor @ R.T + T[:3, 3]
            dist, idx = tree.query(p_world, k=1, distance_upper_bound=gate)
            ok = np.isfinite(dist)
            if ok.sum() < 6:
                fitness = float(ok.mean())
                break
            ps = src_sensor[ok]
            n = map_normals[idx[ok]]
            r = np.einsum("ij,ij->i", n, p_world[ok] - map_points[idx[ok]])
            sig = sigma_src[ok]
            keep = np.abs(r) < gate
            if src_normals is not None and normal_cos_min > 0:
                # a source point on one surface matched to a map point on another (the map's
                # edge: a tread point to the top of the riser below it) pulls the cloud sideways
                keep &= np.abs(np.einsum("ij,ij->i", src_normals[ok] @ R.T, n)) >= normal_cos_min
            ps, n, r, sig = ps[keep], n[keep], r[keep], sig[keep]
            fitness = float(keep.sum()) / len(src_sensor)
            J = point_to_plane_jacobian(ps, n, R)  # d r / d [omega, v]
            z = np.abs(r) / sig
            w = np.where(z <= 2.0, 1.0, 2.0 / np.maximum(z, 1e-12)) / sig**2  # Huber at 2 sigma
            H_data = (J * w[:, None]).T @ J
            g = (J * w[:, None]).T @ r + prior * delta_total
            # degenerate directions (along a plane, along the nosings): no update there; the
            # noise of the map normals alone would let the cloud slide (module docstring)
            cs = constrained_step(H_data, g, scale=scale, degeneracy_ratio=degeneracy_ratio, prior_information=prior)
            step, n_degenerate = cs.step, cs.n_degenerate
            T = T @ se3_exp(step)
            delta_total += step
            if np.linalg.norm(step[:3]) < 1e-5 and np.linalg.norm(step[3:]) < 1e-5:
                break
    return T, fitness, n_degenerate


def _thin_by_voxel(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Indices of one point per ``voxel_m`` cube (the first one)."""
    keys = np.floor(points / voxel_m).astype(np.int64)
    keys -= keys.min(axis=0)
    key = (keys[:, 0] << 42) | (keys[:, 1] << 21) | keys[:, 2]  # 21 bits per axis: 20 km at 1 cm
    _, first = np.unique(key, return_index=True)
    return np.sort(first)


# ----------------------------------------------------------------------------- the sequence
def _anchor(poses: list[np.ndarray], corrected: list[np.ndarray], accepted: list[bool]) -> list[np.ndarray]:
    """The corrected poses moved by the rigid transform A that moves them least onto the given
    ones, rotation and translation averaged separately (a joint least-squares fit over the points
    turns the clouds' translation errors into a tilt: the clouds see different parts of the scene)."""
    ks = [k for k in range(len(poses)) if accepted[k]]
    if len(ks) <= 1:
        return corrected
    M = sum(poses[k][:3, :3] @ corrected[k][:3, :3].T for k in ks)
    R_A = nearest_rotation(M)
    t_A = np.mean([poses[k][:3, 3] - R_A @ corrected[k][:3, 3] for k in ks], axis=0)
    A = pose_matrix(R_A, t_A)
    return [A @ T if ok else T for T, ok in zip(corrected, accepted)]


def stitch_clouds(normals: CloudNormals, T_world_sensor: Sequence[np.ndarray], noise_coeff_per_m: float,
                  config: StitchConfig, rng: np.random.Generator) -> StitchResult:
    """Corrected ``T_world_sensor`` per cloud: ICP of each cloud to the map of the accepted clouds
    before it (pass 1), then (``passes`` > 1) of each cloud to its nearest accepted others, then the
    anchoring transform (module docstring, step 2).

    Args:
        normals: the clouds' downsampled points and normals (:func:`cloud_normals`).
        T_world_sensor: per cloud, the given sensor pose (4x4, m).
        noise_coeff_per_m: depth noise sigma_z = coeff z^2 (m), for the Huber weights.
        config: the tuning (:class:`StitchConfig`).
        rng: draws the source points.
    """
    from scipy.spatial import cKDTree

    poses = list(T_world_sensor)
    down, nrm, rel = normals.down, normals.normals, normals.reliable
    cfg = config
    normal_cos_min = float(np.cos(cfg.max_normal_angle_rad)) if cfg.max_normal_angle_rad < np.pi / 2 else 0.0
    gates_m = tuple(cfg.gates_m)
    K = len(poses)
    # source points: those with a reliable normal (reliable_source), else all
    pools = [np.flatnonzero(r) if cfg.reliable_source else np.arange(len(r)) for r in rel]
    src_idx = [
        np.sort(rng.choice(pool, size=cfg.max_source_points, replace=False)) if len(pool) > cfg.max_source_points
        else pool
        for pool in pools
    ]

    def world_part(j: int, T: np.ndarray):
        return transform_points(T, down[j][rel[j]]), nrm[j][rel[j]] @ T[:3, :3].T

    def target_of(parts: list):
        if not parts:
            return None
        P, N = np.vstack([q for q, _ in parts]), np.vstack([n for _, n in parts])
        keep = _thin_by_voxel(P, cfg.voxel_m)
        if len(keep) < 50:
            return None
        return cKDTree(P[keep]), P[keep], N[keep]

    corrected = [T.copy() for T in poses]
    fitness = [1.0] + [0.0] * (K - 1)
    accepted = [len(down[0]) > 0] + [False] * (K - 1)
    for p in range(max(1, cfg.passes)):
        if p == 0:
            parts = {0: world_part(0, corrected[0])} if accepted[0] else {}
        else:  # every cloud against the others, at their poses of the previous pass
            parts = {j: world_part(j, corrected[j]) for j in range(K) if accepted[j]}
            centres = np.array([T[:3, 3] for T in corrected])
        for k in range(1, K) if p == 0 else range(K):
            members = [j for j in parts if j != k]
            if p > 0 and len(members) > cfg.neighbours:  # the nearest sensor positions only
                dist = np.linalg.norm(centres[members] - centres[k], axis=1)
                members = [members[i] for i in np.argsort(dist)[:cfg.neighbours]]
            tgt = target_of([parts[j] for j in members]) if len(src_idx[k]) >= 20 else None
            if tgt is None:
                continue
            tree, target, target_normals = tgt
            src = down[k][src_idx[k]]
            sigma = np.hypot(noise_coeff_per_m * src[:, 2] ** 2, 0.002)
            T_start = corrected[k] if p > 0 else poses[k]
            T_new, fit, _ = _icp_to_map(
                src, sigma, T_start, tree, target, target_normals,
                gates_m=gates_m if p == 0 else gates_m[-2:], prior_sigma_m=cfg.prior_sigma_m,
                prior_sigma_rad=cfg.prior_sigma_rad, max_iterations=cfg.max_iterations,
                degeneracy_ratio=cfg.degeneracy_ratio, src_normals=nrm[k][src_idx[k]], normal_cos_min=normal_cos_min,
            )
            if fit >= cfg.min_fitness:
                corrected[k] = T_new
                fitness[k] = fit
                accepted[k] = True
                if p == 0:
                    parts[k] = world_part(k, T_new)
            elif p == 0:
                fitness[k] = fit
    return StitchResult(_anchor(poses, corrected, accepted), fitness, accepted)
