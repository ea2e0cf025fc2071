"""Yuan's virtual fixed base: a frame defined by four markers on the body (Yuan et al., Eqs. 4-8).

The markers ``body.1 ... body.4`` are numbered counter-clockwise seen from above, starting at the
left front: 1 = left front, 2 = left rear, 3 = right rear, 4 = right front. For every sample the
frame ``vbase`` is

* origin: the MEAN of the four markers (Yuan's Eq. 4 writes the sum, which is four times the
  centroid -- a typo: the text says "the center point of the 4 marked points");
* z axis: the normal of the least-squares plane through the four markers (smallest right singular
  vector of the centred markers), pointing so that ``z . ((p1 - p3) x (p2 - p4)) > 0`` (up for the
  counter-clockwise numbering). Yuan's Eq. 7 crosses ``(p1 - p2)`` with ``(p3 - p4)``: the left and
  right edges of the quadrilateral, which are anti-parallel for a rectangle, so their cross product
  vanishes; the diagonals used here are not parallel for any convex quadrilateral;
* x axis: Yuan's Eq. 6 direction ``(p1 + p4) - (p2 + p3)`` (front minus rear), made orthogonal to
  z by Gram-Schmidt (Yuan's x and z of Eqs. 6-7 are not orthogonal in general, and his Eq. 8 only
  fixes y);
* y axis: ``z x x`` (left), so the frame is right-handed and exactly orthonormal.

:func:`virtual_base` returns ``T_mocap_vbase`` (the virtual base in the motion-capture frame);
:func:`virtual_base_covariance` the covariance of its right perturbation ``[omega, v]`` caused by
isotropic marker noise (first order, numerical Jacobian of the construction), and
:func:`point_covariance_in_vbase` what that adds to a marker position expressed in ``vbase``.

Units: metres, radians.
"""

from __future__ import annotations

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.geometry import invert_pose

__all__ = [
    "BODY_MARKERS",
    "virtual_base",
    "virtual_base_covariance",
    "point_covariance_in_vbase",
    "vbase_points",
]

#: Names of the body markers in mocap.csv, in Yuan's counter-clockwise order from the left front.
BODY_MARKERS = ("body.1", "body.2", "body.3", "body.4")

#: Smallest allowed spread of the markers (m): below it the frame is not defined.
_MIN_SPREAD_M = 1e-4


def _as_batch(markers) -> tuple[np.ndarray, bool]:
    P = np.asarray(markers, dtype=float)
    single = P.ndim == 2
    if single:
        P = P[None]
    if P.ndim != 3 or P.shape[1:] != (4, 3):
        raise GraphcalError("virtual base: expected the four body markers as an array (N, 4, 3) or (4, 3), "
                            f"got shape {np.shape(markers)}")
    if not np.all(np.isfinite(P)):
        raise GraphcalError("virtual base: body marker positions must be finite")
    return P, single


def virtual_base(markers) -> np.ndarray:
    """``T_mocap_vbase`` from the four body markers.

    Args:
        markers: (N, 4, 3) positions of ``body.1 ... body.4`` in the motion-capture frame (m), or
            (4, 3) for one sample. Order: left front, left rear, right rear, right front.

    Returns:
        (N, 4, 4) poses (or (4, 4) for one sample): origin at the markers' mean, z up (normal of
        their plane), x forward, y left; exactly orthonormal.

    Raises:
        GraphcalError: markers (nearly) coincident or collinear, or numbered clockwise or in an
            order whose front-minus-rear direction is along the plane normal (the message names
            the first bad sample).
    """
    P, single = _as_batch(markers)
    o = P.mean(axis=1)
    C = P - o[:, None, :]
    _, s, Vt = np.linalg.svd(C)
    z = Vt[:, 2, :]
    diag = np.cross(P[:, 0] - P[:, 2], P[:, 1] - P[:, 3])
    dn = np.linalg.norm(diag, axis=1)
    bad = (s[:, 1] < _MIN_SPREAD_M) | (dn < _MIN_SPREAD_M**2)
    if bad.any():
        i = int(np.argmax(bad))
        raise GraphcalError(f"virtual base: the four body markers of sample {i} are coincident or collinear "
                            f"(spread {s[i, 1] * 1e3:.3g} mm); they must span a quadrilateral")
    z = np.where((np.einsum("ni,ni->n", z, diag) < 0)[:, None], -z, z)
    x = (P[:, 0] + P[:, 3]) - (P[:, 1] + P[:, 2])
    x = x - np.einsum("ni,ni->n", x, z)[:, None] * z
    xn = np.linalg.norm(x, axis=1)
    if np.any(xn < _MIN_SPREAD_M):
        i = int(np.argmax(xn < _MIN_SPREAD_M))
        raise GraphcalError(f"virtual base: sample {i}: front minus rear markers ((p1 + p4) - (p2 + p3)) has no "
                            f"component in the markers' plane; are body.1..body.4 numbered counter-clockwise "
                            f"from the left front?")
    x = x / xn[:, None]
    y = np.cross(z, x)
    T = np.zeros((P.shape[0], 4, 4))
    T[:, :3, 0] = x
    T[:, :3, 1] = y
    T[:, :3, 2] = z
    T[:, :3, 3] = o
    T[:, 3, 3] = 1.0
    return T[0] if single else T


def _right_log_small(T0: np.ndarray, T1: np.ndarray) -> np.ndarray:
    """(N, 6) ``[omega, v]`` with ``T1 ~ T0 Exp(xi)`` for small differences (first order)."""
    D = np.einsum("nji,njk->nik", T0[:, :3, :3], T1[:, :3, :3])  # R0^T R1
    w = 0.5 * np.stack([D[:, 2, 1] - D[:, 1, 2], D[:, 0, 2] - D[:, 2, 0], D[:, 1, 0] - D[:, 0, 1]], axis=1)
    v = np.einsum("nji,nj->ni", T0[:, :3, :3], T1[:, :3, 3] - T0[:, :3, 3])
    return np.concatenate([w, v], axis=1)


def virtual_base_covariance(markers, sigma_m: float, *, h: float = 1e-7) -> np.ndarray:
    """(N, 6, 6) covariance of the right perturbation ``[omega, v]`` of ``T_mocap_vbase`` (rad, m)
    when every marker coordinate has independent noise of standard deviation ``sigma_m``.

    First order: ``J (sigma^2 I_12) J^T`` with J the (6, 12) central-difference Jacobian of
    :func:`virtual_base` with respect to the 12 marker coordinates (vectorised over N).
    """
    P, single = _as_batch(markers)
    T0 = virtual_base(P)
    J = np.empty((P.shape[0], 6, 12))
    for c in range(12):
        d = np.zeros((4, 3))
        d.flat[c] = h
        xp = _right_log_small(T0, virtual_base(P + d))
        xm = _right_log_small(T0, virtual_base(P - d))
        J[:, :, c] = (xp - xm) / (2 * h)
    cov = float(sigma_m) ** 2 * J @ np.swapaxes(J, 1, 2)
    return cov[0] if single else cov


def vbase_points(T_mocap_vbase, p_mocap) -> np.ndarray:
    """(N, 3) points ``p_vbase = T_mocap_vbase^-1 p_mocap`` for per-sample poses (N, 4, 4) and points (N, 3)."""
    Ti = invert_pose(np.asarray(T_mocap_vbase, dtype=float))
    p = np.asarray(p_mocap, dtype=float)
    return np.einsum("nij,nj->ni", Ti[:, :3, :3], p) + Ti[:, :3, 3]


def point_covariance_in_vbase(p_vbase, cov_vbase) -> np.ndarray:
    """(N, 3, 3) covariance a point ``p_vbase = T_mocap_vbase^-1 p_mocap`` inherits from the virtual
    base's uncertainty ``cov_vbase`` (N, 6, 6) (the point's own measurement noise is not included).

    With ``T = T_hat Exp([omega, v])``: ``p_vbase = Exp(-xi) p_hat ~ p_hat + [p_hat]x omega - v``,
    so ``J = [[p_hat]x, -I]``.
    """
    p = np.asarray(p_vbase, dtype=float)
    N = p.shape[0]
    J = np.zeros((N, 3, 6))
    J[:, 0, 1], J[:, 0, 2] = -p[:, 2], p[:, 1]
    J[:, 1, 0], J[:, 1, 2] = p[:, 2], -p[:, 0]
    J[:, 2, 0], J[:, 2, 1] = -p[:, 1], p[:, 0]
    J[:, :, 3:] = -np.eye(3)
    return J @ np.asarray(cov_vbase, dtype=float) @ np.swapaxes(J, 1, 2)
