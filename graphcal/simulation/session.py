"""Simulate a static calibration session of a legged robot: stances, commanded poses, what the body
really does, joint encoders, IMU, and what the exteroceptive sensors see.

The physical story, per station (Chai 2015 section 4.2):

1. The controller is asked to hold the set pose ``T_world_body_cmd`` with the feet planted where it
   believes they are (the session's nominal stance on the nominal ground z = 0). It computes the
   joint angles by inverse kinematics of the *nominal* (URDF) robot.
2. The servos reach those angles up to a tracking error (``tracking_sigma_rad`` per joint).
3. The *true* robot (the URDF with the hidden leg errors) with those joint angles, feet planted where
   they really are (on the real, possibly tilted or bumpy ground, sunk by the session offset), ends up
   at the pose that best fits its feet: a rigid fit of the true foot positions in the body frame to the
   planted world positions. Commanded pose, joint angles and real pose all differ a little, as on a
   real robot.
4. The encoders report the reached angles with noise; the IMU reports gravity in its (possibly
   misaligned) frame with bias and noise; each sensor ray-casts the terrain and the robot's own legs
   from ``T_world_body_real @ T_body_sensor_true``.

Everything the data hides is returned as ``truth`` (written to ``truth.yaml``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.geometry import (
    fit_rigid_transform,
    invert_pose,
    matrix_from_axis_angle,
    pose_matrix,
    rot_z,
    rotation_angle_between,
    se3_exp,
    transform_points,
)
from graphcal.io.calibration_yaml import pose_to_dict
from graphcal.models.sensors import sensor_for_type
from graphcal.simulation.effects import Effects
from graphcal.simulation.programs import station_program
from graphcal.simulation.sensors import capture
from graphcal.simulation.terrain import LABEL_ROBOT, Mesh, build_scene, cylinder_mesh, make_terrain, terrain_height

GRAVITY_M_S2 = 9.80665

#: Commanded roll/pitch are scaled by this for robots whose legs reach less than the Octopus.
DEFAULT_TILT_SCALE = {"octopus": 1.0, "qingzhui": 0.75, "messor": 0.5, "a1": 0.5, "a1cam": 0.5}


def wrap_revolute(leg, q: np.ndarray) -> np.ndarray:
    """``q`` (n,) with every revolute joint turned by whole turns to the angle nearest the middle of
    its limits (the same pose; an IK that walked around a full turn otherwise writes an angle 2 pi
    outside the URDF's limits). Joints without finite limits are wrapped into [-pi, pi)."""
    q = np.array(q, dtype=float)
    lo, hi = np.asarray(leg.lower, dtype=float), np.asarray(leg.upper, dtype=float)
    mid = np.where(np.isfinite(lo) & np.isfinite(hi) & (lo < hi), (lo + hi) / 2, 0.0)
    rev = np.array([t == "revolute" for t in leg.joint_types])
    q[rev] = mid[rev] + (q[rev] - mid[rev] + np.pi) % (2 * np.pi) - np.pi
    return q


def _reachable_within_limits(robot, info, q_nominal: dict):
    """``T_stance_body -> bool``: whether every foot, planted at its nominal stance on the ground
    (stance frame), is reached from the body pose within the joint limits (IK from the nominal
    angles, revolute joints wrapped by :func:`wrap_revolute`)."""
    from graphcal.models.kinematics import ik_leg

    p_stance = {f: np.r_[np.asarray(info.nominal_stance[f], dtype=float)[:2], 0.0] for f in robot.feet}

    def reachable(T_stance_body: np.ndarray) -> bool:
        T_body_stance = invert_pose(T_stance_body)
        for f in robot.feet:
            leg = robot.leg(f)
            q, ok = ik_leg(leg, transform_points(T_body_stance, p_stance[f][None, :]), q_nominal[f][None, :])
            if not ok[0] or leg.outside_limits(wrap_revolute(leg, q[0])).any():
                return False
        return True

    return reachable


def _nominal_q(robot, info) -> dict:
    """Joint angles of the nominal stance, per foot: IK from the zero configuration, else from the
    middle of the joint limits, else from random points inside them; the first solution that
    respects the limits wins."""
    from graphcal.models.kinematics import ik_leg

    rng = np.random.default_rng(0)
    out = {}
    for f in robot.feet:
        leg = robot.leg(f)
        lo = np.where(np.isfinite(leg.lower), leg.lower, -np.pi)
        hi = np.where(np.isfinite(leg.upper), leg.upper, np.pi)
        starts = np.vstack([np.zeros(leg.n_joints), (lo + hi) / 2, rng.uniform(lo, hi, (20, leg.n_joints))])
        target = np.repeat(np.asarray(info.nominal_stance[f])[None, :], len(starts), axis=0)
        q, ok = ik_leg(leg, target, starts)
        inside = ok & np.all((q >= lo - 1e-9) & (q <= hi + 1e-9), axis=1)
        if not inside.any():
            raise GraphcalError(f"model {robot.name!r}: foot {f} cannot reach its nominal stance within its joint limits")
        out[f] = q[int(np.argmax(inside))]
    return out


@dataclass(frozen=True, eq=False)
class CustomRobot:
    """A robot that is not built in: its URDF text and what the simulator needs to know about it
    (a :class:`graphcal.models.builtin.BuiltinInfo`: base frame, feet, standing height, nominal
    stance, sensors with their CAD poses, IMU pose)."""

    urdf_xml: str
    info: object


def robot_and_info(config: "SimulationConfig"):
    """(RobotModel, BuiltinInfo) of the configured robot, built-in or custom."""
    from graphcal.models.builtin import builtin_info
    from graphcal.models.robot import load_robot

    if config.custom_robot is not None:
        info = config.custom_robot.info
        robot = load_robot(urdf_xml=config.custom_robot.urdf_xml, base_frame=info.base_frame, feet=info.feet)
        return robot, info
    return load_robot(model=config.robot), builtin_info(config.robot)


@dataclass(frozen=True)
class SimulationConfig:
    """What to simulate. Units SI; angles in rad.

    Attributes:
        robot: built-in model name (see graphcal.models.builtin).
        program: station program (see graphcal.simulation.programs).
        ground: terrain kind (see graphcal.simulation.terrain).
        seed: every random draw derives from it.
        n_stations: for the ``random`` program.
        n_sessions: stances; the feet are re-planted between sessions.
        session_heading_step_deg: the robot turns by this much about the vertical between sessions
            (and steps 0.25 m forward); heading changes are what tell a tilted floor from a tilted
            IMU (docs/diagnosis.md).
        sensors: names of the model's sensors to simulate (default: all).
        cloud_stride: keep every k-th pixel row and column of camera images (1 = full resolution).
        extrinsic_sigma_m, extrinsic_sigma_rad: the true extrinsic is the CAD value perturbed by
            Exp(xi), xi ~ N(0, sigma) per axis (how far the CAD value is off).
        leg_error_sigma_rad, leg_error_sigma_m: random joint-offset and link-length errors drawn on
            every leg joint (0 = the true legs equal the URDF, apart from ``effects``).
        tracking_sigma_rad: joint servo tracking error.
        encoder_sigma_rad: joint encoder noise.
        joint_flex_sigma_rad: deflection/backlash between encoder and link, per joint and station,
            that the encoder does not see (0 by default).
        extrinsic_seed: draw the true extrinsics from this seed instead of ``seed`` (the same sensor
            mounting over runs that differ in noise, as on one physical robot).
        depth_noise_scale: multiplies the depth camera's noise (Chai's illumination conditions:
            weak/strong light made the Kinect noisier).
        imu_accel_sigma_m_s2, imu_gyro_sigma_rad_s: IMU noise of a station average.
        imu_accel_bias_sigma_m_s2, imu_gyro_bias_sigma_rad_s: constant IMU biases drawn once.
        tilt_scale: scales commanded roll/pitch (None: the model's default).
        effects: hidden discrepancy effects (see graphcal.simulation.effects).
        custom_robot: simulate this robot instead of the built-in ``robot`` (then ``robot`` is only
            its name in the outputs).
    """

    robot: str = "octopus"
    program: str = "chai2015"
    ground: str = "level"
    seed: int = 0
    n_stations: int | None = None
    n_sessions: int = 1
    session_heading_step_deg: float = 8.0
    sensors: tuple[str, ...] | None = None
    cloud_stride: int = 4
    extrinsic_sigma_m: float = 0.01
    extrinsic_sigma_rad: float = float(np.radians(1.0))
    leg_error_sigma_rad: float = 0.0
    leg_error_sigma_m: float = 0.0
    tracking_sigma_rad: float = float(np.radians(0.2))
    encoder_sigma_rad: float = float(np.radians(0.02))
    joint_flex_sigma_rad: float = 0.0
    depth_noise_scale: float = 1.0
    extrinsic_seed: int | None = None
    imu_accel_sigma_m_s2: float = 0.005
    imu_gyro_sigma_rad_s: float = 2e-4
    imu_accel_bias_sigma_m_s2: float = 0.02
    imu_gyro_bias_sigma_rad_s: float = 1e-3
    tilt_scale: float | None = None
    effects: Effects = field(default_factory=Effects)
    custom_robot: CustomRobot | None = None


@dataclass(frozen=True)
class StationRecord:
    """One simulated station (all poses 4x4, angles rad, m)."""

    station: int
    session: str
    time_s: float
    T_world_body_cmd: np.ndarray
    T_world_body_real: np.ndarray
    q_measured: dict
    imu_accel: np.ndarray
    imu_gyro: np.ndarray


@dataclass(frozen=True)
class SimulationResult:
    """Simulated data plus the truth it hides.

    Attributes:
        config: the configuration.
        robot_name: built-in model name (or the custom robot's name).
        stations: the station records, in order.
        clouds: (sensor, station) -> points (N, 3) in the sensor frame (m), as measured.
        cloud_labels: (sensor, station) -> labels (N,) of each point (ground/robot/obstacle/stairs).
        sensor_cad: sensor name -> (type, T_body_sensor CAD 4x4, sigma_m, sigma_rad).
        truth: plain dict for truth.yaml.
    """

    config: SimulationConfig
    robot_name: str
    stations: tuple[StationRecord, ...]
    clouds: dict
    cloud_labels: dict
    sensor_cad: dict
    truth: dict


def _chain_points_world(leg, q_leg: np.ndarray, T_world_base: np.ndarray) -> np.ndarray:
    """World positions (n + 1, 3) of every joint origin of a leg and of its foot (for the leg meshes)."""
    from graphcal.models.kinematics import joint_frames

    _, origins_base, _, p_foot = joint_frames(leg, q_leg[None, :])
    return transform_points(T_world_base, np.vstack([origins_base[0], p_foot]))


def _true_robot(robot, config: SimulationConfig, rng: np.random.Generator):
    """The hidden "true" robot: the URDF with drawn leg errors and the catalogue's leg effects."""
    from graphcal.models.perturb import LegPerturbation, apply_perturbation, link_length_delta
    from graphcal.models.robot import load_robot

    joint_offsets, drawn_lengths = draw_leg_errors(robot, robot.feet, config.leg_error_sigma_rad,
                                                   config.leg_error_sigma_m, rng)
    for j, off in config.effects.joint_offset.items():
        joint_offsets[j] = joint_offsets.get(j, 0.0) + float(off)
    link_changes = dict(config.effects.link_length)
    for j, delta in drawn_lengths.items():
        link_changes[j] = link_changes.get(j, 0.0) + delta
    origin_deltas: dict[str, np.ndarray] = {}
    for j, delta in link_changes.items():
        origin_deltas[j] = np.asarray(link_length_delta(robot, j, float(delta)))
    pert = LegPerturbation(
        joint_offsets_rad=joint_offsets,
        origin_deltas_m={k: tuple(float(x) for x in v) for k, v in origin_deltas.items()},
    )
    true_xml = apply_perturbation(robot.urdf_xml, pert)
    true_robot = load_robot(urdf_xml=true_xml, base_frame=robot.base_frame, feet=robot.feet)
    return true_robot, joint_offsets, link_changes


def draw_leg_errors(robot, feet, sigma_rad: float, sigma_m: float,
                    rng: np.random.Generator) -> tuple[dict[str, float], dict[str, float]]:
    """Random kinematic errors of the legs of ``feet``: encoder zero errors ~ N(0, sigma_rad^2) (rad)
    on every revolute joint, then link-length changes ~ N(0, sigma_m^2) (m) on every joint whose
    origin is a link (:func:`_link_joints`). A zero sigma draws nothing. Returns (joint -> offset,
    joint -> length change)."""
    joint_offsets: dict[str, float] = {}
    if sigma_rad > 0:
        for foot in feet:
            leg = robot.leg(foot)
            for j, jtype in zip(leg.joint_names, leg.joint_types):
                if jtype != "prismatic":
                    joint_offsets[j] = float(rng.normal(0.0, sigma_rad))
    link_changes: dict[str, float] = {}
    if sigma_m > 0:
        for foot in feet:
            for j in _link_joints(robot, foot):
                link_changes[j] = link_changes.get(j, 0.0) + float(rng.normal(0.0, sigma_m))
    return joint_offsets, link_changes


def _link_joints(robot, foot: str) -> tuple[str, ...]:
    """Joints of a leg whose origin translation is a link length: the URDF joints of the leg's
    ``delta_m`` parameters (graphcal/models/legs.py: every joint after the first whose origin
    has a translation, and the fixed foot joint). A joint whose origin has no translation (two axes
    through one point, e.g. the qingzhui's coxa-thigh pair) ends no link and is not a candidate."""
    from graphcal.models.legs import leg_model

    param = leg_model(robot, foot, origins="none")
    return tuple(j for j in param.trans_urdf_joints if j is not None)


def leg_link_joints(robot) -> dict[str, tuple[str, ...]]:
    """foot -> joints whose origin is a link length (candidates of the ``link_length`` effect)."""
    return {foot: _link_joints(robot, foot) for foot in robot.feet}


def _simulated_sensors(config: SimulationConfig, info) -> tuple[str, ...]:
    """The names of the simulated sensors (default: all the robot's), checked against the robot and
    the effects that name sensors."""
    sensor_names = tuple(config.sensors) if config.sensors is not None else tuple(info.sensors)
    for s in sensor_names:
        if s not in info.sensors:
            raise GraphcalError(
                f"robot {config.robot!r} has no sensor {s!r}; it has: {', '.join(info.sensors) or 'none'}"
            )
    for s in config.effects.sensor_range_scale:
        if s not in sensor_names:
            raise GraphcalError(f"sensor_range_scale names sensor {s!r}, which is not simulated")
    return sensor_names


def _true_extrinsics(config: SimulationConfig, info, sensor_names: tuple, rng: np.random.Generator) -> dict:
    """sensor -> true T_body_sensor (4, 4): the CAD pose times Exp of a drawn [omega, v] (rad, m),
    from ``rng`` or, with ``config.extrinsic_seed``, from a generator of its own."""
    T_body_sensor_true = {}
    ext_rng = rng if config.extrinsic_seed is None else np.random.default_rng(config.extrinsic_seed)
    for s in sensor_names:
        cad = info.sensors[s]
        xi = np.r_[ext_rng.normal(0, config.extrinsic_sigma_rad, 3), ext_rng.normal(0, config.extrinsic_sigma_m, 3)]
        T_body_sensor_true[s] = cad.T_body_sensor @ se3_exp(xi)
    return T_body_sensor_true


def _check_program(config: SimulationConfig, commands, sensor_names: tuple) -> list:
    """The program's sessions, in order; GraphcalError when an effect names a session, station or
    sensor the simulation does not have."""
    sessions = list(dict.fromkeys(c.session for c in commands))
    for s in config.effects.session_offset:
        if s not in sessions:
            raise GraphcalError(f"session_offset names session {s!r}; the sessions are {', '.join(sessions)}")
    if config.effects.extrinsic_change is not None:
        ch = config.effects.extrinsic_change
        if ch.sensor not in sensor_names:
            raise GraphcalError(f"extrinsic_change names sensor {ch.sensor!r}, which is not simulated")
        if ch.station not in {c.station for c in commands}:
            raise GraphcalError(f"extrinsic_change names station {ch.station}, which the program does not have")
    for st in config.effects.outlier_stations:
        if st not in {c.station for c in commands}:
            raise GraphcalError(f"outlier_stations names station {st}, which the program does not have")
    return sessions


@dataclass(frozen=True, eq=False)
class _Stances:
    """Where each session's feet are planted: session -> ``T_world_stance`` (4, 4), and the feet's
    world positions (n_feet, 3) m as the program assumes them (on z = 0) and as they really are
    (on the terrain, less the session's offset)."""

    T_world_stance: dict
    feet_world_assumed: dict
    feet_world_real: dict


def _stances(config: SimulationConfig, robot, info, sessions: list, terrain, terrain_scene, h0: float) -> _Stances:
    T_world_stance = {}
    feet_world_assumed = {}
    feet_world_real = {}
    for k, s in enumerate(sessions):
        T = pose_matrix(rot_z(np.radians(config.session_heading_step_deg * k)),
                        [0.25 * k, 0.08 * (-1) ** k * (k > 0), 0.0])
        T_world_stance[s] = T
        p_stance = np.array([info.nominal_stance[f] + np.array([0.0, 0.0, h0]) for f in robot.feet])
        p_assumed = transform_points(T, p_stance)
        p_assumed[:, 2] = 0.0
        p_real = p_assumed.copy()
        p_real[:, 2] = terrain_height(terrain, p_real[:, :2], scene=terrain_scene[0])
        p_real[:, 2] -= config.effects.session_offset.get(s, 0.0)
        plate = config.effects.open_world.plate
        if plate and plate[0] == s:
            on_plate = [k for k, f in enumerate(robot.feet) if f in plate[1]]
            p_real[on_plate, 2] += float(plate[2])
        feet_world_assumed[s] = p_assumed
        feet_world_real[s] = p_real
    return _Stances(T_world_stance, feet_world_assumed, feet_world_real)


def _commanded_q(leg, p_body_foot: np.ndarray, q_prev: np.ndarray, q_nominal: np.ndarray, station: int, foot: str) -> np.ndarray:
    """Joint angles (n,) rad that put the foot at ``p_body_foot`` (3,) m (body frame): IK from the
    previous station's angles, or from the nominal stance when that lands outside fewer limits."""
    from graphcal.models.kinematics import ik_leg

    q_ik, ok = ik_leg(leg, p_body_foot[None, :], q_prev[None, :])
    if not ok[0]:
        raise GraphcalError(
            f"station {station}: foot {foot} cannot reach its planted position in the commanded pose"
        )
    q_ik[0] = wrap_revolute(leg, q_ik[0])
    if leg.outside_limits(q_ik[0]).any():  # another branch (a flipped knee): from the nominal stance
        q_nom, ok_nom = ik_leg(leg, p_body_foot[None, :], q_nominal[None, :])
        q_nom[0] = wrap_revolute(leg, q_nom[0])
        if ok_nom[0] and leg.outside_limits(q_nom[0]).sum() < leg.outside_limits(q_ik[0]).sum():
            q_ik = q_nom
    return q_ik[0]


def _complied_q(config: SimulationConfig, true_leg, p_body_planted: np.ndarray, q_act: np.ndarray, station: int,
                foot: str, T_real: np.ndarray | None = None) -> np.ndarray:
    """The leg complies: its joints settle where the true leg reaches its planted foot
    ``p_body_planted`` (3,) m from the real body pose ``T_real`` (the chain closes exactly), from
    ``q_act``; on round feet (effect ``foot_radius``) the foot frame sits ``r (a_b - n_b)`` from the
    contact (three fixed-point rounds: the lower leg's direction depends on the angles)."""
    from graphcal.factors.stance_contact import lower_leg_direction
    from graphcal.models.kinematics import ik_leg

    r = config.effects.foot_radius
    target = p_body_planted
    if r and T_real is not None:
        n_b = T_real[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        q_i = q_act
        for _ in range(3):
            target = p_body_planted - r * (lower_leg_direction(true_leg, q_i) - n_b)
            q_n, ok_n = ik_leg(true_leg, target[None, :], q_i[None, :])
            if not ok_n[0]:
                break
            q_i = q_n[0]
    q_c, ok = ik_leg(true_leg, target[None, :], q_act[None, :])
    if not ok[0]:
        hint = ""
        if config.effects.active() or config.leg_error_sigma_m > 0 or config.leg_error_sigma_rad > 0:
            hint = ("; hidden here: " + (", ".join(config.effects.active()) or "leg errors")
                    + ". Is a magnitude more than this leg can take? (--effect CAUSE:key=value sets it)")
        raise GraphcalError(f"station {station}: foot {foot} cannot stay planted (IK of the true leg "
                            f"failed){hint}")
    return wrap_revolute(true_leg, q_c[0])


def _drifted_imu(config: SimulationConfig, R_body_imu: np.ndarray, i: int, n: int) -> np.ndarray:
    """The IMU mounting (3, 3) at the i-th of n stations: tilted by the open-world ``imu_drift``
    growing linearly from 0 at the first station to its angle at the last."""
    drift = config.effects.open_world.imu_drift
    if not drift:
        return R_body_imu
    ang, az = drift
    return matrix_from_axis_angle([np.cos(az), np.sin(az), 0.0], ang * i / max(n - 1, 1)) @ R_body_imu


def _sunk_feet(config: SimulationConfig, commands, i: int, feet_world: np.ndarray) -> np.ndarray:
    """The planted feet (n_feet, 3) m at the i-th commanded station: ``feet_world`` sunk by the
    open-world ``sinking`` of its session, growing linearly from 0 at the session's first station to
    its depth at the last."""
    session = commands[i].session
    depth = config.effects.open_world.sinking.get(session, 0.0)
    if not depth:
        return feet_world
    idx = [j for j, c in enumerate(commands) if c.session == session]
    frac = idx.index(i) / max(len(idx) - 1, 1)
    out = np.array(feet_world, dtype=float)
    out[:, 2] -= depth * frac
    return out


def _compliance_deflection(config: SimulationConfig, true_leg, q: np.ndarray, T_world_body: np.ndarray):
    """Joint compliance (effect ``joint_compliance``): (n_joints,) rad the links flex away from the
    motors under the foot's load: ``k * lever`` at the effect's joint index, ``lever = (d p_foot /
    d q_j) . n_b`` (torque per newton of vertical load, m; the true leg at the true angles ``q``,
    ``n_b`` the world vertical in the body frame). 0 when no compliance is hidden."""
    comp = config.effects.joint_compliance
    if comp is None or comp[0] >= true_leg.n_joints:
        return 0.0
    from graphcal.factors.stance_contact import compliance_lever

    j, k = comp
    out = np.zeros(true_leg.n_joints)
    out[int(j)] = float(k) * compliance_lever(true_leg, q, int(j), T_world_body[:3, :3])
    return out


def _contact_points(config: SimulationConfig, true_robot, q_act: dict, R_world_body: np.ndarray) -> np.ndarray:
    """Where each foot touches the ground, body frame (n_feet, 3) m: the true legs' foot frames, moved
    by ``r (a_b - n_b)`` on round feet (effect ``foot_radius``: ``a_b`` the lower leg's direction,
    ``n_b`` the world vertical in the body frame at ``R_world_body``)."""
    from graphcal.factors.stance_contact import lower_leg_direction
    from graphcal.models.kinematics import foot_positions

    r = config.effects.foot_radius
    n_b = np.asarray(R_world_body).T @ np.array([0.0, 0.0, 1.0])
    out = []
    for f, qa in q_act.items():
        p = foot_positions(true_robot.leg(f), qa[None, :])[0]
        if r:
            p = p + r * (lower_leg_direction(true_robot.leg(f), qa) - n_b)
        out.append(p)
    return np.array(out)


@dataclass(frozen=True, eq=False)
class _HiddenImu:
    """The true IMU: R_body_imu (3, 3), accelerometer bias (3,) m/s^2 and gyro bias (3,) rad/s."""

    R_body_imu: np.ndarray
    accel_bias: np.ndarray
    gyro_bias: np.ndarray


def _stations(config: SimulationConfig, robot, true_robot, commands, stances: _Stances, q_nominal: dict,
              imu: _HiddenImu, rng: np.random.Generator, progress: bool) -> tuple[list, dict, dict]:
    """At each commanded station: the joint angles that reach the planted feet, tracking errors, the
    real body pose (the true legs' feet fitted to the planted ones), the complied joint angles,
    the encoder and IMU readings. Returns (records, station -> real T_world_body, station ->
    foot -> true joint angles)."""
    q_prev = dict(q_nominal)
    records: list[StationRecord] = []
    real_poses = {}
    leg_q_true = {}
    it = commands
    if progress:
        from graphcal.progress import ProgressBar

        it = ProgressBar(commands, desc="simulate: stations", unit="station")
    for i, cmd in enumerate(it):
        T_cmd = stances.T_world_stance[cmd.session] @ cmd.T_stance_body
        p_body_cmd = transform_points(invert_pose(T_cmd), stances.feet_world_assumed[cmd.session])
        q_act = {}
        for k, f in enumerate(robot.feet):
            leg = robot.leg(f)
            q_prev[f] = _commanded_q(leg, p_body_cmd[k], q_prev[f], q_nominal[f], cmd.station, f)
            qa = q_prev[f] + rng.normal(0.0, config.tracking_sigma_rad, leg.n_joints)
            q_act[f] = qa
        feet_real = _sunk_feet(config, commands, i, stances.feet_world_real[cmd.session])
        T_real = fit_rigid_transform(_contact_points(config, true_robot, q_act, T_cmd[:3, :3]), feet_real)
        if config.effects.foot_radius:  # the contact depends on the attitude: once more at the real one
            T_real = fit_rigid_transform(_contact_points(config, true_robot, q_act, T_real[:3, :3]), feet_real)
        real_poses[cmd.station] = T_real
        # the encoders read the complied angles
        p_body_planted = transform_points(invert_pose(T_real), feet_real)
        for k, f in enumerate(robot.feet):
            q_act[f] = _complied_q(config, true_robot.leg(f), p_body_planted[k], q_act[f], cmd.station, f, T_real)
        leg_q_true[cmd.station] = q_act
        q_meas = {}
        for f in robot.feet:
            leg = robot.leg(f)
            flex = rng.normal(0.0, config.joint_flex_sigma_rad, leg.n_joints) if config.joint_flex_sigma_rad > 0 else 0.0
            flex = flex + _compliance_deflection(config, true_robot.leg(f), q_act[f], T_real)
            noisy = q_act[f] - flex + rng.normal(0.0, config.encoder_sigma_rad, leg.n_joints)
            for name, val in zip(leg.joint_names, noisy):
                q_meas[name] = float(val)
        R_world_imu = T_real[:3, :3] @ _drifted_imu(config, imu.R_body_imu, i, len(commands))
        accel = (R_world_imu.T @ np.array([0.0, 0.0, GRAVITY_M_S2]) + imu.accel_bias
                 + rng.normal(0, config.imu_accel_sigma_m_s2, 3))
        gyro = imu.gyro_bias + rng.normal(0, config.imu_gyro_sigma_rad_s, 3)
        records.append(StationRecord(cmd.station, cmd.session, 10.0 * i, T_cmd, T_real, q_meas, accel, gyro))
    return records, real_poses, leg_q_true


def _sensor_clouds(config: SimulationConfig, robot, true_robot, info, records: list, leg_q_true: dict, terrain,
                   sensor_names: tuple, T_body_sensor_true: dict, h0: float,
                   rng: np.random.Generator) -> tuple[dict, dict, dict]:
    """Every sensor's cloud at every station, of the terrain and the robot's own legs (cylinders),
    the extrinsic knocked from ``config.effects.extrinsic_change``'s station on. Returns
    ((sensor, station) -> points (N, 3) sensor frame m, -> labels (N,), -> T_body_sensor (4, 4))."""
    clouds, labels = {}, {}
    ext_by_station: dict[tuple[str, int], np.ndarray] = {}
    change = config.effects.extrinsic_change
    leg_radius = max(0.008, 0.05 * h0)  # leg segments as cylinders, m
    for rec in records:
        leg_meshes: list[Mesh] = []
        for f in robot.feet:
            pts = _chain_points_world(true_robot.leg(f), leg_q_true[rec.station][f], rec.T_world_body_real)
            for a, b in zip(pts[:-1], pts[1:]):
                if np.linalg.norm(b - a) > 1e-6:
                    leg_meshes.append(cylinder_mesh(a, b, leg_radius, LABEL_ROBOT))
        scene = build_scene(list(terrain.meshes) + leg_meshes)
        for s in sensor_names:
            T_bs = T_body_sensor_true[s]
            if change is not None and change.sensor == s and rec.station >= change.station:
                R_knock = matrix_from_axis_angle(change.axis, change.angle_rad)
                T_bs = pose_matrix(R_knock @ T_bs[:3, :3], T_bs[:3, 3] + np.asarray(change.translation_m))
            ext_by_station[(s, rec.station)] = T_bs
            sensor = sensor_for_type(info.sensors[s].type)
            if config.depth_noise_scale != 1.0 and hasattr(sensor, "noise_coeff_per_m"):
                from dataclasses import replace as _replace

                sensor = _replace(sensor, noise_coeff_per_m=sensor.noise_coeff_per_m * config.depth_noise_scale)
            sensor = strided(sensor, config.cloud_stride)
            scan = capture(
                sensor,
                None,
                rec.T_world_body_real @ T_bs,
                rng,
                range_scale=config.effects.sensor_range_scale.get(s, 1.0),
                scene=scene,
            )
            k_quad = config.effects.open_world.range_quadratic.get(s, 0.0)
            pts = scan.points_sensor
            if k_quad:
                pts = pts * (1.0 + k_quad * np.linalg.norm(pts, axis=1))[:, None]
            clouds[(s, rec.station)] = pts
            labels[(s, rec.station)] = scan.labels
    return clouds, labels, ext_by_station


def _swap_outlier_stations(config: SimulationConfig, records: list, real_poses: dict, sensor_names: tuple,
                           clouds: dict, labels: dict) -> tuple[dict, dict, dict]:
    """Outlier stations: their sensor data are those of the most different other station (by the
    angle between the real body orientations). Returns (clouds, labels, outlier station -> source
    station)."""
    swapped = {}
    clouds, labels = dict(clouds), dict(labels)
    if config.effects.outlier_stations:
        originals = {k: v for k, v in clouds.items()}
        original_labels = dict(labels)
        for st in config.effects.outlier_stations:
            R_st = real_poses[st][:3, :3]
            others = [r.station for r in records if r.station != st]
            angles = [rotation_angle_between(R_st, real_poses[o][:3, :3]) for o in others]
            src = others[int(np.argmax(angles))]
            swapped[st] = src
            for s in sensor_names:
                clouds[(s, st)] = originals[(s, src)]
                labels[(s, st)] = original_labels[(s, src)]
    return clouds, labels, swapped


def simulate(config: SimulationConfig, *, progress: bool = False) -> SimulationResult:
    """Run the simulation described by ``config`` (see the module docstring for the physics)."""
    rng = np.random.default_rng(config.seed)
    robot, info = robot_and_info(config)
    h0 = info.default_body_height_m
    tilt_scale = config.tilt_scale if config.tilt_scale is not None else DEFAULT_TILT_SCALE.get(config.robot, 1.0)
    sensor_names = _simulated_sensors(config, info)

    # -- hidden truth: sensor extrinsics, legs, IMU
    T_body_sensor_true = _true_extrinsics(config, info, sensor_names, rng)
    true_robot, joint_offsets, link_changes = _true_robot(robot, config, rng)
    R_body_imu_true = info.T_body_imu[:3, :3].copy()
    if config.effects.imu_misalignment is not None:
        ang, az = config.effects.imu_misalignment
        R_body_imu_true = matrix_from_axis_angle([np.cos(az), np.sin(az), 0.0], ang) @ R_body_imu_true
    accel_bias = rng.normal(0, config.imu_accel_bias_sigma_m_s2, 3)
    gyro_bias = rng.normal(0, config.imu_gyro_bias_sigma_rad_s, 3)

    tilt = config.effects.ground_tilt or (0.0, 0.0)
    terrain = make_terrain(config.ground, seed=config.seed, tilt_rad=tilt[0], tilt_axis_rad=tilt[1])
    terrain_scene = build_scene(terrain.meshes)

    q_nominal = _nominal_q(robot, info)
    commands = station_program(
        config.program,
        default_height_m=h0,
        n_stations=config.n_stations,
        n_sessions=config.n_sessions,
        seed=config.seed,
        tilt_scale=tilt_scale,
        reachable=_reachable_within_limits(robot, info, q_nominal),
    )
    sessions = _check_program(config, commands, sensor_names)
    stances = _stances(config, robot, info, sessions, terrain, terrain_scene, h0)
    records, real_poses, leg_q_true = _stations(config, robot, true_robot, commands, stances, q_nominal,
                                                _HiddenImu(R_body_imu_true, accel_bias, gyro_bias), rng, progress)
    clouds, labels, ext_by_station = _sensor_clouds(config, robot, true_robot, info, records, leg_q_true, terrain,
                                                    sensor_names, T_body_sensor_true, h0, rng)
    clouds, labels, swapped = _swap_outlier_stations(config, records, real_poses, sensor_names, clouds, labels)

    sensor_cad = {s: info.sensors[s] for s in sensor_names}
    truth = _truth_dict(
        config, info, sensor_names, T_body_sensor_true, ext_by_station, records, joint_offsets, link_changes,
        R_body_imu_true, accel_bias, gyro_bias, terrain, swapped, stances.T_world_stance, stances.feet_world_real,
    )
    return SimulationResult(config, config.robot, tuple(records), clouds, labels, sensor_cad, truth)


def strided(sensor, stride: int):
    """A camera with every ``stride``-th pixel row and column (same field of view)."""
    from dataclasses import replace

    if stride <= 1 or not hasattr(sensor, "width_px"):
        return sensor
    if hasattr(sensor, "noise_focal_px"):  # the noise stays that of the full-resolution camera
        sensor = replace(sensor, noise_focal_px=sensor.focal_px)
    return replace(sensor, width_px=max(8, sensor.width_px // stride), height_px=max(6, sensor.height_px // stride))


def _truth_dict(
    config, info, sensor_names, T_body_sensor_true, ext_by_station, records, joint_offsets, link_changes,
    R_body_imu_true, accel_bias, gyro_bias, terrain, swapped, T_world_stance, feet_world_real,
) -> dict:
    sensors = {}
    for s in sensor_names:
        entry = {"type": info.sensors[s].type, "T_body_sensor": pose_to_dict(T_body_sensor_true[s])}
        ch = config.effects.extrinsic_change
        if ch is not None and ch.sensor == s:
            entry["T_body_sensor_after_change"] = pose_to_dict(ext_by_station[(s, ch.station)])
        sensors[s] = entry
    return {
        "format": "graphcal-truth/1",
        "note": "hidden simulation truth; only evaluations read this file",
        "robot": config.robot,
        "program": config.program,
        "ground": {"type": terrain.kind, "bump_rms_m": float(terrain.bump_rms_m)},
        "seed": int(config.seed),
        "sensors": sensors,
        "imu": {
            "T_body_imu": pose_to_dict(pose_matrix(R_body_imu_true, info.T_body_imu[:3, 3])),
            "accel_bias_m_s2": [float(v) for v in accel_bias],
            "gyro_bias_rad_s": [float(v) for v in gyro_bias],
        },
        "legs": {
            "joint_offsets_rad": {k: float(v) for k, v in joint_offsets.items() if v != 0.0},
            "link_length_deltas_m": {k: float(v) for k, v in link_changes.items() if v != 0.0},
        },
        "effects": config.effects.to_dict(),
        "outliers": {int(k): int(v) for k, v in swapped.items()},
        "sessions": {
            s: {"T_world_stance": pose_to_dict(T), "feet_world": {f: [float(x) for x in p] for f, p in zip(info.feet, feet_world_real[s])}}
            for s, T in T_world_stance.items()
        },
        "stations": {
            int(r.station): {"T_world_body": pose_to_dict(r.T_world_body_real)} for r in records
        },
        "noise": {
            "tracking_sigma_rad": float(config.tracking_sigma_rad),
            "encoder_sigma_rad": float(config.encoder_sigma_rad),
            "joint_flex_sigma_rad": float(config.joint_flex_sigma_rad),
            "imu_accel_sigma_m_s2": float(config.imu_accel_sigma_m_s2),
            "imu_gyro_sigma_rad_s": float(config.imu_gyro_sigma_rad_s),
        },
    }
