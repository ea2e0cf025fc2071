"""Stairs model from depth clouds and (estimated) sensor poses: treads (height, depth, width, edge
line) after ICP stitching, Zhao et al. 2020 section 3.2 with the changes listed below.

Frames and units
----------------
Input clouds are in the sensor frame (optical: z along the optical axis), metres; poses are
``T_world_sensor`` (4x4, world z up, gravity along -z). The model is expressed in the world frame
and in a *stairs frame* ``T_world_stairs``: x = the walking direction up the stairs (horizontal),
z = up (the normal of the floor), y = z x x, origin on the floor plane below the midpoint of the
lowest nosing. Along-stairs coordinates are called ``s`` (stairs x), lateral ``t`` (stairs y),
height ``h`` (stairs z). Planes are ``(n, d)`` with ``n . x + d = 0``, canonical ``d >= 0``
(:func:`graphcal.geometry.canonical_plane`). SI units throughout.

Method (:func:`model_stairs`)
-----------------------------
1. **To world** (Zhao Eq. 10): ``p_world = T_world_sensor @ p_sensor``; points beyond
   ``max_depth_m`` along the optical axis are dropped (Kinect noise grows with z^2: 9 mm at 2.5 m).
   Each cloud is voxel-downsampled (``icp_voxel_m``) and gets PCA normals at two scales from one
   neighbour search (``icp_normal_radius_m`` for the ICP, ``class_normal_radius_m`` to tell
   horizontal from vertical surfaces up to their edges), each with its predicted tilt std
   ``sqrt(lambda_min / (m lambda_mid))``; normals above ``icp_max_normal_tilt_rad`` /
   ``class_max_normal_tilt_rad`` are unreliable (sparse far points, points on an edge).
2. **ICP stitching.** Each cloud is registered to the map of the clouds before it (pass 1), then
   each to all the others (pass 2, ``icp_passes``): Gauss-Newton point-to-plane ICP on the sensor
   pose, ``T_world_sensor Exp(delta)``, against the reliable map points and their normals, with
   Huber weights (per-point Kinect std), a weak prior on ``delta`` (``icp_prior_sigma_m``,
   ``icp_prior_sigma_rad``) and no update along degenerate directions (eigenvalues of the
   information below ``icp_degeneracy_ratio`` of the largest, rotations scaled by 1 m): stairs leave
   the direction along the nosings unconstrained, a view of one tread three directions, and
   point-to-plane ICP slides along them on the noise of the normals. (Open3D's unregularised
   ``registration_icp`` moved clouds 1-5 cm along the nosings and diverged on one-tread views in our
   runs.) Source points are those with a reliable normal (``icp_reliable_source``); each is
   matched to its nearest map point by a k-d tree, gated at 10, 5, 2.5 and 1.5 cm in turn, and
   kept only if the two normals agree within ``icp_max_normal_angle_deg``. (Without these two, the
   points of a tread seen at a grazing angle -- the landing, ~15 cm below the camera -- matched the
   top of the riser in front of it, where the map ends, and pulled the cloud back and down: clouds
   started at their true poses ended up to 1.2 deg of pitch and 1.8 cm off, and the landing's
   height was +3 to +7 mm off in the ``tripod-stairs`` walk.) A cloud whose final inlier fraction
   is below ``icp_min_fitness`` keeps its estimated pose and stays out of the map and the model.
   The stitched map is then moved as a whole by the rigid transform that moves
   the stitched sensor poses least onto the estimated ones (rotation: chordal mean; translation:
   mean): the map keeps the estimate's world frame with the *average* of the clouds' independent
   errors (a joint fit over the points instead turned 1 cm translation errors into 0.5-0.9 deg of
   tilt, because the clouds see different parts of the stairs).
3. **Planes.** :func:`graphcal.clouds.planes.extract_planes` (Open3D RANSAC on a subsample, then Chai's
   2-sigma PCA loop) separately on the points with a reliable horizontal normal and on those with a
   reliable vertical normal (within ``2 max_tilt_deg``): a slanted plane through the nosings cannot
   form from either set. Horizontal planes (normal within ``max_tilt_deg`` of world z) are the
   floor (the lowest) and the treads; vertical planes facing along the walking direction are the
   risers.
4. **Edges dropped** (Zhao: "ignoring 5 % points near the edge"): of each plane's inliers the
   ``edge_drop_fraction`` lowest and highest along each of its two in-plane axes (walking direction
   and lateral for treads, height and lateral for risers) are discarded (the points within a few
   cm of an edge have no reliable normal and are not inliers in the first place); the plane is
   refitted to the rest by weighted PCA (weights ``1 / sigma_i^2``, ``sigma_i`` the Kinect std of
   the point), trimming at 2.5 sigma_i, three rounds.
5. **Treads.** Height = distance of the tread's inlier centroid to the floor plane (distances
   between nearly parallel planes: independent of a common tilt of the map). The front edge
   (nosing) of tread k is the intersection line of its plane with riser k (the riser between the
   level below and tread k, the nearest one in front of the tread's visible points); its back edge
   is that of tread k+1. Depth = distance between the two edge lines, measured in the tread plane
   perpendicular to the nosing. Without a riser the edge comes from the tread's points (a 0.5 %
   quantile along the walking direction, ``edge_from_riser=False``); without a back riser (the
   top landing) the depth is the visible extent and ``depth_complete=False``. Width = lateral
   extent (0.2-99.8 % quantiles) of every map point on the tread's plane between its edges: the
   *visible* width (the lateral ends are seen only far away, where ``max_depth_m`` cuts).

Deviations from Zhao 2020: risers are fitted too (Zhao fits horizontal planes only) because edge
lines and depths from tread points alone are biased by the point spacing (~1 cm at 2 m with a
quarter-resolution Kinect); clouds are registered to the growing map and then to each other, not
pairwise (earlier = source, later = target) -- pairwise errors add up along the sequence; the ICP
is regularised and degeneracy-aware (above).

Measured (docs/stairs_gait.md): ten simulated approaches, pose errors ~1.7 cm / ~0.5 deg: tread
heights within 0.5 mm, depths within 0.2 mm of the truth; ~2 s for ten clouds on 2 busy cores.
Through ``graphcal track`` (its keyframes and EKF poses, docs/state_estimation.md): within 1.3 mm
and 0.3 mm on the ``tripod-stairs`` walk.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.geometry import canonical_plane, nearest_rotation, pose_matrix, se3_exp, transform_points
from graphcal.models.sensors import KINECT_NOISE_COEFF_PER_M
from graphcal.solvers.point_to_plane import constrained_step, point_to_plane_jacobian

__all__ = [
    "StairsError",
    "StairStep",
    "Tread",
    "Riser",
    "StairsModel",
    "TreadError",
    "model_stairs",
    "stairs_model_from_steps",
    "tread_errors",
    "stairs_to_json",
    "KINECT_NOISE_COEFF_PER_M",
]



class StairsError(GraphcalError):
    """Bad input to the stairs model, or no stairs in the clouds."""


# ----------------------------------------------------------------------------- results
@dataclass(frozen=True)
class StairStep:
    """One true step of an untilted staircase rising along world +x (the records that
    :func:`stairs_model_from_steps` and :func:`tread_errors` read; the ``stairs`` list of a
    ``truth.yaml`` ``ground`` section has these keys).

    Attributes:
        x_start_m: world x of the step's nosing (front edge), m.
        depth_m: tread depth along world +x, m.
        height_m: height of the tread's top above the floor, m.
        width_m: tread width along world y, m.
    """

    x_start_m: float
    depth_m: float
    height_m: float
    width_m: float


@dataclass(frozen=True, eq=False)
class Tread:
    """One tread (the top of a step, or the landing).

    Attributes:
        index: 0 for the lowest tread above the floor, counting up.
        height_m: height of the tread's top above the floor (m), along the floor normal.
        depth_m: tread depth along the walking direction (m), front edge (nosing) to the next riser;
            the visible extent when ``depth_complete`` is False.
        depth_complete: True when both edges were found (riser in front and riser behind).
        width_m: visible lateral extent of the tread (m).
        p_world_edge: (3,) world point on the front edge (nosing) line, at the tread's lateral
            middle (m).
        edge_direction_world: (3,) unit vector along the nosing, pointing to stairs +y (left when
            walking up).
        edge_from_riser: True when the front edge is the tread/riser intersection, False when it
            comes from the tread's points.
        plane_world: ``(n (3,), d)`` of the tread, world frame, canonical.
        n_inliers: points of the tread used in the final fit (after dropping the edges).
        s_front_m, s_back_m: front and back edge along the stairs x axis (m); ``s_back_m`` is the
            visible end when the depth is incomplete.
        t_min_m, t_max_m: visible lateral extent along the stairs y axis (m).
    """

    index: int
    height_m: float
    depth_m: float
    depth_complete: bool
    width_m: float
    p_world_edge: np.ndarray
    edge_direction_world: np.ndarray
    edge_from_riser: bool
    plane_world: tuple
    n_inliers: int
    s_front_m: float
    s_back_m: float
    t_min_m: float
    t_max_m: float


@dataclass(frozen=True, eq=False)
class Riser:
    """A riser (the vertical face of a step).

    Attributes:
        plane_world: ``(n (3,), d)``, world frame, canonical.
        s_m: its position along the stairs x axis at the stairs' lateral middle (m).
        h_low_m, h_high_m: height span of its inliers above the floor (m).
        n_inliers: points used in the final fit.
    """

    plane_world: tuple
    s_m: float
    h_low_m: float
    h_high_m: float
    n_inliers: int


@dataclass(frozen=True, eq=False)
class StairsModel:
    """The stairs in the world frame.

    Attributes:
        treads: the treads, lowest first.
        risers: the risers found, lowest first.
        floor_plane_world: ``(n (3,), d)`` of the floor, canonical.
        floor_n_inliers: points of the floor fit.
        T_world_stairs: (4, 4) the stairs frame (module docstring).
        T_world_sensor_corrected: per cloud, the sensor pose after ICP stitching (4x4); the map's
            points are ``T_world_sensor_corrected[k] @ p_sensor``.
        icp_fitness: per cloud, the inlier fraction of its final ICP round (1.0 for the first).
        icp_accepted: per cloud, whether the ICP correction was kept.
        n_points: points in the stitched map used for the planes.
    """

    treads: tuple
    risers: tuple
    floor_plane_world: tuple
    floor_n_inliers: int
    T_world_stairs: np.ndarray
    T_world_sensor_corrected: tuple = field(default=())
    icp_fitness: tuple = field(default=())
    icp_accepted: tuple = field(default=())
    n_points: int = 0

    @property
    def up_world(self) -> np.ndarray:
        """(3,) unit up direction (the floor normal)."""
        return self.T_world_stairs[:3, 2].copy()

    @property
    def walking_direction_world(self) -> np.ndarray:
        """(3,) unit horizontal direction up the stairs."""
        return self.T_world_stairs[:3, 0].copy()


@dataclass(frozen=True)
class TreadError:
    """Model minus truth for one tread (m); depth error is NaN when the model's depth is incomplete
    (the truth's landing depth is not observable).

    ``edge_along_m`` / ``edge_height_m``: the model's nosing point minus the true nosing line, along
    the walking direction and vertically (world frame, includes the map's residual pose error).
    ``true_index``: index of the matched true step (by height), -1 if none within 5 cm.
    """

    index: int
    true_index: int
    height_error_m: float
    depth_error_m: float
    width_error_m: float
    edge_along_m: float
    edge_height_m: float


# ----------------------------------------------------------------------------- input checks
def _check_inputs(clouds_sensor, T_world_sensor) -> tuple[list[np.ndarray], list[np.ndarray]]:
    clouds = list(clouds_sensor)
    poses = list(T_world_sensor)
    if len(clouds) == 0:
        raise StairsError("model_stairs: no clouds given")
    if len(clouds) != len(poses):
        raise StairsError(f"model_stairs: {len(clouds)} clouds but {len(poses)} poses T_world_sensor")
    out_c, out_T = [], []
    for k, (c, T) in enumerate(zip(clouds, poses)):
        c = np.asarray(c, dtype=float)
        if c.ndim != 2 or c.shape[1] != 3:
            raise StairsError(f"model_stairs: cloud {k} must have shape (N, 3) (sensor frame, m), got {c.shape}")
        c = c[np.all(np.isfinite(c), axis=1)]  # depth cameras report no-return pixels as NaN
        T = np.asarray(T, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise StairsError(f"model_stairs: pose {k} must be a finite 4x4 T_world_sensor, got shape {T.shape}")
        R = T[:3, :3]
        if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]) or not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise StairsError(f"model_stairs: pose {k} is not a rigid transform (rotation not orthonormal or bad last row)")
        out_c.append(c)
        out_T.append(T)
    return out_c, out_T


# ----------------------------------------------------------------------------- ICP stitching
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
    surfaces as horizontal or vertical up to their edges), each with its predicted tilt variance
    (:func:`_pca_normals`). Sparse far points and points on an edge (two planes in the
    neighbourhood) have a large one: their noisy normals would give point-to-plane ICP spurious
    constraints along the planes, and they say nothing about a surface's orientation."""
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(points).query(points, k=k, distance_upper_bound=radius_m)
    ok = np.isfinite(dist)
    n_large, v_large = _pca_normals(points, idx, ok)
    n_small, v_small = _pca_normals(points, idx, ok & (dist <= small_radius_m))
    return n_large, v_large, n_small, v_small


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


def _stitch(
    clouds_sensor: list[np.ndarray],
    poses: list[np.ndarray],
    down: list[np.ndarray],
    nrm: list[np.ndarray],
    rel: list[np.ndarray],
    noise_coeff: float,
    *,
    voxel_m: float,
    gates_m: Sequence[float],
    prior_sigma_m: float,
    prior_sigma_rad: float,
    min_fitness: float,
    max_iterations: int,
    degeneracy_ratio: float,
    max_source_points: int,
    passes: int,
    neighbours: int,
    rng: np.random.Generator,
    normal_cos_min: float = 0.0,
    reliable_source: bool = False,
) -> tuple[list[np.ndarray], list[float], list[bool]]:
    """Corrected T_world_sensor per cloud: ICP of each cloud to the map of the accepted clouds
    before it (pass 1), then (passes > 1) of each cloud to all the other accepted clouds, then the
    anchoring transform (module docstring, step 2). ``down``, ``nrm``, ``rel``: per cloud its
    voxel-downsampled points, their normals (sensor frame) and reliability (:func:`_map_normals`)."""
    from scipy.spatial import cKDTree

    K = len(poses)
    # source points: those with a reliable normal (reliable_source), else all
    pools = [np.flatnonzero(r) if reliable_source else np.arange(len(r)) for r in rel]
    src_idx = [
        np.sort(rng.choice(pool, size=max_source_points, replace=False)) if len(pool) > max_source_points else pool
        for pool in pools
    ]

    def world_part(j: int, T: np.ndarray):
        return transform_points(T, down[j][rel[j]]), nrm[j][rel[j]] @ T[:3, :3].T

    def target_of(parts: list):
        if not parts:
            return None
        P, N = np.vstack([q for q, _ in parts]), np.vstack([n for _, n in parts])
        keep = _thin_by_voxel(P, voxel_m)
        if len(keep) < 50:
            return None
        return cKDTree(P[keep]), P[keep], N[keep]

    corrected = [T.copy() for T in poses]
    fitness = [1.0] + [0.0] * (K - 1)
    accepted = [len(down[0]) > 0] + [False] * (K - 1)
    for p in range(max(1, passes)):
        if p == 0:
            parts = {0: world_part(0, corrected[0])} if accepted[0] else {}
        else:  # every cloud against the others, at their poses of the previous pass
            parts = {j: world_part(j, corrected[j]) for j in range(K) if accepted[j]}
            centres = np.array([T[:3, 3] for T in corrected])
        for k in range(1, K) if p == 0 else range(K):
            members = [j for j in parts if j != k]
            if p > 0 and len(members) > neighbours:  # the nearest sensor positions only
                dist = np.linalg.norm(centres[members] - centres[k], axis=1)
                members = [members[i] for i in np.argsort(dist)[:neighbours]]
            tgt = target_of([parts[j] for j in members]) if len(src_idx[k]) >= 20 else None
            if tgt is None:
                continue
            tree, target, normals = tgt
            src = down[k][src_idx[k]]
            sigma = np.hypot(noise_coeff * src[:, 2] ** 2, 0.002)
            T_start = corrected[k] if p > 0 else poses[k]
            T_new, fit, _ = _icp_to_map(
                src, sigma, T_start, tree, target, normals,
                gates_m=gates_m if p == 0 else gates_m[-2:], prior_sigma_m=prior_sigma_m,
                prior_sigma_rad=prior_sigma_rad, max_iterations=max_iterations, degeneracy_ratio=degeneracy_ratio,
                src_normals=nrm[k][src_idx[k]], normal_cos_min=normal_cos_min,
            )
            if fit >= min_fitness:
                corrected[k] = T_new
                fitness[k] = fit
                accepted[k] = True
                if p == 0:
                    parts[k] = world_part(k, T_new)
            elif p == 0:
                fitness[k] = fit
    # anchor: the rigid transform A that moves the stitched poses least onto the estimated ones,
    # rotation and translation averaged separately (a joint least-squares fit over the points turns
    # the clouds' translation errors into a tilt: the clouds see different parts of the stairs)
    ks = [k for k in range(K) if accepted[k]]
    if len(ks) > 1:
        M = sum(poses[k][:3, :3] @ corrected[k][:3, :3].T for k in ks)
        R_A = nearest_rotation(M)
        t_A = np.mean([poses[k][:3, 3] - R_A @ corrected[k][:3, 3] for k in ks], axis=0)
        A = pose_matrix(R_A, t_A)
        corrected = [A @ T if ok else T for T, ok in zip(corrected, accepted)]
    return corrected, fitness, accepted


# ----------------------------------------------------------------------------- plane fitting
def _weighted_plane(P: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Weighted PCA plane: unit n (smallest eigenvector), d, and the weighted centroid."""
    W = w.sum()
    c = (w @ P) / W
    X = P - c
    S = (X * w[:, None]).T @ X
    _, V = np.linalg.eigh(S)
    n = V[:, 0]
    return n, float(-n @ c), c


def _refine_central(P: np.ndarray, sigma: np.ndarray, axis_a: np.ndarray, axis_b: np.ndarray, drop: float, rounds: int = 3):
    """Drop the ``drop`` fraction of points nearest each edge (lowest / highest along ``axis_a``
    and ``axis_b``), then weighted PCA with 2.5-sigma trimming. Returns (n, d, centroid, kept mask)."""
    keep = np.ones(len(P), dtype=bool)
    if drop > 0:
        for ax in (axis_a, axis_b):
            u = P @ ax
            lo, hi = np.quantile(u, [drop, 1.0 - drop])
            keep &= (u >= lo) & (u <= hi)
    w = 1.0 / sigma**2
    sel = keep.copy()
    n, d, c = _weighted_plane(P[sel], w[sel])
    for _ in range(rounds):
        r = np.abs(P @ n + d) / sigma
        new = keep & (r <= 2.5)
        if new.sum() < 10:
            break
        sel = new
        n, d, c = _weighted_plane(P[sel], w[sel])
    return n, d, c, sel


@dataclass(frozen=True, eq=False)
class _Patch:
    n: np.ndarray  # unit, oriented (up for horizontal, towards -walking for risers)
    d: float
    centroid: np.ndarray
    points: np.ndarray  # central inliers used in the final fit (world)
    all_points: np.ndarray  # every inlier of extract_planes (world)
    n_inliers: int


def _edge_line(tread: _Patch, riser: _Patch) -> tuple[np.ndarray, np.ndarray]:
    """Intersection line of the two planes: (point nearest the tread centroid, unit direction)."""
    e = np.cross(riser.n, tread.n)
    e /= np.linalg.norm(e)
    # point x: n_t . x = -d_t, n_r . x = -d_r, e . x = e . c_t
    A = np.vstack([tread.n, riser.n, e])
    b = np.array([-tread.d, -riser.d, e @ tread.centroid])
    return np.linalg.solve(A, b), e


# ----------------------------------------------------------------------------- model_stairs, stage by stage
@dataclass(frozen=True, eq=False)
class _CloudNormals:
    """Per cloud (sensor frame): voxel-downsampled points (M_k, 3) m, their ICP-scale normals and
    reliability, and the classification-scale normals and reliability (module docstring, step 1)."""

    down: list
    normals: list
    reliable: list
    normals_class: list
    reliable_class: list


@dataclass(frozen=True, eq=False)
class _PointMap:
    """The stitched map (world frame): points P (N, 3) m, their noise std sig (N,) m, normals N
    (N, 3) and whether each normal is reliable for classification (N,)."""

    P: np.ndarray
    sig: np.ndarray
    N: np.ndarray
    reliable: np.ndarray


@dataclass(frozen=True, eq=False)
class _TreadInfo:
    """A tread patch, the index of its front riser in the riser patches (None: no riser found),
    the 0.5 % quantile of its visible points along the walking direction (m, world origin) and the
    mask of the map points on its plane."""

    patch: _Patch
    riser: int | None
    s_min: float
    support: np.ndarray


@dataclass(frozen=True, eq=False)
class _FrontEdge:
    """A tread's front edge (nosing): a world point on it (3,) m, its unit direction (3,) towards
    stairs +y, and whether it is the tread/riser intersection."""

    point: np.ndarray
    direction: np.ndarray
    from_riser: bool


def _prepare_clouds(clouds: list[np.ndarray], max_depth_m: float, max_points_per_cloud: int,
                    min_plane_points: int, gen: np.random.Generator) -> list[np.ndarray]:
    """Sensor-frame clouds (N_k, 3) m cut at ``max_depth_m`` along the optical axis and randomly
    thinned to ``max_points_per_cloud``; StairsError when fewer than 3 ``min_plane_points`` remain."""
    clouds = [c[(c[:, 2] > 0) & (c[:, 2] <= max_depth_m)] for c in clouds]
    clouds = [c[np.sort(gen.choice(len(c), max_points_per_cloud, replace=False))] if len(c) > max_points_per_cloud else c
              for c in clouds]
    n_total = sum(len(c) for c in clouds)
    if n_total < 3 * min_plane_points:
        raise StairsError(f"model_stairs: only {n_total} points within {max_depth_m} m in the clouds")
    return clouds


def _cloud_normals(clouds: list[np.ndarray], voxel_m: float, normal_radius_m: float, class_radius_m: float,
                   max_normal_tilt_rad: float, class_max_normal_tilt_rad: float) -> _CloudNormals:
    """Per cloud: voxel-downsampled points with normals (sensor frame) and their reliability."""
    down, nrm, rel, nrm_c, rel_c = [], [], [], [], []
    for c in clouds:
        d = _voxel_down(c, voxel_m) if len(c) else np.zeros((0, 3))
        if len(d) >= 10:
            n, v, n_c, v_c = _map_normals(d, normal_radius_m, class_radius_m)
            r = v < max_normal_tilt_rad**2  # strict: for the ICP
            # loose: horizontal / vertical pools; the small scale where it has the neighbours
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
    return _CloudNormals(down, nrm, rel, nrm_c, rel_c)


def _point_map(clouds: list[np.ndarray], used: list[int], corrected: list[np.ndarray], normals: _CloudNormals,
               noise_coeff_per_m: float, max_points: int, gen: np.random.Generator) -> _PointMap:
    """World points of the ``used`` clouds at their ``corrected`` sensor poses (4x4), their noise std
    and normals (from the nearest downsampled point), randomly thinned to ``max_points``."""
    from scipy.spatial import cKDTree

    Ps, sigs, Ns, Rs = [], [], [], []
    for k in used:
        c = clouds[k]
        if len(c) == 0 or len(normals.down[k]) == 0:
            continue
        _, j = cKDTree(normals.down[k]).query(c, k=1)
        R = corrected[k][:3, :3]
        Ps.append(transform_points(corrected[k], c))
        sigs.append(np.hypot(noise_coeff_per_m * c[:, 2] ** 2, 1e-4))
        Ns.append(normals.normals_class[k][j] @ R.T)
        Rs.append(normals.reliable_class[k][j])
    if not Ps:
        raise StairsError("model_stairs: no cloud could be used (the first cloud is empty?)")
    P, sig, N, reliable = np.vstack(Ps), np.concatenate(sigs), np.vstack(Ns), np.concatenate(Rs)
    if len(P) > max_points:
        pick = gen.choice(len(P), size=max_points, replace=False)
        P, sig, N, reliable = P[pick], sig[pick], N[pick], reliable[pick]
    return _PointMap(P, sig, N, reliable)


def _planes_of(P: np.ndarray, pool: np.ndarray, *, max_planes: int, ransac_distance_m: float,
               min_plane_points: int, gen: np.random.Generator) -> list:
    """Planes among the map points ``P[pool]`` (:func:`graphcal.clouds.planes.extract_planes`, up to
    three draws): (fit, mask over all of P) pairs."""
    from graphcal.clouds.planes import extract_planes

    if len(pool) < min_plane_points:
        return []
    for attempt in range(3):
        try:
            fits = extract_planes(P[pool], max_planes=max_planes, ransac_distance_m=ransac_distance_m,
                                  min_inliers=min_plane_points, rng=gen)
            break
        except GraphcalError:  # a degenerate candidate set in the 2-sigma loop: new draw
            fits = []
    out = []
    for f in fits:
        mask = np.zeros(len(P), dtype=bool)
        mask[pool[f.inlier_mask]] = True
        out.append((f, mask))
    return out


def _initial_walking_direction(walking_direction_world, corrected: list[np.ndarray], z: np.ndarray) -> np.ndarray:
    """Unit horizontal walking direction (3,): the given one, else the mean horizontal viewing
    direction of the clouds (refined by the risers later)."""
    if walking_direction_world is not None:
        w0 = np.asarray(walking_direction_world, dtype=float)
        if w0.shape != (3,) or not np.all(np.isfinite(w0)):
            raise StairsError(f"model_stairs: walking_direction_world must be a finite 3-vector, got {walking_direction_world!r}")
    else:
        w0 = np.sum([T[:3, 2] for T in corrected], axis=0)
    w0 = w0 - (w0 @ z) * z
    if np.linalg.norm(w0) < 1e-6:
        raise StairsError("model_stairs: the walking direction is vertical or zero")
    w0 /= np.linalg.norm(w0)
    return w0


def _horizontal_patches(horiz: list, pm: _PointMap, w0: np.ndarray, z: np.ndarray, min_step_height_m: float,
                        edge_drop_fraction: float) -> list[_Patch]:
    """Horizontal patches, lowest first: oriented up, refined centrally; planes at the same height merged."""
    P, sig = pm.P, pm.sig
    lat0 = np.cross(z, w0)
    patches_h: list[_Patch] = []
    for f, mask in sorted(horiz, key=lambda fm: -fm[0].n_points):
        n = f.n if f.n @ z > 0 else -f.n
        Pin = P[mask]
        h_c = float(np.median(Pin @ n))
        if any(abs(h_c - float(np.median(p.all_points @ p.n))) < min_step_height_m / 2 for p in patches_h):
            continue  # a second fit of an already found level
        nn, dd, c, sel = _refine_central(Pin, sig[mask], w0, lat0, edge_drop_fraction)
        if nn @ z < 0:
            nn, dd = -nn, -dd
        patches_h.append(_Patch(nn, dd, c, Pin[sel], Pin, int(sel.sum())))
    patches_h.sort(key=lambda p: p.centroid @ z)
    return patches_h


def _riser_patches(vert: list, pm: _PointMap, w0: np.ndarray, up: np.ndarray, refine_direction: bool,
                   edge_drop_fraction: float) -> tuple[np.ndarray, np.ndarray, list[_Patch]]:
    """(walking direction w, lateral direction up x w, riser patches): vertical planes facing along
    the walking direction (normal within 30 deg of -+w0), oriented towards the approaching robot;
    with ``refine_direction`` the walking direction is their point-weighted mean normal."""
    risers_raw = [(f, m) for f, m in vert if abs(f.n @ w0) >= np.cos(np.radians(30.0))]
    if refine_direction and risers_raw:
        wsum = np.zeros(3)
        for f, _ in risers_raw:
            nf = -f.n if f.n @ w0 > 0 else f.n  # faces the robot: -w
            wsum -= f.n_points * nf
        w0 = wsum - (wsum @ up) * up
        w0 /= np.linalg.norm(w0)
    w = w0 - (w0 @ up) * up
    w /= np.linalg.norm(w)
    lat = np.cross(up, w)
    patches_r: list[_Patch] = []
    for f, mask in risers_raw:
        Pin = pm.P[mask]
        nn, dd, c, sel = _refine_central(Pin, pm.sig[mask], up, lat, edge_drop_fraction)
        if nn @ w > 0:  # towards the approaching robot
            nn, dd = -nn, -dd
        patches_r.append(_Patch(nn, dd, c, Pin[sel], Pin, int(sel.sum())))
    return w, lat, patches_r


def _height(floor: _Patch, x) -> np.ndarray:
    """Height (m) of world point(s) ``x`` above the floor plane."""
    return np.asarray(x) @ floor.n + floor.d


def _match_risers(steps_h: list[_Patch], floor: _Patch, patches_r: list[_Patch], pm: _PointMap,
                  s_all: np.ndarray, w: np.ndarray, lat: np.ndarray) -> list[_TreadInfo]:
    """Riser k of each tread k: between the level below tread k and tread k, the nearest one in
    front of the tread's visible points (its front may be hidden: the landing is seen at grazing
    angles). ``s_all``: the map points along ``w`` (m, world origin)."""
    levels = [floor] + steps_h
    band = np.maximum(2.5 * pm.sig, 0.003)
    tread_info = []
    used_risers: set[int] = set()
    s_prev = -np.inf
    for k, tp in enumerate(steps_h):
        h_low, h_high = _height(floor, levels[k].centroid), _height(floor, tp.centroid)
        # every map point on the patch's plane (within 2.5 sigma_i, at least 3 mm)
        sup = (np.abs(pm.P @ tp.n + tp.d) <= band) & (s_all > s_prev + 0.02)
        s_min = float(np.quantile(s_all[sup], 0.005)) if sup.any() else float(tp.centroid @ w)
        best, best_s = None, -np.inf
        for i, rp in enumerate(patches_r):
            s_r = float(rp.centroid @ w)
            if i in used_risers or not (h_low < _height(floor, rp.centroid) < h_high):
                continue
            if s_prev + 0.02 < s_r <= s_min + 0.02 and s_r > best_s:
                best, best_s = i, s_r
        if best is not None:
            used_risers.add(best)
        tread_info.append(_TreadInfo(tp, best, s_min, sup))
        s_prev = best_s if best is not None else s_min
    return tread_info


def _front_edges(tread_info: list[_TreadInfo], patches_r: list[_Patch], t_all: np.ndarray, w: np.ndarray,
                 lat: np.ndarray, up: np.ndarray) -> list[_FrontEdge]:
    """Front edges (nosings): tread/riser intersections, else from the tread's points (its
    ``s_min`` along ``w`` at the median lateral position ``t_all`` of its support, onto its plane)."""
    fronts = []
    for ti in tread_info:
        tp, ri, s_min, sup = ti.patch, ti.riser, ti.s_min, ti.support
        if ri is not None:
            p_e, e = _edge_line(tp, patches_r[ri])
            if e @ lat < 0:
                e = -e
            fronts.append(_FrontEdge(p_e, e, True))
        else:
            t_mid = float(np.median(t_all[sup])) if sup.any() else float(tp.centroid @ lat)
            p_e = s_min * w + t_mid * lat
            p_e = p_e - (tp.n @ p_e + tp.d) / (tp.n @ up) * up  # onto the tread plane
            fronts.append(_FrontEdge(p_e, lat.copy(), False))
    return fronts


def _treads(tread_info: list[_TreadInfo], fronts: list[_FrontEdge], floor: _Patch, T_world_stairs: np.ndarray,
            s_all: np.ndarray, t_all: np.ndarray) -> list[Tread]:
    """The treads from their patches and front edges; ``s_all``, ``t_all``: the map points along the
    stairs x and y axes (m, stairs origin)."""
    w, lat, origin = T_world_stairs[:3, 0], T_world_stairs[:3, 1], T_world_stairs[:3, 3]
    treads = []
    for k, (ti, fe) in enumerate(zip(tread_info, fronts)):
        tp, sup = ti.patch, ti.support
        p_e, e, from_riser = fe.point, fe.direction, fe.from_riser
        s_front = float((p_e - origin) @ w)
        if k + 1 < len(fronts) and fronts[k + 1].from_riser and from_riser:
            perp = np.cross(tp.n, e)
            perp /= np.linalg.norm(perp)
            depth = abs(float((fronts[k + 1].point - p_e) @ perp))
            complete = True
            s_back = s_front + depth
        else:
            beyond = sup & (s_all > s_front)
            s_back = float(np.quantile(s_all[beyond], 0.995)) if beyond.any() else s_front
            depth = s_back - s_front
            complete = False
        on = sup & (s_all > s_front + 0.01) & (s_all < s_back - 0.01)
        if on.sum() >= 10:
            t_lo, t_hi = (float(v) for v in np.quantile(t_all[on], [0.002, 0.998]))
        else:
            t_lo = t_hi = float((tp.centroid - origin) @ lat)
        # the edge point at the tread's lateral middle
        t_e = float((p_e - origin) @ lat)
        p_e = p_e + ((t_lo + t_hi) / 2 - t_e) / (e @ lat) * e
        treads.append(
            Tread(
                index=k,
                height_m=float(_height(floor, tp.centroid)),
                depth_m=float(depth),
                depth_complete=complete,
                width_m=t_hi - t_lo,
                p_world_edge=p_e,
                edge_direction_world=e,
                edge_from_riser=from_riser,
                plane_world=canonical_plane(tp.n, tp.d),
                n_inliers=tp.n_inliers,
                s_front_m=s_front,
                s_back_m=float(s_back),
                t_min_m=t_lo,
                t_max_m=t_hi,
            )
        )
    return treads


def _risers(patches_r: list[_Patch], floor: _Patch, T_world_stairs: np.ndarray) -> list[Riser]:
    """The risers, lowest first."""
    w, origin = T_world_stairs[:3, 0], T_world_stairs[:3, 3]
    risers = []
    for rp in sorted(patches_r, key=lambda r: _height(floor, r.centroid)):
        hs = _height(floor, rp.all_points)
        # position along s at the stairs' lateral middle: the plane's point with t = 0, h = its centroid height
        c = rp.centroid
        s_c = float((c - origin) @ w)
        risers.append(Riser(canonical_plane(rp.n, rp.d), s_c, float(np.quantile(hs, 0.01)), float(np.quantile(hs, 0.99)), rp.n_inliers))
    return risers


# ----------------------------------------------------------------------------- public API
def model_stairs(
    clouds_sensor: Sequence[np.ndarray],
    T_world_sensor: Sequence[np.ndarray],
    *,
    walking_direction_world: np.ndarray | None = None,
    icp: bool = True,
    max_depth_m: float = 2.5,
    noise_coeff_per_m: float = KINECT_NOISE_COEFF_PER_M,
    icp_voxel_m: float = 0.01,
    icp_normal_radius_m: float = 0.05,
    class_normal_radius_m: float = 0.025,
    icp_max_normal_tilt_rad: float = 0.02,
    class_max_normal_tilt_rad: float = 0.1,
    icp_gates_m: Sequence[float] = (0.10, 0.05, 0.025, 0.015),
    icp_prior_sigma_m: float = 0.02,
    icp_prior_sigma_rad: float = float(np.radians(1.0)),
    icp_min_fitness: float = 0.15,
    icp_max_iterations: int = 10,
    icp_degeneracy_ratio: float = 0.001,
    icp_max_source_points: int = 3000,
    icp_passes: int = 2,
    icp_neighbours: int = 8,
    icp_max_normal_angle_deg: float = 30.0,
    icp_reliable_source: bool = True,
    max_points_per_cloud: int = 40_000,
    ransac_distance_m: float = 0.02,
    max_planes: int = 12,
    min_plane_points: int = 150,
    max_tilt_deg: float = 10.0,
    edge_drop_fraction: float = 0.05,
    min_step_height_m: float = 0.03,
    max_points: int = 400_000,
    rng: np.random.Generator | int | None = 0,
) -> StairsModel:
    """Model the stairs seen in a sequence of depth clouds (module docstring for the method).

    Args:
        clouds_sensor: per cloud, (N_k, 3) points in the sensor (optical) frame, m; rows with NaN
            are ignored.
        T_world_sensor: per cloud, the (estimated) sensor pose, 4x4, m. Errors of a few cm and
            ~1 deg are corrected by the ICP stitching.
        walking_direction_world: (3,) direction up the stairs; default: the risers' normals, else
            the mean horizontal viewing direction of the clouds.
        icp: stitch the clouds (False: trust the poses).
        max_depth_m: points farther along the optical axis are not used (m).
        noise_coeff_per_m: depth noise model sigma_z = coeff z^2 (m), for weights.
        icp_voxel_m, icp_normal_radius_m, class_normal_radius_m, icp_max_normal_tilt_rad,
            class_max_normal_tilt_rad: downsampling and normals (module docstring, step 1).
        icp_gates_m, icp_prior_sigma_m, icp_prior_sigma_rad, icp_min_fitness,
            icp_max_iterations, icp_degeneracy_ratio, icp_max_source_points, icp_passes,
            icp_neighbours: the stitching (module docstring, step 2); in pass 2 each cloud is
            registered to the ``icp_neighbours`` clouds with the nearest sensor positions. Cost
            grows linearly with the number of clouds (~0.2 s per cloud here): pass keyframes.
        icp_max_normal_angle_deg: a correspondence is used only if the source point's normal and
            the map point's agree within this angle (90: no test).
        icp_reliable_source: register only the source points with a reliable normal (step 1).
        max_points_per_cloud: larger clouds are randomly thinned to this many points first
            (a full 640 x 480 Kinect frame has ~300k).
        ransac_distance_m, max_planes, min_plane_points: plane extraction
            (:func:`graphcal.clouds.planes.extract_planes`).
        max_tilt_deg: a plane is horizontal (vertical) when its normal is within this angle of
            (perpendicular to) world z.
        edge_drop_fraction: fraction of each plane's points dropped near each edge (Zhao: 5 %).
        min_step_height_m: horizontal planes less than this above the floor are part of the floor.
        max_points: the stitched map is randomly thinned to this many points for the planes.
        rng: seed or generator (subsamples, RANSAC).

    Returns:
        :class:`StairsModel`. Heights are above the *lowest* horizontal plane, which must be the
        floor (keep a cloud that sees the floor in front of the stairs in the sequence).

    Raises:
        StairsError: bad input (shapes, non-rigid poses, mismatched lengths), no horizontal plane.
    """
    clouds, poses = _check_inputs(clouds_sensor, T_world_sensor)
    if not 0.0 <= edge_drop_fraction < 0.5:
        raise StairsError(f"model_stairs: edge_drop_fraction must be in [0, 0.5), got {edge_drop_fraction}")
    if not max_depth_m > 0:
        raise StairsError(f"model_stairs: max_depth_m must be > 0, got {max_depth_m}")
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    clouds = _prepare_clouds(clouds, max_depth_m, max_points_per_cloud, min_plane_points, gen)
    normals = _cloud_normals(clouds, icp_voxel_m, icp_normal_radius_m, class_normal_radius_m,
                             icp_max_normal_tilt_rad, class_max_normal_tilt_rad)

    # 2. stitching
    if icp and len(clouds) > 1:
        corrected, fitness, accepted = _stitch(
            clouds, poses, normals.down, normals.normals, normals.reliable, noise_coeff_per_m,
            voxel_m=icp_voxel_m, gates_m=tuple(icp_gates_m),
            prior_sigma_m=icp_prior_sigma_m, prior_sigma_rad=icp_prior_sigma_rad,
            min_fitness=icp_min_fitness, max_iterations=icp_max_iterations,
            degeneracy_ratio=icp_degeneracy_ratio, max_source_points=icp_max_source_points,
            passes=icp_passes, neighbours=icp_neighbours, rng=gen,
            normal_cos_min=float(np.cos(np.radians(icp_max_normal_angle_deg))) if icp_max_normal_angle_deg < 90 else 0.0,
            reliable_source=icp_reliable_source,
        )
        used = [k for k in range(len(clouds)) if accepted[k]]
    else:
        corrected, fitness, accepted = [T.copy() for T in poses], [1.0] * len(poses), [False] * len(poses)
        accepted[0] = True
        used = list(range(len(clouds)))

    # 1. + map: world points, their noise std and normals
    pm = _point_map(clouds, used, corrected, normals, noise_coeff_per_m, max_points, gen)

    # 3. planes: RANSAC + Chai's loop on the points with a reliable horizontal (vertical) normal;
    # a slanted plane through the nosings cannot form from them
    z = np.array([0.0, 0.0, 1.0])
    nz = np.abs(pm.N @ z)
    pool_h = np.flatnonzero(pm.reliable & (nz >= np.cos(np.radians(2 * max_tilt_deg))))
    pool_v = np.flatnonzero(pm.reliable & (nz <= np.sin(np.radians(2 * max_tilt_deg))))
    plane_kw = dict(max_planes=max_planes, ransac_distance_m=ransac_distance_m, min_plane_points=min_plane_points,
                    gen=gen)
    fits_h, fits_v = _planes_of(pm.P, pool_h, **plane_kw), _planes_of(pm.P, pool_v, **plane_kw)
    cos_t = np.cos(np.radians(max_tilt_deg))
    horiz = [(f, m) for f, m in fits_h if abs(f.n @ z) >= cos_t]
    vert = [(f, m) for f, m in fits_v if abs(f.n @ z) <= np.sin(np.radians(max_tilt_deg))]
    if not horiz:
        raise StairsError("model_stairs: no horizontal plane found in the clouds")

    w0 = _initial_walking_direction(walking_direction_world, corrected, z)
    patches_h = _horizontal_patches(horiz, pm, w0, z, min_step_height_m, edge_drop_fraction)
    floor = patches_h[0]
    up = floor.n
    steps_h = [p for p in patches_h[1:] if floor.n @ p.centroid + floor.d >= min_step_height_m]
    w, lat, patches_r = _riser_patches(vert, pm, w0, up, walking_direction_world is None, edge_drop_fraction)

    steps_h.sort(key=lambda p: _height(floor, p.centroid))
    s_all, t_all = pm.P @ w, pm.P @ lat  # along-stairs and lateral coordinates (world origin for now)
    tread_info = _match_risers(steps_h, floor, patches_r, pm, s_all, w, lat)
    fronts = _front_edges(tread_info, patches_r, t_all, w, lat, up)
    # the stairs frame: origin on the floor below the lowest nosing
    p0 = fronts[0].point if fronts else floor.centroid
    origin = p0 - _height(floor, p0) * up
    T_world_stairs = pose_matrix(np.column_stack([w, lat, up]), origin)
    s_all = s_all - origin @ w
    t_all = t_all - origin @ lat
    return StairsModel(
        treads=tuple(_treads(tread_info, fronts, floor, T_world_stairs, s_all, t_all)),
        risers=tuple(_risers(patches_r, floor, T_world_stairs)),
        floor_plane_world=canonical_plane(floor.n, floor.d),
        floor_n_inliers=floor.n_inliers,
        T_world_stairs=T_world_stairs,
        T_world_sensor_corrected=tuple(corrected),
        icp_fitness=tuple(float(f) for f in fitness),
        icp_accepted=tuple(bool(a) for a in accepted),
        n_points=int(len(pm.P)),
    )


def stairs_model_from_steps(
    steps: Sequence,
    *,
    floor_z_m: float = 0.0,
    y_center_m: float = 0.0,
) -> StairsModel:
    """The exact model of an untilted staircase rising along world +x: :class:`StairStep` records
    (or any with their fields, e.g. the simulator's terrain steps) with ``x_start_m`` (nosing x),
    ``depth_m``, ``height_m`` (top above the floor), ``width_m`` (centred on ``y_center_m``), lowest
    first; the floor is ``z = floor_z_m``. Every depth is complete (the last one too)."""
    steps = sorted(steps, key=lambda s: s.height_m)
    if not steps:
        raise StairsError("stairs_model_from_steps: no steps")
    x = np.array([1.0, 0.0, 0.0])
    y = np.array([0.0, 1.0, 0.0])
    up = np.array([0.0, 0.0, 1.0])
    origin = np.array([steps[0].x_start_m, y_center_m, floor_z_m])
    T = pose_matrix(np.eye(3), origin)
    treads, risers = [], []
    prev_h = 0.0
    for k, s in enumerate(steps):
        p_e = np.array([s.x_start_m, y_center_m, floor_z_m + s.height_m])
        sf = s.x_start_m - origin[0]
        treads.append(
            Tread(k, float(s.height_m), float(s.depth_m), True, float(s.width_m), p_e, y.copy(), True,
                  canonical_plane(up, -(floor_z_m + s.height_m)), 0, sf, sf + s.depth_m,
                  -s.width_m / 2, s.width_m / 2)
        )
        risers.append(Riser(canonical_plane(-x, s.x_start_m), sf, prev_h, float(s.height_m), 0))
        prev_h = s.height_m
    return StairsModel(tuple(treads), tuple(risers), canonical_plane(up, -floor_z_m), 0, T)


def tread_errors(model: StairsModel, steps: Sequence, *, floor_z_m: float = 0.0) -> tuple[TreadError, ...]:
    """Compare a model with the true steps (records as in :func:`stairs_model_from_steps`, an
    untilted staircase rising along world +x, floor at ``floor_z_m``). Each model tread is matched
    to the true step of the nearest height (within 5 cm)."""
    truth = sorted(steps, key=lambda s: s.height_m)
    out = []
    for tr in model.treads:
        j = int(np.argmin([abs(s.height_m - tr.height_m) for s in truth])) if truth else -1
        if j < 0 or abs(truth[j].height_m - tr.height_m) > 0.05:
            out.append(TreadError(tr.index, -1, np.nan, np.nan, np.nan, np.nan, np.nan))
            continue
        s = truth[j]
        out.append(
            TreadError(
                index=tr.index,
                true_index=j,
                height_error_m=float(tr.height_m - s.height_m),
                depth_error_m=float(tr.depth_m - s.depth_m) if tr.depth_complete else float("nan"),
                width_error_m=float(tr.width_m - s.width_m),
                edge_along_m=float(tr.p_world_edge[0] - s.x_start_m),
                edge_height_m=float(tr.p_world_edge[2] - (floor_z_m + s.height_m)),
            )
        )
    return tuple(out)


def _f(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


def stairs_to_json(model: StairsModel, errors: Sequence[TreadError] | None = None) -> dict:
    """A JSON-ready dict of the model (metres, keys ending ``_m``); with ``errors`` (from
    :func:`tread_errors`) each tread also carries its errors and the dict the maxima."""
    treads = []
    by_index = {e.index: e for e in (errors or ())}
    for t in model.treads:
        d = {
            "index": t.index,
            "height_m": t.height_m,
            "depth_m": t.depth_m,
            "depth_complete": t.depth_complete,
            "width_m": t.width_m,
            "p_world_edge_m": [float(v) for v in t.p_world_edge],
            "edge_direction_world": [float(v) for v in t.edge_direction_world],
            "edge_from_riser": t.edge_from_riser,
            "plane_world": {"n": [float(v) for v in t.plane_world[0]], "d_m": float(t.plane_world[1])},
            "n_inliers": t.n_inliers,
        }
        if t.index in by_index:
            e = by_index[t.index]
            d["errors"] = {
                "true_index": e.true_index,
                "height_error_m": _f(e.height_error_m),
                "depth_error_m": _f(e.depth_error_m),
                "width_error_m": _f(e.width_error_m),
                "edge_along_m": _f(e.edge_along_m),
                "edge_height_m": _f(e.edge_height_m),
            }
        treads.append(d)
    out = {
        "treads": treads,
        "risers": [
            {"s_m": r.s_m, "h_low_m": r.h_low_m, "h_high_m": r.h_high_m, "n_inliers": r.n_inliers,
             "plane_world": {"n": [float(v) for v in r.plane_world[0]], "d_m": float(r.plane_world[1])}}
            for r in model.risers
        ],
        "floor_plane_world": {"n": [float(v) for v in model.floor_plane_world[0]], "d_m": float(model.floor_plane_world[1])},
        "T_world_stairs": [[float(v) for v in row] for row in model.T_world_stairs],
        "icp_fitness": list(model.icp_fitness),
        "icp_accepted": list(model.icp_accepted),
        "n_points": model.n_points,
    }
    if errors:
        def worst(attr):
            vals = [abs(getattr(e, attr)) for e in errors if np.isfinite(getattr(e, attr))]
            return max(vals) if vals else None

        out["max_abs_height_error_m"] = worst("height_error_m")
        out["max_abs_depth_error_m"] = worst("depth_error_m")
    return out
