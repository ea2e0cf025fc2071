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
(:func:`graphcal.geometry.canonical_plane`). SI units throughout; the tuning is
:class:`StairsModelConfig` (its field names carry their units).

Method (:func:`model_stairs`)
-----------------------------
1. **To world** (Zhao Eq. 10): ``p_world = T_world_sensor @ p_sensor``; points beyond
   ``max_depth_m`` along the optical axis are dropped (Kinect noise grows with z^2: 9 mm at 2.5 m).
   Each cloud is voxel-downsampled and gets PCA normals at two scales
   (:func:`graphcal.clouds.stitch.cloud_normals`: the ICP's, and ``class_normal_radius_m`` to tell
   horizontal from vertical surfaces up to their edges); normals above ``class_max_normal_tilt_rad``
   are unreliable (sparse far points, points on an edge).
2. **ICP stitching** (:func:`graphcal.clouds.stitch.stitch_clouds`, tuned by ``config.stitch``):
   each cloud registered to the map of the clouds before it, then to its nearest others, by
   regularised, degeneracy-aware point-to-plane ICP with normal-compatible correspondences; the
   map then moved as a whole back onto the estimated poses' frame. (Without the normal test, the
   points of a tread seen at a grazing angle -- the landing, ~15 cm below the camera -- matched the
   top of the riser in front of it and pulled the cloud back and down: clouds started at their true
   poses ended up to 1.2 deg of pitch and 1.8 cm off, and the landing's height was +3 to +7 mm off
   in the ``tripod-stairs`` walk.) A cloud whose final inlier fraction is below
   ``stitch.min_fitness`` keeps its estimated pose and stays out of the map and the model.
3. **Planes.** :func:`graphcal.clouds.planes.extract_planes` (Open3D RANSAC on a subsample, then Chai's
   2-sigma PCA loop) separately on the points with a reliable horizontal normal and on those with a
   reliable vertical normal (within ``2 max_tilt_rad``): a slanted plane through the nosings cannot
   form from either set. Horizontal planes (normal within ``max_tilt_rad`` of world z) are the
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
is regularised and degeneracy-aware (:mod:`graphcal.clouds.stitch`).

Measured (docs/stairs_gait.md): ten simulated approaches, pose errors ~1.7 cm / ~0.5 deg: tread
heights within 0.5 mm, depths within 0.2 mm of the truth; ~2 s for ten clouds on 2 busy cores.
Through ``graphcal track`` (its keyframes and EKF poses, docs/state_estimation.md): within 1.3 mm
and 0.3 mm on the ``tripod-stairs`` walk. Its JSON form: :mod:`graphcal.report.stairs_json`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from graphcal.clouds.stitch import CloudNormals, StitchConfig, StitchResult, cloud_normals, stitch_clouds
from graphcal.errors import GraphcalError
from graphcal.geometry import canonical_plane, pose_matrix, transform_points
from graphcal.models.sensors import KINECT_NOISE_COEFF_PER_M

__all__ = [
    "StairsError",
    "StairsModelConfig",
    "Tread",
    "Riser",
    "StairsModel",
    "TreadError",
    "model_stairs",
    "stairs_model_from_steps",
    "tread_errors",
    "KINECT_NOISE_COEFF_PER_M",
]


class StairsError(GraphcalError):
    """Bad input to the stairs model, or no stairs in the clouds."""


@dataclass(frozen=True)
class StairsModelConfig:
    """The tuning of :func:`model_stairs` (module docstring for each step; SI units).

    Attributes:
        icp: stitch the clouds (False: trust the poses).
        stitch: the stitching and its normals (:class:`graphcal.clouds.stitch.StitchConfig`). In its
            pass 2 each cloud is registered to the ``stitch.neighbours`` clouds with the nearest
            sensor positions; cost grows linearly with the number of clouds (~0.2 s per cloud
            here): pass keyframes.
        max_depth_m: points farther along the optical axis are not used (m).
        noise_coeff_per_m: depth noise model sigma_z = coeff z^2 (m), for weights.
        class_normal_radius_m, class_max_normal_tilt_rad: the normals that tell horizontal from
            vertical surfaces (m, rad; step 1).
        max_points_per_cloud: larger clouds are randomly thinned to this many points first
            (a full 640 x 480 Kinect frame has ~300k).
        ransac_distance_m, max_planes, min_plane_points: plane extraction
            (:func:`graphcal.clouds.planes.extract_planes`).
        max_tilt_rad: a plane is horizontal (vertical) when its normal is within this angle of
            (perpendicular to) world z (rad).
        edge_drop_fraction: fraction of each plane's points dropped near each edge (Zhao: 5 %).
        min_step_height_m: horizontal planes less than this above the floor are part of the floor.
        max_points: the stitched map is randomly thinned to this many points for the planes.
    """

    icp: bool = True
    stitch: StitchConfig = StitchConfig()
    max_depth_m: float = 2.5
    noise_coeff_per_m: float = KINECT_NOISE_COEFF_PER_M
    class_normal_radius_m: float = 0.025
    class_max_normal_tilt_rad: float = 0.1
    max_points_per_cloud: int = 40_000
    ransac_distance_m: float = 0.02
    max_planes: int = 12
    min_plane_points: int = 150
    max_tilt_rad: float = float(np.radians(10.0))
    edge_drop_fraction: float = 0.05
    min_step_height_m: float = 0.03
    max_points: int = 400_000


# ----------------------------------------------------------------------------- results
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


def _point_map(clouds: list[np.ndarray], used: list[int], corrected: list[np.ndarray], normals: CloudNormals,
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


# ----------------------------------------------------------------------------- model_stairs's steps
def _stitched(normals: CloudNormals, poses: list[np.ndarray], config: StairsModelConfig,
              gen: np.random.Generator) -> tuple[StitchResult, list[int]]:
    """Step 2: the stitched sensor poses and the clouds the map is made of (every cloud without
    stitching: ``icp`` off or a single cloud)."""
    if config.icp and len(poses) > 1:
        st = stitch_clouds(normals, poses, config.noise_coeff_per_m, config.stitch, gen)
        return st, [k for k in range(len(poses)) if st.accepted[k]]
    accepted = [False] * len(poses)
    accepted[0] = True
    return StitchResult([T.copy() for T in poses], [1.0] * len(poses), accepted), list(range(len(poses)))


def _level_and_upright_planes(pm: _PointMap, config: StairsModelConfig, gen: np.random.Generator) -> tuple[list, list]:
    """Step 3: (horizontal, vertical) planes as (fit, mask over the map) pairs, from RANSAC + Chai's
    loop on the points with a reliable horizontal (vertical) normal: a slanted plane through the
    nosings cannot form from them. StairsError without a horizontal plane."""
    z = np.array([0.0, 0.0, 1.0])
    nz = np.abs(pm.N @ z)
    pool_h = np.flatnonzero(pm.reliable & (nz >= np.cos(2 * config.max_tilt_rad)))
    pool_v = np.flatnonzero(pm.reliable & (nz <= np.sin(2 * config.max_tilt_rad)))
    plane_kw = dict(max_planes=config.max_planes, ransac_distance_m=config.ransac_distance_m,
                    min_plane_points=config.min_plane_points, gen=gen)
    fits_h, fits_v = _planes_of(pm.P, pool_h, **plane_kw), _planes_of(pm.P, pool_v, **plane_kw)
    cos_t = np.cos(config.max_tilt_rad)
    horiz = [(f, m) for f, m in fits_h if abs(f.n @ z) >= cos_t]
    vert = [(f, m) for f, m in fits_v if abs(f.n @ z) <= np.sin(config.max_tilt_rad)]
    if not horiz:
        raise StairsError("model_stairs: no horizontal plane found in the clouds")
    return horiz, vert


def _stairs_geometry(horiz: list, vert: list, pm: _PointMap, corrected: list[np.ndarray], walking_direction_world,
                     config: StairsModelConfig) -> tuple[list[Tread], list[Riser], _Patch, np.ndarray]:
    """Steps 4 and 5: (treads, risers, floor patch, T_world_stairs) from the planes of the map."""
    z = np.array([0.0, 0.0, 1.0])
    w0 = _initial_walking_direction(walking_direction_world, corrected, z)
    patches_h = _horizontal_patches(horiz, pm, w0, z, config.min_step_height_m, config.edge_drop_fraction)
    floor = patches_h[0]
    up = floor.n
    steps_h = [p for p in patches_h[1:] if floor.n @ p.centroid + floor.d >= config.min_step_height_m]
    w, lat, patches_r = _riser_patches(vert, pm, w0, up, walking_direction_world is None, config.edge_drop_fraction)

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
    treads = _treads(tread_info, fronts, floor, T_world_stairs, s_all, t_all)
    return treads, _risers(patches_r, floor, T_world_stairs), floor, T_world_stairs


# ----------------------------------------------------------------------------- public API
def model_stairs(
    clouds_sensor: Sequence[np.ndarray],
    T_world_sensor: Sequence[np.ndarray],
    *,
    config: StairsModelConfig = StairsModelConfig(),
    walking_direction_world: np.ndarray | None = None,
    rng: np.random.Generator | int | None = 0,
) -> StairsModel:
    """Model the stairs seen in a sequence of depth clouds (module docstring for the method).

    Args:
        clouds_sensor: per cloud, (N_k, 3) points in the sensor (optical) frame, m; rows with NaN
            are ignored.
        T_world_sensor: per cloud, the (estimated) sensor pose, 4x4, m. Errors of a few cm and
            ~1 deg are corrected by the ICP stitching.
        config: the tuning (:class:`StairsModelConfig`; e.g. ``StairsModelConfig(icp=False)`` to
            trust the poses).
        walking_direction_world: (3,) direction up the stairs; default: the risers' normals, else
            the mean horizontal viewing direction of the clouds.
        rng: seed or generator (subsamples, RANSAC).

    Returns:
        :class:`StairsModel`. Heights are above the *lowest* horizontal plane, which must be the
        floor (keep a cloud that sees the floor in front of the stairs in the sequence).

    Raises:
        StairsError: bad input (shapes, non-rigid poses, mismatched lengths, a bad config), no
        horizontal plane.
    """
    cfg = config
    clouds, poses = _check_inputs(clouds_sensor, T_world_sensor)
    if not 0.0 <= cfg.edge_drop_fraction < 0.5:
        raise StairsError(f"model_stairs: edge_drop_fraction must be in [0, 0.5), got {cfg.edge_drop_fraction}")
    if not cfg.max_depth_m > 0:
        raise StairsError(f"model_stairs: max_depth_m must be > 0, got {cfg.max_depth_m}")
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    # 1. clouds cut and thinned, their normals; 2. stitching
    clouds = _prepare_clouds(clouds, cfg.max_depth_m, cfg.max_points_per_cloud, cfg.min_plane_points, gen)
    normals = cloud_normals(clouds, cfg.stitch, class_radius_m=cfg.class_normal_radius_m,
                            class_max_normal_tilt_rad=cfg.class_max_normal_tilt_rad)
    stitched, used = _stitched(normals, poses, cfg, gen)
    corrected = stitched.T_world_sensor
    # 1. + map: world points, their noise std and normals; 3. planes; 4.-5. treads and risers
    pm = _point_map(clouds, used, corrected, normals, cfg.noise_coeff_per_m, cfg.max_points, gen)
    horiz, vert = _level_and_upright_planes(pm, cfg, gen)
    treads, risers, floor, T_world_stairs = _stairs_geometry(horiz, vert, pm, corrected, walking_direction_world, cfg)
    return StairsModel(
        treads=tuple(treads),
        risers=tuple(risers),
        floor_plane_world=canonical_plane(floor.n, floor.d),
        floor_n_inliers=floor.n_inliers,
        T_world_stairs=T_world_stairs,
        T_world_sensor_corrected=tuple(corrected),
        icp_fitness=tuple(float(f) for f in stitched.fitness),
        icp_accepted=tuple(bool(a) for a in stitched.accepted),
        n_points=int(len(pm.P)),
    )


def stairs_model_from_steps(
    steps: Sequence,
    *,
    floor_z_m: float = 0.0,
    y_center_m: float = 0.0,
) -> StairsModel:
    """The exact model of an untilted staircase rising along world +x: step records (e.g. the
    simulator's terrain steps, or the ``stairs`` list of a ``truth.yaml`` ``ground`` section) with
    ``x_start_m`` (nosing x), ``depth_m``, ``height_m`` (top above the floor), ``width_m`` (centred
    on ``y_center_m``), lowest first; the floor is ``z = floor_z_m``. Every depth is complete (the
    last one too)."""
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
