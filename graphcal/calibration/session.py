"""One calibration as ``graphcal calibrate`` runs it: the options from its switches, batch or
incremental, and the notes that belong to the result (the ``--noise-from`` notes and ``noise_source``,
the collapsed plane noise scales). The command only checks its output folder, calls
:func:`calibrate_session` and writes the outputs."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from graphcal.calibration.calibrate import calibrate
from graphcal.calibration.graph import CalibrationOptions, options_for_ground_roughness
from graphcal.calibration.result import CalibrationResult

__all__ = ["calibrate_session", "COLLAPSED_PLANE_SCALE", "collapsed_plane_scale_warnings", "noise_from_notes"]

#: a learned plane noise scale below this has collapsed: the planes' residuals are explained without
#: their fits' point noise (measured on the Octopus chai2015 demo: learned x0.64 on a flat floor;
#: x2.6e-14 with --ground-roughness-mm 3, whose floor alone is 40x the residuals)
COLLAPSED_PLANE_SCALE = 0.05


def collapsed_plane_scale_warnings(noise_groups, ground_roughness_m: float) -> tuple[str, ...]:
    """A warning per sensor whose learned plane noise scale collapsed below
    :data:`COLLAPSED_PLANE_SCALE` (``noise_groups``: :class:`~graphcal.calibration.result.NoiseGroupEstimate`;
    ``ground_roughness_m``: calibrate's --ground-roughness-mm, in m). The scale multiplies the fit's
    own point noise; with a roughness floor added to every plane the floor alone can exceed the
    residuals, and the scale runs to ~0 ("plane:depth x5.49e-09" without a word)."""
    out = []
    for g in noise_groups:
        if not g.group.startswith("plane:") or g.status == "given" or not g.fields:
            continue
        scale = g.fields[0][1]
        if not scale < COLLAPSED_PLANE_SCALE:
            continue
        sensor = g.group.split(":", 1)[1]
        if ground_roughness_m > 0:
            why = (f"the planes scatter less than --ground-roughness-mm {1e3 * ground_roughness_m:.3g} alone allows "
                   f"for (their residuals are {g.data_scale:.2g} of their sigma), so the share of the fits' point noise "
                   "went to zero and the plane noise is the roughness floor, which then sets the extrinsic's sigma. "
                   "The ground looks smoother than that: try a smaller --ground-roughness-mm, or 0")
        else:
            why = (f"the planes scatter far less than the point noise of their fits predicts (their residuals are "
                   f"{g.data_scale:.2g} of their sigma); check the planes.csv covariances (too large?)")
        out.append(f"{sensor}: learned plane noise scale x{scale:.2g} (near zero): {why}")
    return tuple(out)


def noise_from_notes(noise_from: str | Path, result: CalibrationResult, scaled: tuple[str, ...]) -> tuple[str, ...]:
    """The warnings of a calibration whose noise model came from the ``calibration.yaml`` at
    ``noise_from``: another robot's or other sensors' file (:func:`~graphcal.calibration.noise_file.noise_from_mismatch`),
    and each sensor of ``result`` without a plane scale in it (``scaled``: those with one)."""
    from graphcal.calibration.noise_file import noise_from_mismatch

    unscaled = [name for name in result.sensors if name not in scaled]
    return noise_from_mismatch(noise_from, result.robot_name, result.sensors) + tuple(
        f"{noise_from} has no plane_scale:{name}: the plane noise of {name} is its own noise "
        "model, unscaled" for name in unscaled)


def calibrate_session(dataset, *, legs: bool = False, incremental: bool = False, ground_roughness_m: float = 0.0,
                      plane_max_points: int | None = None, noise_from: str | Path | None = None,
                      progress: bool = False) -> CalibrationResult:
    """Calibrate ``dataset`` as ``graphcal calibrate`` does; returns the final result.

    Args:
        dataset: dataset folder (or a :class:`~graphcal.io.dataset.Dataset`).
        legs: also estimate the leg joint offsets and link lengths.
        incremental: iSAM2, one station at a time, with change detection
            (:func:`graphcal.calibration.incremental.calibrate_incremental`); else batch
            (:func:`graphcal.calibration.calibrate.calibrate`).
        ground_roughness_m: RMS bump height of the ground (m),
            :func:`graphcal.calibration.graph.options_for_ground_roughness`.
        plane_max_points: fit each cloud's plane on at most this many points (None: all).
        noise_from: an earlier ``calibration.yaml`` whose noise model is used as given, not learned
            (:func:`graphcal.calibration.noise_file.options_with_noise_from`); the result then has
            ``noise_source`` set and the notes of :func:`noise_from_notes` among its warnings.
        progress: progress bars (tqdm) and one log line per solve.

    The result's warnings end with :func:`collapsed_plane_scale_warnings`.
    """
    options = options_for_ground_roughness(CalibrationOptions(legs=legs), ground_roughness_m)
    scaled: tuple[str, ...] = ()
    if noise_from is not None:
        from graphcal.calibration.noise_file import options_with_noise_from

        options, scaled = options_with_noise_from(noise_from, options)
    if incremental:
        from graphcal.calibration.incremental import calibrate_incremental

        result = calibrate_incremental(dataset, options=options, progress=progress,
                                       plane_max_points=plane_max_points)
    else:
        result = calibrate(dataset, options=options, progress=progress, plane_max_points=plane_max_points)
    if noise_from is not None:
        result = dataclasses.replace(result, noise_source=str(noise_from),
                                     warnings=result.warnings + noise_from_notes(noise_from, result, scaled))
    return dataclasses.replace(result, warnings=result.warnings + collapsed_plane_scale_warnings(
        result.noise_groups, ground_roughness_m))
