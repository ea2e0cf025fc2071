"""Variance-component estimation: the sigma of each factor group, learned from the residuals.

The defaults of :class:`~graphcal.calibration.graph.CalibrationOptions` (3 mm per foot, 0.5 deg
IMU, ...) are guesses about a robot we have not seen. If they are too large the covariance is too
pessimistic; too small and it is overconfident. Helmert/Förstner variance-component estimation fixes
that from the data: at the solution, for every group g of factors,

    s_g^2 = sum_{rows in g} e_i^2 / sum_{rows in g} r_i,

with e_i the whitened residual rows and r_i = 1 - h_i their redundancy numbers, h_i the diagonal of
the hat matrix A (A^T A)^-1 A^T of the whitened linear system (how much of row i the solution
absorbs). ``sum r_i`` is the degrees of freedom the group contributes; under a correct noise model
E[s_g^2] = 1. Each group's sigma is multiplied by s_g and the graph is solved again; two or three
rounds converge. h_i comes from the joint marginal covariance of the factor's variables: read from
one dense inverse of the information matrix for graphs of up to ``DENSE_MAX_DIM`` unknowns (a
calibration of a few hundred stations), otherwise from ``gtsam.Marginals`` factor by factor (cost
growing with the number of factors, not cubically).

A group whose covariance is a sum of components, ``Sigma = sum_k Sigma_k`` (a foot: joint noise
through the leg Jacobian plus isotropic contact noise), gets one scale per component (Förstner's
iterative estimator): in the factor's whitened space ``C_k = L^-1 Sigma_k L^-T`` (``Sigma = L L^T``),
``R = I - A Sigma_x A^T`` its redundancy matrix and ``b`` its whitened residual,

    s_k^2 = sum_factors b^T C_k b / sum_factors tr(R C_k),

which reduces to the formula above for a single component (``C = I``). Components that the data
tell apart only by direction converge slowly with that update, so the components of one group are
solved together with Helmert's equations instead, ``sum_l tr(R C_k R C_l) theta_l = sum b^T C_k b``
(summed over the group's factors, each factor's own block of R), and ``s_k^2 = theta_k``.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from ..errors import GraphcalError


@dataclass(frozen=True)
class GroupVariance:
    """One noise group at a solution: sum of squared whitened residuals, its redundancy (dof), rows."""

    group: str
    chi2: float
    redundancy: float
    rows: int

    helmert_theta: float | None = None

    @property
    def scale(self) -> float:
        """The factor to apply to the group's sigma (1 = the noise model fits)."""
        if self.helmert_theta is not None:
            return float(np.sqrt(max(self.helmert_theta, 1e-8)))
        if self.redundancy <= 1e-6:
            return 1.0
        return float(np.sqrt(self.chi2 / self.redundancy))


#: graphs with at most this many unknowns get their joint marginals from one dense inverse
DENSE_MAX_DIM = 3000


def _joint_covariance_reader(graph, values, lin):
    """A function keys -> joint marginal covariance (blocks in the order of ``keys``)."""
    keys = sorted(int(k) for k in graph.keyVector())
    dims = {int(k): int(d) for k, d in values.dims().items()}
    if sum(dims[k] for k in keys) <= DENSE_MAX_DIM:
        from ..solvers.covariance import dense_covariance

        cov, null, offsets = dense_covariance(lin, keys, dims)
        if null.shape[1]:
            raise GraphcalError("noise estimation: the graph has an undetermined variable")

        def dense(ks):
            idx = np.concatenate([np.arange(offsets[int(k)], offsets[int(k)] + dims[int(k)]) for k in ks])
            return cov[np.ix_(idx, idx)]

        return dense
    try:
        marginals = gtsam.Marginals(graph, values)
    except RuntimeError as exc:
        raise GraphcalError(f"noise estimation: the graph has an undetermined variable ({exc})") from None

    def sparse(ks):
        jm = marginals.jointMarginalCovariance(gtsam.KeyVector(ks))
        return np.block([[np.asarray(jm.at(a, c)) for c in ks] for a in ks])

    return sparse


def group_variances(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, groups: dict,
                    components: dict | None = None) -> dict:
    """group (or ``group/component``) -> :class:`GroupVariance` at ``values`` (module docstring).

    Args:
        groups: factor index -> group name.
        components: factor index -> {component name: covariance Sigma_k (unwhitened, the factor's
            current value)} for factors whose covariance is a sum of components; their results are
            keyed ``group/component``.
    """
    components = components or {}
    lin = graph.linearize(values)
    joint = _joint_covariance_reader(graph, values, lin)
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
        total = sum(comps.values())
        L_inv = np.linalg.inv(np.linalg.cholesky(total))
        names, N, q = helmert.setdefault(g, (list(comps), {}, {}))
        C = {name: L_inv @ Sk @ L_inv.T for name, Sk in comps.items()}
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
        theta = np.linalg.lstsq(Nm, qv, rcond=None)[0]
        for k, th in zip(names, theta):
            key = f"{g}/{k}"
            out[key] = GroupVariance(key, out[key].chi2, out[key].redundancy, out[key].rows, float(th))
    return out
