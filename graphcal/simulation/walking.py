"""Simulated walking: the Qingzhui hexapod (Zhao 2020) in the alternating tripod gait, on level
ground (``tripod-walk``) or up and down three 130 x 300 mm stairs (``tripod-stairs``); the a1
quadruped in a trot (``trot``: diagonal pairs) or a walk (``walk``: one foot at a time) on level
ground, with foot-force sensors (:data:`GAITS`).

What is simulated, all vectorised over the samples (numpy, one loop over the legs and the steps):

* **Body trajectory** (the truth): a smooth path (C2; speed ramps with quintic smoothsteps) at
  the body height above the ground, with a small vertical bob, roll sway and pitch nod at the step
  frequency. On level ground the path weaves (heading ``A sin(2 pi s / lambda)``), so the yaw
  changes; on the stairs it runs straight along +x and the body stays parallel to the least-squares ground
  line under its nominal feet (smoothed), at its standing height above it less the depth of the
  lowest foot's ground below that line (pitch like Zhao's Fig. 9b).
* **Standing up and lying down** (optional, ``stand_up_s`` / ``lie_down_s``): the robot starts on
  its belly at ``lying_height_m`` with its feet on the ground at their first footholds carrying
  ``lying_load_fraction`` of its weight, the legs take the load, the body rises to its standing
  height; at the end the reverse. Feet stay planted; the IMU, the truth and the foot forces
  follow the body's height (forces: the legs' share of ``m (a - g)``).
* **Gait** (Zhao Fig. 4): group A = mf, rb, lb; group B = mb, rf, lf, half a cycle apart, duty
  factor ``duty_factor`` > 0.5 (a short six-foot support at each switch). The quadruped programs
  give each foot its phase offset (:class:`GaitSpec`). Each foothold is the
  foot's nominal stance under the body pose at the middle of its stance, dropped vertically onto
  the terrain, and on stairs at least ``edge_margin_m`` from every stair edge. Feet are planted exactly
  during stance. A swing rises to ``swing_clearance_m`` above the highest ground between lift-off and
  touch-down while it starts moving forward, crosses, and lowers (blended quintic smoothsteps; the
  clearance above the ground along the swing is checked).
* **Joint angles**: inverse kinematics (:func:`graphcal.models.kinematics.ik_leg`) of the foot
  positions in the body frame, solved every 10th sample, spline-interpolated and refined at every
  sample (residual < 1e-9 m); encoder noise ``encoder_sigma_rad`` (white).
* **Joint torques**: quasi-static force distribution. The ground reaction forces carry
  ``m (a - g)`` with zero moment about the body origin (the centre of mass): the weighted
  minimum-norm solution over the feet in contact, the weight of a foot ramping from 0 at
  touch-down to 1 over the double-support time and back to 0 at lift-off (smooth load transfer;
  legs massless). tau = J^T f, with f the force the foot exerts on the ground (body frame) and J
  the leg's position Jacobian (body frame); white noise ``torque_sigma_nm``. The quadruped programs
  share the reaction by weight only (a trot's diagonal pair cannot hold a moment quasi-statically)
  and read foot-force sensors: the load along the body's -z axis plus white noise
  ``force_sigma_n`` (``force_<foot>`` columns, N).
* **IMU** at every sample: gyro = R_world_imu^T-frame angular rate + bias + white noise; accel =
  specific force ``R_world_imu^T (a_imu - g)`` (g = (0, 0, -9.80665) m/s^2) + bias + white
  noise; biases start from a random draw and follow a random walk. Continuous-time densities:
  white noise sigma per sample = density * sqrt(rate); random walk step = density * sqrt(dt).
* **Depth clouds** at ``cloud_rate_hz`` from the robot's depth camera (Kinect model of
  :mod:`graphcal.models.sensors`, every ``cloud_stride``-th pixel row and column), ray cast
  into the terrain (not the robot's own legs) from ``T_world_body @ T_body_sensor`` (the CAD
  extrinsic is the true one here). Default stride 16 on level ground, 8 on the stairs.

The stairs are :func:`graphcal.simulation.terrain.up_and_down_stairs`. The walk as a dataset
(``timeseries.csv``, the clouds, ``truth.yaml`` and ``truth_trajectory.csv``, which only evaluations
read): :func:`graphcal.simulation.write.write_walking`.

Units: SI (m, rad, s, N, N m, m/s^2, rad/s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.geometry import body_rates_from_rpy_rates, matrix_from_rpy, skew_batch
from graphcal.simulation.terrain import Terrain, make_terrain, stair_edges, stair_profile, up_and_down_stairs

__all__ = [
    "WALKING_PROGRAMS",
    "GRAVITY_M_S2",
    "WalkingConfig",
    "WalkingResult",
    "simulate_walking",
]

WALKING_PROGRAMS = ("tripod-walk", "tripod-stairs", "trot", "walk")


@dataclass(frozen=True)
class GaitSpec:
    """A walking program's gait: the robot it walks and when each foot swings.

    Attributes:
        robot: the built-in model the program walks.
        phase_offsets: foot -> offset (cycles) of its gait phase: the foot swings while
            ``mod(phase + offset, 1) < 1 - duty_factor`` (phase in cycles since the gait starts).
            None: the model's two tripod ``gait_groups``, half a cycle apart (offsets 0 and 0.5).
        speed_m_s, cycle_s, duty_factor, body_mass_kg: the program's defaults (m/s, s, fraction of
            the cycle on the ground, kg).
        ramp_cycles: load transfer time at touchdown and lift-off, in cycles; None: the double
            support of a two-group gait (``duty_factor - 0.5``).
        force_sensors: the feet carry force sensors (``force_<foot>`` columns, N); their forces
            are spread over the feet in contact by load weight only (no moment balance: a trot's
            two feet cannot balance one); without, the zero-moment quasi-static distribution.
    """

    robot: str
    phase_offsets: dict | None = None
    speed_m_s: float = 0.4
    cycle_s: float = 0.9
    duty_factor: float = 0.55
    ramp_cycles: float | None = None
    force_sensors: bool = False
    body_mass_kg: float = 40.0


#: the gait of each walking program (tripods: Zhao 2020; quadruped trot: diagonal pairs half a cycle
#: apart; quadruped walk: the lateral sequence rl, fl, rr, fr a quarter cycle apart, 3-4 feet down)
GAITS = {
    "tripod-walk": GaitSpec("qingzhui"),
    "tripod-stairs": GaitSpec("qingzhui", speed_m_s=0.25, cycle_s=1.2),
    "trot": GaitSpec("a1", {"fl_foot": 0.0, "rr_foot": 0.0, "fr_foot": 0.5, "rl_foot": 0.5},
                     speed_m_s=0.5, cycle_s=0.5, duty_factor=0.6, ramp_cycles=0.05, force_sensors=True,
                     body_mass_kg=12.0),
    "walk": GaitSpec("a1", {"rl_foot": 0.0, "fl_foot": 0.25, "rr_foot": 0.5, "fr_foot": 0.75},
                     speed_m_s=0.25, cycle_s=0.8, duty_factor=0.8, ramp_cycles=0.05, force_sensors=True,
                     body_mass_kg=12.0),
}
GRAVITY_M_S2 = 9.80665
_G_WORLD = np.array([0.0, 0.0, -GRAVITY_M_S2])
#: On stairs the body is lowered by this fraction of the depth of the lowest foot's ground below
#: the ground line (chosen: the legs of the model keep >= 1.5 cm reach and 0.05 rad abduction margin).
_K_BELOW = 0.3
#: Swing profile (fractions of the swing time): lift during [0, _LIFT], horizontal transfer during
#: [_ACROSS0, 1 - _ACROSS0], lowering during [1 - _LIFT, 1] (quintic smoothsteps, blended).
_LIFT = 0.3
_ACROSS0 = 0.15


@dataclass(frozen=True)
class WalkingConfig:
    """What to simulate. SI units; ``None`` means the program's default.

    Attributes:
        program: ``tripod-walk`` (level ground, weaving path) or ``tripod-stairs`` (straight up
            three stairs, over a 1.5 m landing, down three stairs, level run-out) of the qingzhui;
            ``trot`` or ``walk`` of the a1 quadruped on level ground (weaving path; :data:`GAITS`).
        robot: the program's built-in model (:data:`GAITS`; None: that one, another is refused).
        seed: every random draw derives from it.
        distance_m: body path length (m). Level default 20; stairs default: from the start to
            1.2 m past the last stair edge.
        duration_s: if given (level walk only), the path length is chosen so that the walk lasts
            about this long (s), overriding ``distance_m``.
        speed_m_s: cruise speed (m/s); default 0.4 level, 0.25 stairs, 0.5 trot, 0.25 walk.
        cycle_s: gait cycle period (s); default 0.9 level, 1.2 stairs (stride = speed * cycle:
            0.3 m = one tread on the stairs), 0.5 trot, 0.8 walk.
        duty_factor: fraction of the cycle a foot is on the ground (0.5 < beta < 0.9); default
            0.55 tripods, 0.6 trot, 0.8 walk.
        rate_hz: sample rate of joints, torques and IMU (Hz).
        cloud_rate_hz: depth-cloud rate (Hz); 0 = no clouds.
        cloud_stride: keep every k-th camera pixel row and column; default 16 (40 x 30 rays) on
            level ground, 8 (80 x 60) on the stairs (the stairs model needs the denser clouds).
        still_s: the robot stands still this long at the start and at the end (s).
        ramp_s: speed ramp-up and ramp-down time (s).
        weave_amplitude_rad, weave_wavelength_m: heading A sin(2 pi s / lambda) on level ground.
        bob_m, sway_rad, nod_rad: body oscillation amplitudes (vertical, roll, pitch) at full speed.
        body_height_m: standing height of the body origin above the ground (m); default: the
            model's (0.45 m), 0.03 m less on the stairs (the legs need the reach there).
        stairs_start_x_m: x of the first riser (m).
        edge_margin_m: footholds stay this far (along x) from every stair edge (m).
        swing_clearance_m: swing height above the highest ground under the swing (m).
        body_mass_kg: mass carried by the legs (chosen; Zhao gives none): default 40 qingzhui, 12 a1.
        encoder_sigma_rad: joint encoder noise (white, per sample).
        torque_sigma_nm: joint torque sensor noise (white, per sample).
        gyro_noise_density, accel_noise_density: IMU white noise, rad/s/sqrt(Hz) and m/s^2/sqrt(Hz).
        gyro_bias_rw, accel_bias_rw: bias random walks, rad/s^2/sqrt(Hz) and m/s^3/sqrt(Hz).
        gyro_bias_sigma_rad_s, accel_bias_sigma_m_s2: spread of the initial biases.
        truth_rate_hz: rate of ``truth_trajectory.csv``.
        force_sigma_n: foot-force sensor noise (white, per sample, N; programs with force sensors).
        imu_xyz_m: the IMU's position in the body frame (m; None: the model's), as on a robot whose
            IMU board sits off the base link.
        joint_offset_sigma_rad: a constant zero offset per joint encoder, drawn with this spread
            (rad; 0: none) from its own generator (the other draws are unchanged): the kinematic
            error a real robot's joint calibration leaves.
        stand_up_s: > 0: the robot starts on its belly (``lying_s`` s at ``lying_height_m``, the feet
            on the ground carrying ``lying_load_fraction`` of its weight, the belly the rest) and
            stands up over this long (s) before its first ``still_s``: the legs take the load over
            the first fifth, the body rises to ``body_height_m`` over the rest (quintic
            smoothsteps). 0 (default): it starts standing.
        lie_down_s: > 0: after its last ``still_s`` the robot lies down over this long (s) -- the
            body lowers over the first four fifths, the legs unload over the last fifth -- and lies
            ``lying_s`` s. 0 (default): it ends standing.
        lying_s: time on the belly before standing up and after lying down (s).
        lying_height_m: body origin height on the belly (m); default 0.4 x ``body_height_m``
            (a1 0.112 m: the folded leg keeps 0.17 rad from its knee limit).
        lying_load_fraction: share of the weight the feet carry while lying (the belly the rest).
        cad_error_m, cad_error_rad: the depth camera's CAD prior (dataset.yaml) is its true pose
            moved by a draw of this spread per axis (m; rad, about the sensor's own axes) from its
            own generator (the other draws are unchanged); 0: the prior is the truth.
        camera_delay_s: every depth cloud is stamped this late (s >= 0): the cloud captured at
            sample k is written on the row ``round(camera_delay_s * rate_hz)`` samples later.
    """

    program: str = "tripod-walk"
    robot: str | None = None
    seed: int = 0
    distance_m: float | None = None
    duration_s: float | None = None
    speed_m_s: float | None = None
    cycle_s: float | None = None
    duty_factor: float | None = None
    rate_hz: float = 1000.0
    cloud_rate_hz: float = 30.0
    cloud_stride: int | None = None
    still_s: float = 1.0
    ramp_s: float = 1.0
    weave_amplitude_rad: float = 0.25
    weave_wavelength_m: float = 8.0
    bob_m: float = 0.005
    sway_rad: float = float(np.radians(1.0))
    nod_rad: float = float(np.radians(0.5))
    body_height_m: float | None = None
    stairs_start_x_m: float = 1.6
    edge_margin_m: float = 0.05
    swing_clearance_m: float = 0.06
    body_mass_kg: float | None = None
    encoder_sigma_rad: float = float(np.radians(0.02))
    torque_sigma_nm: float = 0.5
    gyro_noise_density: float = 2.5e-4
    accel_noise_density: float = 1.5e-3
    gyro_bias_rw: float = 1e-5
    accel_bias_rw: float = 1e-4
    gyro_bias_sigma_rad_s: float = 1e-3
    accel_bias_sigma_m_s2: float = 0.02
    truth_rate_hz: float = 100.0
    force_sigma_n: float = 2.0
    stand_up_s: float = 0.0
    lie_down_s: float = 0.0
    lying_s: float = 1.0
    lying_height_m: float | None = None
    lying_load_fraction: float = 0.1
    imu_xyz_m: tuple | None = None
    joint_offset_sigma_rad: float = 0.0
    cad_error_m: float = 0.0
    cad_error_rad: float = 0.0
    camera_delay_s: float = 0.0

    @property
    def posture_s(self) -> tuple[float, float]:
        """(before, after) the walk's standing time: lying plus standing up, lying down plus lying (s)."""
        return (self.lying_s + self.stand_up_s if self.stand_up_s > 0 else 0.0,
                self.lie_down_s + self.lying_s if self.lie_down_s > 0 else 0.0)

    @property
    def gait(self) -> GaitSpec:
        """The program's :class:`GaitSpec`."""
        return GAITS[self.program]

    @property
    def stairs(self) -> bool:
        return self.program == "tripod-stairs"

    def resolved(self) -> "WalkingConfig":
        """The configuration with every program default filled in (and checked)."""
        if self.program not in WALKING_PROGRAMS:
            raise GraphcalError(f"unknown walking program {self.program!r}; expected one of "
                                f"{', '.join(WALKING_PROGRAMS)}")
        st = self.stairs
        gait = self.gait
        if self.robot is not None and self.robot != gait.robot:
            raise GraphcalError(f"walking program {self.program} walks the {gait.robot}, not {self.robot!r}")
        c = replace(
            self,
            robot=gait.robot,
            speed_m_s=self.speed_m_s if self.speed_m_s is not None else gait.speed_m_s,
            cycle_s=self.cycle_s if self.cycle_s is not None else gait.cycle_s,
            duty_factor=self.duty_factor if self.duty_factor is not None else gait.duty_factor,
            body_mass_kg=self.body_mass_kg if self.body_mass_kg is not None else gait.body_mass_kg,
            cloud_stride=self.cloud_stride if self.cloud_stride is not None else (8 if st else 16),
        )
        if c.distance_m is None:
            if st:
                dist = c.stairs_start_x_m + 2.7 + 1.2
            elif c.duration_s is not None:
                dist = c.speed_m_s * (c.duration_s - 2 * c.still_s - c.ramp_s - c.cycle_s)
                if c.stand_up_s > 0 or c.lie_down_s > 0:
                    dist -= c.speed_m_s * sum(c.posture_s)
            else:
                dist = 20.0
            c = replace(c, distance_m=float(dist))
        elif c.duration_s is not None and not st:
            raise GraphcalError("give distance_m or duration_s for a walk, not both")
        checks = [
            (c.rate_hz > 0, "rate_hz must be > 0"),
            (c.cloud_rate_hz >= 0, "cloud_rate_hz must be >= 0"),
            (c.cloud_rate_hz <= c.rate_hz, "cloud_rate_hz must not exceed rate_hz"),
            (c.cloud_stride >= 1, "cloud_stride must be >= 1"),
            (0.5 < c.duty_factor < 0.9, "duty_factor must be in (0.5, 0.9)"),
            (c.speed_m_s > 0 and c.cycle_s > 0, "speed_m_s and cycle_s must be > 0"),
            (c.distance_m >= c.speed_m_s * c.ramp_s,
             (f"duration_s {c.duration_s:g} s is too short for a walk: it needs at least "
              f"{2 * c.still_s + 2 * c.ramp_s + c.cycle_s:g} s (standing still {c.still_s:g} s at each end, "
              f"speed ramps of {c.ramp_s:g} s, a gait cycle of {c.cycle_s:g} s)"
              if c.duration_s is not None and not st else
              f"the path ({c.distance_m:.2f} m) is shorter than the speed ramps "
              f"({c.speed_m_s * c.ramp_s:.2f} m): walk further or longer")),
            (c.still_s >= 0 and c.ramp_s > 0, "still_s must be >= 0 and ramp_s > 0"),
            (c.stand_up_s >= 0 and c.lie_down_s >= 0 and c.lying_s >= 0,
             "stand_up_s, lie_down_s and lying_s must be >= 0"),
            (0.0 <= c.lying_load_fraction < 1.0, "lying_load_fraction must be in [0, 1)"),
            (c.lying_height_m is None or c.lying_height_m > 0, "lying_height_m must be > 0"),
            (c.cad_error_m >= 0 and c.cad_error_rad >= 0, "cad_error_m and cad_error_rad must be >= 0"),
            (0.0 <= c.camera_delay_s <= 1.0, "camera_delay_s must be in [0, 1] s"),
        ]
        if st:
            checks.append((c.distance_m >= c.stairs_start_x_m + 2.7 + 0.9,
                           f"the stairs walk must end at least 0.9 m past the last stair edge "
                           f"(distance_m >= {c.stairs_start_x_m + 3.6:.2f} m)"))
        for ok, msg in checks:
            if not ok:
                raise GraphcalError(f"walking simulation: {msg}")
        return c


@dataclass(frozen=True, eq=False)
class WalkingResult:
    """A simulated walk: measurements and the truth they hide (arrays over the N samples).

    Attributes:
        config: the resolved configuration.
        robot: the :class:`~graphcal.models.robot.RobotModel`; ``info``: its BuiltinInfo.
        times: (N,) s.
        T_world_body: (N, 4, 4) true body poses, m.
        v_world_body: (N, 3) true body velocity in the world frame, m/s.
        feet: foot frame names (``robot.feet`` order); ``groups``: the two tripods (foot names).
        p_world_foot: (n_feet, N, 3) true foot positions, m.
        contact: (N, n_feet) bool, foot planted.
        q_true, q_measured: joint name -> (N,) rad.
        tau_measured: joint name -> (N,) N m.
        force_body_foot: (n_feet, N, 3) force each foot exerts on the ground, body frame, N.
        imu_accel, imu_gyro: (N, 3) measured specific force (m/s^2) and rate (rad/s), IMU frame.
        accel_bias, gyro_bias: (N, 3) true biases.
        T_body_imu, T_body_sensor: (4, 4) true IMU and depth-camera poses in the body frame.
        cloud_indices: (M,) sample index of each cloud; clouds: M arrays (K, 3), sensor frame, m.
        terrain: the :class:`~graphcal.simulation.terrain.Terrain` (meshes and treads).
        foot_force: (N, n_feet) measured foot loads (N: the force each foot exerts on the ground
            along the body's -z axis, plus noise), or None without foot-force sensors.
        T_body_sensor_cad: (4, 4) the depth camera's CAD prior (the truth unless
            ``config.cad_error_m`` / ``cad_error_rad``), or None (the truth).
    """

    config: WalkingConfig
    robot: object
    info: object
    times: np.ndarray
    T_world_body: np.ndarray
    v_world_body: np.ndarray
    feet: tuple
    groups: tuple
    p_world_foot: np.ndarray
    contact: np.ndarray
    q_true: dict
    q_measured: dict
    tau_measured: dict
    force_body_foot: np.ndarray
    imu_accel: np.ndarray
    imu_gyro: np.ndarray
    accel_bias: np.ndarray
    gyro_bias: np.ndarray
    T_body_imu: np.ndarray
    T_body_sensor: np.ndarray
    cloud_indices: np.ndarray
    clouds: list = field(default_factory=list)
    terrain: Terrain | None = None
    foot_force: np.ndarray | None = None
    T_body_sensor_cad: np.ndarray | None = None

    @property
    def distance_m(self) -> float:
        """Length of the true body path, m."""
        return float(np.linalg.norm(np.diff(self.T_world_body[:, :3, 3], axis=0), axis=1).sum())


# ----------------------------------------------------------------------------- small helpers
def _cumtrapz(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    out = np.zeros_like(y, dtype=float)
    out[1:] = np.cumsum(0.5 * (y[1:] + y[:-1]) * np.diff(x))
    return out


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) index ranges where ``mask`` is True."""
    m = np.r_[False, mask, False].astype(np.int8)
    d = np.diff(m)
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def _nominal_q(leg, p_body_foot) -> np.ndarray:
    from graphcal.models.kinematics import ik_leg

    lo = np.where(np.isfinite(leg.lower), leg.lower, -np.pi)
    hi = np.where(np.isfinite(leg.upper), leg.upper, np.pi)
    starts = np.vstack([np.zeros(leg.n_joints), (lo + hi) / 2,
                        [0.0, 0.5, 1.0][: leg.n_joints] + np.zeros(leg.n_joints)])
    q, ok = ik_leg(leg, np.repeat(np.asarray(p_body_foot)[None], len(starts), axis=0), starts)
    inside = ok & np.all((q >= lo - 1e-9) & (q <= hi + 1e-9), axis=1)
    if not inside.any():
        raise GraphcalError(f"foot {leg.foot} cannot reach its nominal stance")
    return q[int(np.argmax(inside))]


# ----------------------------------------------------------------------------- the walk, stage by stage
@dataclass(frozen=True, eq=False)
class _Timeline:
    """Still, ramp up, cruise, ramp down, (gait finishes), still: the sample times ``t`` (N,) s at
    interval ``dt`` s, the gait's start and end ``t_g0``, ``t_g1`` s, the forward speed ``v`` (N,)
    m/s, the distance walked ``s`` (N,) m, ``gain`` = v / the cruise speed and the gait ``phase``
    (N,) in cycles; ``h0`` the nominal body height, m."""

    t: np.ndarray
    dt: float
    t_g0: float
    t_g1: float
    v: np.ndarray
    s: np.ndarray
    gain: np.ndarray
    phase: np.ndarray
    h0: float
    posture: "_Posture | None" = None


@dataclass(frozen=True, eq=False)
class _Posture:
    """Standing up and lying down (WalkingConfig's ``stand_up_s``, ``lie_down_s``): per sample the
    body's ``rise`` (N,) from its lying height (0) to its standing height (1), the ``legs_share``
    (N,) of the weight the feet carry (the belly the rest), and the lying height ``h_lie`` (m)."""

    rise: np.ndarray
    legs_share: np.ndarray
    h_lie: float


#: the part of a stand-up (lie-down) in which the legs take (give up) the load, the body still on
#: its belly; the body rises (lowers) over the rest
_LOAD_PART = 0.2


def _posture(c: WalkingConfig, t: np.ndarray, t_g1: float, h0: float) -> _Posture | None:
    """The stand-up before the walk and the lie-down after it (None when neither is asked)."""
    from graphcal.models.kinematics import smoothstep

    if c.stand_up_s <= 0 and c.lie_down_s <= 0:
        return None
    rise = np.ones(len(t))
    load = np.ones(len(t))
    if c.stand_up_s > 0:
        u = (t - c.lying_s) / c.stand_up_s
        load *= smoothstep(u / _LOAD_PART, degree=5)
        rise *= smoothstep((u - _LOAD_PART) / (1 - _LOAD_PART), degree=5)
    if c.lie_down_s > 0:
        u = (t - t_g1 - c.still_s) / c.lie_down_s
        rise *= 1.0 - smoothstep(u / (1 - _LOAD_PART), degree=5)
        load *= 1.0 - smoothstep((u - 1 + _LOAD_PART) / _LOAD_PART, degree=5)
    h_lie = c.lying_height_m if c.lying_height_m is not None else 0.4 * h0
    share = c.lying_load_fraction + (1.0 - c.lying_load_fraction) * load
    return _Posture(rise, share, float(h_lie))


def _timeline(c: WalkingConfig, info) -> _Timeline:
    from graphcal.models.kinematics import smoothstep

    h0 = c.body_height_m if c.body_height_m is not None else info.default_body_height_m - (0.03 if c.stairs else 0.0)
    v_max, Tc, beta = c.speed_m_s, c.cycle_s, c.duty_factor
    dt = 1.0 / c.rate_hz
    t_cruise = c.distance_m / v_max - c.ramp_s
    pre, post = c.posture_s
    t_g0 = c.still_s + pre
    t_stop = t_g0 + 2 * c.ramp_s + t_cruise
    n_cycles = int(math.ceil((t_stop - t_g0) / Tc + beta))
    t_g1 = t_g0 + n_cycles * Tc
    t_end = t_g1 + c.still_s + post
    N = int(round(t_end * c.rate_hz)) + 1
    t = np.arange(N) * dt
    v = v_max * (smoothstep((t - t_g0) / c.ramp_s, degree=5)
                 - smoothstep((t - t_stop + c.ramp_s) / c.ramp_s, degree=5))
    s = _cumtrapz(v, t)
    gain = v / v_max
    phase = (t - t_g0) / Tc
    return _Timeline(t, dt, t_g0, t_g1, v, s, gain, phase, h0, _posture(c, t, t_g1, h0))


@dataclass(frozen=True, eq=False)
class _BodyPath:
    """The true body trajectory: ``roll``, ``pitch``, ``yaw`` (N,) rad, ``p`` (N, 3) m and ``R``
    (N, 3, 3) of T_world_body, the ``terrain`` and ``ground_stairs`` (the steps under the walk; empty
    on level ground)."""

    roll: np.ndarray
    pitch: np.ndarray
    yaw: np.ndarray
    p: np.ndarray
    R: np.ndarray
    terrain: Terrain
    ground_stairs: tuple

    @property
    def T_world_body(self) -> np.ndarray:
        """(N, 4, 4) body poses."""
        T_world_body = np.zeros((len(self.p), 4, 4))
        T_world_body[:, :3, :3] = self.R
        T_world_body[:, :3, 3] = self.p
        T_world_body[:, 3, 3] = 1.0
        return T_world_body


def _ground_height(stairs: tuple, xy: np.ndarray) -> np.ndarray:
    """Ground height (m) under world points ``xy`` (..., >= 2): the stairs' profile along x, 0 on
    level ground (no ``stairs``)."""
    if stairs:
        return stair_profile(stairs, xy[..., 0])
    return np.zeros(xy.shape[:-1])


def _stairs_height_and_pitch(c: WalkingConfig, info, feet: tuple, terrain: Terrain, x: np.ndarray, h0: float):
    """(z (N,) m without the bob, pitch (N,) rad without the nod) of the body walking up the stairs
    at world x (N,) m: the ground line under the nominal feet (least squares over their x offsets),
    smoothed: body pitch parallel to it, body height h0 above it (perpendicular), less the depth
    of the lowest foot's ground below the line."""
    from scipy.interpolate import CubicSpline
    from scipy.ndimage import gaussian_filter1d, maximum_filter1d

    res = 0.005
    xg = np.arange(-3.0, c.distance_m + 3.0, res)
    dxs = np.array([info.nominal_stance[f][0] for f in feet])
    dxs = dxs - dxs.mean()
    hg = stair_profile(terrain.stairs, xg[:, None] + dxs[None, :])
    a_raw = hg.mean(axis=1)
    b_raw = hg @ dxs / (dxs @ dxs)
    # lower the body by as much as a foot's ground lies below that line (no leg over-extends)
    below = np.max(a_raw[:, None] + b_raw[:, None] * dxs[None, :] - hg, axis=1)
    below = gaussian_filter1d(maximum_filter1d(below, size=int(0.3 / res)), 0.1 / res)
    a_g = gaussian_filter1d(a_raw, 0.1 / res)
    b_g = gaussian_filter1d(b_raw, 0.1 / res)
    A_s, B_s, D_s = CubicSpline(xg, a_g), CubicSpline(xg, b_g), CubicSpline(xg, below)
    slope = np.arctan(B_s(x))
    return A_s(x) + (h0 - _K_BELOW * D_s(x)) / np.cos(slope), -slope


def _body_path(c: WalkingConfig, info, feet: tuple, tl: _Timeline) -> _BodyPath:
    """The body trajectory: sway (roll), nod (pitch) and bob (z) with the gait; on stairs along x,
    following the ground line; on level ground weaving (yaw) along a sine."""
    N = len(tl.t)
    roll = c.sway_rad * tl.gain * np.sin(2 * np.pi * tl.phase)
    nod = c.nod_rad * tl.gain * np.sin(4 * np.pi * tl.phase + 0.3)
    bob = c.bob_m * tl.gain * np.sin(4 * np.pi * tl.phase)
    if c.stairs:
        terrain = up_and_down_stairs(c.stairs_start_x_m, extent_m=max(12.0, c.distance_m + 8.0))
        x = tl.s.copy()
        y = np.zeros(N)
        yaw = np.zeros(N)
        z, pitch = _stairs_height_and_pitch(c, info, feet, terrain, x, tl.h0)
        z = z + bob
        pitch = pitch + nod
        ground_stairs = tuple(terrain.stairs)
    else:
        terrain = make_terrain("level", extent_m=max(12.0, c.distance_m + 8.0))
        yaw = c.weave_amplitude_rad * np.sin(2 * np.pi * tl.s / c.weave_wavelength_m)
        x = _cumtrapz(np.cos(yaw), tl.s)
        y = _cumtrapz(np.sin(yaw), tl.s)
        z = tl.h0 + bob
        pitch = nod
        ground_stairs = ()
    if tl.posture is not None:  # on its belly before standing up and after lying down
        z = z + (tl.posture.h_lie - tl.h0) * (1.0 - tl.posture.rise)
    R = matrix_from_rpy(np.column_stack(np.broadcast_arrays(roll, pitch, yaw)))
    return _BodyPath(roll, pitch, yaw, np.c_[x, y, z], R, terrain, ground_stairs)


@dataclass(frozen=True, eq=False)
class _FootPlan:
    """Contacts and feet: ``contact`` (N, n_feet) bool, the feet's share of the body's weight
    ``weight`` (n_feet, N) (smooth ramps at touchdown and lift-off) and the true foot positions
    ``p_world_foot`` (n_feet, N, 3) m."""

    contact: np.ndarray
    weight: np.ndarray
    p_world_foot: np.ndarray


def _foothold_xy(c: WalkingConfig, body: _BodyPath, edges: np.ndarray, foot: str, xy: np.ndarray, z_nominal: float) -> np.ndarray:
    """Stairs: the foothold (x, y) m within +-8 cm along x of the nominal ``xy``, at least
    edge_margin_m from every edge, whose ground is nearest the nominal foot height (then nearest
    the nominal x)."""
    xy = xy.copy()
    cand = xy[0] + np.linspace(-0.08, 0.08, 33)
    ok = np.min(np.abs(cand[:, None] - edges[None, :]), axis=1) >= c.edge_margin_m - 1e-12
    if not ok.any():  # pragma: no cover - treads are 0.3 m deep
        raise GraphcalError(f"walking simulation: no foothold for {foot} near x = {xy[0]:.3f} m")
    cand = cand[ok]
    cost = np.abs(stair_profile(body.terrain.stairs, cand) - z_nominal) + 0.5 * np.abs(cand - xy[0])
    xy[0] = cand[int(np.argmin(cost))]
    return xy


def _swing_path(c: WalkingConfig, body: _BodyPath, t: np.ndarray, lo: int, td: int, A: np.ndarray,
                B: np.ndarray) -> np.ndarray:
    """(td - lo - 1, 3) world positions (m) of a foot swinging from hold A (lift-off after sample
    ``lo``) to hold B (touchdown at sample ``td``): lift, transfer, lower (quintic smoothsteps)
    ``swing_clearance_m`` above the holds and the ground between them."""
    from graphcal.models.kinematics import smoothstep

    ks = np.arange(lo + 1, td)
    u = (t[ks] - t[lo]) / (t[td] - t[lo])
    xs = np.linspace(0.0, 1.0, 25)[:, None] * (B[:2] - A[:2]) + A[:2]
    z_top = max(A[2], B[2], float(np.max(_ground_height(body.ground_stairs, xs)))) + c.swing_clearance_m
    up = smoothstep(u / _LIFT, degree=5)
    across = smoothstep((u - _ACROSS0) / (1 - 2 * _ACROSS0), degree=5)
    down = smoothstep((u - 1 + _LIFT) / _LIFT, degree=5)
    out = np.empty((len(ks), 3))
    out[:, :2] = A[:2] + across[:, None] * (B[:2] - A[:2])
    out[:, 2] = A[2] + up * (z_top - A[2]) + down * (B[2] - z_top)
    return out


def _foot_plan(c: WalkingConfig, info, feet: tuple, groups: tuple, tl: _Timeline, body: _BodyPath) -> _FootPlan:
    """Contacts (alternating tripods, duty factor ``c.duty_factor``), footholds (under the nominal
    stance at mid-stance; on stairs away from the edges) and swing paths between them."""
    from graphcal.models.kinematics import smoothstep

    t, h0 = tl.t, tl.h0
    N = len(t)
    Tc, beta = c.cycle_s, c.duty_factor
    p, R = body.p, body.R
    in_gait = (t >= tl.t_g0) & (t < tl.t_g1)
    offsets = c.gait.phase_offsets
    if offsets is None:  # two tripods half a cycle apart
        group_of = {f: gi for gi, g in enumerate(groups) for f in g}
        swing_group = [in_gait & (np.mod(tl.phase, 1.0) < 1.0 - beta),
                       in_gait & (np.mod(tl.phase + 0.5, 1.0) < 1.0 - beta)]
        swings = {f: swing_group[group_of[f]] for f in feet}
    else:
        swings = {f: in_gait & (np.mod(tl.phase + offsets[f], 1.0) < 1.0 - beta) for f in feet}
    edges = stair_edges(body.terrain.stairs) if c.stairs else np.zeros(0)
    nf = len(feet)
    contact = np.zeros((N, nf), dtype=bool)
    weight = np.zeros((nf, N))
    p_world_foot = np.zeros((nf, N, 3))
    ramp = c.gait.ramp_cycles if c.gait.ramp_cycles is not None else beta - 0.5
    ramp_n = max(1, int(round(ramp * Tc * c.rate_hz)))
    for i, f in enumerate(feet):
        stance = ~swings[f]
        contact[:, i] = stance
        nominal = np.asarray(info.nominal_stance[f], dtype=float)
        nominal = np.r_[nominal[:2], -h0]
        runs = _runs(stance)
        holds = []
        for j, (a, b) in enumerate(runs):
            k = 0 if a == 0 else (N - 1 if b == N else (a + b - 1) // 2)
            p_nom = p[k] + R[k] @ nominal
            xy = p_nom[:2].copy()
            if a > 0 and len(edges):
                xy = _foothold_xy(c, body, edges, f, xy, p_nom[2])
            hold = np.r_[xy, float(_ground_height(body.ground_stairs, xy[None])[0])]
            holds.append(hold)
            p_world_foot[i, a:b] = hold
            w = np.ones(b - a)
            idx = np.arange(b - a)
            if a > 0:
                w *= smoothstep(idx / ramp_n, degree=5)
            if b < N:
                w *= smoothstep((b - 1 - idx) / ramp_n, degree=5)
            weight[i, a:b] = w
        for j in range(len(runs) - 1):
            lo, td = runs[j][1] - 1, runs[j + 1][0]
            p_world_foot[i, lo + 1 : td] = _swing_path(c, body, t, lo, td, holds[j], holds[j + 1])
    # the swinging feet stay above the ground (stairs: also while crossing an edge)
    for i, f in enumerate(feet):
        sw = ~contact[:, i]
        if sw.any():
            gap = p_world_foot[i, sw, 2] - _ground_height(body.ground_stairs, p_world_foot[i, sw])
            if gap.min() < -1e-9:  # pragma: no cover - the swing profile is built to clear
                k = np.flatnonzero(sw)[int(np.argmin(gap))]
                raise GraphcalError(f"walking simulation: foot {f} swings through the ground at t = {t[k]:.3f} s")
    return _FootPlan(contact, weight, p_world_foot)


def _joint_angles(robot, info, feet: tuple, t: np.ndarray, p_body_foot: np.ndarray, h0: float):
    """Joint angles of every leg reaching its planned foot positions ``p_body_foot`` (n_feet, N, 3)
    m (body frame): IK every 10th sample (ik_leg), spline, Newton-refined at every sample. Returns
    (joint name -> (N,) rad, foot -> (N, n) rad, foot -> (N, 3, n) Jacobians); GraphcalError when a
    foot cannot reach or a joint leaves its limits."""
    from scipy.interpolate import CubicSpline

    from graphcal.models.kinematics import ik_leg, newton_ik

    N = len(t)
    q_true: dict[str, np.ndarray] = {}
    q_leg: dict[str, np.ndarray] = {}
    jac: dict[str, np.ndarray] = {}
    coarse = np.r_[np.arange(0, N, 10), N - 1] if (N - 1) % 10 else np.arange(0, N, 10)
    for i, f in enumerate(feet):
        leg = robot.leg(f)
        q_nom = _nominal_q(leg, np.r_[info.nominal_stance[f][:2], -h0])
        qc, ok = ik_leg(leg, p_body_foot[i, coarse], q_nom)
        if not ok.all():
            k = coarse[int(np.argmin(ok))]
            raise GraphcalError(f"walking simulation: foot {f} cannot reach its planned position at t = {t[k]:.3f} s")
        # Newton refinement at every sample from the spline (square 3x3 Jacobian), 4 steps at most
        sol = newton_ik(leg, p_body_foot[i], CubicSpline(t[coarse], qc, axis=0)(t), iterations=4, stop_tol=1e-12)
        q, J, err = sol.q, sol.J, sol.err
        if err.max() > 1e-9:
            k = int(np.argmax(err))
            raise GraphcalError(f"walking simulation: foot {f} cannot reach its planned position at t = {t[k]:.3f} s")
        jac[f] = J
        lo_lim, hi_lim = leg.lower, leg.upper
        bad = (q < lo_lim) | (q > hi_lim)
        if bad.any():
            k, jj = np.unravel_index(int(np.argmax(bad)), bad.shape)
            raise GraphcalError(f"walking simulation: joint {leg.joint_names[jj]} leaves its limits "
                                f"[{lo_lim[jj]:.2f}, {hi_lim[jj]:.2f}] rad at t = {t[k]:.3f} s ({q[k, jj]:.3f} rad)")
        q_leg[f] = q
        for jj, name in enumerate(leg.joint_names):
            q_true[name] = q[:, jj]
    return q_true, q_leg, jac


@dataclass(frozen=True, eq=False)
class _ImuData:
    """The IMU: its pose in the body frame ``T_body_imu`` (4, 4), measured ``gyro`` (N, 3) rad/s
    and ``accel`` (N, 3) m/s^2 (IMU frame, rounded like a driver's output) and the true biases
    ``gyro_bias``, ``accel_bias`` (N, 3) (random walks)."""

    T_body_imu: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray


def _body_rates(body: _BodyPath, dt: float) -> np.ndarray:
    """(N, 3) body-frame angular rates (rad/s) from central differences of roll, pitch, yaw."""
    rpy = np.c_[body.roll, body.pitch, body.yaw]
    return body_rates_from_rpy_rates(rpy, np.gradient(rpy, dt, axis=0))


def _second_difference(p: np.ndarray, dt: float) -> np.ndarray:
    """(N, 3) accelerations of positions p (N, 3) by central second differences (ends repeated)."""
    a = np.zeros_like(p)
    a[1:-1] = (p[2:] - 2 * p[1:-1] + p[:-2]) / dt**2
    a[0], a[-1] = a[1], a[-2]
    return a


def _imu(c: WalkingConfig, info, body: _BodyPath, dt: float, rng: np.random.Generator) -> _ImuData:
    """The IMU's true rate and specific force (the smooth trajectory differentiated) plus biases
    (initial offset + random walk) and white noise, drawn from ``rng`` in that order."""
    p, R = body.p, body.R
    N = len(p)
    w_body = _body_rates(body, dt)
    T_body_imu = np.array(info.T_body_imu, dtype=float)
    if c.imu_xyz_m is not None:
        T_body_imu[:3, 3] = np.asarray(c.imu_xyz_m, dtype=float)
    p_imu = p + np.einsum("nij,j->ni", R, T_body_imu[:3, 3])
    a_imu = _second_difference(p_imu, dt)
    R_world_imu = R @ T_body_imu[:3, :3]
    f_imu = np.einsum("nji,nj->ni", R_world_imu, a_imu - _G_WORLD)
    w_imu = w_body @ T_body_imu[:3, :3]
    sq = math.sqrt(c.rate_hz)
    gyro_bias = rng.normal(0, c.gyro_bias_sigma_rad_s, 3) + np.cumsum(
        rng.normal(0, c.gyro_bias_rw * math.sqrt(dt), (N, 3)), axis=0)
    accel_bias = rng.normal(0, c.accel_bias_sigma_m_s2, 3) + np.cumsum(
        rng.normal(0, c.accel_bias_rw * math.sqrt(dt), (N, 3)), axis=0)
    imu_gyro = np.round(w_imu + gyro_bias + rng.normal(0, c.gyro_noise_density * sq, (N, 3)), 7)
    imu_accel = np.round(f_imu + accel_bias + rng.normal(0, c.accel_noise_density * sq, (N, 3)), 6)
    return _ImuData(T_body_imu, imu_gyro, imu_accel, gyro_bias, accel_bias)


def _quasi_static_forces(c: WalkingConfig, body: _BodyPath, p_body_foot: np.ndarray, weight: np.ndarray,
                         dt: float, legs_share: np.ndarray | None = None) -> np.ndarray:
    """(n_feet, N, 3) force (N) each foot exerts on the ground, body frame: the ground reaction that
    carries the body's mass and acceleration, spread over the feet by their ``weight`` (n_feet, N)
    with zero moment about the body origin (weighted least norm); ``legs_share`` (N,) the part of
    it the legs carry (lying: the belly carries the rest), None for all of it."""
    R = body.R
    N = len(R)
    a_body = _second_difference(body.p, dt)
    F_body = c.body_mass_kg * np.einsum("nji,nj->ni", R, a_body - _G_WORLD)  # ground reaction sum, body frame
    if legs_share is not None:  # lying: the belly carries the rest
        F_body = F_body * legs_share[:, None]
    P = np.swapaxes(p_body_foot, 0, 1)  # (N, nf, 3)
    W = weight.T  # (N, nf)
    Px = skew_batch(P)  # (N, nf, 3, 3)
    M = np.zeros((N, 6, 6))
    M[:, :3, :3] = W.sum(axis=1)[:, None, None] * np.eye(3)
    S1 = np.einsum("nf,nfij->nij", W, Px)
    M[:, 3:, :3] = S1
    M[:, :3, 3:] = np.swapaxes(S1, 1, 2)
    M[:, 3:, 3:] = np.einsum("nf,nfij,nfkj->nik", W, Px, Px)
    b = np.c_[F_body, np.zeros((N, 3))]
    yv = np.linalg.solve(M, b[:, :, None])[:, :, 0]
    # f_i = w_i (y_F + y_M x p_i): the ground's force on foot i
    f_ground = W[:, :, None] * (yv[:, None, :3] + np.cross(yv[:, None, 3:], P))
    return -np.swapaxes(f_ground, 0, 1)  # what each foot exerts on the ground


def _shared_forces(c: WalkingConfig, body: _BodyPath, weight: np.ndarray, dt: float,
                   legs_share: np.ndarray | None = None) -> np.ndarray:
    """(n_feet, N, 3) force (N) each foot exerts on the ground, body frame: the ground reaction that
    carries the body's mass and acceleration, shared by the feet in proportion to their ``weight``
    (n_feet, N) -- no moment balance (two diagonal feet of a trot cannot hold one quasi-statically);
    the torques follow from these forces. ``legs_share`` (N,): the part the legs carry (lying: the
    belly carries the rest), None for all of it."""
    F_body = c.body_mass_kg * np.einsum("nji,nj->ni", body.R, _second_difference(body.p, dt) - _G_WORLD)
    if legs_share is not None:  # lying: the belly carries the rest
        F_body = F_body * legs_share[:, None]
    share = weight / np.maximum(weight.sum(axis=0, keepdims=True), 1e-12)
    return -share[:, :, None] * F_body[None]


def _joint_measurements(c: WalkingConfig, robot, feet: tuple, q_leg: dict, jac: dict, force_body_foot: np.ndarray,
                        rng: np.random.Generator) -> tuple[dict, dict]:
    """(joint name -> measured angle (N,) rad, joint name -> measured torque (N,) N m): the true
    angles and the torques that hold the feet's forces, plus encoder and torque noise, rounded."""
    tau_measured: dict[str, np.ndarray] = {}
    q_measured: dict[str, np.ndarray] = {}
    offsets = np.random.default_rng([c.seed, 7919])  # its own draws: the others are those of no offsets
    for i, f in enumerate(feet):
        leg = robot.leg(f)
        tau = np.einsum("nji,nj->ni", jac[f], force_body_foot[i])
        noisy_q = q_leg[f] + rng.normal(0, c.encoder_sigma_rad, q_leg[f].shape)
        if c.joint_offset_sigma_rad > 0:
            noisy_q = noisy_q + offsets.normal(0, c.joint_offset_sigma_rad, leg.n_joints)
        noisy_tau = tau + rng.normal(0, c.torque_sigma_nm, tau.shape)
        for jj, name in enumerate(leg.joint_names):
            q_measured[name] = np.round(noisy_q[:, jj], 8)
            tau_measured[name] = np.round(noisy_tau[:, jj], 4)
    return q_measured, tau_measured


def _depth_clouds(c: WalkingConfig, T_body_sensor: np.ndarray | None, t: np.ndarray, T_world_body: np.ndarray,
                  terrain: Terrain, rng: np.random.Generator, progress: bool) -> tuple[np.ndarray, list[np.ndarray]]:
    """(sample index (M,) of each cloud, M clouds (K, 3) in the sensor frame, m) of the depth camera
    at ``T_body_sensor`` (4, 4) every 1 / ``c.cloud_rate_hz`` s; none without a camera."""
    N = len(t)
    cloud_idx = np.zeros(0, dtype=np.int64)
    clouds: list[np.ndarray] = []
    if c.cloud_rate_hz > 0 and T_body_sensor is not None:
        from graphcal.models.sensors import DepthCamera
        from graphcal.simulation.sensors import capture
        from graphcal.simulation.terrain import build_scene

        cam = DepthCamera()
        cam = replace(cam, width_px=max(8, cam.width_px // c.cloud_stride),
                      height_px=max(6, cam.height_px // c.cloud_stride))
        scene = build_scene(terrain.meshes)
        n_cl = int(math.floor(t[-1] * c.cloud_rate_hz)) + 1
        cloud_idx = np.unique(np.round(np.arange(n_cl) / c.cloud_rate_hz * c.rate_hz).astype(np.int64))
        cloud_idx = cloud_idx[cloud_idx < N]
        it = cloud_idx
        if progress:
            from tqdm import tqdm

            it = tqdm(cloud_idx, desc="simulate: depth clouds", unit="cloud")
        for k in it:
            scan = capture(cam, None, T_world_body[k] @ T_body_sensor, rng, scene=scene)
            clouds.append(scan.points_sensor)
    return cloud_idx, clouds


def simulate_walking(config: WalkingConfig = WalkingConfig(), *, progress: bool = False) -> WalkingResult:
    """Simulate a walk (see the module docstring). Raises GraphcalError if the walk is infeasible
    (a foot out of reach or past a joint limit), naming the foot and the time."""
    from graphcal.models.builtin import builtin_info
    from graphcal.models.robot import load_robot

    c = config.resolved()
    info = builtin_info(c.robot)
    if c.gait.phase_offsets is None and len(info.gait_groups) != 2:
        raise GraphcalError(f"robot {c.robot!r} has no tripod gait groups (the {c.program} program needs two)")
    robot = load_robot(model=c.robot)
    rng = np.random.default_rng(c.seed)
    feet = tuple(robot.feet)
    groups = tuple(tuple(g) for g in info.gait_groups) if c.gait.phase_offsets is None else ()
    tl = _timeline(c, info)
    t = tl.t
    body = _body_path(c, info, feet, tl)
    T_world_body = body.T_world_body
    plan = _foot_plan(c, info, feet, groups, tl, body)
    p_body_foot = np.einsum("nji,fnj->fni", body.R, plan.p_world_foot - body.p[None])
    q_true, q_leg, jac = _joint_angles(robot, info, feet, t, p_body_foot, tl.h0)
    v_world = np.gradient(body.p, tl.dt, axis=0)
    imu = _imu(c, info, body, tl.dt, rng)
    share = tl.posture.legs_share if tl.posture is not None else None
    if c.gait.force_sensors:
        force_body_foot = _shared_forces(c, body, plan.weight, tl.dt, share)
    else:
        force_body_foot = _quasi_static_forces(c, body, p_body_foot, plan.weight, tl.dt, share)
    q_measured, tau_measured = _joint_measurements(c, robot, feet, q_leg, jac, force_body_foot, rng)
    foot_force = None
    if c.gait.force_sensors:  # drawn after the joints: the tripod walks' draws are unchanged
        load = -force_body_foot[:, :, 2].T  # (N, n_feet) along the body's -z
        foot_force = np.round(load + rng.normal(0, c.force_sigma_n, load.shape), 2)
    T_body_sensor = np.asarray(info.sensors["depth"].T_body_sensor, dtype=float) if "depth" in info.sensors else None
    cloud_idx, clouds = _depth_clouds(c, T_body_sensor, t, T_world_body, body.terrain, rng, progress)
    T_cad = _cad_prior(c, T_body_sensor) if T_body_sensor is not None else None
    return WalkingResult(
        config=c, robot=robot, info=info, times=t, T_world_body=T_world_body, v_world_body=v_world,
        feet=feet, groups=groups, p_world_foot=plan.p_world_foot, contact=plan.contact, q_true=q_true,
        q_measured=q_measured, tau_measured=tau_measured, force_body_foot=force_body_foot,
        imu_accel=imu.accel, imu_gyro=imu.gyro, accel_bias=imu.accel_bias, gyro_bias=imu.gyro_bias,
        T_body_imu=imu.T_body_imu, T_body_sensor=T_body_sensor if T_body_sensor is not None else np.eye(4),
        cloud_indices=cloud_idx, clouds=clouds, terrain=body.terrain, foot_force=foot_force,
        T_body_sensor_cad=T_cad,
    )


def _cad_prior(c: WalkingConfig, T_body_sensor: np.ndarray) -> np.ndarray:
    """The CAD prior of the depth camera: its true pose (4, 4) moved by N(0, cad_error_m) per axis
    and rotated by N(0, cad_error_rad) per sensor axis, from a generator of its own."""
    from graphcal.geometry import so3_exp

    if c.cad_error_m == 0 and c.cad_error_rad == 0:
        return np.array(T_body_sensor, dtype=float)
    draw = np.random.default_rng([int(c.seed), 7]).normal(0.0, 1.0, 6)
    T = np.array(T_body_sensor, dtype=float)
    T[:3, :3] = T[:3, :3] @ so3_exp(c.cad_error_rad * draw[:3])
    T[:3, 3] = T[:3, 3] + c.cad_error_m * draw[3:]
    return T
