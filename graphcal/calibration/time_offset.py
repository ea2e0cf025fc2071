"""A camera's time offset from a walk: the calibration's chi-square profiled over the offset.

A frame stamped late by dt is matched with joint angles dt too early; while the body sways, nods
and bobs, the floor it predicts is then off by about dt times the body's rate, and the misfit grows
with |dt - offset|. The offset is the minimum of the profile chi2(dt) (every other variable solved
at each dt), its sigma the curvature's (delta chi2 = 1, with the noise learned at the minimum).
Offsets are the sensor's stamp minus its capture time (s).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["TimeOffsetEstimate", "estimate_time_offset", "COARSE_HALF_WIDTH_S", "UNDETERMINED_SIGMA_S"]

#: the offsets searched: +- this around 0 (s), on a grid of COARSE_STEP_S
COARSE_HALF_WIDTH_S = 0.1
COARSE_STEP_S = 0.02
#: the coarse profile uses every COARSE_THINNING-th camera frame (it only finds the minimum's 20 ms)
COARSE_THINNING = 3
#: the fine profile around the coarse minimum: +- FINE_HALF_WIDTH_S on a grid of FINE_STEP_S
FINE_HALF_WIDTH_S = 0.008
FINE_STEP_S = 0.004
#: times the fine window is moved when the vertex lies outside it (a coarse minimum more than
#: FINE_HALF_WIDTH_S off)
FINE_RECENTRES = 2
#: a walk whose profile gives the offset a sigma above this (s) does not determine it
UNDETERMINED_SIGMA_S = 0.005


@dataclass(frozen=True, eq=False)
class TimeOffsetEstimate:
    """One camera's time offset.

    Attributes:
        sensor: its name; offset_s: stamp minus capture time (s); sigma_s: 1-sigma (s), None when
            given or not determined; source: ``estimated``, ``given`` or ``not determined``.
        profile: ((offset s, chi2, stage), ...) every offset solved; stage ``coarse`` (every
            third frame, the noise given) or ``fine`` (every frame, the noise learned): the two
            stages' chi2 are not comparable with each other.
        extrinsic_rate: (6,) d xi / d offset of the extrinsic at the estimate ([omega, v] tangent,
            rad/s and m/s), to carry the offset's sigma into the extrinsic's; None when not estimated.
    """

    sensor: str
    offset_s: float
    sigma_s: float | None
    source: str
    profile: tuple = ()
    extrinsic_rate: np.ndarray | None = None


def _solve_at(ds, robot, frames, priors, options, sensor: str, offsets: dict, dt: float, steady, start=None):
    """(chi2, T_body_sensor (4, 4), solution) of the walk solved with ``sensor`` at offset ``dt``
    (s), warm started from ``start`` (the solution at a neighbouring offset: the same stations)."""
    from graphcal.calibration.calibrate import solve_problem
    from graphcal.calibration.graph import build_problem
    from graphcal.calibration.walking import walking_data
    from graphcal.geometry import from_gtsam_pose

    data, _ = walking_data(frames, robot, priors, offsets={**offsets, sensor: dt}, steady=steady)
    problem = build_problem(ds, robot, data, options, initial=start)
    lm = solve_problem(problem)
    return 2.0 * lm.error_final, from_gtsam_pose(lm.values.atPose3(problem.sensor_keys[sensor])), lm.values


def _profile(ds, robot, frames, priors, options, sensor: str, offsets: dict, grid, steady) -> list:
    """[(chi2, T_body_sensor), ...] at every offset of ``grid`` (s), each solve warm started from the last."""
    out, start = [], None
    for dt in grid:
        chi2, T, start = _solve_at(ds, robot, frames, priors, options, sensor, offsets, float(dt), steady, start)
        out.append((chi2, T))
    return out


def _parabola(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(vertex x, curvature a of y = a (x - x0)^2 + c) of a least-squares parabola."""
    a, b, _ = np.polyfit(x, y, 2)
    return (-b / (2 * a) if a > 0 else float(x[np.argmin(y)])), float(a)


def estimate_time_offset(ds, robot, frames, priors: dict, options, sensor: str, *, offsets: dict | None = None,
                         learn_noise=None, progress: bool = False) -> TimeOffsetEstimate:
    """The time offset of ``sensor`` from the walk ``frames`` (:func:`~graphcal.calibration.walking.walking_frames`):
    a coarse profile over +- :data:`COARSE_HALF_WIDTH_S` at ``options``' noise, then a fine one
    around its minimum at the noise ``learn_noise(offset)`` returns (CalibrationOptions; None: the
    same options). ``offsets``: the other sensors' (s)."""
    import logging

    from graphcal.geometry import pose_log_between

    log = logging.getLogger("graphcal")
    offsets = dict(offsets or {})
    import dataclasses

    coarse = np.round(np.arange(-COARSE_HALF_WIDTH_S, COARSE_HALF_WIDTH_S + 1e-9, COARSE_STEP_S), 6)
    steady = (float(coarse[0]), float(coarse[-1]))
    rows, paths = frames.cloud_rows[sensor]
    thin = dataclasses.replace(frames, cloud_rows={**frames.cloud_rows, sensor: (rows[::COARSE_THINNING],
                                                                                  paths[::COARSE_THINNING])})
    chi = np.array([c for c, _ in _profile(ds, robot, thin, priors, options, sensor, offsets, coarse, steady)])
    k = int(np.argmin(chi))
    lo, hi = max(0, k - 1), min(len(coarse), k + 2)
    start, _ = _parabola(coarse[lo:hi], chi[lo:hi]) if hi - lo == 3 else (float(coarse[k]), 0.0)
    start = float(np.clip(start, coarse[0], coarse[-1]))
    if progress:
        log.info(f"calibrate: {sensor}: time offset profile {1e3 * coarse[0]:+.0f}..{1e3 * coarse[-1]:+.0f} ms, "
                 f"minimum near {1e3 * start:+.1f} ms")
    fine_options = learn_noise(start) if learn_noise is not None else options
    fine_all: list = []
    for _ in range(FINE_RECENTRES + 1):  # the vertex outside the fine window: centre it there and profile again
        fine = start + np.arange(-FINE_HALF_WIDTH_S, FINE_HALF_WIDTH_S + 1e-9, FINE_STEP_S)
        steady = (float(fine[0]), float(fine[-1]))
        solved = _profile(ds, robot, frames, priors, fine_options, sensor, offsets, fine, steady)
        fchi = np.array([c for c, _ in solved])
        fine_all += list(zip(fine, fchi))
        x0, a = _parabola(fine, fchi)
        if a > 0 and fine[0] <= x0 <= fine[-1]:
            break
        start = float(np.clip(x0 if a > 0 else fine[int(np.argmin(fchi))], fine[0] - FINE_HALF_WIDTH_S,
                              fine[-1] + FINE_HALF_WIDTH_S))
    profile = tuple([(float(d), float(c), "coarse") for d, c in zip(coarse, chi)]
                    + [(float(d), float(c), "fine") for d, c in fine_all])
    if a <= 0 or not (fine[0] <= x0 <= fine[-1]):
        return TimeOffsetEstimate(sensor, start, None, "not determined", profile)
    sigma = float(1.0 / np.sqrt(a))
    T_mid = solved[len(solved) // 2][1]
    xi = np.array([pose_log_between(T_mid, T) for _, T in solved])
    rate = np.array([np.polyfit(fine, xi[:, j], 1)[0] for j in range(6)])
    source = "estimated" if sigma <= UNDETERMINED_SIGMA_S else "not determined"
    return TimeOffsetEstimate(sensor, float(x0), sigma, source, profile, rate)
