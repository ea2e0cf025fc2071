"""Change detection for the incremental calibration: has the sensor moved on the body?

Before a station's plane (or scan) factor is fused, its innovation is taken against the body pose
predicted without it and the current extrinsic: ``NIS = e^T (J P J^T + R)^-1 e``, chi-square with
``dim(e)`` dof (3 for a plane) when the sensor has not moved (:func:`innovation_nis`, in gtsam's
whitened form). :class:`ChangeDetector` sums the NIS of the last ``window`` stations against the
chi-square quantile at ``alpha = p_false_alarm / n_tests`` (Bonferroni), locates the change, and
with the outlier guard holds a failing station until the next one tells a change from an outlier.
Units: the factors' own (rad, m); the statistic is dimensionless.

The statistic, the location and the guard: docs/incremental.md, "The change test".
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import gtsam
import numpy as np

from graphcal import stats as chi2

__all__ = [
    "Decision",
    "ChangeDetector",
    "gaussian_linearization",
    "innovation_nis",
    "joint_covariance",
]


def joint_covariance(source, keys, dims=None) -> np.ndarray:
    """Dense joint marginal covariance of ``keys`` (in that order).

    Args:
        source: an iSAM2 instance (its Bayes tree) or a ``gtsam.Marginals`` of a batch solution.
        keys: the variable keys.
        dims: their tangent dimensions (same order; None: read from the diagonal blocks).
    """
    keys = [int(k) for k in keys]
    jm = source.jointMarginalCovariance(keys)
    if dims is None:
        dims = [np.asarray(jm.at(k, k)).shape[0] for k in keys]
    offs = np.concatenate([[0], np.cumsum(dims)]).astype(int)
    P = np.zeros((offs[-1], offs[-1]))
    for a, ka in enumerate(keys):
        for b in range(a, len(keys)):
            blk = np.asarray(jm.at(ka, keys[b]), dtype=float)
            P[offs[a]:offs[a + 1], offs[b]:offs[b + 1]] = blk
            if b != a:
                P[offs[b]:offs[b + 1], offs[a]:offs[a + 1]] = blk.T
    return 0.5 * (P + P.T)


def gaussian_linearization(factor: gtsam.NonlinearFactor, values: gtsam.Values) -> tuple[np.ndarray, np.ndarray, list]:
    """(A, b, keys) of a noise-model factor's whitened linearisation WITHOUT its robust loss.

    gtsam's ``Robust`` noise model whitens with the Gaussian model and then scales ``A`` and ``b``
    by one scalar ``sqrt(w(|b|))``; that scalar is undone here (``|b_gauss| / |b_robust|``, with
    ``b_gauss`` from ``unwhitenedError`` and the Gaussian model), so one factor object serves both
    the (robust) graph and the (Gaussian) test. ``b = -whiten(e)``.
    """
    lin = factor.linearize(values)
    A, b = lin.jacobian()
    A = np.array(A, dtype=float)
    b = np.asarray(b, dtype=float).reshape(-1)
    model = factor.noiseModel() if hasattr(factor, "noiseModel") else None
    if isinstance(model, gtsam.noiseModel.Robust):
        e = np.asarray(factor.unwhitenedError(values), dtype=float).reshape(-1)
        bg = -np.asarray(model.noise().whiten(e), dtype=float).reshape(-1)
        nr, ng = float(np.linalg.norm(b)), float(np.linalg.norm(bg))
        if nr > 0.0:
            A *= ng / nr
        b = bg
    return A, b, list(lin.keys())


def innovation_nis(factor: gtsam.NonlinearFactor, values: gtsam.Values, covariance_of) -> tuple[float, int]:
    """Normalised innovation squared of a measurement factor (its Gaussian model; a robust loss
    is undone, see :func:`gaussian_linearization`).

    Args:
        factor: the measurement factor (not yet in the graph).
        values: the current estimate of the factor's variables.
        covariance_of: ``callable(keys) -> (D, D)`` joint covariance of the factor's variables in
            the order given (tangent at ``values``), e.g. a closure over :func:`joint_covariance`.

    Returns:
        (NIS, dof): ``b^T (A P A^T + I)^-1 b`` of the whitened linearisation, and ``dim(e)``.
    """
    A, b, keys = gaussian_linearization(factor, values)
    P = covariance_of(keys)
    S = A @ P @ A.T + np.eye(len(b))
    return float(b @ np.linalg.solve(S, b)), int(len(b))


@dataclass(frozen=True)
class Decision:
    """What the detector says about one station's measurement.

    Attributes:
        action: ``"accept"`` (fuse it), ``"hold"`` (outlier guard: wait for the next station),
            ``"change"`` (the sensor moved: start a new extrinsic segment at ``change_station``;
            fuse this station and the ``reroute`` stations into the new segment).
        change_station: station id where the change happened (``action == "change"``).
        outlier_station: a held station found to be an outlier (leave it out), or None.
        reroute: earlier station ids whose measurements belong to the new segment (on a change):
            already fused ones must be moved from the old extrinsic to the new one, a held one
            fused into the new one.
        window_chi2, window_dof: the window statistic at this station and its dof.
        threshold: the window test's chi-square quantile.
        nis, dof: this station's own statistic.
    """

    action: str
    change_station: int | None
    outlier_station: int | None
    reroute: tuple[int, ...]
    window_chi2: float
    window_dof: int
    threshold: float
    nis: float
    dof: int


class ChangeDetector:
    """Sliding-window chi-square test on the innovations of one sensor (see the module docstring).

    Args:
        window: number of stations summed.
        p_false_alarm: false-alarm probability over ``n_tests`` tests (per sensor).
        n_tests: number of tests it is spread over (Bonferroni); 1 = ``p_false_alarm`` per test.
        p_station: level of a single station's NIS when locating a change / confirming a held one.
        guard: outlier guard (hold an individually significant station until the next one).
    """

    def __init__(self, *, window: int = 3, p_false_alarm: float = 1e-4, n_tests: int = 1,
                 p_station: float = 0.01, guard: bool = False):
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        if not (0.0 < p_false_alarm < 1.0):
            raise ValueError(f"p_false_alarm must be in (0, 1), got {p_false_alarm}")
        if n_tests < 1:
            raise ValueError(f"n_tests must be >= 1, got {n_tests}")
        if not (0.0 < p_station < 1.0):
            raise ValueError(f"p_station must be in (0, 1), got {p_station}")
        self.window = int(window)
        self.alpha = float(p_false_alarm) / int(n_tests)
        self.p_station = float(p_station)
        self.guard = bool(guard)
        self._entries: deque = deque(maxlen=self.window)  # (station, nis, dof)
        self._held: tuple[int, float, int] | None = None
        self._quantiles: dict[tuple[float, int], float] = {}

    # -- thresholds
    def threshold(self, dof: int) -> float:
        """Chi-square quantile of the window test (level ``alpha``)."""
        return self._quantile(self.alpha, dof)

    def station_threshold(self, dof: int) -> float:
        """Chi-square quantile of a single station's NIS at ``p_station``."""
        return self._quantile(self.p_station, dof)

    def _quantile(self, p: float, dof: int) -> float:
        q = self._quantiles.get((p, dof))
        if q is None:
            q = self._quantiles[(p, dof)] = float(chi2.isf(p, dof))
        return q

    @property
    def held(self) -> int | None:
        """The station held by the outlier guard, or None."""
        return None if self._held is None else self._held[0]

    def reset(self) -> None:
        """Forget the window (after a change: the new segment starts afresh)."""
        self._entries.clear()
        self._held = None

    def _window(self) -> tuple[float, int]:
        return float(sum(e[1] for e in self._entries)), int(sum(e[2] for e in self._entries))

    def _locate(self) -> int:
        entries = list(self._entries)
        for st, nis, dof in entries:
            if nis > self.station_threshold(dof):
                return st
        # CUSUM change point: the suffix with the largest excess over its expectation
        best, best_j, acc = -np.inf, 0, 0.0
        for j in range(len(entries) - 1, -1, -1):
            acc += entries[j][1] - entries[j][2]
            if acc > best:
                best, best_j = acc, j
        return entries[best_j][0]

    def test(self, station: int, nis: float, dof: int) -> Decision:
        """Feed one station's innovation; returns what to do with its measurement."""
        outlier = None
        if self._held is not None:
            h_station, h_nis, h_dof = self._held
            self._held = None
            if nis > self.station_threshold(dof):
                # confirmed: the held station was the first with the new extrinsic
                self._entries.append((station, nis, dof))
                stat, wdof = self._window()
                thr = self.threshold(wdof)
                self.reset()
                return Decision("change", h_station, None, (h_station,), stat, wdof, thr, nis, dof)
            # not confirmed: the held station was an outlier; forget its NIS
            self._entries = deque((e for e in self._entries if e[0] != h_station), maxlen=self.window)
            outlier = h_station
        self._entries.append((station, nis, dof))
        stat, wdof = self._window()
        thr = self.threshold(wdof)
        if self.guard and nis > self.threshold(dof):
            self._held = (station, nis, dof)
            return Decision("hold", None, outlier, (), stat, wdof, thr, nis, dof)
        if stat > thr:
            where = self._locate()
            ids = [e[0] for e in self._entries]
            reroute = tuple(ids[ids.index(where):-1])
            self.reset()
            return Decision("change", where, outlier, reroute, stat, wdof, thr, nis, dof)
        return Decision("accept", None, outlier, (), stat, wdof, thr, nis, dof)
