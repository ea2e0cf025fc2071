"""A noise model that was given, not learned, checked against the residuals of the run that used it.

``calibrate --noise-from`` (and the incremental solver, which cannot learn the noise) uses the
sigmas as given. They were learned on another session, or are the defaults: nothing guarantees
that they fit this one. At the final solution, :func:`given_noise_check` reads every noise group's
variance-component statistics (noise_estimation.py: chi-square over redundancy, the factor the
residuals point to for the group's sigma) and

* reports them (status ``given``; the report and ``calibration.yaml`` show them);
* with ``options.scale_to_plane_residuals`` (set by ``--noise-from``: a noise model learned on
  another session), multiplies each sensor's extrinsic covariance by its plane group's variance
  factor when that is above 1 (never below: a noise model larger than the data need stays
  conservative), and warns when it is significant or above :data:`WARN_SCALE`. The factor is the
  plane groups' variance components iterated to their fixed point on the final linearisation with
  the other groups held as given: one update reads too little when the planes are understated,
  because the body poses then absorb most of their residuals (a plane noise given at 0.25 of what
  the planes point to: one update x1.8^2, the fixed point x8.4, the truth x9.2).

Why the planes: they carry the extrinsic, and their scatter varies from session to session more
than chi-square sampling does (with unmodelled joint flex, one update at session B's solution
under session A's learned noise read 0.77-1.86 over 60 pairs, from 10-56 dof), so the scale learned on one session often
understates the next one's. Not for the defaults: they are conservative as a whole (large joint
sigma, small plane noise), and scaling their planes alone made a conservative covariance more so.

Measured (docs/incremental.md): the Octopus on Chai's program, joints flexing 0.3 deg per joint
and station, noise learned by a batch run on session A and used on session B, 40 pairs (seeds
20-59): mean NEES of the extrinsic, batch 9.56 as given -> 5.85 with the factor, incremental
8.52 -> 5.76 (95 % interval for 40 runs [4.97, 7.12]; B's own learned noise: 7.34). Half the
runs were scaled, their covariance by x1.08-x8.4 (A's learned plane scale is itself an estimate
from ~30 dof of correlated residuals), 8 of 40 with a warning.

The incremental solver's per-station sigmas (its stop rule, ``history``) are not scaled: the
factor needs every residual of the run.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from graphcal.calibration.graph import CalibrationOptions, CalibrationProblem
from graphcal.calibration.noise_estimation import (NOISE_TOO_SMALL_P, VCE_INNER_ITERATIONS, VCE_INNER_TOLERANCE,
                                                   VCE_MIN_REDUNDANCY, converged_scales, noise_groups_report)
from graphcal.calibration.result import NoiseGroupEstimate, SensorEstimate


#: a covariance multiplied by more than this is warned about even when the chi-square test is not
#: significant (few dof)
WARN_SCALE = 2.0


def given_noise_check(
    problem: CalibrationProblem, values, options: CalibrationOptions, sensors: dict[str, SensorEstimate],
) -> tuple[dict[str, SensorEstimate], tuple[NoiseGroupEstimate, ...], list[str]]:
    """(sensors with their covariance scaled, the noise groups' statistics, warnings).

    Args:
        problem, values: the graph of the final solve and its solution.
        options: the noise model it used (given, not learned).
        sensors: name -> :class:`SensorEstimate` computed with that noise model (covariance of
            ``xi = [omega (rad), v (m)]``, sigmas in deg and mm about body axes).

    Returns:
        With ``options.scale_to_plane_residuals``, every sensor whose plane group has at least
        ``VCE_MIN_REDUNDANCY`` dof and a variance factor ``s^2 > 1`` gets its covariance and every
        segment's covariance multiplied by ``s^2``, its sigmas by ``s`` and
        ``covariance_scale = s^2``; the others are returned as given (``covariance_scale = 1``).
    """
    scaling = options.scale_to_plane_residuals
    # the statistics at the solution (the first iteration) and, when scaling, the plane groups'
    # scales iterated to their fixed point on this linearisation with the other groups held
    fit = converged_scales(problem.graph, values, problem.factor_groups, problem.factor_components,
                           eligible=lambda v: v.group.startswith("plane:") and v.redundancy >= VCE_MIN_REDUNDANCY,
                           tolerance=VCE_INNER_TOLERANCE, max_iterations=VCE_INNER_ITERATIONS if scaling else 1)
    groups, warnings = noise_groups_report(fit.first, options, given=True)
    out = dict(sensors)
    if not scaling:
        return out, groups, warnings
    fixed = fit.scales
    by_group = {g.group: g for g in groups}
    for name, est in sensors.items():
        v = by_group.get(f"plane:{name}")
        if v is None:
            continue
        if v.dof < VCE_MIN_REDUNDANCY:
            warnings.append(
                f"{name}: its plane residuals carry {v.dof:.2g} dof, too few to check the given noise model "
                "against (the body poses absorb them: the plane noise given is small against the legs' and IMU's); "
                "the covariance may be too small (calibrate without --noise-from learns the noise)")
            continue
        s = float(fixed.get(f"plane:{name}", 1.0))
        if not np.isfinite(s) or s <= 1.0:
            continue
        f = s * s
        out[name] = dataclasses.replace(
            est,
            covariance=np.asarray(est.covariance) * f,
            sigma_rot_deg=np.asarray(est.sigma_rot_deg) * s,
            sigma_xyz_mm=np.asarray(est.sigma_xyz_mm) * s,
            segments=tuple(dataclasses.replace(seg, covariance=np.asarray(seg.covariance) * f) for seg in est.segments),
            covariance_scale=f,
        )
        if v.p_high < NOISE_TOO_SMALL_P or f > WARN_SCALE:
            warnings.append(
                f"{name}: the plane residuals are {s:.2g} times what the given noise model predicts (chi-square p = "
                f"{v.p_high:.2g}, {v.dof:.0f} dof): it does not fit this session (a noisier sensor, uneven "
                f"ground, or a model learned on different data); the covariance was multiplied by {f:.2g}")
    return out, groups, warnings
