"""The self-calibration factor graph of a static dataset.

Variables (factors/keys.py): X(i) body pose per station, S(k) extrinsic per sensor, F(j) planted
foot per (session, foot), L(l) leg parameters per leg (with ``legs``).

Factors:
* plane observation (X, S): the ground plane each camera measured, with its covariance (Chai 2015);
* range-to-plane (X, S): every laser beam's range against where it meets the ground (Łabęcki
  2012's z_M = 0 criterion, made unbiased for noise along the beams: factors/range_to_plane.py);
* stance foot (X, F[, L]): forward kinematics of the measured joint angles against the planted foot;
* foot on ground (F): the planted foot lies on the ground z = 0;
* IMU attitude (X[, M]): the measured specific force is "up"; with the IMU mounting rotation M
  estimated by default (a custom factor), else the built-in AttitudeFactorPose3;
* commanded-pose prior (X): the set pose, loose (x, y and yaw are otherwise a free gauge); with
  ``legs`` on x, y and yaw only (see :func:`station_factors`);
* extrinsic prior (S): the CAD value and its sigma from dataset.yaml;
* leg-offset prior (L).

The initial values come in closed form: body poses from the stance feet (kinematic_pose.py), the
extrinsic rotation from the normals (Wahba) and its translation from the plane distances (linear
least squares), laser scanners from their points (linear) — see graphcal/solvers/closed_form.py.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Protocol

import gtsam
import numpy as np

from graphcal.calibration.kinematic_pose import kinematic_bodies, leg_kinematics, leg_parameter_kinematics
from graphcal.calibration.measurements import CalibrationData
from graphcal.errors import GraphcalError
from graphcal.factors.keys import C, F, G, L, M, S, X
from graphcal.geometry import to_gtsam_pose


@dataclass(frozen=True)
class CalibrationOptions:
    """Noise models and switches of the calibration graph (SI units).

    Attributes:
        legs: estimate leg kinematic parameters (joint offsets, link lengths) beside the extrinsics.
        sigma_commanded_rad, sigma_commanded_m: commanded-pose prior. Default 1 deg / 10 mm: the
            controller holds the set pose within servo tracking, but kinematic errors move the real
            pose by millimetres to centimetres (Chai 2015 section 4.2).
        sigma_joint_rad, sigma_contact_m: stance-foot noise: joint-angle noise (encoder, backlash)
            mapped through the leg's Jacobian, plus an isotropic contact/compliance term; 0.1 deg and
            1 mm by default.
        sigma_ground_m: a planted foot's height above the nominal ground, 3 mm.
        sigma_imu_rad: attitude from the accelerometer of a station average, 0.5 deg (an AHRS's
            static accuracy, Łabęcki 2012; the constant bias dominates).
        sigma_scan_m: laser range noise per point, 10 mm (URG-04LX).
        plane_angle_floor_rad, plane_distance_floor_m: added to every plane's covariance
            (unmodelled ground roughness); 0 by default.
        robust: Huber loss on the plane and scan factors (threshold: the ``huber_p`` chi-square
            quantile of the factor's dimension, on the whole factor's whitened norm); stations whose
            plane fails the chi-square test at ``outlier_p`` are listed as outliers and left out of
            a second solve.
        leg_offset_sigma_rad, leg_length_sigma_m: leg-parameter priors (how far the URDF may be off).
        plane_sigma_scales: (sensor, scale) pairs multiplying that sensor's plane/scan noise.
        estimate_imu_mounting: estimate the IMU's mounting rotation M (prior: dataset.yaml's
            T_body_imu_prior, sigma ``max(its sigma, sigma_imu_mounting_rad)``). A station-average
            accelerometer's constant bias tilts its "up" by a near-constant angle (0.1 deg for
            0.02 m/s^2); with M estimated the IMU tells relative attitude and the stance feet the
            absolute one. Off: the IMU is trusted as mounted (a bias then tilts every body pose).
        estimate_noise: re-estimate the sigma of every factor group from the residuals
            (variance-component estimation, noise_estimation.py) so that the covariance is honest
            when the defaults above do not fit the robot.
        scale_to_plane_residuals: with ``estimate_noise`` off and the noise learned elsewhere
            (``calibrate --noise-from`` sets it): multiply each sensor's extrinsic covariance by its
            plane residuals' variance factor when above 1 (noise_check.py). Off for the defaults,
            which are conservative as a whole: scaling their too-small plane noise alone made the
            incremental covariance more conservative still (mean NEES 5.99 -> 1.37 over 40 simulated
            sessions, docs/incremental.md).
        ground_unevenness_m, ground_unevenness_rad: how far the ground the sensors see may lie from
            the plane the feet stand on, per session (offset along the normal, m; tilt, rad): on
            uneven ground the feet rest on bumps, and within one stance that offset cannot be told
            from the extrinsic. > 0 adds a ground plane per session G(1 + j) with this prior, seen
            by the cameras' plane factors, so the extrinsic's covariance carries it (several
            sessions with re-planted feet then average it out). Laser scans keep the flat floor.
            0 (default): the floor is flat.
    """

    legs: bool = False
    sigma_commanded_rad: float = float(np.radians(1.0))
    sigma_commanded_m: float = 0.01
    sigma_joint_rad: float = float(np.radians(0.1))
    sigma_contact_m: float = 0.001
    sigma_ground_m: float = 0.003
    sigma_imu_rad: float = float(np.radians(0.5))
    sigma_scan_m: float = 0.01
    plane_angle_floor_rad: float = 0.0
    plane_distance_floor_m: float = 0.0
    robust: bool = True
    huber_p: float = 0.99
    outlier_p: float = 0.999
    leg_offset_sigma_rad: float = float(np.radians(3.0))
    leg_length_sigma_m: float = 0.02
    plane_sigma_scales: tuple[tuple[str, float], ...] = ()
    estimate_noise: bool = True
    scale_to_plane_residuals: bool = False
    estimate_imu_mounting: bool = True
    sigma_imu_mounting_rad: float = float(np.radians(2.0))
    ground_unevenness_m: float = 0.0
    ground_unevenness_rad: float = 0.0

    def plane_scale(self, sensor: str) -> float:
        """Multiplier of the plane (or scan) noise of ``sensor`` (from variance-component estimation)."""
        return dict(self.plane_sigma_scales).get(sensor, 1.0)


#: footprint length (m) over which a ground offset becomes a tilt in :func:`options_for_ground_roughness`
#: (an Octopus-sized stance: 1 mm of offset across it is 0.1 deg)
ROUGHNESS_FOOTPRINT_M = 0.573


def options_for_ground_roughness(options: CalibrationOptions, roughness_m: float) -> CalibrationOptions:
    """``options`` for ground with bumps of RMS height ``roughness_m`` (m; 0 keeps the flat floor).

    The feet rest on bumps and each camera plane is fitted to a bumpy patch, so two terms enter,
    each of the roughness h: the ground the cameras see lies off the feet's plane per session
    (``ground_unevenness_m`` = h, ``ground_unevenness_rad`` = that offset across
    :data:`ROUGHNESS_FOOTPRINT_M`), and every plane gets a floor on its noise (the same distance and
    angle). Measured on the simulator's smooth random bumps (Chai's little and big bumpiness, 3 and
    10 mm RMS, Table A1 program, 12 seeds each, stride 8): with the defaults the error of the
    Kinect extrinsic was up to 14.8 of its reported sigma; with terms of h/3 (until the eighteenth
    stop) the mean NEES was 82 and 24 (95 % interval [4.2, 8.1]: overconfident); with h, 9.1 and 2.6,
    every axis within 2.8 sigma (docs/calibration.md)."""
    import dataclasses

    if not np.isfinite(roughness_m) or roughness_m < 0:
        raise GraphcalError(f"ground roughness must be a finite number >= 0 (m), got {roughness_m}")
    if roughness_m == 0:
        return options
    h = roughness_m
    tilt = float(np.arctan2(h, ROUGHNESS_FOOTPRINT_M))
    return dataclasses.replace(options, ground_unevenness_m=h, ground_unevenness_rad=tilt,
                               plane_distance_floor_m=max(options.plane_distance_floor_m, h),
                               plane_angle_floor_rad=max(options.plane_angle_floor_rad, tilt))


#: key offset of an extrinsic segment: segment j of sensor k is S(k + SEGMENT_KEY_STRIDE * j)
SEGMENT_KEY_STRIDE = 1000


@dataclass(frozen=True, eq=False)
class CalibrationProblem:
    """A built graph with its initial values and the bookkeeping to read results back.

    Attributes:
        graph, initial: the factor graph and initial gtsam.Values.
        sensor_keys: sensor name -> key of its extrinsic.
        sensor_priors: sensor name -> (T_cad 4x4, sigma_m, sigma_rad).
        station_keys: station id -> key of its body pose.
        leg_keys: foot -> (key, LegModel) with ``legs``.
        plane_factors: factor index -> (station, sensor) of every plane / scan factor.
        initial_body: station id -> (4, 4) kinematic body pose (the "before" model).
        initial_extrinsics: sensor -> (4, 4) closed-form extrinsic.
        excluded: (station, sensor) measurements left out (outliers of a previous solve).
        factor_groups: factor index -> noise group ("plane:<sensor>", "stance_foot",
            "foot_on_ground", "imu", "commanded"); priors on S and L belong to no group.
        factor_components: factor index -> {component: covariance} for factors whose noise is a sum
            of components (stance feet: "joint", "contact").
        extensions: the :class:`GraphExtension` the graph was built with (a :class:`CalibrateExtension`
            without one).
        extension_keys: extension name -> key: ``range_scale:<sensor>``, ``session_offset:<session>``,
            ``ground_tilt``, ``imu_mounting``, ``segment:<sensor>:<station>``.
        extension_priors: factor index -> extension name of the priors on those variables.
        measurement_keys: (station, sensor) -> key of the extrinsic (segment) its factor uses.
    """

    graph: gtsam.NonlinearFactorGraph
    initial: gtsam.Values
    sensor_keys: dict
    sensor_priors: dict
    station_keys: dict
    leg_keys: dict
    plane_factors: dict
    initial_body: dict
    initial_extrinsics: dict
    excluded: frozenset = field(default_factory=frozenset)
    factor_groups: dict = field(default_factory=dict)
    factor_components: dict = field(default_factory=dict)
    extensions: object = None
    extension_keys: dict = field(default_factory=dict)
    extension_priors: dict = field(default_factory=dict)
    measurement_keys: dict = field(default_factory=dict)


#: prior pinning x, y and yaw of a session's first body pose when the dataset has no commanded
#: poses (those directions are a free gauge); sigmas [roll, pitch, yaw (rad), x, y, z (m)]
GAUGE_PRIOR_SIGMAS = np.array([1e3, 1e3, 0.1, 0.1, 0.1, 1e3])
#: the same for a walk's first station: tighter, so that the gauge of a long walk's chain of
#: stances is no weaker than the chain itself (with 0.1 m / 0.1 rad a 60 s walk's joint marginals
#: failed as "indeterminate" near its last planted foot); it fixes only x, y and yaw of the walk
WALK_GAUGE_PRIOR_SIGMAS = np.array([1e3, 1e3, 1e-3, 1e-3, 1e-3, 1e3])
#: sigma (rad or m) of a prior's component that is meant to carry no information
LOOSE_SIGMA = 1e3
#: plane covariance used when planes.csv gives none (of (nx, ny, nz, d))
DEFAULT_PLANE_COV = np.diag([1e-6, 1e-6, 1e-6, 1e-6])


#: a zero sigma in dataset.yaml's T_body_sensor_prior ("known exactly") enters the graph at these
PRIOR_SIGMA_FLOOR_M = 1e-6
PRIOR_SIGMA_FLOOR_RAD = 1e-9


def _stations_file(ds) -> str:
    """The dataset's stations.csv as a user would name it (its folder's, when the dataset has one)."""
    return str(ds.root / "stations.csv") if getattr(ds, "root", None) is not None else "stations.csv"


def floored_extrinsic_prior(key: int, T_body_sensor, sigma_m: float, sigma_rad: float):
    """The prior factor of an extrinsic (or of one of its segments) at ``T_body_sensor`` (4x4 or
    gtsam.Pose3: the CAD pose, or the estimate before a change) with dataset.yaml's sigmas (m, rad);
    a zero sigma ("known exactly") enters at ``PRIOR_SIGMA_FLOOR_M`` / ``PRIOR_SIGMA_FLOOR_RAD``."""
    from graphcal.factors.priors import extrinsic_prior

    return extrinsic_prior(key, T_body_sensor, max(sigma_m, PRIOR_SIGMA_FLOOR_M), max(sigma_rad, PRIOR_SIGMA_FLOOR_RAD))


def extrinsic_prior_for_observability(sigma_m: float, sigma_rad: float) -> tuple[np.ndarray, tuple[str, ...]]:
    """The 6x6 prior covariance ``[rot, trans]`` (rad, m) the posterior of an extrinsic is compared
    with to name undetermined directions, and a note per part held at the CAD value. A zero sigma
    (the user says the CAD value is exact) is not "undetermined by the data": that part counts as
    determined (compared with 1 rad / 1 m) and gets the note instead."""
    rot = sigma_rad if sigma_rad > 0 else 1.0
    trans = sigma_m if sigma_m > 0 else 1.0
    notes = tuple(f"{part} held at the CAD value ({key}: 0 in dataset.yaml: known exactly)"
                  for part, key, s in (("rotation", "sigma_rpy_deg", sigma_rad), ("translation", "sigma_mm", sigma_m))
                  if not s > 0)
    return np.diag([rot**2] * 3 + [trans**2] * 3), notes


def huber_loss(dim: int, options: CalibrationOptions):
    """Huber loss for a factor of ``dim`` rows. GTSAM's Robust model applies the M-estimator to the
    whole factor's whitened norm, so its threshold grows with the dimension: k is the chi-square
    quantile ``huber_p`` of ``dim`` dof (a whole station's plane or scan that no noise explains is
    down-weighted; ordinary noise never is)."""
    return gtsam.noiseModel.mEstimator.Huber.Create(_huber_threshold(float(options.huber_p), int(dim)))


@functools.lru_cache(maxsize=64)
def _huber_threshold(p: float, dim: int) -> float:
    """sqrt of the chi-square quantile p of dim dof (one per factor: cached)."""
    from graphcal import stats as chi2

    return float(np.sqrt(chi2.ppf(p, dim)))


def measurement_factor(x_key: int, s_key: int, sensor: str, options: CalibrationOptions, *, plane=None,
                       points=None, robust: bool = False, c_key: int | None = None, g_key: int | None = None):
    """The factor of what one sensor saw at one station: the ground plane of a camera
    (plane_observation, its covariance scaled by the sensor's noise scale) or the beams of a laser
    scan (range_to_plane). ``robust``: Huber loss sized to the factor's dimension. ``c_key``: the
    sensor's range-scale variable (factors/range_scale.py); ``g_key``: an estimated ground plane
    (cameras only)."""
    from graphcal.factors.plane_observation import plane_noise_model, plane_observation_factor
    from graphcal.factors.range_scale import scaled_plane_factor, scaled_range_factor
    from graphcal.factors.range_to_plane import range_to_plane_factor

    scale = options.plane_scale(sensor)
    if plane is not None:
        cov = (plane.cov if plane.cov is not None else DEFAULT_PLANE_COV) * scale**2
        n_m = np.asarray(plane.n, dtype=float)
        if c_key is not None:
            noise = plane_noise_model(n_m, cov, options.plane_angle_floor_rad, options.plane_distance_floor_m,
                                      robust=huber_loss(3, options) if robust else None)
            return scaled_plane_factor(x_key, s_key, c_key, n_m, float(plane.d), noise_model=noise, g_key=g_key)
        return plane_observation_factor(
            x_key, s_key, n_m, float(plane.d), cov, g_key=g_key,
            sigma_angle_floor_rad=options.plane_angle_floor_rad,
            sigma_distance_floor_m=options.plane_distance_floor_m,
            robust=huber_loss(3, options) if robust else None)
    if points is None:
        raise GraphcalError(f"sensor {sensor}: a measurement needs a plane or scan points")
    if g_key is not None:
        raise GraphcalError(f"sensor {sensor}: an estimated ground plane is not supported for laser scans")
    pts = np.asarray(points, dtype=float)
    rob = huber_loss(len(pts), options) if robust else None
    if c_key is not None:
        return scaled_range_factor(x_key, s_key, c_key, pts, options.sigma_scan_m * scale, robust=rob)
    return range_to_plane_factor(x_key, s_key, pts, options.sigma_scan_m * scale, robust=rob)


def leg_parameter_priors(robot, options: CalibrationOptions) -> list:
    """(foot, key L(l), LegModel, prior factor) per leg, for ``options.legs``."""
    from graphcal.factors.priors import leg_offset_prior
    from graphcal.models.legs import leg_model

    out = []
    for idx, foot in enumerate(robot.feet):
        param = leg_model(robot, foot, origins="none")
        sig = np.array([options.leg_offset_sigma_rad if nm.endswith(".offset_rad") else options.leg_length_sigma_m
                        for nm in param.names])
        out.append((foot, L(idx), param, leg_offset_prior(L(idx), len(param.names), sig)))
    return out


def imu_mounting_prior(R_body_imu: np.ndarray, prior_sigma_rad: float, options: CalibrationOptions):
    """Prior on the IMU mounting rotation M(0) (dataset.yaml's prior, at least
    ``options.sigma_imu_mounting_rad``)."""
    sig = max(prior_sigma_rad, options.sigma_imu_mounting_rad)
    return gtsam.PriorFactorRot3(M(0), gtsam.Rot3(R_body_imu), gtsam.noiseModel.Isotropic.Sigma(3, sig))


def station_factors(robot, st, x_key: int, foot_keys: dict, leg_keys: dict, options: CalibrationOptions, *,
                    R_body_imu: np.ndarray | None, kinematics: dict | None = None, w_key: int | None = None,
                    stance=None, parameter_kinematics: dict | None = None) -> list:
    """The proprioceptive factors of one station, as (factor, noise group or None, noise components or None):
    a stance-foot factor per planted foot (noise: joint noise through the leg plus contact noise),
    the IMU attitude, and the commanded-pose prior. ``kinematics``: :func:`leg_kinematics` when
    already computed; ``stance``: an extension's stance-foot factors (:attr:`ExtensionKeys.stance`);
    ``parameter_kinematics``: foot -> :func:`leg_parameter_kinematics` of the legs estimated."""
    from graphcal.factors.imu_attitude import imu_attitude_factor, imu_attitude_misaligned_factor
    from graphcal.factors.priors import commanded_pose_prior
    from graphcal.factors.stance_foot import stance_foot_factor
    from graphcal.factors.stance_foot_builtin import MIN_RANGE_M, stance_foot_builtin_factors
    from graphcal.models.kinematics import foot_positions, leg_jacobian

    var_joint, var_contact = options.sigma_joint_rad**2, options.sigma_contact_m**2
    feet = []  # (foot, q, leg key, param, p_fk or None, leg position Jacobian)
    for f, q in st.q_by_foot.items():
        leg_key, param = leg_keys.get(f, (None, None))
        cached = kinematics.get((st.station, f)) if kinematics is not None else None
        if cached is None:
            qa = np.asarray(q, dtype=float)
            cached = (foot_positions(robot.leg(f), qa) if leg_key is None else None, leg_jacobian(robot.leg(f), qa))
        feet.append((f, q, leg_key, param, cached[0] if leg_key is None else None, cached[1]))
    # legs held fixed: GTSAM's bearing-range factor in C++, the noise components mapped to its error
    # (first-order equivalent, factors/stance_foot_builtin.py); one batch per station
    fixed = [j for j, e in enumerate(feet) if e[4] is not None and np.linalg.norm(e[4]) >= MIN_RANGE_M
             and stance is None]
    built = {}
    if fixed:
        P = np.array([feet[j][4] for j in fixed])
        Jl = [feet[j][5] for j in fixed]
        cov_joint = var_joint * np.stack([J @ J.T for J in Jl])
        cov_contact = np.broadcast_to(var_contact * np.eye(3), cov_joint.shape)
        factors, mapped = stance_foot_builtin_factors(x_key, [foot_keys[feet[j][0]] for j in fixed], P,
                                                      {"joint": cov_joint, "contact": cov_contact})
        for i, j in enumerate(fixed):
            built[j] = (factors[i], {k: v[i] for k, v in mapped.items()})
    out = []
    for j, (f, q, leg_key, param, p_fk, J) in enumerate(feet):
        if j not in built:
            cov_joint, cov_contact = var_joint * (J @ J.T), var_contact * np.eye(3)
            factor = None if stance is None else stance(st, f, x_key, foot_keys[f], cov_joint + cov_contact, leg_key,
                                                        param)
            if factor is None:
                at = (parameter_kinematics or {}).get(f, {}).get(st.station) if leg_key is not None else None
                factor = stance_foot_factor(x_key, foot_keys[f], q, robot.leg(f), l_key=leg_key, param=param,
                                            cov_m2=cov_joint + cov_contact, p_fk=p_fk, kin_at=at)
            built[j] = (factor, {"joint": cov_joint, "contact": cov_contact})
        out.append((built[j][0], "stance_foot", built[j][1]))
    if st.imu_accel is not None and R_body_imu is not None:
        if options.estimate_imu_mounting and w_key is not None:
            from graphcal.factors.gravity_tilt import imu_attitude_tilted_factor

            out.append((imu_attitude_tilted_factor(x_key, M(0), w_key, st.imu_accel, options.sigma_imu_rad), "imu", None))
        elif options.estimate_imu_mounting:
            out.append((imu_attitude_misaligned_factor(x_key, M(0), st.imu_accel, options.sigma_imu_rad), "imu", None))
        else:
            out.append((imu_attitude_factor(x_key, st.imu_accel, options.sigma_imu_rad, R_body_imu=R_body_imu),
                        "imu", None))
    if st.T_world_body_cmd is not None and options.legs:
        # the controller computed the commanded pose with the nominal legs: its difference from the
        # real pose is a function of the leg errors being estimated, not independent noise (as a
        # prior on roll, pitch and height, with its sigma learned from the residuals, it pulled the
        # legs and the extrinsic height by 10-20 sigma; docs/calibration.md, "Leg offsets from
        # stance"). With legs it keeps only x, y and yaw (the gauge the ground cannot see) at its
        # default sigma, in no noise group.
        s_rad, s_m = options.sigma_commanded_rad, options.sigma_commanded_m
        out.append((commanded_pose_prior(x_key, st.T_world_body_cmd, [LOOSE_SIGMA, LOOSE_SIGMA, s_rad],
                                         [s_m, s_m, LOOSE_SIGMA]), None, None))
    elif st.T_world_body_cmd is not None:
        out.append((commanded_pose_prior(x_key, st.T_world_body_cmd, options.sigma_commanded_rad,
                                         options.sigma_commanded_m), "commanded", None))
    return out


@dataclass(frozen=True, eq=False)
class GraphBuild:
    """The calibration graph while :func:`build_problem` builds it: what a :class:`GraphExtension`
    reads (the dataset, the sensors' variables) and where it adds its variables and priors.

    Attributes:
        ds, data, options: the dataset, its :class:`CalibrationData` and the options of the build.
        graph, values: the factor graph and initial values being filled.
        sensor_keys, sensor_priors, initial_extrinsics: as in :class:`CalibrationProblem` (filled
            before the extension is called).
        station_order: station id -> its position in ``data.stations``.
        sessions: the session labels in station order (each once).
        factor_groups: factor index -> noise group (as in :class:`CalibrationProblem`).
        extension_keys, extension_priors: as in :class:`CalibrationProblem`; an extension records
            the keys of its variables and (through :meth:`add_prior`) the indices of their priors.
    """

    ds: object
    data: CalibrationData
    options: CalibrationOptions
    graph: gtsam.NonlinearFactorGraph = field(default_factory=gtsam.NonlinearFactorGraph)
    values: gtsam.Values = field(default_factory=gtsam.Values)
    sensor_keys: dict = field(default_factory=dict)
    sensor_priors: dict = field(default_factory=dict)
    initial_extrinsics: dict = field(default_factory=dict)
    station_order: dict = field(default_factory=dict)
    sessions: list = field(default_factory=list)
    factor_groups: dict = field(default_factory=dict)
    factor_components: dict = field(default_factory=dict)
    extension_keys: dict = field(default_factory=dict)
    extension_priors: dict = field(default_factory=dict)

    def add(self, factor, group: str | None = None, components: dict | None = None) -> None:
        """Add a factor, in noise group ``group`` (None: no group), its noise a sum of ``components``."""
        if group is not None:
            self.factor_groups[self.graph.size()] = group
        if components is not None:
            self.factor_components[self.graph.size()] = components
        self.graph.add(factor)

    def add_prior(self, factor, name: str) -> None:
        """Add the prior of an extension's variable, recorded in ``extension_priors`` as ``name``."""
        self.extension_priors[self.graph.size()] = name
        self.graph.add(factor)


@dataclass(frozen=True)
class ExtensionKeys:
    """The variables a :class:`GraphExtension` added that the calibration's own factors use.

    Attributes:
        range_scale: sensor -> key of its range scale (its plane and scan factors read scaled ranges).
        ground_tilt: key of gravity against the ground (Rot3) in every IMU factor, or None.
        segments: sensor -> ((position in station order from which it applies, key of an extrinsic
            segment (Pose3)), ...): the measurements from there on use that extrinsic.
        session_planes: session -> key of the ground plane (OrientedPlane3) the sensors see at its
            stations.
        leg_feet: feet whose leg parameters get the extension's prior (:meth:`GraphExtension.leg_prior`).
        stance: None, or ``stance(st, foot, x_key, f_key, cov_m2, leg_key, param)`` -> the stance-foot
            factor of that station and foot (a foot radius, joint compliance), or None for the usual one.
    """

    range_scale: dict = field(default_factory=dict)
    ground_tilt: int | None = None
    segments: dict = field(default_factory=dict)
    session_planes: dict = field(default_factory=dict)
    leg_feet: frozenset = frozenset()
    stance: object = None


class GraphExtension(Protocol):
    """A hook of :func:`build_problem`: extra variables and priors in the calibration graph (the
    diagnosis catalogue's model extensions, graphcal/diagnosis/extensions.py)."""

    def add_variables(self, build: GraphBuild) -> ExtensionKeys:
        """Add variables with their priors (:meth:`GraphBuild.add_prior`) once the sensors' extrinsics
        are in ``build``; return the keys the measurement and station factors must use."""

    def leg_prior(self, foot: str, key: int, n_params: int):
        """The prior factor on leg ``foot``'s parameters (key ``key``, ``n_params`` of them, SI) for a
        foot of :attr:`ExtensionKeys.leg_feet` (replacing ``options``' leg priors)."""

    def imu_mounting_prior(self, R_body_imu: np.ndarray):
        """The prior factor on the IMU mounting rotation M(0) about ``R_body_imu`` (3x3, body <- IMU),
        or None for the default (:func:`imu_mounting_prior`)."""


def add_range_scale_variables(build: GraphBuild, range_scale) -> dict:
    """Add a range scale C(k) (Vector 1, factors/range_scale.py) for each ``(sensor, sigma)`` of
    ``range_scale``, at 1 with a prior 1 +- sigma (recorded as ``range_scale:<sensor>`` in
    ``extension_keys`` and ``extension_priors``); returns sensor -> key, for
    :attr:`ExtensionKeys.range_scale` (the sensor's planes and scans then read scaled ranges)."""
    sensor_index = {name: k for k, name in enumerate(build.ds.sensors)}
    out = {}
    for name, sig in range_scale:
        if name not in build.sensor_keys:
            raise GraphcalError(f"range_scale names sensor {name!r}, which has no measurements")
        key = C(sensor_index[name])
        build.extension_keys[f"range_scale:{name}"] = out[name] = key
        build.values.insert(key, np.array([1.0]))
        build.add_prior(gtsam.PriorFactorVector(key, np.array([1.0]), gtsam.noiseModel.Isotropic.Sigma(1, float(sig))),
                        f"range_scale:{name}")
    return out


def add_extrinsic_segments(build: GraphBuild, extrinsic_segments) -> dict:
    """Add an extrinsic segment S(k + SEGMENT_KEY_STRIDE j) for each ``(sensor, station)`` of
    ``extrinsic_segments`` (from that station on, in station order, the sensor's measurements use
    it), at the closed-form extrinsic with the sensor's prior (recorded as
    ``segment:<sensor>:<station>``); returns sensor -> [(position in station order, key)], for
    :attr:`ExtensionKeys.segments`."""
    sensor_index = {name: k for k, name in enumerate(build.ds.sensors)}
    segments: dict[str, list[tuple[int, int]]] = {}
    for name, station in extrinsic_segments:
        if name not in build.sensor_keys:
            raise GraphcalError(f"extrinsic segment names sensor {name!r}, which has no measurements")
        if station not in build.station_order:
            raise GraphcalError(f"extrinsic segment of {name!r} starts at station {station}, which does not exist")
        j = len(segments.setdefault(name, [])) + 1
        key = S(sensor_index[name] + SEGMENT_KEY_STRIDE * j)
        segments[name].append((build.station_order[station], key))
        build.extension_keys[f"segment:{name}:{station}"] = key
        build.values.insert(key, to_gtsam_pose(build.initial_extrinsics[name]))
        T_cad, sig_m, sig_r = build.sensor_priors[name]
        build.add_prior(floored_extrinsic_prior(key, T_cad, sig_m, sig_r), f"segment:{name}:{station}")
    return segments


@dataclass(frozen=True)
class CalibrateExtension:
    """calibrate's own extensions of its graph: none by default (the graph as calibrate builds it);
    for the robust covariance's terms (robust.py) a range scale per sensor of ``range_scale``
    ((sensor, prior sigma) pairs) and a second extrinsic of each sensor of ``extrinsic_segments``
    ((sensor, station) pairs) from that station on."""

    range_scale: tuple[tuple[str, float], ...] = ()
    extrinsic_segments: tuple[tuple[str, int], ...] = ()

    def add_variables(self, build: GraphBuild) -> ExtensionKeys:
        return ExtensionKeys(range_scale=add_range_scale_variables(build, self.range_scale),
                             segments=add_extrinsic_segments(build, self.extrinsic_segments))

    def leg_prior(self, foot: str, key: int, n_params: int):
        return None

    def imu_mounting_prior(self, R_body_imu: np.ndarray):
        return None


def build_problem(ds, robot, data: CalibrationData, options: CalibrationOptions, *,
                  exclude: frozenset = frozenset(), extensions: GraphExtension | None = None,
                  initial: gtsam.Values | None = None) -> CalibrationProblem:
    """Build the calibration graph of a dataset (see the module docstring).

    Args:
        exclude: (station, sensor) measurements to leave out.
        extensions: extra variables (a :class:`GraphExtension`: the diagnosis catalogue's
            :class:`~graphcal.diagnosis.extensions.ModelExtensions`); None: none.
        initial: values to start from instead of the closed form, for every variable they hold
            (a warm start from a previous solve of a similar graph).
    """
    ext = extensions if extensions is not None else CalibrateExtension()
    if not data.stations:
        raise GraphcalError(f"{_stations_file(ds)}: no stations (a header without rows): nothing to calibrate")
    if options.legs and not any(st.q_by_foot for st in data.stations):
        raise GraphcalError(f"{_stations_file(ds)}: --legs estimates the legs from the stance feet's joint angles, "
                            f"and no station has any (no q_<joint> columns for the feet of dataset.yaml's robot); "
                            f"calibrate without --legs")
    b = GraphBuild(ds, data, options, station_order={st.station: i for i, st in enumerate(data.stations)},
                   sessions=list(dict.fromkeys(st.session for st in data.stations)))
    u_body, height, T_body0 = kinematic_bodies(data, robot)
    station_keys = {st.station: X(st.station) for st in data.stations}
    for st in data.stations:
        b.values.insert(station_keys[st.station], to_gtsam_pose(T_body0[st.station]))
    _add_sensors(b, exclude, u_body, height)
    ek = ext.add_variables(b)
    uneven_planes = _add_uneven_ground(b, ek)
    plane_factors, measurement_keys = _add_measurements(b, exclude, ek, uneven_planes)
    leg_keys = _add_legs(b, robot, ext, ek)
    _add_stations(b, robot, station_keys, leg_keys, T_body0, ext, ek)
    if initial is not None:
        for k in initial.keys():
            if b.values.exists(k):
                _copy_value(b.values, initial, int(k))
    return CalibrationProblem(b.graph, b.values, b.sensor_keys, b.sensor_priors, station_keys, leg_keys, plane_factors,
                              T_body0, b.initial_extrinsics, frozenset(exclude), b.factor_groups, b.factor_components,
                              ext, b.extension_keys, b.extension_priors, measurement_keys)


def _add_sensors(b: GraphBuild, exclude: frozenset, u_body: dict, height: dict) -> None:
    """Every sensor with data: its extrinsic S(k) at the closed form, and its CAD prior."""
    from graphcal.solvers.closed_form import extrinsic_from_scan_points, robust_closed_form_extrinsic

    data = b.data
    for k, (name, spec) in enumerate(b.ds.sensors.items()):
        T_cad = spec.T_body_sensor_prior.matrix
        prior = (T_cad, spec.T_body_sensor_prior.sigma_m, spec.T_body_sensor_prior.sigma_rad)
        planes = [(st.station, data.planes[(st.station, name)]) for st in data.stations
                  if (st.station, name) in data.planes and (st.station, name) not in exclude]
        scans = [(st.station, data.scan_points[(st.station, name)]) for st in data.stations
                 if (st.station, name) in data.scan_points and (st.station, name) not in exclude]
        if not planes and not scans:
            continue  # a sensor with no data at the stations: nothing to calibrate
        if planes:
            ids = [s for s, _ in planes]
            T0 = robust_closed_form_extrinsic(
                np.array([u_body[s] for s in ids]), np.array([p.n for _, p in planes]),
                np.array([p.d for _, p in planes]), np.array([height[s] for s in ids]), T_cad)
        else:
            T0, _ = extrinsic_from_scan_points([u_body[s] for s, _ in scans], [height[s] for s, _ in scans],
                                               [p for _, p in scans], T_prior=T_cad)
        key = S(k)
        b.sensor_keys[name], b.sensor_priors[name], b.initial_extrinsics[name] = key, prior, T0
        b.values.insert(key, to_gtsam_pose(T0))
        b.graph.add(floored_extrinsic_prior(key, T_cad, prior[1], prior[2]))
    if not b.sensor_keys:
        raise GraphcalError("no sensor has ground planes or scan points at any station: nothing to calibrate")


def _add_uneven_ground(b: GraphBuild, ek: ExtensionKeys) -> dict:
    """session -> G(1 + j), the plane the cameras see on uneven ground (``options.ground_unevenness_*``;
    laser scans: not supported), for the sessions without an extension's plane."""
    from graphcal.factors.plane_prior import plane_prior_factor

    options = b.options
    uneven_planes = {}
    if options.ground_unevenness_m > 0 or options.ground_unevenness_rad > 0:
        for j, s_name in enumerate(b.sessions):
            if s_name in ek.session_planes:
                continue
            key = G(1 + j)
            uneven_planes[s_name] = key
            b.values.insert(key, gtsam.OrientedPlane3(0.0, 0.0, 1.0, 0.0))
            b.add_prior(plane_prior_factor(key, [0.0, 0.0, 1.0, 0.0], max(options.ground_unevenness_rad, 1e-9),
                                           max(options.ground_unevenness_m, 1e-9)), f"ground_unevenness:{s_name}")
    return uneven_planes


def _add_measurements(b: GraphBuild, exclude: frozenset, ek: ExtensionKeys, uneven_planes: dict) -> tuple[dict, dict]:
    """The plane and scan factors of every sensor and station; returns (factor index -> (station,
    sensor), (station, sensor) -> key of the extrinsic its factor uses)."""
    data, options = b.data, b.options
    session_of = {st.station: st.session for st in data.stations}

    def extrinsic_key(name: str, station: int) -> int:
        key = b.sensor_keys[name]
        for start, k in sorted(ek.segments.get(name, [])):
            if b.station_order[station] >= start:
                key = k
        return key

    plane_factors, measurement_keys = {}, {}
    for name in b.sensor_keys:
        c_key = ek.range_scale.get(name)
        for st in data.stations:
            m = (st.station, name)
            if m in exclude:
                continue
            key = extrinsic_key(name, st.station)
            gk = ek.session_planes.get(session_of[st.station])
            if m in data.planes:
                gk = uneven_planes.get(session_of[st.station], gk)
                f = measurement_factor(X(st.station), key, name, options, plane=data.planes[m],
                                       robust=options.robust, c_key=c_key, g_key=gk)
            elif m in data.scan_points:
                f = measurement_factor(X(st.station), key, name, options, points=data.scan_points[m],
                                       robust=options.robust, c_key=c_key, g_key=gk)
            else:
                continue
            plane_factors[b.graph.size()] = m
            measurement_keys[m] = key
            b.add(f, f"plane:{name}")
    return plane_factors, measurement_keys


def _add_legs(b: GraphBuild, robot, ext: GraphExtension, ek: ExtensionKeys) -> dict:
    """foot -> (L(l), LegParameterization) of every leg estimated (``options.legs``, or a leg of the
    extension), with its prior."""
    leg_keys = {}
    if b.options.legs or ek.leg_feet:
        for foot, key, param, prior in leg_parameter_priors(robot, b.options):
            if foot in ek.leg_feet:
                factor = ext.leg_prior(foot, key, len(param.names))
                leg_keys[foot] = (key, param)
                b.values.insert(key, np.zeros(len(param.names)))
                b.add_prior(factor, f"legs:{foot}")
            elif b.options.legs:
                leg_keys[foot] = (key, param)
                b.values.insert(key, np.zeros(len(param.names)))
                b.graph.add(prior)
    return leg_keys


def planted_foot_index(data, robot) -> dict:
    """(stance label, foot) -> j of the planted-foot variable F(j): every (session, foot) of
    ``robot.feet`` in session order, then the walks' own stances (a foot's label per touchdown,
    :attr:`~graphcal.calibration.measurements.StationMeasurements.stances`) in order of appearance."""
    sessions = list(dict.fromkeys(st.session for st in data.stations if st.stances is None))
    index = {(s, f): j for j, (s, f) in enumerate((s, f) for s in sessions for f in robot.feet)}
    for st in data.stations:
        if st.stances is not None:
            for f in st.q_by_foot:
                index.setdefault((st.stances[f], f), len(index))
    return index


def _add_stations(b: GraphBuild, robot, station_keys: dict, leg_keys: dict, T_body0: dict, ext: GraphExtension,
                  ek: ExtensionKeys) -> None:
    """The proprioceptive factors of every station (:func:`station_factors`), the IMU mounting
    variable with its prior, the planted feet F(j) on the ground, and the gauge priors when the
    dataset has no commanded poses."""
    from graphcal.factors.foot_on_ground import foot_on_ground_factor

    ds, data, options, values = b.ds, b.data, b.options, b.values
    kin = leg_kinematics(data, robot)
    par_kin = {f: leg_parameter_kinematics(data, robot, f, param) for f, (_, param) in leg_keys.items()}
    foot_index = planted_foot_index(data, robot)
    feet_sum: dict = {}
    R_body_imu = ds.imu.T_body_imu_prior.matrix[:3, :3] if ds.imu is not None else None
    for st in data.stations:
        T = T_body0[st.station]
        if R_body_imu is not None and st.imu_accel is not None and options.estimate_imu_mounting \
                and not values.exists(M(0)):
            values.insert(M(0), gtsam.Rot3(R_body_imu))
            factor = ext.imu_mounting_prior(R_body_imu)
            if factor is None:
                b.graph.add(imu_mounting_prior(R_body_imu, ds.imu.T_body_imu_prior.sigma_rad, options))
            else:
                b.extension_keys["imu_mounting"] = M(0)
                b.add_prior(factor, "imu_mounting")
        foot_keys = {f: F(foot_index[(st.stance_of(f), f)]) for f in st.q_by_foot}
        for factor, group, comps in station_factors(robot, st, station_keys[st.station], foot_keys, leg_keys,
                                                    options, R_body_imu=R_body_imu, kinematics=kin,
                                                    w_key=ek.ground_tilt, stance=ek.stance,
                                                    parameter_kinematics=par_kin):
            b.add(factor, group, comps)
        for f, q in st.q_by_foot.items():
            p_world = T[:3, :3] @ kin[(st.station, f)][0] + T[:3, 3]
            feet_sum.setdefault(foot_index[(st.stance_of(f), f)], []).append(p_world)
    for j, pts in feet_sum.items():
        p0 = np.mean(pts, axis=0)
        p0[2] = 0.0
        values.insert(F(j), p0)
        b.add(foot_on_ground_factor(F(j), options.sigma_ground_m), "foot_on_ground")
    if not any(st.T_world_body_cmd is not None for st in data.stations):
        # no commanded poses: x, y and yaw of each session are a free gauge; pin them loosely
        first = {}
        for st in data.stations:
            first.setdefault(st.session, st.station)
        walked = {st.station for st in data.stations if st.stances is not None}
        for s, station in first.items():
            sig = WALK_GAUGE_PRIOR_SIGMAS if station in walked else GAUGE_PRIOR_SIGMAS
            b.graph.add(gtsam.PriorFactorPose3(station_keys[station], to_gtsam_pose(T_body0[station]),
                                               gtsam.noiseModel.Diagonal.Sigmas(sig)))


def _copy_value(values: gtsam.Values, source: gtsam.Values, key: int) -> None:
    """values[key] = source[key] for the kinds the calibration graph uses."""
    for getter in ("atPose3", "atPoint3", "atRot3", "atOrientedPlane3", "atVector"):
        try:
            v = getattr(source, getter)(key)
        except RuntimeError:
            continue
        if getter == "atVector" and np.size(v) != values.atVector(key).size:
            return
        values.update(key, v)
        return


def predicted_plane_errors(T_world_body: np.ndarray, T_body_sensor: np.ndarray, n_m, d_m) -> tuple[float, float]:
    """Chai's theta (deg) and e_d (mm) of a measured plane against the ground z = 0 seen from the
    given body pose and extrinsic."""
    from graphcal.factors.plane_observation import plane_angle_distance_error

    ang, dist = plane_angle_distance_error(T_world_body @ T_body_sensor, n_m, d_m)
    return float(np.degrees(ang)), float(1e3 * abs(dist))


__all__ = ["CalibrationOptions", "CalibrationProblem", "build_problem", "predicted_plane_errors", "CalibrateExtension",
           "add_range_scale_variables", "add_extrinsic_segments"]
