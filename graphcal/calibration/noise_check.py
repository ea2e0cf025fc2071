"""A noise model that was given, not learned, checked against the residuals of the run that used it.

``calibrate --noise-from`` (and the incremental solver, which cannot learn the noise) uses the
sigmas as given. At the final solution, :func:`given_noise_check` reads every noise group's
variance-component statistics (status ``given``) and, with ``options.scale_to_plane_residuals``
(set by ``--noise-from``), multiplies each sensor's extrinsic covariance (rad, m) by its plane
group's variance factor when that is above 1, iterated to its fixed point on the final
linearisation with the other groups held; it warns when the factor is significant or above
:data:`WARN_SCALE`. The defaults are not scaled (conservative as a whole), nor the incremental
solver's per-station sigmas.

Why the planes, and the measured NEES: docs/incremental.md, "The given noise, checked against
the run".
"""

from __future__ import annotations

import dataclasses

import numpy as np

from graphcal.calibration.graph import CalibrationOptions, CalibrationProblem
from graphcal.calibration.noise_estimation import (
    NOISE_TOO_SMALL_P,
    VCE_INNER_ITERATIONS,
    VCE_INNER_TOLERANCE,
    VCE_MIN_REDUNDANCY,
    converged_scales,
    noise_groups_report,
)
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
