"""Variance-component estimation (Förstner / Helmert): the sigma of each factor group, learned from
its whitened residuals and redundancy numbers at the solution, ``s_g^2 = sum e_i^2 / sum r_i``.

A group whose covariance is a sum of components (a foot: joint noise through the leg Jacobian plus
isotropic contact noise) gets one scale per component from Helmert's equations
(:func:`consistent_helmert_matrix`), split only where the data determine it
(:func:`split_determined`). The scales are iterated to their fixed point on one linearisation
(:func:`converged_scales`); :func:`group_variances` is one update. Scales are dimensionless
multipliers of the sigmas of :class:`~graphcal.calibration.graph.CalibrationOptions` (m, rad).

The method and its formulas: docs/calibration.md, "Variance-component estimation".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, NamedTuple

import gtsam
import numpy as np

from graphcal.calibration.graph import CalibrationOptions, CalibrationProblem
from graphcal.calibration.result import NoiseGroupEstimate
from graphcal.errors import GraphcalError


def whitening_matrix(factor) -> np.ndarray:
    """The square matrix W that whitens a Gaussian factor's error (``W^T W = Sigma^-1``, GTSAM's
    upper-triangular ``R``; a robust model's underlying Gaussian). Any square root of Sigma^-1
    whitens, but they differ by a rotation of the rows, so a component's covariance must be carried
    into the whitened space with the one the linearisation used: ``C_k = W Sigma_k W^T``."""
    nm = factor.noiseModel()
    if isinstance(nm, gtsam.noiseModel.Robust):
        nm = nm.noise()
    return np.asarray(nm.R(), dtype=float)


@dataclass(frozen=True)
class GroupVariance:
    """One noise group at a solution: sum of squared whitened residuals, its redundancy (dof), rows."""

    group: str
    chi2: float
    redundancy: float
    rows: int

    helmert_theta: float | None = None
    #: the other components of its group that share its scale (the split was not determined)
    shared_with: tuple[str, ...] = ()

    @property
    def scale(self) -> float:
        """The factor to apply to the group's sigma (1 = the noise model fits)."""
        if self.helmert_theta is not None:
            return float(np.sqrt(max(self.helmert_theta, 1e-8)))
        if self.redundancy <= 1e-6:
            return 1.0
        return float(np.sqrt(self.chi2 / self.redundancy))


#: a component's Helmert theta (in units of its current variance) with a larger standard deviation
#: is not determined by the data: its group's components share one scale (docs/calibration.md)
SPLIT_MAX_THETA_STD = 0.5


def split_determined(N: np.ndarray) -> bool:
    """Whether Helmert's equations ``N theta = q`` of one group determine each component's theta:
    every standard deviation ``sqrt(2 (N^-1)_kk)`` at most :data:`SPLIT_MAX_THETA_STD` (False for a
    singular ``N``, e.g. a component at its floor that carries no redundancy)."""
    N = np.asarray(N, dtype=float)
    if not np.all(np.isfinite(N)) or np.linalg.cond(N) > 1e12:
        return False
    var = 2.0 * np.diag(np.linalg.inv(N))
    return bool(np.all(var > 0) and np.all(np.sqrt(var) <= SPLIT_MAX_THETA_STD))


def consistent_helmert_matrix(N: np.ndarray, redundancy) -> np.ndarray:
    """Helmert's matrix of one group, each row ``k`` scaled to sum to the component's redundancy
    ``tr(R C_k)`` (``redundancy``, (K,)), so that the equations' fixed point is Förstner's, the
    REML one: ``q_k = tr(R C_k)``.

    ``N`` is summed from each factor's own block of ``R``; the exact ``tr(R C_k R C_l)`` also has the
    blocks between two factors of the group (two feet on one body pose, one foot over the stations
    of its session), all of one sign for ``C = I``. Without them the row sums are ``sum_a tr(R_aa^2
    C_k)``, below ``tr(R C_k)`` (``R_aa^2 <= R_aa``), and ``theta = N^-1 q`` reads a correct noise
    model too large, which learning puts into a contact term the data do not have (measured:
    docs/calibration.md, "Helmert's matrix of the stance feet"). ``N`` stays as given for
    :func:`split_determined`. Summed over all components of all groups the rows of the exact
    matrix are ``tr(R C_k R) = tr(R C_k)`` (``R`` a projector in the whitened space): the scale
    restores that. A row that sums to 0 is kept."""
    N = np.asarray(N, dtype=float)
    sums = N.sum(axis=1)
    red = np.asarray(redundancy, dtype=float)
    factor = np.where(sums > 0, red / np.where(sums > 0, sums, 1.0), 1.0)
    return N * factor[:, None]


def helmert_components(group: str, names: list, N: np.ndarray, q: np.ndarray, redundancy: list,
                       rows: int, split: bool) -> dict:
    """``group/component`` -> :class:`GroupVariance` from one group's Helmert equations.

    Args:
        group, names: the group and its component names.
        N, q: Helmert's equations ``N theta = q`` summed over the group's factors (docs/calibration.md);
            ``N``'s rows are scaled to ``redundancy`` first (:func:`consistent_helmert_matrix`).
        redundancy: ``sum tr(R C_k)`` per component (its dof).
        rows: residual rows of the group.
        split: solve per component (:func:`split_determined`); False: one theta shared by all, with
            the chi-square and dof of their sum.
    """
    keys = [f"{group}/{k}" for k in names]
    N = consistent_helmert_matrix(N, redundancy)
    if split:
        theta = np.linalg.lstsq(N, q, rcond=None)[0]
        return {key: GroupVariance(key, float(qk), float(r), rows, float(th))
                for key, qk, r, th in zip(keys, q, redundancy, theta)}
    total = float(np.sum(N))
    theta = float(np.sum(q)) / total if total > 0 else 1.0
    return {key: GroupVariance(key, float(np.sum(q)), float(np.sum(redundancy)), rows, theta,
                               tuple(k for k in keys if k != key)) for key in keys}


#: graphs with at most this many unknowns get their joint marginals from one inverse through the
#: Schur complement of the station poses (:class:`_ArrowLayout`: memory ~ unknowns x globals); larger
#: graphs use the factor-by-factor marginals, several times slower (docs/calibration.md,
#: "1,000 stations"); not raised further: larger graphs were not measured
DENSE_MAX_DIM = 8000


def _is_dense(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> bool:
    """Whether the graph's unknowns are few enough for the dense algebra (``DENSE_MAX_DIM``)."""
    dims = {int(k): int(d) for k, d in values.dims().items()}
    return sum(dims[int(k)] for k in graph.keyVector()) <= DENSE_MAX_DIM


def _marginals_reader(graph, values):
    """A function keys -> joint marginal covariance (blocks in the order of ``keys``), factor by
    factor from ``gtsam.Marginals`` (large graphs)."""
    try:
        marginals = gtsam.Marginals(graph, values)
    except RuntimeError as exc:
        raise GraphcalError(f"noise estimation: the graph has an undetermined variable ({exc})") from None

    def joint(ks):
        jm = marginals.jointMarginalCovariance(gtsam.KeyVector(ks))
        return np.block([[np.asarray(jm.at(a, c)) for c in ks] for a in ks])

    return joint


def group_variances(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, groups: dict,
                    components: dict | None = None) -> dict:
    """group (or ``group/component``) -> :class:`GroupVariance` at ``values`` (docs/calibration.md).

    Args:
        groups: factor index -> group name.
        components: factor index -> {component name: covariance Sigma_k (unwhitened, the factor's
            current value)} for factors whose covariance is a sum of components; their results are
            keyed ``group/component``.
    """
    components = components or {}
    if _is_dense(graph, values):  # one dense update: the first iteration of converged_scales
        return converged_scales(graph, values, groups, components, eligible=lambda v: True, max_iterations=1).first
    lin = graph.linearize(values)
    joint = _marginals_reader(graph, values)
    acc: dict[str, list[float]] = {}
    cache: dict[tuple, np.ndarray] = {}
    helmert: dict[str, tuple[list, dict, dict]] = {}  # group -> (component names, N, q)
    for i, g in groups.items():
        f = lin.at(i)
        A, b = f.jacobian()
        keys = list(f.keys())
        sig = cache.get(tuple(keys))
        if sig is None:
            sig = joint(keys)
            cache[tuple(keys)] = sig
        comps = components.get(i)
        if not comps:
            h = np.einsum("ij,jk,ik->i", A, sig, A)
            r = np.clip(1.0 - h, 0.0, 1.0)
            a = acc.setdefault(g, [0.0, 0.0, 0])
            a[0] += float(b @ b)
            a[1] += float(r.sum())
            a[2] += len(b)
            continue
        R = np.eye(len(b)) - A @ sig @ A.T
        W = whitening_matrix(graph.at(i))
        names, N, q = helmert.setdefault(g, (list(comps), {}, {}))
        C = {name: W @ Sk @ W.T for name, Sk in comps.items()}
        for k in names:
            RCk = R @ C[k]
            q[k] = q.get(k, 0.0) + float(b @ C[k] @ b)
            for m in names:
                N[(k, m)] = N.get((k, m), 0.0) + float(np.trace(RCk @ R @ C[m]))
            a = acc.setdefault(f"{g}/{k}", [0.0, 0.0, 0])
            a[0] += float(b @ C[k] @ b)
            a[1] += float(max(np.trace(RCk), 0.0))
            a[2] += len(b)
    out = {g: GroupVariance(g, a[0], a[1], a[2]) for g, a in acc.items()}
    for g, (names, N, q) in helmert.items():
        Nm = np.array([[N[(k, m)] for m in names] for k in names])
        qv = np.array([q[k] for k in names])
        first = out[f"{g}/{names[0]}"]
        out.update(helmert_components(g, names, Nm, qv, [out[f"{g}/{k}"].redundancy for k in names],
                                      first.rows, split_determined(Nm)))
    return out


def _factor_blocks(lin: gtsam.GaussianFactorGraph, values: gtsam.Values, keys, n_factors: int) -> tuple[dict, list, dict, list]:
    """The whitened linear system by factor, gathered into blocks of equal shape.

    Each factor's Jacobian comes over the columns of its own variables (``lin.at(i).jacobian()``,
    keys in the factor's order); the unknowns are those of ``keys`` (the graph's), numbered in sorted
    key order.

    Returns (blocks, where, columns, factor_keys): ``blocks`` (r, k) -> (factor ids (F,), A (F, r, k),
    b (F, r), column indices (F, k)) for the factors of r rows over k unknowns, ``where[i]`` = ((r, k),
    position) of factor i, ``columns`` key -> its unknowns' column indices, and ``factor_keys[i]``
    the keys of factor i.
    """
    dims = {int(k): int(d) for k, d in values.dims().items()}
    key_cols, n = {}, 0
    for k in sorted(int(k) for k in keys):
        key_cols[k] = list(range(n, n + dims[k]))
        n += dims[k]
    parts: dict[tuple, tuple[list, list, list, list]] = {}
    where: list = [None] * n_factors
    factor_keys: list = [None] * n_factors
    for i in range(n_factors):
        f = lin.at(i)
        A, b = f.jacobian()
        factor_keys[i] = tuple(int(k) for k in f.keys())
        cols = [c for k in factor_keys[i] for c in key_cols[k]]
        A = np.asarray(A, dtype=float)
        key = A.shape
        if key[1] != len(cols):
            raise GraphcalError(f"noise estimation: factor {i} has {key[1]} Jacobian columns for {len(cols)} unknowns")
        ids, As, bs, cs = parts.setdefault(key, ([], [], [], []))
        where[i] = (key, len(ids))
        ids.append(i)
        As.append(A)
        bs.append(np.asarray(b, dtype=float).reshape(-1))
        cs.append(cols)
    blocks = {key: (np.asarray(ids), np.stack(As), np.stack(bs), np.stack(cs)) for key, (ids, As, bs, cs) in parts.items()}
    return blocks, where, key_cols, factor_keys


def _arrow_split(columns: dict, factor_keys: list) -> tuple[dict, np.ndarray]:
    """Split the unknowns for :class:`_ArrowLayout`: "local" variables, no two of which share a
    factor (a calibration graph's station poses: each station's factors touch its own pose and the
    shared variables only), chosen greedily by fewest neighbours; the rest is "global".

    Returns (dimension -> (m, d) column indices of the local variables of that dimension, the
    global columns (g,))."""
    neighbours: dict = {k: set() for k in columns}
    for keys in factor_keys:
        for k in keys:
            neighbours[k].update(keys)
    local, blocked = [], set()
    for k in sorted(columns, key=lambda k: (len(neighbours[k]), k)):
        if k not in blocked:
            local.append(k)
            blocked |= neighbours[k]
    by_dim: dict = {}
    for k in local:
        by_dim.setdefault(len(columns[k]), []).append(columns[k])
    in_local = set(local)
    global_cols = [c for k in sorted(columns) if k not in in_local for c in columns[k]]
    return {d: np.asarray(c, dtype=np.int64) for d, c in by_dim.items()}, np.asarray(global_cols, dtype=np.int64)


def _pd_inverse(M: np.ndarray) -> np.ndarray:
    """Inverses of symmetric positive-definite matrices (..., d, d); GraphcalError if one is not."""
    try:
        np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        raise GraphcalError("noise estimation: the graph has an undetermined variable") from None
    return np.linalg.inv(M) if M.shape[-1] else M.copy()


class _ArrowLayout:
    """Where the blocks of an arrow-shaped normal matrix live in one flat array (:func:`_arrow_split`:
    local variables coupled only through the global columns, ``H = [[D, B], [B^T, G]]`` with D block
    diagonal), and their solution in the same layout. Per dimension d of the local variables (m_d of
    them): ``D_d`` (m_d, d, d) and ``B_d`` (m_d, d, g); then ``G`` (g, g). The covariance uses the same
    layout (``Sigma_LL`` per local variable, ``Sigma_LG``, ``Sigma_GG``): the blocks a factor can read,
    since no factor touches two local variables. Memory O(stations x globals), not O(n^2) (1,000
    stations: 6,100 unknowns, a dense n x n was 300 MB an array)."""

    def __init__(self, n: int, local: dict, global_cols: np.ndarray):
        self.n, self.local, self.g = n, local, np.asarray(global_cols, dtype=np.int64)
        G = len(self.g)
        # per column: local or not, its local variable (a number over all dimensions), its row in
        # its dimension group's stack (variable v, component p: v * d + p), its D and B offsets; or
        # its position among the globals
        self.is_local = np.zeros(n, dtype=bool)
        self.var = np.full(n, -1, dtype=np.int64)
        self.row = np.zeros(n, dtype=np.int64)
        self.dim = np.ones(n, dtype=np.int64)
        self.d_off = np.zeros(n, dtype=np.int64)
        self.b_off = np.zeros(n, dtype=np.int64)
        self.gpos = np.full(n, -1, dtype=np.int64)
        self.gpos[self.g] = np.arange(G)
        self.offsets = {}
        off = n_vars = 0
        for d, idx in local.items():
            m = len(idx)
            self.offsets[d] = (off, off + m * d * d)  # D_d, then B_d
            self.is_local[idx] = True
            self.var[idx] = n_vars + np.arange(m)[:, None]
            self.row[idx] = np.arange(m * d).reshape(m, d)
            self.dim[idx] = d
            self.d_off[idx], self.b_off[idx] = self.offsets[d]
            off += m * d * d + m * d * G
            n_vars += m
        self.g_offset = off
        self.size = off + G * G

    def _index(self, C: np.ndarray, transpose_lg: bool) -> np.ndarray:
        """Flat index of every entry (i, j) of the blocks C (F, k) x C (F, k, k) in the layout. -1:
        two different local variables (never read: no factor touches both) and, with
        ``transpose_lg`` False (the normal matrix keeps B = H_LG only), a (global, local) entry;
        with True, its transpose's place (Sigma_GL = Sigma_LG^T)."""
        ci, cj = C[:, :, None], C[:, None, :]
        li, lj = self.is_local[ci], self.is_local[cj]
        G = len(self.g)
        out = np.full(np.broadcast_shapes(ci.shape, cj.shape), -1, dtype=np.int64)
        same = li & lj & (self.var[ci] == self.var[cj])
        out = np.where(same, self.d_off[ci] + self.row[ci] * self.dim[ci] + self.row[cj] % self.dim[cj], out)
        out = np.where(li & ~lj, self.b_off[ci] + self.row[ci] * G + self.gpos[cj], out)
        if transpose_lg:
            out = np.where(~li & lj, self.b_off[cj] + self.row[cj] * G + self.gpos[ci], out)
        return np.where(~li & ~lj, self.g_offset + self.gpos[ci] * G + self.gpos[cj], out)

    def two_locals(self, C: np.ndarray) -> bool:
        """Whether a factor of the blocks C (F, k) touches two different local variables."""
        v = np.where(self.is_local[C], self.var[C], -1)
        return bool(np.any((v[:, :, None] >= 0) & (v[:, None, :] >= 0) & (v[:, :, None] != v[:, None, :])))

    def h_target(self, C: np.ndarray) -> np.ndarray:
        """Where each entry of the factors' A^T A blocks (F, k, k) is summed (-1: not kept)."""
        return self._index(C, transpose_lg=False)

    def sigma_source(self, C: np.ndarray) -> np.ndarray:
        """Where each entry of the factors' Sigma_x blocks (F, k, k) is read."""
        return self._index(C, transpose_lg=True)

    def solve(self, H_flat: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(Sigma_x in this layout, H^-1 rhs (n,))``: the Schur complement ``S = G - B^T D^-1 B``
        of the local variables (a few dozen globals) is inverted densely, the local blocks one by one
        (batched):

            Sigma_GG = S^-1,   Sigma_LG = -D^-1 B S^-1,   Sigma_LiLi = D_i^-1 + D_i^-1 B_i S^-1 B_i^T D_i^-1.

        Raises GraphcalError when H is not positive definite (a local block or S is not)."""
        G = len(self.g)
        S = H_flat[self.g_offset:].reshape(G, G)
        r_g = rhs[self.g].copy()
        Sigma = np.empty(self.size)
        parts = []
        for d, idx in self.local.items():
            m = len(idx)
            o_d, o_b = self.offsets[d]
            D = H_flat[o_d:o_d + m * d * d].reshape(m, d, d)
            B = H_flat[o_b:o_b + m * d * G].reshape(m, d, G)
            D_inv = _pd_inverse(D)
            D_inv_B = D_inv @ B
            D_inv_r = np.einsum("mij,mj->mi", D_inv, rhs[idx])
            S = S - np.einsum("mdg,mdh->gh", B, D_inv_B)
            r_g -= np.einsum("mdg,md->g", B, D_inv_r)
            parts.append((d, idx, D_inv, D_inv_B, D_inv_r))
        S_inv = _pd_inverse(0.5 * (S + S.T))
        delta = np.empty(self.n)
        d_g = S_inv @ r_g
        Sigma[self.g_offset:] = S_inv.ravel()
        delta[self.g] = d_g
        for d, idx, D_inv, D_inv_B, D_inv_r in parts:
            m = len(idx)
            o_d, o_b = self.offsets[d]
            X = D_inv_B @ S_inv  # (m, d, g) = -Sigma_LG
            Sigma[o_b:o_b + m * d * G] = -X.ravel()
            Sigma[o_d:o_d + m * d * d] = (D_inv + X @ np.swapaxes(D_inv_B, 1, 2)).ravel()
            delta[idx] = D_inv_r - np.einsum("mdg,g->md", D_inv_B, d_g)
        return Sigma, delta


class ConvergedScales(NamedTuple):
    """What :func:`converged_scales` returns."""

    #: statistics of the first iteration: key -> :class:`GroupVariance` (:func:`group_variances`)
    first: dict
    #: key -> cumulative sigma scale of every eligible key relative to the graph's current noise
    scales: dict
    #: the linear solution with the last iteration's weights (a step from ``values``, to start the
    #: re-solve near its optimum); None on the large-graph path
    step: gtsam.VectorValues | None


def converged_scales(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, groups: dict,
                     components: dict | None = None, *, eligible, bounds: dict | None = None,
                     tolerance: float = 1e-3, max_iterations: int = 60,
                     settled: Callable[[dict], bool] | None = None) -> ConvergedScales:
    """Variance components iterated to their fixed point on the graph linearised at ``values``.

    The graph is linearised once; each iteration re-weights the whitened rows with the current
    scales (a single-component group: rows / s; a sum of components: re-whitened with the Cholesky
    factor of ``sum_k s_k^2 Sigma_k``), solves the normal equations (the linear solution moves with
    the weights: residuals are taken there) and applies the update of docs/calibration.md. Only
    the linearisation is held fixed, so the caller re-solves the nonlinear graph with the result and
    checks it with one more call (the first iteration's statistics are exactly
    :func:`group_variances` at ``values``): usually one re-solve and one check suffice.

    The algebra works on each factor's own block (its rows over its variables' columns, stacked
    into arrays of equal shape), never on the whole Jacobian: the normal matrix is summed from
    the blocks and inverted through the Schur complement of the station poses
    (:class:`_ArrowLayout`, at most ``DENSE_MAX_DIM`` unknowns; never an n x n array), and the hat
    matrix is read block by block.

    Args:
        graph, values, groups, components: as :func:`group_variances`.
        eligible: ``GroupVariance -> bool``: whether a group (or component) has enough redundancy for
            its scale to be updated in an iteration; the others keep their scale.
        bounds: key -> (low, high) bounds on a key's cumulative sigma scale (default (0.02, 50)).
        tolerance: stop once every step's scale is within this of 1.
        max_iterations: cap (1: one update, exactly :func:`group_variances` with ``eligible``).
        settled: ``first statistics -> bool``: when True after the first iteration, stop there (the
            caller keeps its noise and only reads the statistics: the iterations of a confirming
            call would be spent for nothing).

    Returns:
        :class:`ConvergedScales`: the first iteration's statistics, the scales, and the linear
        step of the last iteration (with the weights it used; at the fixed point, the optimum of the
        re-weighted graph to first order: ``values.retract(step)`` starts the re-solve there).

    Raises:
        GraphcalError: the graph has an undetermined variable.
    """
    components = components or {}
    bounds = bounds or {}
    if not _is_dense(graph, values):  # large graphs: one update (factor-wise marginals)
        once = group_variances(graph, values, groups, components)
        return ConvergedScales(once, {g: _clip(v.scale, bounds.get(g)) for g, v in once.items() if eligible(v)},
                               None)
    lin = graph.linearize(values)
    blocks, where, columns, factor_keys = _factor_blocks(lin, values, graph.keyVector(), int(graph.size()))
    n = sum(len(c) for c in columns.values())
    local, global_cols = _arrow_split(columns, factor_keys)
    single_idx, multi, multi_idx = _group_rows(graph, groups, components, blocks, where)
    # where each block's entries land: in the normal matrix's blocks and read from Sigma_x's
    # (_ArrowLayout), and in the right-hand side
    order = list(blocks)
    layout = _ArrowLayout(n, local, global_cols)
    if any(layout.two_locals(C) for (_, _, _, C) in blocks.values()):
        raise GraphcalError("noise estimation: a factor touches two local variables")  # _arrow_split prevents it
    h_tgt = np.concatenate([layout.h_target(blocks[key][3]).ravel() for key in order])
    h_keep = h_tgt >= 0
    h_tgt = h_tgt[h_keep]
    sigma_src = {key: layout.sigma_source(C) for key, (_, _, _, C) in blocks.items()}
    g_idx = np.concatenate([blocks[key][3].ravel() for key in order])

    scale = {g: 1.0 for g in single_idx}
    for g, m in multi.items():
        scale.update({f"{g}/{k}": 1.0 for k in m["names"]})
    A = {key: A0.copy() for key, (_, A0, _, _) in blocks.items()}
    b = {key: b0.copy() for key, (_, _, b0, _) in blocks.items()}
    first: dict = {}
    updated: set = set()
    split: dict[str, bool] = {}
    for it in range(max_iterations):
        Linv = _reweight(blocks, single_idx, multi, multi_idx, scale, A, b)
        # normal equations summed from the blocks (a factor touches a few unknowns)
        AtA = np.concatenate([(np.swapaxes(A[key], 1, 2) @ A[key]).ravel() for key in order])
        Atb = np.concatenate([np.einsum("frk,fr->fk", A[key], b[key]).ravel() for key in order])
        H_blocks = np.bincount(h_tgt, weights=AtA[h_keep], minlength=layout.size)
        Sigma_x, delta = layout.solve(H_blocks, np.bincount(g_idx, weights=Atb, minlength=n))
        # whitened residuals at the re-weighted linear solution, and the hat matrix A Sigma_x A^T
        # of each factor (its diagonal block)
        e, hat = {}, {}
        for key, (_, _, _, C) in blocks.items():
            A_f = A[key]
            e[key] = b[key] - np.einsum("frk,fk->fr", A_f, delta[C])
            hat[key] = A_f @ Sigma_x[sigma_src[key]] @ np.swapaxes(A_f, 1, 2)
        stats, split = _group_statistics(single_idx, multi, e, hat, Linv, scale, split)
        if it == 0:
            first = stats
            if settled is not None and settled(first):
                break  # no scale updated: the caller keeps its noise
        worst = 0.0
        for key, v in stats.items():
            if key in scale and eligible(v):
                new = _clip(scale[key] * v.scale, bounds.get(key))
                worst = max(worst, abs(new / scale[key] - 1.0))
                scale[key] = new
                updated.add(key)
        if worst <= tolerance:
            break
    step = gtsam.VectorValues()
    for k, cols in columns.items():
        step.insert(k, delta[cols[0]:cols[-1] + 1])
    return ConvergedScales(first, {key: scale[key] for key in updated}, step)


def _group_rows(graph: gtsam.NonlinearFactorGraph, groups: dict, components: dict, blocks: dict,
                where: dict) -> tuple[dict, dict, dict]:
    """Where each noise group's rows sit in the factor blocks of :func:`_factor_blocks`
    (``where``: factor index -> (block key, position)), for :func:`converged_scales`.

    Returns ``single_idx`` (group -> block key -> positions of its factors, groups of one
    component), ``multi`` (group -> its components' names, whitening matrices, covariances
    ``S[k]`` (F, r, r) in the factors' error units, and its unwhitened rows ``raw`` per block) and
    ``multi_idx`` (group -> block key -> (positions, indices among the group's factors)).
    """
    single: dict[str, list] = {}
    multi: dict[str, dict] = {}
    for i, g in groups.items():
        key, pos = where[i]
        comps = components.get(i)
        if not comps:
            single.setdefault(g, []).append((key, pos))
            continue
        m = multi.setdefault(g, {"names": list(comps), "where": [], "W": [], "S": {k: [] for k in comps}})
        if list(comps) != m["names"]:
            raise GraphcalError(f"noise estimation: factors of group {g} have different components")
        m["where"].append((key, pos))
        m["W"].append(whitening_matrix(graph.at(i)))
        for k, Sk in comps.items():
            m["S"][k].append(np.asarray(Sk, dtype=float))
    for g, m in multi.items():
        m["S"] = {k: np.stack(v) for k, v in m["S"].items()}  # (F, r, r)
        m["W0_inv"] = np.linalg.inv(np.stack(m["W"]))  # the linearisation's whitening, undone
    # index of each single group's factors within their blocks
    single_idx = {g: {} for g in single}
    for g, locs in single.items():
        for key, pos in locs:
            single_idx[g].setdefault(key, []).append(pos)
    single_idx = {g: {key: np.asarray(p) for key, p in d.items()} for g, d in single_idx.items()}
    multi_idx = {}
    for g, m in multi.items():
        d: dict = {}
        for j, (key, pos) in enumerate(m["where"]):
            d.setdefault(key, ([], []))
            d[key][0].append(pos)
            d[key][1].append(j)
        multi_idx[g] = {key: (np.asarray(p), np.asarray(j)) for key, (p, j) in d.items()}
        # unwhitened rows, per block (a group's factors may span several unknowns, e.g. legs with and
        # without estimated parameters): (F_b, r, k_b) and (F_b, r)
        m["raw"] = {key: (m["W0_inv"][j] @ blocks[key][1][pos], np.einsum("fij,fj->fi", m["W0_inv"][j], blocks[key][2][pos]))
                    for key, (pos, j) in multi_idx[g].items()}
    return single_idx, multi, multi_idx


def _reweight(blocks: dict, single_idx: dict, multi: dict, multi_idx: dict, scale: dict, A: dict, b: dict) -> dict:
    """The whitened rows ``A``, ``b`` (block key -> arrays, written in place) re-weighted with the
    current ``scale`` (key -> sigma scale): a single-component group's rows divided by its scale, a
    sum of components re-whitened with the Cholesky factor of ``sum_k s_k^2 Sigma_k``. Returns group
    -> the inverse Cholesky factors (F, r, r) used."""
    for g, d in single_idx.items():
        for key, pos in d.items():
            A[key][pos] = blocks[key][1][pos] / scale[g]
            b[key][pos] = blocks[key][2][pos] / scale[g]
    Linv = {}
    for g, m in multi.items():
        Sig = sum(scale[f"{g}/{k}"] ** 2 * m["S"][k] for k in m["names"])
        Linv[g] = np.linalg.inv(np.linalg.cholesky(Sig))
        for key, (pos, j) in multi_idx[g].items():
            A_raw, b_raw = m["raw"][key]
            A[key][pos] = Linv[g][j] @ A_raw
            b[key][pos] = np.einsum("fij,fj->fi", Linv[g][j], b_raw)
    return Linv


def _group_statistics(single_idx: dict, multi: dict, e: dict, hat: dict, Linv: dict, scale: dict,
                      split: dict) -> tuple[dict, dict]:
    """Each group's (and component's) :class:`GroupVariance` from the whitened residuals ``e`` and
    the hat-matrix blocks ``hat`` (block key -> arrays) at the re-weighted linear solution, and
    ``split`` (group -> whether its components are estimated apart) with the groups decided now
    added."""
    split = dict(split)
    stats: dict[str, GroupVariance] = {}
    for g, d in single_idx.items():
        chi2 = red = 0.0
        rows = 0
        for key, pos in d.items():
            ef = e[key][pos]
            h = np.einsum("fii->fi", hat[key][pos])
            chi2 += float(np.einsum("fr,fr->", ef, ef))
            red += float(np.clip(1.0 - h, 0.0, 1.0).sum())
            rows += ef.size
        stats[g] = GroupVariance(g, chi2, red, rows)
    for g, m in multi.items():
        names, locs = m["names"], m["where"]
        R = np.eye(locs[0][0][0]) - np.stack(  # r rows, equal within a group
            [hat[key][pos] for key, pos in locs])
        ef = np.stack([e[key][pos] for key, pos in locs])
        C = {k: Linv[g] @ (scale[f"{g}/{k}"] ** 2 * m["S"][k]) @ np.swapaxes(Linv[g], 1, 2) for k in names}
        RC = {k: R @ C[k] for k in names}
        q = np.array([float(np.einsum("fi,fij,fj->", ef, C[k], ef)) for k in names])
        Nm = np.array([[float(np.einsum("fij,fji->", RC[k], RC[l])) for l in names] for k in names])
        # decided at the ratio the call was given, kept for the call: a first step may overshoot
        # through a ratio where the split looks undetermined (a known mixture then froze at a
        # joint scale of 0.33 instead of its fixed point 0.46)
        if g not in split:
            split[g] = split_determined(Nm)
        red = [float(np.maximum(np.trace(RC[k], axis1=1, axis2=2), 0.0).sum()) for k in names]
        stats.update(helmert_components(g, names, Nm, q, red, ef.size, split[g]))
    return stats, split


def _clip(s: float, bound) -> float:
    lo, hi = bound if bound is not None else (0.02, 50.0)
    return float(min(max(s, lo), hi))


# ----------------------------------------------------------------------------- the calibration's noise groups
#: re-solves of the calibration graph with re-estimated noise (calibrate's outer loop)
VCE_ROUNDS = 8
#: iterations of the variance components on one linearisation, and their stopping tolerance
VCE_INNER_ITERATIONS = 60
VCE_INNER_TOLERANCE = 1e-3
#: stop once every scale is within this of 1
VCE_TOLERANCE = 0.02
#: a group's sigma is re-estimated only with at least this much redundancy (dof), and this share
#: of its rows: below it the residuals say little about the noise (e.g. the planes, whose errors the
#: body poses can absorb almost entirely)
VCE_MIN_REDUNDANCY = 3.0
VCE_MIN_REDUNDANCY_SHARE = 0.05
#: bounds on a re-estimated sigma relative to its default, and absolute floors (SI)
VCE_SCALE_BOUNDS = (0.02, 50.0)
VCE_FLOOR = {"sigma_joint_rad": 1e-6, "sigma_contact_m": 1e-6, "sigma_ground_m": 1e-6, "sigma_imu_rad": 1e-5,
             "sigma_commanded_rad": 1e-5, "sigma_commanded_m": 5e-5}


#: option fields scaled by each noise group's variance component
_GROUP_FIELDS = {"stance_foot/joint": ("sigma_joint_rad",), "stance_foot/contact": ("sigma_contact_m",),
                 "foot_on_ground": ("sigma_ground_m",), "imu": ("sigma_imu_rad",),
                 "commanded": ("sigma_commanded_rad", "sigma_commanded_m")}


class NoiseUpdate(NamedTuple):
    """One variance-component update at a solution (:func:`noise_update`)."""

    #: options with every eligible group's sigma multiplied by its converged scale
    options: CalibrationOptions
    #: False once every eligible scale is within ``VCE_TOLERANCE`` of 1 (a scale held at its bound
    #: is no change)
    changed: bool
    #: the linear step from the solution with the new weights (None on the large-graph path)
    step: "gtsam.VectorValues | None"
    #: group -> :class:`~graphcal.calibration.noise_estimation.GroupVariance` at the solution with
    #: the options given (the statistics a report on the noise model reads)
    stats: dict


def _vce_eligible(v) -> bool:
    """Whether a group's residuals carry enough redundancy for its sigma to be re-estimated."""
    return v.redundancy >= max(VCE_MIN_REDUNDANCY, VCE_MIN_REDUNDANCY_SHARE * v.rows)


#: the last :func:`noise_update` (its arguments, its result): asked again for the same solution
#: (the same problem and values objects, equal options), it is not computed again
_LAST_UPDATE: list = []


def noise_update(options: CalibrationOptions, problem: CalibrationProblem, values, *,
                 converge: bool = True) -> NoiseUpdate:
    """Every noise group's sigma multiplied by its variance-component scale
    (noise_estimation.py) at ``values``. ``converge``: iterate the scales to their fixed point on
    the graph linearised at ``values``
    (:func:`~graphcal.calibration.noise_estimation.converged_scales`); False: one update. The same
    update asked again (the same ``problem`` and ``values`` objects, equal options) is the last one
    returned, not computed again (diagnose's re-check learns the noise, then judges it there)."""
    import dataclasses

    for was, update in _LAST_UPDATE:  # the same update asked again (diagnose's re-check, then its verdict)
        if was[1] is problem and was[2] is values and was[0] == options and was[3] == converge:
            return update
    bounds = {g: (max(VCE_SCALE_BOUNDS[0], *(VCE_FLOOR[n] / getattr(options, n) for n in names)), VCE_SCALE_BOUNDS[1])
              for g, names in _GROUP_FIELDS.items()}

    def changes(stats: dict) -> bool:
        # a scale held at its bound (a sigma at its floor) is no change
        return any(abs(float(np.clip(v.scale, *bounds.get(g, VCE_SCALE_BOUNDS))) - 1.0) > VCE_TOLERANCE
                   for g, v in stats.items() if _vce_eligible(v))

    # converging, a first update that changes nothing ends the call: calibrate then keeps its noise
    # and reads only the statistics (with converge=False the one update is returned as it is)
    first, scale, step = converged_scales(problem.graph, values, problem.factor_groups, problem.factor_components,
                                          eligible=_vce_eligible, bounds=bounds, tolerance=VCE_INNER_TOLERANCE,
                                          max_iterations=VCE_INNER_ITERATIONS if converge else 1,
                                          settled=(lambda stats: not changes(stats)) if converge else None)
    changed = changes(first)
    update = {}
    for group, names in _GROUP_FIELDS.items():
        if group in scale:
            for name in names:
                update[name] = max(getattr(options, name) * scale[group], VCE_FLOOR[name])
    planes = dict(options.plane_sigma_scales)
    for group, s in scale.items():
        if group.startswith("plane:"):
            sensor = group.split(":", 1)[1]
            planes[sensor] = planes.get(sensor, 1.0) * s
    update["plane_sigma_scales"] = tuple(sorted(planes.items()))
    out = NoiseUpdate(dataclasses.replace(options, **update), changed, step, first)
    _LAST_UPDATE[:] = [((options, problem, values, converge), out)]
    return out


def rescaled_options(options: CalibrationOptions, problem: CalibrationProblem, values, *,
                     converge: bool = True) -> tuple[CalibrationOptions, bool, "gtsam.VectorValues | None"]:
    """(options, changed, step) of :func:`noise_update`."""
    u = noise_update(options, problem, values, converge=converge)
    return u.options, u.changed, u.step


#: a held group whose residuals are this improbable under its sigma (chi-square upper tail) makes
#: calibrate warn that the covariance may be too small
NOISE_TOO_SMALL_P = 0.01


#: a learned plane noise scale above this makes calibrate warn: flat floors stay below it, uneven
#: ground goes above (the learned scales: docs/calibration.md)
PLANE_SCALE_WARN = 1.5


def noise_groups_report(stats: dict, options: CalibrationOptions, *,
                        given: bool = False) -> tuple[tuple[NoiseGroupEstimate, ...], list[str]]:
    """How each noise group's sigma was set, from the variance-component statistics ``stats`` at
    the final solution with the final ``options`` (:class:`NoiseUpdate` ``stats``), and a warning
    for every group whose residuals say its sigma is too small (chi-square upper tail below
    :data:`NOISE_TOO_SMALL_P`) but which the estimation could not correct (too few dof, or the
    rounds ran out): then the reported covariance may be too small.

    A group held with residuals *below* its sigma (``data_scale`` < 1, e.g. the feet's height
    above a perfectly flat simulated floor: 6 rows, under 3 dof) only makes the covariance
    conservative; it is reported, not warned about (docs/calibration.md measures its effect). A
    learned plane noise scale above :data:`PLANE_SCALE_WARN` is warned about: it is what uneven
    ground looks like to this model (and a sensor noisier than its noise model).

    ``given``: the noise was not learned (``--noise-from``, or the defaults): every group's status
    is ``given``, and nothing is warned about here: one group's residuals above its sigma does not
    make the covariance too small when others are conservative (docs/incremental.md, "Noise from
    an earlier calibration");
    :func:`~graphcal.calibration.noise_check.given_noise_check` scales and warns per sensor."""
    from graphcal import stats as chi2_dist

    fields_of = dict(_GROUP_FIELDS)
    out, warnings = [], []
    for key, v in sorted(stats.items()):
        if key in fields_of:
            names = fields_of[key]
            fields = tuple((n, float(getattr(options, n))) for n in names)
        elif key.startswith("plane:"):
            sensor = key.split(":", 1)[1]
            names = ()
            fields = ((f"plane_scale:{sensor}", float(options.plane_scale(sensor))),)
        else:  # not a group whose sigma calibrate re-estimates
            continue
        dof = float(v.redundancy)
        scale = float(v.scale)
        # chi2 / dof = scale^2 for a single group; for one component of a sum, Helmert's theta = scale^2
        # times its dof is the same test to first order
        p_high = float(chi2_dist.sf(scale * scale * dof, dof)) if dof > 1e-9 else float("nan")
        at_floor = bool(names) and all(getattr(options, n) <= VCE_FLOOR[n] * (1 + 1e-9) for n in names)
        if given:
            status = "given"
        elif not _vce_eligible(v):
            status = "too few dof"
        elif abs(scale - 1.0) <= VCE_TOLERANCE:
            status = "learned"
        elif at_floor and scale < 1.0:
            status = "at floor"
        else:
            status = "not converged"
        out.append(NoiseGroupEstimate(key, fields, status, dof, int(v.rows), scale, p_high,
                                      tuple(getattr(v, "shared_with", ()))))
        if given:
            continue
        if key.startswith("plane:") and fields[0][1] > PLANE_SCALE_WARN:
            warnings.append(
                f"{key.split(':', 1)[1]}: the planes scatter {fields[0][1]:.2g} times more than the point noise of "
                "their fits predicts (learned plane noise scale): the sensor is noisier than its noise model, "
                "or the ground is not one plane (bumps: give --ground-roughness-mm; an offset per session or a "
                "tilted floor: graphcal diagnose). On uneven ground the reported covariance is too small: the "
                "scale treats the unevenness as independent noise per station")
        # only residuals above their sigma make the covariance too small (with ~0 dof the chi-square
        # puts all its mass at 0 and any positive statistic has a tiny p: 1 station gave 'residuals
        # 0.058 times its sigma ... may be too small')
        if status != "learned" and scale > 1.0 and p_high < NOISE_TOO_SMALL_P:
            warnings.append(
                f"noise group {key} ({status}, {dof:.1f} dof): its residuals are {scale:.2g} times its sigma "
                f"(chi-square p = {p_high:.2g}); the reported covariance may be too small")
    return tuple(out), warnings
