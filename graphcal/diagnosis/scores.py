"""Score (Lagrange-multiplier) tests of every candidate extension at once, from one linearisation.

At the current model's optimum, linearise the *screening* graph (the current model plus every
candidate's variable at its nominal value) and stack the whitened system ``A = [J | K]``, ``b``
(gtsam's convention: ``A delta = b``, ``b = -`` whitened error) over every factor except the
candidates' own priors. For a candidate with columns ``K_c`` (its variables; for an extrinsic
change the extrinsic's columns on the rows from the change on; for an outlier station the identity
on that station's measurement rows):

    u_c = K_c^T b,     I_c = K_c^T K_c - K_c^T J (J^T J)^-1 J^T K_c,     T_c = u_c^T I_c^+ u_c

``T_c`` is chi-square with ``rank(I_c)`` degrees of freedom when the current model is right (the
score test: the information of the candidate's parameters after the current model's parameters
are projected out); ``I_c^+ u_c`` is the one-step estimate of the candidate's parameters. The score
test needs no fit of the extended model, so every location of every cause is tested in one pass.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from scipy import sparse

from graphcal.diagnosis.catalogue import Candidate, Evidence
from graphcal.stats import logsf as chi2_logsf

__all__ = ["LinearSystem", "linear_system", "screening_system", "score_candidates", "freed_rows_test", "evidence"]


@dataclass(frozen=True, eq=False)
class LinearSystem:
    """The stacked whitened linearisation.

    Attributes:
        A (rows, cols), b (rows,): whitened Jacobian and right-hand side.
        col: key -> (offset, dim) of its columns.
        row_factor: (rows,) factor index of each row; row_station: (rows,) station id or -1.
        measurement_rows: (station, sensor) -> row indices of its plane / scan factor.
        station_order: station id -> position in the dataset's order.
        tight_cols: columns of the screening variables held at their nominal value (their priors
            are not in the rows); never part of the current model.
    """

    A: np.ndarray
    b: np.ndarray
    col: dict
    row_factor: np.ndarray
    row_station: np.ndarray
    measurement_rows: dict
    station_order: dict
    tight_cols: np.ndarray


def linear_system(problem, values: gtsam.Values) -> LinearSystem:
    """Stack the whitened linearisation of ``problem.graph`` at ``values`` (skipping the tight priors of
    the screening variables: every extension prior whose variable is not free)."""
    lin = problem.graph.linearize(values)
    dims = {int(k): int(d) for k, d in values.dims().items()}
    col, off = {}, 0
    for k in sorted(int(k) for k in problem.graph.keyVector()):
        col[k] = (off, dims[k])
        off += dims[k]
    from graphcal.diagnosis.model import TIGHT_SIGMA

    skip = set()
    tight = []
    for i in problem.extension_priors:
        model = problem.graph.at(i).noiseModel()
        if np.max(np.asarray(model.sigmas())) <= 10 * TIGHT_SIGMA:
            skip.add(i)
            for k in problem.graph.at(i).keys():
                o, d = col[int(k)]
                tight.extend(range(o, o + d))
    x_station = {int(k): st for st, k in problem.station_keys.items()}
    factor_station = {i: m[0] for i, m in problem.plane_factors.items()}
    blocks = []  # (factor index, its Jacobian, its b, its keys, its station)
    for i in range(problem.graph.size()):
        jf = None if i in skip else lin.at(i)
        if jf is not None:
            keys = [int(k) for k in jf.keys()]
            st = factor_station.get(i, next((x_station[k] for k in keys if k in x_station), -1))
            blocks.append((i, *jf.jacobian(), keys, st))
    A = np.zeros((sum(len(b) for _, _, b, _, _ in blocks), off))
    rhs, rf, rs = [], [], []
    mrows = {}
    n = 0
    for i, Ai, bi, keys, st in blocks:
        m, c0 = len(bi), 0
        for k in keys:
            o, d = col[k]
            A[n:n + m, o:o + d] = Ai[:, c0:c0 + d]
            c0 += d
        rhs.append(bi)
        rf.append(np.full(m, i))
        rs.append(np.full(m, st))
        if i in problem.plane_factors:
            mrows[problem.plane_factors[i]] = np.arange(n, n + m)
        n += m
    order = {st: j for j, st in enumerate(problem.station_keys)}
    return LinearSystem(A, np.concatenate(rhs), col, np.concatenate(rf), np.concatenate(rs), mrows, order,
                        np.array(sorted(set(tight)), dtype=int))


#: the last screening linearisations kept (:func:`screening_system`): ((ds, robot, data, values),
#: (options, findings), (problem, LinearSystem)), newest first
_SCREENED: list = []


def screening_system(model, values: gtsam.Values) -> tuple:
    """(the screening graph of ``model`` (a DiagnosisModel: every catalogued cause's variable at its
    nominal value) built at ``values``, its :func:`linear_system` there); the last two are kept (the
    segments finder's and the diagnosis loop's first round are the same). Neither may be modified."""
    key = (model.ds, model.robot, model.data, values)
    for ids, was, screened in _SCREENED:
        if all(a is b for a, b in zip(ids, key)) and was == (model.options, model.findings):
            return screened
    problem = model.build(screen=True, initial=values)
    screened = problem, linear_system(problem, problem.initial)
    _SCREENED[:0] = [(key, (model.options, model.findings), screened)]
    del _SCREENED[2:]
    return screened


def evidence(test: str, statistic: float, dof: int, family_size: int, n_rows: int) -> Evidence:
    """Chi-square evidence with the family-wise (Bonferroni) p-value and the BIC difference."""
    dof = max(int(dof), 1)
    stat = max(float(statistic), 0.0)
    logsf = float(chi2_logsf(stat, dof))
    log10_family = min(0.0, (logsf + np.log(max(family_size, 1))) / np.log(10.0))
    return Evidence(test, stat, dof, float(np.exp(logsf)), float(10.0**log10_family), log10_family,
                    stat - dof * np.log(max(n_rows, 2)))


@dataclass(frozen=True)
class CandidateColumns:
    """How a candidate enters the linearisation: ``cols`` (its own variables, every row), ``cols`` on
    ``rows`` only (an extrinsic change from a station on: the extrinsic's columns on the later rows; a
    session offset: the ground offset on that session's plane rows), the identity on ``rows``
    (``cols`` None: an outlier station, whose measurement rows are set free), or ``dense`` columns
    built from the system (a foot radius, a joint compliance: diagnosis/contact.py)."""

    candidate: Candidate
    cols: np.ndarray | None
    rows: np.ndarray | None = None
    dense: np.ndarray | None = None  # (rows, p) columns built from the system (a shared-parameter cause)

    def matrix(self, system: "LinearSystem") -> np.ndarray:
        """The candidate's columns K, full height (zero outside the rows it acts on)."""
        n = len(system.b)
        if self.dense is not None:
            return self.dense
        if self.cols is None:
            K = np.zeros((n, len(self.rows)))
            K[self.rows, np.arange(len(self.rows))] = 1.0
            return K
        if self.rows is None:
            return system.A[:, self.cols]
        K = np.zeros((n, len(self.cols)))
        K[self.rows] = system.A[np.ix_(self.rows, self.cols)]
        return K


@dataclass(frozen=True)
class Score:
    candidate: Candidate
    evidence: Evidence
    estimate: np.ndarray  # one-step estimate of the candidate's parameters (its variables' tangent)
    columns: CandidateColumns


def _pinv_quadratic(I: np.ndarray, u: np.ndarray, rtol: float = 1e-8) -> tuple[float, int, np.ndarray]:
    w, V = np.linalg.eigh(0.5 * (I + I.T))
    keep = w > rtol * max(w.max(), 1e-300)
    if not keep.any():
        return 0.0, 0, np.zeros_like(u)
    z = V[:, keep].T @ u
    stat = float(np.sum(z**2 / w[keep]))
    est = V[:, keep] @ (z / w[keep])
    return stat, int(keep.sum()), est


def current_columns(system: LinearSystem, candidates: list) -> np.ndarray:
    """Columns of the current model: every column but the tight screening variables' and the
    candidates' own."""
    out = set(int(c) for c in system.tight_cols)
    for cc in candidates:
        if cc.cols is not None and cc.rows is None:
            out.update(int(c) for c in cc.cols)
    return np.array([c for c in range(system.A.shape[1]) if c not in out], dtype=int)


def _current_projection(system: LinearSystem, candidates: list) -> tuple:
    """(J, (J^T J)^-1) of the current model's columns (:func:`current_columns`)."""
    j_cols = current_columns(system, candidates)
    J = sparse.csr_matrix(system.A[:, j_cols])  # a factor touches few variables: J is >95 % zeros
    Q = (J.T @ J).toarray()
    try:
        Lq = np.linalg.cholesky(Q)
        Li = np.linalg.inv(Lq)
        return J, Li.T @ Li
    except np.linalg.LinAlgError:
        return J, np.linalg.pinv(Q, rcond=1e-12)


def freed_rows_test(system: LinearSystem, candidates: list):
    """A function ``rows -> (statistic, dof)``: the score test of setting the whitened rows ``rows``
    (indices into ``system.b``) free at once, against the current model of ``candidates``
    (:func:`current_columns`). Several outlier stations freed together: the statistic of a set minus
    that of a subset is the test of the rest given the subset (a gross outlier's pull on its
    neighbours' residuals projected out)."""
    J, Qinv = _current_projection(system, candidates)

    def test(rows) -> tuple[float, int]:
        rows = np.asarray(rows, dtype=int)
        Jr = J[rows].toarray()
        stat, dof, _ = _pinv_quadratic(np.eye(len(rows)) - Jr @ Qinv @ Jr.T, system.b[rows], rtol=1e-6)
        return stat, dof

    return test


def score_candidates(system: LinearSystem, candidates: list) -> list[Score]:
    """Score tests of every candidate (:class:`CandidateColumns`)."""
    A, b = system.A, system.b
    J, Qinv = _current_projection(system, candidates)
    n_rows = len(b)
    out = []
    for cc in candidates:
        if cc.dense is not None:  # columns built from the system (foot radius, compliance)
            K = cc.dense
            W = J.T @ K
            I = K.T @ K - W.T @ Qinv @ W
            stat, dof, est = _pinv_quadratic(I, K.T @ b)
        elif cc.cols is None:  # identity on rows
            Jr = J[cc.rows].toarray()
            I = np.eye(len(cc.rows)) - Jr @ Qinv @ Jr.T
            stat, dof, est = _pinv_quadratic(I, b[cc.rows], rtol=1e-6)
        else:
            rows = cc.rows if cc.rows is not None else np.arange(len(b))
            K = A[np.ix_(rows, cc.cols)]
            W = J[rows].T @ K
            I = K.T @ K - W.T @ Qinv @ W
            stat, dof, est = _pinv_quadratic(I, K.T @ b[rows])
        if dof == 0:
            continue
        out.append(Score(cc.candidate, evidence("score", stat, dof, cc.candidate.family_size, n_rows), est, cc))
    return out
