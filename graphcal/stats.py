"""Chi-square distribution functions for the calibration's tests, from ``scipy.special`` (what
``scipy.stats.chi2`` calls underneath): importing ``scipy.stats`` costs ~1 s of every command,
``scipy.special`` is imported with the plane fits anyway. Degrees of freedom may be fractional (a
noise group's redundancy); arguments broadcast like numpy's."""

from __future__ import annotations

import numpy as np
from scipy.special import chdtrc, chdtri


def ppf(q, dof):
    """Quantile: the x with P(chi2(dof) <= x) = q (``scipy.stats.chi2.ppf``)."""
    return chdtri(np.asarray(dof, dtype=float), 1.0 - np.asarray(q, dtype=float))


def isf(p, dof):
    """Upper quantile: the x with P(chi2(dof) > x) = p (``scipy.stats.chi2.isf``)."""
    return chdtri(np.asarray(dof, dtype=float), np.asarray(p, dtype=float))


def sf(x, dof):
    """Upper tail P(chi2(dof) > x) (``scipy.stats.chi2.sf``)."""
    return chdtrc(np.asarray(dof, dtype=float), np.asarray(x, dtype=float))


def logsf(x, dof):
    """log of the upper tail, ``-inf`` where it underflows: ``scipy.stats.chi2.logsf`` to 1e-15
    (tests/test_chi2.py), without its ~40 us of argument handling per call."""
    with np.errstate(divide="ignore"):
        return np.log(sf(x, dof))
