"""Plane extraction from point clouds: RANSAC on a random subsample, then Chai's iterative 2-sigma
PCA refinement on every point near the RANSAC plane, with a covariance of ``(n, d)``.

Frames and units: the points are in the sensor frame (metres), so are the planes. A plane is
``(n, d)`` with unit ``n`` and ``n . x + d = 0`` (see :mod:`graphcal.geometry`), canonical
``d >= 0``: ``n`` points from the plane towards the sensor origin. Bad input raises
:class:`graphcal.errors.GraphcalError`; randomness comes from ``rng`` (seed or Generator).

The method (the loop, the plane check, the trimmed covariance ``H^-1 / tau(a)``, the
errors-in-variables correction) and its speed: docs/planes.md.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Callable

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.geometry import canonical_plane
from graphcal.models.sensors import KINECT_NOISE_COEFF_PER_M

__all__ = [
    "PlaneFit",
    "PlaneWorkspace",
    "extract_planes",
    "fit_ground_plane",
    "plane_tangent_basis",
    "kinect_sigma_z",
    "depth_camera_distance_sigma",
    "kinect_distance_sigma",
    "truncation_variance_ratio",
]

#: ``range_noise(points_sensor (M, 3) m, n_sensor (3,)) -> (M,)`` std (m) of each point's
#: distance to the plane along ``n_sensor``.
RangeNoise = Callable[[np.ndarray, np.ndarray], np.ndarray]

_WATCH_FRACTION = 0.8  # points with |distance| > this * threshold are re-tested every iteration
# A plane's inliers must concentrate inside the candidate band: rms <= this * band half-width
# (points spread uniformly over the band give 0.58; a plane with noise std band / 2 gives 0.36).
_MAX_RMS_OF_BAND = 0.42
_MAX_REJECTED = 3  # RANSAC planes rejected by that test before extract_planes gives up
# Weighted loop (range_noise given): the 2-sigma threshold never goes below this many model std.
# Points that follow the model converge at 1.45; a threshold below 0.5 means points far less noisy
# than the model (noise-free simulated depth images, a wrong model), whose whitened spread can fall
# to the rounding error of the moments: the loop would then trim rounding noise (decided by the
# machine's BLAS/LAPACK kernels), may drop every point, and tau(a) -> 0 would inflate the covariance
# without bound. At the floor nothing closer than 0.5 model std is dropped, and the covariance is the
# model's, untruncated (docs/planes.md).
_MIN_WHITENED_THRESHOLD = 0.5


@dataclass(frozen=True, eq=False)
class PlaneFit:
    """One extracted plane, in the frame of the input points (the sensor frame).

    Attributes:
        n: (3,) unit normal, pointing from the plane towards the frame origin.
        d: offset (m), canonical ``d >= 0``: ``n . x + d = 0`` on the plane; the distance of the
            origin to the plane.
        cov: (4, 4) covariance of the stacked ``(nx, ny, nz, d)`` (m for d); rank 3, null along
            ``(n, 0)``. See docs/planes.md, "Covariance".
        n_points: number of inliers (the points kept by the 2-sigma loop).
        rms: point-to-plane RMS of the inliers (m).
        inlier_mask: (N,) bool over the input points.
        iterations: iterations of the 2-sigma loop (PCA fits).
        converged: False when the loop stopped at ``max_iterations`` with points still to drop.
        trim_distance_m: Chai's final threshold ``2 sigma_d`` (m): every inlier has
            ``|n . x + d| <=`` it (weighted fit: the largest inlier distance; the threshold itself
            is per point, ``truncation_sigmas * sigma_i``).
        truncation_sigmas: ``a``, the final threshold in noise std units (1.45 for Gaussian
            noise at convergence); ``cov`` is inflated by ``1 / tau(a)`` (docs/planes.md).
            inf: weighted fit of points far less noisy than the model (the threshold at its
            floor), ``cov`` the model's untruncated one.
        weighted: True when ``range_noise`` was used (whitened loop, weighted PCA, model
            covariance).
    """

    n: np.ndarray
    d: float
    cov: np.ndarray
    n_points: int
    rms: float
    inlier_mask: np.ndarray
    iterations: int
    converged: bool
    trim_distance_m: float
    truncation_sigmas: float
    weighted: bool

    def cov_tangent(self, basis: np.ndarray | None = None) -> np.ndarray:
        """(3, 3) covariance of ``(alpha, beta, d)``: the normal's components along the two columns
        of ``basis`` (3, 2) (default :func:`plane_tangent_basis` of ``n``; rad for small angles)
        and ``d`` (m)."""
        T = plane_tangent_basis(self.n) if basis is None else np.asarray(basis, dtype=float)
        G = np.zeros((4, 3))
        G[:3, :2] = T
        G[3, 2] = 1.0
        return G.T @ self.cov @ G


# ----------------------------------------------------------------------------- noise models
def kinect_sigma_z(z_m):
    """Kinect depth noise (m, 1-sigma) along the optical axis at depth ``z_m`` (m): 1.425e-3 z^2."""
    return KINECT_NOISE_COEFF_PER_M * np.asarray(z_m, dtype=float) ** 2


def depth_camera_distance_sigma(sigma_z: Callable[[np.ndarray], np.ndarray]) -> RangeNoise:
    """A ``range_noise`` for a depth camera whose noise is along the ray, of std ``sigma_z(z)`` in
    depth ``z`` (optical frame: z along the optical axis).

    A point ``x = z u`` (``u = x / z``) moved by ``dz`` along its ray moves by ``u dz``; its distance
    to a plane of normal ``n`` changes by ``(n . u) dz``, so ``s = |n . x| / z * sigma_z(z)``.
    """

    def sigma(points_sensor: np.ndarray, n_sensor: np.ndarray) -> np.ndarray:
        z = points_sensor[:, 2]
        return np.abs(_dot_rows(points_sensor, n_sensor)) / z * sigma_z(z)

    return sigma


def kinect_distance_sigma(points_sensor: np.ndarray, n_sensor: np.ndarray) -> np.ndarray:
    """``range_noise`` of the Kinect: std (m) of each point's distance to a plane of normal
    ``n_sensor``, ``1.425e-3 * z * |n . x|`` (see :func:`depth_camera_distance_sigma`)."""
    return KINECT_NOISE_COEFF_PER_M * points_sensor[:, 2] * np.abs(_dot_rows(points_sensor, n_sensor))


def _dot_rows(points: np.ndarray, n) -> np.ndarray:
    """points (M, 3) . n (3,) column by column (no threaded BLAS)."""
    return points[:, 0] * n[0] + points[:, 1] * n[1] + points[:, 2] * n[2]


# ----------------------------------------------------------------------------- helpers
def plane_tangent_basis(n) -> np.ndarray:
    """(3, 2) orthonormal basis ``[t1, t2]`` of the plane orthogonal to unit ``n``, with
    ``t1 x t2 = n``; a fixed function of ``n`` (the helper axis is the world axis least aligned
    with ``n``)."""
    n = np.asarray(n, dtype=float)
    helper = np.eye(3)[int(np.argmin(np.abs(n)))]
    t1 = np.cross(helper, n)
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)
    return np.column_stack([t1, t2])


def truncation_variance_ratio(a):
    """``tau(a)``: variance of N(0, 1) conditioned on ``|e| < a``, elementwise (``a > 0``).

    ``tau = 1 - 2 a phi(a) / (2 Phi(a) - 1)``; its series ``a^2/3 - 2 a^4/45 + 2 a^6/945`` for
    ``a < 0.05`` (the closed form cancels there).
    """
    from scipy.special import erf

    a = np.asarray(a, dtype=float)
    small = a < 0.05
    ab = np.where(small, 1.0, a)
    phi = np.exp(-0.5 * ab * ab) / np.sqrt(2.0 * np.pi)
    tau = 1.0 - 2.0 * ab * phi / erf(ab / np.sqrt(2.0))
    a2 = a * a
    return np.where(small, a2 * (1.0 / 3.0 - a2 * (2.0 / 45.0 - a2 * 2.0 / 945.0)), tau)


def _truncation_from_ratio(c_over_rms: float) -> float:
    """``a`` with ``a / sqrt(tau(a)) = c_over_rms`` (truncation in noise std units)."""
    from scipy.optimize import brentq

    f = lambda a: a / np.sqrt(float(truncation_variance_ratio(a))) - c_over_rms  # noqa: E731
    lo, hi = 1e-3, 50.0
    if f(lo) >= 0.0:  # residuals look uniform in the window: no information left
        return lo
    if f(hi) <= 0.0:
        return hi
    return float(brentq(f, lo, hi, xtol=1e-10))


def _as_points(points_sensor, drop_nonfinite: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """(N, 3) float64 C-contiguous points, and the indices of the finite rows (None: all)."""
    try:
        P = np.asarray(points_sensor, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise GraphcalError(f"extract_planes: points must be an (N, 3) array of numbers ({exc})") from None
    if P.ndim != 2 or P.shape[1] != 3:
        raise GraphcalError(f"extract_planes: points must have shape (N, 3), got {P.shape}")
    P = np.ascontiguousarray(P)
    keep = None
    if not np.isfinite(P.sum()):
        finite = np.isfinite(P).all(axis=1)
        bad = np.flatnonzero(~finite)
        if len(bad):
            if not drop_nonfinite:
                raise GraphcalError(
                    f"extract_planes: {len(bad)} of {len(P)} points are not finite (NaN or inf), "
                    f"first at row {bad[0]}; remove them or pass drop_nonfinite=True"
                )
            keep = np.flatnonzero(finite)
    n_valid = len(P) if keep is None else len(keep)
    if n_valid < 3:
        raise GraphcalError(f"extract_planes: a plane needs at least 3 finite points, got {n_valid}")
    return P, keep


def _o3d():
    import open3d as o3d  # slow import: only when a plane is extracted

    return o3d


def import_fit_modules() -> None:
    """Import now what a first plane fit imports lazily (Open3D, scipy.special, scipy.optimize:
    ~1 s, then ~0.14 s a process). Called before forking worker processes, which otherwise pay
    it in every worker on every call."""
    import scipy.optimize  # noqa: F401
    import scipy.special  # noqa: F401

    _o3d()


#: Open3D's random engine is global: seeding and sampling are one step for a thread
_RANSAC_LOCK = threading.Lock()


def _ransac(P_sample: np.ndarray, distance_m: float, iterations: int, seed: int):
    """Open3D RANSAC on (S, 3) points -> canonical (n, d), inlier indices; None if no plane.

    Not exactly repeatable: Open3D 0.20 draws the samples of its parallel workers (TBB) from one
    engine in the order the workers ask (how much it varies: docs/planes.md)."""
    o3d = _o3d()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P_sample))
    try:
        with _RANSAC_LOCK:
            o3d.utility.random.seed(seed)
            model, inliers = pcd.segment_plane(float(distance_m), 3, int(iterations))
    except RuntimeError:
        return None
    model = np.asarray(model, dtype=float).ravel()
    norm = np.linalg.norm(model[:3])
    if not np.all(np.isfinite(model)) or norm < 1e-12 or len(inliers) < 3:
        return None
    n, d = canonical_plane(model[:3], model[3])
    return n, d, np.asarray(inliers, dtype=np.int64)


# Thin products (N x 3) are done elementwise, never by BLAS: on a loaded 2-core machine OpenBLAS's
# threaded gemv and ddot wait for a busy core. And as few numpy calls as possible per pass: each
# call over a large array releases the GIL and must take it back, which waits for the other fitting
# thread, so chunked loops of small calls stall two threads; ``np.einsum`` does a dot product in one
# single-threaded call (the costs: docs/planes.md, "Speed").


def _matvec_rows(A: np.ndarray, v: np.ndarray, out: np.ndarray | None = None,
                 tmp: np.ndarray | None = None) -> np.ndarray:
    """A (N, 3) @ v (3,) column by column (into ``out`` (N,) if given; ``tmp`` (N,) scratch)."""
    out = np.empty(len(A)) if out is None else out
    tmp = np.empty(len(A)) if tmp is None else tmp
    np.multiply(A[:, 0], v[0], out=out)
    np.multiply(A[:, 1], v[1], out=tmp)
    out += tmp
    np.multiply(A[:, 2], v[2], out=tmp)
    out += tmp
    return out


def _dist_soa(XT: np.ndarray, n: np.ndarray, d: float, out: np.ndarray, tmp: np.ndarray,
              s: np.ndarray | None = None) -> np.ndarray:
    """``n . x + d`` of the columns of XT (3, M) (rows contiguous), into ``out``; with ``s`` (M,),
    the columns are whitened points ``y = s x`` and the result is ``s (n . x + d) = n . y + d s``."""
    np.multiply(XT[0], n[0], out=out)
    np.multiply(XT[1], n[1], out=tmp)
    out += tmp
    np.multiply(XT[2], n[2], out=tmp)
    out += tmp
    if s is None:
        out += d
    else:
        np.multiply(s, d, out=tmp)
        out += tmp
    return out


def _sdot(a: np.ndarray, b: np.ndarray) -> float:
    """a . b of two 1-D arrays (one single-threaded call)."""
    return float(np.einsum("i,i->", a, b))


def _gram_soa(XT: np.ndarray) -> np.ndarray:
    """sum_i x_i x_i^T (3, 3) of the columns of XT (3, M) (rows contiguous): six dot products
    (``einsum("ik,jk->ij")`` in one call takes 1.7x as long)."""
    S = np.empty((3, 3))
    for i in range(3):
        for j in range(i, 3):
            S[i, j] = S[j, i] = _sdot(XT[i], XT[j])
    return S


class PlaneWorkspace:
    """Scratch arrays reused by the :func:`extract_planes` calls of one thread.

    Fitting a 300k-point frame needs a dozen frame-sized temporaries; fresh ones cost a page fault
    per 4 kB on every frame (docs/planes.md, "Speed"). Pass one workspace to the calls of one
    thread (it is not thread-safe); the arrays grow to the largest frame and are freed with the
    workspace. Nothing a caller receives lives in it.
    """

    def __init__(self) -> None:
        self._arrays: dict = {}

    def array(self, name: str, shape: tuple, dtype=np.float64) -> np.ndarray:
        """An uninitialised C-contiguous array of ``shape`` (the same memory on every call of ``name``)."""
        size = math.prod(shape)
        key = (name, np.dtype(dtype).str)
        buf = self._arrays.get(key)
        if buf is None or buf.size < size:
            buf = np.empty(max(size + size // 4, 1), dtype=dtype)  # headroom for the next, larger frame
            self._arrays[key] = buf
        return buf[:size].reshape(shape)


@dataclass(frozen=True)
class _Refined:
    """Result of the 2-sigma loop, in the shifted frame (x - q); weights 1 (unweighted) or 1/sigma^2."""

    n: np.ndarray  # (3,) normal (same directions as the sensor frame)
    d_shift: float  # offset in the shifted frame
    keep: np.ndarray  # (M,) bool over the candidates (may live in the workspace)
    count: int  # kept points
    W: float  # sum of the kept points' weights (= count when unweighted)
    mean_shift: np.ndarray  # (3,) weighted centroid of the kept points
    scatter: np.ndarray  # (3, 3) weighted sum of centred outer products of the kept points
    sum_sq: float  # weighted sum of squared distances (smallest eigenvalue of scatter)
    iterations: int
    converged: bool
    threshold: float  # final 2 sigma_d (m, or whitened units when weighted)


def _pca(W: float, s1: np.ndarray, S2: np.ndarray, n_ref: np.ndarray):
    """Plane of the (weighted) points with weight sum W, sum s1 and sum of outer products S2."""
    mean = s1 / W
    scatter = S2 - W * (mean[:, None] * mean)
    w, V = np.linalg.eigh(scatter)
    n = V[:, 0]
    if n @ n_ref < 0:
        n = -n
    return n, float(-(n @ mean)), mean, scatter, w


def _check_not_collinear(w: np.ndarray, what: str) -> None:
    """Raise if the eigenvalues (ascending) of a scatter matrix say the points are on a line."""
    if not np.all(np.isfinite(w)) or w[2] <= 0.0 or w[1] <= 1e-12 * w[2]:
        raise GraphcalError(
            f"extract_planes: the {what} lie on a line (or a point): no unique plane "
            f"(scatter eigenvalues {w[0]:.3g}, {w[1]:.3g}, {w[2]:.3g})"
        )


def _moments(YT: np.ndarray, s: np.ndarray | None) -> tuple[float, np.ndarray, np.ndarray]:
    """Weighted moments of points ``x_j`` with weights ``s_j^2`` from the whitened columns
    ``YT = s x`` (3, k) and ``s`` (k,) (None: unit weights, ``YT = x``):
    ``(sum s^2, sum s^2 x = sum s y, sum s^2 x x^T = sum y y^T)``."""
    k = YT.shape[1]
    if k <= 3072:  # small: single-threaded BLAS calls (gemv threads above m * n = 9216)
        S2 = YT @ YT.T
        if s is None:
            return float(k), YT.sum(axis=1), S2
        return float(s @ s), YT @ s, S2
    S2 = _gram_soa(YT)
    if s is None:
        return float(k), YT.sum(axis=1), S2
    return _sdot(s, s), np.einsum("ik,k->i", YT, s), S2


def _chai_refine(YT: np.ndarray, n0: np.ndarray, max_iterations: int, inv_sigma: np.ndarray | None,
                 ws: PlaneWorkspace | None = None) -> _Refined:
    """Chai's iterative 2-sigma PCA on the candidates (shifted frame, float64, rows contiguous).

    ``inv_sigma`` None: Chai's metric loop, ``YT`` (3, M) the shifted candidates ``x``.
    ``inv_sigma`` (M,), 1 / the model's noise std per point: the whitened loop (weights
    ``inv_sigma^2``), ``YT`` the whitened candidates ``inv_sigma * x`` (whitened distances are then
    ``n . y + d inv_sigma`` and the weighted moments plain sums of ``y``; no weighted copy is made).

    Exact shortcut ("watch set"): every kept point outside the watch set is known to satisfy
    ``|n_ref . y + d_ref s| <= inner_bound`` for a reference plane; with ``|y_j| <= A_j`` and
    ``s <= s_max`` its (whitened) distance to the current plane is at most
    ``inner_bound + sum_j |n_j - n_ref_j| A_j + |d - d_ref| s_max``. While that is below the current
    threshold only the watch set can lose points and only it is tested; otherwise a full pass
    rebuilds it. As the threshold settles the watch set is shrunk to the points near it.
    """
    ws = ws if ws is not None else PlaneWorkspace()
    s = inv_sigma
    M = YT.shape[1]
    count = M
    W, s1, S2 = _moments(YT, s)
    keep = ws.array("keep", (M,), bool)
    keep[:] = True
    A = np.maximum(YT.max(axis=1), -YT.min(axis=1))  # (3,) per-axis bound on |y_j|
    s_max = 1.0 if s is None else float(s.max())
    dist = ws.array("dist_c", (M,))
    tmp = ws.array("tmp_c", (M,))
    mask = ws.array("mask_c", (M,), bool)
    watch_idx = watch_pts = watch_s = watch_keep = dw = tw = None
    inner_bound = ref_d = 0.0
    ref_n = n_ref = n0
    converged = False
    it = 0
    ev = None
    thr = thr_prev = np.inf
    for it in range(1, max_iterations + 1):
        if count < 3:
            raise GraphcalError("extract_planes: fewer than 3 points left in the 2-sigma loop")
        n, d, mean, scatter, ev = _pca(W, s1, S2, n_ref)
        if it == 1:
            _check_not_collinear(ev, "points near the RANSAC plane")
        n_ref = n
        # Chai Eq. 16: sigma_d^2 = sum of squared (whitened) distances / (n - 1)
        thr_prev, thr = thr, 2.0 * float(np.sqrt(max(ev[0], 0.0) / (count - 1)))
        if s is not None:
            thr = max(thr, _MIN_WHITENED_THRESHOLD)
        safe = False
        if watch_idx is not None:
            dn = np.abs(n - ref_n)
            shift = float(dn[0] * A[0] + dn[1] * A[1] + dn[2] * A[2]) + abs(d - ref_d) * s_max
            safe = inner_bound + shift < thr
        if safe:
            _dist_soa(watch_pts, n, d, dw, tw, watch_s)
            np.abs(dw, out=dw)
            drop_local = dw > thr
            drop_local &= watch_keep
            drop_idx = watch_idx[drop_local]
            watch_keep &= ~drop_local
            # shrink the watch set to the points near the threshold, if the bound allows it
            r = min(thr / thr_prev, 1.0)
            gamma = min(max(0.99 - 3.0 * (1.0 - r), 0.5), 0.99)
            if gamma * thr >= inner_bound + shift:
                sel = dw > gamma * thr
                sel &= watch_keep
                sel_idx = np.flatnonzero(sel)
                if len(sel_idx) < 0.7 * len(watch_idx):
                    watch_idx = watch_idx[sel_idx]
                    watch_pts = np.take(watch_pts, sel_idx, axis=1)
                    watch_s = None if watch_s is None else watch_s[sel_idx]
                    watch_keep = np.ones(len(sel_idx), dtype=bool)
                    dw, tw = np.empty(len(sel_idx)), np.empty(len(sel_idx))
                    inner_bound, ref_n, ref_d = gamma * thr, n, d
        else:
            _dist_soa(YT, n, d, dist, tmp, s)
            np.abs(dist, out=dist)
            np.greater(dist, thr, out=mask)
            mask &= keep
            drop_idx = np.flatnonzero(mask)
            keep[drop_idx] = False
            np.greater(dist, _WATCH_FRACTION * thr, out=mask)
            mask &= keep
            watch_idx = np.flatnonzero(mask)
            watch_pts = np.take(YT, watch_idx, axis=1)
            watch_s = None if s is None else s[watch_idx]
            watch_keep = np.ones(len(watch_idx), dtype=bool)
            dw, tw = np.empty(len(watch_idx)), np.empty(len(watch_idx))
            inner_bound, ref_n, ref_d = _WATCH_FRACTION * thr, n, d
        if len(drop_idx) == 0:
            converged = True
            break
        keep[drop_idx] = False
        dW, ds1, dS2 = _moments(np.take(YT, drop_idx, axis=1), None if s is None else s[drop_idx])
        W -= dW
        s1 -= ds1
        S2 -= dS2
        count -= len(drop_idx)
    if not converged:
        # stopped by the cap after a drop: report the PCA plane of the points actually kept
        n, d, mean, scatter, ev = _pca(W, s1, S2, n_ref)
    _check_not_collinear(ev, "plane inliers")
    return _Refined(n, d, keep, count, W, mean, scatter, max(float(ev[0]), 0.0), it, converged, thr)


def _covariance(n: np.ndarray, mean: np.ndarray, scatter_w: np.ndarray, W: float) -> np.ndarray:
    """4x4 covariance of (n, d) for the information ``H = sum w_i J_i J_i^T`` (docs/planes.md).

    ``mean`` is the weighted centroid (sensor frame), ``scatter_w = sum w_i (x_i - m)(x_i - m)^T``
    and ``W = sum w_i``, ``w_i`` the per-point information (1 / variance). With
    ``J_i = (t1 . x_i, t2 . x_i, 1)`` and ``x_i = m + (x_i - m)``, H has the blocks
    ``T^T scatter_w T + W (T^T m)(T^T m)^T``, ``W T^T m`` and ``W``.
    """
    T = plane_tangent_basis(n)
    Tm = T.T @ mean
    H = np.empty((3, 3))
    H[:2, :2] = T.T @ scatter_w @ T + W * np.outer(Tm, Tm)
    H[:2, 2] = H[2, :2] = W * Tm
    H[2, 2] = W
    cov3 = np.linalg.inv(H)
    G = np.zeros((4, 3))
    G[:3, :2] = T
    G[3, 2] = 1.0
    cov = G @ cov3 @ G.T
    return 0.5 * (cov + cov.T)


def _project_on_plane_along_rays(CT: np.ndarray, q: np.ndarray, nx: np.ndarray, d: float,
                                 out: np.ndarray | None = None) -> np.ndarray:
    """Candidates (shifted, (3, M)) moved along their rays from the sensor origin onto the plane
    ``(n, d)``, given ``nx`` (M,) = ``n . x`` of each (unshifted) candidate (overwritten): (M, 3)
    sensor-frame points (F-ordered; the transpose of ``out`` (3, M) if given): where the noise model
    and the errors-in-variables scatter are evaluated (docs/planes.md)."""
    ok = np.abs(nx) > 1e-3 * max(d, 1e-9)  # grazing or through the origin: keep the point
    scale = nx
    np.divide(-d, nx, out=scale, where=ok)
    scale[~ok] = 1.0
    X = np.add(CT, q[:, None], out=out)
    X *= scale
    return X.T


def _fit_one(
    P: np.ndarray,
    pool: np.ndarray | None,
    available: np.ndarray | None,
    rng: np.random.Generator,
    *,
    ransac_distance_m: float,
    candidate_distance_m: float,
    ransac_iterations: int,
    subsample: int,
    min_inliers: int,
    max_iterations: int,
    range_noise: RangeNoise | None,
    first: bool,
    workspace: PlaneWorkspace | None = None,
):
    """One plane from the points P[pool] (pool None: all of P).

    Returns None (no plane) or (candidate indices, PlaneFit or None, status) with status
    "ok", "small" (fewer than min_inliers) or "spread" (inliers spread over the band: no plane).
    """
    n_pool = len(P) if pool is None else len(pool)
    if n_pool < 3:
        return None
    if n_pool > subsample:
        pick = rng.choice(n_pool, size=subsample, replace=False)
        P_sample = np.take(P, pick if pool is None else pool[pick], axis=0)
    else:
        P_sample = P if pool is None else np.take(P, pool, axis=0)
    if first and len(P_sample) <= 4096:
        # small input: check for a line before RANSAC (cheap here)
        _check_not_collinear(np.linalg.eigvalsh(np.cov(P_sample.T, bias=True)), "points")
    found = _ransac(P_sample, ransac_distance_m, ransac_iterations, int(rng.integers(0, 2**31 - 1)))
    if found is None:
        if first:
            _check_not_collinear(np.linalg.eigvalsh(np.cov(P_sample.T, bias=True)), "points")
            raise GraphcalError("extract_planes: RANSAC found no plane in the points")
        return None
    n0, d0, sample_inliers = found
    q = P_sample[sample_inliers].mean(axis=0)  # shift: coordinates become small and centred

    ws = workspace if workspace is not None else PlaneWorkspace()
    N_all = len(P)
    dist = ws.array("dist", (N_all,))
    nx = _matvec_rows(P, n0, out=ws.array("nx", (N_all,)), tmp=dist)  # n0 . x (signed; -d0 on the plane)
    np.add(nx, d0, out=dist)
    np.abs(dist, out=dist)
    cand_mask = np.less_equal(dist, candidate_distance_m, out=ws.array("cand", (N_all,), bool))
    if available is not None:
        cand_mask &= available
    cand = np.flatnonzero(cand_mask)
    M = len(cand)
    if M < max(min_inliers, 3):
        return None
    # gathered by the mask, not the indices: np.compress is ~3x faster than np.take here
    rows = np.compress(cand_mask, P, axis=0, out=ws.array("rows", (M, 3)))
    CT = np.subtract(rows.T, q[:, None], out=ws.array("CT", (3, M)))  # (3, M) shifted candidates

    inv_sigma = None
    if range_noise is not None:
        nx_c = np.compress(cand_mask, nx, out=ws.array("nx_c", (M,)))
        X_ray = _project_on_plane_along_rays(CT, q, nx_c, d0, out=ws.array("X_ray", (3, M)))  # (M, 3)
        sig = np.asarray(range_noise(X_ray, n0), dtype=float).reshape(-1)
        if sig.shape != (M,) or not np.isfinite(sig).all() or (sig <= 0).any():
            raise GraphcalError(
                f"extract_planes: range_noise must return a positive finite std (m) for every point, shape ({M},)"
            )
        inv_sigma = np.divide(1.0, sig, out=ws.array("inv_sigma", (M,)))
        CT *= inv_sigma  # whitened candidates (what the weighted loop works on)
    ref = _chai_refine(CT, n0, max_iterations, inv_sigma, ws)
    if ref.count < min_inliers:
        return cand, None, "small"

    n_fit, d_shift = ref.n, ref.d_shift
    if inv_sigma is None:
        rms = float(np.sqrt(ref.sum_sq / ref.count))
        trim_m = ref.threshold
    else:
        keep_f = ws.array("keep_f", (M,))
        np.copyto(keep_f, ref.keep)
        quiet = ref.threshold <= _MIN_WHITENED_THRESHOLD  # far less noise than the model: none to remove
        if d0 > 0.0 and not quiet:
            # errors in variables: the noise is along the rays, not along the normal; subtract
            # its expected weighted scatter N = sum x* x*^T / d^2 over the kept points
            # (docs/planes.md, "Errors in variables")
            XkT = X_ray.T  # (3, M) rows contiguous; not needed afterwards: zero the dropped points
            XkT *= keep_f
            N = _gram_soa(XkT) / (d0 * d0)
            _, V = np.linalg.eigh(ref.scatter - N)
            n_fit = V[:, 0] if V[:, 0] @ ref.n >= 0 else -V[:, 0]
            d_shift = float(-(n_fit @ ref.mean_shift))
        r = _dist_soa(CT, n_fit, 0.0, ws.array("r", (M,)), ws.array("tmp_c", (M,)))  # n . (inv_sigma x)
        r /= inv_sigma
        r += d_shift
        r *= keep_f  # dropped points: 0
        rms = float(np.sqrt(_sdot(r, r) / ref.count))
        np.abs(r, out=r)
        trim_m = float(r.max())
    if rms > _MAX_RMS_OF_BAND * candidate_distance_m:
        return cand, None, "spread"
    if inv_sigma is None:
        a = _truncation_from_ratio(ref.threshold / max(rms, np.finfo(float).tiny))
        tau = float(truncation_variance_ratio(a))
        var = max(rms * rms / tau, np.finfo(float).tiny)  # untruncated sigma^2 (equal noise)
        info_scale = tau / var  # H = sum J J^T / sigma^2, cov = H^-1 / tau
    else:
        # whitened threshold = truncation in model std units; at the floor the points are far less
        # noisy than the model, no truncation of the model's noise applies: cov = H^-1 (a = inf)
        a = math.inf if quiet else ref.threshold
        tau = 1.0 if quiet else float(truncation_variance_ratio(a))
        info_scale = tau  # H = sum J J^T / sigma_i^2 (ref.scatter, ref.W are weighted)
    n, d = canonical_plane(n_fit, d_shift - n_fit @ q)
    n.flags.writeable = False
    cov = _covariance(n, ref.mean_shift + q, ref.scatter * info_scale, ref.W * info_scale)
    cov.flags.writeable = False
    mask = np.zeros(len(P), dtype=bool)
    mask[cand] = ref.keep
    mask.flags.writeable = False
    fit = PlaneFit(
        n=n,
        d=float(d),
        cov=cov,
        n_points=int(ref.count),
        rms=rms,
        inlier_mask=mask,
        iterations=int(ref.iterations),
        converged=bool(ref.converged),
        trim_distance_m=float(trim_m),
        truncation_sigmas=float(a),
        weighted=range_noise is not None,
    )
    return cand, fit, "ok"


# ----------------------------------------------------------------------------- public API
def extract_planes(
    points_sensor,
    *,
    max_planes: int = 1,
    ransac_distance_m: float = 0.02,
    candidate_distance_m: float | None = None,
    subsample: int = 5000,
    ransac_iterations: int = 100,
    min_inliers: int | None = None,
    max_iterations: int = 100,
    range_noise: RangeNoise | None = None,
    rng: np.random.Generator | int | None = None,
    drop_nonfinite: bool = False,
    workspace: PlaneWorkspace | None = None,
) -> list[PlaneFit]:
    """Extract up to ``max_planes`` planes from a point cloud, largest first.

    Args:
        points_sensor: (N, 3) points in the sensor frame (m).
        max_planes: planes to look for; after each plane its candidate points (within
            ``candidate_distance_m`` of its RANSAC plane) are removed and the search repeats.
        ransac_distance_m: RANSAC inlier distance (m). Should exceed ~2x the noise std along the
            normal.
        candidate_distance_m: half-width (m) of the band around the RANSAC plane whose points
            (of the full cloud) enter the 2-sigma loop; default ``ransac_distance_m``.
        subsample: RANSAC runs on this many random points (all points if fewer). Only the
            starting plane depends on it; Open3D's RANSAC costs ~0.9 ms per 1000 points here
            (100 iterations), hence the default 5000.
        ransac_iterations: Open3D RANSAC iterations.
        min_inliers: planes with fewer inliers are discarded and the search stops;
            default ``max(50, 2 % of the finite points)``.
        max_iterations: cap on the 2-sigma loop's iterations.
        range_noise: ``sigma(points_sensor (M, 3), n_sensor (3,)) -> (M,)`` std (m) of each point's
            distance along the normal (e.g. :func:`kinect_distance_sigma`): the 2-sigma loop runs
            on whitened distances with the weighted PCA, and the covariance uses the model.
            None: Chai's metric loop, covariance from the inliers' rms (equal noise assumed).
        rng: seed or generator for the subsample and the RANSAC.
        drop_nonfinite: ignore rows with NaN/inf instead of raising.
        workspace: scratch arrays to reuse across the calls of one thread (:class:`PlaneWorkspace`;
            default: a new one per call). The results never share memory with it.

    Returns:
        A list of :class:`PlaneFit` (possibly empty), in extraction order.

    Raises:
        GraphcalError: fewer than 3 finite points, non-finite points (unless ``drop_nonfinite``),
            points on a line, bad arguments.
    """
    if max_planes < 1:
        raise GraphcalError(f"extract_planes: max_planes must be >= 1, got {max_planes}")
    if not ransac_distance_m > 0:
        raise GraphcalError(f"extract_planes: ransac_distance_m must be > 0, got {ransac_distance_m}")
    if subsample < 3:
        raise GraphcalError(f"extract_planes: subsample must be >= 3, got {subsample}")
    band = ransac_distance_m if candidate_distance_m is None else float(candidate_distance_m)
    if not band > 0:
        raise GraphcalError(f"extract_planes: candidate_distance_m must be > 0, got {candidate_distance_m}")
    P, finite_idx = _as_points(points_sensor, drop_nonfinite)
    n_valid = len(P) if finite_idx is None else len(finite_idx)
    if min_inliers is None:
        min_inliers = max(50, int(np.ceil(0.02 * n_valid)))
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    if workspace is None:
        workspace = PlaneWorkspace()

    available: np.ndarray | None = None
    pool = finite_idx
    if finite_idx is not None:
        available = np.zeros(len(P), dtype=bool)
        available[finite_idx] = True
        P = P.copy()
        P[~available] = 0.0  # never a candidate: masked out by `available`
    planes: list[PlaneFit] = []
    sampling: np.ndarray | None = None  # points RANSAC may draw (available minus rejected bands)
    rejected = 0
    first = True
    ransac_d = ransac_distance_m
    while len(planes) < max_planes:
        out = _fit_one(
            P,
            pool,
            available,
            gen,
            ransac_distance_m=ransac_d,
            candidate_distance_m=band,
            ransac_iterations=ransac_iterations,
            subsample=subsample,
            min_inliers=min_inliers,
            max_iterations=max_iterations,
            range_noise=range_noise,
            first=first,
            workspace=workspace,
        )
        first = False
        if out is None:
            break
        cand, fit, status = out
        if status == "small":
            break
        if status == "ok":
            planes.append(fit)
            if len(planes) == max_planes:
                break
        else:  # "spread": RANSAC's plane is not a plane (e.g. through the nosings of stairs)
            rejected += 1
            if rejected > _MAX_REJECTED:
                break
            # a finer RANSAC threshold favours flat surfaces over such envelopes
            ransac_d = max(0.5 * ransac_d, 0.25 * ransac_distance_m)
        if available is None:
            available = np.ones(len(P), dtype=bool)
        if sampling is None:
            sampling = available.copy()
        sampling[cand] = False
        if status == "ok":
            available[cand] = False
        pool = np.flatnonzero(sampling)
    return planes


def fit_ground_plane(
    points_sensor,
    *,
    up_sensor=None,
    max_tilt_deg: float = 30.0,
    max_candidates: int = 3,
    **kwargs,
) -> PlaneFit:
    """The ground plane of a frame (see :func:`extract_planes` for the method and ``kwargs``).

    Without ``up_sensor``: the largest plane. With ``up_sensor`` (3,), the expected up direction in
    the sensor frame (e.g. from the IMU and the extrinsic prior): the plane with most inliers among
    the first ``max_candidates`` whose normal is within ``max_tilt_deg`` of it (the canonical normal
    points towards the sensor, i.e. up for a ground below it).

    Raises:
        GraphcalError: no plane (or none within the tilt), or the errors of :func:`extract_planes`.
    """
    if up_sensor is None:
        planes = extract_planes(points_sensor, max_planes=1, **kwargs)
        if not planes:
            raise GraphcalError("fit_ground_plane: no plane with enough inliers in the points")
        return planes[0]
    up = np.asarray(up_sensor, dtype=float)
    if up.shape != (3,) or not np.isfinite(up).all() or np.linalg.norm(up) == 0:
        raise GraphcalError(f"fit_ground_plane: up_sensor must be a nonzero 3-vector, got {up_sensor!r}")
    up = up / np.linalg.norm(up)
    planes = extract_planes(points_sensor, max_planes=max_candidates, **kwargs)
    cos_max = np.cos(np.radians(max_tilt_deg))
    ok = [p for p in planes if p.n @ up >= cos_max]
    if not ok:
        raise GraphcalError(
            f"fit_ground_plane: none of the {len(planes)} planes found is within {max_tilt_deg} deg of up_sensor"
        )
    return max(ok, key=lambda p: p.n_points)
