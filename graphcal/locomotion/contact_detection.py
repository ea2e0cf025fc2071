"""Foot contacts from real signals: per-foot thresholds learned from each foot's own force (or
effort) signal, a hysteresis between them, and minimum stance and swing durations.

A foot's signal -- a foot-force sensor's reading in N, raw ADC counts with any offset and gain, or a
load derived from joint torques (N) -- has two modes over a walk: swing (near the sensor's offset)
and stance (the share of the body weight the foot carries). :func:`learn_thresholds` finds them
(the deepest valley of the histogram between robust quantiles, between the highest bins either
side of Otsu's split; then the median of each side) and puts the
hysteresis between them: ``off = low + off_fraction (high - low)``, ``on = low + on_fraction (high -
low)`` (defaults 0.2 and 0.4: 10 N and 20 N for a foot carrying 50 N). Everything is in the
signal's own unit, so the result does not depend on it (unit-agnostic: counts or N).

A foot whose signal shows no two separated modes (flat, always loaded, never loaded: a robot that
only stands, a dead sensor) raises :class:`ContactSignalError` naming the foot. Callers that have
a better guess pass ``fallback=(on, off)`` to :func:`detect_contacts` (the filter: its fixed N
thresholds; the import: the map's threshold); the result says which feet used it
(``source: fallback``).

:func:`stance_mask` applies the hysteresis (:func:`hysteresis_mask`)
and then drops runs shorter than the minimum durations (s): stances shorter than ``min_stance_s``
become swing, then swings shorter than ``min_swing_s`` become stance. The first and the last run of
a foot (cut by the log's ends) are kept whatever their length. Times in s throughout.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graphcal.errors import GraphcalError

__all__ = ["ContactSignalError", "ContactThresholds", "FootContacts", "ContactDetection", "learn_thresholds",
           "hysteresis_mask", "remove_short_runs", "stance_mask", "detect_contacts", "MIN_STANCE_S", "MIN_SWING_S"]

#: default minimum stance and swing durations (s): a third of the shortest stance or swing of a
#: fast trot (0.3 s cycle, duty 0.5: 150 ms), above the spurious ones of real logs (< 40 ms)
MIN_STANCE_S = 0.05
MIN_SWING_S = 0.05
#: two modes are separated when the histogram (40 bins between the robust quantiles, smoothed over
#: 3) dips between them to at most 1 - this of the smaller mode's peak (one Gaussian or uniform
#: spread: ~0; the simulated trot and walk: 0.98-0.99)
MIN_SEPARATION = 0.5
#: ... and when each mode holds at least this share of the samples
MIN_MODE_SHARE = 0.01


class ContactSignalError(GraphcalError):
    """A foot's force/effort signal from which no contact thresholds can be learned."""


@dataclass(frozen=True)
class ContactThresholds:
    """The contact thresholds of one foot, in the signal's own unit (N, or raw counts).

    Attributes:
        foot: foot frame name.
        on, off: a foot enters stance above ``on`` and leaves it below ``off`` (off <= on).
        low_mode, high_mode: the swing and stance modes of the signal (NaN when not learned).
        source: ``learned`` (from the signal), ``fixed`` (given), ``fallback`` (given because the
            signal had no two modes) or ``contact`` (a 0/1 or probability column, threshold 0.5).
        separation: depth of the histogram's valley between the modes, 0-1 (1: no sample between
            them; NaN when not learned).
    """

    foot: str
    on: float
    off: float
    low_mode: float = float("nan")
    high_mode: float = float("nan")
    source: str = "learned"
    separation: float = float("nan")


@dataclass(frozen=True)
class FootContacts:
    """What the detection found for one foot: its ``thresholds``, ``duty_factor`` (share of the
    samples in stance, whole log), ``n_stances`` (stance runs kept), ``n_short_stances`` and
    ``n_short_swings`` (runs removed by the minimum durations)."""

    thresholds: ContactThresholds
    duty_factor: float
    n_stances: int
    n_short_stances: int
    n_short_swings: int

    def as_dict(self) -> dict:
        """Plain numbers for metrics.json / a report (thresholds in the signal's unit)."""
        t = self.thresholds
        return {"source": t.source, "on": _num(t.on), "off": _num(t.off), "low_mode": _num(t.low_mode),
                "high_mode": _num(t.high_mode), "separation": _num(t.separation),
                "duty_factor": round(float(self.duty_factor), 4), "n_stances": int(self.n_stances),
                "n_short_stances_removed": int(self.n_short_stances), "n_short_swings_removed": int(self.n_short_swings)}


def _num(v: float):
    return None if not np.isfinite(v) else float(round(float(v), 6))


@dataclass(frozen=True, eq=False)
class ContactDetection:
    """``mask`` (N, n_feet) bool stance per sample and foot; ``feet`` one :class:`FootContacts` per
    column; ``min_stance_s``, ``min_swing_s`` the durations used (s)."""

    mask: np.ndarray
    feet: tuple
    min_stance_s: float
    min_swing_s: float

    def summary(self) -> dict:
        """foot -> :meth:`FootContacts.as_dict`."""
        return {f.thresholds.foot: f.as_dict() for f in self.feet}


def _robust(x: np.ndarray) -> np.ndarray:
    """The finite samples between the 0.5 % and 99.5 % quantiles (spikes out)."""
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return x
    lo, hi = np.quantile(x, [0.005, 0.995])
    return x[(x >= lo) & (x <= hi)]


def _histogram(x: np.ndarray, bins: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """(counts, edges) of ``x``: at least 3 bins, no narrower than the signal's quantisation step
    (raw counts are integers; a 0/1 signal gets an empty middle bin), smoothed over 3 bins when
    there are 10 or more."""
    u = np.unique(x)
    step = float(np.min(np.diff(u))) if len(u) > 1 else 1.0
    n = int(max(3, min(bins, np.ceil(np.ptp(x) / step) + 1)))
    h, edges = np.histogram(x, bins=n)
    if n < 10:
        return h.astype(float), edges
    smooth = np.convolve(np.pad(h.astype(float), 1, mode="edge"), np.ones(3) / 3.0, mode="valid")
    return smooth, edges


def _otsu_bin(h: np.ndarray) -> int:
    """Otsu's split of a histogram: the number of bins below it (1..len(h) - 1)."""
    c = np.arange(len(h), dtype=float)
    w0 = np.cumsum(h)[:-1]
    w1 = h.sum() - w0
    s0 = np.cumsum(h * c)[:-1]
    m0 = s0 / np.maximum(w0, 1e-12)
    m1 = (float(np.sum(h * c)) - s0) / np.maximum(w1, 1e-12)
    return int(np.argmax(w0 * w1 * (m0 - m1) ** 2)) + 1


def _valley(x: np.ndarray) -> tuple[float, float]:
    """(split value, valley depth 0-1) of ``x``: the deepest bin of the histogram between the
    highest bin either side of Otsu's split, and ``1 - valley / smaller peak`` (0: one mode)."""
    h, edges = _histogram(x)
    k = _otsu_bin(h)
    p_lo, p_hi = int(np.argmax(h[:k])), k + int(np.argmax(h[k:]))
    v = p_lo + int(np.argmin(h[p_lo : p_hi + 1]))
    peak = min(h[p_lo], h[p_hi])
    depth = 1.0 - h[v] / peak if peak > 0 else 0.0
    return float(0.5 * (edges[v] + edges[v + 1])), float(depth)


def learn_thresholds(signal, foot: str, *, on_fraction: float = 0.4, off_fraction: float = 0.2) -> ContactThresholds:
    """The contact thresholds of ``foot`` from its own signal (N,) (any unit: N or raw counts):
    the swing and stance modes (medians either side of the histogram's valley), ``on`` and ``off``
    at ``on_fraction`` and ``off_fraction`` of the way from the low mode to the high one.

    Raises:
        ContactSignalError: the signal is flat, or shows no two separated modes (an always or never
            loaded foot), naming the foot and what was found.
    """
    if not 0.0 <= off_fraction <= on_fraction <= 1.0:
        raise GraphcalError(f"contact thresholds: expected 0 <= off_fraction <= on_fraction <= 1, got "
                            f"{off_fraction}, {on_fraction}")
    x = _robust(np.asarray(signal, dtype=float).ravel())
    if len(x) < 10 or float(np.ptp(x)) == 0.0:
        got = f"{len(x)} finite samples" if len(x) < 10 else f"a flat signal at {x[0]:.4g}"
        raise ContactSignalError(f"foot {foot}: expected a force/effort signal with a swing and a stance mode to "
                                 f"learn contact thresholds from, got {got}")
    split, depth = _valley(x)
    low_side, high_side = x[x <= split], x[x > split]
    frac = min(len(low_side), len(high_side)) / len(x)
    if depth < MIN_SEPARATION or frac < MIN_MODE_SHARE:
        q5, q50, q95 = np.quantile(x, [0.05, 0.5, 0.95])
        raise ContactSignalError(
            f"foot {foot}: expected a force/effort signal with two separated modes (swing and stance: a histogram "
            f"valley >= {MIN_SEPARATION:.0%} deep, each mode >= {MIN_MODE_SHARE:.0%} of the samples), got one mode "
            f"(median {q50:.4g}, 5-95 % {q5:.4g}..{q95:.4g}; valley {depth:.0%} deep, smaller side {frac:.1%}): "
            f"a foot always or never loaded, or a flat signal")
    low, high = float(np.median(low_side)), float(np.median(high_side))
    span = high - low
    return ContactThresholds(foot, low + on_fraction * span, low + off_fraction * span, low, high, "learned", depth)


def hysteresis_mask(loads, on, off) -> np.ndarray:
    """(N, n_feet) bool: a foot enters stance when its load (N, n_feet) exceeds ``on`` and leaves
    it below ``off`` (numbers or one per foot, the loads' unit, off <= on); before its first
    decisive sample it is in stance when its first load is above the midpoint."""
    loads = np.asarray(loads, dtype=float)
    N, n = loads.shape
    on = np.broadcast_to(np.asarray(on, dtype=float), (n,))
    off = np.broadcast_to(np.asarray(off, dtype=float), (n,))
    bad = np.flatnonzero(~(off <= on))
    if bad.size:
        i = int(bad[0])
        raise GraphcalError(f"contact thresholds (column {i}): expected off ({off[i]:g}) not to exceed on ({on[i]:g})")
    up = loads > on
    down = loads < off
    # the state is the last decisive sample's: forward-fill the index of the last up/down sample
    last = np.where(up | down, np.arange(N)[:, None], -1)
    np.maximum.accumulate(last, axis=0, out=last)
    first = loads[0] > 0.5 * (on + off) if N else np.zeros(n, dtype=bool)
    return np.where(last >= 0, np.take_along_axis(up, np.maximum(last, 0), axis=0), first[None, :])


def _runs(col: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(start index, end index exclusive) of the runs of equal values of a bool column."""
    change = np.flatnonzero(col[1:] != col[:-1]) + 1
    starts = np.concatenate([[0], change])
    ends = np.concatenate([change, [len(col)]])
    return starts, ends


def _drop_runs(col: np.ndarray, times: np.ndarray, value: bool, min_s: float) -> tuple[np.ndarray, int]:
    """``col`` with the inner runs of ``value`` shorter than ``min_s`` (s) flipped; how many."""
    if min_s <= 0 or len(col) < 3:
        return col, 0
    starts, ends = _runs(col)
    t_end = np.append(times, times[-1])  # a run lasts from its first sample to the next run's first
    dur = t_end[ends] - times[starts]
    inner = np.zeros(len(starts), dtype=bool)
    inner[1:-1] = True
    short = inner & (col[starts] == value) & (dur < min_s)
    run_of = np.repeat(np.arange(len(starts)), ends - starts)  # the run of each sample
    out = np.where(short[run_of], not value, col)
    return out, int(short.sum())


def remove_short_runs(mask, times, *, min_stance_s: float = MIN_STANCE_S,
                      min_swing_s: float = MIN_SWING_S) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mask, stances removed per foot, swings removed per foot): inner stance runs shorter than
    ``min_stance_s`` (s) become swing, then inner swing runs shorter than ``min_swing_s`` become
    stance. ``mask`` (N, n_feet) bool, ``times`` (N,) s increasing."""
    mask = np.asarray(mask, dtype=bool)
    times = np.asarray(times, dtype=float)
    out = mask.copy()
    n_st = np.zeros(mask.shape[1], dtype=np.int64)
    n_sw = np.zeros(mask.shape[1], dtype=np.int64)
    for i in range(mask.shape[1]):
        out[:, i], n_st[i] = _drop_runs(out[:, i], times, True, min_stance_s)
        out[:, i], n_sw[i] = _drop_runs(out[:, i], times, False, min_swing_s)
    return out, n_st, n_sw


def stance_mask(signals, times, thresholds, *, min_stance_s: float = MIN_STANCE_S,
                min_swing_s: float = MIN_SWING_S) -> ContactDetection:
    """The stance mask of ``signals`` (N, n_feet) at ``times`` (N,) s with one
    :class:`ContactThresholds` per column: a hysteresis per foot, then the minimum durations (s)."""
    x = np.asarray(signals, dtype=float)
    on = np.array([t.on for t in thresholds])
    off = np.array([t.off for t in thresholds])
    raw = hysteresis_mask(x, on, off)
    mask, n_st, n_sw = remove_short_runs(raw, times, min_stance_s=min_stance_s, min_swing_s=min_swing_s)
    feet = []
    for i, t in enumerate(thresholds):
        starts, _ = _runs(mask[:, i]) if len(mask) else (np.zeros(0, dtype=np.int64), None)
        n_runs = int(np.count_nonzero(mask[starts, i])) if len(mask) else 0
        duty = float(mask[:, i].mean()) if len(mask) else 0.0
        feet.append(FootContacts(t, duty, n_runs, int(n_st[i]), int(n_sw[i])))
    return ContactDetection(mask, tuple(feet), float(min_stance_s), float(min_swing_s))


def detect_contacts(signals, times, feet, *, thresholds: str = "learned", fixed=None, fallback=None,
                    min_stance_s: float = MIN_STANCE_S, min_swing_s: float = MIN_SWING_S) -> ContactDetection:
    """Stance of every foot from its signal (N, n_feet) at ``times`` (N,) s, ``feet`` the columns' names.

    Args:
        thresholds: ``learned`` (per foot, :func:`learn_thresholds`) or ``fixed`` (``fixed`` for all).
        fixed: (on, off) in the signal's unit, for ``thresholds="fixed"``.
        fallback: (on, off), or per foot a dict foot -> (on, off), used for a foot whose signal has
            no two modes; None: that foot's :class:`ContactSignalError` is raised.
        min_stance_s, min_swing_s: minimum durations (s), see :func:`remove_short_runs`.
    """
    x = np.asarray(signals, dtype=float)
    if x.ndim != 2 or x.shape[1] != len(feet):
        raise GraphcalError(f"contact detection: expected signals of shape (N, {len(feet)}), got {x.shape}")
    if thresholds not in ("learned", "fixed"):
        raise GraphcalError(f"contact thresholds: expected learned or fixed, got {thresholds!r}")
    if thresholds == "fixed":
        on, off = fixed
        th = [ContactThresholds(f, float(on), float(off), source="fixed") for f in feet]
    else:
        th = [_learned_or_fallback(x[:, i], f, fallback) for i, f in enumerate(feet)]
    return stance_mask(x, times, th, min_stance_s=min_stance_s, min_swing_s=min_swing_s)


def _learned_or_fallback(signal: np.ndarray, foot: str, fallback) -> ContactThresholds:
    try:
        return learn_thresholds(signal, foot)
    except ContactSignalError:
        fb = fallback.get(foot) if isinstance(fallback, dict) else fallback
        if fb is None:
            raise
        return ContactThresholds(foot, float(fb[0]), float(fb[1]), source="fallback")
