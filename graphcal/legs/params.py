"""Kinematic parameters of a leg for identification, and the forward kinematics of a point on its foot.

:class:`LegModel` extends :class:`graphcal.models.leg_params.LegParameterization` (joint offsets
``<joint>.offset_rad``, link lengths ``<joint>.delta_m``) with 3-D origin translations
``<joint>.dx_m``, ``<joint>.dy_m``, ``<joint>.dz_m``: the change of a URDF joint's ``<origin xyz>``
in its parent link frame. By default only the FIRST moving joint gets them -- the hip position in
the body frame, which Yuan et al. write with the body length and width ``l_b``, ``w_b`` (their
lateral hip offset ``omega`` is the link from the hip joint to the thigh joint, i.e. the A1
``<leg>_thigh_joint.delta_m``). With ``origins="all"`` every moving joint (and the fixed joint that
carries the foot frame) gets a 3-D translation instead of its one link-length parameter, a model
close to a full geometric calibration (3 translations + the joint angle offset per joint; the
two remaining rotations per joint are not modelled).

Parameter order in ``theta`` (k,): all offsets (base -> foot), then the translation parameters
(link deltas and origin components, base -> foot). ``theta = 0`` is the nominal URDF.

:func:`point_kinematics` is vectorised over N configurations: the position of a point fixed in the
foot frame (a motion-capture marker ``p_foot_marker``) in the leg's base frame, its Jacobian with
respect to ``theta`` (analytic: a joint offset turns the point about the joint axis, a translation
parameter moves it along its direction), with respect to the measured joint values ``q`` (for
noise propagation) and the rotation of the foot frame (the Jacobian with respect to the marker
position is ``R_base_foot``).

Units: metres and radians. Frames: ``base`` is the leg's base frame (``RobotModel.base_frame``).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

from graphcal.errors import ModelError
from graphcal.geometry import invert_pose, matrix_from_rpy
from graphcal.models.leg_params import LegParameterization, leg_parameterization
from graphcal.models.perturb import LegPerturbation
from graphcal.models.robot import Leg, RobotModel

__all__ = [
    "ORIGIN_CHOICES",
    "LegModel",
    "PointKinematics",
    "leg_model",
    "point_kinematics",
    "perturbation_from_theta",
    "theta_from_perturbation",
]

#: Which joints get a 3-D origin translation: none, the first moving joint (hip position), or all.
ORIGIN_CHOICES = ("none", "first", "all")
_AXES = ("dx_m", "dy_m", "dz_m")


def _readonly(a) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class LegModel:
    """The identification parameters ``theta`` (k,) of one leg.

    Attributes:
        foot: foot frame of the leg (the frame a marker's position ``p_foot_marker`` is given in).
        joint_names: the leg's moving joints, base -> foot.
        joint_types: ``"revolute"`` / ``"prismatic"`` per joint.
        names: parameter names in ``theta`` order.
        offset_joints: joint index (into ``joint_names``) of each offset parameter (the first
            ``n_offsets`` entries of ``theta``).
        trans_joints: for each translation parameter, the index ``j`` of the :class:`Leg` placement
            it changes (``T_parent_joint[j]``, or ``n`` for ``T_lastjoint_foot``).
        trans_dirs: (n_trans, 3) unit directions, in the frame that placement is expressed in.
        trans_urdf_joints: URDF joint whose ``<origin xyz>`` each translation parameter changes
            (None for a ``<foot>.delta_m`` without URDF joint).
        trans_dirs_urdf: (n_trans, 3) the directions in that URDF joint's parent link frame.
        origins: ``"none"``, ``"first"`` or ``"all"`` (see module docstring).
    """

    foot: str
    joint_names: tuple[str, ...]
    joint_types: tuple[str, ...]
    names: tuple[str, ...]
    offset_joints: tuple[int, ...]
    trans_joints: tuple[int, ...]
    trans_dirs: np.ndarray
    trans_urdf_joints: tuple[str | None, ...]
    trans_dirs_urdf: np.ndarray
    origins: str = "first"

    @property
    def dim(self) -> int:
        """Number of parameters k."""
        return len(self.names)

    @property
    def n_offsets(self) -> int:
        """Number of joint offsets (first in ``theta``)."""
        return len(self.offset_joints)

    @property
    def n_trans(self) -> int:
        """Number of translation parameters (after the offsets)."""
        return len(self.trans_joints)

    def index(self, name: str) -> int:
        """Position of ``name`` in ``theta``; ModelError if unknown."""
        try:
            return self.names.index(name)
        except ValueError:
            raise ModelError(f"{name!r} is not a parameter of the leg of {self.foot!r}; "
                             f"parameters: {', '.join(self.names)}") from None

    def is_angle(self, i: int) -> bool:
        """True when parameter ``i`` is in radians (a revolute joint's offset)."""
        return self.names[i].endswith(".offset_rad")

    def check_leg(self, leg: Leg) -> None:
        """ModelError unless ``leg`` is the leg this model was built for."""
        if leg.foot != self.foot or tuple(leg.joint_names) != self.joint_names:
            raise ModelError(f"leg model of foot {self.foot!r} used with the leg of foot {leg.foot!r}")

    def check_theta(self, theta) -> np.ndarray:
        """``theta`` as a (k,) float array; ModelError on a wrong shape."""
        theta = np.asarray(theta, dtype=float)
        if theta.shape != (self.dim,):
            raise ModelError(f"leg of {self.foot!r} has {self.dim} parameters; theta must have shape "
                             f"({self.dim},), got {theta.shape}")
        return theta

    def as_dict(self, theta) -> dict[str, float]:
        """name -> value."""
        return {n: float(v) for n, v in zip(self.names, self.check_theta(theta))}


# ----------------------------------------------------------------------------- construction
def _urdf_joints(urdf_xml: str) -> dict[str, ET.Element]:
    return {j.get("name"): j for j in ET.fromstring(urdf_xml).findall("joint")}


def _urdf_origin(joint: ET.Element) -> np.ndarray:
    o = joint.find("origin")
    T = np.eye(4)
    if o is None:
        return T
    if o.get("xyz", "").strip():
        T[:3, 3] = [float(x) for x in o.get("xyz").split()]
    if o.get("rpy", "").strip():
        T[:3, :3] = matrix_from_rpy([float(x) for x in o.get("rpy").split()])
    return T


def _foot_fixed_joint(joints: dict[str, ET.Element], foot: str) -> ET.Element | None:
    for j in joints.values():
        c = j.find("child")
        if c is not None and c.get("link") == foot and j.get("type") == "fixed":
            return j
    return None


def leg_model(robot: RobotModel, foot: str, *, origins: str = "first", joint_offsets: bool = True,
              link_lengths: bool = True) -> LegModel:
    """The identification parameters of the leg of ``foot``.

    Args:
        robot: the robot (its URDF text gives the joint origins).
        foot: foot frame of the leg.
        origins: ``"first"`` (default): a 3-D translation of the first moving joint's origin (the
            hip position); ``"all"``: a 3-D translation of every moving joint's origin and of the
            fixed joint carrying the foot, replacing the link lengths; ``"none"``: neither.
        joint_offsets: include one offset per moving joint.
        link_lengths: include the link lengths of :func:`graphcal.models.leg_params.leg_parameterization`
            (ignored with ``origins="all"``, which contains them).

    Raises:
        ModelError: unknown ``origins``, ``foot`` not a foot of ``robot``, a leg joint missing from the URDF.
    """
    if origins not in ORIGIN_CHOICES:
        raise ModelError(f"origins must be one of {', '.join(ORIGIN_CHOICES)}, got {origins!r}")
    leg = robot.leg(foot)
    base: LegParameterization = leg_parameterization(
        robot, foot, joint_offsets=joint_offsets, link_lengths=link_lengths and origins != "all")
    names = list(base.names[: base.n_offsets])
    offset_joints = list(base.offset_joints)
    t_joints: list[int] = []
    t_dirs: list[np.ndarray] = []
    t_urdf: list[str | None] = []
    t_dirs_urdf: list[np.ndarray] = []
    t_names: list[str] = []
    joints = _urdf_joints(robot.urdf_xml)

    def add_origin(j: int, urdf_joint: ET.Element, T_leg: np.ndarray) -> None:
        # T_leg (the Leg placement) = T_prev_parentlink @ T_origin: an origin change d (parent link
        # frame) changes the placement's translation by R_prev_parentlink @ d
        R = (T_leg @ invert_pose(_urdf_origin(urdf_joint)))[:3, :3]
        for a, suffix in enumerate(_AXES):
            e = np.zeros(3)
            e[a] = 1.0
            t_joints.append(j)
            t_dirs.append(R @ e)
            t_urdf.append(urdf_joint.get("name"))
            t_dirs_urdf.append(e)
            t_names.append(f"{urdf_joint.get('name')}.{suffix}")

    n = leg.n_joints
    if origins in ("first", "all") and n > 0:
        for j in range(n if origins == "all" else 1):
            jname = leg.joint_names[j]
            if jname not in joints:
                raise ModelError(f"joint {jname!r} of the leg of {foot!r} is not a URDF joint")
            add_origin(j, joints[jname], leg.T_parent_joint[j])
    for i, j in enumerate(base.link_joints):
        t_joints.append(j)
        t_dirs.append(base.directions[i])
        t_urdf.append(base.link_urdf_joints[i])
        t_dirs_urdf.append(base.directions_urdf[i])
        t_names.append(base.names[base.n_offsets + i])
    if origins == "all":
        fj = _foot_fixed_joint(joints, foot)
        if fj is not None:
            add_origin(n, fj, leg.T_lastjoint_foot)
    # translation parameters base -> foot (stable within one joint)
    order = sorted(range(len(t_joints)), key=lambda i: t_joints[i])
    names += [t_names[i] for i in order]
    return LegModel(
        foot=foot,
        joint_names=tuple(leg.joint_names),
        joint_types=tuple(leg.joint_types),
        names=tuple(names),
        offset_joints=tuple(offset_joints),
        trans_joints=tuple(t_joints[i] for i in order),
        trans_dirs=_readonly(np.reshape([t_dirs[i] for i in order], (len(order), 3))),
        trans_urdf_joints=tuple(t_urdf[i] for i in order),
        trans_dirs_urdf=_readonly(np.reshape([t_dirs_urdf[i] for i in order], (len(order), 3))),
        origins=origins,
    )


# ----------------------------------------------------------------------------- kinematics
@dataclass(frozen=True, eq=False)
class PointKinematics:
    """Result of :func:`point_kinematics` for N configurations (base frame, m).

    Attributes:
        p_base_point: (N, 3) the point (marker) in the base frame.
        J_theta: (N, 3, k) d p_base_point / d theta.
        J_q: (N, 3, n) d p_base_point / d q (measured joint values).
        R_base_foot: (N, 3, 3) rotation of the foot frame (= d p_base_point / d p_foot_point).
        p_base_foot: (N, 3) the foot frame origin.
    """

    p_base_point: np.ndarray
    J_theta: np.ndarray
    J_q: np.ndarray
    R_base_foot: np.ndarray
    p_base_foot: np.ndarray


def _rodrigues(axis: np.ndarray, angles: np.ndarray) -> np.ndarray:
    K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    s = np.sin(angles)[:, None, None]
    c = np.cos(angles)[:, None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def point_kinematics(leg: Leg, model: LegModel, q, theta, p_foot_point=None) -> PointKinematics:
    """Position of a point fixed in the foot frame, and its Jacobians, for N configurations.

    Args:
        leg: the nominal leg (base frame -> foot frame).
        model: its :class:`LegModel`.
        q: (N, n) measured joint values (rad / m), ``leg.joint_names`` order; (n,) for one.
        theta: (k,) parameter values (``model.names`` order).
        p_foot_point: (3,) the point in the foot frame, m (default: the foot frame origin).

    Returns:
        :class:`PointKinematics` (arrays with a leading N axis, also for a single configuration).
    """
    model.check_leg(leg)
    theta = model.check_theta(theta)
    q = np.atleast_2d(np.asarray(q, dtype=float))
    n = leg.n_joints
    if q.shape[1] != n:
        raise ModelError(f"leg of {leg.foot!r} has {n} joints; q must have shape (N, {n}), got {q.shape}")
    m = np.zeros(3) if p_foot_point is None else np.asarray(p_foot_point, dtype=float).reshape(3)
    N = q.shape[0]
    k = model.dim
    no = model.n_offsets
    offsets = np.zeros(n)
    offsets[list(model.offset_joints)] = theta[:no]
    q_true = q + offsets
    tvals = theta[no:]
    # translation change of each placement (constant over the batch)
    dt = np.zeros((n + 1, 3))
    for i, j in enumerate(model.trans_joints):
        dt[j] += tvals[i] * model.trans_dirs[i]

    R = np.broadcast_to(np.eye(3), (N, 3, 3)).copy()
    p = np.zeros((N, 3))
    axes = np.empty((N, n, 3))
    origins = np.empty((N, n, 3))
    R_frame = np.empty((n + 1, N, 3, 3))  # rotation of the frame each placement is expressed in
    for j in range(n):
        T = leg.T_parent_joint[j]
        R_frame[j] = R
        p = p + R @ (T[:3, 3] + dt[j])
        R = R @ T[:3, :3]
        a = leg.axes[j]
        axes[:, j] = R @ a
        origins[:, j] = p
        if leg.joint_types[j] == "revolute":
            R = R @ _rodrigues(a, q_true[:, j])
        else:
            p = p + q_true[:, j, None] * axes[:, j]
    Tf = leg.T_lastjoint_foot
    R_frame[n] = R
    p_foot = p + R @ (Tf[:3, 3] + dt[n])
    R_foot = R @ Tf[:3, :3]
    point = p_foot + R_foot @ m

    J_q = np.empty((N, 3, n))
    for j in range(n):
        if leg.joint_types[j] == "revolute":
            J_q[:, :, j] = np.cross(axes[:, j], point - origins[:, j])
        else:
            J_q[:, :, j] = axes[:, j]
    J = np.empty((N, 3, k))
    if no:
        J[:, :, :no] = J_q[:, :, list(model.offset_joints)]
    for i, j in enumerate(model.trans_joints):
        J[:, :, no + i] = R_frame[j] @ model.trans_dirs[i]
    return PointKinematics(point, J, J_q, R_foot, p_foot)


# ----------------------------------------------------------------------------- URDF round trip
def perturbation_from_theta(model: LegModel, theta) -> LegPerturbation:
    """The :class:`~graphcal.models.perturb.LegPerturbation` equal to ``theta`` (URDF writing, tests).

    Raises:
        ModelError: a non-zero translation parameter without URDF joint (``<foot>.delta_m``).
    """
    theta = model.check_theta(theta)
    offs = {model.joint_names[j]: float(theta[i]) for i, j in enumerate(model.offset_joints)}
    deltas: dict[str, np.ndarray] = {}
    for i, (uj, u) in enumerate(zip(model.trans_urdf_joints, model.trans_dirs_urdf)):
        v = float(theta[model.n_offsets + i])
        if uj is None:
            if v != 0.0:
                raise ModelError(f"parameter {model.names[model.n_offsets + i]!r} has no URDF joint to carry it")
            continue
        deltas[uj] = deltas.get(uj, np.zeros(3)) + v * u
    return LegPerturbation(offs, {j: tuple(d) for j, d in deltas.items()})


def theta_from_perturbation(model: LegModel, pert: LegPerturbation, *, tol: float = 1e-12) -> np.ndarray:
    """The ``theta`` (k,) that reproduces ``pert`` on this leg (e.g. a simulation's truth).

    Offsets map one to one; an origin delta of a joint is projected on that joint's translation
    parameters (least squares over their directions in the URDF parent frame).

    Raises:
        ModelError: the perturbation touches a joint of the leg that the model cannot express (an
            offset without offset parameter, or an origin delta outside the span of the joint's
            translation directions, e.g. a sideways shift where only a link length is modelled).
    """
    theta = np.zeros(model.dim)
    joint_set = set(model.joint_names)
    for j, v in pert.joint_offsets_rad.items():
        if j not in joint_set:
            continue
        idx = [i for i, jj in enumerate(model.offset_joints) if model.joint_names[jj] == j]
        if not idx:
            raise ModelError(f"joint offset of {j!r} has no parameter in the leg model of {model.foot!r}")
        theta[idx[0]] = v
    for j, d in pert.origin_deltas_m.items():
        idx = [i for i, uj in enumerate(model.trans_urdf_joints) if uj == j]
        d = np.asarray(d, dtype=float)
        if not idx:
            if j in joint_set and np.linalg.norm(d) > tol:
                raise ModelError(f"origin delta of {j!r} has no parameter in the leg model of {model.foot!r}")
            continue
        U = model.trans_dirs_urdf[idx].T  # (3, m)
        x, *_ = np.linalg.lstsq(U, d, rcond=None)
        if np.linalg.norm(U @ x - d) > max(tol, 1e-9 * np.linalg.norm(d)):
            have = [model.names[model.n_offsets + i] for i in idx]
            raise ModelError(f"origin delta {d.tolist()} of {j!r} is not expressible by {have}")
        theta[[model.n_offsets + i for i in idx]] = x
    return theta
