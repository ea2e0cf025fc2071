"""Run the legged EKF over a timeseries: support detection, IMU propagation at every sample, stance
kinematics, and (second stage) ICP between keyframe clouds as relative-pose measurements.

``run_filter(inputs, config)`` is the loop over a :class:`~graphcal.locomotion.track_inputs.TrackInputs`
(built from a dataset or a simulated walk in track_inputs.py). ``estimate_trajectory(dataset)`` returns
``(times (N,), T_world_body (N, 4, 4))`` for other modules (the stairs model).

World frame of the estimate: z up (gravity), origin on the ground under the body at the first
sample (the feet of the first stance tripod define the ground, z = 0), x along the body's
initial heading (yaw = 0). Roll and pitch start from the mean accelerometer reading of the first
``init_window_s``; the initial velocity is 0 (uncertain), the biases 0 (uncertain).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.geometry import matrix_from_rpy, rotation_angle_between
from graphcal.locomotion.ekf import GRAVITY_WORLD as GRAVITY
from graphcal.locomotion.ekf import EkfNoise, LeggedEKF, NominalState, state_dim, tangent_pose_covariance
from graphcal.locomotion.track_inputs import TrackInputs, inputs_from_dataset

__all__ = ["TrackerConfig", "TrackResult", "run_filter", "estimate_trajectory", "still_samples", "lever_arm_corrected"]


@dataclass(frozen=True)
class TrackerConfig:
    """Filter settings (SI units).

    Attributes:
        noise: :class:`~graphcal.locomotion.ekf.EkfNoise`.
        stance_every: stance-kinematics update every k-th sample (1: every sample); the
            covariance is propagated once between updates, the nominal state at every sample.
        icp: fuse ICP between keyframe clouds (when the data have clouds).
        keyframe_distance_m, keyframe_angle_rad, keyframe_max_s: a new keyframe (and an ICP
            measurement against the previous one) once the body moved this far, turned this much,
            or this long after the last one.
        icp_max_correspondence_m: correspondence search radius (m).
        icp_neighbours: neighbours of a keyframe point's local plane.
        icp_degenerate_ratio: ICP directions whose Hessian eigenvalue (rotation scaled by 1 m) is
            below this fraction of the largest are neither solved nor fused.
        icp_min_fitness: an ICP result with a smaller inlier fraction is not fused.
        icp_gate_prob: an ICP measurement whose NIS exceeds this chi-square quantile is not fused.
        icp_max_points: clouds with more points are evenly thinned to this many for ICP.
        hysteresis_n: support detection hysteresis of the two-tripod gait (N).
        contact_thresholds: any other gait (a quadruped's): a foot enters stance when its load
            (foot-force sensor ``force_<foot>``, else from its leg's torques) exceeds its ``on``
            threshold and leaves it below its ``off`` one
            (:func:`graphcal.locomotion.support.stance_from_loads`). ``learned`` (default): both
            learned per foot from the foot's own signal, between its swing and stance modes
            (:mod:`graphcal.locomotion.contact_detection`; any unit: N or raw counts); a foot whose
            signal has no two modes (a log where it only stands) falls back to ``contact_on_n`` /
            ``contact_off_n``. ``fixed``: ``contact_on_n`` / ``contact_off_n`` for every foot (N).
            With contacts only (``contact_<foot>`` 0/1 or a probability) the threshold is 0.5.
        contact_on_n, contact_off_n: the fixed thresholds (N), off <= on.
        level_ground: the ground is declared level (dataset.yaml ``ground: {type: level}``): a foot
            touching down is measured at the height of the floor the robot started on (world z 0),
            within ``noise.floor_sigma_m``.
        phases: segment the log (:func:`graphcal.locomotion.phases.phases_of_inputs`) and use no
            leg model while the robot lies on its belly or is lifted; while it lies, a zero-velocity
            update (``lying_velocity_sigma_m_s``, m/s) instead.
        contact_min_stance_s, contact_min_swing_s: stances and swings shorter than these (s) are
            removed from the mask (a spurious touchdown, a dip of a loaded foot); 0.05 s, a third of
            the shortest stance of a fast trot (0.3 s cycle), above the < 40 ms spurious stances of
            real logs.
        init_window_s: accelerometer averaging window for the initial roll and pitch (s), when the
            data do not start still.
        still_start, still_min_s, still_joint_tol_rad: a still start -- the leading samples whose
            joint angles all stay within ``still_joint_tol_rad`` of their mean over the first 20
            samples, at least ``still_min_s`` long -- gives the initial roll and pitch (mean
            accelerometer over it) and the initial gyro bias (mean gyro over it, sigma
            ``noise.gyro_noise_density / sqrt(duration)``); ``still_start=False`` ignores it.
        sigma_init_*: initial standard deviations (position m; roll/pitch, yaw rad; velocity m/s;
            gyro bias rad/s; accel bias m/s^2). Position x, y and yaw define the world frame; the
            roll/pitch error also carries the accelerometer bias (correlated) and the white noise of
            the window's mean (``noise.accel_noise_density / sqrt(init_window_s) / g``), both added
            to ``sigma_init_roll_pitch_rad`` (the motion in the window) by ``_initial_covariance``.
            Defaults match the simulator's IMU (graphcal.simulation.walking).
        record_cov_every: keep the pose covariance every k-th sample.
    """

    noise: EkfNoise = field(default_factory=EkfNoise)
    stance_every: int = 5
    icp: bool = True
    keyframe_distance_m: float = 0.3
    keyframe_angle_rad: float = float(np.radians(10.0))
    keyframe_max_s: float = 2.0
    icp_max_correspondence_m: float = 0.1
    icp_neighbours: int = 15
    icp_degenerate_ratio: float = 1e-2
    icp_min_fitness: float = 0.3
    icp_gate_prob: float = 0.999
    icp_max_points: int = 1500
    hysteresis_n: float = 20.0
    contact_on_n: float = 20.0
    contact_off_n: float = 10.0
    contact_thresholds: str = "learned"
    contact_min_stance_s: float = 0.05
    contact_min_swing_s: float = 0.05
    level_ground: bool = False
    phases: bool = True
    lying_velocity_sigma_m_s: float = 0.01
    init_window_s: float = 0.1
    still_start: bool = True
    still_min_s: float = 0.3
    still_joint_tol_rad: float = 0.002
    sigma_init_xy_m: float = 1e-6
    sigma_init_z_m: float = 0.0002
    sigma_init_roll_pitch_rad: float = 0.0002
    sigma_init_yaw_rad: float = 1e-6
    sigma_init_velocity_m_s: float = 0.05
    sigma_init_gyro_bias: float = 0.001
    sigma_init_accel_bias: float = 0.02
    record_cov_every: int = 10

    def __post_init__(self):
        if self.stance_every < 1 or self.record_cov_every < 1:
            raise GraphcalError("stance_every and record_cov_every must be >= 1")
        if self.contact_thresholds not in ("learned", "fixed"):
            raise GraphcalError(f"contact_thresholds: expected learned or fixed, got {self.contact_thresholds!r}")
        if not self.contact_off_n <= self.contact_on_n:
            raise GraphcalError(f"contact_off_n ({self.contact_off_n}) must not exceed contact_on_n ({self.contact_on_n})")
        if not (self.contact_min_stance_s >= 0 and self.contact_min_swing_s >= 0):
            raise GraphcalError("contact_min_stance_s and contact_min_swing_s must be >= 0 (s)")
        if not self.lying_velocity_sigma_m_s > 0:
            raise GraphcalError("lying_velocity_sigma_m_s must be > 0 (m/s)")


@dataclass(frozen=True, eq=False)
class TrackResult:
    """The estimate and the filter's own diagnostics.

    Attributes:
        times: (N,) s. T_world_body: (N, 4, 4). v_world_body, gyro_bias, accel_bias: (N, 3).
        cov_index: (M,) sample indices of ``cov_pose``.
        cov_pose: (M, 6, 6) covariance of the filter's pose error at those samples, in the filter's
            order ``[dp, dtheta]``: ``dp = p_true - p_est`` in the world frame (m), then ``dtheta``
            with ``R_true = R_est Exp(dtheta)`` in the body frame (rad). This is NOT the
            ``[omega, v]`` right-perturbation order of docs/conventions.md (position first, and in
            the world frame); it matches :func:`graphcal.locomotion.metrics.pose_errors` (NEES) and
            the report's per-axis world position sigmas. :meth:`cov_pose_tangent` gives the
            ``[omega, v]`` form.
        stance_nis: (K,) NIS of the stance updates (dof ``stance_dofs``); stance_times (K,);
        stance_innovations: (K, stance_dof) innovations whitened by their covariance (Cholesky), in
            slot order, NaN for the slots an update did not measure (feet in swing).
        stance_dof: the largest stance dof (3 x the filter's foot slots); stance_dofs: (K,) the
            dof of each update (3 x the feet it measured).
        icp_nis, icp_dof, icp_times: NIS and number of fused directions of each ICP update.
        n_icp_rejected: ICP results not fused (too few inliers or failed).
        support_group: (N,) tripod in stance (index into ``groups``); for other gaits the stance
            mask as an integer (bit i: foot i of ``robot.feet``); groups (() for other gaits).
        stance_mask: (N, n_feet) bool, feet detected in stance (``robot.feet`` order).
        contacts: how the stance mask was decided (any gait but the two tripods; None there), plain
            values for metrics.json: ``signal`` (``force_<foot>``, ``loads from joint torques (N)``
            or ``contact_<foot>``), ``thresholds`` (``learned`` / ``fixed``), ``min_stance_s``,
            ``min_swing_s``, ``feet``: foot -> ``source``, ``on``, ``off``, ``low_mode``,
            ``high_mode`` (the signal's unit), ``separation``, ``duty_factor`` (share of the samples
            in stance), ``n_stances``, ``n_short_stances_removed``, ``n_short_swings_removed``
            (:meth:`graphcal.locomotion.contact_detection.FootContacts.as_dict`).
        floor_nis, floor_times, floor_dofs: the level-floor updates at touchdowns (NIS, s, feet);
            floor_y2, floor_s: per update the sum of the squared innovations (m^2) and of the
            innovation variances (m^2) -- covariance matching reads them.
        n_zero_velocity: zero-velocity updates (lying). phases: the
            :class:`~graphcal.locomotion.phases.PhaseResult`, or None.
        processing_s: wall time of the filter (support detection, kinematics and loop included).
        duration_s: span of the data (s).
    """

    times: np.ndarray
    T_world_body: np.ndarray
    v_world_body: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray
    cov_index: np.ndarray
    cov_pose: np.ndarray
    stance_nis: np.ndarray
    stance_times: np.ndarray
    stance_innovations: np.ndarray
    stance_dof: int
    icp_nis: np.ndarray
    icp_dof: np.ndarray
    icp_times: np.ndarray
    n_icp_rejected: int
    support_group: np.ndarray
    groups: tuple
    processing_s: float
    duration_s: float
    stance_dofs: np.ndarray | None = None
    stance_mask: np.ndarray | None = None
    contacts: dict | None = None
    floor_nis: np.ndarray = field(default_factory=lambda: np.zeros(0))
    floor_times: np.ndarray = field(default_factory=lambda: np.zeros(0))
    floor_dofs: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    floor_y2: np.ndarray = field(default_factory=lambda: np.zeros(0))
    floor_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    n_zero_velocity: int = 0
    phases: object = None

    def cov_pose_tangent(self) -> np.ndarray:
        """(M, 6, 6) ``cov_pose`` converted to docs/conventions.md's order: covariance of
        ``xi = [omega, v]`` with ``T_true = T_est Exp(xi)`` (body frame; rad, m), by
        :func:`graphcal.locomotion.ekf.tangent_pose_covariance` at the estimated orientations."""
        return tangent_pose_covariance(self.T_world_body[self.cov_index, :3, :3], self.cov_pose)

    @property
    def real_time_factor(self) -> float:
        """Data duration / processing time (> 1: faster than real time)."""
        return self.duration_s / self.processing_s if self.processing_s > 0 else float("inf")


def _init_window(times: np.ndarray, cfg: TrackerConfig) -> tuple[int, float]:
    """(number of samples, duration s) of the accelerometer window that gives the initial roll and
    pitch: the samples within ``init_window_s`` of the first; the duration is their number x the
    sample interval (what the white noise of their mean depends on)."""
    t = np.asarray(times, dtype=float)
    n0 = max(1, int(np.searchsorted(t, t[0] + cfg.init_window_s)))
    dt = float(np.median(np.diff(t[: max(n0 + 1, 2)]))) if len(t) > 1 else 0.0
    return n0, n0 * dt


def still_samples(inp: TrackInputs, cfg: TrackerConfig) -> int:
    """Number of leading samples of a still start (TrackerConfig's ``still_*``), 0 when there is
    none (the data start in motion, or it lasts less than ``still_min_s``)."""
    t = np.asarray(inp.times, dtype=float)
    if not cfg.still_start or len(t) < 40 or not inp.q:
        return 0
    n_max = int(np.searchsorted(t, t[0] + 30.0))  # a still start is looked for in the first 30 s
    Q = np.column_stack([np.asarray(v, dtype=float)[:n_max] for v in inp.q.values()])
    dev = np.abs(Q - Q[:20].mean(axis=0)).max(axis=1)
    moved = np.flatnonzero(dev > cfg.still_joint_tol_rad)
    n = int(moved[0]) if len(moved) else n_max
    return n if n > 1 and t[n - 1] - t[0] >= cfg.still_min_s else 0


def _initial_state(inp: TrackInputs, pbf: np.ndarray, feet_idx: list[int], cfg: TrackerConfig,
                   n_still: int = 0):
    """The initial state: roll and pitch from the mean accelerometer over the first
    ``init_window_s`` or the still start (``n_still`` samples; then the gyro bias is their mean
    gyro, IMU frame), yaw 0, the body above the stance feet ``feet_idx``."""
    n0, _ = _init_window(inp.times, cfg) if n_still == 0 else (n_still, 0.0)
    a = inp.T_body_imu[:3, :3] @ inp.accel[:n0].mean(axis=0)
    roll = math.atan2(a[1], a[2])
    pitch = math.atan2(-a[0], math.hypot(a[1], a[2]))
    R0 = matrix_from_rpy([roll, pitch, 0.0])
    feet_world = pbf[feet_idx, 0] @ R0.T
    z0 = -float(feet_world[:, 2].mean())
    bg = np.asarray(inp.gyro[:n_still], dtype=float).mean(axis=0) if n_still else np.zeros(3)
    return NominalState(np.array([0.0, 0.0, z0]), np.zeros(3), R0, bg, np.zeros(3))


def _initial_covariance(cfg: TrackerConfig, n_slots: int, R_body_imu: np.ndarray,
                        window_s: float | None = None, still_s: float = 0.0) -> np.ndarray:
    """P0. Roll and pitch come from the mean accelerometer reading over ``window_s`` (default
    ``cfg.init_window_s``), so their errors are the accelerometer bias seen as a tilt:
    dtheta_x = -b_y / g, dtheta_y = b_x / g (correlated with the bias), plus the white noise of
    that mean seen as a tilt, ``accel_noise_density / sqrt(window_s) / g`` per axis (0.48 mrad
    with the defaults), plus ``sigma_init_roll_pitch_rad`` for motion in the window."""
    D = state_dim(n_slots)
    g = 9.80665
    window = cfg.init_window_s if window_s is None else window_s
    s = np.ones(D) * 1e-3
    s[0:2] = cfg.sigma_init_xy_m
    s[2] = cfg.sigma_init_z_m
    s[3:6] = cfg.sigma_init_velocity_m_s
    tilt_noise_var = cfg.noise.accel_noise_density**2 / window / g**2 if window > 0 else 0.0
    s[6:8] = math.sqrt(cfg.sigma_init_roll_pitch_rad**2 + tilt_noise_var)
    s[8] = cfg.sigma_init_yaw_rad
    s[9:12] = cfg.sigma_init_gyro_bias
    if still_s > 0:  # the mean gyro over a still start: its white noise (and the bias's walk over it)
        s[9:12] = math.sqrt(cfg.noise.gyro_noise_density**2 / still_s + cfg.noise.gyro_bias_rw**2 * still_s)
    s[12:15] = 0.0
    P = np.diag(s**2)
    G = np.zeros((D, 3))  # how the accelerometer bias (IMU frame) enters the initial state error
    G[6:8, :] = np.array([[0.0, -1.0 / g, 0.0], [1.0 / g, 0.0, 0.0]]) @ R_body_imu
    G[12:15, :] = np.eye(3)
    return P + cfg.sigma_init_accel_bias**2 * (G @ G.T)


@dataclass(frozen=True, eq=False)
class _FootKinematics:
    """Forward kinematics of every foot at every sample: ``p_body_foot`` (n_feet, N, 3) m,
    ``cov`` (n_feet, N, 3, 3) m^2 the covariance of each measured foot position (encoders and
    model), ``jacobians`` foot -> (N, 3, n_joints) m/rad (body frame)."""

    p_body_foot: np.ndarray
    cov: np.ndarray
    jacobians: dict


def _foot_kinematics(inp: TrackInputs, feet: tuple, cfg: TrackerConfig, N: int) -> _FootKinematics:
    """Kinematics of every foot at every sample (vectorised, one pass per leg): positions,
    Jacobians, and the covariance of the measured foot positions. Inputs carrying body-frame foot
    points instead of joint angles (``inp.p_body_foot``: a robot given by its feet) give those
    points, the kinematic noise only and no encoder Jacobian (zero joints)."""
    from graphcal.models.kinematics import joint_frames, position_jacobian

    enc_var = cfg.noise.encoder_sigma_rad**2
    kin_cov = np.eye(3) * cfg.noise.kinematic_sigma_m**2
    if inp.p_body_foot is not None:
        pbf = np.asarray(inp.p_body_foot, dtype=float).reshape(len(feet), N, 3)
        cov = np.broadcast_to(kin_cov, (len(feet), N, 3, 3)).copy()
        return _FootKinematics(pbf, cov, {f: np.zeros((N, 3, 0)) for f in feet})
    pbf = np.empty((len(feet), N, 3))
    Rf = np.empty((len(feet), N, 3, 3))
    jac = {}
    for i, f in enumerate(feet):
        leg = inp.robot.leg(f)
        q = np.column_stack([inp.q[j] for j in leg.joint_names])
        axes, origins, _, p_foot = joint_frames(leg, q)
        J = position_jacobian(leg.joint_types, axes, origins, p_foot)
        pbf[i] = p_foot
        jac[f] = J
        Rf[i] = enc_var * (J @ np.swapaxes(J, 1, 2)) + kin_cov
    return _FootKinematics(pbf, Rf, jac)


def _support_group(inp: TrackInputs, feet: tuple, groups: tuple, jacobians: dict, cfg: TrackerConfig) -> np.ndarray:
    """(N,) index into ``groups`` of the tripod in stance at each sample: from the joint torques
    when there are any, else from the contacts (ties, all feet down, keep the previous tripod)."""
    from graphcal.locomotion.support import support_from_torques

    if inp.tau is not None:
        sup = support_from_torques(inp.robot, inp.q, inp.tau, groups, hysteresis_n=cfg.hysteresis_n,
                                   jacobians=jacobians)
        return sup.group
    cont = np.asarray(inp.contact, dtype=bool)
    load = np.stack([cont[:, [feet.index(f) for f in g]].sum(axis=1) for g in groups], axis=1).astype(float)
    group = np.where(load[:, 1] > load[:, 0], 1, 0)
    for k in range(1, len(group)):  # ties (all feet down) keep the previous tripod
        if load[k, 1] == load[k, 0]:
            group[k] = group[k - 1]
    return group


@dataclass(frozen=True, eq=False)
class _Support:
    """The feet in stance as the filter's slots see them, per sample: ``slot_feet`` (N, n_slots)
    the foot (index into robot.feet) in each slot, ``slot_stance`` (N, n_slots) whether it is in
    stance; ``touchdown`` (N, n_slots) a new foot in the slot at that sample (reset, no update);
    ``mask`` (N, n_feet) feet in stance; ``code`` (N,) the tripod index (two-tripod gait) or the
    mask as an integer (bit i: foot i); ``contacts`` how the mask was decided (TrackResult.contacts);
    ``at_rest`` (N,) samples of a zero-velocity update (lying), or None."""

    slot_feet: np.ndarray
    slot_stance: np.ndarray
    touchdown: np.ndarray
    mask: np.ndarray
    code: np.ndarray
    contacts: dict | None = None
    at_rest: np.ndarray | None = None

    @property
    def n_slots(self) -> int:
        return self.slot_feet.shape[1]


def _posture_moving(times: np.ndarray, p_body_foot: np.ndarray, *, rate_m_s: float = 0.02,
                    window_s: float = 0.1) -> np.ndarray:
    """(N,) bool: the legs raise or lower the body (the mean foot height in the body frame,
    ``p_body_foot`` (n_feet, N, 3) m, averaged over ``window_s``, changes faster than ``rate_m_s``)."""
    h = -np.asarray(p_body_foot, dtype=float)[:, :, 2].mean(axis=0)
    if len(h) < 3:
        return np.zeros(len(h), dtype=bool)
    n = max(1, int(round(window_s / float(np.median(np.diff(times))))))
    hs = np.convolve(h, np.ones(n) / n, mode="same")
    return np.abs(np.gradient(hs, times)) > rate_m_s


def _support(inp: TrackInputs, feet: tuple, groups: tuple, jacobians: dict, cfg: TrackerConfig,
             phases=None, moving=None) -> _Support:
    """The support model. Two tripods (``groups``, no foot-force sensors): one slot per foot of a
    tripod, all of them reset when the other tripod takes over (:func:`_support_group`). Any other
    gait: one slot per foot, stance from each foot's load (force sensors, else torques; per-foot
    hysteresis and minimum durations, :func:`_stance_mask`) or its contact column; a foot touching
    down is reset. With ``phases`` (a PhaseResult), no foot is in stance where its
    ``leg_model_mask`` is False unless the legs are raising or lowering the body (``moving`` (N,):
    the segmentation's edges lag the motion), and its lying samples are at rest where they do not."""
    N = len(inp.times)
    contacts = None
    if groups and inp.force is None:
        group = _support_group(inp, feet, groups, jacobians, cfg)
        group_idx = np.array([[feet.index(f) for f in g] for g in groups])
        slot_feet = group_idx[group]
        slot_stance = np.ones(slot_feet.shape, dtype=bool)
        mask = np.zeros((N, len(feet)), dtype=bool)
        np.put_along_axis(mask, slot_feet, True, axis=1)
        code = np.asarray(group)
    else:
        mask, contacts = _stance_mask(inp, feet, jacobians, cfg)
        slot_feet = np.broadcast_to(np.arange(len(feet)), mask.shape)
        slot_stance = mask
        code = (mask.astype(np.int64) << np.arange(len(feet))).sum(axis=1)
    at_rest = None
    if phases is not None:
        from graphcal.locomotion.phases import PHASES

        moving = np.zeros(N, dtype=bool) if moving is None else np.asarray(moving, dtype=bool)
        use = np.asarray(phases.leg_model_mask, dtype=bool) | moving
        mask = mask & use[:, None]
        slot_stance = slot_stance & use[:, None]
        at_rest = (np.asarray(phases.labels) == PHASES.index("lying")) & ~moving
    touchdown = np.zeros(slot_stance.shape, dtype=bool)
    touchdown[1:] = slot_stance[1:] & (~slot_stance[:-1] | (slot_feet[1:] != slot_feet[:-1]))
    return _Support(slot_feet, slot_stance, touchdown, mask, code, contacts, at_rest)


def _stance_mask(inp: TrackInputs, feet: tuple, jacobians: dict, cfg: TrackerConfig) -> tuple[np.ndarray, dict]:
    """(N, n_feet) stance mask and how it was decided (TrackResult.contacts): from the foot-force
    signals, else the loads from the joint torques (N), else the contact columns (threshold 0.5);
    thresholds learned per foot or fixed (``cfg.contact_thresholds``), then the minimum durations."""
    from graphcal.locomotion.contact_detection import detect_contacts
    from graphcal.locomotion.support import foot_loads

    fixed = (cfg.contact_on_n, cfg.contact_off_n)
    mode = cfg.contact_thresholds
    if inp.force is not None:
        signal, what = np.asarray(inp.force, dtype=float), "force_<foot>"
    elif inp.tau is not None:
        signal, what = foot_loads(inp.robot, inp.q, inp.tau, feet, jacobians=jacobians), "loads from joint torques (N)"
    else:
        signal, what, mode, fixed = np.asarray(inp.contact, dtype=float), "contact_<foot>", "fixed", (0.5, 0.5)
    det = detect_contacts(signal, inp.times, feet, thresholds=mode, fixed=fixed, fallback=fixed,
                          min_stance_s=cfg.contact_min_stance_s, min_swing_s=cfg.contact_min_swing_s)
    info = {"signal": what, "thresholds": mode, "min_stance_s": det.min_stance_s, "min_swing_s": det.min_swing_s,
            "feet": det.summary()}
    return det.mask, info


def _stance_measurement(kin: _FootKinematics, feet_idx: list[int], k: int) -> tuple[np.ndarray, np.ndarray]:
    """(p_body_foot (n_slots, 3) m, block-diagonal covariance (3 n_slots, 3 n_slots) m^2) of the
    feet ``feet_idx`` at sample k."""
    n_slots = len(feet_idx)
    Rm = np.zeros((3 * n_slots, 3 * n_slots))
    for s, i in enumerate(feet_idx):
        Rm[3 * s : 3 * s + 3, 3 * s : 3 * s + 3] = kin.cov[i, k]
    return kin.p_body_foot[feet_idx, k], Rm


@dataclass(frozen=True, eq=False)
class _IcpSetup:
    """The ICP stage: ``use`` (clouds, a sensor pose and ``cfg.icp``), ``T_body_sensor`` (4, 4)
    and its inverse, ``Ad_inv`` (6, 6) the inverse adjoint of T_body_sensor ([omega, v]) and the
    sensor's range-noise function (None when unused)."""

    use: bool
    T_body_sensor: np.ndarray
    T_sensor_body: np.ndarray
    Ad_inv: np.ndarray | None
    sigma_fn: object


def _icp_setup(inp: TrackInputs, cfg: TrackerConfig) -> _IcpSetup:
    use_icp = cfg.icp and bool(inp.clouds) and inp.T_body_sensor is not None
    T_bs = inp.T_body_sensor if inp.T_body_sensor is not None else np.eye(4)
    T_sb = np.linalg.inv(T_bs)
    Ad_inv = None
    sigma_fn = None
    if use_icp:
        from graphcal.clouds.icp import range_sigma_function
        from graphcal.geometry import pose_adjoint as adjoint

        Ad_bs = adjoint(T_bs)
        Ad_inv = np.linalg.inv(Ad_bs)
        sigma_fn = range_sigma_function(inp.sensor_type)
    return _IcpSetup(use_icp, T_bs, T_sb, Ad_inv, sigma_fn)


def _events(N: int, every: int, sup: _Support, cloud_samples: np.ndarray,
            measured: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(events, switches): the samples that end an IMU chunk (every ``every``-th sample, support
    changes, clouds and the last sample; increasing, > 0) and the support changes (a foot touching
    down or lifting off; the tripods' switches)."""
    changed = np.any(np.diff(sup.slot_feet, axis=0) != 0, axis=1) | np.any(np.diff(sup.slot_stance, axis=0), axis=1)
    switches = np.flatnonzero(changed) + 1
    updates = np.arange(every, N, every) if measured is None else np.flatnonzero(measured)
    events = np.union1d(np.union1d(updates, switches), cloud_samples)
    events = np.union1d(events[(events > 0) & (events < N)], [N - 1]).astype(np.int64)
    return events, switches


def lever_arm_corrected(times: np.ndarray, w_body: np.ndarray, f_body: np.ndarray, p_body_imu: np.ndarray, *,
                        window_s: float = 0.02) -> np.ndarray:
    """The specific force at the body origin (N, 3) m/s^2, body frame, from the IMU's ``f_body`` (N, 3)
    (rotated into the body frame) at ``p_body_imu`` (3,) m: less ``alpha x r + w x (w x r)``, with
    ``w_body`` (N, 3) rad/s and the angular acceleration alpha the difference of the mean rates over
    ``window_s`` after and before each sample (the gyro's noise differentiated otherwise)."""
    r = np.asarray(p_body_imu, dtype=float)
    if not np.any(r) or len(times) < 3:
        return f_body
    dt = float(np.median(np.diff(times)))
    n = max(1, int(round(window_s / dt)))
    c = np.vstack([np.zeros((1, 3)), np.cumsum(w_body, axis=0)])
    N = len(times)
    k = np.arange(N)
    hi = np.minimum(k + n, N - 1)
    lo = np.maximum(k - n, 0)
    after = (c[hi + 1] - c[k + 1]) / np.maximum(hi - k, 1)[:, None]
    before = (c[k] - c[lo]) / np.maximum(k - lo, 1)[:, None]
    span = 0.5 * ((hi - k) + (k - lo) + 2) * dt
    alpha = (after - before) / span[:, None]
    alpha[(hi == k) | (lo == k)] = 0.0
    return f_body - np.cross(alpha, r) - np.cross(w_body, np.cross(w_body, r))


def _preintegrated_imu(inp: TrackInputs, times: np.ndarray, events: np.ndarray):
    """IMU: body-frame rates and specific forces (at the body origin: :func:`lever_arm_corrected`) held
    over each interval (mean of its two ends), preintegrated between ``events`` (vectorised; see graphcal.locomotion.imu)."""
    from graphcal.locomotion.imu import preintegrate

    R_bi = np.asarray(inp.T_body_imu, dtype=float)[:3, :3]
    gyro = np.asarray(inp.gyro, dtype=float) @ R_bi.T
    accel = lever_arm_corrected(times, gyro, np.asarray(inp.accel, dtype=float) @ R_bi.T,
                                np.asarray(inp.T_body_imu, dtype=float)[:3, 3])
    w_mid = np.empty_like(gyro)
    a_mid = np.empty_like(accel)
    w_mid[0], a_mid[0] = gyro[0], accel[0]
    w_mid[1:] = 0.5 * (gyro[1:] + gyro[:-1])
    a_mid[1:] = 0.5 * (accel[1:] + accel[:-1])
    dts = np.diff(times, prepend=times[0])
    return preintegrate(w_mid, a_mid, dts, events)


@dataclass(frozen=True, eq=False)
class _EventInputs:
    """Per event (n_ev of them): the chunk's preintegration stacked as the filter takes it
    (``dR`` (n_ev, 3, 3), ``dpv`` (n_ev, 6) m and m/s, ``J`` (n_ev, 6, 6), ``T`` (n_ev,) s), the
    foot of each slot ``feet`` (n_ev, n_slots) (index into robot.feet), its measured position ``z``
    (n_ev, n_slots, 3) m (body frame) and their block-diagonal covariance ``R`` (n_ev, 3 n_slots,
    3 n_slots) m^2; ``stance`` and ``touchdown`` (n_ev, n_slots) bool per slot (:class:`_Support`)."""

    dR: np.ndarray
    dpv: np.ndarray
    J: np.ndarray
    T: np.ndarray
    feet: np.ndarray
    z: np.ndarray
    R: np.ndarray
    stance: np.ndarray
    touchdown: np.ndarray
    at_rest: np.ndarray


def _event_inputs(pre, events: np.ndarray, sup: _Support, kin: _FootKinematics, n_slots: int) -> _EventInputs:
    ev_dR = pre.dR[events]
    ev_dpv = np.concatenate([pre.dp[events], pre.dv[events]], axis=1)
    ev_J = np.concatenate([np.concatenate([pre.Jpg[events], pre.Jpa[events]], axis=2),
                           np.concatenate([pre.Jvg[events], pre.Jva[events]], axis=2)], axis=1)
    ev_T = pre.tau[events]
    # the slots' measured feet and their block-diagonal covariance (vectorised)
    ev_feet = sup.slot_feet[events]  # (n_ev, n_slots) foot indices
    ev_z = kin.p_body_foot[ev_feet, events[:, None]]  # (n_ev, n_slots, 3)
    ev_R = np.zeros((len(events), 3 * n_slots, 3 * n_slots))
    for s_ in range(n_slots):
        ev_R[:, 3 * s_ : 3 * s_ + 3, 3 * s_ : 3 * s_ + 3] = kin.cov[ev_feet[:, s_], events]
    at_rest = sup.at_rest[events] if sup.at_rest is not None else np.zeros(len(events), dtype=bool)
    return _EventInputs(ev_dR, ev_dpv, ev_J, ev_T, ev_feet, ev_z, ev_R, sup.slot_stance[events],
                        sup.touchdown[events], at_rest)


def _fuse_icp(ekf: LeggedEKF, pts: np.ndarray, kf_cloud, icp: _IcpSetup, cfg: TrackerConfig) -> tuple[float, int] | None:
    """ICP of the cloud ``pts`` (M, 3) (sensor frame, m) against the keyframe's and its fusion as a
    relative-pose update: (NIS, fused directions), or None when not fused (ICP failed, too few
    inliers, or gated out)."""
    from scipy.stats import chi2

    from graphcal.clouds.icp import icp_relative_pose

    T_bs, T_sb = icp.T_body_sensor, icp.T_sensor_body
    T_pred = T_sb @ ekf.predicted_relative_pose() @ T_bs  # T_kfcam_cam
    try:
        res = icp_relative_pose(pts, kf_cloud, T_pred, icp.sigma_fn,
                                max_correspondence_m=cfg.icp_max_correspondence_m,
                                degenerate_ratio=cfg.icp_degenerate_ratio)
    except GraphcalError:
        res = None
    if res is None or res.fitness < cfg.icp_min_fitness:
        return None
    T_meas = T_bs @ res.T_target_source @ T_sb
    A_body = res.A @ icp.Ad_inv  # z = A xi_cam, xi_cam = Ad(T_bs)^-1 xi_body
    dof = A_body.shape[0]
    nis, fused = ekf.update_relative_pose(T_meas, A_body, res.cov * cfg.noise.icp_cov_scale,
                                          gate_chi2=float(chi2.ppf(cfg.icp_gate_prob, dof)))
    return (nis, dof) if fused else None


def _needs_keyframe(ekf: LeggedEKF, t_k: float, kf_time: float, cfg: TrackerConfig) -> bool:
    """Whether the body moved (distance, angle or time) enough since the keyframe clone."""
    return ekf.has_clone and (
        np.linalg.norm(ekf.p - ekf.p_c) >= cfg.keyframe_distance_m
        or rotation_angle_between(ekf.R_c, ekf.R) >= cfg.keyframe_angle_rad
        or t_k - kf_time >= cfg.keyframe_max_s
    )


@dataclass(frozen=True, eq=False)
class _LoopOutput:
    """What the event loop leaves: the filter state after each event (row 0: the initial state;
    p, v (n_ev + 1, 3), R (n_ev + 1, 3, 3), body-frame biases bg, ba (n_ev + 1, 3)); the stance
    updates' innovations (K, 3 n_slots; NaN in the slots not measured), their covariances, NIS,
    dof and times; the ICP updates' NIS,
    dof and times and the number not fused; the sample indices and (6, 6) pose covariances kept;
    the level-floor updates ``floors`` (K, 5): time s, NIS, dof, sum of y^2 and of S_ii (m^2); the
    number of zero-velocity updates."""

    S_p: np.ndarray
    S_v: np.ndarray
    S_R: np.ndarray
    S_bg: np.ndarray
    S_ba: np.ndarray
    st_y: np.ndarray
    st_S: np.ndarray
    st_nis: np.ndarray
    st_t: np.ndarray
    st_dof: np.ndarray
    icp_nis: list
    icp_dof: list
    icp_times: list
    n_rejected: int
    cov_index: list
    cov_pose: list
    floors: np.ndarray
    n_zupt: int


def _floor_step(ekf: LeggedEKF, slots, cfg: TrackerConfig):
    """The level-floor update of the feet just reset in ``slots``: (NIS, dof, sum y^2, sum S_ii)."""
    var = cfg.noise.floor_sigma_m**2
    nis = ekf.update_floor(slots, 0.0, var)
    return nis, len(slots), float(ekf.last_innovation @ ekf.last_innovation), float(np.trace(ekf.last_S))


def _stance_step(ekf: LeggedEKF, ev: _EventInputs, e: int, names: tuple, update: bool, cfg: TrackerConfig):
    """At event ``e``: the feet touching down are reset (all slots at once at a tripod switch) and,
    on level ground, measured at the floor's height; with ``update``, the other feet in stance are
    measured. Returns (the stance update's (NIS, measured slots) or None, the floor update's
    :func:`_floor_step` or None)."""
    touch = ev.touchdown[e]
    floor = None
    if touch.all():  # a tripod switch (or every foot landing at once)
        ekf.reset_feet(tuple(names[i] for i in ev.feet[e]), ev.z[e], ev.R[e])
        if cfg.level_ground:
            floor = _floor_step(ekf, np.arange(len(touch)), cfg)
        return None, floor
    if touch.any():
        idx = np.flatnonzero(touch)
        rows = (3 * idx[:, None] + np.arange(3)[None]).ravel()
        ekf.reset_slots(idx, ev.z[e][idx], ev.R[e][np.ix_(rows, rows)])
        if cfg.level_ground:
            floor = _floor_step(ekf, idx, cfg)
    meas = ev.stance[e] & ~touch
    if not update or not meas.any():
        return None, floor
    if meas.all():
        return (ekf.update_stance(ev.z[e], ev.R[e]), meas), floor
    idx = np.flatnonzero(meas)
    rows = (3 * idx[:, None] + np.arange(3)[None]).ravel()
    return (ekf.update_stance(ev.z[e][idx], ev.R[e][np.ix_(rows, rows)], slots=idx), meas), floor


def _run_events(ekf: LeggedEKF, inp: TrackInputs, times: np.ndarray, events: np.ndarray, switches: np.ndarray,
                cloud_samples: np.ndarray, ev: _EventInputs, icp: _IcpSetup, cfg: TrackerConfig, *,
                progress: bool) -> _LoopOutput:
    """The filter over the events (sample indices): propagate over each chunk, then take the feet
    touching down (a tripod switch: all of them) and update with the others in stance (every
    ``stance_every``-th sample), and at a cloud sample (``cloud_samples``) a keyframe and an ICP
    update."""
    if icp.use:
        from graphcal.clouds.icp import prepare_target

    N = len(times)
    n_slots = ekf.n_slots
    pose_idx = np.r_[0:3, 6:9]
    st_dof = 3 * n_slots
    every = cfg.stance_every
    names = tuple(inp.robot.feet)
    is_cloud = np.zeros(N, dtype=bool)
    is_cloud[cloud_samples] = True
    max_st = len(events)
    st_y = np.empty((max_st, st_dof))
    st_S = np.empty((max_st, st_dof, st_dof))
    st_nis = np.empty(max_st)
    st_t = np.empty(max_st)
    st_k = np.empty(max_st, dtype=np.int64)
    n_st = 0
    cov_index: list[int] = [0]
    cov_pose: list[np.ndarray] = [ekf.P[np.ix_(pose_idx, pose_idx)].copy()]
    kf_cloud = None
    kf_time = -np.inf
    icp_nis, icp_dof, icp_times = [], [], []
    n_rejected = 0
    floors: list[tuple] = []
    n_zupt = 0
    # chunk-start states (for the per-sample reconstruction afterwards)
    n_ev = len(events)
    S_p = np.empty((n_ev + 1, 3))
    S_v = np.empty((n_ev + 1, 3))
    S_R = np.empty((n_ev + 1, 3, 3))
    S_bg = np.empty((n_ev + 1, 3))
    S_ba = np.empty((n_ev + 1, 3))
    S_p[0], S_v[0], S_R[0] = ekf.p, ekf.v, ekf.R
    S_bg[0], S_ba[0] = ekf.body_biases()
    it = range(n_ev)
    if progress:
        from graphcal.progress import ProgressBar

        it = ProgressBar(it, desc="track: EKF", unit="update", mininterval=0.5)
    next_cov = cfg.record_cov_every
    pose_r, pose_c = np.meshgrid(pose_idx, pose_idx, indexing="ij")
    for e in it:
        k = int(events[e])
        ekf.propagate(ev.dR[e], ev.dpv[e], ev.J[e], ev.T[e])
        due = k % every == 0 if inp.p_body_measured is None else bool(inp.p_body_measured[k])
        upd, floor = _stance_step(ekf, ev, e, names, due, cfg)
        if floor is not None:
            floors.append((times[k], *floor))
        if ev.at_rest[e] and due:
            ekf.update_zero_velocity(cfg.lying_velocity_sigma_m_s**2)
            n_zupt += 1
        if upd is not None:
            st_nis[n_st] = upd[0]
            st_t[n_st] = times[k]
            st_k[n_st] = 3 * int(upd[1].sum())
            if st_k[n_st] == st_dof:
                st_y[n_st] = ekf.last_innovation
                st_S[n_st] = ekf.last_S
            else:  # some slots not measured: NaN innovations there, identity covariance
                rows = np.flatnonzero(np.repeat(upd[1], 3))
                st_y[n_st] = np.nan
                st_y[n_st, rows] = ekf.last_innovation
                st_S[n_st] = np.eye(st_dof)
                st_S[n_st][np.ix_(rows, rows)] = ekf.last_S
            n_st += 1
        if is_cloud[k]:
            moved = _needs_keyframe(ekf, times[k], kf_time, cfg)
            if not ekf.has_clone or moved:
                pts = np.asarray(inp.clouds[k](), dtype=float)
                if len(pts) > cfg.icp_max_points:  # evenly thinned (deterministic): ICP cost bounded
                    pts = pts[np.linspace(0, len(pts) - 1, cfg.icp_max_points).astype(np.int64)]
                if moved and kf_cloud is not None and len(pts) >= 10:
                    fused = _fuse_icp(ekf, pts, kf_cloud, icp, cfg)
                    if fused is None:
                        n_rejected += 1
                    else:
                        icp_nis.append(fused[0])
                        icp_dof.append(fused[1])
                        icp_times.append(times[k])
                if len(pts) >= 10:
                    try:
                        kf_cloud = prepare_target(pts, icp.sigma_fn, k=cfg.icp_neighbours)
                        ekf.clone_pose()
                        kf_time = times[k]
                    except GraphcalError:
                        pass
        if e % 200 == 199:
            ekf.renormalize()
        if k >= next_cov:
            cov_index.append(k)
            cov_pose.append(ekf.P[pose_r, pose_c])
            next_cov = k + cfg.record_cov_every
        S_p[e + 1], S_v[e + 1], S_R[e + 1] = ekf.p, ekf.v, ekf.R
        S_bg[e + 1], S_ba[e + 1] = ekf.body_biases()
    return _LoopOutput(S_p, S_v, S_R, S_bg, S_ba, st_y[:n_st], st_S[:n_st], st_nis[:n_st], st_t[:n_st],
                       st_k[:n_st], icp_nis, icp_dof, icp_times, n_rejected, cov_index, cov_pose,
                       np.asarray(floors, dtype=float).reshape(-1, 5), n_zupt)


def _states_at_samples(pre, events: np.ndarray, out: _LoopOutput, R_bi: np.ndarray, N: int):
    """The state at every sample: chunk-start state + bias-corrected partial preintegration; event
    samples get their post-update state. Returns p, v (N, 3), R (N, 3, 3) and the IMU-frame biases
    bg, ba (N, 3)."""
    from graphcal.locomotion.imu import reconstruct

    S_p, S_v, S_R, S_bg, S_ba = out.S_p, out.S_v, out.S_R, out.S_bg, out.S_ba
    P_out = np.empty((N, 3))
    R_out = np.empty((N, 3, 3))
    V_out = np.empty((N, 3))
    BG_out = np.empty((N, 3))
    BA_out = np.empty((N, 3))
    chunk = np.searchsorted(events, np.arange(N), side="left")  # sample k in chunk (events[c-1], events[c]]
    row = np.where(np.arange(N) == 0, 0, chunk)  # index into the kept states (0 = the initial state)
    p_all, v_all, R_all = reconstruct(pre, S_p[row], S_v[row], S_R[row], S_bg[row], S_ba[row], GRAVITY)
    P_out[:], V_out[:], R_out[:] = p_all, v_all, R_all
    BG_out[:] = np.asarray(S_bg[row]) @ R_bi  # back to the IMU frame
    BA_out[:] = np.asarray(S_ba[row]) @ R_bi
    P_out[0], V_out[0], R_out[0] = S_p[0], S_v[0], S_R[0]
    P_out[events], V_out[events], R_out[events] = S_p[1:], S_v[1:], S_R[1:]
    BG_out[events], BA_out[events] = S_bg[1:] @ R_bi, S_ba[1:] @ R_bi
    return P_out, V_out, R_out, BG_out, BA_out


def _whitened_innovations(st_y: np.ndarray, st_S: np.ndarray) -> np.ndarray:
    """Innovations (K, m) whitened by their covariances (K, m, m) (Cholesky, batched); NaN when one
    is not positive definite."""
    n_st, st_dof = st_y.shape
    st_w = np.full((n_st, st_dof), np.nan)
    if n_st:
        missing = np.isnan(st_y)
        try:
            L = np.linalg.cholesky(st_S)
            st_w = np.linalg.solve(L, np.where(missing, 0.0, st_y)[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:  # pragma: no cover
            pass
        st_w[missing] = np.nan
    return st_w


def _phases(inp: TrackInputs, cfg: TrackerConfig):
    """The log's phases (:func:`graphcal.locomotion.phases.phases_of_inputs`) when ``cfg.phases``
    and the log shows them (None when its loads cannot be segmented)."""
    if not cfg.phases:
        return None
    from graphcal.locomotion.phases import phases_of_inputs

    try:
        return phases_of_inputs(inp)
    except GraphcalError:
        return None


def run_filter(inp: TrackInputs, config: TrackerConfig = TrackerConfig(), *, progress: bool = False) -> TrackResult:
    """Run the EKF over ``inp`` (see the module docstring); returns the estimate at every sample."""
    # imports first: the processing time measures the filter, not module loading
    import filterpy.kalman  # noqa: F401

    from graphcal.locomotion import imu, support  # noqa: F401
    from graphcal.models import kinematics  # noqa: F401
    if config.icp and inp.clouds:
        import open3d  # noqa: F401
        import scipy.stats  # noqa: F401

        from graphcal.clouds import icp  # noqa: F401
    t_start = time.perf_counter()
    cfg = config
    robot = inp.robot
    times = np.asarray(inp.times, dtype=float)
    N = len(times)
    feet = tuple(robot.feet)
    groups = tuple(tuple(g) for g in inp.groups)

    kin = _foot_kinematics(inp, feet, cfg, N)
    phases = _phases(inp, cfg)
    moving = _posture_moving(times, kin.p_body_foot) if phases is not None else None
    sup = _support(inp, feet, groups, kin.jacobians, cfg, phases, moving)
    n_slots = sup.n_slots
    n_joints = robot.leg(feet[0]).n_joints

    first = sup.slot_feet[0][sup.slot_stance[0]] if sup.slot_stance[0].any() else sup.slot_feet[0]
    n_still = still_samples(inp, cfg)
    x0 = _initial_state(inp, kin.p_body_foot, list(first), cfg, n_still)
    still_s = float(times[n_still - 1] - times[0]) if n_still else 0.0
    window_s = _init_window(times, cfg)[1] if not n_still else n_still * float(np.median(np.diff(times[:n_still])))
    P0 = _initial_covariance(cfg, n_slots, np.asarray(inp.T_body_imu, dtype=float)[:3, :3], window_s, still_s)
    ekf = LeggedEKF(x0, P0, cfg.noise.process_density(n_slots), np.eye(max(n_joints, 1)) * cfg.noise.encoder_sigma_rad**2,
                    np.eye(3) * cfg.noise.kinematic_sigma_m**2, n_slots=n_slots, T_body_imu=inp.T_body_imu)
    z, Rm = _stance_measurement(kin, list(sup.slot_feet[0]), 0)
    ekf.reset_feet(tuple(feet[i] for i in sup.slot_feet[0]), z, Rm)

    icp = _icp_setup(inp, cfg)
    cloud_samples = np.array(sorted(inp.clouds), dtype=np.int64) if icp.use else np.zeros(0, dtype=np.int64)
    events, switches = _events(N, cfg.stance_every, sup, cloud_samples, inp.p_body_measured)
    pre = _preintegrated_imu(inp, times, events)
    ev = _event_inputs(pre, events, sup, kin, n_slots)
    out = _run_events(ekf, inp, times, events, switches, cloud_samples, ev, icp, cfg, progress=progress)

    R_bi = np.asarray(inp.T_body_imu, dtype=float)[:3, :3]
    P_out, V_out, R_out, BG_out, BA_out = _states_at_samples(pre, events, out, R_bi, N)
    st_w = _whitened_innovations(out.st_y, out.st_S)
    T = np.zeros((N, 4, 4))
    T[:, :3, :3] = R_out
    T[:, :3, 3] = P_out
    T[:, 3, 3] = 1.0
    elapsed = time.perf_counter() - t_start
    return TrackResult(
        times=times, T_world_body=T, v_world_body=V_out, gyro_bias=BG_out, accel_bias=BA_out,
        cov_index=np.asarray(out.cov_index, dtype=np.int64), cov_pose=np.asarray(out.cov_pose),
        stance_nis=out.st_nis, stance_times=out.st_t, stance_innovations=st_w, stance_dof=3 * n_slots,
        icp_nis=np.asarray(out.icp_nis),
        icp_dof=np.asarray(out.icp_dof, dtype=np.int64), icp_times=np.asarray(out.icp_times),
        n_icp_rejected=out.n_rejected, support_group=np.asarray(sup.code), groups=groups, processing_s=elapsed,
        duration_s=float(times[-1] - times[0]), stance_dofs=out.st_dof, stance_mask=sup.mask,
        contacts=sup.contacts, floor_times=out.floors[:, 0], floor_nis=out.floors[:, 1],
        floor_dofs=out.floors[:, 2].astype(np.int64), floor_y2=out.floors[:, 3], floor_s=out.floors[:, 4],
        n_zero_velocity=out.n_zupt, phases=phases,
    )


def estimate_trajectory(dataset, config: TrackerConfig = TrackerConfig()) -> tuple[np.ndarray, np.ndarray]:
    """The estimated body trajectory of a dataset (folder path or a read Dataset).

    Returns:
        times (N,) s and T_world_body (N, 4, 4) at every timeseries sample (world frame: see the
        module docstring).
    """
    from graphcal.io.dataset import Dataset, read_dataset

    ds = dataset if isinstance(dataset, Dataset) else read_dataset(dataset)
    res = run_filter(inputs_from_dataset(ds), config)
    return res.times, res.T_world_body

