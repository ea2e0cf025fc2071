"""Levenberg–Marquardt driven from Python over a gtsam factor graph, and per-factor chi-square.

Why not ``gtsam.LevenbergMarquardtOptimizer``: a Python ``CustomFactor`` inside gtsam's C++
optimizers receives a fresh copy of the whole ``Values`` at every callback. Here the loop runs in
Python on a ``Values`` it owns, so pybind11 passes it by reference: same optimum, no copies.
:func:`solve_lm` damps with gtsam's default ``lambda I`` in whitened units, solves by multifrontal
Cholesky (QR when gtsam calls the damped system indeterminate), and first factors the undamped
system once: an under-constrained graph raises :class:`UnderdeterminedError` naming the variable
(``"S0"``). :func:`whitened_errors` gives each factor's chi-square before the robust loss. Units
are those of the factors; errors are gtsam's ``graph.error`` (0.5 sum of squared whitened rows).

The loop, the stopping rule and the rank test: docs/solvers.md, "2. Levenberg–Marquardt from Python".
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np

from graphcal.errors import GraphcalError

__all__ = [
    "LMResult",
    "UnderdeterminedError",
    "solve_lm",
    "whitened_errors",
    "outlier_factors",
    "key_name",
    "indeterminate_key",
    "diag_information",
]

#: Meaning of the symbol letters of graphcal's graphs (factors/keys.py).
_KEY_MEANING = {
    "x": "body pose T_world_body of station",
    "s": "sensor extrinsic T_body_sensor",
    "f": "planted foot p_world_foot",
    "l": "kinematic parameters of leg",
    "g": "ground plane",
    "m": "IMU mounting rotation",
}

_INDETERMINATE_RE = re.compile(r"indetermina\w*\s+linear\s+system", re.IGNORECASE)
_KEY_RE = re.compile(r"near\s+variable\s+(\d+)", re.IGNORECASE)

#: Relative pivot |R_jj| / ||A_j|| of the whitened Jacobian below which a direction counts as
#: undetermined in the QR rank test (a gauge freedom gives ~1e-16, an ill-conditioned but
#: determined clique typically > 1e-6).
RELATIVE_PIVOT_TOL = 1e-9

#: Relative round-off of one factor's contribution to ``graph.error``: changes of the error
#: below ``_ROUNDOFF * number_of_factors * error`` are noise (4 machine epsilons per factor).
_ROUNDOFF = 4.0 * np.finfo(float).eps


class UnderdeterminedError(GraphcalError):
    """The graph does not determine a variable (or a combination of variables).

    Attributes:
        key: the gtsam key near which elimination found no information (may be None).
        name: the key in graphcal's notation, e.g. ``"S0"``.
    """

    def __init__(self, message: str, key: int | None = None):
        super().__init__(message)
        self.key = key
        self.name = key_name(key) if key is not None else None


@dataclass(frozen=True, eq=False)
class LMResult:
    """What :func:`solve_lm` returns.

    Attributes:
        values: the optimum (a new ``gtsam.Values``; the input is not modified).
        error_initial, error_final: ``graph.error`` = 0.5 * sum of squared whitened residuals
            (after the robust loss, as gtsam defines it) at the start and at the end.
        iterations: number of linearisations (outer iterations) performed.
        converged: True when a stopping tolerance was met (not merely max_iterations or lambda).
        lambda_final: the damping when the loop stopped.
        message: why the loop stopped, in words.
    """

    values: gtsam.Values
    error_initial: float
    error_final: float
    iterations: int
    converged: bool
    lambda_final: float
    message: str


# ----------------------------------------------------------------------------- key names
def key_name(key: int) -> str:
    """A gtsam key in graphcal's notation: ``S(0)`` -> ``"S0"``, a plain integer key -> ``"5"``."""
    key = int(key)
    sym = gtsam.Symbol(key)
    c = sym.chr()
    if 32 < c < 127 and chr(c).isalpha():
        return f"{chr(c).upper()}{sym.index()}"
    return str(key)


def _describe_key(key: int) -> str:
    name = key_name(key)
    sym = gtsam.Symbol(int(key))
    c = sym.chr()
    meaning = _KEY_MEANING.get(chr(c).lower()) if 32 < c < 127 else None
    return f"{name} ({meaning} {sym.index()})" if meaning else name


def indeterminate_key(exc: BaseException) -> int | None:
    """The key of gtsam's "Indeterminant linear system" exception, or None when ``exc`` is not one.
    Returns -1 when it is one but names no key."""
    text = str(exc)
    if not _INDETERMINATE_RE.search(text):
        return None
    m = _KEY_RE.search(text)
    return int(m.group(1)) if m else -1


def _underdetermined(key: int | None, detail: str) -> UnderdeterminedError:
    if key is None or key < 0:
        return UnderdeterminedError(f"the factor graph does not determine every variable: {detail}")
    return UnderdeterminedError(
        f"the factor graph does not determine variable {_describe_key(key)}: {detail}. Add the "
        "measurements that observe it or a prior on it", key)


# ----------------------------------------------------------------------------- linear algebra
def _ordering(lin: gtsam.GaussianFactorGraph) -> gtsam.Ordering:
    return gtsam.Ordering.ColamdGaussianFactorGraph(lin)


def diag_information(lin: gtsam.GaussianFactorGraph, dims: dict[int, int]) -> dict[int, np.ndarray]:
    """Per variable, the diagonal of A^T A of the whitened linear system (column norms squared).

    ``lin``: a graph linearised at a solution (whitened rows); ``dims``: key -> its tangent
    dimension. Returns key -> (dim,) in the units of the whitened information (1 / tangent unit^2)."""
    out = {k: np.zeros(d) for k, d in dims.items()}
    for i in range(lin.size()):
        f = lin.at(i)
        if f is None:
            continue
        info = f.information()
        off = 0
        for k in f.keys():
            d = dims[k]
            out[k] += np.diag(info)[off : off + d]
            off += d
    return out


def _qr_rank_test(lin: gtsam.GaussianFactorGraph, ordering: gtsam.Ordering, dims: dict[int, int]) -> int | None:
    """Scale-invariant rank test by sequential QR: the key of the first variable whose pivot is
    negligible relative to its own column norm, or None when every direction is determined.
    Raises UnderdeterminedError when gtsam's QR itself finds an empty column."""
    try:
        bn = lin.eliminateSequential(ordering, gtsam.EliminateQR)
    except RuntimeError as e:
        k = indeterminate_key(e)
        if k is None:
            raise
        raise _underdetermined(k, "elimination found no information left for it (a free variable, or a "
                                  "free combination with its neighbours such as a missing prior)") from None
    colnorm = {k: np.sqrt(v) for k, v in diag_information(lin, dims).items()}
    for i in range(bn.size()):
        c = bn.at(i)
        R = np.asarray(c.R())
        keys = list(c.keys())
        off = 0
        piv = np.abs(np.diag(R))
        for k in keys[: _n_frontals(c, dims)]:
            d = dims[k]
            p = piv[off : off + d]
            cn = colnorm[k]
            if np.any(~np.isfinite(p)) or np.any(p <= RELATIVE_PIVOT_TOL * np.maximum(cn, 1e-300)):
                return k
            off += d
    return None


def _n_frontals(cond: gtsam.GaussianConditional, dims: dict[int, int]) -> int:
    """Number of frontal keys of a conditional (its R is square over them)."""
    n = np.asarray(cond.R()).shape[0]
    total, count = 0, 0
    for k in cond.keys():
        if total >= n:
            break
        total += dims[k]
        count += 1
    return count


def _check_determined(lin: gtsam.GaussianFactorGraph, ordering: gtsam.Ordering, dims: dict[int, int]) -> None:
    """Raise UnderdeterminedError when the undamped linear system is rank deficient."""
    try:
        lin.optimize(ordering)
        return
    except RuntimeError as e:
        k = indeterminate_key(e)
        if k is None:
            raise
    # gtsam's Cholesky also refuses ill-conditioned cliques: decide by a scale-invariant QR test
    bad = _qr_rank_test(lin, ordering, dims)
    if bad is not None:
        raise _underdetermined(bad, "the linear system is rank deficient there (a free direction of it "
                                    "or of a combination with its neighbours, e.g. a missing prior or a "
                                    "gauge freedom)")


class _Damping:
    """Caches the lambda*I damping factors (lambda takes few distinct values)."""

    def __init__(self, dims: dict[int, int]):
        self.items = [(k, d, gtsam.noiseModel.Unit.Create(d), np.zeros(d)) for k, d in dims.items()]
        self.cache: dict[float, gtsam.GaussianFactorGraph] = {}

    def graph(self, lam: float) -> gtsam.GaussianFactorGraph:
        g = self.cache.get(lam)
        if g is None:
            if len(self.cache) > 16:
                self.cache.clear()
            g = gtsam.GaussianFactorGraph()
            s = math.sqrt(lam)
            scaled = {d: s * np.eye(d) for d in {d for _, d, _, _ in self.items}}
            for k, d, model, zero in self.items:
                g.push_back(gtsam.JacobianFactor(k, scaled[d], zero, model))
            self.cache[lam] = g
        return g


def _solve_damped(lin, damping: _Damping, lam: float, ordering) -> gtsam.VectorValues | None:
    damped = gtsam.GaussianFactorGraph()
    damped.push_back(lin)
    damped.push_back(damping.graph(lam))
    try:
        return damped.optimize(ordering)
    except RuntimeError as e:
        if indeterminate_key(e) is None:
            raise
    try:
        return damped.optimize(ordering, gtsam.EliminateQR)
    except RuntimeError as e:
        if indeterminate_key(e) is None:
            raise
    return None


# ----------------------------------------------------------------------------- LM
def solve_lm(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    *,
    max_iterations: int = 100,
    relative_tol: float = 1e-9,
    absolute_tol: float = 1e-12,
    lambda_initial: float = 1e-3,
    lambda_factor: float = 10.0,
    lambda_upper_bound: float = 1e10,
    progress: Callable[[int, float], None] | None = None,
    check_determined: bool = True,
) -> LMResult:
    """Levenberg–Marquardt over ``graph`` from ``initial``, driven from Python (see module doc).

    Args:
        graph: the nonlinear factor graph (built-in and/or Python ``CustomFactor`` factors; robust
            noise models are handled by ``graph.linearize``).
        initial: initial values of every variable of the graph (not modified).
        max_iterations: maximum number of linearisations.
        relative_tol, absolute_tol: stop when an accepted step decreases the error by less than
            ``relative_tol * error`` or ``absolute_tol``.
        lambda_initial, lambda_factor: damping start and its multiplier on reject / divisor on accept.
        lambda_upper_bound: give up (``converged=False``) when the damping exceeds this.
        progress: called as ``progress(iteration, error)`` after every linearisation's accepted
            step (iteration 0 with the initial error).
        check_determined: factor the undamped system once first and raise
            :class:`UnderdeterminedError` (a GraphcalError) naming the free variable when the
            graph does not determine every variable. Switch off only for graphs known to be
            determined (it costs one extra elimination).

    Returns:
        :class:`LMResult`.

    Raises:
        GraphcalError: a variable of the graph is missing from ``initial``, or the graph does not
            determine a variable (:class:`UnderdeterminedError`, message names it, e.g. ``S0``).
    """
    keys_graph = set(graph.keyVector())
    missing = [k for k in keys_graph if not initial.exists(k)]
    if missing:
        names = ", ".join(key_name(k) for k in sorted(missing)[:5])
        raise GraphcalError(f"initial values lack {len(missing)} variable(s) of the graph: {names}")
    values = gtsam.Values(initial)  # Python-owned copy: never modify the caller's
    error = float(graph.error(values))
    error_initial = error
    if not math.isfinite(error):
        raise GraphcalError(f"the graph error at the initial values is {error}")
    if progress is not None:
        progress(0, error)
    if graph.size() == 0 or not keys_graph:
        return LMResult(values, error, error, 0, True, lambda_initial, "empty graph")

    dims = {k: d for k, d in values.dims().items() if k in keys_graph}
    n_factors = max(int(graph.size()), 1)
    damping = _Damping(dims)
    lam = float(lambda_initial)
    ordering = None
    converged, message = False, "maximum iterations reached"
    iterations = 0
    while iterations < max_iterations:
        lin = graph.linearize(values)
        iterations += 1
        if ordering is None:
            ordering = _ordering(lin)
            if check_determined:
                _check_determined(lin, ordering, dims)
        stop = False
        while True:
            delta = _solve_damped(lin, damping, lam, ordering)
            new_values = new_error = None
            if delta is not None:
                new_values = values.retract(delta)
                new_error = float(graph.error(new_values))
            # tolerance, never below the round-off of summing the factor errors
            tol = max(absolute_tol, relative_tol * error, _ROUNDOFF * n_factors * error)
            if new_error is not None and math.isfinite(new_error) and new_error <= error:
                decrease = error - new_error
                values, error = new_values, new_error
                lam = lam / lambda_factor
                if decrease <= tol:
                    converged, stop = True, True
                    message = f"converged: error decrease {decrease:.3g} below tolerance {tol:.3g}"
                break
            if new_error is not None and math.isfinite(new_error) and new_error - error <= tol:
                converged, stop = True, True
                message = f"converged: no step changes the error by more than {tol:.3g}"
                break
            lam = lam * lambda_factor
            if lam > lambda_upper_bound:
                stop = True
                message = f"stopped: lambda exceeded {lambda_upper_bound:g} without reducing the error"
                break
        if progress is not None:
            progress(iterations, error)
        if stop:
            break
    return LMResult(values, error_initial, error, iterations, converged, lam, message)


# ----------------------------------------------------------------------------- chi-square
def _underlying_model(model):
    """The Gaussian model under a Robust one (or the model itself)."""
    if isinstance(model, gtsam.noiseModel.Robust):
        return model.noise()
    return model


def whitened_errors(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                    indices: Sequence[int] | None = None) -> np.ndarray:
    """Squared Mahalanobis distance of each factor's residual, BEFORE any robust reweighting.

    For a noise-model factor (built-in or ``CustomFactor``): ``r = unwhitenedError(values)`` and
    ``||whiten(r)||^2`` with the Gaussian model under a ``Robust`` one; this is ``2 * error`` for a
    non-robust factor and chi-square distributed with ``dim`` degrees of freedom when the model
    is right. For any other factor type the robust loss cannot be undone from Python and
    ``2 * factor.error(values)`` is returned. Removed (null) factor slots give NaN.

    Args:
        graph, values: the graph and the point to evaluate at.
        indices: factor indices (default: every factor).

    Returns:
        (len(indices),) float array.
    """
    idx = range(graph.size()) if indices is None else indices
    out = []
    for i in idx:
        f = graph.at(int(i))
        if f is None:
            out.append(float("nan"))
            continue
        model = getattr(f, "noiseModel", None)
        unwhitened = getattr(f, "unwhitenedError", None)
        if model is not None and unwhitened is not None:
            nm = _underlying_model(model())
            if nm is not None:
                r = np.asarray(unwhitened(values), dtype=float).reshape(-1)
                w = np.asarray(nm.whiten(r), dtype=float).reshape(-1)
                out.append(float(w @ w))
                continue
        out.append(2.0 * float(f.error(values)))
    return np.asarray(out, dtype=float)


def outlier_factors(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                    indices: Sequence[int] | None, dof=None, p: float = 0.999) -> list[int]:
    """Factors whose whitened error fails the chi-square test at probability ``p``.

    Args:
        indices: factor indices to test (None: every factor).
        dof: degrees of freedom: an int for all, a sequence (one per index), or None for each
            factor's dimension.
        p: the test probability (0.999: one good measurement in 1000 is flagged).

    Returns:
        The indices (subset of ``indices``, same order) with ``whitened error > chi2.ppf(p, dof)``.
    """
    from graphcal import stats as chi2

    idx = list(range(graph.size())) if indices is None else [int(i) for i in indices]
    e = whitened_errors(graph, values, idx)
    if dof is None:
        dofs = np.array([graph.at(i).dim() if graph.at(i) is not None else 1 for i in idx], dtype=float)
    else:
        dofs = np.broadcast_to(np.asarray(dof, dtype=float), (len(idx),))
    thresholds = chi2.ppf(p, dofs)
    return [i for i, ei, th in zip(idx, e, thresholds) if np.isfinite(ei) and ei > th]
