"""Leg kinematic identification from motion capture (Yuan's virtual fixed base): graph, identifiable
set, LM to convergence, covariance, verdict.

Unknowns: ``T_body_mocap`` (Pose3, key ``V(0)``: the motion-capture frame, or the virtual base, in
the body frame), per leg the parameters ``theta`` of :mod:`graphcal.models.legs` (key ``L(l)``),
per marker whose position on the foot is not given its ``p_foot_marker`` (Point3, key ``K(j)``).
:func:`identify_legs` fits the nominal model ("before"), chooses the free set
(:mod:`graphcal.legs.identifiability`), iterates LM over it ("after"), scales the covariance by
``sigma0^2`` and judges the fit (:mod:`graphcal.legs.adequacy`). Units: m, rad; errors
(``TrackResiduals``) are measured minus predicted marker positions in BODY axes (m; mm in summaries).

The steps and the noise model: docs/legs.md, "The factor" and "Solving".
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import gtsam
import numpy as np

from graphcal.errors import GraphcalError
from graphcal.factors.keys import K, L, V
from graphcal.factors.mocap_marker import marker_covariance, mocap_marker_error, mocap_marker_factor, sqrt_information
from graphcal.factors.mocap_pose import (
    frame_kinematics,
    mocap_pose_error,
    mocap_pose_factor,
    pose_covariance,
    sqrt_information6,
)
from graphcal.geometry import fit_rigid_transform, invert_pose, pose_log_between
from graphcal.legs.adequacy import Adequacy, adequacy, jackknife_covariance, significance
from graphcal.legs.identifiability import IdentifiabilityReport, identifiability
from graphcal.legs.marker_ids import exchange_markers, find_exchanged_markers, find_exchanged_postures
from graphcal.legs.mocap_data import MarkerTrack, MocapData, PoseTrack
from graphcal.models.legs import LegModel, leg_model, point_kinematics

__all__ = [
    "MOCAP_COMPONENTS",
    "HELD_SIGMA",
    "ROBUST_LOSSES",
    "IdentifyOptions",
    "ParameterEstimate",
    "TrackResiduals",
    "LegIdentificationResult",
    "identify_legs",
    "identify_legs_dataset",
]

#: tangent components of T_body_mocap, GTSAM order [omega, v] (right perturbation, mocap axes)
MOCAP_COMPONENTS = ("rx", "ry", "rz", "x", "y", "z")
#: prior sigma (rad / m) holding a pose or marker component at its value
HELD_SIGMA = 1e-9
_LOOSE_SIGMA = 1e3
#: robust losses of ``IdentifyOptions.robust`` and their default thresholds (whitened units, 95 %
#: efficiency under Gaussian noise), applied per sample of a track (one marker or pose at one posture)
ROBUST_LOSSES = {"none": None, "huber": 1.345, "cauchy": 2.3849}


@dataclass(frozen=True)
class IdentifyOptions:
    """Settings of :func:`identify_legs`.

    Attributes:
        sigma_marker_m: marker noise per coordinate (m), a priori.
        sigma_joint_rad: joint encoder noise per joint (rad; m for prismatic), a priori.
        origins: leg model: ``"first"`` (hip position 3-D, default), ``"all"`` or ``"none"``
            (:func:`graphcal.models.legs.leg_model`).
        link_lengths: include link-length parameters.
        joint_offsets: include joint-offset parameters (all three switched off with
            ``origins="none"``: the nominal model, only the pose and the markers are fitted).
        mocap_free: components of ``T_body_mocap`` that are unknown (the others are held at the
            nominal pose). Default all six; Yuan's setting is ``("rz", "z")`` (his alpha_h, z_h).
        scale_offset_rad, scale_length_m, scale_mocap_rad, scale_mocap_m, scale_marker_m:
            a-priori error scales for the identifiability analysis (SI).
        rtol, s_min, f_identifiable: identifiability tolerances (:mod:`graphcal.legs.identifiability`).
        scale_covariance: multiply the covariance by ``sigma0^2``.
        max_iterations: LM limit.
        robust: robust loss per sample (``"none"``, ``"huber"``, ``"cauchy"``; gtsam mEstimators):
            down-weights a posture far from the others (:data:`ROBUST_LOSSES`).
        robust_k: its threshold in noise standard deviations (default: :data:`ROBUST_LOSSES`).
        noise_source: where ``sigma_marker_m`` / ``sigma_joint_rad`` come from (dataset.yaml, the
            command line, the documented defaults), named in the verdict.
    """

    sigma_marker_m: float = 0.001
    sigma_joint_rad: float = 0.0
    origins: str = "first"
    link_lengths: bool = True
    joint_offsets: bool = True
    mocap_free: tuple[str, ...] = MOCAP_COMPONENTS
    scale_offset_rad: float = math.radians(2.0)
    scale_length_m: float = 0.01
    scale_mocap_rad: float = 1.0
    scale_mocap_m: float = 1.0
    scale_marker_m: float = 0.1
    rtol: float = 1e-8
    s_min: float = 3.0
    f_identifiable: float = 0.05
    scale_covariance: bool = True
    max_iterations: int = 100
    robust: str = "none"
    robust_k: float | None = None
    noise_source: str = "options"

    def __post_init__(self):
        if self.robust not in ROBUST_LOSSES:
            raise GraphcalError(f"robust: expected one of {', '.join(ROBUST_LOSSES)}, got {self.robust!r}")
        if self.robust_k is not None and not (np.isfinite(self.robust_k) and self.robust_k > 0):
            raise GraphcalError(f"robust_k must be a finite number > 0 (noise standard deviations), got {self.robust_k}")
        bad = [c for c in self.mocap_free if c not in MOCAP_COMPONENTS]
        if bad:
            raise GraphcalError(f"mocap_free: unknown component(s) {bad}; choose from {', '.join(MOCAP_COMPONENTS)}")
        if not (np.isfinite(self.sigma_marker_m) and self.sigma_marker_m > 0):
            raise GraphcalError(f"sigma_marker_m must be a finite number > 0 (m), got {self.sigma_marker_m}")
        if not (np.isfinite(self.sigma_joint_rad) and self.sigma_joint_rad >= 0):
            raise GraphcalError(f"sigma_joint_rad must be a finite number >= 0 (rad), got {self.sigma_joint_rad}")
        object.__setattr__(self, "mocap_free", tuple(self.mocap_free))


@dataclass(frozen=True)
class ParameterEstimate:
    """One estimated (or held) parameter, SI units.

    Attributes:
        name: parameter name (``<joint>.offset_rad``, ``T_body_mocap.rz``, ``<marker>.p_foot_marker.x``).
        value: estimate (leg parameters: the change from the nominal URDF; pose components: the
            right-perturbation tangent from the reference pose, see
            :attr:`LegIdentificationResult.T_body_mocap_reference`; marker coordinates: the position).
        sigma: the governing 1-sigma: the larger of ``sigma_model`` and ``sigma_jackknife`` (0 when held).
        sigma_model: 1-sigma of the model covariance (scaled by sigma0^2 unless switched off).
        sigma_jackknife: 1-sigma of the leave-one-posture-out jackknife (nan when not available).
        status: identifiability verdict (``identifiable`` / ``combination`` / ``unidentifiable`` /
            ``known`` for a pose component that is not a candidate).
        free: estimated (True) or held at its nominal value (False).
        note: the identifiability sentence.
    """

    name: str
    value: float
    sigma: float
    status: str
    free: bool
    note: str = ""
    sigma_model: float = float("nan")
    sigma_jackknife: float = float("nan")

    @property
    def significance(self) -> dict:
        """``{z, p_value, level}`` of ``|value| / sigma`` (:func:`graphcal.legs.adequacy.significance`)."""
        return significance(self.value, self.sigma) if self.free else {"z": float("nan"), "p_value": float("nan"),
                                                                        "level": "held"}


@dataclass(frozen=True, eq=False)
class TrackResiduals:
    """Errors of one marker (measured minus predicted, body axes, m).

    Attributes:
        marker, foot: names.
        time: (N,) sample times.
        before: (N, 3) nominal legs (pose and unknown markers fitted).
        after: (N, 3) identified legs.
        nominal: (N, 3) everything nominal (only when the nominal T_body_mocap is known), else None.
    """

    marker: str
    foot: str
    time: np.ndarray
    before: np.ndarray
    after: np.ndarray
    nominal: np.ndarray | None = None

    @staticmethod
    def _rmse(e) -> float:
        return float(np.sqrt(np.mean(np.sum(np.asarray(e) ** 2, axis=1)))) if len(e) else float("nan")

    @property
    def rmse_before_mm(self) -> float:
        """3-D RMS error before (mm)."""
        return 1e3 * self._rmse(self.before)

    @property
    def rmse_after_mm(self) -> float:
        """3-D RMS error after (mm)."""
        return 1e3 * self._rmse(self.after)

    @property
    def rmse_nominal_mm(self) -> float | None:
        """3-D RMS error with everything nominal (mm), or None."""
        return None if self.nominal is None else 1e3 * self._rmse(self.nominal)


@dataclass(frozen=True, eq=False)
class LegIdentificationResult:
    """What :func:`identify_legs` returns.

    Attributes:
        models: foot -> :class:`~graphcal.models.legs.LegModel`.
        legs: foot -> tuple of :class:`ParameterEstimate` (``model.names`` order).
        theta: foot -> (k,) identified parameter vector.
        theta_covariance: foot -> (k, k) covariance (zeros on held parameters).
        T_body_mocap: (4, 4) estimated pose of the measurement frame in the body frame.
        T_body_mocap_covariance: (6, 6) covariance of its right perturbation [omega, v].
        T_body_mocap_reference: (4, 4) the pose the ``T_body_mocap.*`` values are relative to (the
            nominal pose when known, else the "before" fit).
        T_body_mocap_before: (4, 4) the "before" fit (nominal legs).
        marker_positions_before: marker -> (3,) marker positions of the "before" fit.
        mocap: tuple of :class:`ParameterEstimate` for rx, ry, rz, x, y, z.
        markers: marker -> tuple of :class:`ParameterEstimate` (x, y, z in the foot frame) -- only
            for markers whose position was estimated.
        marker_positions: marker -> (3,) position in the foot frame used (known or estimated).
        identifiability: the :class:`~graphcal.legs.identifiability.IdentifiabilityReport`.
        residuals: one :class:`TrackResiduals` per marker.
        sigma0: a-posteriori standard deviation of unit weight (1 when the noise model fits; with a
            robust loss, of the robust-weighted residuals). Not the verdict: see ``adequacy``.
        dof: residuals minus free unknowns.
        iterations, converged: of the final LM.
        frame: ``"mocap"`` or ``"vbase"``; pose_name: ``"T_body_mocap"`` or ``"T_body_vbase"``.
        base_frame, robot_name, urdf_xml: the robot.
        source: dataset path or description.
        options: the :class:`IdentifyOptions`.
        warnings: sentences.
        adequacy: the :class:`~graphcal.legs.adequacy.Adequacy` verdict (declared noise), or None.
    """

    models: dict
    legs: dict
    theta: dict
    theta_covariance: dict
    T_body_mocap: np.ndarray
    T_body_mocap_covariance: np.ndarray
    T_body_mocap_reference: np.ndarray
    T_body_mocap_before: np.ndarray
    marker_positions_before: dict
    mocap: tuple
    markers: dict
    marker_positions: dict
    identifiability: IdentifiabilityReport
    residuals: tuple
    sigma0: float
    dof: int
    iterations: int
    converged: bool
    frame: str
    pose_name: str
    base_frame: str
    robot_name: str
    urdf_xml: str
    source: str
    options: IdentifyOptions
    warnings: tuple = field(default_factory=tuple)
    adequacy: Adequacy | None = None

    @property
    def feet(self) -> tuple[str, ...]:
        return tuple(self.models)

    def rmse_mm(self, foot: str) -> tuple[float, float]:
        """(before, after) 3-D RMS error of every marker of ``foot`` together (mm)."""
        rs = [r for r in self.residuals if r.foot == foot]
        b = np.concatenate([r.before for r in rs])
        a = np.concatenate([r.after for r in rs])
        return 1e3 * TrackResiduals._rmse(b), 1e3 * TrackResiduals._rmse(a)

    def parameter(self, foot: str, name: str) -> ParameterEstimate:
        """The estimate of leg parameter ``name`` of ``foot``."""
        for p in self.legs[foot]:
            if p.name == name:
                return p
        raise KeyError(f"{name!r} is not a parameter of the leg of {foot!r}")

    def leg_values(self) -> dict[str, dict[str, float]]:
        """foot -> {parameter: value} of the estimated (free) leg parameters (for the URDF)."""
        return {f: {p.name: p.value for p in ps if p.free} for f, ps in self.legs.items()}


# ----------------------------------------------------------------------------- helpers
@dataclass
class _Track:
    track: MarkerTrack
    leg: object
    model: LegModel
    k_key: int | None
    marker: np.ndarray  # current / fixed position
    cov: np.ndarray | None = None  # (N,d,d) mocap frame (markers) / measured frame (poses)
    L: np.ndarray | None = None

    @property
    def is_pose(self) -> bool:
        return isinstance(self.track, PoseTrack)

    @property
    def dim(self) -> int:
        """Error rows per sample: 3 (marker) or 6 (pose)."""
        return 6 if self.is_pose else 3


def _track_error(tr: _Track, T, theta, marker, want: bool):
    """(e (N, d), [H_V, H_L, H_K or None] or None) of a track, unwhitened (markers: measured minus
    predicted, mocap axes, m; poses: :func:`~graphcal.factors.mocap_pose.mocap_pose_error`)."""
    if tr.is_pose:
        e, H = mocap_pose_error(T, theta, tr.track.q, tr.track.T_meas, tr.leg, tr.model, want)
        return e, (None if H is None else [H[0], H[1], None])
    return mocap_marker_error(T, theta, marker, tr.track.q, tr.track.p_meas, tr.leg, tr.model, want)


def _whiten(tr: _Track, B: np.ndarray, opts: "IdentifyOptions") -> np.ndarray:
    """Rows of ``B`` (N, d[, c]) divided by the track's noise (its sqrt information, or sigma)."""
    if tr.L is not None:
        return np.einsum("nij,nj->ni", tr.L, B) if B.ndim == 2 else tr.L @ B
    return B / opts.sigma_marker_m


def _fk_points(tr: _Track, theta) -> tuple[np.ndarray, object]:
    pk = point_kinematics(tr.leg, tr.model, tr.track.q, theta, tr.marker)
    return pk.p_base_point, pk


def _initial_pose(tracks: list[_Track], thetas: Mapping[str, np.ndarray], T0, known_T: bool, n_alt: int = 8):
    """T_body_mocap start (rigid fit unless known) and linear fits of the unknown markers."""
    T = None if T0 is None else np.asarray(T0, dtype=float)
    for _ in range(n_alt if any(t.k_key is not None for t in tracks) else 1):
        if not known_T:
            Pb = np.concatenate([_fk_points(t, thetas[t.track.foot])[0] for t in tracks])
            Pm = np.concatenate([t.track.p_meas for t in tracks])
            try:
                T_mb = fit_rigid_transform(Pb, Pm)
            except np.linalg.LinAlgError:
                raise GraphcalError("cannot start: the marker positions do not determine a rigid fit") from None
            T = invert_pose(T_mb)
        T_mb = invert_pose(T)
        for t in tracks:
            if t.k_key is None:
                continue
            pk = point_kinematics(t.leg, t.model, t.track.q, thetas[t.track.foot], np.zeros(3))
            A = np.einsum("ij,njk->nik", T_mb[:3, :3], pk.R_base_foot).reshape(-1, 3)
            b = (t.track.p_meas - (pk.p_base_point @ T_mb[:3, :3].T + T_mb[:3, 3])).reshape(-1)
            t.marker = np.linalg.lstsq(A, b, rcond=None)[0]
        if known_T:
            break
    return T


def _pose_prior(T, held: Sequence[bool]) -> gtsam.PriorFactorPose3:
    s = np.where(np.asarray(held, dtype=bool), HELD_SIGMA, _LOOSE_SIGMA)
    return gtsam.PriorFactorPose3(V(0), gtsam.Pose3(np.asarray(T, dtype=float)), gtsam.noiseModel.Diagonal.Sigmas(s))


def _errors_body(tr: _Track, T, theta, marker) -> np.ndarray:
    """Measured minus predicted position (N, 3) in body axes, m (a pose track: its origin)."""
    e, _ = _track_error(tr, T, theta, marker, False)
    if tr.is_pose:  # e_t = R_meas^T (p_pred - p_meas) -> p_meas - p_pred in mocap axes
        e = -np.einsum("nij,nj->ni", tr.track.T_meas[:, :3, :3], e[:, 3:])
    return e @ np.asarray(T)[:3, :3].T  # mocap axes -> body axes


# ----------------------------------------------------------------------------- main
#: fewer residual degrees of freedom than this (or than the unknowns) and identify-legs warns that
#: the fit is nearly exact (3 samples of the A1's leg: 9 coordinates for 9 unknowns, 0 dof, a calf
#: offset 18 sigma off the truth with no warning)
MIN_REDUNDANCY_DOF = 10


def identify_legs(
    robot,
    tracks: Sequence[MarkerTrack],
    *,
    options: IdentifyOptions = IdentifyOptions(),
    T_body_mocap_nominal=None,
    frame: str = "mocap",
    source: str = "",
    warnings: Sequence[str] = (),
    progress: Callable[[str], None] | None = None,
) -> LegIdentificationResult:
    """Identify the kinematic parameters of the legs that carry markers (see module docstring).

    Args:
        robot: the :class:`~graphcal.models.robot.RobotModel` (nominal URDF).
        tracks: the markers' samples (:class:`~graphcal.legs.mocap_data.MarkerTrack`), measurement
            frame = motion-capture frame (or virtual base when ``frame="vbase"``).
        options: :class:`IdentifyOptions`.
        T_body_mocap_nominal: (4, 4) nominal pose of the measurement frame in the body frame, or
            None (unknown: a rigid fit starts it; every component should then be in ``mocap_free``).
        frame: ``"mocap"`` or ``"vbase"`` (names the pose ``T_body_mocap`` / ``T_body_vbase``).
        source: description for reports.
        warnings: sentences carried into the result.
        progress: called with a stage description before each stage.

    Raises:
        GraphcalError: no tracks, a foot that is not a foot of the robot, a graph the data do not
            determine (:class:`~graphcal.solvers.batch.UnderdeterminedError`).
    """
    say = progress or (lambda s: None)
    opts = options
    if not tracks:
        raise GraphcalError("identify_legs: no marker tracks")
    warnings = list(warnings)
    pose_name = "T_body_vbase" if frame == "vbase" else "T_body_mocap"
    feet = []
    for t in tracks:
        if t.foot not in feet:
            feet.append(t.foot)
    feet = [f for f in robot.feet if f in feet] + [f for f in feet if f not in robot.feet]
    models = {f: leg_model(robot, f, origins=opts.origins, link_lengths=opts.link_lengths,
                           joint_offsets=opts.joint_offsets) for f in feet}
    legs = {f: robot.leg(f) for f in feet}
    zero = {f: np.zeros(models[f].dim) for f in feet}

    trs: list[_Track] = []
    n_unknown = 0
    for t in tracks:
        known = t.p_foot_marker is not None
        k_key = None if known else K(n_unknown)
        n_unknown += 0 if known else 1
        trs.append(_Track(t, legs[t.foot], models[t.foot], k_key,
                          np.zeros(3) if not known else np.asarray(t.p_foot_marker, dtype=float)))

    # 1. start
    say("start: nominal model, rigid fit")
    known_T = T_body_mocap_nominal is not None
    T0 = _initial_pose(trs, zero, T_body_mocap_nominal, known_T)
    held_pose = [c not in opts.mocap_free for c in MOCAP_COMPONENTS]
    if not known_T and any(held_pose):
        held_names = ", ".join(c for c, h in zip(MOCAP_COMPONENTS, held_pose) if h)
        warnings.append(f"{pose_name} has no nominal value: its held components ({held_names}) "
                        "are held at the rigid-fit start")
    _set_noise_models(trs, opts, T0, zero)

    # 2. before: the pose (and the unknown markers) with the nominal legs
    say("before: fit the pose (and markers) with the nominal legs")
    before = _fit_before(trs, feet, opts, T0, held_pose, zero, T_body_mocap_nominal)

    # 3. identifiability on the stacked whitened Jacobian at the "before" point
    say("identifiability: SVD / pivoted QR of the identification Jacobian")
    fs = _free_set(trs, feet, models, opts, before.T, zero, pose_name, warnings)

    # 4. after: LM to convergence over the free set
    say("after: Levenberg-Marquardt over the identifiable parameters")
    after = _fit_after(trs, feet, models, opts, before.T, fs)

    # 5. covariance, scaled by the variance factor
    say("covariance")
    T_ref = np.asarray(T_body_mocap_nominal, dtype=float) if known_T else before.T
    return _result(robot, trs, feet, models, opts, fs, before, after, T_ref, frame, pose_name, source, warnings)


@dataclass(frozen=True, eq=False)
class _Before:
    """The "before" fit: pose ``T`` (4, 4), markers, and body-frame errors per marker (nominal legs)."""

    T: np.ndarray
    markers: dict
    errors: dict
    errors_nominal_pose: dict


@dataclass(frozen=True, eq=False)
class _FreeSet:
    """The identification's candidate columns, the identifiability report and what it leaves free."""

    cand_names: list
    pose_cols: list
    theta_off: dict
    marker_off: dict
    report: IdentifiabilityReport
    held_T: list
    free_theta: dict
    marker_held: dict


@dataclass(frozen=True, eq=False)
class _After:
    """The "after" fit: its LM result and graph, the pose (4, 4) and the full parameter vectors."""

    res: object
    graph: gtsam.NonlinearFactorGraph
    T: np.ndarray
    theta: dict


def _set_noise_models(trs: list[_Track], opts: IdentifyOptions, T0: np.ndarray, zero: Mapping[str, np.ndarray]) -> None:
    """Per track, the covariance of its samples (mocap frame) and its square-root information,
    fixed for the whole identification (joint noise propagated at the nominal legs, pose ``T0``)."""
    R_bm = T0[:3, :3]
    for tr in trs:
        if tr.is_pose:
            R, _, _, _, Jw_q, Jp_q = frame_kinematics(tr.leg, tr.model, tr.track.q, zero[tr.track.foot])
            tr.cov = pose_covariance(tr.track.cov, R, Jw_q, Jp_q, opts.sigma_joint_rad)
            tr.L = sqrt_information6(tr.cov)
            continue
        extra = tr.track.cov_extra
        if opts.sigma_joint_rad > 0 or extra is not None:
            _, pk = _fk_points(tr, zero[tr.track.foot])
            Jq_m = np.einsum("ji,njk->nik", R_bm, pk.J_q)  # R^T J_q
            tr.cov = marker_covariance(Jq_m, opts.sigma_marker_m, opts.sigma_joint_rad, extra)
            tr.L = sqrt_information(tr.cov)


def _graph(trs: list[_Track], feet: list, opts: IdentifyOptions, free_theta: Mapping[str, np.ndarray] | None,
           held_T: Sequence[bool], T_hold, marker_held: Mapping[int, np.ndarray]) -> gtsam.NonlinearFactorGraph:
    """The identification graph: one marker factor per track (leg parameters ``free_theta`` free
    when given), a prior holding the ``held_T`` components of ``T_hold`` and the held marker axes."""
    g = gtsam.NonlinearFactorGraph()
    robust = _m_estimator(opts)
    for tr in trs:
        f = tr.track.foot
        kw = {}
        if free_theta is not None and free_theta[f].size:
            kw.update(l_key=L(feet.index(f)), free=free_theta[f])
        # a robust loss acts per sample: one factor per sample (else one factor per track)
        parts = [np.arange(len(tr.track))] if robust is None else [np.array([i]) for i in range(len(tr.track))]
        for rows in parts:
            if tr.is_pose:
                g.add(mocap_pose_factor(V(0), tr.track.q[rows], tr.track.T_meas[rows], tr.leg, tr.model,
                                        cov=tr.cov[rows], robust=robust, **kw))
                continue
            kw2 = dict(kw, cov_m2=tr.cov[rows]) if tr.cov is not None else dict(kw, sigma_m=opts.sigma_marker_m)
            if tr.k_key is None:
                kw2["p_foot_marker"] = tr.marker
            else:
                kw2["k_key"] = tr.k_key
            g.add(mocap_marker_factor(V(0), tr.track.q[rows], tr.track.p_meas[rows], tr.leg, tr.model,
                                      robust=robust, **kw2))
    if any(held_T):
        g.add(_pose_prior(T_hold, held_T))
    for key, (pos, held) in marker_held.items():
        s = np.where(held, HELD_SIGMA, _LOOSE_SIGMA)
        g.add(gtsam.PriorFactorPoint3(key, np.asarray(pos, dtype=float), gtsam.noiseModel.Diagonal.Sigmas(s)))
    return g


def _m_estimator(opts: IdentifyOptions):
    """The gtsam mEstimator of ``opts.robust`` (None for ``"none"``)."""
    if opts.robust == "none":
        return None
    k = opts.robust_k if opts.robust_k is not None else ROBUST_LOSSES[opts.robust]
    return (gtsam.noiseModel.mEstimator.Huber.Create(k) if opts.robust == "huber"
            else gtsam.noiseModel.mEstimator.Cauchy.Create(k))


def _fit_before(trs: list[_Track], feet: list, opts: IdentifyOptions, T0: np.ndarray, held_pose: list,
                zero: Mapping[str, np.ndarray], T_body_mocap_nominal) -> _Before:
    """Fit the pose (and the unknown markers, updated in ``trs``) with the nominal legs."""
    from graphcal.solvers.batch import solve_lm

    known_T = T_body_mocap_nominal is not None
    vals = gtsam.Values()
    vals.insert(V(0), gtsam.Pose3(T0))
    for tr in trs:
        if tr.k_key is not None:
            vals.insertPoint3(tr.k_key, tr.marker)
    gA = _graph(trs, feet, opts, None, held_pose, T0, {})
    resA = solve_lm(gA, vals, max_iterations=opts.max_iterations)
    TA = np.asarray(resA.values.atPose3(V(0)).matrix())
    for tr in trs:
        if tr.k_key is not None:
            tr.marker = np.asarray(resA.values.atPoint3(tr.k_key), dtype=float)
    markerA = {tr.track.marker: tr.marker.copy() for tr in trs}
    before = {tr.track.marker: _errors_body(tr, TA, zero[tr.track.foot], tr.marker) for tr in trs}
    nominal = {}
    if known_T:
        _initial_pose(trs, zero, T_body_mocap_nominal, True)  # markers fitted with the nominal pose
        nominal = {tr.track.marker: _errors_body(tr, T0, zero[tr.track.foot], tr.marker) for tr in trs}
        for tr in trs:
            tr.marker = markerA[tr.track.marker]
    return _Before(TA, markerA, before, nominal)


def _free_set(trs: list[_Track], feet: list, models: Mapping[str, LegModel], opts: IdentifyOptions, TA: np.ndarray,
              zero: Mapping[str, np.ndarray], pose_name: str, warnings: list) -> _FreeSet:
    """Identifiability of every candidate (pose components, leg parameters, unknown markers) on the
    stacked whitened Jacobian at the "before" point ``TA``; appends a warning per leg left without one."""
    cand_names: list[str] = []
    scales: list[float] = []
    pose_cols = [i for i, c in enumerate(MOCAP_COMPONENTS) if c in opts.mocap_free]
    for i in pose_cols:
        cand_names.append(f"{pose_name}.{MOCAP_COMPONENTS[i]}")
        scales.append(opts.scale_mocap_rad if i < 3 else opts.scale_mocap_m)
    dup = {n for f in feet for n in models[f].names if sum(n in models[g].names for g in feet) > 1}
    theta_off: dict[str, int] = {}
    for f in feet:
        theta_off[f] = len(cand_names)
        for i, n in enumerate(models[f].names):
            cand_names.append(f"{f}:{n}" if n in dup else n)
            scales.append(opts.scale_offset_rad if models[f].is_angle(i) else opts.scale_length_m)
    marker_off: dict[str, int] = {}
    for tr in trs:
        if tr.k_key is not None:
            marker_off[tr.track.marker] = len(cand_names)
            for a in "xyz":
                cand_names.append(f"{tr.track.marker}.p_foot_marker.{a}")
                scales.append(opts.scale_marker_m)
    blocks = []
    for tr in trs:
        f = tr.track.foot
        e, H = _track_error(tr, TA, zero[f], tr.marker, True)
        N = e.shape[0]
        A = np.zeros((N, tr.dim, len(cand_names)))
        A[:, :, : len(pose_cols)] = H[0][:, :, pose_cols]
        A[:, :, theta_off[f] : theta_off[f] + models[f].dim] = H[1]
        if tr.k_key is not None:
            o = marker_off[tr.track.marker]
            A[:, :, o : o + 3] = H[2]
        blocks.append(_whiten(tr, A, opts).reshape(tr.dim * N, -1))
    report = identifiability(np.concatenate(blocks), cand_names, scales, rtol=opts.rtol, s_min=opts.s_min,
                             f_identifiable=opts.f_identifiable)
    free_names = set(report.free)
    held_T = [True] * 6
    for i in pose_cols:
        held_T[i] = cand_names[pose_cols.index(i)] not in free_names
    free_theta = {f: np.array([i for i in range(models[f].dim) if cand_names[theta_off[f] + i] in free_names], dtype=int)
                  for f in feet}
    marker_held = {}
    for tr in trs:
        if tr.k_key is not None:
            o = marker_off[tr.track.marker]
            h = np.array([cand_names[o + a] not in free_names for a in range(3)])
            marker_held[tr.k_key] = (tr.marker.copy(), h)
    for f in feet:
        if free_theta[f].size == 0 and models[f].dim:
            warnings.append(f"no kinematic parameter of the leg of {f!r} is identifiable from these data")
    return _FreeSet(cand_names, pose_cols, theta_off, marker_off, report, held_T, free_theta, marker_held)


def _fit_after(trs: list[_Track], feet: list, models: Mapping[str, LegModel], opts: IdentifyOptions, TA: np.ndarray,
               fs: _FreeSet) -> _After:
    """Levenberg-Marquardt to convergence over the free set, from the "before" point (markers
    updated in ``trs``)."""
    from graphcal.solvers.batch import solve_lm

    free_theta = fs.free_theta
    vals = gtsam.Values()
    vals.insert(V(0), gtsam.Pose3(TA))
    for tr in trs:
        if tr.k_key is not None:
            vals.insertPoint3(tr.k_key, tr.marker)
    for f in feet:
        if free_theta[f].size:
            vals.insert(L(feet.index(f)), np.zeros(free_theta[f].size))
    gB = _graph(trs, feet, opts, free_theta, fs.held_T, TA, fs.marker_held)
    resB = solve_lm(gB, vals, max_iterations=opts.max_iterations)
    v = resB.values
    T_est = np.asarray(v.atPose3(V(0)).matrix())
    theta = {}
    for f in feet:
        th = np.zeros(models[f].dim)
        if free_theta[f].size:
            th[free_theta[f]] = np.asarray(v.atVector(L(feet.index(f))), dtype=float)
        theta[f] = th
    for tr in trs:
        if tr.k_key is not None:
            tr.marker = np.asarray(v.atPoint3(tr.k_key), dtype=float)
    return _After(resB, gB, T_est, theta)


@dataclass(frozen=True, eq=False)
class _System:
    """The whitened linearised problem at the solution (declared noise): rows of every track."""

    A: np.ndarray  # (m, u) free columns
    r: np.ndarray  # (m,)
    posture: np.ndarray  # (m,) time of each row, s
    track: np.ndarray  # (m,) track name of each row
    names: list  # (u,) column names (the ParameterEstimate names)
    weight: np.ndarray  # (m,) robust weight of each row (1 without a robust loss)


def _system(trs: list[_Track], feet: list, models: Mapping[str, LegModel], opts: IdentifyOptions, fs: _FreeSet,
            T: np.ndarray, theta: Mapping[str, np.ndarray]) -> _System:
    """Whitened residuals and Jacobian of the free unknowns at ``T``, ``theta`` and the current markers."""
    cols = [fs.cand_names[k] for k, i in enumerate(fs.pose_cols) if not fs.held_T[i]]
    pose_free = [i for i in fs.pose_cols if not fs.held_T[i]]
    th_cols = {f: len(cols) for f in feet}
    for f in feet:
        th_cols[f] = len(cols)
        cols += [fs.cand_names[fs.theta_off[f] + i] for i in fs.free_theta[f]]
    mk_cols: dict[str, tuple[int, np.ndarray]] = {}
    for tr in trs:
        if tr.k_key is not None:
            axes = np.flatnonzero(~fs.marker_held[tr.k_key][1])
            mk_cols[tr.track.marker] = (len(cols), axes)
            cols += [fs.cand_names[fs.marker_off[tr.track.marker] + a] for a in axes]
    est = _m_estimator(opts)
    As, rs, ps, ts, ws = [], [], [], [], []
    for tr in trs:
        f = tr.track.foot
        e, H = _track_error(tr, T, theta[f], tr.marker, True)
        N, d = e.shape
        A = np.zeros((N, d, len(cols)))
        A[:, :, : len(pose_free)] = H[0][:, :, pose_free]
        A[:, :, th_cols[f] : th_cols[f] + fs.free_theta[f].size] = H[1][:, :, fs.free_theta[f]]
        if tr.track.marker in mk_cols:
            o, axes = mk_cols[tr.track.marker]
            A[:, :, o : o + axes.size] = H[2][:, :, axes]
        sign = 1.0 if tr.is_pose else -1.0  # H is d e / d x; the marker's e is measured minus predicted
        rw = _whiten(tr, e, opts)
        w = np.ones(N) if est is None else np.array([est.weight(float(x)) for x in np.linalg.norm(rw, axis=1)])
        As.append(sign * _whiten(tr, A, opts).reshape(N * d, -1))
        rs.append(sign * rw.reshape(-1))
        ps.append(np.repeat(tr.track.time, d))
        ts.append(np.repeat(np.array([tr.track.marker], dtype=object), N * d))
        ws.append(np.repeat(w, d))
    return _System(np.concatenate(As), np.concatenate(rs), np.concatenate(ps), np.concatenate(ts), cols,
                   np.concatenate(ws))


def _verdict(trs: list[_Track], sysm: _System, opts: IdentifyOptions, T: np.ndarray, theta) -> Adequacy:
    """:func:`graphcal.legs.adequacy.adequacy` of the solution, with each posture's 3-D RMS position error."""
    sq: dict[float, list[float]] = {}
    for tr in trs:
        e = _errors_body(tr, T, theta[tr.track.foot], tr.marker)
        for t, x in zip(tr.track.time.tolist(), np.sum(e**2, axis=1).tolist()):
            sq.setdefault(float(t), []).append(x)
    rms = {t: 1e3 * math.sqrt(sum(v) / len(v)) for t, v in sq.items()}
    noise = {"sigma_marker_m": float(opts.sigma_marker_m), "sigma_joint_rad": float(opts.sigma_joint_rad),
             "source": opts.noise_source}
    if any(tr.is_pose for tr in trs):
        noise["pose"] = "per-row sigma or covariance of mocap_poses.csv"
    return adequacy(sysm.A, sysm.r, sysm.posture, sysm.track, noise, position_errors_mm=rms)


def _result(robot, trs: list[_Track], feet: list, models: Mapping[str, LegModel], opts: IdentifyOptions,
            fs: _FreeSet, before: _Before, after: _After, T_ref: np.ndarray, frame: str, pose_name: str, source: str,
            warnings: list) -> LegIdentificationResult:
    """Covariance (scaled by the variance factor), the estimates with their sigmas, the residuals."""
    from graphcal.solvers.covariance import marginal_covariances

    free_theta, held_T, marker_held, cand_names = fs.free_theta, fs.held_T, fs.marker_held, fs.cand_names
    gB, v, resB, T_est, theta = after.graph, after.res.values, after.res, after.T, after.theta
    m_rows = sum(tr.dim * len(tr.track) for tr in trs)
    u = sum(not h for h in held_T) + sum(int(free_theta[f].size) for f in feet) + sum(int((~h).sum()) for _, h in marker_held.values())
    dof = m_rows - u
    sysm = _system(trs, feet, models, opts, fs, T_est, theta)
    chi2 = float(sysm.r @ sysm.r)  # declared noise, no robust weights (2 x the graph's error without a loss)
    verdict = _verdict(trs, sysm, opts, T_est, theta)
    sw = np.sqrt(sysm.weight)
    jk = np.sqrt(np.clip(np.diag(jackknife_covariance(sysm.A * sw[:, None], sysm.r * sw, sysm.posture)), 0.0, None))
    sigma_jk = dict(zip(sysm.names, jk.tolist()))
    if opts.robust != "none":  # the robust fit's scale: the weighted residuals (down-weighted postures count less)
        chi2 = float(np.sum(sysm.weight * sysm.r**2))
    sigma0 = math.sqrt(chi2 / dof) if dof > 0 else float("nan")
    if dof < max(MIN_REDUNDANCY_DOF, u):
        per_marker = math.ceil(2 * u / (3 * max(1, len(trs))))
        warnings.append(
            f"only {dof} residual degree(s) of freedom ({m_rows} marker coordinates for {u} unknowns): the fit is "
            "(nearly) exact, so its residuals cannot check the sigmas, and errors of the parameters held at nominal "
            f"go unseen into the free ones; record more samples (at least {per_marker} per marker for twice as many "
            "coordinates as unknowns)")
    keys = [V(0)] + [L(feet.index(f)) for f in feet if free_theta[f].size] + [tr.k_key for tr in trs if tr.k_key is not None]
    covs = marginal_covariances(gB, v, keys)
    warnings.extend(covs.warnings)
    factor = sigma0**2 if (opts.scale_covariance and math.isfinite(sigma0)) else 1.0

    cov_T = np.asarray(covs[V(0)]) * factor
    cov_T[np.asarray(held_T), :] = 0.0
    cov_T[:, np.asarray(held_T)] = 0.0
    xi = pose_log_between(T_ref, T_est)
    by_name = {p.name: p for p in fs.report.parameters}

    def est(name: str, value: float, var: float, candidate: bool) -> ParameterEstimate:
        if not candidate:
            return ParameterEstimate(name, value, 0.0, "known", False, f"{name}: known (held at its nominal value)")
        p = by_name[name]
        s = math.sqrt(max(var, 0.0)) if p.free else 0.0
        sj = sigma_jk.get(name, float("nan")) if p.free else float("nan")
        gov = max(s, sj) if math.isfinite(sj) else s
        return ParameterEstimate(name, value, gov, p.status, p.free, p.text, s, sj)

    mocap = tuple(est(f"{pose_name}.{c}", float(xi[i]), float(cov_T[i, i]), c in opts.mocap_free)
                  for i, c in enumerate(MOCAP_COMPONENTS))
    legs_out, theta_cov = {}, {}
    for f in feet:
        k = models[f].dim
        Ck = np.zeros((k, k))
        if free_theta[f].size:
            Cf = np.asarray(covs[L(feet.index(f))]) * factor
            Ck[np.ix_(free_theta[f], free_theta[f])] = Cf
        theta_cov[f] = Ck
        ests = (est(cand_names[fs.theta_off[f] + i], float(theta[f][i]), float(Ck[i, i]), True) for i in range(k))
        # plain parameter names in the per-leg output (the report may prefix a shared joint with its foot)
        legs_out[f] = tuple(ParameterEstimate(n, p.value, p.sigma, p.status, p.free, p.note, p.sigma_model,
                                              p.sigma_jackknife) for n, p in zip(models[f].names, ests))
    markers_out, marker_pos = {}, {}
    for tr in trs:
        marker_pos[tr.track.marker] = tr.marker.copy()
        if tr.k_key is None:
            continue
        Cm = np.asarray(covs[tr.k_key]) * factor
        o = fs.marker_off[tr.track.marker]
        markers_out[tr.track.marker] = tuple(
            est(cand_names[o + a], float(tr.marker[a]), float(Cm[a, a]), True) for a in range(3))
    residuals = tuple(
        TrackResiduals(tr.track.marker, tr.track.foot, tr.track.time, before.errors[tr.track.marker],
                       _errors_body(tr, T_est, theta[tr.track.foot], tr.marker), before.errors_nominal_pose.get(tr.track.marker))
        for tr in trs)
    if not resB.converged:
        warnings.append(f"Levenberg-Marquardt did not converge: {resB.message}")
    if not verdict.fits or verdict.flagged:
        warnings.insert(0, verdict.message)
    return LegIdentificationResult(
        models=models, legs=legs_out, theta=theta, theta_covariance=theta_cov, T_body_mocap=T_est,
        T_body_mocap_covariance=cov_T, T_body_mocap_reference=T_ref, T_body_mocap_before=before.T,
        marker_positions_before=before.markers, mocap=mocap, markers=markers_out,
        marker_positions=marker_pos, identifiability=fs.report, residuals=residuals, sigma0=sigma0, dof=dof,
        iterations=resB.iterations, converged=resB.converged, frame=frame, pose_name=pose_name,
        base_frame=robot.base_frame, robot_name=robot.name, urdf_xml=robot.urdf_xml, source=source,
        options=opts, warnings=tuple(warnings), adequacy=verdict)


def identify_legs_dataset(dataset, *, options: IdentifyOptions = IdentifyOptions(), sigma_body_marker_m: float | None = None,
                          progress: Callable[[str], None] | None = None) -> LegIdentificationResult:
    """:func:`identify_legs` on a dataset folder (``mocap.csv`` and / or ``mocap_poses.csv``;
    :func:`~graphcal.legs.mocap_data.mocap_data_from_dataset`).

    With ``options.noise_source == "dataset"`` the a-priori (physical) noise is the one dataset.yaml
    declares (``mocap.sigma_mm``, ``mocap.sigma_joint_deg``), else the documented defaults
    (:data:`~graphcal.legs.adequacy.DEFAULT_SIGMA_MARKER_M`, :data:`~graphcal.legs.adequacy.DEFAULT_SIGMA_JOINT_RAD`);
    otherwise ``options``' sigmas are used as given. ``sigma_body_marker_m`` (default: the marker
    sigma) is the body markers' noise, propagated through the virtual base when the dataset has body markers.
    """
    say = progress or (lambda s: None)
    say("read the dataset")
    if not isinstance(dataset, MocapData) and options.noise_source == "dataset":
        from graphcal.io.dataset import Dataset, read_dataset

        ds = dataset if isinstance(dataset, Dataset) else read_dataset(dataset)
        options = _declared_noise(options, ds.mocap_noise)
        sb = options.sigma_marker_m if sigma_body_marker_m is None else sigma_body_marker_m
        data = _mocap_data(ds, sb)
    else:
        if isinstance(dataset, MocapData) and options.noise_source == "dataset":
            options = _declared_noise(options, dataset.noise)
        sb = options.sigma_marker_m if sigma_body_marker_m is None else sigma_body_marker_m
        data = dataset if isinstance(dataset, MocapData) else _mocap_data(dataset, sb)
    def run(tracks):
        return identify_legs(data.robot, tracks, options=options, T_body_mocap_nominal=data.T_body_mocap_nominal,
                             frame=data.frame, source=data.source, warnings=data.warnings, progress=progress)

    # two feet's marker ids, or two postures' samples, exchanged: looked for only when nothing fits
    tracks = data.tracks
    found, result, notes = find_exchanged_markers(run(tracks), tracks, run)
    tracks = tracks if found is None else exchange_markers(tracks, *found.markers)
    _, result, more = find_exchanged_postures(result, tracks, run)
    notes = tuple(notes) + tuple(more)
    return dataclasses.replace(result, warnings=tuple(result.warnings) + notes) if notes else result


def _declared_noise(options: IdentifyOptions, noise: Mapping[str, float]) -> IdentifyOptions:
    """``options`` with the declared noise of dataset.yaml, else the documented defaults, and its source named."""
    from dataclasses import replace

    from graphcal.legs.adequacy import DEFAULT_SIGMA_JOINT_RAD, DEFAULT_SIGMA_MARKER_M

    sm = noise.get("sigma_m", DEFAULT_SIGMA_MARKER_M)
    sj = noise.get("sigma_joint_rad", DEFAULT_SIGMA_JOINT_RAD)
    src = (f"marker {sm * 1e3:g} mm ({'dataset.yaml mocap.sigma_mm' if 'sigma_m' in noise else 'default'}), "
           f"encoders {math.degrees(sj):g} deg ({'dataset.yaml mocap.sigma_joint_deg' if 'sigma_joint_rad' in noise else 'default'})")
    return replace(options, sigma_marker_m=sm, sigma_joint_rad=sj, noise_source=src)


def _mocap_data(dataset, sigma_body_marker_m):
    from graphcal.legs.mocap_data import mocap_data_from_dataset

    return mocap_data_from_dataset(dataset, sigma_body_marker_m=sigma_body_marker_m)
