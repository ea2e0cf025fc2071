"""The filter's noise learned from the log itself (docs/state_estimation.md, "Noise from the log").

* IMU white noise and encoder noise from the still windows: a window is still when every joint,
  gyro and accelerometer channel looks white in it (its variance is no more than ``ratio**2`` times
  half the variance of its first differences: motion is smooth, so it fails that test); the
  noise per sample is ``sqrt(var(diff) / 2)`` pooled over the still windows, a density
  ``sigma * sqrt(dt)`` for the IMU.
* The kinematic noise from the stance innovations (covariance matching): the filter is run, the
  mean stance NIS per dof compared with 1, ``kinematic_sigma_m`` raised (or, when it is 0 and the
  encoder noise is the default, that lowered) and the filter run again, to a fixed point.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

__all__ = ["StillNoise", "still_windows", "still_noise", "match_measurement_noise", "MatchResult",
           "matched_floor_sigma"]


@dataclass(frozen=True)
class StillNoise:
    """Noise read off the still windows: ``windows`` [(start s, end s)], ``duration_s`` in all,
    per-sample sigmas of the encoders (rad), gyro (rad/s), accelerometer (m/s^2), and the
    densities (per sqrt(Hz)) at the sample interval ``dt_s``."""

    windows: tuple
    duration_s: float
    dt_s: float
    encoder_sigma_rad: float
    gyro_sigma: float
    accel_sigma: float

    @property
    def gyro_noise_density(self) -> float:
        return self.gyro_sigma * float(np.sqrt(self.dt_s))

    @property
    def accel_noise_density(self) -> float:
        return self.accel_sigma * float(np.sqrt(self.dt_s))


def _window_stack(x: np.ndarray, n: int) -> np.ndarray:
    """(W, n, C) non-overlapping windows of n samples of x (N, C)."""
    w = len(x) // n
    return x[: w * n].reshape(w, n, x.shape[1])


def still_windows(times: np.ndarray, channels: np.ndarray, *, window_s: float = 0.25,
                  ratio: float = 1.5) -> tuple[np.ndarray, np.ndarray, int]:
    """(still (W,) bool, start index (W,), samples per window): a window of ``window_s`` is still when
    every channel of ``channels`` (N, C) is white in it (a constant channel, e.g. a quantised encoder
    at rest, counts as white)."""
    dt = float(np.median(np.diff(times)))
    n = max(8, int(round(window_s / dt)))
    X = _window_stack(np.asarray(channels, dtype=float), n)
    var = X.var(axis=1)
    dvar = np.diff(X, axis=1).var(axis=1) / 2.0
    scale = np.abs(X).mean(axis=1) + 1.0
    white = var <= ratio**2 * dvar + (1e-12 * scale) ** 2
    return white.all(axis=1), np.arange(len(X)) * n, n


def _pooled_sigma(x: np.ndarray, starts: np.ndarray, n: int) -> np.ndarray:
    """Per channel: sqrt(mean over the windows of var(diff) / 2); a channel constant in every window
    gets its quantum over sqrt(12) (the smallest non-zero step in x)."""
    d = np.concatenate([np.diff(x[s : s + n], axis=0) for s in starts])
    sig = np.sqrt(d.var(axis=0) / 2.0)
    for c in np.flatnonzero(sig == 0):
        steps = np.abs(np.diff(x[:, c]))
        steps = steps[steps > 0]
        sig[c] = steps.min() / np.sqrt(12.0) if len(steps) else 0.0
    return sig


def still_noise(times: np.ndarray, q: np.ndarray, gyro: np.ndarray, accel: np.ndarray, *, window_s: float = 0.25,
                min_still_s: float = 0.5) -> StillNoise | None:
    """Noise of the still windows of a log (times (N,) s; q (N, J) rad; gyro, accel (N, 3) in the
    IMU frame), or None when they last less than ``min_still_s`` in all."""
    times = np.asarray(times, dtype=float)
    ch = np.column_stack([q, gyro, accel])
    ok, starts, n = still_windows(times, ch, window_s=window_s)
    starts = starts[ok]
    dt = float(np.median(np.diff(times)))
    if len(starts) * n * dt < min_still_s:
        return None
    sig = _pooled_sigma(ch, starts, n)
    J = q.shape[1]
    rms = lambda s: float(np.sqrt(np.mean(s**2)))  # noqa: E731 -- one value for every axis/joint
    windows = _merged(times, starts, n)
    return StillNoise(windows, float(len(starts) * n * dt), dt, rms(sig[:J]), rms(sig[J:J + 3]), rms(sig[J + 3:]))


def _merged(times: np.ndarray, starts: np.ndarray, n: int) -> tuple:
    """Adjacent still windows joined: ((start s, end s), ...)."""
    if not len(starts):
        return ()
    breaks = np.flatnonzero(np.diff(starts) != n) + 1
    runs = np.split(starts, breaks)
    last = len(times) - 1
    return tuple((round(float(times[r[0]]), 3), round(float(times[min(r[-1] + n, last)]), 3)) for r in runs)


@dataclass(frozen=True)
class MatchResult:
    """The covariance matching: the final filter result, the noise it used, every pass
    ({kinematic_sigma_m, encoder_sigma_rad, stance_nis_per_dof}), whether it converged, a note."""

    result: object
    noise: object
    passes: tuple
    converged: bool
    note: str


def _nis_per_dof(res) -> float:
    dofs = res.stance_dofs if res.stance_dofs is not None else np.full(len(res.stance_nis), res.stance_dof)
    return float(np.mean(res.stance_nis / np.maximum(dofs, 1))) if len(res.stance_nis) else float("nan")


def _next_sigma(a: tuple, b: tuple) -> float:
    """The kinematic sigma (m) where NIS/dof = 1 on the model r = A / (s0 + sigma^2) through the passes
    a and b (sigma m, r); the step r-proportional when the two do not determine it."""
    (sa, ra), (sb, rb) = a, b
    if abs(ra - rb) > 1e-3 * max(ra, rb):
        s0 = (rb * sb**2 - ra * sa**2) / (ra - rb)
        A = ra * (s0 + sa**2)
        if s0 > 0 and A - s0 > 0:
            return float(np.sqrt(A - s0))
    return float(max(sb, 1e-3) * np.sqrt(max(rb, 1e-6)))


def _record(noise, r: float, res) -> dict:
    out = {"kinematic_sigma_m": noise.kinematic_sigma_m, "foot_rw": noise.foot_rw,
           "encoder_sigma_rad": noise.encoder_sigma_rad, "stance_nis_per_dof": r}
    n = int(np.sum(getattr(res, "floor_dofs", ())))
    if n:
        out.update({"floor_sigma_m": noise.floor_sigma_m, "floor_nis_per_dof": float(np.sum(res.floor_nis)) / n})
    return out


def matched_floor_sigma(res, sigma_m: float, *, min_m: float = 1e-3) -> float | None:
    """Covariance matching of the level-floor updates: the floor sigma (m) whose variance is the
    innovations' mean square less the state's part of their variance, at least ``min_m``; None
    without floor updates."""
    n = int(np.sum(res.floor_dofs))
    if not n:
        return None
    hph = float(np.sum(res.floor_s)) - sigma_m**2 * n
    return float(np.sqrt(max(min_m**2, (float(np.sum(res.floor_y2)) - hph) / n)))


def _floor_moved(noise, res, free) -> object | None:
    """The noise with the matched floor sigma when it moved by more than 10 % (else None)."""
    if "floor_sigma_m" not in free:
        return None
    s = matched_floor_sigma(res, noise.floor_sigma_m)
    if s is None or abs(np.log(s / noise.floor_sigma_m)) < 0.1:
        return None
    return replace(noise, floor_sigma_m=s)


def _raised(noise, pts: list, r: float, first_guess_m: float, max_kinematic_m: float):
    """The noise with ``kinematic_sigma_m`` where the NIS per dof should be 1 (None: beyond the bound)."""
    if len(pts) == 1 and pts[0][0] == 0:
        s = first_guess_m
    elif len(pts) > 1:
        s = _next_sigma(pts[-2], pts[-1])
    else:
        s = pts[-1][0] * np.sqrt(r)
    if s > max_kinematic_m and noise.kinematic_sigma_m >= max_kinematic_m:
        return None
    return replace(noise, kinematic_sigma_m=float(min(s, max_kinematic_m)))


def _lowered(knob: str, noise, passes: list, r: float) -> float:
    """The next value of ``knob`` (foot_rw or encoder_sigma_rad) towards NIS per dof 1: the secant in
    log-log through the last two passes that moved it, else a quarter of the value."""
    v = getattr(noise, knob)
    prev = [p for p in passes if p[knob] != v]
    if prev and prev[-1]["stance_nis_per_dof"] != r:
        a, ra = prev[-1][knob], prev[-1]["stance_nis_per_dof"]
        slope = (np.log(r) - np.log(ra)) / (np.log(v) - np.log(a))
        if slope < -1e-3:
            return float(v * np.exp(np.clip(-np.log(r) / slope, -4.0, 0.0)))
    return float(v / 4.0)


def match_measurement_noise(run, noise, *, free: frozenset, tol: float = 1.02, max_passes: int = 6,
                            max_kinematic_m: float = 0.1, first_guess_m: float = 0.005) -> MatchResult:
    """Covariance matching of the stance updates: ``run(noise) -> TrackResult`` is called with
    ``noise`` (an EkfNoise) changed until the mean stance NIS per dof is within ``[1/tol, tol]``.
    Only the names in ``free`` change: ``kinematic_sigma_m`` up when the NIS is high; when it is low,
    ``kinematic_sigma_m`` down to 0, then ``foot_rw``, then ``encoder_sigma_rad`` (:func:`_lowered`), a
    knob given up when a pass moves the NIS less than a tenth of the way; ``floor_sigma_m`` (if
    free) matched alongside (:func:`matched_floor_sigma`) until it moves less than 10 %."""
    passes: list[dict] = []
    res = run(noise)
    r = _nis_per_dof(res)
    passes.append(_record(noise, r, res))
    pts: list[tuple] = [(noise.kinematic_sigma_m, r)]
    down = [k for k in ("foot_rw", "encoder_sigma_rad") if k in free]
    while len(passes) < max_passes and np.isfinite(r):
        knob = None
        floor_new = _floor_moved(noise, res, free)
        if 1 / tol <= r <= tol:
            if floor_new is None:
                break
            new = floor_new
        elif r > tol and "kinematic_sigma_m" in free:
            new = _raised(noise, pts, r, first_guess_m, max_kinematic_m)
            if new is None:
                return MatchResult(res, noise, tuple(passes), False, f"the stance innovations need a kinematic "
                                   f"noise above {max_kinematic_m} m: the leg model or the contacts do not fit")
        elif r < 1 / tol and noise.kinematic_sigma_m > 0 and "kinematic_sigma_m" in free:
            s = _next_sigma(pts[-2], pts[-1]) if len(pts) > 1 else noise.kinematic_sigma_m * np.sqrt(r)
            new = replace(noise, kinematic_sigma_m=float(max(s, 0.0)))
        elif r < 1 / tol and down:
            knob = down[0]
            new = replace(noise, **{knob: _lowered(knob, noise, passes, r)})
        else:
            break
        if floor_new is not None:
            new = replace(new, floor_sigma_m=floor_new.floor_sigma_m)
        res, r_old = run(new), r
        r = _nis_per_dof(res)
        noise = new
        passes.append(_record(noise, r, res))
        pts.append((noise.kinematic_sigma_m, r))
        if knob is not None and abs(np.log(r / r_old)) < 0.1 * abs(np.log(r_old)):
            down.remove(knob)  # this knob does not carry the innovations' level
    ok = bool(np.isfinite(r) and 1 / tol <= r <= tol)
    note = "converged" if ok else (f"stopped after {len(passes)} passes at a stance NIS per dof of {r:.3g}"
                                   if np.isfinite(r) else "no stance update")
    return MatchResult(res, noise, tuple(passes), ok, note)
