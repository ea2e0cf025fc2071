"""Bookkeeping finder (graphcal/diagnosis/bookkeeping.py): two legs' joint columns exchanged in the
logger, for the whole run or from / until one station, plainly or with mirrored signs.

Such an exchange leaves every stance foot of the two legs far from where the other legs and the
sensors put the body; the nominal model reads it as huge joint offsets. Looked for in three steps,
each gated on the previous one, all at physical noise: the stance-foot noise learned against the
physical one (free), the per-leg stance chi-square (:data:`CONCENTRATION`, :data:`MIN_LEG_CHI2`,
confirmed with the sensors weighted out), then one refit per hypothesis (pairs, sign patterns,
spans). A :class:`~graphcal.diagnosis.correction.Correction` ``legs_exchanged`` is made only when
the best hypothesis explains the data and beats the next-best by :data:`MIN_CONFIDENCE` in
chi-square; otherwise a note. Joint values in rad (m for prismatic joints).

The method, the decision rule and its measurements: docs/diagnosis.md, "Exchanged legs".
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2 as chi2_dist

from graphcal.diagnosis.correction import Correction
from graphcal.diagnosis.model import chi2_of, model_options
from graphcal.diagnosis.structure import MIN_EXCESS, STRUCTURE_ALPHA
from graphcal.errors import GraphcalError

__all__ = ["find_joint_columns", "exchange_legs", "candidate_pairs", "leg_chi2", "second_leg_percentile",
           "concentration", "span_text",
           "Hypothesis",
           "CANDIDATE_LEGS", "CONCENTRATION", "MIN_LEG_CHI2", "SENSOR_WEIGHT_OUT", "CHANGE_CONCENTRATION", "CHANGE_PAIRS",
           "MIN_CONFIDENCE"]

log = logging.getLogger(__name__)

#: the legs whose stance feet fail worst at physical noise that make the candidate pairs
CANDIDATE_LEGS = 3
#: the search goes on only when the stance chi-square concentrates on two legs: the second-worst
#: leg's at least this many times the third-worst's (an exchange concentrates there, even mirrored;
#: the other effects spread over the legs: docs/diagnosis.md, "Exchanged legs")
CONCENTRATION = 1.5
#: ... and the second-worst leg's stance-foot chi-square at its 75th percentile over the stations
#: at least this (about 30 mm of foot displacement at physical noise; a percentile, so that a few
#: outlier stations do not open the search); exchanges read several times this, the battery's other
#: effects well below it (docs/diagnosis.md, "Exchanged legs")
MIN_LEG_CHI2 = 1000.0
#: ... and the same percentile again with every sensor's noise scaled by this (the sensors' rows
#: weighted 1e-6): outlier stations can open the plain gate through the sensor rows, exchanged
#: columns pass it on the kinematics alone
SENSOR_WEIGHT_OUT = 1e3
#: ... and the exchange from one station on is tried only above this concentration
CHANGE_CONCENTRATION = 5.0
#: chi-square margin (physical noise) by which the best exchange must beat the next-best
#: hypothesis to be corrected (chi-square 1-dof quantile at 1e-6 is 23.9)
MIN_CONFIDENCE = 25.0
#: when no whole-run hypothesis fits, the change point (exchanged from one station on) is tested for
#: this many pairs that fit best exchanged for the whole run and this many of the legs that fail worst
CHANGE_PAIRS = 2


@dataclass(frozen=True)
class Hypothesis:
    """One hypothesis about the joint columns, scored at physical noise.

    Attributes:
        legs: (a, b) feet exchanged, () for the data as given.
        signs: per joint, the sign the exchanged angles carry (+1 plain exchange, -1 mirrored).
        from_station: first station id exchanged (None: from the first station).
        chi2, dof: the whole model's chi-square at physical noise and its rows minus parameters.
        until_station: first station id no longer exchanged (None: to the last station).
        stalled: its fit ran out of steps (model.Fit.stalled): ``chi2`` is an upper bound.
    """

    legs: tuple
    signs: tuple
    from_station: int | None
    chi2: float
    dof: int
    until_station: int | None = None
    stalled: bool = False

    @property
    def fits(self) -> bool:
        dof = max(self.dof, 1)
        return self.chi2 <= MIN_EXCESS * dof or chi2_dist.sf(self.chi2, dof) >= STRUCTURE_ALPHA

    def label(self) -> str:
        if not self.legs:
            return "the data as given"
        s = "" if all(x > 0 for x in self.signs) else f" with signs {list(self.signs)}"
        return f"legs {self.legs[0]} and {self.legs[1]} exchanged{s}{span_text(self.from_station, self.until_station)}"


def span_text(from_station, until_station) -> str:
    """" from station 18 on", " before station 18", " from station 5 until station 18", or ""."""
    w = "" if from_station is None else f" from station {from_station}"
    if until_station is None:
        return w + (" on" if w else "")
    return f"{w} until station {until_station}" if w else f" before station {until_station}"


def exchange_legs(data, a: str, b: str, signs=None, from_station: int | None = None,
                  until_station: int | None = None):
    """A new CalibrationData with the joint columns of feet ``a`` and ``b`` exchanged in every
    station's ``q_by_foot`` (from station id ``from_station`` on, None: from the first; up to but not
    including station id ``until_station``, None: to the last; in file order), each exchanged angle
    multiplied by ``signs`` (per joint; None: all +1). ``data`` is not changed."""
    started, ended = from_station is None, False
    stations = []
    for st in data.stations:
        started = started or st.station == from_station
        ended = ended or st.station == until_station
        if started and not ended and a in st.q_by_foot and b in st.q_by_foot:
            s = np.ones(len(st.q_by_foot[a])) if signs is None else np.asarray(signs, float)
            q = dict(st.q_by_foot)
            q[a], q[b] = s * np.asarray(st.q_by_foot[b], float), s * np.asarray(st.q_by_foot[a], float)
            st = dataclasses.replace(st, q_by_foot=q)
        stations.append(st)
    return dataclasses.replace(data, stations=tuple(stations))


def _stance_misfit(model) -> float:
    """Learned over physical variance of the stance-foot noise (the larger of its joint and
    contact components); free: read from the options the nominal model learned."""
    phys = model_options(model.ds)
    o = model.options
    return max((o.sigma_joint_rad / phys.sigma_joint_rad) ** 2, (o.sigma_contact_m / phys.sigma_contact_m) ** 2)


def _fit(phys, data, legs=(), signs=(), span=None, initial=None):
    """(Hypothesis, problem, values) of the nominal model of ``data`` solved at physical noise;
    ``span``: (from_station, until_station) of the exchange, None for the whole run; ``initial``:
    gtsam.Values to start from (None: the closed form)."""
    m = dataclasses.replace(phys, data=data, findings=())
    fit = m.fit(initial=initial)
    chi2, rows = chi2_of(fit.problem, fit.values)
    n_par = sum(int(d) for _, d in fit.values.dims().items())
    first, until = span or (None, None)
    return (Hypothesis(tuple(legs), tuple(signs), first, chi2, max(rows - n_par, 1), until, fit.stalled), fit.problem,
            fit.values)


def _free_legs_chi2(phys, a: str, b: str) -> float:
    """Chi-square at physical noise of the data as given with every joint offset and link length of
    legs ``a`` and ``b`` free: the physical explanation the diagnosis would otherwise name."""
    from graphcal.diagnosis.catalogue import Candidate

    m = phys
    for foot in (a, b):
        for name in m.leg_params()[foot].names:
            joint, kind = name.rsplit(".", 1)
            cause = {"offset_rad": "joint_offset", "delta_m": "link_length"}.get(kind)
            if cause is not None:
                m = m.with_finding(Candidate(cause, (("joint", joint), ("leg", foot))))
    problem, values = m.solve()
    return chi2_of(problem, values)[0]


def _stance_chi2(phys, problem, values) -> dict:
    """(station, foot) -> the stance-foot factor's chi-square at ``values``."""
    from graphcal.calibration.graph import planted_foot_index
    from graphcal.factors.keys import F
    from graphcal.solvers.batch import whitened_errors

    foot_of = {int(F(j)): f for (_, f), j in planted_foot_index(phys.data, phys.robot).items()}
    x_station = {int(k): st for st, k in problem.station_keys.items()}
    idx = [i for i, g in problem.factor_groups.items() if g == "stance_foot"]
    e = whitened_errors(problem.graph, values, idx)
    out = {}
    for i, chi in zip(idx, e):
        keys = [int(k) for k in problem.graph.at(i).keys()]
        st = next((x_station[k] for k in keys if k in x_station), None)
        f = next((foot_of[k] for k in keys if k in foot_of), None)
        if st is not None and f is not None and np.isfinite(chi):
            out[(st, f)] = float(chi)
    return out


def leg_chi2(per_station: dict) -> dict:
    """foot -> the sum of its stance-foot chi-squares, worst first (``per_station``: (station,
    foot) -> chi-square)."""
    per_leg: dict = {}
    for (_, f), c in per_station.items():
        per_leg[f] = per_leg.get(f, 0.0) + c
    return dict(sorted(per_leg.items(), key=lambda kv: -kv[1]))


def second_leg_percentile(per_station: dict) -> float:
    """The 75th percentile over the stations of the second-worst leg's stance-foot chi-square
    (``per_station``: (station, foot) -> chi-square); 0 with fewer than two legs."""
    per_leg = leg_chi2(per_station)
    if len(per_leg) < 2:
        return 0.0
    second = list(per_leg)[1]
    return float(np.percentile([c for (_, f), c in per_station.items() if f == second], 75))


def concentration(per_leg: dict) -> float:
    """The second-worst leg's stance chi-square over the third-worst's (inf with two legs)."""
    c = list(per_leg.values())
    return float("inf") if len(c) < 3 else float(c[1] / max(c[2], 1e-12))


def candidate_pairs(data, per_station: dict) -> list:
    """Pairs of the CANDIDATE_LEGS feet with the largest stance chi-square that have the same joint
    count at every station, worst first."""
    worst = list(leg_chi2(per_station))[:CANDIDATE_LEGS]
    pairs = []
    for a, b in itertools.combinations(worst, 2):
        if all(len(st.q_by_foot.get(a, ())) == len(st.q_by_foot.get(b, ())) > 0 for st in data.stations):
            pairs.append((a, b))
    return pairs


def _change_spans(data, a: str, b: str, before: dict, after: dict) -> list:
    """The spans (from_station, until_station) over which the exchange of a and b explains the
    stance feet better than the data as given (``before``/``after``: per (station, foot)
    chi-square of the two fits), by the largest cumulative evidence: exchanged from station k on,
    and exchanged before station k (none that is the whole run)."""
    ids = [st.station for st in data.stations]
    gain = np.array([sum(before.get((s, f), 0.0) - after.get((s, f), 0.0) for f in (a, b)) for s in ids])
    # exchanged from k on: evidence sum(gain[k:]) - sum(gain[:k]) = total - 2 * cumsum(gain)[k-1];
    # exchanged before k: its negative
    score = gain.sum() - 2.0 * np.r_[0.0, np.cumsum(gain)[:-1]]
    spans = []
    k = int(np.argmax(score))
    if k > 0:
        spans.append((ids[k], None))
    k = int(np.argmin(score[1:])) + 1 if len(ids) > 1 else 0
    if k > 0:
        spans.append((None, ids[k]))
    return spans


def _kinematic_percentile(phys, initial) -> float:
    """The 75th percentile over the stations of the second-worst leg's stance-foot chi-square in
    the nominal model at physical noise with every sensor's rows weighted out
    (:data:`SENSOR_WEIGHT_OUT`): the stance feet against each other, the IMU and the ground alone.
    Exchanged columns break the legs' kinematics whatever the sensors see; outlier stations pull
    the stance feet only through the sensor rows (measured: docs/diagnosis.md, "Exchanged legs").
    ``initial``: gtsam.Values to start from."""
    m = _weighted_out(phys)
    _, problem, values = _fit(m, m.data, initial=initial)
    return second_leg_percentile(_stance_chi2(m, problem, values))


def _remaining_text(best: Hypothesis, free: float, kinematic: str) -> str:
    """What the correction's note adds when the exchange does not fit at physical noise
    (:func:`_explains`'s ``free`` and ``kinematic``)."""
    if best.fits:
        return ""
    if not kinematic:
        return (f"; other causes remain (it does not fit at physical noise), but the two legs' joint offsets and "
                f"link lengths freed instead leave {free:.0f}")
    return (f"; other causes remain: it does not fit at physical noise, where the two legs' joint offsets and link "
            f"lengths freed explain the data as well ({free:.0f}), but {kinematic}: the other causes are on the "
            "sensors' side (outlier stations, a knock?)")


def _weighted_out(phys):
    """``phys`` (a DiagnosisModel at physical noise) with every sensor's noise scaled by
    :data:`SENSOR_WEIGHT_OUT`: the stance feet against each other, the IMU and the ground alone."""
    scales = tuple((s, SENSOR_WEIGHT_OUT) for s in phys.sensors())
    return dataclasses.replace(phys, options=dataclasses.replace(phys.options, plane_sigma_scales=scales))


def _explains(phys, data, best: Hypothesis) -> tuple:
    """(whether ``best``, the best exchange, explains the stance feet; the two legs' joint offsets and
    link lengths freed instead: their chi-square at physical noise (nan when not needed); the
    judgement with the sensors weighted out as text, "" when not needed). ``data``: the data with
    ``best`` applied. It explains when it fits at physical noise, or beats the freed legs there by
    MIN_CONFIDENCE (another cause left in the data), or -- when a sensor-side cause (outlier
    stations) keeps both from fitting -- fits with the sensors weighted out
    (:func:`_weighted_out`; its dof without the sensors' rows) and beats the freed legs there by
    MIN_CONFIDENCE: outlier stations can keep an exchange from fitting at physical noise while the
    freed legs explain the data as well (docs/diagnosis.md, "Exchanged legs", "Beside outlier
    stations")."""
    if best.fits:
        return True, float("nan"), ""
    free = _free_legs_chi2(phys, *best.legs)
    if best.chi2 + MIN_CONFIDENCE <= free:
        return True, free, ""
    m = _weighted_out(phys)
    hyp, problem, _ = _fit(m, data, best.legs, best.signs, (best.from_station, best.until_station))
    sensor_rows = sum(problem.graph.at(i).dim() for i, g in problem.factor_groups.items() if g.startswith("plane:"))
    hyp = dataclasses.replace(hyp, dof=max(hyp.dof - sensor_rows, 1))
    free_k = _free_legs_chi2(m, *best.legs)
    text = (f"with the sensors weighted out it {'fits' if hyp.fits else 'does not fit'} (chi-square {hyp.chi2:.0f} "
            f"on {hyp.dof} dof) and the freed legs leave {free_k:.0f}")
    return hyp.fits and hyp.chi2 + MIN_CONFIDENCE <= free_k, free, text


def _search(model, phys, say, initial=None) -> tuple:
    """(every Hypothesis scored, best first; the data of the best) of the exchange search, when the
    stance misfit concentrates on two legs (:data:`CONCENTRATION`): the candidate pairs plainly
    exchanged; the mirror sign patterns of the best pair (and of the two worst legs when no plain
    exchange fits); when still nothing fits, the exchange from one station on and before one station."""
    given, problem, values = _fit(phys, phys.data, initial=initial)
    per_station = _stance_chi2(phys, problem, values)
    pairs = candidate_pairs(phys.data, per_station)
    per_leg = leg_chi2(per_station)
    ratio = concentration(per_leg)
    second = second_leg_percentile(per_station)
    if ratio < CONCENTRATION or second < MIN_LEG_CHI2:
        return [given], phys.data
    kinematic = _kinematic_percentile(phys, values)
    if kinematic < MIN_LEG_CHI2:
        say(f"joint columns: the stance feet fail at physical noise (chi2 {given.chi2:.0f}), but not against each "
            f"other with the sensors weighted out (75th percentile {kinematic:.0f}): not an exchange, no search")
        return [given], phys.data
    say(f"joint columns: stance feet fail at physical noise (chi2 {given.chi2:.0f} on {given.dof} dof); "
        f"the two worst legs carry {ratio:.1f}x the third's; testing {len(pairs)} exchanged leg pair(s)")
    scored = {(): (given, phys.data)}

    def test(a, b, signs, span=None):
        data = exchange_legs(phys.data, a, b, signs, *(span or (None, None)))
        try:
            scored[(a, b, tuple(signs), span)] = (_fit(phys, data, (a, b), signs, span)[0], data)
        except (GraphcalError, RuntimeError) as exc:  # a hypothesis the solver cannot fit is no candidate
            log.debug("joint columns: %s %s %s %s not fitted: %s", a, b, signs, span, exc)

    def best(exchanges_only=False):
        keys = [k for k in scored if k or not exchanges_only]
        return min(keys, key=lambda k: scored[k][0].chi2) if keys else None

    n_joints = {(a, b): len(phys.data.stations[0].q_by_foot[a]) for a, b in pairs}
    for a, b in pairs:
        test(a, b, (1,) * n_joints[(a, b)])
    top = best(exchanges_only=True)
    # the best plain pair's patterns; when nothing fits, also those of the two worst legs
    mirror_pairs = list(dict.fromkeys(([] if top is None else [top[:2]]) +
                                      ([] if top is not None and scored[top][0].fits else pairs[:1])))
    for a, b in mirror_pairs:  # a logger converting left and right conventions: exchanged angles negated
        for signs in itertools.product((1, -1), repeat=n_joints[(a, b)]):
            if (a, b, signs, None) not in scored:
                test(a, b, signs)
    # from one station on: the change point of each pair's evidence
    if not scored[best()][0].fits and ratio >= CHANGE_CONCENTRATION:
        ids = [st.station for st in phys.data.stations]
        by_chi2 = list(dict.fromkeys(k[:2] for k in sorted((k for k in scored if k), key=lambda k: scored[k][0].chi2)))
        # the pairs that fit best exchanged for the whole run, and those of the legs that fail worst
        for a, b in dict.fromkeys(by_chi2[:CHANGE_PAIRS] + pairs[:CHANGE_PAIRS]):
            # the plain exchange and the sign pattern that fits best for the whole run
            tried = [k for k in scored if k and k[:2] == (a, b) and k[3] is None]
            if not tried:
                continue
            fitted = min(tried, key=lambda k: scored[k][0].chi2)[2]
            for signs in dict.fromkeys(((1,) * n_joints[(a, b)], fitted)):
                if (a, b, signs, None) not in scored:
                    continue
                _, pr, vals = _fit(phys, scored[(a, b, signs, None)][1])
                for span in _change_spans(phys.data, a, b, per_station, _stance_chi2(phys, pr, vals)):
                    test(a, b, signs, span)
        spans = [key for key in scored if key and key[3] is not None]
        if spans:  # the neighbours of the best change station
            a, b, signs, (first, until) = min(spans, key=lambda key: scored[key][0].chi2)
            k = ids.index(first if first is not None else until)
            for j in (max(k - 1, 1), min(k + 1, len(ids) - 1)):
                span = (ids[j], None) if first is not None else (None, ids[j])
                if (a, b, signs, span) not in scored:
                    test(a, b, signs, span)
    order = sorted(scored, key=lambda k: scored[k][0].chi2)
    return [scored[k][0] for k in order], scored[order[0]][1]


def find_joint_columns(model, say, initial=None) -> tuple:
    """(corrections, corrected data, notes) for the nominal ``model`` (a DiagnosisModel with its
    noise learned); see graphcal/diagnosis/bookkeeping.py and this module's docstring. ``say(msg)``
    logs a progress line; ``initial``: gtsam.Values the fit of the data as given starts from."""
    if len(model.robot.feet) < 2 or _stance_misfit(model) <= MIN_EXCESS:
        return (), model.data, ()
    phys = dataclasses.replace(model, options=model_options(model.ds), findings=())
    hyps, data = _search(model, phys, say, initial)
    given = next(h for h in hyps if not h.legs)
    best = hyps[0]
    stalled = _stalled_note(hyps)
    if not best.legs:
        return (), model.data, stalled
    runner = hyps[1]
    margin = runner.chi2 - best.chi2
    alternatives = tuple(h.label() for h in hyps[1:] if h.chi2 - best.chi2 < MIN_CONFIDENCE)
    p_given = float(chi2_dist.sf(given.chi2, given.dof))
    # another cause left in the data keeps the exchange from fitting: it must then beat the physical
    # explanation of the same two legs (their joint offsets and link lengths free) clearly
    explains, free, kinematic = _explains(phys, data, best)
    if not explains or margin < MIN_CONFIDENCE:
        why = (f"the stance feet still do not fit at physical noise after it, and the two legs' joint offsets "
               f"and link lengths explain them as well (chi-square {free:.0f}; {kinematic})") if not explains else \
            f"{runner.label()} explains the data almost as well (chi-square {margin:.1f} apart)"
        note = (f"joint columns: {best.label()} is the best explanation of the stance feet tried "
                f"(chi-square {given.chi2:.0f} -> {best.chi2:.0f} at physical noise, {best.dof} dof), but {why}: "
                f"not corrected")
        say(note)
        return (), model.data, (note,) + stalled
    a, b = sorted(best.legs, key=list(model.robot.feet).index)
    where = [("legs", (a, b))] + ([] if best.from_station is None else [("from_station", int(best.from_station))]) \
        + ([] if best.until_station is None else [("until_station", int(best.until_station))])
    mirrored = not all(s > 0 for s in best.signs)
    note = (f"the joint columns of legs {a} and {b} are exchanged"
            f"{span_text(best.from_station, best.until_station)}"
            f"{' with mirrored signs ' + str(list(best.signs)) if mirrored else ''}: exchanging them back drops the "
            f"chi-square at physical noise from {given.chi2:.0f} to {best.chi2:.0f} on {best.dof} dof "
            f"({margin:.0f} better than {runner.label()})"
            + _remaining_text(best, free, kinematic))
    corr = Correction(
        cause="legs_exchanged", where=tuple(sorted(where)),
        corrected=(("signs", tuple(int(s) for s in best.signs)), ("chi2_per_dof_given", given.chi2 / given.dof),
                   ("chi2_per_dof_corrected", best.chi2 / best.dof),
                   ("p_value_corrected", float(chi2_dist.sf(best.chi2, best.dof))),
                   ("chi2_legs_free", free)),
        statistic=float(given.chi2 - best.chi2), dof=int(best.dof), p_value=p_given, confidence=float(margin),
        alternatives=alternatives, note=note)
    say(f"joint columns: {note}")
    return (corr,), data, stalled


def _stalled_note(hyps: list) -> tuple:
    """() or the one note on the hypotheses ranked (best first) whose fit stalled: their chi-squares
    are upper bounds, so the ranking read on them is not final. None ranked (the gate closed): ()."""
    stalled = [h for h in hyps if h.stalled]
    if len(hyps) < 2 or not stalled:
        return ()
    from graphcal.diagnosis.model import stalled_text

    return (f"joint columns: {stalled_text([h.label() for h in stalled])}, and the ranking of the hypotheses on "
            f"{'it' if len(stalled) == 1 else 'them'} is not final (best {hyps[0].label()}, chi-square "
            f"{hyps[0].chi2:.0f})",)
