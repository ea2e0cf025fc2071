"""Does the identified leg model fit the data? Verdict, per-posture outlier test, jackknife, significance.

Input: the whitened residuals ``r`` (m,) and the whitened Jacobian ``A`` (m, u) of the free
unknowns at the final estimate, each row divided by the PHYSICAL noise the user declared (marker
and encoder sigma of dataset.yaml, else the documented defaults: 1 mm per marker coordinate, 0 for
the encoders), and the posture (sample time) of every row. Nothing here uses a noise level learned
from the same residuals.

* **Model adequacy** (:func:`adequacy`): ``chi2 = |r|^2`` against ``chi2(dof)``, ``dof = m - u``;
  p-value ``P(chi2(dof) >= chi2)``; ``fits`` when ``p >= ALPHA`` (1 %), else ``does not fit``.
  ``sigma0 = sqrt(chi2 / dof)`` is compared with its upper ``1 - ALPHA`` bound under the declared
  noise (``sqrt(chi2_{1-ALPHA}(dof) / dof)``, e.g. 1.05 for 3000 residuals). The *group* is the
  track (marker or measured frame) with the largest ``chi2 / rows``.
* **Posture outliers** (:func:`posture_tests`): for each posture P (its rows of every track),
  the deletion statistic ``d_P = r_P^T (I - H_PP)^-1 r_P`` (``H = A (A^T A)^-1 A^T``: the chi-square
  of predicting posture P from all the others; exact for the linearised problem) in an externally
  studentised F test ``F = (d_P / k) / ((chi2 - d_P) / (dof - k))`` ~ ``F(k, dof - k)`` (Pope's
  tau / Baarda's w test with the variance taken from the other postures, so a wrong declared
  noise level does not flag every posture), Bonferroni over the n postures: flagged when
  ``n * p_P < ALPHA``.
* **Jackknife** (:func:`jackknife_covariance`): leave-one-posture-out, linearised at the solution
  (the change of the estimate when posture P is deleted is ``(A^T A)^-1 A_P^T (I - H_PP)^-1 r_P``,
  exact for a linear model), ``V_J = (n - 1) / n sum (d_P - mean)(d_P - mean)^T``. Beside the model
  covariance; the larger sigma governs.
* **Significance** (:func:`significance`): ``z = |value| / sigma`` against the normal
  distribution, two-sided p-value, level 0.1 % / 1 % / 5 % or not significant.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.stats

__all__ = [
    "ALPHA",
    "DEFAULT_SIGMA_MARKER_M",
    "DEFAULT_SIGMA_JOINT_RAD",
    "PostureTest",
    "Adequacy",
    "adequacy",
    "posture_tests",
    "jackknife_covariance",
    "significance",
]

#: significance level of the verdict and (family-wise, Bonferroni) of the posture outlier test
ALPHA = 0.01
#: documented physical default of a motion-capture marker coordinate (m): an optical system
DEFAULT_SIGMA_MARKER_M = 0.001
#: documented default of a joint encoder (rad): exact encoders (a leg's absolute encoders are
#: ~0.01 deg; declare mocap.sigma_joint_deg in dataset.yaml otherwise)
DEFAULT_SIGMA_JOINT_RAD = 0.0
#: below this smallest eigenvalue of ``I - H_PP`` a posture alone determines a parameter: untestable
_MIN_REDUNDANCY = 1e-9


@dataclass(frozen=True)
class PostureTest:
    """Outlier test of one posture (all rows of all tracks at one sample time).

    Attributes:
        time: the posture's time (s).
        rows: whitened residual rows k of the posture.
        statistic: ``d_P`` (chi-square of predicting the posture from the others, declared noise).
        f_statistic: ``(d_P / k) / s_-P^2`` (nan when untestable).
        p_value: ``P(F(k, dof - k) >= f_statistic)``.
        p_bonferroni: ``min(1, n * p_value)``.
        flagged: ``p_bonferroni < ALPHA``.
        rms_mm: 3-D RMS of the posture's position errors (mm), for the report.
    """

    time: float
    rows: int
    statistic: float
    f_statistic: float
    p_value: float
    p_bonferroni: float
    flagged: bool
    rms_mm: float = float("nan")


@dataclass(frozen=True)
class Adequacy:
    """The verdict on one identification (field names shared with calibrate's ``adequacy:``).

    Attributes:
        verdict: ``"fits"`` or ``"does not fit"``.
        statistic: ``chi2`` of the whitened residuals with the declared noise.
        reference: ``"chi2(dof)"`` text; dof: its degrees of freedom.
        p_value: ``P(chi2(dof) >= statistic)``.
        group: the track carrying the largest misfit (``chi2 / rows``), or "" when it fits.
        group_sigma0: that track's ``sqrt(chi2 / rows)``.
        sigma0: ``sqrt(chi2 / dof)``; sigma0_limit: its upper ``1 - ALPHA`` bound under the declared noise.
        noise: the declared noise judged against (``sigma_marker_m``, ``sigma_joint_rad``, ``source``).
        alpha: level.
        postures: the :class:`PostureTest` of every posture.
        flagged: times of the flagged postures.
        without_flagged: ``(statistic, dof, p_value, verdict)`` with the flagged postures deleted
            (linearised), or None when none is flagged.
        message: one sentence for the console and the report.
    """

    verdict: str
    statistic: float
    reference: str
    dof: int
    p_value: float
    group: str
    group_sigma0: float
    sigma0: float
    sigma0_limit: float
    noise: dict
    alpha: float = ALPHA
    postures: tuple = field(default_factory=tuple)
    flagged: tuple = field(default_factory=tuple)
    without_flagged: tuple | None = None
    message: str = ""

    @property
    def fits(self) -> bool:
        return self.verdict == "fits"

    def as_dict(self) -> dict:
        """Plain values for legs.yaml (``adequacy:``)."""
        d = {"verdict": self.verdict, "statistic": float(self.statistic), "reference": self.reference,
             "dof": int(self.dof), "p_value": float(self.p_value), "alpha": float(self.alpha),
             "group": self.group, "group_sigma0": float(self.group_sigma0), "sigma0": float(self.sigma0),
             "sigma0_limit": float(self.sigma0_limit), "judged_against": dict(self.noise),
             "flagged_postures": [float(t) for t in self.flagged],
             "outlier_test": "per posture: deletion chi-square in an F test against the other postures, "
                             f"Bonferroni over {len(self.postures)} postures at {self.alpha:g}"}
        if self.without_flagged is not None:
            s, dof, p, v = self.without_flagged
            d["without_flagged"] = {"statistic": float(s), "dof": int(dof), "p_value": float(p), "verdict": v}
        d["message"] = self.message
        return d


def _deletion(A: np.ndarray, r: np.ndarray, M: np.ndarray, rows: np.ndarray):
    """(d, delta) for deleting ``rows``: d = r_P^T (I - H_PP)^-1 r_P, delta = M A_P^T (I - H_PP)^-1 r_P;
    None when the rows alone determine a direction."""
    AP, rP = A[rows], r[rows]
    W = np.eye(len(rows)) - AP @ M @ AP.T
    W = 0.5 * (W + W.T)
    if np.linalg.eigvalsh(W).min() < _MIN_REDUNDANCY:
        return None
    y = np.linalg.solve(W, rP)
    return float(rP @ y), M @ (AP.T @ y)


def _normal_inverse(A: np.ndarray) -> np.ndarray:
    return np.linalg.pinv(A.T @ A, rcond=1e-12, hermitian=True)


def posture_tests(A, r, posture, *, alpha: float = ALPHA, position_errors_mm=None) -> tuple[PostureTest, ...]:
    """Outlier test of every posture (module docstring).

    Args:
        A: (m, u) whitened Jacobian of the free unknowns (declared noise).
        r: (m,) whitened residuals.
        posture: (m,) the posture (time, s) of each row.
        alpha: family-wise level.
        position_errors_mm: optional posture time -> 3-D RMS position error (mm), copied into the tests.
    """
    A, r, posture = np.asarray(A, float), np.asarray(r, float), np.asarray(posture, float)
    m, u = A.shape
    dof = m - u
    chi2 = float(r @ r)
    M = _normal_inverse(A)
    times = np.unique(posture)
    n = len(times)
    stats = []  # (time, k, d, F) per posture; the p-values in one call below
    for t in times:
        rows = np.flatnonzero(posture == t)
        k = len(rows)
        dd = _deletion(A, r, M, rows) if dof - k > 0 else None
        if dd is None:
            stats.append((float(t), k, float("nan"), float("nan")))
        else:
            stats.append((float(t), k, dd[0], (dd[0] / k) / (max(chi2 - dd[0], 1e-300) / (dof - k))))
    ks = np.array([x[1] for x in stats], dtype=float)
    F = np.array([x[3] for x in stats], dtype=float)
    ok = np.isfinite(F)
    p = np.full(n, np.nan)
    p[ok] = scipy.stats.f.sf(F[ok], ks[ok], dof - ks[ok])
    out = []
    for (t, k, d, f), pv in zip(stats, p.tolist()):
        pb = min(1.0, n * pv) if math.isfinite(pv) else float("nan")
        rms = float("nan") if position_errors_mm is None else float(position_errors_mm.get(t, float("nan")))
        out.append(PostureTest(t, k, d, f, pv, pb, bool(math.isfinite(pb) and pb < alpha), rms))
    return tuple(out)


def jackknife_covariance(A, r, posture) -> np.ndarray:
    """(u, u) leave-one-posture-out jackknife covariance of the free unknowns (linearised; module
    docstring), in the units of the columns of ``A``. Postures that alone determine a direction
    are skipped."""
    A, r, posture = np.asarray(A, float), np.asarray(r, float), np.asarray(posture, float)
    M = _normal_inverse(A)
    deltas = []
    for t in np.unique(posture):
        dd = _deletion(A, r, M, np.flatnonzero(posture == t))
        if dd is not None:
            deltas.append(dd[1])
    n = len(deltas)
    if n < 2:
        return np.full((A.shape[1], A.shape[1]), np.nan)
    D = np.array(deltas)
    D = D - D.mean(axis=0)
    return (n - 1) / n * (D.T @ D)


def adequacy(A, r, posture, track_of_row, noise: dict, *, alpha: float = ALPHA,
             position_errors_mm=None) -> Adequacy:
    """The verdict (module docstring).

    Args:
        A: (m, u) whitened Jacobian; r: (m,) whitened residuals (declared noise ``noise``).
        posture: (m,) posture time of each row (s).
        track_of_row: (m,) track name of each row.
        noise: the declared noise (``sigma_marker_m``, ``sigma_joint_rad``, ``source``), reported.
        alpha: level.
        position_errors_mm: optional posture time -> RMS position error (mm).
    """
    A, r = np.asarray(A, float), np.asarray(r, float)
    m, u = A.shape
    dof = m - u
    chi2 = float(r @ r)
    if dof <= 0:
        return Adequacy("fits", chi2, f"chi2({dof})", dof, float("nan"), "", float("nan"), float("nan"), float("nan"),
                        dict(noise), alpha, message="no redundancy: the fit is exact and cannot be checked")
    p = float(scipy.stats.chi2.sf(chi2, dof))
    sigma0 = math.sqrt(chi2 / dof)
    limit = math.sqrt(float(scipy.stats.chi2.isf(alpha, dof)) / dof)
    tracks = np.asarray(track_of_row)
    per = {str(t): float(np.mean(r[tracks == t] ** 2)) for t in dict.fromkeys(tracks.tolist())}
    worst = max(per, key=per.get)
    tests = posture_tests(A, r, posture, alpha=alpha, position_errors_mm=position_errors_mm)
    flagged = tuple(t.time for t in tests if t.flagged)
    without = None
    if flagged:
        rows = np.flatnonzero(np.isin(np.asarray(posture, float), flagged))
        dd = _deletion(A, r, _normal_inverse(A), rows) if dof - len(rows) > 0 else None
        if dd is not None:
            s2, dof2 = chi2 - dd[0], dof - len(rows)
            p2 = float(scipy.stats.chi2.sf(s2, dof2))
            without = (s2, dof2, p2, "fits" if p2 >= alpha else "does not fit")
    fits = p >= alpha
    verdict = "fits" if fits else "does not fit"
    src = noise.get("source", "")
    if fits:
        msg = (f"the model fits: chi2 {chi2:.1f} for {dof} dof (p = {p:.3g}) against the declared noise "
               f"({src}); sigma0 {sigma0:.2f}")
    else:
        msg = (f"the model does NOT fit: chi2 {chi2:.1f} for {dof} dof (p = {p:.2g}) against the declared noise "
               f"({src}); sigma0 {sigma0:.2f} > {limit:.2f}, largest in {worst!r} ({math.sqrt(per[worst]):.2f})")
    if flagged:
        msg += (f"; {len(flagged)} posture(s) flagged as outliers (t = {', '.join(f'{t:g}' for t in flagged)})")
        if without is not None:
            msg += f", without them chi2 {without[0]:.1f} for {without[1]} dof: {without[3]}"
        msg += "; next: check those postures, remove them or rerun with --robust huber"
    elif not fits:
        msg += ("; next: a richer leg model (--origins all), the declared noise (mocap.sigma_mm, "
                "mocap.sigma_joint_deg in dataset.yaml) or --robust huber")
    return Adequacy(verdict, chi2, f"chi2({dof})", dof, p, "" if fits and not flagged else worst,
                    math.sqrt(per[worst]), sigma0, limit, dict(noise), alpha, tests, flagged, without, msg)


def significance(value: float, sigma: float) -> dict:
    """``{z, p_value, level}``: ``z = |value| / sigma``, two-sided normal p-value, and the level
    (``"0.1 %"``, ``"1 %"``, ``"5 %"`` or ``"not significant"``)."""
    if not (sigma > 0 and math.isfinite(sigma)):
        return {"z": float("nan"), "p_value": float("nan"), "level": "not tested"}
    z = abs(float(value)) / float(sigma)
    p = float(2.0 * scipy.stats.norm.sf(z))
    level = "0.1 %" if p < 0.001 else "1 %" if p < 0.01 else "5 %" if p < 0.05 else "not significant"
    return {"z": z, "p_value": p, "level": level}
