"""Honest covariances: marginals that do not crash, body-axis sigmas, and named unobservable directions.

Conventions (graphcal/geometry.py): a Pose3 covariance is of the right perturbation
``T = T_hat Exp(xi)``, ``xi = [omega (rad), v (m)]`` — the tangent of the SENSOR frame for
``T_body_sensor``. Body-axis quantities rotate it by ``R = R_body_sensor`` (first order).

* :func:`marginal_covariances`: gtsam ``Marginals`` (Cholesky); when gtsam calls the system
  indeterminate (it also does so for merely ill-conditioned cliques) the linearised graph is
  eliminated by QR and each marginal read from the Bayes tree; when that fails too (an exactly
  empty direction) a dense pseudo-inverse (small graphs) or a weakly regularised QR (large graphs)
  gives the finite part and ``np.inf`` marks the free components. The result says which path
  was taken and which directions are free.
* :func:`body_axis_sigmas`: 1-sigma rotation (deg) and translation (mm) about/along body axes.
* :func:`unobservable_directions`: sentences naming the directions the data does not determine
  (posterior barely tighter than the prior) and the motion that would determine them.
* :func:`nees`: normalised estimation error squared (chi-square with 6 dof when honest).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import gtsam
import numpy as np

from graphcal.errors import GraphcalError
from graphcal.geometry import pose_log_between, rotation_angle_between, so3_log
from graphcal.solvers.batch import diag_information, indeterminate_key, key_name

__all__ = [
    "MarginalCovariances",
    "marginal_covariances",
    "body_axis_sigmas",
    "unobservable_directions",
    "nees",
    "extrinsic_errors",
]

#: Relative eigenvalue (of the Jacobi-scaled information) below which a direction is free.
NULL_RCOND = 1e-12


class MarginalCovariances(dict):
    """``dict[key, (d, d) covariance]`` with how it was obtained.

    Attributes:
        method: ``"cholesky"`` (gtsam Marginals), ``"qr"`` (QR elimination, Bayes-tree marginals),
            ``"dense"`` (pseudo-inverse of the dense information) or ``"regularised"`` (QR with a
            negligible prior on every variable, large graphs whose information is singular).
        null_directions: key -> (d, m) orthonormal columns (tangent of that variable) that the
            graph does not determine; only for singular systems. The covariance is the
            pseudo-inverse on the rest and ``np.inf`` on the diagonal entries they touch.
        warnings: human-readable sentences, one per variable with free directions.
    """

    def __init__(self, *args, method: str = "cholesky", **kwargs):
        super().__init__(*args, **kwargs)
        self.method = method
        self.null_directions: dict[int, np.ndarray] = {}
        self.warnings: list[str] = []

    @property
    def singular(self) -> bool:
        """True when some requested variable has a direction the graph does not determine."""
        return bool(self.null_directions)


# ----------------------------------------------------------------------------- helpers
def _is_indeterminate(exc: BaseException) -> bool:
    return indeterminate_key(exc) is not None


def _inverse_with_null(info: np.ndarray, rcond: float = NULL_RCOND) -> tuple[np.ndarray, np.ndarray]:
    """(covariance, null basis (d, m)) of a symmetric information matrix: pseudo-inverse after
    Jacobi scaling (scale invariant), ``inf`` on the diagonal entries a free direction touches."""
    info = 0.5 * (np.asarray(info, dtype=float) + np.asarray(info, dtype=float).T)
    d = info.shape[0]
    dg = np.diag(info).copy()
    pos = dg > 0
    D = np.ones(d)
    D[pos] = 1.0 / np.sqrt(dg[pos])
    Hs = info * D[:, None] * D[None, :]
    if d and pos.all():
        # fast path: a clearly positive-definite system (Cholesky, ~10x faster than eigh); the
        # pivots bound the smallest eigenvalue well above the null threshold
        try:
            Lc = np.linalg.cholesky(Hs)
        except np.linalg.LinAlgError:
            Lc = None
        if Lc is not None and float(np.min(np.diag(Lc))) ** 2 > 1e3 * rcond * float(np.max(np.diag(Lc))) ** 2:
            Li = np.linalg.inv(Lc)
            cov = (Li.T @ Li) * D[:, None] * D[None, :]
            return 0.5 * (cov + cov.T), np.zeros((d, 0))
    w, V = np.linalg.eigh(Hs)
    wmax = max(float(w.max()), 0.0) if w.size else 0.0
    keep = w > rcond * wmax if wmax > 0 else np.zeros(d, dtype=bool)
    Vr = V[:, keep]
    cov = (D[:, None] * Vr) @ np.diag(1.0 / w[keep]) @ (Vr.T * D[None, :])
    null = D[:, None] * V[:, ~keep]
    if null.shape[1]:
        null = np.linalg.qr(null / np.linalg.norm(null, axis=0))[0]
        _mark_inf(cov, null)
    return 0.5 * (cov + cov.T), null


def _mark_inf(cov: np.ndarray, null: np.ndarray, tol: float = 1e-6) -> None:
    touched = np.linalg.norm(null, axis=1) > tol
    idx = np.flatnonzero(touched)
    cov[idx, idx] = np.inf


def _null_warning(key: int, null: np.ndarray) -> str:
    return (f"{key_name(key)}: the graph does not determine {null.shape[1]} direction(s) of it "
            "(covariance set to inf along them)")


def _finish(out: MarginalCovariances, key: int, cov: np.ndarray, null: np.ndarray) -> None:
    out[key] = cov
    if null.size and null.shape[1]:
        out.null_directions[key] = null
        out.warnings.append(_null_warning(key, null))


# ----------------------------------------------------------------------------- marginals
def marginal_covariances(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    keys: Iterable[int],
    *,
    dense_max_dim: int = 2000,
) -> MarginalCovariances:
    """Marginal covariance of each key at ``values``; never raises for a singular graph.

    Order of attempts: gtsam ``Marginals`` (Cholesky) -> QR elimination
    (``lin.eliminateMultifrontal(COLAMD, EliminateQR)``, marginals from the Bayes tree with QR) ->
    dense pseudo-inverse of the information when the total dimension is at most
    ``dense_max_dim``, else QR with a negligible per-variable prior (1e-14 of each column's own
    information) whose influence identifies the free directions. Keys of ``values`` that no
    factor involves get ``inf`` variance and are reported free.

    Args:
        graph, values: the graph and the point of linearisation (usually the optimum).
        keys: the variables wanted.
        dense_max_dim: largest total dimension for the dense fallback.

    Returns:
        :class:`MarginalCovariances` (a dict key -> covariance in the variable's tangent; for a
        Pose3 ``[omega, v]`` of the right perturbation), with ``method``, ``null_directions`` and
        ``warnings``.

    Raises:
        GraphcalError: a key is not a variable of ``values``.
    """
    keys = [int(k) for k in keys]
    for k in keys:
        if not values.exists(k):
            raise GraphcalError(f"marginal_covariances: {key_name(k)} is not in the values")
    dims = {int(k): int(d) for k, d in values.dims().items()}
    graph_keys = {int(k) for k in graph.keyVector()}  # (iterating a temporary KeySet segfaults)
    free = [k for k in keys if k not in graph_keys]
    keys_in = [k for k in keys if k in graph_keys]

    def with_free(res: MarginalCovariances) -> MarginalCovariances:
        _unconstrained(free, dims, res)
        return res

    if not keys_in:
        return with_free(MarginalCovariances(method="cholesky"))
    # 1. gtsam Marginals (Cholesky)
    try:
        m = gtsam.Marginals(graph, values)
        covs = {k: np.asarray(m.marginalCovariance(k), dtype=float) for k in keys_in}
        if all(np.all(np.isfinite(c)) for c in covs.values()):
            out = MarginalCovariances(method="cholesky")
            for k, c in covs.items():
                out[k] = 0.5 * (c + c.T)
            return with_free(out)
    except RuntimeError as e:
        if not _is_indeterminate(e):
            raise
    lin = graph.linearize(values)
    # 2. QR elimination, marginals from the Bayes tree
    try:
        ordering = gtsam.Ordering.ColamdGaussianFactorGraph(lin)
        bt = lin.eliminateMultifrontal(ordering, gtsam.EliminateQR)
        res = MarginalCovariances(method="qr")
        for k in keys_in:
            cond = bt.marginalFactor(k, gtsam.EliminateQR)
            info = np.asarray(cond.information(), dtype=float)
            if not np.all(np.isfinite(info)):
                raise FloatingPointError("non-finite marginal information")
            cov, null = _inverse_with_null(info)
            _finish(res, k, cov, null)
        return with_free(res)
    except (RuntimeError, FloatingPointError, np.linalg.LinAlgError) as e:
        if isinstance(e, RuntimeError) and not _is_indeterminate(e):
            raise
    gk = sorted(int(k) for k in lin.keyVector())
    total = sum(dims[k] for k in gk)
    if total <= dense_max_dim:
        return with_free(_dense_marginals(lin, gk, dims, keys_in))
    return with_free(_regularised_marginals(lin, gk, dims, keys_in))


def _unconstrained(keys, dims, out: MarginalCovariances) -> None:
    """Keys in the values but in no factor: infinite variance, every direction free."""
    for k in keys:
        d = dims[k]
        cov = np.zeros((d, d))
        cov[np.arange(d), np.arange(d)] = np.inf
        _finish(out, k, cov, np.eye(d))


def dense_covariance(lin, graph_keys, dims) -> tuple[np.ndarray, np.ndarray, dict]:
    """(full covariance, null directions (n, m), key -> column offset) of a linearised graph, from
    one dense inverse of its information matrix (columns in sorted key order; free directions get
    inf on the diagonal and appear in the null columns)."""
    ordering = gtsam.Ordering()
    offsets, off = {}, 0
    for k in sorted(graph_keys):
        ordering.push_back(k)
        offsets[k] = off
        off += dims[k]
    H, _ = lin.hessian(ordering)
    cov_full, null = _inverse_with_null(np.asarray(H, dtype=float))
    return cov_full, null, offsets


def _dense_marginals(lin, graph_keys, dims, keys) -> MarginalCovariances:
    out = MarginalCovariances(method="dense")
    keys_in = keys
    cov_full, null, offsets = dense_covariance(lin, graph_keys, dims)
    # _inverse_with_null put inf on the touched diagonal entries of the full matrix already
    for k in keys_in:
        o, d = offsets[k], dims[k]
        cov = cov_full[o : o + d, o : o + d].copy()
        nk = null[o : o + d, :] if null.shape[1] else np.zeros((d, 0))
        if nk.shape[1]:
            U, s, _ = np.linalg.svd(nk, full_matrices=False)
            nk = U[:, s > 1e-6]
        _finish(out, k, cov, nk)
    return out


def _regularised_marginals(lin, graph_keys, dims, keys, eps: float = 1e-14) -> MarginalCovariances:
    out = MarginalCovariances(method="regularised")
    keys_in = keys
    diag = diag_information(lin, {k: dims[k] for k in graph_keys})
    reg = gtsam.GaussianFactorGraph()
    reg.push_back(lin)
    scale = {}
    for k in graph_keys:
        dg = diag[k]
        ref = float(dg.max()) if dg.size and dg.max() > 0 else 1.0
        s2 = np.where(dg > 0, dg, ref)
        scale[k] = np.sqrt(s2)
        reg.push_back(gtsam.JacobianFactor(k, np.diag(np.sqrt(eps * s2)), np.zeros(dims[k]),
                                           gtsam.noiseModel.Unit.Create(dims[k])))
    bt = reg.eliminateMultifrontal(gtsam.Ordering.ColamdGaussianFactorGraph(reg), gtsam.EliminateQR)
    for k in keys_in:
        cond = bt.marginalFactor(k, gtsam.EliminateQR)
        C = np.linalg.inv(np.asarray(cond.information(), dtype=float))
        S = scale[k]
        Cs = C * S[:, None] * S[None, :]  # scaled: the regulariser alone gives 1/eps
        w, V = np.linalg.eigh(0.5 * (Cs + Cs.T))
        free = w > 0.01 / eps
        Vf = V[:, ~free]
        cov = (Vf / S[:, None]) @ np.diag(w[~free]) @ (Vf.T / S[None, :])
        null = V[:, free] / S[:, None]
        if null.shape[1]:
            null = np.linalg.qr(null / np.linalg.norm(null, axis=0))[0]
            _mark_inf(cov, null)
        _finish(out, k, 0.5 * (cov + cov.T), null)
    return out


# ----------------------------------------------------------------------------- body axes
def _rotation_of(T) -> np.ndarray:
    if isinstance(T, gtsam.Pose3):
        return np.asarray(T.rotation().matrix(), dtype=float)
    T = np.asarray(T, dtype=float)
    if T.shape == (4, 4):
        return T[:3, :3]
    if T.shape == (3, 3):
        return T
    raise GraphcalError(f"expected a 4x4 pose, 3x3 rotation or gtsam.Pose3, got shape {T.shape}")


def _to_body(R: np.ndarray, cov6) -> tuple[np.ndarray, np.ndarray]:
    """(J cov J^T with J = blockdiag(R, R), mask of body components with infinite variance)."""
    cov6 = np.asarray(cov6, dtype=float)
    if cov6.shape != (6, 6):
        raise GraphcalError(f"expected a 6x6 covariance, got shape {cov6.shape}")
    J = np.zeros((6, 6))
    J[:3, :3] = R
    J[3:, 3:] = R
    bad = ~np.isfinite(np.diag(cov6))
    C = np.where(np.isfinite(cov6), cov6, 0.0)
    C[bad, :] = 0.0
    C[:, bad] = 0.0
    out = J @ C @ J.T
    inf_body = (np.abs(J[:, bad]).sum(axis=1) > 1e-9) if bad.any() else np.zeros(6, dtype=bool)
    return 0.5 * (out + out.T), inf_body


def body_axis_sigmas(T_body_sensor, cov6) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """1-sigma of an extrinsic about and along the BODY axes.

    ``cov6`` is of ``xi = [omega, v]`` with ``T = T_hat Exp(xi)`` (sensor-frame tangent). To
    first order the body-frame rotation error is ``R omega`` (``R_true = Exp(R omega) R_hat``)
    and the error of ``t_body_sensor`` is ``R v``, so ``cov_body = J cov6 J^T`` with
    ``J = blockdiag(R, R)``.

    Returns:
        (sigma_rot_deg (3,) about body x, y, z; sigma_xyz_mm (3,) along body x, y, z;
        correlation (6, 6) in the order [rx, ry, rz, x, y, z]; cov_body (6, 6) in rad and m).
        Components with infinite variance get sigma inf and correlation 0 (1 on the diagonal).
    """
    R = _rotation_of(T_body_sensor)
    cov_body, inf_body = _to_body(R, cov6)
    var = np.clip(np.diag(cov_body), 0.0, None)
    s = np.sqrt(var)
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = cov_body / np.outer(s, s)
    corr[~np.isfinite(corr)] = 0.0
    s = np.where(inf_body, np.inf, s)
    corr[inf_body, :] = 0.0
    corr[:, inf_body] = 0.0
    np.fill_diagonal(corr, 1.0)
    corr = np.clip(corr, -1.0, 1.0)
    cov_body = cov_body.copy()
    cov_body[inf_body, inf_body] = np.inf
    return np.degrees(s[:3]), 1e3 * s[3:], corr, cov_body


# ----------------------------------------------------------------------------- unobservable directions
def _named_axes(up_body) -> tuple[np.ndarray, list[str], list[str], list[frozenset]]:
    """Six unit directions in body [rx, ry, rz, x, y, z] order, their names, motions."""
    u = np.asarray(up_body, dtype=float)
    u = u / np.linalg.norm(u)
    ex = np.array([1.0, 0.0, 0.0])
    h1 = ex - (ex @ u) * u
    if np.linalg.norm(h1) < 0.1:
        ey = np.array([0.0, 1.0, 0.0])
        h1 = ey - (ey @ u) * u
    h1 /= np.linalg.norm(h1)
    h2 = np.cross(u, h1)
    level = np.degrees(np.arccos(np.clip(u[2], -1, 1))) < 1.0
    ax = ("body x", "body y", "body z") if level else ("the horizontal axis nearest body x",
                                                        "the horizontal axis nearest body y", "the up axis")
    B = np.zeros((6, 6))
    for j, a in enumerate((h1, h2, u)):
        B[:3, j] = a
        B[3:, 3 + j] = a
    names = [
        f"rotation about {ax[0]} (roll)",
        f"rotation about {ax[1]} (pitch)",
        f"rotation about the ground normal (yaw about {ax[2]})",
        f"translation along {ax[0]}",
        f"translation along {ax[1]}",
        f"height (translation along {ax[2]})",
    ]
    motions = [
        frozenset({"ground"}),
        frozenset({"ground"}),
        frozenset({"roll", "pitch"}),
        frozenset({"pitch"}),
        frozenset({"roll"}),
        frozenset({"height"}),
    ]
    return B, names, ax, motions


def _motion_phrase(tokens: set) -> str:
    parts = []
    tilt = [t for t in ("roll", "pitch") if t in tokens]
    if tilt:
        parts.append(f"add {' and '.join(tilt)} variation")
    if "height" in tokens:
        parts.append("vary the body height")
    if "ground" in tokens:
        parts.append("make sure the sensor sees the ground at more stations")
    return " and ".join(parts)


def unobservable_directions(
    T_body_sensor,
    cov_posterior,
    cov_prior,
    *,
    up_body: Sequence[float] = (0.0, 0.0, 1.0),
    ratio: float = 0.5,
    pure_fraction: float = 0.8,
) -> tuple[str, ...]:
    """Sentences naming each direction of the extrinsic that the data does not determine.

    The prior is a unary factor on the extrinsic, so information adds:
    ``I_data = inv(P) - inv(Q)`` (P posterior, Q prior, both rotated to body axes). A direction
    ``x`` is "not determined by the data" when the posterior sigma along it exceeds ``ratio``
    times the prior sigma, i.e. ``x^T inv(Q) x / x^T inv(P) x > ratio^2``. These directions are
    the generalised eigenvectors of (P, Q) with eigenvalue > ratio^2; they are expressed in
    prior-scaled body coordinates (each component divided by its prior sigma, so rad and m are
    comparable) and matched to named axes built from ``up_body``: yaw about the ground normal,
    roll and pitch of the sensor, translation along the two horizontal axes and the height. An
    axis carrying at least ``pure_fraction`` of such a direction gets its own sentence; the rest
    of the undetermined subspace is described as a combination with percentages.

    Args:
        T_body_sensor: (4, 4) estimate (or gtsam.Pose3).
        cov_posterior: (6, 6) posterior covariance of the right perturbation [omega, v].
        cov_prior: (6, 6) prior covariance (same convention; e.g. diag(sig_rad^2 x3, sig_m^2 x3)).
        up_body: the mean up direction in the body frame at the stations (default body z).
        ratio: threshold of posterior sigma / prior sigma.

    Returns:
        One sentence per undetermined direction, e.g. ``"rotation about the ground normal (yaw
        about body z) is not determined by the data: add roll and pitch variation (posterior
        sigma 98 % of the prior's)"``; empty when the data determines everything.
    """
    import scipy.linalg

    R = _rotation_of(T_body_sensor)
    P, p_inf = _to_body(R, cov_posterior)
    Q, q_inf = _to_body(R, cov_prior)
    if q_inf.any():
        raise GraphcalError("unobservable_directions: the prior covariance must be finite")
    if np.any(np.linalg.eigvalsh(Q) <= 0):
        raise GraphcalError("unobservable_directions: the prior covariance must be positive definite")
    # components with infinite posterior: the data (and prior) say nothing there -> as the prior
    if p_inf.any():
        P[p_inf, :] = Q[p_inf, :]
        P[:, p_inf] = Q[:, p_inf]
    Qinv = np.linalg.inv(Q)
    try:
        Pinv = np.linalg.inv(P)
    except np.linalg.LinAlgError:
        Pinv = np.linalg.pinv(P)
    sig = np.sqrt(np.diag(Q))  # prior sigmas per body component: the scaling
    # generalised eigenproblem in scaled coordinates: P_s a = mu Q_s a
    Ps = P / np.outer(sig, sig)
    Qs = Q / np.outer(sig, sig)
    mu, A = scipy.linalg.eigh(0.5 * (Ps + Ps.T), 0.5 * (Qs + Qs.T))
    und = mu > ratio**2
    if not und.any():
        return ()
    # parameter-space directions x = Q a (scaled coordinates), normalised
    X = Qs @ A[:, und]
    X = X[:, np.argsort(-mu[und])]
    X /= np.linalg.norm(X, axis=0)
    S, _ = np.linalg.qr(X)  # orthonormal basis of the undetermined subspace (scaled coords)
    B, names, _, motions = _named_axes(up_body)
    Bs = B / sig[:, None]  # named axes in scaled coordinates
    Bs /= np.linalg.norm(Bs, axis=0)

    def sigma_ratio(xs: np.ndarray) -> float:
        x = xs * sig  # back to body units
        den = float(x @ Pinv @ x)
        return float(np.sqrt(max(x @ Qinv @ x, 0.0) / den)) if den > 0 else float("inf")

    sentences, taken = [], []
    frac = np.sum((S.T @ Bs) ** 2, axis=0)  # fraction of each named axis inside the subspace
    for j in range(6):  # body-axis order: rx, ry, rz, x, y, z
        if frac[j] >= pure_fraction:
            r = sigma_ratio(Bs[:, j])
            if r > ratio:
                taken.append(j)
                sentences.append(f"{names[j]} is not determined by the data: {_motion_phrase(set(motions[j]))} "
                                 f"(posterior sigma {100 * min(r, 1.0):.0f} % of the prior's)")
    # remaining part of the subspace, described as combinations
    if taken:
        T_ax = Bs[:, taken]
        Qt, _ = np.linalg.qr(T_ax)
        Srem = S - Qt @ (Qt.T @ S)
        U_, s_, _ = np.linalg.svd(Srem, full_matrices=False)
        rem = U_[:, s_ > 0.5]
    else:
        rem = S
    for c in range(rem.shape[1]):
        xs = rem[:, c]
        r = sigma_ratio(xs)
        if r <= ratio:
            continue
        w = (Bs.T @ xs) ** 2  # Bs orthonormal when the prior is isotropic per block
        w = w / w.sum()
        order = [j for j in np.argsort(-w) if w[j] >= 0.1]
        if len(order) == 1:
            j = order[0]
            sentences.append(f"{names[j]} is not determined by the data: {_motion_phrase(set(motions[j]))} "
                             f"(posterior sigma {100 * min(r, 1.0):.0f} % of the prior's)")
            continue
        parts = [f"{names[j]} ({100 * w[j]:.0f} %)" for j in order]
        tokens = set().union(*(motions[j] for j in order))
        sentences.append(
            f"a combination of {', '.join(parts[:-1])} and {parts[-1]} is not determined by the data: "
            f"{_motion_phrase(tokens)} (posterior sigma {100 * min(r, 1.0):.0f} % of the prior's)"
        )
    return tuple(sentences)


# ----------------------------------------------------------------------------- NEES
def _check_pose(T):
    if not isinstance(T, gtsam.Pose3) and np.shape(T) != (4, 4):
        raise GraphcalError(f"expected a 4x4 pose or gtsam.Pose3, got shape {np.shape(T)}")
    return T


def nees(T_true, T_est, cov6) -> float:
    """Normalised estimation error squared ``xi^T inv(cov6) xi`` with
    ``xi = Log(T_est^-1 T_true)`` (the right-perturbation error, [omega, v]). Averages 6 over
    many runs when ``cov6`` is honest (chi-square, 6 dof)."""
    xi = pose_log_between(_check_pose(T_est), _check_pose(T_true))
    C = np.asarray(cov6, dtype=float)
    if C.shape != (6, 6):
        raise GraphcalError(f"expected a 6x6 covariance, got shape {C.shape}")
    return float(xi @ np.linalg.solve(C, xi))


def extrinsic_errors(T_est, T_true, cov6=None) -> dict:
    """An estimated extrinsic's errors against the truth, about and along the BODY axes.

    Args:
        T_est, T_true: 4x4 T_body_sensor, estimated and true (m).
        cov6: optional 6x6 covariance of the estimate's right perturbation [omega, v] (rad, m; sensor axes).

    Returns:
        ``angle_deg``: angle of ``R_est^T R_true`` (deg); ``distance_mm``: ``|t_est - t_true|`` (mm);
        ``dphi_deg`` (3,): ``Log(R_est R_true^T)`` (deg), the estimate's rotation error
        (``R_est = Exp(dphi) R_true``); ``dt_mm`` (3,): ``t_est - t_true`` (mm);
        ``error`` (6,): the truth relative to the estimate, ``xi = Log(T_est^-1 T_true)`` rotated to the
        body axes, ``[R omega (deg), R v (mm)]``. With ``cov6`` also ``sigma`` (6,) the 1-sigma in the
        same axes and units (:func:`body_axis_sigmas`), ``z2`` (6,) (error/sigma)^2 per axis and
        ``nees`` (:func:`nees`, 6 dof).
    """
    T, T_t = np.asarray(T_est, dtype=float), np.asarray(T_true, dtype=float)
    R = T[:3, :3]
    dt_mm = 1e3 * (T[:3, 3] - T_t[:3, 3])
    xi = pose_log_between(T, T_t)
    e_body = np.concatenate([R @ xi[:3], R @ xi[3:]])
    out = {"angle_deg": float(np.degrees(rotation_angle_between(R, T_t[:3, :3]))),
           "distance_mm": float(np.linalg.norm(dt_mm)),
           "dphi_deg": np.degrees(so3_log(R @ T_t[:3, :3].T)),
           "dt_mm": dt_mm,
           "error": np.concatenate([np.degrees(e_body[:3]), 1e3 * e_body[3:]])}
    if cov6 is not None:
        C = np.asarray(cov6, dtype=float)
        s_rot_deg, s_xyz_mm, _, cov_body = body_axis_sigmas(T, C)
        out.update(sigma=np.concatenate([s_rot_deg, s_xyz_mm]), z2=e_body**2 / np.diag(cov_body),
                   nees=float(nees(T_t, T, C)))
    return out
