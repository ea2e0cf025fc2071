"""Is the filter consistent with its own covariance? A verdict from the NIS of each update kind
(stance kinematics, ICP, ...) over windows of the run.

Under the filter's model the NIS of an update with m measured dof is chi-square(m), and the NIS of
successive updates are independent (the innovations are white). Over a window of the run (default
10 s) the NIS of one kind summed over its n updates is then chi-square(D), D the summed dof; the
windowed mean NIS per dof ``sum NIS / D`` (1 when consistent) lies in the two-sided ``prob`` (95 %)
interval ``[chi2.ppf(a, D) / D, chi2.ppf(1 - a, D) / D]``, a = (1 - prob) / 2. A window outside
that interval is a window where the innovations do not fit the covariance (too large: noise or a
model error the filter does not know; too small: noise overstated).

The verdict of a kind: ``statistic`` = the number of windows outside their interval, reference
distribution Binomial(n_windows, 1 - prob) (what a consistent filter gives), ``p_value`` = P(at
least that many); ``inconsistent`` when the p-value is below ``alpha`` (default 0.01), and always
when the mean NIS per dof over the whole run is outside its interval widened by ``tolerance``
(default 0.1 relative: rounding, discretisation of the IMU integration, the filter's slip noise --
a run of thousands of updates has an interval of a percent or two, narrower than those). Overall:
``inconsistent`` when any kind is. A kind with no update is ``not tested``.

The whole-run mean NIS per dof and its own chi-square p-value are reported beside the verdict
(information: with tens of thousands of dof the test is sensitive to percent-level effects).
"""

from __future__ import annotations

import numpy as np

__all__ = ["nis_consistency", "consistency_verdict", "innovation_bias"]


def nis_consistency(times, nis, dof, *, window_s: float = 10.0, prob: float = 0.95, alpha: float = 0.01,
                    tolerance: float = 0.1) -> dict:
    """The windowed NIS test of one update kind (module docstring).

    Args:
        times: (K,) time of each update, s.
        nis: (K,) NIS of each update.
        dof: (K,) measured dof of each update (or one number for all).
        window_s: window length, s (the last window takes the remainder when shorter than half a
            window; a run shorter than a window is one window).
        prob: two-sided probability of each window's interval.
        alpha: significance level of the verdict.
        tolerance: relative widening of the whole-run interval (module docstring).

    Returns:
        dict with ``verdict`` (``consistent`` / ``inconsistent`` / ``not tested``), ``statistic``,
        ``reference``, ``p_value``, ``n_windows``, ``fraction_outside``, ``windows`` (per window:
        start and end s, updates, mean NIS per dof, its interval and two-sided p-value, outside),
        ``mean_nis_per_dof`` (whole run) with its interval and p-value, ``n_updates``.
    """
    from scipy.stats import binom, chi2

    t = np.asarray(times, dtype=float)
    x = np.asarray(nis, dtype=float)
    d = np.broadcast_to(np.asarray(dof, dtype=float), x.shape)
    ok = np.isfinite(t) & np.isfinite(x) & (d > 0)
    t, x, d = t[ok], x[ok], d[ok]
    a = (1.0 - prob) / 2.0
    out = {"n_updates": int(len(x)), "window_s": float(window_s), "interval_probability": prob, "alpha": alpha,
           "tolerance": tolerance}
    if len(x) == 0:
        return {**out, "verdict": "not tested", "statistic": None, "reference": None, "p_value": None,
                "n_windows": 0, "fraction_outside": None, "windows": [], "mean_nis_per_dof": None,
                "mean_interval": None, "mean_p_value": None}
    n_win = max(1, int(np.floor((t[-1] - t[0]) / window_s + 0.5)))
    edges = t[0] + window_s * np.arange(n_win + 1)
    edges[-1] = np.inf
    which = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, n_win - 1)
    windows = []
    for j in range(n_win):
        sel = which == j
        if not sel.any():
            continue
        D = float(d[sel].sum())
        s = float(x[sel].sum())
        lo, hi = float(chi2.ppf(a, D) / D), float(chi2.ppf(1.0 - a, D) / D)
        p = float(min(1.0, 2.0 * min(chi2.cdf(s, D), chi2.sf(s, D))))
        windows.append({"start_s": float(t[sel][0]), "end_s": float(t[sel][-1]), "updates": int(sel.sum()),
                        "dof": D, "mean_nis_per_dof": s / D, "interval": [lo, hi], "p_value": p,
                        "outside": bool(s / D < lo or s / D > hi)})
    k = sum(w["outside"] for w in windows)
    n = len(windows)
    p_val = float(binom.sf(k - 1, n, 1.0 - prob)) if k > 0 else 1.0
    D = float(d.sum())
    m = float(x.sum() / D)
    lo, hi = float(chi2.ppf(a, D) / D), float(chi2.ppf(1.0 - a, D) / D)
    lo_t, hi_t = lo * (1.0 - tolerance), hi * (1.0 + tolerance)
    bad = p_val < alpha or not (lo_t <= m <= hi_t)
    return {
        **out,
        "verdict": "inconsistent" if bad else "consistent",
        "statistic": int(k),
        "statistic_name": f"windows whose mean NIS per dof lies outside its chi-square {100 * prob:g} % interval",
        "reference": f"Binomial({n}, {1.0 - prob:g})",
        "p_value": p_val,
        "n_windows": n,
        "fraction_outside": k / n,
        "windows": windows,
        "mean_nis_per_dof": m,
        "mean_interval": [lo, hi],
        "mean_interval_with_tolerance": [lo_t, hi_t],
        "mean_p_value": float(min(1.0, 2.0 * min(chi2.cdf(m * D, D), chi2.sf(m * D, D)))),
    }


def consistency_verdict(kinds: dict, **kw) -> dict:
    """The verdict of every update kind and overall.

    Args:
        kinds: kind name -> (times (K,) s, NIS (K,), dof (K,) or one number).
        **kw: :func:`nis_consistency`'s options.

    Returns:
        ``{"verdict": ..., "kinds": {name: nis_consistency(...)}, "inconsistent_kinds": [...],
        "method": ...}``; overall ``inconsistent`` when any kind is, ``not tested`` when none was.
    """
    per = {name: nis_consistency(*v, **kw) for name, v in kinds.items()}
    bad = [name for name, r in per.items() if r["verdict"] == "inconsistent"]
    tested = [name for name, r in per.items() if r["verdict"] != "not tested"]
    verdict = "inconsistent" if bad else ("consistent" if tested else "not tested")
    return {
        "verdict": verdict,
        "inconsistent_kinds": bad,
        "kinds": per,
        "method": "per update kind: windowed mean NIS per dof against its chi-square interval; statistic = "
                  "windows outside, reference Binomial(windows, 1 - prob), p-value P(at least that many); "
                  "inconsistent when p < alpha or the whole-run mean is outside its interval widened by the "
                  "tolerance (graphcal.locomotion.consistency)",
    }


def innovation_bias(times, whitened, slot_names, *, block_s: float = 1.0, min_mean: float = 0.3,
                    min_t: float = 5.0) -> dict:
    """Are the stance innovations zero-mean? A leg model with a constant error (a joint's zero
    offset, a link length) leaves each foot's innovations biased in the body frame, a bias that
    neither the NIS level nor its windows see once the noise is matched to it.

    ``whitened`` (K, 3 n_slots): the stance innovations whitened by their covariance (NaN where a
    slot was not measured), at ``times`` (K,) s; ``slot_names``: a name per slot (a foot, or "slot
    i" when slots change feet). Per slot axis: the mean whitened innovation and its t statistic over
    blocks of ``block_s`` (the block means are ~independent, the samples are not). ``biased`` where
    both |mean| >= ``min_mean`` and |t| >= ``min_t`` (measured: right leg models 0.08 / 3.0 at most,
    5 mrad joint offsets 0.73 / 7.7; docs/state_estimation.md)."""
    w = np.asarray(whitened, dtype=float)
    t = np.asarray(times, dtype=float)
    if not len(w):
        return {"verdict": "not tested", "reason": "no stance update", "worst": None}
    blocks = np.floor((t - t[0]) / block_s).astype(np.int64)
    ids = np.unique(blocks)
    with np.errstate(invalid="ignore"):
        bm = np.array([np.nanmean(w[blocks == b], axis=0) if np.isfinite(w[blocks == b]).any() else
                       np.full(w.shape[1], np.nan) for b in ids])
        n = np.sum(np.isfinite(bm), axis=0)
        mean = np.nanmean(w, axis=0)
        tstat = np.nanmean(bm, axis=0) / (np.nanstd(bm, axis=0, ddof=1) / np.sqrt(np.maximum(n, 1)))
    ok = np.isfinite(tstat) & (n >= 5)
    if not ok.any():
        return {"verdict": "not tested", "reason": "fewer than 5 blocks of stance updates per axis", "worst": None}
    score = np.where(ok, np.minimum(np.abs(mean) / min_mean, np.abs(tstat) / min_t), -np.inf)
    k = int(np.argmax(score))
    worst = {"slot": slot_names[k // 3], "axis": "xyz"[k % 3], "mean_sigma": float(mean[k]), "t": float(tstat[k]),
             "blocks": int(n[k])}
    flagged = [{"slot": slot_names[j // 3], "axis": "xyz"[j % 3], "mean_sigma": float(mean[j]), "t": float(tstat[j])}
               for j in np.flatnonzero(score >= 1.0)]
    return {"verdict": "biased" if flagged else "unbiased", "worst": worst, "biased": flagged,
            "bounds": {"min_mean_sigma": min_mean, "min_t": min_t, "block_s": block_s}}
