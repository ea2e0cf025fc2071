"""What a calibration returns: estimates with their covariance, residuals before and after, outliers;
:func:`calibration_result` reads it off a solved graph (batch or incremental).

Frames and units: ``T_body_sensor`` maps sensor coordinates to the body frame (4x4, m). Every
covariance is of the right perturbation ``T = T_hat * Exp(xi)``, ``xi = [omega (rad), v (m)]``
(GTSAM's tangent order, SI units), unless its name says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from graphcal.calibration.residuals import StationResidual


@dataclass(frozen=True, eq=False)
class ExtrinsicSegment:
    """The extrinsic of one sensor over a run of stations (a new segment starts when the sensor
    was knocked). ``first_station``/``last_station`` are station ids (inclusive)."""

    first_station: int
    last_station: int
    T_body_sensor: np.ndarray
    covariance: np.ndarray


@dataclass(frozen=True, eq=False)
class SensorEstimate:
    """The calibrated pose of one sensor.

    Attributes:
        name, type: as in dataset.yaml.
        T_body_sensor: (4, 4) estimate (of the last segment when the sensor moved).
        covariance: (6, 6) of ``xi = [omega, v]`` with ``T = T_hat * Exp(xi)`` (rad, m).
        T_body_sensor_prior: (4, 4) the CAD value from dataset.yaml.
        sigma_rot_deg: (3,) 1-sigma rotation about the body x, y, z axes (deg).
        sigma_xyz_mm: (3,) 1-sigma translation along the body x, y, z axes (mm).
        correlation: (6, 6) correlation matrix in the body-axis order [rx, ry, rz, x, y, z].
        unobservable: one sentence per direction the data does not determine, naming the motion
            that would determine it; empty when everything is determined.
        segments: the extrinsic segments in station order (one when the sensor never moved).
        change_stations: station ids where a change of the extrinsic was detected.
        covariance_scale: the factor ``covariance`` (and every segment's) was multiplied by because
            the plane residuals were larger than a noise model that was given, not learned, predicts
            (noise_check.py; 1: not scaled).
        covariance_model, covariance_robust: when the model does not fit (``result.adequacy``),
            the model's covariance and the robust one (robust.py); ``covariance`` and the sigmas
            are then the robust one, which governs. None when the model fits (``covariance`` is the
            model's).
        robust_terms: when the robust covariance governs, (name, note) of each term summed into it
            (robust.py: ``model``, ``jackknife``, ``legs_shift``, ``range_scale_shift``); empty otherwise.
        range_scale_check: how well the data determine the sensor's range scale and what a scale
            error would do (:class:`~graphcal.calibration.range_observability.RangeScaleCheck`);
            None when not checked.
        time_offset_s, time_offset_sigma_s, time_offset_source: a walk's camera: its stamp minus
            its capture time (s), the 1-sigma (s; None when given or not determined) and
            ``estimated``, ``given`` or ``not determined`` (calibration/time_offset.py); None and
            "" for stations.
    """

    name: str
    type: str
    T_body_sensor: np.ndarray
    covariance: np.ndarray
    T_body_sensor_prior: np.ndarray
    sigma_rot_deg: np.ndarray
    sigma_xyz_mm: np.ndarray
    correlation: np.ndarray
    unobservable: tuple[str, ...] = ()
    segments: tuple[ExtrinsicSegment, ...] = ()
    change_stations: tuple[int, ...] = ()
    covariance_scale: float = 1.0
    covariance_model: np.ndarray | None = None
    covariance_robust: np.ndarray | None = None
    robust_terms: tuple[tuple[str, str], ...] = ()
    range_scale_check: object = None
    time_offset_s: float | None = None
    time_offset_sigma_s: float | None = None
    time_offset_source: str = ""

    @property
    def model_covariance(self) -> np.ndarray:
        """The model's covariance (``covariance`` when the model fits, ``covariance_model`` otherwise)."""
        return self.covariance if self.covariance_model is None else self.covariance_model


@dataclass(frozen=True, eq=False)
class LegEstimate:
    """Estimated kinematic parameters of one leg: ``names`` like ``lf_femur_joint.offset_rad`` or
    ``lf_foot_joint.delta_m`` (SI units in the name), ``values`` and ``sigmas`` (same units)."""

    foot: str
    names: tuple[str, ...]
    values: np.ndarray
    sigmas: np.ndarray


@dataclass(frozen=True, eq=False)
class IncrementalStep:
    """After adding one station to the incremental (iSAM2) solver: the sensor's estimate and 1-sigma
    (body axes, deg and mm), the window chi-square statistic and whether a change was declared."""

    station: int
    sensor: str
    T_body_sensor: np.ndarray
    sigma_rot_deg: np.ndarray
    sigma_xyz_mm: np.ndarray
    window_chi2: float
    window_dof: int
    change_detected: bool = False


@dataclass(frozen=True)
class NoiseGroupEstimate:
    """How variance-component estimation set one noise group's sigma, read at the final solution.

    Attributes:
        group: the factor group, e.g. ``foot_on_ground``, ``imu``, ``stance_foot/joint`` (one
            component of a group whose covariance is a sum), ``plane:depth``.
        fields: the :class:`~graphcal.calibration.graph.CalibrationOptions` fields (or
            ``plane_scale:<sensor>``) the group's scale multiplies, with their final values (SI).
        status: ``learned`` (the residuals fit the sigma); ``too few dof`` (the group's rows have
            too little redundancy for its sigma to be estimated: it was held, the residuals only
            hint at ``data_scale``); ``at floor`` (learned down to the smallest sigma allowed);
            ``not converged`` (the re-estimation rounds ran out).
        dof: redundancy of the group's rows at the final solution (degrees of freedom the
            residuals carry about the sigma; a variance from r dof has a relative std of
            ``sqrt(2 / r)``).
        rows: residual rows of the group.
        data_scale: ``sqrt(chi2 / dof)``, the factor the residuals point to for the sigma (1: the
            sigma fits; below 1: the sigma is larger than the data need).
        p_high: probability of a chi-square ``data_scale^2 dof`` at least this large with ``dof``
            degrees of freedom, were the sigma right (small: the sigma is too small for these
            residuals; for one component of a sum an approximation).
        shared_with: the other components of its group that share its scale, because the data did
            not determine their split (``dof``, ``data_scale`` and ``p_high`` are then those of the
            components' sum); empty otherwise.
    """

    group: str
    fields: tuple[tuple[str, float], ...]
    status: str
    dof: float
    rows: int
    data_scale: float
    p_high: float
    shared_with: tuple[str, ...] = ()

    def values_text(self) -> str:
        """The values at the edge, e.g. ``0.06 mm`` (``_m``), ``0.038 deg`` (``_rad``), ``x1.01`` (a scale)."""
        out = []
        for name, v in self.fields:
            if name.endswith("_rad"):
                out.append(f"{np.degrees(v):.3g} deg")
            elif name.endswith("_m"):
                out.append(f"{1e3 * v:.3g} mm")
            else:
                out.append(f"x{v:.3g}")
        return ", ".join(out)


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Everything ``graphcal calibrate`` found.

    Attributes:
        dataset: path of the dataset folder.
        robot_urdf_xml: the nominal URDF (the calibrated one is written from it).
        base_frame: URDF frame of the body.
        sensors: name -> :class:`SensorEstimate`, dataset order.
        legs: foot -> :class:`LegEstimate` (empty without ``--legs``).
        outliers: station ids the robust loss down-weighted.
        residuals: per station and sensor, before and after.
        normal_rms_deg, distance_rms_mm: RMS of the plane angle and distance residuals after.
        T_world_body: station id -> (4, 4) estimated body pose.
        solver: ``"batch"`` or ``"incremental"``.
        iterations: solver iterations (batch) or stations added (incremental).
        history: incremental steps (empty for batch).
        warnings: human-readable warnings (e.g. a direction not determined).
        noise: the noise model the final solve used (SI; after variance-component estimation):
            name -> value, e.g. ``sigma_joint_rad``, ``plane_scale:depth``.
        noise_groups: how each group's sigma was set (:class:`NoiseGroupEstimate`; empty when the
            noise was not learned).
        noise_source: the ``calibration.yaml`` the noise model was read from
            (``calibrate --noise-from``), or "" (learned, or the defaults in incremental mode).
        robot_name: the robot's name (a built-in model's, or the URDF's ``<robot name>``), written
            to ``calibration.yaml`` so that ``--noise-from`` can tell another robot's file; "" if unknown.
        adequacy: the verdict on the model (:class:`~graphcal.calibration.adequacy.Adequacy`), or
            None when not judged.
        walk: a walking dataset's summary (``duration_s``, ``stations``, ``frames`` and
            ``frames_in_log`` per sensor, ``station_times_s``: station -> log time, s, ``profiles``:
            sensor -> ((time offset s, chi2, stage), ...) of each estimated offset), or None.
    """

    dataset: str
    robot_urdf_xml: str
    base_frame: str
    sensors: dict
    legs: dict = field(default_factory=dict)
    outliers: tuple[int, ...] = ()
    residuals: tuple[StationResidual, ...] = ()
    normal_rms_deg: float = float("nan")
    distance_rms_mm: float = float("nan")
    T_world_body: dict = field(default_factory=dict)
    solver: str = "batch"
    iterations: int = 0
    history: tuple[IncrementalStep, ...] = ()
    warnings: tuple[str, ...] = ()
    noise: dict = field(default_factory=dict)
    noise_groups: tuple[NoiseGroupEstimate, ...] = ()
    noise_source: str = ""
    robot_name: str = ""
    adequacy: object = None
    walk: dict | None = None


#: A CAD prior further from the estimate than this many of its own sigmas is reported as wrong.
PRIOR_CONFLICT_SIGMAS = 5.0
#: an estimate this far from its CAD prior, whatever the prior's sigma, points to data in the wrong
#: frame (an audit's planes in the body frame with a 60 deg / 500 mm prior: 137 deg / 395 mm off, no word)
FRAME_MISTAKE_DEG = 30.0
FRAME_MISTAKE_M = 0.25


def prior_conflict(T_body_sensor: np.ndarray, T_prior: np.ndarray, sigma_m: float, sigma_rad: float) -> str:
    """A sentence when the CAD prior (4x4, with its sigma in m and rad from dataset.yaml) is further
    from the calibrated extrinsic than :data:`PRIOR_CONFLICT_SIGMAS` of its own sigma, in rotation
    angle or in translation distance; empty otherwise. The data then outweighed a prior that said
    otherwise: either the prior is wrong or its sigma is too small (and it pulled the estimate)."""
    from graphcal.geometry import rotation_angle_between

    angle = float(rotation_angle_between(T_body_sensor[:3, :3], T_prior[:3, :3]))
    dist = float(np.linalg.norm(T_body_sensor[:3, 3] - T_prior[:3, 3]))
    # a zero sigma holds that part at the CAD value (a note says so): what is left of it is rounding
    k_rot = angle / sigma_rad if sigma_rad > 0 else 0.0
    k_xyz = dist / sigma_m if sigma_m > 0 else 0.0
    frames = angle > np.radians(FRAME_MISTAKE_DEG) or dist > FRAME_MISTAKE_M
    hint = ("; a difference this large is seldom a mounting error: are the planes (planes.csv) and clouds in the "
            "sensor frame, not the body or world frame, and is the prior T_body_sensor, not its inverse? (planes "
            "in the body frame make the data fit a sensor at the body origin)")
    if max(k_rot, k_xyz) <= PRIOR_CONFLICT_SIGMAS:
        if not frames:
            return ""
        return (f"the calibrated pose is {np.degrees(angle):.1f} deg and {1e3 * dist:.0f} mm from the CAD prior in "
                f"dataset.yaml ({max(k_rot, k_xyz):.1f} times its sigma, which allows it)" + hint)
    return (f"the CAD prior in dataset.yaml is {np.degrees(angle):.1f} deg and {1e3 * dist:.0f} mm from the "
            f"calibrated pose, {max(k_rot, k_xyz):.0f} times its stated sigma ({np.degrees(sigma_rad):.3g} deg, "
            f"{1e3 * sigma_m:.3g} mm): the prior is wrong or its sigma too small (a tight wrong prior pulls "
            "the estimate; widen sigma_rpy_deg / sigma_mm or correct the prior)" + (hint if frames else ""))


def calibration_result(ds, robot, data, problem, values, outliers: set, iterations: int,
                       options) -> CalibrationResult:
    """The :class:`CalibrationResult` of a solved calibration graph (batch, or the graph iSAM2 holds).

    Args:
        ds, robot: the dataset (:class:`graphcal.io.dataset.Dataset`) and its robot model.
        data: the :class:`~graphcal.calibration.measurements.CalibrationData` the graph was built from.
        problem, values: the :class:`~graphcal.calibration.graph.CalibrationProblem` and its solution
            (gtsam.Values; body poses T_world_body and extrinsics T_body_sensor in m).
        outliers: the (station, sensor) measurements left out as outliers.
        iterations: solver iterations (batch) or stations added (incremental).
        options: the :class:`~graphcal.calibration.graph.CalibrationOptions` of the final solve.

    Every covariance is of ``xi = [omega (rad), v (m)]`` with ``T = T_hat * Exp(xi)`` (the module's
    convention); sigmas about the body axes in deg and mm.
    """
    from graphcal.calibration.graph import extrinsic_prior_for_observability
    from graphcal.calibration.noise_file import noise_summary
    from graphcal.calibration.residuals import flipped_normal_warnings, plane_residuals
    from graphcal.geometry import from_gtsam_pose
    from graphcal.solvers.covariance import body_axis_sigmas, marginal_covariances, unobservable_directions

    keys = list(problem.sensor_keys.values()) + [k for k, _ in problem.leg_keys.values()]
    covs = marginal_covariances(problem.graph, values, keys)
    sensors, warnings = {}, []
    for name, key in problem.sensor_keys.items():
        T = from_gtsam_pose(values.atPose3(key))
        cov = np.asarray(covs[key])
        T_cad, sig_m, sig_rad = problem.sensor_priors[name]
        cov_prior, held = extrinsic_prior_for_observability(sig_m, sig_rad)
        s_rot, s_xyz, corr, _ = body_axis_sigmas(T, cov)
        unobs = tuple(unobservable_directions(T, cov, cov_prior))
        warnings += [f"{name}: {u}" for u in unobs + held]
        conflict = prior_conflict(T, T_cad, sig_m, sig_rad)
        if conflict:
            warnings.append(f"{name}: {conflict}")
        ids = [st.station for st in data.stations]
        sensors[name] = SensorEstimate(
            name=name, type=ds.sensors[name].type, T_body_sensor=T, covariance=cov, T_body_sensor_prior=T_cad,
            sigma_rot_deg=np.asarray(s_rot), sigma_xyz_mm=np.asarray(s_xyz), correlation=np.asarray(corr),
            unobservable=unobs, segments=(ExtrinsicSegment(min(ids), max(ids), T, cov),),
        )
    legs = {}
    for foot, (key, param) in problem.leg_keys.items():
        legs[foot] = LegEstimate(foot, tuple(param.names), np.asarray(values.atVector(key)),
                                 np.sqrt(np.clip(np.diag(covs[key]), 0.0, None)))
    T_world_body = {st: from_gtsam_pose(values.atPose3(k)) for st, k in problem.station_keys.items()}
    residuals = plane_residuals(data, problem, values, T_world_body, sensors, outliers)
    warnings += flipped_normal_warnings(residuals)
    after = [r for r in residuals if not r.outlier]
    normal_rms = float(np.sqrt(np.mean([r.angle_after_deg**2 for r in after]))) if after else float("nan")
    dist_rms = float(np.sqrt(np.mean([r.distance_after_mm**2 for r in after]))) if after else float("nan")
    return CalibrationResult(
        dataset=str(ds.root) if ds.root is not None else "",
        robot_urdf_xml=robot.urdf_xml,
        robot_name=str(robot.name),
        base_frame=robot.base_frame,
        sensors=sensors,
        legs=legs,
        outliers=tuple(sorted({m[0] for m in outliers})),
        residuals=tuple(residuals),
        normal_rms_deg=normal_rms,
        distance_rms_mm=dist_rms,
        T_world_body=T_world_body,
        solver="batch",
        iterations=iterations,
        warnings=tuple(warnings),
        noise=noise_summary(options, problem),
    )
