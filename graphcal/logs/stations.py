"""Stations from a continuous log, found while streaming: windows where the body is still (gyro rate
and joint velocities under thresholds) for at least a minimum time with every declared foot loaded.
One station per window (joints and IMU averaged over it); every window found and every one rejected
is kept with its reason. Times in seconds, angles in rad, rates in rad/s, forces in N."""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

__all__ = ["StationThresholds", "Window", "StationFinder"]


@dataclass(frozen=True)
class StationThresholds:
    """When the robot counts as standing still.

    Attributes:
        gyro_max_rad_s: norm of the mean angular rate over ``baseline_s`` (rad/s).
        joint_velocity_max_rad_s: largest joint speed over ``baseline_s`` (rad/s; m/s for prismatic).
        min_duration_s: a window shorter than this is rejected (s).
        baseline_s: the rates are measured over the last ``baseline_s`` (s), which smooths sensor noise.
        report_min_s: still periods shorter than this are not reported as rejected (the short
            pauses of a gait), s.
        force_threshold_n: a foot is loaded when its force is above this (N); a foot's own
            ``threshold_n`` in the mapping replaces it.
    """

    gyro_max_rad_s: float = 0.05
    joint_velocity_max_rad_s: float = 0.05
    min_duration_s: float = 1.0
    baseline_s: float = 0.1
    report_min_s: float = 0.25
    force_threshold_n: float = 20.0


@dataclass
class Window:
    """A still window: ``start``, ``end`` (s), averages (joints in the order of the finder's names,
    IMU specific force m/s² and rate rad/s, NaN when no sample), and, when rejected, ``reason``."""

    start: float
    end: float
    q: np.ndarray | None = None
    accel: np.ndarray | None = None
    gyro: np.ndarray | None = None
    n_joint: int = 0
    n_imu: int = 0
    reason: str = ""
    lifts: int = 0
    clouds: dict = field(default_factory=dict)

    @property
    def centre(self) -> float:
        return 0.5 * (self.start + self.end)

    @property
    def duration(self) -> float:
        return self.end - self.start


class StationFinder:
    """Feed samples in time order (:meth:`joints`, :meth:`imu`, :meth:`feet`), then :meth:`finish`;
    ``accepted`` and ``rejected`` hold the windows.

    Args:
        joint_names: the joints, in the order of the ``q`` arrays given to :meth:`joints`.
        feet: the feet that must be loaded (their loads come through :meth:`feet`); empty: no condition.
        has_imu: whether IMU samples come (without, only the joints tell stillness).
        thresholds: :class:`StationThresholds`.
    """

    def __init__(self, joint_names, feet, has_imu: bool, thresholds: StationThresholds):
        self.names = tuple(joint_names)
        self.th = thresholds
        self.has_imu = has_imu
        self.loaded: dict[str, bool] = {f: False for f in feet}
        self._q: deque = deque()
        self._g: deque = deque()
        self._g_sum = [0.0, 0.0, 0.0]
        self._joint_still = False
        self._gyro_still = not has_imu
        self.accepted: list[Window] = []
        self.rejected: list[Window] = []
        self._still_since: float | None = None
        self._good: Window | None = None
        self._run_windows: list[Window] = []
        self._run_unloaded: set[str] = set()
        self._sums = None
        self._t = -np.inf
        self._pending: deque = deque()
        #: how many times a foot went from loaded to unloaded so far (a window keeps the count at its
        #: start: two windows with the same count were taken without a foot lifted between them)
        self.lifts = 0

    # -- samples
    def joints(self, t: float, q: np.ndarray) -> None:
        """Joint positions ``q`` (rad) at ``t`` (s)."""
        self._q.append((t, q))
        while self._q and self._q[0][0] < t - self.th.baseline_s:
            self._q.popleft()
        t0, q0 = self._q[0]
        span = t - t0
        self._joint_still = bool(span >= 0.5 * self.th.baseline_s
                                 and np.max(np.abs(q - q0), initial=0.0) <= self.th.joint_velocity_max_rad_s * span)
        self._step(t)
        if self._good is not None:
            self._pending.append((t, "q", q))
            self._commit(t)

    def imu(self, t: float, accel, gyro) -> None:
        """IMU specific force (m/s²) and rate (rad/s) at ``t`` (s), each three numbers."""
        gx, gy, gz = gyro
        self._g.append((t, gx, gy, gz))
        s = self._g_sum
        s[0] += gx
        s[1] += gy
        s[2] += gz
        while self._g[0][0] < t - self.th.baseline_s:
            _, ox, oy, oz = self._g.popleft()
            s[0] -= ox
            s[1] -= oy
            s[2] -= oz
        span = t - self._g[0][0]
        n = len(self._g)
        self._gyro_still = (span >= 0.5 * self.th.baseline_s
                            and math.sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2]) <= self.th.gyro_max_rad_s * n)
        self._step(t)
        if self._good is not None:
            self._pending.append((t, "imu", (accel, gyro)))
            self._commit(t)

    def _commit(self, t: float) -> None:
        """Samples enter a window's averages only ``baseline_s`` after they were taken: motion is
        seen up to that late, so the samples of its first instants never count."""
        while self._pending and self._pending[0][0] < t - self.th.baseline_s:
            _, kind, v = self._pending.popleft()
            if kind == "q":
                self._sums["q"] += v
                self._good.n_joint += 1
            else:
                self._sums["accel"] += np.asarray(v[0], dtype=np.float64)
                self._sums["gyro"] += np.asarray(v[1], dtype=np.float64)
                self._good.n_imu += 1

    def feet(self, t: float, loaded: dict[str, bool]) -> None:
        """Whether each foot named in ``loaded`` is loaded at ``t`` (s)."""
        for name, ok in loaded.items():
            if self.loaded[name] and not ok:
                self.lifts += 1
            self.loaded[name] = bool(ok)
        self._step(t)

    # -- the state machine
    def _step(self, t: float) -> None:
        self._t = max(self._t, t)
        still = self._joint_still and self._gyro_still
        good = still and all(self.loaded.values())
        if self._good is not None and not good:
            self._close_good(t)
        if self._still_since is not None and not still:
            self._close_run(t)
        if still and self._still_since is None:
            self._still_since = t
            self._run_windows, self._run_unloaded = [], set()
        if still:
            self._run_unloaded |= {f for f, ok in self.loaded.items() if not ok}
        if good and self._good is None:
            self._good = Window(t, t, lifts=self.lifts)
            self._sums = {"q": np.zeros(len(self.names)), "accel": np.zeros(3), "gyro": np.zeros(3)}

    def _close_good(self, t: float) -> None:
        w, s = self._good, self._sums
        self._good = None
        self._pending.clear()
        w.end = max(w.start, t - self.th.baseline_s)
        w.q = s["q"] / w.n_joint if w.n_joint else np.full(len(self.names), np.nan)
        w.accel = s["accel"] / w.n_imu if w.n_imu else np.full(3, np.nan)
        w.gyro = s["gyro"] / w.n_imu if w.n_imu else np.full(3, np.nan)
        self._run_windows.append(w)

    def _close_run(self, t: float) -> None:
        start, self._still_since = self._still_since, None
        min_s = self.th.min_duration_s
        good = [w for w in self._run_windows if w.duration >= min_s]
        self.accepted += good
        if good or t - start < self.th.report_min_s:
            return
        if t - start < min_s:
            reason = f"still for {t - start:.2f} s only (minimum {min_s:g} s)"
        elif self._run_unloaded:
            longest = max((w.duration for w in self._run_windows), default=0.0)
            reason = (f"foot {', '.join(sorted(self._run_unloaded))} not loaded (all feet loaded for "
                      f"{longest:.2f} s at most of the {t - start:.2f} s still; minimum {min_s:g} s)")
        else:
            reason = "no sample in the window"
        self.rejected.append(Window(start, t, reason=reason))

    def finish(self) -> None:
        """End of the log: close an open window at the last sample time."""
        if self._good is not None:
            self._close_good(self._t)
        if self._still_since is not None:
            self._close_run(self._t)
