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
rounds converge. h_i comes from the joint marginal covariance of the factor's variables
(``gtsam.Marginals``), so the cost grows with the number of factors, not with a dense inverse.
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

    @property
    def scale(self) -> float:
        """The factor to apply to the group's sigma (1 = the noise model fits)."""
        if self.redundancy <= 1e-6:
            return 1.0
        return float(np.sqrt(self.chi2 / self.redundancy))


def group_variances(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, groups: dict) -> dict:
    """group -> :class:`GroupVariance` at ``values`` (see the module docstring)."""
    try:
        marginals = gtsam.Marginals(graph, values)
    except RuntimeError as exc:
        raise GraphcalError(f"noise estimation: the graph has an undetermined variable ({exc})") from None
    lin = graph.linearize(values)
    acc: dict[str, list[float]] = {}
    cache: dict[tuple, np.ndarray] = {}
    for i, g in groups.items():
        f = lin.at(i)
        A, b = f.jacobian()
        keys = list(f.keys())
        sig = cache.get(tuple(keys))
        if sig is None:
            jm = marginals.jointMarginalCovariance(gtsam.KeyVector(keys))
            sig = np.block([[np.asarray(jm.at(a, c)) for c in keys] for a in keys])
            cache[tuple(keys)] = sig
        h = np.einsum("ij,jk,ik->i", A, sig, A)
        r = np.clip(1.0 - h, 0.0, 1.0)
        a = acc.setdefault(g, [0.0, 0.0, 0])
        a[0] += float(b @ b)
        a[1] += float(r.sum())
        a[2] += len(b)
    return {g: GroupVariance(g, a[0], a[1], a[2]) for g, a in acc.items()}
