"""Bookkeeping finder (graphcal/diagnosis/bookkeeping.py): undeclared segment boundaries -- a
**height step** (from a station on, the ground every sensor sees lies at another height relative to
the feet, inside a declared session) or a **knock** (one sensor's extrinsic changes from a station
on) -- by change-point segmentation over the station sequence (dataset order).

Score tests on the nominal model's whitened linearisation (:mod:`graphcal.diagnosis.scores`): a
step is one column (a vertical shift of the ground seen, m), a knock the extrinsic's six columns
(rad, m); a BIC-like penalty with a Bonferroni gate (:data:`ALPHA`), a confidence against outlier
stations (:data:`MIN_CONFIDENCE`), binary segmentation up to :data:`MAX_BOUNDARIES`. A step's
stations get a new session label (``<session>@<first station>``); each boundary a Correction.

The method and its measurements: docs/diagnosis.md, "Undeclared segment boundaries".
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
from scipy.linalg import solve_triangular
from scipy.stats import chi2 as chi2_dist

from graphcal.diagnosis.catalogue import Candidate
from graphcal.diagnosis.correction import Correction
from graphcal.diagnosis.scores import linear_system, screening_system

__all__ = ["find_segments", "ALPHA", "MAX_BOUNDARIES", "MAX_OUTLIERS", "MIN_CONFIDENCE", "RANK_RTOL", "REFIT_KNOCKS",
           "KNOCK_GRID", "GRID_SHARE", "GRID_GAIN_BOUND", "KNOCK_GAIN_BOUND"]

log = logging.getLogger(__name__)

#: family-wise level of a boundary (Bonferroni over every boundary tested)
ALPHA = 1e-3
#: at most this many boundaries are put into the model (binary segmentation)
MAX_BOUNDARIES = 3
#: the BIC difference a boundary must have over the next-best explanation at its place
MIN_CONFIDENCE = 2.0
#: a boundary must explain the data better than up to this many outlier stations (the worst-fitting)
MAX_OUTLIERS = 3
#: information eigenvalues below this share of the largest are not counted as degrees of freedom of a
#: boundary: a knock seen on two planes of nearly the same normal is a 3-parameter effect (the
#: normal's two angles and the distance); its three weak directions carry noise only, and counted they
#: would make a knock at two end stations as costly as two outlier measurements
RANK_RTOL = 0.05


@dataclasses.dataclass(frozen=True)
class _Test:
    """One scored explanation: a step or knock at boundary ``index`` (the first station after it, its
    position in the station sequence), or outliers (``stations``: positions whose rows are set free)."""

    kind: str  # "step", "knock", "outlier" (every sensor's rows), "measurement" (one sensor's rows)
    index: int
    sensor: str
    statistic: float
    dof: int
    estimate: np.ndarray
    information: np.ndarray
    declared: bool = False  # a step at a declared session start
    stations: tuple = ()
    head: bool = False  # a step of the stations BEFORE the boundary (from their session's start)

    def bic(self, n_rows: int) -> float:
        return self.statistic - self.dof * np.log(max(n_rows, 2))


@dataclasses.dataclass(frozen=True)
class _Layout:
    """The station sequence of a model and where each measurement's rows lie in a linear system."""

    stations: tuple
    session: list
    rows_at: dict  # position -> {sensor: row indices}
    P: np.ndarray  # orthonormal basis of the columns projected out (see _projector)
    r: np.ndarray  # the whitened residual with every column fitted

    @classmethod
    def of(cls, model, system) -> "_Layout":
        stations = model.data.stations
        index = {st.station: j for j, st in enumerate(stations)}
        rows_at: dict = {}
        for (st, s), r in system.measurement_rows.items():
            rows_at.setdefault(index[st], {})[s] = r
        return cls(tuple(stations), [st.session for st in stations], rows_at, *_projector(system))

    def session_end(self, k: int) -> int:
        end = k
        while end < len(self.stations) and self.session[end] == self.session[k]:
            end += 1
        return end

    def session_start(self, k: int) -> int:
        a = k
        while a > 0 and self.session[a - 1] == self.session[k]:
            a -= 1
        return a

    def sensor_positions(self, s: str) -> list[int]:
        return [j for j in sorted(self.rows_at) if s in self.rows_at[j]]


def _step_columns(problem, values, system, lay: _Layout) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per station position, (rows, column on them): the whitened Jacobian of its plane rows with
    respect to a vertical shift of the ground they see: a world-vertical move of the body pose (its
    tangent's translation is in the body frame, so world z is R^T e_z there); +1 = the sensors see
    the ground 1 m further. A step of stations k..end-1 is their concatenation."""
    out = []
    for j, st in enumerate(lay.stations):
        rows, col = [], []
        if lay.rows_at.get(j):
            x = problem.station_keys[st.station]
            o, _ = system.col[int(x)]
            up = values.atPose3(x).rotation().matrix().T @ np.array([0.0, 0.0, 1.0])
            for r in lay.rows_at[j].values():
                rows.append(r)
                col.append(system.A[np.ix_(r, np.arange(o + 3, o + 6))] @ up)
        out.append((np.concatenate(rows) if rows else np.zeros(0, dtype=int),
                    np.concatenate(col) if col else np.zeros(0)))
    return out


def _block(columns: list, k: int, end: int) -> tuple[np.ndarray, np.ndarray]:
    rows = np.concatenate([columns[j][0] for j in range(k, end)])
    return rows, np.concatenate([columns[j][1] for j in range(k, end)])[:, None]


def _boundaries(model, problem, values, system, lay: _Layout) -> list[_Test]:
    """Every step and knock boundary, scored at the current fit."""
    n = len(lay.stations)
    ccs, meta = [], []
    columns = _step_columns(problem, values, system, lay)
    for k in range(1, n):
        a, e = lay.session_start(k), lay.session_end(k)
        # the stations from k to the session's end at another height; within a session, also those
        # from its start to k (several sessions share one ground: the two are different hypotheses)
        for head, (lo, hi) in ((False, (k, e)), (True, (a, k))):
            if head and a == k:
                continue
            rows, K = _block(columns, lo, hi)
            if K.any():
                ccs.append((rows, K))
                meta.append(("step", k, "", (a == k, head)))
    for s in model.sensors():
        ms = lay.sensor_positions(s)
        keys = {j: problem.measurement_keys[(lay.stations[j].station, s)] for j in ms}
        for i in range(1, len(ms)):
            k = ms[i]
            if keys[ms[i - 1]] != keys[k]:
                continue  # a boundary already in the model
            o, d = system.col[int(keys[k])]
            rows = np.concatenate([lay.rows_at[j][s] for j in ms[i:] if keys[j] == keys[k]])
            ccs.append((rows, system.A[np.ix_(rows, np.arange(o, o + d))]))
            meta.append(("knock", k, s, (False, False)))
    return [_Test(kind, k, s, *sc, declared=flags[0], head=flags[1])
            for (kind, k, s, flags), sc in zip(meta, _scores(lay, ccs)) if sc is not None]


def _outliers(system, lay: _Layout, positions: tuple, sensor: str = "") -> _Test | None:
    """The stations at ``positions`` as outliers: every sensor's rows free, or only ``sensor``'s."""
    rows = [r for j in positions for s, r in lay.rows_at.get(j, {}).items() if not sensor or s == sensor]
    if not rows:
        return None
    sc = _scores(lay, [(np.concatenate(rows), None)])[0]
    if sc is None:
        return None
    return _Test("measurement" if sensor else "outlier", positions[0], sensor, *sc, stations=tuple(positions))


def _projector(system) -> tuple[np.ndarray, np.ndarray]:
    """(P, r): P = J L^-T (J^T J = L L^T, with a ridge far below any measured direction: the
    screening variables include gauges, e.g. a session's ground against the extrinsic), whose
    orthonormal columns span J -- the model's columns and every screening variable's; r = the
    whitened residual with all of them fitted (the screening variables are not, at the nominal fit)."""
    J, b = system.A, system.b
    Q = J.T @ J
    Q[np.diag_indices_from(Q)] += 1e-9 * max(np.trace(Q) / len(Q), 1e-300)
    try:
        P = solve_triangular(np.linalg.cholesky(Q), J.T, lower=True).T
    except np.linalg.LinAlgError:  # not positive definite even with the ridge: an orthonormal basis
        U, sv, _ = np.linalg.svd(J, full_matrices=False)
        P = U[:, sv > 1e-10 * max(sv.max(), 1e-300)]
    return P, b - P @ (P.T @ b)


def _scores(lay: "_Layout", ccs: list) -> list:
    """(T, dof, estimate, information) per candidate ``(rows, K)`` -- its columns K on those rows
    (zero elsewhere), or K None: the identity on the rows (outliers) -- None where it has no
    information. The current model's columns and the catalogued causes' are projected out once
    (:func:`_projector`), so each candidate costs only its own rows. dof counted with RANK_RTOL:
    the weak directions of an extrinsic seen on two planes are no evidence either way."""
    P, r = lay.P, lay.r
    out = []
    for rows, K in ccs:
        Pr = P[rows]
        if K is None:
            I = np.eye(len(rows)) - Pr @ Pr.T
            u = r[rows]
            rtol = 1e-6
        else:
            G = Pr.T @ K
            I = K.T @ K - G.T @ G
            u = K.T @ r[rows]
            rtol = RANK_RTOL
        w, V = np.linalg.eigh(0.5 * (I + I.T))
        keep = w > rtol * max(w.max(), 1e-300)
        # nothing left once the model and the catalogued causes are projected out (a step at a
        # declared session's start is that session's offset)
        if not keep.any() or w.max() < 1e-6 * max(np.trace(I + G.T @ G) if K is not None else len(rows), 1e-300):
            out.append(None)
            continue
        z = V[:, keep].T @ u
        out.append((float(np.sum(z**2 / w[keep])), int(keep.sum()), V[:, keep] @ (z / w[keep]), I))
    return out


def _log10_p(tests: list[_Test], family: int) -> np.ndarray:
    """Bonferroni log10 p-values of the tests over a family of ``family``."""
    if not tests:
        return np.zeros(0)
    T = np.array([t.statistic for t in tests])
    dof = np.array([t.dof for t in tests])
    return (chi2_dist.logsf(T, dof) + np.log(max(family, 1))) / np.log(10.0)


def _posterior(tests: list[_Test], best: _Test, lay: _Layout) -> tuple[float, tuple[int, int]]:
    """P(boundary at best.index) and the 95 % interval (station ids) of the boundary's location:
    p(k) ~ exp(T_k / 2) over the same kind's boundaries in the same segment (same sensor; for a
    step, the same session), a flat prior over the locations (one change point's profile likelihood)."""
    same = [t for t in tests if t.kind == best.kind and t.sensor == best.sensor and not t.declared
            and (best.kind != "step" or lay.session[t.index] == lay.session[best.index])]
    if best.declared or not same:
        return 1.0, (lay.stations[best.index].station,) * 2
    by_index: dict = {}
    for t in same:  # a step's two readings (head, tail) at one boundary: the better one
        by_index[t.index] = max(by_index.get(t.index, -np.inf), t.statistic)
    idx = sorted(by_index)
    T = np.array([by_index[k] for k in idx])
    w = np.exp(0.5 * (T - T.max()))
    w /= w.sum()
    order = np.argsort(-w)
    keep, acc = [], 0.0
    for i in order:
        keep.append(idx[i])
        acc += w[i]
        if acc >= 0.95:
            break
    p_best = float(w[idx.index(best.index)])
    return p_best, (lay.stations[min(keep)].station, lay.stations[max(keep)].station)


def _short_side(lay: _Layout, best: _Test) -> tuple:
    """Positions of the shorter side of a boundary when it holds at most two stations (an end
    segment: there a boundary competes with outliers), else ()."""
    if best.kind == "step":
        a, e = lay.session_start(best.index), lay.session_end(best.index)
        before, after = list(range(a, best.index)), list(range(best.index, e))
    else:
        ms = lay.sensor_positions(best.sensor)
        i = ms.index(best.index)
        before, after = ms[:i], ms[i:]
    side = min((before, after), key=len)
    return tuple(side) if 0 < len(side) <= 2 else ()


def _alternatives(best: _Test, tests: list[_Test], system, lay: _Layout) -> list[_Test]:
    """The next-best explanations of what ``best`` explains: the other kind of boundary near it
    (a knock for a step and back), outliers on its short side."""
    other = "knock" if best.kind == "step" else "step"
    alts = [t for t in tests if t.kind == other and abs(t.index - best.index) <= 1]
    n = len(lay.stations)
    # outliers: the short side of an end segment; one or two stations from the boundary on (a
    # boundary there and another back reads as them)
    groups = {_short_side(lay, best), (best.index,), tuple(j for j in (best.index, best.index + 1) if j < n)}
    # and the few stations whose data fit worst anywhere: outliers on either side of a boundary pull
    # it towards them (three outlier stations can read as a knock between them)
    single = [o for o in (_outliers(system, lay, (j,), best.sensor) for j in sorted(lay.rows_at)) if o is not None]
    single.sort(key=lambda o: -o.statistic)
    for m in range(1, MAX_OUTLIERS + 1):
        groups.add(tuple(sorted(o.index for o in single[:m])))
    for side in groups:
        if side:
            o = _outliers(system, lay, side, best.sensor)
            if o is not None:
                alts.append(o)
    return alts


def _label(t: _Test, lay: _Layout) -> str:
    st = lay.stations[t.index].station
    if t.kind == "step":
        return f"height_step(from_station={st})"
    if t.kind == "knock":
        return f"extrinsic_knock(sensor={t.sensor}, from_station={st})"
    ids = [lay.stations[j].station for j in t.stations]
    return f"outlier_stations(stations={ids})" if t.kind == "outlier" else f"outlier_measurement(sensor={t.sensor}, stations={ids})"


def _new_session(data, old: str, st: int) -> str:
    names = {s.session for s in data.stations}
    label = f"{old}@{st}"
    while label in names:
        label += "'"
    return label


def _relabel(data, lay: _Layout, k: int, end: int, label: str):
    moved = {lay.stations[j].station for j in range(k, end)}
    stations = tuple(dataclasses.replace(st, session=label) if st.station in moved else st for st in data.stations)
    return dataclasses.replace(data, stations=stations)


#: knocks fitted (solved) to place a knock: the strongest linear scores and their neighbours, a
#: grid of every KNOCK_GRID-th place, and the places around the best fitted one
REFIT_KNOCKS = 8
KNOCK_GRID = 3
#: the grid is fitted only when the strongest knocks fitted explain at least this share of what the
#: best outlier explanation does
GRID_SHARE = 0.5
#: how far the grid of places can raise the best knock fitted first, at most. The grid is not fitted
#: when even this bound on that knock loses to the best outlier explanation by BIC: its ~25 knock fits
#: could not change the answer (docs/diagnosis.md, "Outliers before knocks")
GRID_GAIN_BOUND = 1.1
#: how far fitting can raise a knock's statistic above its linear score, at most: 2.1x (the outliers
#: pull the nominal fit), then the grid of places (GRID_GAIN_BOUND). No knock is fitted when even this
#: bound on the strongest knock loses to the best outlier explanation by BIC (outliers clearly explain
#: more); real knocks are never skipped (docs/diagnosis.md, "Outliers before knocks")
KNOCK_GAIN_BOUND = 2.1 * GRID_GAIN_BOUND


def _cannot_win(knock: _Test, gain: float, outlier: _Test | None, n_rows: int) -> bool:
    """Whether ``knock``'s statistic raised ``gain`` times still loses to ``outlier`` by BIC by more
    than MIN_CONFIDENCE."""
    return outlier is not None and gain * knock.statistic - knock.dof * np.log(max(n_rows, 2)) < \
        outlier.bic(n_rows) - MIN_CONFIDENCE


def _refit_knocks(model, solved: tuple, best: _Test, tests: list[_Test], lay: _Layout,
                  outlier: _Test | None = None, n_rows: int = 0) -> tuple:
    """(the knock that fits best, the runner-up or None, their chi-square difference, the fitted
    knocks as (chi2, test), the knocks whose fit stalled (model.Fit.stalled)): the
    :data:`REFIT_KNOCKS` knocks of any sensor with the strongest linear
    scores (at least a quarter of ``best``'s), the neighbours of ``best``, every :data:`KNOCK_GRID`-th
    place of those sensors, then the places around the best of them, each FITTED (the model with
    that extrinsic change, solved). A large knock is far from the nominal linearisation: the linear
    score can peak stations away from it, and with two sensors the conflict between them at a few
    stations can be put on either (docs/diagnosis.md, "Placing a knock by fitted likelihoods").
    ``outlier``: the best outlier explanation (:func:`_alternatives`); when the
    strongest knocks fitted explain less than :data:`GRID_SHARE` of its statistic, the grid is not
    fitted (an outlier station scores as a knock beside it: ~25 solves saved), nor when the best of
    them raised by :data:`GRID_GAIN_BOUND` loses to it by BIC over ``n_rows`` rows. ``solved``:
    (problem, values) of ``model`` solved; every knock's fit starts from those values. A stalled
    fit's chi-square is an upper bound: it is ranked as it is, and returned so that it is said."""
    from graphcal.diagnosis.model import chi2_of

    knocks = sorted((t for t in tests if t.kind == "knock"), key=lambda t: -t.statistic)
    strong = [t for t in knocks if t.statistic >= 0.25 * best.statistic]
    by_place = {(t.sensor, t.index): t for t in knocks}
    # the strongest linear scores, the neighbours of the best, and a coarse grid over every sensor's
    # knocks (every KNOCK_GRID-th place); then the places around the best fitted one
    first = strong[:REFIT_KNOCKS] + [t for t in strong if abs(t.index - best.index) <= 1]
    strong_first = list(first)
    for sensor in {t.sensor for t in strong}:
        first += sorted((t for t in knocks if t.sensor == sensor), key=lambda t: t.index)[::KNOCK_GRID]
    chi0 = chi2_of(*solved)[0]
    values0 = solved[1]
    fitted: dict = {}
    stalled: list = []

    def fit(t):
        if (t.sensor, t.index) in fitted:
            return
        cand = Candidate("extrinsic_change", (("sensor", t.sensor), ("station", int(lay.stations[t.index].station))), 1)
        done = model.with_finding(cand).fit(initial=values0)
        chi = chi2_of(done.problem, done.values)[0]
        if done.stalled:
            stalled.append(t)
        # its statistic: the fitted likelihood ratio (the outliers it is compared with are exact)
        fitted[(t.sensor, t.index)] = (chi, dataclasses.replace(t, statistic=max(chi0 - chi, 0.0)))

    for t in strong_first:
        fit(t)
    top = min(fitted.values(), key=lambda x: x[0])[1]
    if outlier is not None and (top.statistic < GRID_SHARE * outlier.statistic
                                or _cannot_win(top, GRID_GAIN_BOUND, outlier, n_rows)):
        # the knocks of strongest score fitted explain less than half of what outliers do, or lose to
        # them by BIC even raised as much as the grid ever raised one: no place the grid could find
        # turns that around, and the outliers win below (or one station at an end cannot tell)
        return _ranked(fitted) + (tuple(stalled),)
    for t in first:
        fit(t)
    top = min(fitted.values(), key=lambda x: x[0])[1]
    for k in range(top.index - KNOCK_GRID + 1, top.index + KNOCK_GRID):
        if (top.sensor, k) in by_place:
            fit(by_place[(top.sensor, k)])
    return _ranked(fitted) + (tuple(stalled),)


def _stalled_note(stalled: tuple, best: _Test, margin: float, lay: _Layout) -> str:
    """The note on knock fits that stalled (model.Fit.stalled): their chi-squares are upper bounds."""
    from graphcal.diagnosis.model import stalled_text

    return (f"{stalled_text([_label(t, lay) for t in stalled])}, and the knocks' ranking on "
            f"{'it' if len(stalled) == 1 else 'them'} is not final (best {_label(best, lay)}, by {margin:.1f} over "
            "the runner-up)")


def _ranked(fitted: dict) -> tuple:
    """(best, runner-up or None, their chi-square difference, fitted as (chi2, test) best first)."""
    fitted = sorted(fitted.values(), key=lambda x: x[0])
    if len(fitted) < 2:
        return fitted[0][1], None, float("inf"), fitted
    return fitted[0][1], fitted[1][1], fitted[1][0] - fitted[0][0], fitted


def _search(model, problem, values, system=None) -> tuple:
    """(system, layout, boundary tests, rows) of ``problem`` linearised at ``values`` (``system``:
    that linearisation when already made)."""
    system = linear_system(problem, values) if system is None else system
    lay = _Layout.of(model, system)
    return system, lay, _boundaries(model, problem, values, system, lay), len(system.b)


def _passing(tests: list, n_rows: int) -> list:
    """The boundaries that pass: Bonferroni p over every boundary tested below ALPHA, and BIC > 0."""
    log10_p = _log10_p(tests, len(tests))
    return [t for t, lp in zip(tests, log10_p) if lp < np.log10(ALPHA) and t.bic(n_rows) > 0]


def find_segments(model, say, initial=None) -> tuple:
    """(corrections, corrected data, notes) for the nominal ``model`` (a DiagnosisModel with its
    noise learned); see graphcal/diagnosis/bookkeeping.py and this module's docstring. ``initial``:
    gtsam.Values to start the first solve from (the nominal model's solution: a warm start)."""
    corrections: list = []
    notes: list = []
    data = model.data
    cur = model
    for rnd in range(MAX_BOUNDARIES):
        if rnd == 0 and initial is None:
            # the gate: no boundary passes even against the model alone, linearised at its initial
            # estimate (the extrinsics fitted to the kinematic body poses; the projection in _scores
            # is the Gauss-Newton step from there) -- no solve, no screening variables, no leg
            # parameters to linearise: nothing to look for. Given the solution (diagnose), the
            # screening below is the diagnosis loop's first (scores.screening_system): no gate
            problem = cur.build()
            if not _passing(*_search(cur, problem, problem.initial)[2:]):
                break
        solved = cur.solve(initial=initial)
        values = initial = solved[1]
        # the screening graph: every catalogued cause's variable at its nominal value, projected
        # out with the model's own (_scores): a boundary must explain what none of them can
        problem, system = screening_system(cur, values)
        system, lay, tests, n_rows = _search(cur, problem, problem.initial, system)
        passing = _passing(tests, n_rows)
        if not passing:
            break
        best = max(passing, key=lambda t: t.bic(n_rows))
        st = lay.stations[best.index].station
        if best.declared:
            # a declared session's offset explains best: in the model (the loop names it), search on
            session = lay.session[best.index]
            say(f"segments: the declared session {session} is offset; searching on")
            cur = cur.with_finding(Candidate("session_offset", (("session", session),), 1))
            continue
        rival = None
        located = tests
        if best.kind == "knock":
            outliers = [t for t in _alternatives(best, tests, system, lay) if t.kind in ("outlier", "measurement")]
            outlier = max(outliers, key=lambda t: t.statistic) if outliers else None
            strongest = max((t for t in tests if t.kind == "knock"), key=lambda t: t.statistic)
            if _cannot_win(strongest, KNOCK_GAIN_BOUND, outlier, n_rows):
                say(f"segments: {_label(best, lay)} is explained better by {_label(outlier, lay)} (linear scores "
                    f"{strongest.statistic:.0f} and {outlier.statistic:.0f}: fitted, no knock can win); no boundary")
                break
            best, rival, margin, fitted, stalled = _refit_knocks(cur, solved, best, tests, lay, outlier, n_rows)
            if stalled:
                notes.append(_stalled_note(stalled, best, margin, lay))
                say(f"segments: {notes[-1]}")
            if outlier is not None and best.statistic < GRID_SHARE * outlier.statistic:
                say(f"segments: {_label(best, lay)} is explained better by {_label(outlier, lay)}; no boundary")
                break
            st = lay.stations[best.index].station
            located = [t for _, t in fitted]  # its location from the fitted likelihoods, not the linear scores
        alts = _alternatives(best, tests, system, lay)
        alt = max(alts, key=lambda t: t.bic(n_rows)) if alts else None
        confidence = best.bic(n_rows) - alt.bic(n_rows) if alt is not None else float("inf")
        p_k, (lo, hi) = _posterior(located, best, lay)
        close = tuple(_label(t, lay) for t in alts if best.bic(n_rows) - t.bic(n_rows) < 2 * MIN_CONFIDENCE + 6)
        if rival is not None and margin < confidence:
            alt, confidence = rival, margin
            close += (_label(rival, lay),) if margin < 2 * MIN_CONFIDENCE + 6 else ()
        where_text = f"station {st}" if lo == hi else f"station {st} (95 % interval {lo}..{hi})"
        side = _short_side(lay, best)
        if best.kind == "knock" and len(side) == 1:
            ids = lay.stations[side[0]].station
            knock = f"after it (from station {st} on)" if side[0] < best.index else "at it (the last station)"
            notes.append(f"station {ids}: an outlier measurement of {best.sensor}, or {best.sensor} knocked {knock}; "
                         "one station cannot tell: nothing corrected")
            say(f"segments: {notes[-1]}")
            break
        if confidence < -MIN_CONFIDENCE and alt.kind in ("outlier", "measurement"):
            # outliers explain it clearly better: not a boundary (the loop tests outlier stations)
            say(f"segments: {_label(best, lay)} is explained better by {_label(alt, lay)}; no boundary")
            break
        if confidence < MIN_CONFIDENCE:
            notes.append(f"{where_text}: {_label(best, lay)} or {_label(alt, lay)}; the data cannot tell them apart "
                         f"(BIC difference {confidence:.1f}): nothing corrected")
            say(f"segments: {notes[-1]}")
            break
        common = dict(statistic=best.statistic, dof=best.dof, p_value=float(chi2_dist.sf(best.statistic, best.dof)),
                      confidence=float(confidence), alternatives=close)
        if best.kind == "step":
            session = lay.session[best.index]
            # the stations at the other height get the new session: from the boundary to the session's
            # end, or (a step of the stations before it) from the session's start to the boundary
            lo_j, end = ((lay.session_start(best.index), best.index) if best.head
                         else (best.index, lay.session_end(best.index)))
            label = _new_session(data, session, lay.stations[lo_j].station)
            h = -float(best.estimate[0]) if best.head else float(best.estimate[0])
            sigma = float(1.0 / np.sqrt(best.information[0, 0]))
            note = (f"the ground the sensors see is {1e3 * abs(h):.1f} mm {'further' if h > 0 else 'closer'} from "
                    f"station {st} on (session "
                    f"{session}, undeclared; P(boundary at {st}) {p_k:.2f}, 95 % interval {lo}..{hi}): stations "
                    f"{lay.stations[lo_j].station}..{lay.stations[end - 1].station} given session {label}")
            if len(side) == 1:
                odd = lay.stations[side[0]].station
                note += (f"; one station ({odd}) on its short side: an outlier whose only error is its distance "
                         "would look the same")
                if f"outlier_stations(stations=[{odd}])" not in common["alternatives"]:
                    common["alternatives"] += (f"outlier_stations(stations=[{odd}])",)
            corrections.append(Correction("height_step", (("from_station", int(st)), ("session", session)),
                                          (("new_session", label), ("ground_distance_change_m", h), ("sigma_m", sigma),
                                           ("boundary_probability", p_k), ("boundary_interval", (int(lo), int(hi)))),
                                          note=note, **common))
            data = _relabel(data, lay, lo_j, end, label)
            cur = dataclasses.replace(cur, data=_relabel(cur.data, lay, lo_j, end, label))
            cur = cur.with_finding(Candidate("session_offset", (("session", label),), 1))
        else:
            note = (f"{best.sensor}'s extrinsic changes at station {st} (undeclared; P(boundary at {st}) {p_k:.2f}, "
                    f"95 % interval {lo}..{hi}): reported through extrinsic_change")
            corrections.append(Correction("extrinsic_knock", (("from_station", int(st)), ("sensor", best.sensor)),
                                          (("boundary_probability", p_k), ("boundary_interval", (int(lo), int(hi)))),
                                          note=note, **common))
            cur = cur.with_finding(Candidate("extrinsic_change", (("sensor", best.sensor), ("station", int(st))), 1))
        say(f"segments: {corrections[-1].label()}: T {best.statistic:.1f} on {best.dof} dof, confidence "
            f"{confidence:.1f}; {note}")
    return tuple(corrections), data, tuple(notes)
