"""Covariances that still cover the error when the model does not fit.

When the adequacy verdict (:mod:`graphcal.calibration.adequacy`) is ``does not fit``, the model's
covariance is not to be trusted. The robust covariance of each extrinsic is the sum of the model
covariance scaled by the residuals' variance factor relative to the noise the model *used*
(:func:`variance_factor`), a jackknife over stations (:func:`jackknife_tangents`) and, where they
apply, the shifts (with their covariances) to the legs calibrated, to a range-scale solution and
to a second extrinsic from the station :func:`change_station` picks. Each term is kept with its
name and a note (:class:`RobustTerm`); calibration.yaml's ``robust_terms`` lists them.

Every covariance is of the right perturbation ``T = T_hat Exp(xi)``, ``xi = [omega (rad), v (m)]``
in the sensor's axes. The method and its measurements: docs/calibration.md, "Does the model fit?".
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Callable

import numpy as np

from graphcal.calibration.graph import CalibrationProblem

log = logging.getLogger(__name__)

__all__ = ["station_chi2", "variance_factor", "shift_covariances", "misfit_sensors",
           "with_robust_covariance", "robust_parts", "RobustTerm", "LEG_GROUPS", "PLANE_GROUP_PREFIX",
           "PLAUSIBLE_RANGE_SCALE_ERROR", "plausible_range_scales", "jackknife_tangents", "change_station",
           "change_shift_covariances", "MIN_SEGMENT_STATIONS"]

#: noise groups a wrong leg (joint offset, link length) shows in
LEG_GROUPS = frozenset({"stance_foot", "stance_foot/joint", "stance_foot/contact", "foot_on_ground"})
#: the noise group of a sensor's planes or scans is this prefix and the sensor's name
PLANE_GROUP_PREFIX = "plane:"
#: a range scale further than this from 1 is no depth sensor's scale error (depth cameras and laser
#: scanners: a few per cent at most; the simulator draws 1-3 %): the misfit is something else (a
#: knocked sensor, say) and the shift to that solution no measure of the error
PLAUSIBLE_RANGE_SCALE_ERROR = 0.1


@dataclass(frozen=True, eq=False)
class RobustTerm:
    """One term of a robust covariance: ``name`` (``model``, ``jackknife``, ``legs_shift``,
    ``range_scale_shift``), its 6x6 ``covariance`` (the extrinsic's tangent, rad and m, sensor
    axes; for ``model`` the scaled model covariance) and a ``note`` saying what it is (one line)."""

    name: str
    covariance: np.ndarray
    note: str


def station_chi2(problem: CalibrationProblem, values, stations=None) -> dict[int, tuple[float, float]]:
    """station -> (chi-square of every factor on its body pose at ``values``, rows - 6).

    Args:
        problem, values: a solved calibration graph (gtsam.Values).
        stations: the stations to read (default: every station of ``problem``).
    """
    from graphcal.solvers.batch import whitened_errors

    by_key = {k: st for st, k in problem.station_keys.items() if stations is None or st in stations}
    acc: dict[int, list[float]] = {st: [0.0, 0.0] for st in by_key.values()}
    graph = problem.graph
    errs = whitened_errors(graph, values)
    for i in range(graph.size()):
        f = graph.at(i)
        if f is None or not np.isfinite(errs[i]):
            continue
        for k in f.keys():
            st = by_key.get(int(k))
            if st is not None:
                acc[st][0] += float(errs[i])
                acc[st][1] += float(f.dim())
    return {st: (x, rows - 6.0) for st, (x, rows) in acc.items()}


def variance_factor(groups) -> float:
    """``max(1, sum r_g m_g^2 / sum r_g)`` over :class:`~graphcal.calibration.adequacy.GroupCheck` s
    (``m_g`` their ``model_ratio``, ``r_g`` their dof): the residuals' variance factor relative to
    the noise the model used, not the physical one (module docstring; 1 when none is judged)."""
    dof = sum(g.dof for g in groups)
    if dof <= 0:
        return 1.0
    return float(max(1.0, sum(g.dof * g.model_ratio ** 2 for g in groups) / dof))


def _tangent(T_hat: np.ndarray, T: np.ndarray) -> np.ndarray:
    from graphcal.geometry import pose_log_between

    return np.asarray(pose_log_between(T_hat, T), dtype=float)


def _jackknife_covariance(X: np.ndarray) -> np.ndarray:
    n = len(X)
    D = X - X.mean(axis=0)
    return (n - 1) / n * D.T @ D


def jackknife_tangents(problem: CalibrationProblem, values, outliers: frozenset) -> dict[str, tuple[list, np.ndarray]]:
    """sensor -> (the stations, in station order, whose leaving out was solved; their tangents
    ``xi_s`` (n x 6)): each station's planes (or scans) left out in turn; empty with fewer than 3
    stations with measurements, a sensor left out with fewer than 3 tangents.

    Each leave-one-station-out solution is one Gauss-Newton step from the full solution on the
    graph linearised there (whitened, robust weights included): with ``A, b`` the whitened system
    (``A^T b = 0`` at the optimum) and ``A_s, b_s`` the rows of station s's planes or scans,
    ``dx_s = -(A^T A - A_s^T A_s)^-1 A_s^T b_s``; the extrinsic's part of ``dx_s`` is its tangent
    ``xi_s``, through Woodbury's identity from one solve with ``A^T A``: ``dx_s = -Y_s M^-1 b_s``,
    ``Y_s = (A^T A)^-1 A_s^T``, ``M = I - A_s Y_s``. (Solving the graph again per station took 0.5 s
    a station on the Octopus; the same numbers to 4 digits.)

    Args:
        problem, values: the final graph and its solution (gtsam.Values).
        outliers: the (station, sensor) measurements already left out (not in ``problem``).
    """
    by_station = _measurement_factors(problem, outliers)
    if len(by_station) < 3:
        return {}
    A, b, offsets, rows_of = _whitened_system(problem, values)
    H = A.T @ A
    stations = sorted(by_station)
    rows = {st: np.concatenate([np.arange(*rows_of[i]) for i in by_station[st] if i in rows_of]) for st in stations}
    every = np.concatenate([rows[st] for st in stations])
    try:  # one factorisation for every station (Woodbury below)
        Y = np.linalg.solve(H, A[every].T)
    except np.linalg.LinAlgError:
        return {}
    xis: dict[str, list] = {name: [] for name in problem.sensor_keys}
    done: dict[str, list] = {name: [] for name in problem.sensor_keys}
    start = 0
    for st in stations:
        idx = rows[st]
        Ys = Y[:, start:start + len(idx)]
        start += len(idx)
        # (H - As^T As)^-1 As^T bs = Ys M^-1 bs with M = I - As Ys (Woodbury)
        M = np.eye(len(idx)) - A[idx] @ Ys
        try:
            dx = -Ys @ np.linalg.solve(M, b[idx])
        except np.linalg.LinAlgError:  # the station alone determined a direction
            continue
        for name, k in problem.sensor_keys.items():
            o = offsets[k]
            xis[name].append(dx[o:o + 6])
            done[name].append(st)
    return {name: (done[name], np.asarray(rows)) for name, rows in xis.items() if len(rows) >= 3}


def _measurement_factors(problem: CalibrationProblem, outliers: frozenset, sensor: str | None = None) -> dict:
    """station -> indices of its plane / scan factors in the graph (of ``sensor`` only when given)."""
    by_station: dict[int, list[int]] = {}
    for i, m in problem.plane_factors.items():
        if m not in outliers and problem.graph.at(i) is not None and (sensor is None or m[1] == sensor):
            by_station.setdefault(int(m[0]), []).append(i)
    return by_station


def _whitened_system(problem: CalibrationProblem, values):
    """(A, b, key -> first column, factor index -> (first row, end row)) of the graph linearised at
    ``values`` (whitened, robust weights included; ``A^T b = 0`` at the optimum)."""
    import gtsam

    graph = problem.graph
    keys = list(values.keys())
    zero = values.zeroVectors()
    offsets, col = {}, 0
    for k in keys:
        offsets[k] = col
        col += int(np.asarray(zero.at(k)).size)
    ordering = gtsam.Ordering()
    for k in keys:
        ordering.push_back(k)
    rows_of, row = {}, 0
    lin = gtsam.GaussianFactorGraph()
    for i in range(graph.size()):
        f = graph.at(i)
        if f is None:
            continue
        g = f.linearize(values)
        if g is None:
            continue
        n = int(g.rows()) if hasattr(g, "rows") else int(f.dim())
        rows_of[i] = (row, row + n)
        row += n
        lin.push_back(g)
    A, b = lin.jacobian(ordering)
    return np.asarray(A), np.asarray(b).reshape(-1), offsets, rows_of


#: the fewest stations on either side of the station the extrinsic-change term splits at
MIN_SEGMENT_STATIONS = 5


def change_station(problem: CalibrationProblem, values, outliers: frozenset, sensor: str) -> int | None:
    """The station from which ``sensor`` most likely sat elsewhere (a knock): the split of its
    stations (in station order, at least :data:`MIN_SEGMENT_STATIONS` on each side) whose second
    extrinsic would lower the χ² of the graph linearised at ``values`` the most. Score test of the
    split at k (no solve per k): with ``A, b`` the whitened system (``A^T b = 0`` at the optimum),
    ``B_k`` the extrinsic's columns on the rows of the stations from k on, the χ² drop is
    ``g^T S^-1 g``, ``g = B_k^T b``, ``S = B_k^T B_k - B_k^T A (A^T A)^-1 A^T B_k``; ``B_k^T A`` and
    ``B_k^T B_k`` are suffix sums over stations. None with too few stations or a singular system."""
    import scipy.linalg

    by_station = _measurement_factors(problem, outliers, sensor)
    key = problem.sensor_keys.get(sensor)
    order = {st: i for i, st in enumerate(problem.station_keys)}
    stations = sorted(by_station, key=lambda st: order.get(st, st))
    n = len(stations)
    if key is None or n < 2 * MIN_SEGMENT_STATIONS:
        return None
    A, b, offsets, rows_of = _whitened_system(problem, values)
    cols = slice(offsets[key], offsets[key] + 6)
    P, Q, g = [], [], []  # per station: A_s^T A_s[:, cols], A_s[:, cols]^T A_s[:, cols], A_s[:, cols]^T b_s
    for st in stations:
        idx = np.concatenate([np.arange(*rows_of[i]) for i in by_station[st] if i in rows_of])
        As = A[idx]
        P.append(As.T @ As[:, cols])
        Q.append(As[:, cols].T @ As[:, cols])
        g.append(As[:, cols].T @ b[idx])
    try:
        H = scipy.linalg.cho_factor(A.T @ A)
    except np.linalg.LinAlgError:
        return None
    Ps, Qs, gs = (np.cumsum(np.asarray(x)[::-1], axis=0)[::-1] for x in (P, Q, g))  # suffix sums
    best, at = -np.inf, None
    for k in range(MIN_SEGMENT_STATIONS, n - MIN_SEGMENT_STATIONS + 1):
        S = Qs[k] - Ps[k].T @ scipy.linalg.cho_solve(H, Ps[k])
        try:
            score = float(gs[k] @ np.linalg.solve(S, gs[k]))
        except np.linalg.LinAlgError:
            continue
        if np.isfinite(score) and score > best:
            best, at = score, stations[k]
    return at


def shift_covariances(result, other) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """sensor -> (``C_other + d d^T``, ``d``) (module docstring), ``d = Log(T_hat^-1 T_other)`` from
    the base ``result`` to the result of the same data under an extended model (``--legs``, a
    range scale: :class:`~graphcal.calibration.result.CalibrationResult` s)."""
    out = {}
    for name, s in result.sensors.items():
        e = other.sensors.get(name)
        if e is None:
            continue
        d = _tangent(np.asarray(s.T_body_sensor), np.asarray(e.T_body_sensor))
        out[name] = (np.asarray(e.covariance) + np.outer(d, d), d)
    return out


def _shift_text(d: np.ndarray) -> str:
    return f"{np.degrees(np.linalg.norm(d[:3])):.3g} deg, {1e3 * np.linalg.norm(d[3:]):.3g} mm"


def misfit_sensors(groups) -> tuple[str, ...]:
    """The sensors whose planes or scans (group ``plane:<sensor>``) do not fit, in group order."""
    return tuple(g.group[len(PLANE_GROUP_PREFIX):] for g in groups
                 if g.misfit and g.group.startswith(PLANE_GROUP_PREFIX))


def plausible_range_scales(scales: dict) -> bool:
    """Whether every range scale of ``scales`` (sensor -> (scale, 1-sigma)) is within
    :data:`PLAUSIBLE_RANGE_SCALE_ERROR` of 1 (a sensor's scale error, not another misfit)."""
    return all(abs(float(v) - 1.0) <= PLAUSIBLE_RANGE_SCALE_ERROR for v, _ in scales.values())


def with_robust_covariance(result, extra: dict[str, list[RobustTerm]], scale: float):
    """``result`` with every sensor's covariance replaced by its robust one,
    ``max(1, scale / covariance_scale) * C_model + sum(extra[sensor])`` (:class:`RobustTerm` s;
    ``covariance_scale`` the factor the given-noise check already multiplied ``C_model`` by); the model's kept as
    ``covariance_model``, the robust one also as ``covariance_robust``, the terms' names and notes
    as ``robust_terms``; sigmas and correlation (body axes) from the robust one."""
    from graphcal.solvers.covariance import body_axis_sigmas

    sensors = {}
    for name, s in result.sensors.items():
        C_model = np.asarray(s.covariance)
        already = float(getattr(s, "covariance_scale", 1.0) or 1.0)
        k = max(1.0, scale / already)
        said = "" if already == 1.0 else f", over the x {already:.4g} already applied for the given plane noise"
        terms = [RobustTerm("model", k * C_model,
                            f"the model covariance x {k:.4g} (the residuals' variance factor relative to the noise "
                            f"the model used, at least 1{said})")] + list(extra.get(name, ()))
        C = sum((np.asarray(t.covariance) for t in terms), np.zeros((6, 6)))
        C = 0.5 * (C + C.T)
        rot, xyz, corr, _ = body_axis_sigmas(s.T_body_sensor, C)
        segments = s.segments
        if len(segments) == 1:
            segments = (dataclasses.replace(segments[0], covariance=C),)
        sensors[name] = dataclasses.replace(
            s, covariance=C, covariance_model=C_model, covariance_robust=C, sigma_rot_deg=np.asarray(rot),
            sigma_xyz_mm=np.asarray(xyz), correlation=np.asarray(corr), segments=segments,
            robust_terms=tuple((t.name, t.note) for t in terms))
    return dataclasses.replace(result, sensors=sensors)


def change_shift_covariances(result, segments: dict) -> dict[str, tuple[np.ndarray, tuple]]:
    """sensor -> (``sum_j C_j + d_j d_j^T``, the ``d_j``) over its segments ``segments[sensor]``
    (((T_j 4x4, C_j 6x6), ...): the same data solved with the extrinsic split at a station),
    ``d_j = Log(T_hat^-1 T_j)``: the one extrinsic estimated lies between where the sensor sat
    before and after; the sum covers the shift to either."""
    out = {}
    for name, segs in segments.items():
        s = result.sensors.get(name)
        if s is None:
            continue
        C, ds = np.zeros((6, 6)), []
        for T, C_j in segs:
            d = _tangent(np.asarray(s.T_body_sensor), np.asarray(T))
            C = C + np.asarray(C_j) + np.outer(d, d)
            ds.append(d)
        out[name] = (C, tuple(ds))
    return out


def _change_terms(extra, problem, values, outliers, result, sensors, change_calibration) -> None:
    """Add the extrinsic-change term of each of ``sensors`` (module docstring) to ``extra``."""
    at = {}
    for name in sensors:
        k = change_station(problem, values, outliers, name)
        if k is not None:
            at[name] = k
    if not at:
        return
    segments = change_calibration(at)
    if segments is None:
        return
    for name, (C, ds) in change_shift_covariances(result, segments).items():
        extra[name].append(RobustTerm(
            "extrinsic_change_shift", C,
            f"sum_j C_j + d_j d_j^T, d_j the shifts to the extrinsic before and after station {at[name]} of the same "
            f"data solved with a second extrinsic from there on ({'; '.join(_shift_text(d) for d in ds)})"))


def robust_parts(problem, values, outliers, result, groups, legs_calibration: Callable | None,
                 range_calibration: Callable | None = None,
                 change_calibration: Callable | None = None) -> tuple[dict[str, list[RobustTerm]], float]:
    """(sensor -> terms to add to the scaled model covariance, the scale) of the module docstring.
    The range-scale term is left out when a scale is further than
    :data:`PLAUSIBLE_RANGE_SCALE_ERROR` from 1.

    Args:
        problem, values, outliers: the final graph, its solution and the measurements left out.
        result: the :class:`~graphcal.calibration.result.CalibrationResult` read off them.
        groups: the judged noise groups (:class:`~graphcal.calibration.adequacy.GroupCheck` s).
        legs_calibration: ``() ->`` the ``--legs`` result of the same data, or None (None: no such term).
        range_calibration: ``(sensors) ->`` (the result of the same data with a range scale of each
            of ``sensors``, sensor -> (scale, 1-sigma)), or None; called only when a ``plane:<sensor>``
            group does not fit (None: no such term).
        change_calibration: ``(sensor -> station) ->`` sensor -> ((T, C) of its extrinsic before the
            station, (T, C) from it on) of the same data solved with the extrinsic split there, or
            None; called only when a ``plane:<sensor>`` group does not fit (None: no such term).
    """
    extra: dict[str, list] = {name: [] for name in result.sensors}
    tangents = jackknife_tangents(problem, values, frozenset(outliers))
    for name, (_, X) in tangents.items():
        extra[name].append(RobustTerm("jackknife", _jackknife_covariance(X), "jackknife over stations (each "
                                                                             "station's planes or scans left out in turn)"))
    if legs_calibration is not None and any(g.misfit and g.group in LEG_GROUPS for g in groups):
        legs_result = legs_calibration()
        if legs_result is not None:
            for name, (C, d) in shift_covariances(result, legs_result).items():
                extra[name].append(RobustTerm("legs_shift", C, "C_legs + d d^T, d the shift to the --legs solution "
                                                               f"of the same data ({_shift_text(d)})"))
    sensors = misfit_sensors(groups)
    if range_calibration is not None and sensors:
        solved = range_calibration(sensors)
        if solved is not None and not plausible_range_scales(solved[1]):
            log.info("robust covariance: no range-scale term: the scale that fits best ("
                     + ", ".join(f"{s} {v:.4g}" for s, (v, _) in solved[1].items())
                     + f") is more than {PLAUSIBLE_RANGE_SCALE_ERROR:.0%} from 1, no sensor's scale error")
            solved = None
        if solved is not None:
            ext_result, scales = solved
            said = ", ".join(f"{s} {v:.5f} ± {sg:.2g}" for s, (v, sg) in scales.items())
            for name, (C, d) in shift_covariances(result, ext_result).items():
                extra[name].append(RobustTerm(
                    "range_scale_shift", C, f"C_ext + d d^T, d the shift to the solution of the same data with a "
                                            f"range scale (measured / true range: {said}) ({_shift_text(d)})"))
    if change_calibration is not None and sensors:
        _change_terms(extra, problem, values, frozenset(outliers), result, sensors, change_calibration)
    return extra, variance_factor(groups)
