"""Error-state extended Kalman filter of a legged robot: IMU propagation, stance-foot kinematics,
relative-pose (ICP) updates, through filterpy's ``ExtendedKalmanFilter`` (its ``predict`` and
``update``); docs/state_estimation.md.

Nominal state (kept here, on the manifold):
    ``p`` = p_world_body (m), ``v`` = v_world_body (m/s), ``R`` = R_world_body, ``b_g`` gyro bias
    (rad/s, IMU frame), ``b_a`` accelerometer bias (m/s^2, IMU frame), the world positions of the
    stance feet ``p_world_foot`` (one slot per foot, m) and a clone of the body pose at the last
    keyframe (``p_c``, ``R_c``) for relative-pose measurements (stochastic cloning).

Error state (filterpy's ``x``, zero between updates; its covariance is filterpy's ``P``), in order:
    ``dp`` (3, world), ``dv`` (3, world), ``dtheta`` (3, body; R = R_hat Exp(dtheta), the right
    perturbation of docs/conventions.md), ``db_g`` (3), ``db_a`` (3), one ``dp_foot`` (3, world) per
    stance slot, ``dp_c`` (3), ``dtheta_c`` (3). Dimension ``15 + 3 n_slots + 6``.

Models:
    IMU (``propagate``): omega = R_body_imu (gyro - b_g), a = R_body_imu (accel - b_a) (no lever
    arm), applied as a preintegrated chunk (:mod:`graphcal.locomotion.imu`); the covariance takes
    one filterpy ``predict`` per chunk with F (the chunk's error transition) and Q = Qc T.
    Stance kinematics (``update_stance``, Zhao Eqs. 6-9): each stance foot in the body frame,
    h = R^T (p_world_foot - p); filterpy's ``update`` with ``HJacobian``/``Hx`` at the nominal state.
    Foot slots (``reset_feet``, ``reset_slots``): a foot touching down is placed at
    p + R p_body_foot with the covariance that implies (cross-covariances included).
    Relative pose (``update_relative_pose``): T_c^-1 T measured (ICP between keyframe clouds) in
    the directions it constrains, z = A xi (xi = [omega, v], the right perturbation); filterpy's
    ``update`` with ``Hx`` the predicted relative pose and ``residual`` the pose difference on the
    manifold (:func:`relative_pose_residual`); optionally gated by its NIS.

Kept here, not in filterpy (it knows no manifold): the nominal state, the injection of the updated
error into it and the reset of the error to zero (covariance reset Jacobian taken as I, first
order), the foot-slot and clone covariance blocks. NIS of every update: :attr:`last_nis`,
:attr:`last_innovation`, :attr:`last_S`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.geometry import nearest_rotation, skew, so3_exp, so3_log

__all__ = ["GRAVITY_WORLD", "EkfNoise", "NominalState", "LeggedEKF", "state_dim", "check_covariance",
           "tangent_pose_covariance", "relative_pose_residual"]

GRAVITY_WORLD = np.array([0.0, 0.0, -9.80665])


def state_dim(n_slots: int) -> int:
    """Error-state dimension for ``n_slots`` stance-foot slots."""
    return 15 + 3 * n_slots + 6


@dataclass(frozen=True)
class EkfNoise:
    """Noise parameters of the filter (continuous-time densities; our defaults match the
    simulator's, see docs/state_estimation.md).

    Attributes:
        gyro_noise_density: rad/s/sqrt(Hz). accel_noise_density: m/s^2/sqrt(Hz).
        gyro_bias_rw: rad/s^2/sqrt(Hz). accel_bias_rw: m/s^3/sqrt(Hz).
        foot_rw: random walk of a planted foot (slip), m/sqrt(s).
        encoder_sigma_rad: joint encoder noise (per sample), rad.
        kinematic_sigma_m: extra foot-position noise for model errors, per axis, m.
        icp_cov_scale: the ICP covariance (from its point-to-plane information) is multiplied by
            this (unmodelled errors: sampling, local planes; measured ~2.5-3 on simulated data).
        floor_sigma_m: on declared level ground, a foot touching down is at the height of the floor
            the robot started on, within this (m; unevenness, foot radius and compliance).
    """

    gyro_noise_density: float = 2.5e-4
    accel_noise_density: float = 1.5e-3
    gyro_bias_rw: float = 1e-5
    accel_bias_rw: float = 1e-4
    foot_rw: float = 1e-5
    encoder_sigma_rad: float = float(np.radians(0.02))
    kinematic_sigma_m: float = 0.0
    icp_cov_scale: float = 4.0
    floor_sigma_m: float = 0.01

    def __post_init__(self):
        for name, v in self.__dict__.items():
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise GraphcalError(f"EkfNoise.{name} must be a finite number >= 0, got {v!r}")
        if self.icp_cov_scale <= 0:
            raise GraphcalError("EkfNoise.icp_cov_scale must be > 0")
        if self.floor_sigma_m <= 0:
            raise GraphcalError("EkfNoise.floor_sigma_m must be > 0")

    def process_density(self, n_slots: int) -> np.ndarray:
        """Qc: the error state's process-noise spectral density (diagonal), per second."""
        q = np.zeros(state_dim(n_slots))
        q[3:6] = self.accel_noise_density**2
        q[6:9] = self.gyro_noise_density**2
        q[9:12] = self.gyro_bias_rw**2
        q[12:15] = self.accel_bias_rw**2
        q[15 : 15 + 3 * n_slots] = self.foot_rw**2
        return np.diag(q)


@dataclass(frozen=True)
class NominalState:
    """A full state: p_world_body (3,) m, v_world_body (3,) m/s, R_world_body (3, 3), gyro_bias
    (3,) rad/s and accel_bias (3,) m/s^2 (IMU frame)."""

    p_world_body: np.ndarray
    v_world_body: np.ndarray
    R_world_body: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray


def _as_matrix(name: str, M, shape: tuple[int, int]) -> np.ndarray:
    try:
        A = np.array(M, dtype=float)
    except (TypeError, ValueError):
        raise GraphcalError(f"{name} must be a numeric matrix of shape {shape}") from None
    if A.shape != shape:
        raise GraphcalError(f"{name} must have shape {shape}, got {A.shape}")
    if not np.isfinite(A).all():
        raise GraphcalError(f"{name} must be finite (no nan or inf)")
    return A


def _as_vector(name: str, v, n: int = 3) -> np.ndarray:
    try:
        a = np.array(v, dtype=float)
    except (TypeError, ValueError):
        raise GraphcalError(f"{name} must be {n} numbers") from None
    if a.shape != (n,) or not np.isfinite(a).all():
        raise GraphcalError(f"{name} must be {n} finite numbers, got shape {a.shape}")
    return a


def check_covariance(name: str, M, n: int | None, *, definite: bool = False) -> np.ndarray:
    """``M`` as an (n, n) float matrix (any square size with ``n=None``), symmetrised; GraphcalError
    naming ``name`` unless finite, symmetric and positive semi-definite (definite with ``definite``)."""
    if n is None:
        try:
            shape = np.shape(M)
        except ValueError:
            shape = "ragged"
        if len(shape) != 2 or shape[0] != shape[1] or shape[0] < 1:
            raise GraphcalError(f"{name} must be a square (n, n) matrix, got shape {shape}")
        n = shape[0]
    A = _as_matrix(name, M, (n, n))
    scale = max(1.0, float(np.abs(A).max()))
    if not np.allclose(A, A.T, rtol=1e-9, atol=1e-12 * scale):
        raise GraphcalError(f"{name} must be symmetric (max |{name} - {name}^T| = {np.abs(A - A.T).max():.3g})")
    w = np.linalg.eigvalsh(0.5 * (A + A.T))
    tol = 1e-12 * scale
    if definite and w.min() <= 0:
        raise GraphcalError(f"{name} must be positive definite (smallest eigenvalue {w.min():.3g})")
    if w.min() < -tol:
        raise GraphcalError(f"{name} must be positive semi-definite (smallest eigenvalue {w.min():.3g})")
    return 0.5 * (A + A.T)


def relative_pose_residual(A: np.ndarray, T_meas: np.ndarray, T_pred: np.ndarray) -> np.ndarray:
    """``A xi`` (k,), ``xi = [Log(R_pred^T R_meas), R_pred^T (t_meas - t_pred)]`` (rad, m): measured
    minus predicted relative pose T_keyframebody_body (4, 4 each) as the right perturbation
    ``T_meas = T_pred Exp(xi)`` (to first order); filterpy's ``residual`` of the relative-pose update
    (``functools.partial(relative_pose_residual, A)``)."""
    R_pred = T_pred[:3, :3]
    return A @ np.r_[so3_log(R_pred.T @ T_meas[:3, :3]), R_pred.T @ (T_meas[:3, 3] - T_pred[:3, 3])]


def tangent_pose_covariance(R_world_body: np.ndarray, cov_dp_dtheta: np.ndarray) -> np.ndarray:
    """The filter's pose covariance in the SE(3) order of docs/conventions.md.

    The filter's pose error is ``e = [dp, dtheta]``: ``p = p_hat + dp`` (dp in the world frame, m)
    and ``R = R_hat Exp(dtheta)`` (dtheta in the body frame, rad). The right perturbation
    ``T = T_hat Exp(xi)``, ``xi = [omega, v]``, is to first order ``omega = dtheta``,
    ``v = R_hat^T dp`` (body frame), i.e. ``xi = J e`` with ``J = [[0, I], [R_hat^T, 0]]``.

    Args:
        R_world_body: (..., 3, 3) the estimated orientations R_hat.
        cov_dp_dtheta: (..., 6, 6) covariances of ``[dp, dtheta]`` (m^2, m rad, rad^2), e.g.
            :meth:`LeggedEKF.pose_covariance` or ``TrackResult.cov_pose``.

    Returns:
        (..., 6, 6) covariances of ``xi = [omega, v]`` (rad^2, rad m, m^2): ``J cov J^T``.
    """
    R = np.asarray(R_world_body, dtype=float)
    C = np.asarray(cov_dp_dtheta, dtype=float)
    J = np.zeros(R.shape[:-2] + (6, 6))
    J[..., 0:3, 3:6] = np.eye(3)
    J[..., 3:6, 0:3] = np.swapaxes(R, -1, -2)
    return J @ C @ np.swapaxes(J, -1, -2)


class LeggedEKF:
    """The error-state EKF (see the module docstring); every matrix is given to and checked by the
    constructor, which builds the filterpy filter from them (:meth:`_filterpy_filter`).

    Args:
        x0: the initial :class:`NominalState`.
        P0: (D, D) initial error-state covariance, D = :func:`state_dim` (``n_slots``); symmetric
            positive definite. Foot and clone blocks are overwritten when those are first set.
        Qc: (D, D) process-noise spectral density of the error state (per second), symmetric PSD;
            the discrete noise of a step of length dt is ``Qc * dt``.
        encoder_cov: (n, n) covariance of one leg's joint encoders (rad^2), symmetric PSD.
        kinematic_cov: (3, 3) extra covariance of a foot position from kinematics (m^2), PSD.
        n_slots: number of stance feet tracked (3 for a tripod).
        T_body_imu: (4, 4) IMU pose in the body frame (its rotation is used; no lever arm).

    Raises:
        GraphcalError: naming the matrix: wrong shape, not finite, not symmetric, not PSD (P0 not PD),
            x0's rotation or T_body_imu's not a rotation.
    """

    def __init__(self, x0: NominalState, P0, Qc, encoder_cov, kinematic_cov, *, n_slots: int = 3,
                 T_body_imu=None):
        if not isinstance(n_slots, int) or n_slots < 1:
            raise GraphcalError(f"n_slots must be a positive integer, got {n_slots!r}")
        D = state_dim(n_slots)
        self.n_slots = n_slots
        self.dim = D
        # p, v, b_g, b_a are views into one array (updated in place: one add injects an error)
        self._xn = np.zeros(12)
        self.p, self.v, self.bg, self.ba = self._xn[0:3], self._xn[3:6], self._xn[6:9], self._xn[9:12]
        self.p[:] = _as_vector("x0.p_world_body", x0.p_world_body)
        self.v[:] = _as_vector("x0.v_world_body", x0.v_world_body)
        R0 = _as_matrix("x0.R_world_body", x0.R_world_body, (3, 3))
        if not np.allclose(R0.T @ R0, np.eye(3), atol=1e-6) or np.linalg.det(R0) < 0:
            raise GraphcalError("x0.R_world_body must be a rotation matrix")
        self.R = R0.copy()
        self.bg[:] = _as_vector("x0.gyro_bias", x0.gyro_bias)
        self.ba[:] = _as_vector("x0.accel_bias", x0.accel_bias)
        P0 = check_covariance("P0", P0, D, definite=True)
        self.Qc = check_covariance("Qc", Qc, D)
        self.encoder_cov = check_covariance("encoder_cov", encoder_cov, None)
        self.kinematic_cov = check_covariance("kinematic_cov", kinematic_cov, 3)
        T = np.eye(4) if T_body_imu is None else _as_matrix("T_body_imu", T_body_imu, (4, 4))
        Rbi = T[:3, :3]
        if not np.allclose(Rbi.T @ Rbi, np.eye(3), atol=1e-6) or np.linalg.det(Rbi) < 0:
            raise GraphcalError("T_body_imu must hold a rotation matrix")
        self.R_body_imu = Rbi.copy()
        self._imu_identity = bool(np.allclose(Rbi, np.eye(3), atol=1e-12))
        self._Rbi6 = np.kron(np.eye(2), Rbi)
        self._xn_idx = np.r_[0:6, 9:15]
        self._Sk2 = np.zeros((2, 3, 3))

        self.kf = self._filterpy_filter(P0)
        self.p_feet = np.zeros((n_slots, 3))
        self.feet: tuple = ()
        self.p_c = self.p.copy()
        self.R_c = self.R.copy()
        self.has_clone = False
        self.last_nis = float("nan")
        self.last_innovation = np.zeros(0)
        self.last_S = np.zeros((0, 0))
        self._Qdiag = np.diag(self.Qc).copy() if np.count_nonzero(self.Qc - np.diag(np.diag(self.Qc))) == 0 else None
        self._fs = slice(15, 15 + 3 * n_slots)
        self._c = 15 + 3 * n_slots
        self._H = np.zeros((3 * n_slots, D))
        self._H3 = self._H.reshape(n_slots, 3, D)
        self._Sk = np.zeros((n_slots, 3, 3))
        # skew(h): entries (0,1)=-h2, (0,2)=h1, (1,0)=h2, (1,2)=-h0, (2,0)=-h1, (2,1)=h0
        self._sk_i = np.array([0, 0, 1, 1, 2, 2])
        self._sk_j = np.array([1, 2, 0, 2, 0, 1])
        self._sk_k = np.array([2, 1, 2, 0, 1, 0])
        self._sk_sign = np.array([-1.0, 1.0, 1.0, -1.0, -1.0, 1.0])
        slot, a, b = np.meshgrid(np.arange(n_slots), np.arange(3), np.arange(3), indexing="ij")
        self._foot_rows = (3 * slot + a).ravel()
        self._foot_cols = (15 + 3 * slot + b).ravel()
        self._foot_src = np.tile(np.arange(9), n_slots)

    def _filterpy_filter(self, P0: np.ndarray):
        """filterpy's EKF over the error state with the checked P0. Its constructor takes only the
        dimensions; x, P, F, Q are the attributes its ``predict``/``update`` read (filterpy's
        documented use). ``dim_z`` is nominal: every ``update`` passes its own R."""
        from filterpy.kalman import ExtendedKalmanFilter

        kf = ExtendedKalmanFilter(dim_x=self.dim, dim_z=3 * self.n_slots)
        kf.x = np.zeros(self.dim)  # the error state: zero between updates
        kf.P = P0.copy()
        kf.F = np.eye(self.dim)  # filled per chunk by propagate (in place)
        kf.Q = np.zeros((self.dim, self.dim))
        return kf

    # ------------------------------------------------------------------ accessors
    @property
    def P(self) -> np.ndarray:
        """The error-state covariance (filterpy's ``P``)."""
        return self.kf.P

    @property
    def T_world_body(self) -> np.ndarray:
        """(4, 4) current pose estimate."""
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.p
        return T

    def pose_covariance(self) -> np.ndarray:
        """(6, 6) covariance of the filter's pose error (dp (world, m), dtheta (body, rad)): position
        first and in the world frame, unlike the ``[omega, v]`` right-perturbation order of
        docs/conventions.md; :func:`tangent_pose_covariance` converts."""
        idx = np.r_[0:3, 6:9]
        return self.kf.P[np.ix_(idx, idx)].copy()

    # ------------------------------------------------------------------ IMU
    def body_biases(self) -> tuple[np.ndarray, np.ndarray]:
        """(gyro bias, accel bias) rotated into the body frame (what the preintegration uses)."""
        if self._imu_identity:
            return self.bg.copy(), self.ba.copy()
        return self.R_body_imu @ self.bg, self.R_body_imu @ self.ba

    def propagate(self, dR, dpv, J, T: float) -> None:
        """Propagate over a chunk of preintegrated IMU (see :mod:`graphcal.locomotion.imu`).

        Args:
            dR: (3, 3) zero-bias preintegrated rotation of the chunk.
            dpv: (6,) zero-bias preintegrated position (m) and velocity (m/s) changes [dp, dv],
                body frame at the chunk start.
            J: (6, 6) Jacobian of [dp, dv] w.r.t. the body-frame biases [b_g, b_a]
                (``[[Jpg, Jpa], [Jvg, Jva]]``).
            T: chunk length, s.

        The nominal state takes the chunk with the current biases (dR Exp(-b_g T), dpv + J b);
        the covariance takes one step over it through filterpy's ``predict`` with its F =
        d(error after)/d(error before) below and Q = Qc T (the error state stays zero: F 0 = 0).
        """
        xn = self._xn
        b = xn[6:12] if self._imu_identity else self._Rbi6 @ xn[6:12]
        RD = self.R @ (dpv + J @ b).reshape(2, 3).T  # columns: R dp_c, R dv_c
        g = GRAVITY_WORLD
        xn[0:3] += self.v * T + (0.5 * T * T) * g + RD[:, 0]
        xn[3:6] += g * T + RD[:, 1]
        dRc = dR @ so3_exp(-T * b[:3])
        R = self.R
        self.R = R @ dRc
        kf = self.kf
        F = kf.F
        F[0, 3] = F[1, 4] = F[2, 5] = T
        Sk = self._Sk2  # skew(-R dp_c), skew(-R dv_c): -R [d]x = -[R d]x R
        Sk[:, self._sk_i, self._sk_j] = -RD.T[:, self._sk_k] * self._sk_sign
        F[0:6, 6:9] = (Sk @ R).reshape(6, 3)
        F[6:9, 6:9] = dRc.T
        if self._imu_identity:
            F[0:6, 9:15] = (R @ J.reshape(2, 3, 6)).reshape(6, 6)
            F[6, 9] = F[7, 10] = F[8, 11] = -T
        else:
            F[0:6, 9:15] = (R @ (J @ self._Rbi6).reshape(2, 3, 6)).reshape(6, 6)
            F[6:9, 9:12] = -T * self.R_body_imu
        if self._Qdiag is not None:
            np.fill_diagonal(kf.Q, self._Qdiag * T)
        else:
            kf.Q = self.Qc * T
        kf.predict()

    # ------------------------------------------------------------------ kinematics
    def foot_covariance(self, J: np.ndarray) -> np.ndarray:
        """(3, 3) covariance of a foot position from kinematics with leg Jacobian J (3, n)."""
        return J @ self.encoder_cov @ J.T + self.kinematic_cov

    def reset_feet(self, feet: tuple, p_body_foot: np.ndarray, R_meas: np.ndarray) -> None:
        """Start tracking ``feet`` (names) at the measured p_body_foot (n_slots, 3) m with
        measurement covariance R_meas (3 n_slots, 3 n_slots): p_world_foot = p + R p_body_foot."""
        n = self.n_slots
        P = self.kf.P
        fs = self._fs
        P[fs, :] = 0.0
        P[:, fs] = 0.0
        G = np.zeros((3 * n, self.dim))
        for i in range(n):
            z = p_body_foot[i]
            self.p_feet[i] = self.p + self.R @ z
            G[3 * i : 3 * i + 3, 0:3] = np.eye(3)
            G[3 * i : 3 * i + 3, 6:9] = -self.R @ skew(z)
        GP = G @ P
        Gz = np.kron(np.eye(n), self.R)
        Rz = Gz @ R_meas @ Gz.T
        P[fs, :] = GP
        P[:, fs] = GP.T
        P[fs, fs] = GP @ G.T + Rz
        self.feet = tuple(feet)

    def reset_slots(self, slots, p_body_foot: np.ndarray, R_meas: np.ndarray) -> None:
        """Start tracking new feet in some ``slots`` (indices) only (a foot touching down while the
        others stay planted): p_world_foot = p + R p_body_foot for p_body_foot (k, 3) m with
        measurement covariance R_meas (3 k, 3 k); the other slots keep their estimates."""
        slots = np.asarray(slots, dtype=np.int64)
        k = len(slots)
        P = self.kf.P
        fs = (15 + 3 * slots[:, None] + np.arange(3)[None]).ravel()
        P[fs, :] = 0.0
        P[:, fs] = 0.0
        G = np.zeros((3 * k, self.dim))
        for i, s in enumerate(slots):
            z = p_body_foot[i]
            self.p_feet[s] = self.p + self.R @ z
            G[3 * i : 3 * i + 3, 0:3] = np.eye(3)
            G[3 * i : 3 * i + 3, 6:9] = -self.R @ skew(z)
        GP = G @ P
        Gz = np.kron(np.eye(k), self.R)
        P[fs, :] = GP
        P[:, fs] = GP.T
        P[np.ix_(fs, fs)] = GP @ G.T + Gz @ R_meas @ Gz.T

    def stance_prediction(self, dx: np.ndarray, rows=None) -> np.ndarray:
        """filterpy's ``Hx`` of the stance update: h = R^T (p_world_foot - p) (3 n_slots,) m of the
        tracked feet (``rows`` of them), at the nominal state (``dx``, filterpy's error state, is
        zero before an update)."""
        h = ((self.p_feet - self.p) @ self.R).ravel()  # rows: R^T (p_world_foot - p)
        return h if rows is None else h[rows]

    def stance_jacobian(self, dx: np.ndarray, rows=None) -> np.ndarray:
        """filterpy's ``HJacobian`` of the stance update: dh/d(error state) (3 n_slots, D) at the
        nominal state (``rows`` of it): -R^T for dp, [h]x for dtheta, R^T for the foot's dp_foot."""
        RT = self.R.T
        h = (self.p_feet - self.p) @ self.R
        H, H3 = self._H, self._H3
        H3[:, :, 0:3] = -RT
        Sk = self._Sk
        Sk[:, self._sk_i, self._sk_j] = h[:, self._sk_k] * self._sk_sign
        H3[:, :, 6:9] = Sk
        H[self._foot_rows, self._foot_cols] = RT.ravel()[self._foot_src]
        return H if rows is None else H[rows]

    def update_stance(self, p_body_foot: np.ndarray, R_meas: np.ndarray, slots=None) -> float:
        """Stance update with the measured p_body_foot (n_slots, 3) m of the tracked feet (same
        order as :meth:`reset_feet`), covariance R_meas (3 n_slots, 3 n_slots) m^2. With ``slots``
        (indices) only those feet are measured: p_body_foot (k, 3), R_meas (3 k, 3 k) of them.
        Returns the NIS."""
        rows = None
        if slots is not None:
            rows = (3 * np.asarray(slots, dtype=np.int64)[:, None] + np.arange(3)[None]).ravel()
        z = np.asarray(p_body_foot, dtype=float).ravel()
        m = 3 * self.n_slots if rows is None else len(rows)
        if z.shape != (m,) or np.shape(R_meas) != (m, m):
            raise GraphcalError(f"update_stance: expected p_body_foot ({m // 3}, 3) and R_meas ({m}, {m}), got "
                                f"{np.shape(p_body_foot)} and {np.shape(R_meas)}")
        return self._update(z, self.stance_jacobian, self.stance_prediction, R_meas, args=(rows,), hx_args=(rows,))

    # ------------------------------------------------------------------ level floor, zero velocity
    def update_floor(self, slots, z_floor_m: float, var_m2: float) -> float:
        """Level-ground update of the feet in ``slots`` (indices; just touched down): their world
        height ``p_world_foot_z`` measured as ``z_floor_m`` (m) with variance ``var_m2`` (m^2) each.
        Returns the NIS (dof = len(slots))."""
        slots = np.asarray(slots, dtype=np.int64)
        cols = 15 + 3 * slots + 2
        H = np.zeros((len(slots), self.dim))
        H[np.arange(len(slots)), cols] = 1.0
        z = np.full(len(slots), float(z_floor_m))
        return self._update(z, lambda dx: H, lambda dx: self.p_feet[slots, 2].copy(),
                            np.eye(len(slots)) * float(var_m2))

    def update_zero_velocity(self, var_m2_s2: float) -> float:
        """Zero-velocity update (the body at rest, e.g. lying on its belly): ``v_world_body`` = 0
        with variance ``var_m2_s2`` (m^2/s^2) per axis. Returns the NIS (dof 3)."""
        H = np.zeros((3, self.dim))
        H[:, 3:6] = np.eye(3)
        return self._update(np.zeros(3), lambda dx: H, lambda dx: self.v.copy(), np.eye(3) * float(var_m2_s2))

    # ------------------------------------------------------------------ relative pose (ICP)
    def clone_pose(self) -> None:
        """Make the current body pose the keyframe clone (with its covariance)."""
        P = self.kf.P
        c = self._c
        src = np.r_[0:3, 6:9]
        dst = np.arange(c, c + 6)
        P[dst, :] = P[src, :]
        P[:, dst] = P[:, src]
        P[np.ix_(dst, dst)] = P[np.ix_(src, src)]
        self.p_c = self.p.copy()
        self.R_c = self.R.copy()
        self.has_clone = True

    def predicted_relative_pose(self, dx: np.ndarray | None = None) -> np.ndarray:
        """(4, 4) T_keyframebody_body = T_c^-1 T from the current estimate (the nominal state; as
        filterpy's ``Hx`` of the relative-pose update ``dx`` is its zero error state)."""
        T = np.eye(4)
        T[:3, :3] = self.R_c.T @ self.R
        T[:3, 3] = self.R_c.T @ (self.p - self.p_c)
        return T

    def relative_pose_jacobian(self, dx: np.ndarray, A: np.ndarray) -> np.ndarray:
        """filterpy's ``HJacobian`` of the relative-pose update: d(A xi)/d(error state) (k, D) at the
        nominal state, xi the right perturbation [omega, v] of T_c^-1 T (clone and current pose)."""
        dR_hat = self.R_c.T @ self.R
        dt_hat = self.R_c.T @ (self.p - self.p_c)
        c = self._c
        Hx = np.zeros((6, self.dim))
        Hx[0:3, 6:9] = np.eye(3)
        Hx[0:3, c + 3 : c + 6] = -dR_hat.T
        Hx[3:6, 0:3] = dR_hat.T @ self.R_c.T
        Hx[3:6, c : c + 3] = -dR_hat.T @ self.R_c.T
        Hx[3:6, c + 3 : c + 6] = dR_hat.T @ skew(dt_hat)
        return A @ Hx

    def update_relative_pose(self, T_meas: np.ndarray, A: np.ndarray, cov: np.ndarray, *,
                             gate_chi2: float | None = None) -> tuple[float, bool]:
        """Fuse a measured T_keyframebody_body (4, 4) in the directions it constrains.

        Args:
            T_meas: measured relative pose T_c^-1 T (body frames, m).
            A: (k, 6) measured combinations of the right perturbation xi = [omega, v] of the
                relative pose: z = A xi with T_true = T_meas Exp(-xi).
            cov: (k, k) covariance of z (rad^2, rad m, m^2).
            gate_chi2: reject the measurement (no update) when its NIS exceeds this.

        Returns:
            (NIS, fused).
        """
        if not self.has_clone:
            raise GraphcalError("update_relative_pose: no keyframe clone (call clone_pose first)")
        A = np.atleast_2d(np.asarray(A, dtype=float))
        k = A.shape[0]
        if A.shape[1] != 6 or k == 0:
            raise GraphcalError(f"update_relative_pose: A must have shape (k, 6), k >= 1, got {A.shape}")
        cov = check_covariance("relative-pose covariance", cov, k, definite=True)
        T_meas = _as_matrix("T_meas", T_meas, (4, 4))
        residual = functools.partial(relative_pose_residual, A)
        if gate_chi2 is not None:
            y0 = residual(T_meas, self.predicted_relative_pose())
            H = self.relative_pose_jacobian(self.kf.x, A)
            nis0 = float(y0 @ np.linalg.solve(H @ self.kf.P @ H.T + cov, y0))
            if nis0 > gate_chi2:
                self.last_nis = nis0
                return nis0, False
        return self._update(T_meas, self.relative_pose_jacobian, self.predicted_relative_pose, cov, args=(A,),
                            residual=residual), True

    # ------------------------------------------------------------------ common
    def _update(self, z, HJacobian, Hx, R, *, args=(), hx_args=(), residual=np.subtract) -> float:
        """filterpy's ``update`` of the error state (gain, Joseph-form covariance; its ``y``, ``S``,
        ``SI``, ``K`` kept), then graphcal's part: the error injected into the nominal state and
        reset to zero. Returns the NIS ``y^T S^-1 y``."""
        kf = self.kf
        kf.update(z, HJacobian, Hx, R=R, args=args, hx_args=hx_args, residual=residual)
        y = kf.y
        nis = float(y @ kf.SI @ y)
        self.last_innovation = y
        self.last_S = kf.S
        self.last_nis = nis
        self._inject(kf.x)
        kf.x = np.zeros(self.dim)
        return nis

    def _inject(self, dx: np.ndarray) -> None:
        """The error ``dx`` (D,) into the nominal state: p, v, biases, feet, clone position add; R and
        R_c take Exp of their dtheta on the right."""
        self._xn += dx[self._xn_idx]
        self.R = self.R @ so3_exp(dx[6:9])
        self.p_feet += dx[self._fs].reshape(self.n_slots, 3)
        if self.has_clone:
            c = self._c
            self.p_c = self.p_c + dx[c : c + 3]
            self.R_c = self.R_c @ so3_exp(dx[c + 3 : c + 6])

    def renormalize(self) -> None:
        """Re-orthonormalise R (call now and then: rounding accumulates over many steps)."""
        self.R = nearest_rotation(self.R)
