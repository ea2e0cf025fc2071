"""What a calibration returns: estimates with their covariance, residuals before and after, outliers.

Frames and units: ``T_body_sensor`` maps sensor coordinates to the body frame (4x4, m). Every
covariance is of the right perturbation ``T = T_hat * Exp(xi)``, ``xi = [omega (rad), v (m)]``
(GTSAM's tangent order, SI units), unless its name says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


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


@dataclass(frozen=True, eq=False)
class LegEstimate:
    """Estimated kinematic parameters of one leg: ``names`` like ``lf_femur_joint.offset_rad`` or
    ``lf_foot_joint.delta_m`` (SI units in the name), ``values`` and ``sigmas`` (same units)."""

    foot: str
    names: tuple[str, ...]
    values: np.ndarray
    sigmas: np.ndarray


@dataclass(frozen=True)
class StationResidual:
    """Plane residual of one station and sensor, against the model before (CAD prior, body poses
    from kinematics) and after calibration. Chai 2015's theta (angle between measured and predicted
    ground, deg) and e_d (distance error, mm)."""

    station: int
    sensor: str
    angle_before_deg: float
    distance_before_mm: float
    angle_after_deg: float
    distance_after_mm: float
    chi2_after: float
    outlier: bool = False


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
