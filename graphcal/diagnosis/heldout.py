"""Held-out gain: how much better the extended model predicts sensor measurements it was not fitted on.

Two folds by station (even and odd positions in the dataset's order). In each fold both models are
fitted without the held-out stations' sensor measurements (their joint angles, IMU and commanded
pose stay: they place the body), and the held-out measurements are predicted; the gain is the RMS
of the whitened prediction residuals, pooled over both folds, before and after the extension.

The refits are Gauss-Newton steps on the whitened linearisation at the current model's optimum
(the screening system of scores.py, which already holds the candidate's columns): exact for a
linear model and, near the optimum, within a few per cent of a full nonlinear refit at a
hundredth of the cost (the extension's own parameters start at their nominal value, where the
screening linearised them).

Significance: a ratio below 1 is not evidence (wrong causes scored 0.70-1.03 on an independent
robot). :func:`paired_test` pairs the two models' held-out chi-square station by station and
gives the one-sided p-value of the Wilcoxon signed-rank test; diagnose names a cause as supported
only when it is below ``HELDOUT_ALPHA`` (diagnose.py).

For ``outlier_stations`` the extended model leaves the named stations out of the fit, and those
stations are left out of the evaluation of both models.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse

from graphcal.diagnosis.catalogue import Gain

__all__ = ["heldout_gain", "paired_test", "N_FOLDS"]

N_FOLDS = 2


def _predict(A_train, b_train, A_held, b_held) -> np.ndarray:
    """Held-out residuals after the least-squares step on the training rows (normal equations with
    Jacobi column scaling and Cholesky; an SVD least squares where that is singular: ~50x slower).
    ``A_train``, ``A_held``: scipy.sparse CSR (a factor touches few variables)."""
    N = (A_train.T @ A_train).toarray()
    dg = np.sqrt(np.clip(np.diag(N), 1e-300, None))
    try:
        Lc = np.linalg.cholesky(N / dg[:, None] / dg[None, :])
        y = np.linalg.solve(Lc, (A_train.T @ b_train) / dg)
        delta = np.linalg.solve(Lc.T, y) / dg
    except np.linalg.LinAlgError:
        delta, *_ = np.linalg.lstsq(A_train.toarray(), b_train, rcond=None)
    return b_held - A_held @ delta


def heldout_gain(system, j_cols: np.ndarray, K: np.ndarray | None, station_order: list,
                 drop_rows: np.ndarray | None = None, skip_stations: set | None = None) -> Gain:
    """Two-fold held-out whitened RMS of the sensors' measurements, current vs extended model.

    Args:
        system: the screening linearisation (scores.LinearSystem) at the current optimum.
        j_cols: the current model's columns.
        K: (rows, p) the candidate's columns (zero outside the rows it acts on), or None.
        station_order: station ids in the dataset's order (the folds alternate along it).
        drop_rows: rows the extended model leaves out of the fit (outlier stations).
        skip_stations: stations left out of the evaluation of both models.
    """
    A, b = system.A, system.b
    J = sparse.csr_matrix(A[:, j_cols])
    skip = skip_stations or set()
    meas_rows = {}
    for (st, _), rows in system.measurement_rows.items():
        meas_rows.setdefault(st, []).append(rows)
    n = len(b)
    sums = np.zeros(2)
    count = 0
    per_station: dict[int, np.ndarray] = {}
    for k in range(N_FOLDS):
        held_st = [st for j, st in enumerate(station_order) if j % N_FOLDS == k]
        held = np.concatenate([np.concatenate(meas_rows[st]) for st in held_st if st in meas_rows]) \
            if any(st in meas_rows for st in held_st) else np.zeros(0, dtype=int)
        if held.size == 0:
            continue
        train = np.ones(n, dtype=bool)
        train[held] = False
        evaluate = np.array([r for r in held if system.row_station[r] not in skip], dtype=int)
        if evaluate.size == 0:
            continue
        r0 = _predict(J[np.flatnonzero(train)], b[train], J[evaluate], b[evaluate])
        train_ext = train.copy()
        if drop_rows is not None:
            train_ext[drop_rows] = False
        A_ext = J if K is None else sparse.hstack([J, sparse.csr_matrix(K)], format="csr")
        r1 = _predict(A_ext[np.flatnonzero(train_ext)], b[train_ext], A_ext[evaluate], b[evaluate])
        sums += [r0 @ r0, r1 @ r1]
        count += evaluate.size
        for st, a, c in zip(system.row_station[evaluate], r0, r1):
            per_station.setdefault(int(st), np.zeros(2))[:] += [a * a, c * c]
    if count == 0:
        return Gain(float("nan"), float("nan"), N_FOLDS)
    p, n_st = paired_test(per_station)
    return Gain(float(np.sqrt(sums[0] / count)), float(np.sqrt(sums[1] / count)), N_FOLDS, p, n_st)


def paired_test(per_station: dict) -> tuple[float, int]:
    """(one-sided p-value, stations) of the paired Wilcoxon signed-rank test that the extended
    model predicts held-out stations better: per station the held-out chi-square (sum of squared
    whitened prediction residuals, unitless) before minus after; H0: the differences are symmetric
    about 0. NaN with fewer than 6 stations (the test cannot reach 0.05)."""
    from scipy.stats import wilcoxon

    d = np.array([v[0] - v[1] for v in per_station.values()], dtype=float)
    d = d[np.abs(d) > 1e-12 * max(np.abs(d).max(initial=0.0), 1e-300)]
    if d.size < 6:
        return float("nan"), int(d.size)
    return float(wilcoxon(d, alternative="greater").pvalue), int(d.size)
