"""``graphcal calibrate`` on a walking dataset: every camera's time offset profiled, then the batch
calibration of the walk's stations (docs/calibration.md, "Calibrating from a walk")."""

from __future__ import annotations

import dataclasses

import numpy as np

from graphcal.calibration.graph import CalibrationOptions
from graphcal.calibration.result import CalibrationResult

__all__ = ["calibrate_walk", "with_time_offsets"]


def _priors(ds) -> dict:
    """sensor -> (T_body_sensor CAD (4, 4), sigma m, sigma rad) of dataset.yaml."""
    return {name: (spec.T_body_sensor_prior.matrix, spec.T_body_sensor_prior.sigma_m, spec.T_body_sensor_prior.sigma_rad)
            for name, spec in ds.sensors.items()}


def calibrate_walk(ds, robot, contact: np.ndarray, *, options: CalibrationOptions = CalibrationOptions(),
                   time_offsets_s: dict | None = None, progress: bool = False,
                   plane_max_points: int | None = None) -> CalibrationResult:
    """Calibrate the cameras of the walking dataset ``ds`` (:func:`~graphcal.calibration.walking.is_walking_dataset`)
    with stance ``contact`` (N, n_feet) bool per timeseries row. ``time_offsets_s``: sensor -> its
    known offset (s, stamp minus capture; not estimated); every other camera's is estimated."""
    from graphcal.calibration.calibrate import BatchInputs, calibrate, solve_batch
    from graphcal.calibration.time_offset import TimeOffsetEstimate, estimate_time_offset
    from graphcal.calibration.walking import walking_data, walking_frames

    frames = walking_frames(ds, robot, contact, progress=progress, plane_max_points=plane_max_points)
    priors = _priors(ds)
    given = dict(time_offsets_s or {})
    offsets = {s: float(given.get(s, 0.0)) for s in frames.cloud_rows}
    estimates = []
    for sensor in sorted(frames.cloud_rows):
        if sensor in given:
            estimates.append(TimeOffsetEstimate(sensor, float(given[sensor]), None, "given"))
            continue

        def learned(dt, sensor=sensor):
            data, _ = walking_data(frames, robot, priors, offsets={**offsets, sensor: dt})
            return solve_batch(BatchInputs(ds, robot, data, progress), options)[1]

        est = estimate_time_offset(ds, robot, frames, priors, options, sensor, offsets=offsets, learn_noise=learned,
                                   progress=progress)
        estimates.append(est)
        offsets[sensor] = est.offset_s
    data, where = walking_data(frames, robot, priors, offsets=offsets)
    result = calibrate(ds, options=options, data=data, progress=progress)
    times = frames.times
    walk = {"duration_s": float(times[-1] - times[0]), "stations": len(data.stations),
            "frames": {s: int(sum(1 for _, cl in where.values() if s in cl)) for s in frames.cloud_rows},
            "frames_in_log": {s: int(len(rows)) for s, (rows, _) in frames.cloud_rows.items()},
            "station_times_s": {int(k): float(v[0]) for k, v in where.items()},
            "profiles": {e.sensor: tuple(e.profile) for e in estimates if e.profile}}
    return with_time_offsets(dataclasses.replace(result, walk=walk), tuple(estimates))


def with_time_offsets(result: CalibrationResult, estimates: tuple) -> CalibrationResult:
    """``result`` with each sensor's time offset, its sigma carried into the extrinsic's covariance
    (J sigma^2 J^T, J the extrinsic's rate of change with the offset), and a warning per offset the
    walk does not determine."""
    from graphcal.solvers.covariance import body_axis_sigmas

    sensors = dict(result.sensors)
    warnings = list(result.warnings)
    for est in estimates:
        s = sensors.get(est.sensor)
        if s is None:
            continue
        cov = np.array(s.covariance, dtype=float)
        if est.sigma_s is not None and est.extrinsic_rate is not None:  # also a sigma above the limit
            J = np.asarray(est.extrinsic_rate, dtype=float)
            cov = cov + np.outer(J, J) * est.sigma_s**2
        rot, xyz, corr, _ = body_axis_sigmas(s.T_body_sensor, cov)
        sensors[est.sensor] = dataclasses.replace(
            s, covariance=cov, sigma_rot_deg=np.asarray(rot), sigma_xyz_mm=np.asarray(xyz), correlation=np.asarray(corr),
            time_offset_s=est.offset_s,
            time_offset_sigma_s=est.sigma_s if est.source == "estimated" else None, time_offset_source=est.source)
        if est.source == "not determined":
            warnings.append(
                f"{est.sensor}: this walk does not determine the camera's time offset "
                f"({'sigma ' + format(1e3 * est.sigma_s, '.1f') + ' ms' if est.sigma_s else 'no minimum in its profile'}): "
                "the body hardly rocks, nods or bobs relative to the floor; the extrinsic is the one at offset "
                f"{1e3 * est.offset_s:+.1f} ms. Walk with more sway, or give the offset (--time-offset-ms)")
    return dataclasses.replace(result, sensors=sensors, warnings=tuple(warnings))
