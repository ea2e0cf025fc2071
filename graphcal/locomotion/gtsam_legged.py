"""GTSAM 4.3's legged estimators on graphcal's filter inputs (:class:`~graphcal.locomotion.track_inputs.TrackInputs`).

GTSAM ships three legged estimators that share one parameter set (``gtsam.LeggedEstimatorParams``)
and one interface (``predict(omega, f, dt)`` with the IMU reading, ``processContacts([...])`` with
one ``gtsam.ContactMeasurement`` -- foot index, body-frame foot point, touchdown flag -- per foot in
stance); :func:`run_gtsam_legged` runs one of them over the same inputs as graphcal's
:func:`~graphcal.locomotion.estimator.run_filter`, used as GTSAM's example
(``gtsam/examples/LeggedEstimatorExample.py``) uses them:

* ``invariant_ekf``: ``gtsam.LeggedInvariantEKF`` -- an invariant EKF on the extended pose
  SE_{2+K}(3) (rotation, position, velocity, the K footholds); no IMU bias in its state;
* ``invariant_iekf``: ``gtsam.LeggedInvariantIEKF`` -- the same, iterated at each contact update
  (the example calls it ``invariant_graph``);
* ``fixed_lag``: ``gtsam.LeggedFixedLagSmoother`` -- a fixed-lag smoother (``lag_s``) of
  preintegrated IMU factors and foothold factors with one constant bias (``fixed_lag_single_bias``
  in the example); it reports no covariance.

The IMU: the readings in the IMU frame, ``params.body_P_imu = inputs.T_body_imu``; the estimators'
state is the IMU's navigation state (the example's ``world_T_body = world_T_imu * body_P_imu^-1``),
turned into T_world_body here. The feet: the body-frame foot points (``inputs.p_body_foot``, or the
forward kinematics of the joint angles, :func:`foot_points_from_joints`), measured where the stance
mask says (the mask graphcal's filter decided, ``TrackResult.stance_mask``, or ``inputs.contact``).

Noise from graphcal's :class:`~graphcal.locomotion.ekf.EkfNoise` where GTSAM has the same quantity
(:func:`legged_params`; docs/state_estimation.md, "GTSAM's legged estimators, side by side"):
gyro and accelerometer white noise (density^2 -> the preintegration covariances), bias random
walks, the planted foot's random walk (``foot_rw`` -> ``footholdProcessSigma``, a density in both:
measured, 1 s of prediction adds sigma^2 to the foothold variance), the contact covariance (the
kinematic noise plus the encoders' seen through the leg Jacobians, averaged over the stance
samples: GTSAM takes one constant covariance). GTSAM has no ICP, no per-sample contact covariance
and (in the two EKFs) no IMU bias; graphcal has no integration noise, no height prior, no robust
contact noise.

World frame: graphcal's (:mod:`graphcal.locomotion.estimator`): roll and pitch from the mean
accelerometer of the first ``init_window_s``, yaw 0, the body above the first stance feet, those
feet at z = 0. Covariance: the EKFs' error is left-invariant (measured: a position-only contact
update leaves a yaw variance untouched 10 m from the origin), ``X_true = X Exp(xi)`` with
``xi = [dtheta, dp, dv, dfeet]`` in the IMU frame; it is turned into graphcal's pose order
``[dp world, dtheta body]`` (``TrackResult.cov_pose``) so that the NEES is computed alike.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.geometry import matrix_from_rpy, pose_adjoint
from graphcal.locomotion.ekf import GRAVITY_WORLD, EkfNoise

__all__ = ["VARIANTS", "EXAMPLE_NOISE", "GtsamLeggedSettings", "GtsamLeggedResult", "legged_params", "contact_covariance",
           "foot_points_from_joints", "run_gtsam_legged", "stance_mask_of"]

#: the three estimators and GTSAM's classes (the example's names in parentheses in the docstring)
VARIANTS = ("invariant_ekf", "invariant_iekf", "fixed_lag")
#: the noise of GTSAM's example for its Spot sample, as graphcal's EkfNoise (gyro 8e-4, accel 2e-2,
#: foothold process 1e-4, bias walks 1e-4 / 5e-3); its contact sigmas are GtsamLeggedSettings.example()'s
EXAMPLE_NOISE = EkfNoise(gyro_noise_density=8e-4, accel_noise_density=2e-2, foot_rw=1e-4, gyro_bias_rw=1e-4,
                         accel_bias_rw=5e-3)


@dataclass(frozen=True)
class GtsamLeggedSettings:
    """What GTSAM's estimators take beyond graphcal's noise (SI units).

    Attributes:
        lag_s: the fixed-lag smoother's window (s); the example's 1 s.
        contact_every: contacts processed every k-th sample (and at every touchdown); graphcal's
            stance update rate (TrackerConfig.stance_every) by default.
        integration_sigma: preintegration's integration noise (m/s^2/sqrt(Hz)); graphcal has none.
        foothold_init_sigma_m: a new foothold's standard deviation (m); the example's 0.5.
        contact_sigma_m: (x, y, z) contact standard deviations (m) overriding the one from the noise,
            or None.
        height_prior_sigma_m, terrain_height_m, height_prior_until_s: a prior on the stance feet's
            height (terrain_height_m, sigma) during the first ``height_prior_until_s`` s (0: never);
            the example keeps it on for 8 s at 0 m.
        robust_contact, huber_k: Huber contact noise (off in the example).
        full_contact_init: GTSAM's initialisation at the first full contact (on in the example);
            used only when the stance mask has a sample with every foot down.
        marginalize_leaving_foot: marginalize a foot that lifts off (on in the example).
        gravity_m_s2: |g|; graphcal's 9.80665 (the example: 9.81).
        sigma_init_rot_rad, sigma_init_pos_m, sigma_init_vel_m_s: initial standard deviations
            (roll/pitch and yaw; x/y and z; velocity), None for graphcal's TrackerConfig defaults.
        init_window_s: accelerometer window of the initial roll and pitch (s).
        level_start: start level (roll = pitch = 0, as the example) instead of from the accelerometer.
        initial_height_m: the initial IMU height (m; the example's 0.76), None: the body above the
            first stance feet (graphcal's).
        zero_footholds: start the footholds at the world origin (the example's, with its 0.5 m
            sigma) instead of where the first sample's foot points put them.
    """

    lag_s: float = 1.0
    contact_every: int = 5
    integration_sigma: float = 1e-4
    foothold_init_sigma_m: float = 0.5
    contact_sigma_m: tuple | None = None
    height_prior_sigma_m: float = 0.02
    terrain_height_m: float = 0.0
    height_prior_until_s: float = 0.0
    robust_contact: bool = False
    huber_k: float = 2.0
    full_contact_init: bool = True
    marginalize_leaving_foot: bool = True
    gravity_m_s2: float = float(-GRAVITY_WORLD[2])
    sigma_init_rot_rad: tuple = (0.0002, 1e-6)
    sigma_init_pos_m: tuple = (1e-6, 0.0002)
    sigma_init_vel_m_s: float = 0.05
    init_window_s: float = 0.1
    level_start: bool = False
    initial_height_m: float | None = None
    zero_footholds: bool = False

    @classmethod
    def example(cls) -> GtsamLeggedSettings:
        """GTSAM's example's settings for its Spot sample (LeggedEstimatorExample.py's parameters,
        initial state and covariance; its noise: :data:`EXAMPLE_NOISE`)."""
        v = math.sqrt(0.05)
        return cls(integration_sigma=1e-3, contact_sigma_m=(0.03, 0.03, 0.02), height_prior_until_s=8.0,
                   gravity_m_s2=9.81, sigma_init_rot_rad=(0.1, 1e-3), sigma_init_pos_m=(v, v), sigma_init_vel_m_s=v,
                   level_start=True, initial_height_m=0.76, zero_footholds=True)

    def __post_init__(self):
        if self.contact_every < 1 or self.lag_s <= 0:
            raise GraphcalError("GtsamLeggedSettings: contact_every >= 1 and lag_s > 0 required")


@dataclass(frozen=True, eq=False)
class GtsamLeggedResult:
    """One GTSAM estimator's run: ``times`` (N,) s, ``T_world_body`` (N, 4, 4) after each sample,
    ``T_world_imu`` (N, 4, 4) (the estimator's own state), ``cov_index`` (M,) and ``cov_pose``
    (M, 6, 6) in graphcal's order ``[dp world, dtheta body]`` (empty for the smoother),
    ``processing_s`` wall time, ``duration_s`` the data's span, ``n_contact_updates``."""

    variant: str
    times: np.ndarray
    T_world_body: np.ndarray
    T_world_imu: np.ndarray
    cov_index: np.ndarray
    cov_pose: np.ndarray
    processing_s: float
    duration_s: float
    n_contact_updates: int


def foot_points_from_joints(inputs) -> np.ndarray:
    """(n_feet, N, 3) body-frame foot points (m): ``inputs.p_body_foot``, else the forward
    kinematics of the joint angles (``robot.leg(f)``)."""
    from graphcal.models.kinematics import foot_positions

    if getattr(inputs, "p_body_foot", None) is not None:
        return np.asarray(inputs.p_body_foot, dtype=float)
    robot = inputs.robot
    out = []
    for f in robot.feet:
        leg = robot.leg(f)
        out.append(foot_positions(leg, np.column_stack([inputs.q[j] for j in leg.joint_names])))
    return np.stack(out)


def contact_covariance(inputs, noise: EkfNoise, stance_mask: np.ndarray) -> np.ndarray:
    """(3, 3) m^2: graphcal's foot measurement covariance (kinematic_sigma_m^2 I plus the encoder
    noise through the leg Jacobian, ``encoder_sigma^2 J J^T``) averaged over the stance samples of
    every foot -- GTSAM takes one constant contact covariance. Foot points without joints: the
    kinematic noise only."""
    from graphcal.models.kinematics import leg_jacobian

    C = np.eye(3) * noise.kinematic_sigma_m**2
    if getattr(inputs, "p_body_foot", None) is not None or not inputs.q:
        return C
    acc, n = np.zeros((3, 3)), 0
    for i, f in enumerate(inputs.robot.feet):
        leg = inputs.robot.leg(f)
        k = np.flatnonzero(stance_mask[:, i])[::10]
        if not len(k):
            continue
        J = leg_jacobian(leg, np.column_stack([np.asarray(inputs.q[j])[k] for j in leg.joint_names]))
        acc += (J @ np.swapaxes(J, 1, 2)).sum(axis=0)
        n += len(k)
    return C + (noise.encoder_sigma_rad**2 * acc / n if n else 0.0)


def legged_params(inputs, noise: EkfNoise, settings: GtsamLeggedSettings, stance_mask: np.ndarray):
    """``gtsam.LeggedEstimatorParams`` from graphcal's noise and the settings (module docstring)."""
    import gtsam

    from graphcal.geometry import to_gtsam_pose

    p = gtsam.LeggedEstimatorParams()
    p.preintegrationParams = gtsam.PreintegrationParams.MakeSharedU(settings.gravity_m_s2)
    p.preintegrationParams.setGyroscopeCovariance(np.eye(3) * noise.gyro_noise_density**2)
    p.preintegrationParams.setAccelerometerCovariance(np.eye(3) * noise.accel_noise_density**2)
    p.preintegrationParams.setIntegrationCovariance(np.eye(3) * settings.integration_sigma**2)
    p.body_P_imu = to_gtsam_pose(np.asarray(inputs.T_body_imu, dtype=float))
    p.footholdProcessSigma = noise.foot_rw
    p.footholdInitSigma = settings.foothold_init_sigma_m
    if settings.contact_sigma_m is not None:
        p.contactCovariance = np.diag(np.asarray(settings.contact_sigma_m, dtype=float) ** 2)
    else:
        p.contactCovariance = contact_covariance(inputs, noise, stance_mask) + np.eye(3) * 1e-12
    p.heightPriorSigma = settings.height_prior_sigma_m
    p.useRobustContactNoise = settings.robust_contact
    p.robustContactHuberK = settings.huber_k
    p.imuBias = gtsam.imuBias.ConstantBias()
    p.biasAccRandomWalkSigma = noise.accel_bias_rw
    p.biasOmegaRandomWalkSigma = noise.gyro_bias_rw
    # GTSAM waits for a sample with every foot down before it estimates anything (measured: a
    # hexapod's tripod mask never has one, and the estimate stays at its start): only when there is one
    p.useFullContactInitialization = settings.full_contact_init and bool(np.all(stance_mask, axis=1).any())
    p.marginalizeLeavingFoot = settings.marginalize_leaving_foot
    return p


def stance_mask_of(inputs) -> np.ndarray:
    """(N, n_feet) stance mask from ``inputs.contact`` (> 0.5); for loads or torques pass graphcal's
    own (``run_filter(...).stance_mask``) to :func:`run_gtsam_legged`."""
    if inputs.contact is None:
        raise GraphcalError("no contact columns: pass stance_mask= (e.g. run_filter(inputs).stance_mask)")
    return np.asarray(inputs.contact, dtype=float) > 0.5


def _initial_T_world_body(inputs, pbf: np.ndarray, stance0: np.ndarray, settings: GtsamLeggedSettings):
    """graphcal's initial pose: roll, pitch from the mean accelerometer of the first window, yaw 0,
    the stance feet at z = 0."""
    t = np.asarray(inputs.times, dtype=float)
    n0 = max(1, int(np.searchsorted(t, t[0] + settings.init_window_s)))
    a = np.asarray(inputs.T_body_imu, dtype=float)[:3, :3] @ np.asarray(inputs.accel[:n0], dtype=float).mean(axis=0)
    R0 = matrix_from_rpy([math.atan2(a[1], a[2]), math.atan2(-a[0], math.hypot(a[1], a[2])), 0.0])
    if settings.level_start:
        R0 = np.eye(3)
    feet = stance0 if stance0.any() else np.ones_like(stance0)
    T = np.eye(4)
    T[:3, :3] = R0
    T[2, 3] = -float((pbf[feet, 0] @ R0.T)[:, 2].mean())
    if settings.initial_height_m is not None:
        T[:3, 3] = [0.0, 0.0, settings.initial_height_m] - R0 @ np.asarray(inputs.T_body_imu, dtype=float)[:3, 3]
    return T


def _initial_covariance(n_feet: int, settings: GtsamLeggedSettings, full: bool) -> np.ndarray:
    """P0 in the estimators' order [dtheta, dp, dv, (dfeet)] (the feet: ``foothold_init_sigma_m``)."""
    from graphcal.locomotion.estimator import TrackerConfig

    cfg = TrackerConfig()
    rp, yaw = settings.sigma_init_rot_rad if settings.sigma_init_rot_rad else (cfg.sigma_init_roll_pitch_rad,
                                                                               cfg.sigma_init_yaw_rad)
    xy, z = settings.sigma_init_pos_m
    s = np.array([rp, rp, yaw, xy, xy, z] + [settings.sigma_init_vel_m_s] * 3)
    if full:
        s = np.r_[s, np.full(3 * n_feet, settings.foothold_init_sigma_m)]
    return np.diag(s**2)


def _make_estimator(variant: str, nav0, footholds0: np.ndarray, params, names, settings: GtsamLeggedSettings):
    import gtsam

    n = len(names)
    if variant == "fixed_lag":
        return gtsam.LeggedFixedLagSmoother(nav0, footholds0, _initial_covariance(n, settings, False), params,
                                            settings.lag_s, list(names))
    cls = {"invariant_ekf": gtsam.LeggedInvariantEKF, "invariant_iekf": gtsam.LeggedInvariantIEKF}.get(variant)
    if cls is None:
        raise GraphcalError(f"GTSAM legged variant: expected one of {', '.join(VARIANTS)}, got {variant!r}")
    return cls(nav0, footholds0, _initial_covariance(n, settings, True), params, list(names))


def _contact_samples(mask: np.ndarray, every: int) -> np.ndarray:
    """Samples where contacts are processed: every ``every``-th, every touchdown and lift-off."""
    N = len(mask)
    change = np.flatnonzero(np.any(mask[1:] != mask[:-1], axis=1)) + 1
    return np.union1d(np.arange(0, N, every), change).astype(np.int64)


def _measurements(pbf: np.ndarray, mask: np.ndarray, k: int, last: np.ndarray) -> list:
    import gtsam

    out = []
    for i in np.flatnonzero(mask[k]):
        m = gtsam.ContactMeasurement()
        m.foot = int(i)
        m.bodyPoint = np.asarray(pbf[i, k], dtype=float)
        m.touchdown = not bool(last[i])
        out.append(m)
    return out


def _pose_cov(P: np.ndarray, T_world_imu: np.ndarray, T_body_imu: np.ndarray) -> np.ndarray:
    """The IMU's left-invariant [dtheta, dp] covariance as the body pose's [dp world, dtheta body]."""
    Ad = pose_adjoint(T_body_imu)  # xi_body = Ad(T_body_imu) xi_imu ([omega, v])
    R_wb = T_world_imu[:3, :3] @ T_body_imu[:3, :3].T
    M = np.zeros((6, 6))
    M[:3, 3:] = R_wb  # dp_world = R_wb v_body
    M[3:, :3] = np.eye(3)
    A = M @ Ad
    return A @ P[:6, :6] @ A.T


def run_gtsam_legged(inputs, variant: str, *, noise: EkfNoise = EkfNoise(),
                     settings: GtsamLeggedSettings = GtsamLeggedSettings(), stance_mask: np.ndarray | None = None,
                     contact_samples: np.ndarray | None = None, record_cov_every: int = 10) -> GtsamLeggedResult:
    """Run GTSAM's ``variant`` (:data:`VARIANTS`) over ``inputs``: ``predict`` with each IMU
    sample held over the interval to the next (as the example), ``processContacts`` with the feet in
    stance at ``contact_samples`` (default: every ``settings.contact_every``-th sample and every
    stance change); the height prior on for the first ``settings.height_prior_until_s``. Returns the
    poses after every sample (:class:`GtsamLeggedResult`)."""
    import gtsam

    from graphcal.geometry import to_gtsam_pose

    pbf = foot_points_from_joints(inputs)
    mask = stance_mask_of(inputs) if stance_mask is None else np.asarray(stance_mask, dtype=bool)
    times = np.asarray(inputs.times, dtype=float)
    gyro, accel = np.asarray(inputs.gyro, dtype=float), np.asarray(inputs.accel, dtype=float)
    T_bi = np.asarray(inputs.T_body_imu, dtype=float)
    params = legged_params(inputs, noise, settings, mask)
    T_wb0 = _initial_T_world_body(inputs, pbf, mask[0], settings)
    T_wi0 = T_wb0 @ T_bi
    feet0 = np.zeros((3, len(inputs.robot.feet))) if settings.zero_footholds else T_wb0[:3, :3] @ pbf[:, 0].T + T_wb0[:3, 3:4]
    nav0 = gtsam.NavState(to_gtsam_pose(T_wi0).rotation(), T_wi0[:3, 3], np.zeros(3))
    t0 = time.perf_counter()
    est = _make_estimator(variant, nav0, feet0, params, inputs.robot.feet, settings)
    upd = np.zeros(len(times), dtype=bool)
    upd[_contact_samples(mask, settings.contact_every) if contact_samples is None else contact_samples] = True
    T_wi, cov_index, cov_pose, n_upd = _loop(est, times, gyro, accel, pbf, mask, upd, settings, record_cov_every,
                                             variant != "fixed_lag")
    elapsed = time.perf_counter() - t0
    cov_pose = np.array([_pose_cov(P, T_wi[k], T_bi) for k, P in zip(cov_index, cov_pose)]).reshape(-1, 6, 6)
    return GtsamLeggedResult(variant, times, T_wi @ np.linalg.inv(T_bi), T_wi, np.asarray(cov_index, dtype=np.int64),
                             cov_pose, elapsed, float(times[-1] - times[0]), n_upd)


def _loop(est, times, gyro, accel, pbf, mask, upd, settings: GtsamLeggedSettings, every: int, has_cov: bool):
    """predict / processContacts over the samples; (T_world_imu (N, 4, 4), cov sample indices, the
    estimator's covariances there, number of contact updates)."""
    N = len(times)
    T_wi = np.empty((N, 4, 4))
    last = np.zeros(mask.shape[1], dtype=bool)
    prior_on = None
    cov_index, covs, n_upd = [], [], 0
    for k in range(N):
        if k:
            est.predict(gyro[k - 1], accel[k - 1], float(times[k] - times[k - 1]))
        on = times[k] - times[0] <= settings.height_prior_until_s
        if on != prior_on:
            est.turnHeightPriorOn(settings.terrain_height_m) if on else est.turnHeightPriorOff()
            prior_on = on
        if upd[k] and (mask[k].any() or last.any()):
            est.processContacts(_measurements(pbf, mask, k, last))
            last = mask[k].copy()
            n_upd += 1
        T_wi[k] = _imu_pose(est.estimate())
        if has_cov and k % every == 0:
            cov_index.append(k)
            covs.append(np.asarray(est.covariance())[:6, :6])
    return T_wi, cov_index, covs, n_upd


def _imu_pose(x) -> np.ndarray:
    """T_world_imu (4, 4) of the estimators' ExtendedPose3d state (rotation, x(0) the position)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(x.rotation().matrix(), dtype=float)
    T[:3, 3] = np.asarray(x.x(0), dtype=float)
    return T
