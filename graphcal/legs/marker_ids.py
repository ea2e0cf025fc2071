"""Exchanged marker ids in motion-capture data (issue 29): two feet's marker tracks filed under each other's name.

A motion-capture export that labels foot a's marker with foot b's id (and b's with a's) pairs every
sample of both markers with the other leg's joint angles: the identification then fits huge,
confidently wrong joint offsets and link changes to both legs (measured on a simulated A1 with
four feet, fl and fr exchanged: offsets of 0.2-1.6 rad, marker RMSE 422 -> 249 mm, verdict "does
not fit"). Looked for only when the identification does not fit at the declared noise by far
(sigma0 above :data:`MAX_SIGMA0`; free on data that fit):

1. for each pair of the :data:`CANDIDATE_TRACKS` marker tracks with the largest "before" errors
   (nominal legs, pose fitted) that lie on different feet and are sampled at the same times, the
   measured positions exchanged and the legs identified again; each hypothesis is scored by the
   identification's chi-square at the declared noise (the adequacy statistic). (The errors do not
   always concentrate on the two exchanged tracks: fr and rl of an A1 exchanged left the
   second-worst track's mean squared error only 1.4x the third's, so every pair of the worst
   four is tried.)
2. the exchange is applied only when its identification fits at the declared noise (verdict
   "fits", or sigma0 at most :data:`MAX_SIGMA0`: data whose own noise is above the declared one,
   e.g. undeclared body-marker noise, do not fit even when clean) and beats the next-best
   hypothesis (another pair, or the data as given) by at least :data:`MIN_CONFIDENCE` in
   chi-square; otherwise a note says what was suspected.

What is returned is the identification of the corrected tracks with a warning naming the exchange
and its evidence (the dataset is not changed).
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass

import numpy as np

from graphcal.legs.mocap_data import MarkerTrack

__all__ = ["ExchangeEvidence", "MarkerExchange", "exchange_markers", "find_exchanged_markers", "PostureExchange", "exchange_postures",
           "find_exchanged_postures", "CANDIDATE_TRACKS", "CANDIDATE_POSTURES", "MAX_SIGMA0", "MIN_CONFIDENCE"]

#: the marker tracks with the largest "before" errors whose pairs are tested
CANDIDATE_TRACKS = 4
#: the corrected identification's sigma0 (sqrt(chi2 / dof) at the declared noise) up to which it
#: counts as fitting (measured: 1.4 on clean simulated A1 data with undeclared body-marker noise,
#: 170 with two markers' ids exchanged)
MAX_SIGMA0 = 3.0
#: chi-square margin (declared noise) by which the exchange must beat the next-best hypothesis
MIN_CONFIDENCE = 25.0


@dataclass(frozen=True)
class ExchangeEvidence:
    """How an exchange of two labels (marker ids, postures) was judged, at the declared noise.

    Attributes:
        chi2_given, chi2_corrected: the identification's chi-square as given and with the labels
            exchanged back; dof: the corrected identification's degrees of freedom.
        confidence: chi-square margin over the next-best hypothesis.
        alternatives: hypotheses within MIN_CONFIDENCE of it (labels).
        note: one sentence for the report.
    """

    chi2_given: float
    chi2_corrected: float
    dof: int
    confidence: float
    alternatives: tuple = ()
    note: str = ""


@dataclass(frozen=True)
class MarkerExchange:
    """Two marker tracks' measured positions exchanged (their ids swapped in the export).

    Attributes:
        markers: (a, b) the marker names; feet: their feet; evidence: how it was judged.
    """

    markers: tuple
    feet: tuple
    evidence: ExchangeEvidence


def _best_exchange(scored: list, what: str) -> tuple:
    """(best, note) of the hypotheses ``scored`` ((label, chi2, identification, key) each; key None
    for the data as given, which must be among them). ``best``: (chi2, identification, key, margin
    over the runner-up, alternatives within MIN_CONFIDENCE, the runner-up's label) of the best
    exchange, or None when the data as given are best, or when the best does not fit (sigma0 above
    MAX_SIGMA0) or beats the runner-up by less than MIN_CONFIDENCE; ``note``: then the sentence
    that says so (``what``: what the exchange would explain), else None."""
    scored = sorted(scored, key=lambda s: s[1])
    label, chi2, best, key = scored[0]
    if key is None:
        return None, None
    given = next(s[1] for s in scored if s[3] is None)
    margin = scored[1][1] - chi2
    alternatives = tuple(s[0] for s in scored[1:] if s[1] - chi2 < MIN_CONFIDENCE)
    fits = best.adequacy.fits or best.adequacy.sigma0 <= MAX_SIGMA0
    if not fits or margin < MIN_CONFIDENCE:
        why = "the legs still do not fit after it" if not fits else \
            f"{scored[1][0]} explains the data almost as well (chi-square {margin:.1f} apart)"
        return None, (f"{label} is the best explanation tried of {what} (chi-square {given:.0f} -> {chi2:.0f} at "
                      f"the declared noise), but {why}: not corrected")
    return (chi2, best, key, margin, alternatives, scored[1][0]), None


def exchange_markers(tracks, a: str, b: str) -> tuple:
    """``tracks`` with the measured positions (and their extra covariance) of markers ``a`` and
    ``b`` exchanged; both must be :class:`MarkerTrack` sampled at the same times."""
    ta = next(t for t in tracks if t.marker == a)
    tb = next(t for t in tracks if t.marker == b)
    out = []
    for t in tracks:
        if t.marker == a:
            t = dataclasses.replace(t, p_meas=tb.p_meas, cov_extra=tb.cov_extra)
        elif t.marker == b:
            t = dataclasses.replace(t, p_meas=ta.p_meas, cov_extra=ta.cov_extra)
        out.append(t)
    return tuple(out)


def _mse_before(result) -> dict:
    """marker -> mean squared "before" error (m^2), worst first."""
    mse = {r.marker: float(np.mean(np.sum(np.asarray(r.before) ** 2, axis=1))) for r in result.residuals
           if len(r.before)}
    return dict(sorted(mse.items(), key=lambda kv: -kv[1]))


def _pairs(tracks, worst: list) -> list:
    by_name = {t.marker: t for t in tracks}
    out = []
    for a, b in itertools.combinations(worst, 2):
        ta, tb = by_name.get(a), by_name.get(b)
        if isinstance(ta, MarkerTrack) and isinstance(tb, MarkerTrack) and ta.foot != tb.foot \
                and ta.time.shape == tb.time.shape and np.allclose(ta.time, tb.time):
            out.append((a, b))
    return out


def find_exchanged_markers(result, tracks, identify) -> tuple:
    """(MarkerExchange or None, the identification to report, notes) for an identification
    ``result`` of ``tracks``; ``identify(tracks)`` identifies the legs again from other tracks
    (same options). Returns ``result`` itself unless an exchange is applied."""
    if result.adequacy is None or result.adequacy.fits or result.adequacy.sigma0 <= MAX_SIGMA0:
        return None, result, ()
    mse = _mse_before(result)
    pairs = _pairs(tracks, list(mse)[:CANDIDATE_TRACKS])
    if not pairs:
        return None, result, ()
    scored = [("the data as given", result.adequacy.statistic, result, None)]
    for a, b in pairs:
        res = identify(exchange_markers(tracks, a, b))
        if res.adequacy is not None:
            scored.append((f"markers {a} and {b} exchanged", res.adequacy.statistic, res, (a, b)))
    exchange, refused = _best_exchange(scored, "the markers' errors")
    if exchange is None:
        return None, result, () if refused is None else (refused,)
    chi2, best, pair, margin, alternatives, runner_up = exchange
    order = [t.marker for t in tracks]
    pair = tuple(sorted(pair, key=order.index))
    feet = tuple(next(t.foot for t in tracks if t.marker == m) for m in pair)
    note = (f"the ids of markers {pair[0]} ({feet[0]}) and {pair[1]} ({feet[1]}) are exchanged in the data: "
            f"exchanging their positions back drops the identification's chi-square at the declared noise from "
            f"{result.adequacy.statistic:.0f} to {chi2:.0f} ({best.adequacy.reference}), {margin:.0f} better than "
            f"{runner_up}; the legs were identified from the corrected markers")
    found = MarkerExchange(pair, feet, ExchangeEvidence(float(result.adequacy.statistic), float(chi2),
                                                        int(best.adequacy.dof), float(margin), alternatives, note))
    return found, dataclasses.replace(best, warnings=tuple(best.warnings) + (note,)), ()


# ----------------------------------------------------------------------------- two postures' labels exchanged
#: the flagged postures (largest outlier statistic first) whose pairs are tested
CANDIDATE_POSTURES = 4


@dataclass(frozen=True)
class PostureExchange:
    """Two postures' marker positions exchanged (each posture's joint angles logged with the other's
    motion-capture frame).

    Attributes:
        times: (t1, t2) the postures' times (s); evidence: how it was judged.
    """

    times: tuple
    evidence: ExchangeEvidence


def exchange_postures(tracks, t1: float, t2: float) -> tuple:
    """``tracks`` with the measured positions (and extra covariance) of the samples at times ``t1``
    and ``t2`` exchanged in every :class:`MarkerTrack` that has both (joint angles kept)."""
    out = []
    for t in tracks:
        i = np.flatnonzero(np.isclose(t.time, t1)) if isinstance(t, MarkerTrack) else ()
        j = np.flatnonzero(np.isclose(t.time, t2)) if isinstance(t, MarkerTrack) else ()
        if len(i) == 1 and len(j) == 1:
            p = np.array(t.p_meas, dtype=float)
            p[[i[0], j[0]]] = p[[j[0], i[0]]]
            ce = None
            if t.cov_extra is not None:
                ce = np.array(t.cov_extra, dtype=float)
                ce[[i[0], j[0]]] = ce[[j[0], i[0]]]
            t = dataclasses.replace(t, p_meas=p, cov_extra=ce)
        out.append(t)
    return tuple(out)


def find_exchanged_postures(result, tracks, identify) -> tuple:
    """(PostureExchange or None, the identification to report, notes) for an identification
    ``result`` of ``tracks`` whose per-posture outlier test flags two postures or more: each pair
    of the :data:`CANDIDATE_POSTURES` most outlying flagged postures exchanged and the legs
    identified again (``identify(tracks)``); applied when it fits (as :func:`find_exchanged_markers`)
    and beats the next-best hypothesis by :data:`MIN_CONFIDENCE` in chi-square."""
    a = result.adequacy
    if a is None or a.fits or len(a.flagged) < 2:
        return None, result, ()
    flagged = sorted((p for p in a.postures if p.flagged), key=lambda p: -p.statistic)[:CANDIDATE_POSTURES]
    scored = [("the data as given", a.statistic, result, None)]
    for p, q in itertools.combinations(flagged, 2):
        res = identify(exchange_postures(tracks, p.time, q.time))
        if res.adequacy is not None:
            times = tuple(sorted((float(p.time), float(q.time))))
            scored.append((f"postures at {times[0]:g} s and {times[1]:g} s exchanged", res.adequacy.statistic, res,
                           times))
    exchange, refused = _best_exchange(scored, "the flagged postures")
    if exchange is None:
        return None, result, () if refused is None else (refused,)
    chi2, best, times, margin, alternatives, runner_up = exchange
    note = (f"the motion-capture samples of the postures at {times[0]:g} s and {times[1]:g} s are exchanged "
            f"(each posture's joint angles logged with the other's markers): exchanging them back drops the "
            f"identification's chi-square at the declared noise from {a.statistic:.0f} to {chi2:.0f} "
            f"({best.adequacy.reference}), {margin:.0f} better than {runner_up}; the legs were identified "
            f"from the corrected samples")
    found = PostureExchange(times, ExchangeEvidence(float(a.statistic), float(chi2), int(best.adequacy.dof),
                                                    float(margin), alternatives, note))
    return found, dataclasses.replace(best, warnings=tuple(best.warnings) + (note,)), ()
