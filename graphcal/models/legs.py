"""The one kinematic model of a leg: its parameters ``theta`` (joint offsets, link lengths, joint
origins) and the forward kinematics of a point on its foot, with its Jacobians.

:class:`LegModel` names the parameters of one leg, used by the calibration
(:mod:`graphcal.factors.stance_foot`) and by Yuan's leg identification (:mod:`graphcal.legs`,
:mod:`graphcal.factors.mocap_marker`); ``theta = 0`` is the nominal URDF. :func:`point_kinematics`
is vectorised over N configurations: the point in the leg's base frame and its Jacobians in
``theta``, in the measured joint values ``q`` and the foot frame's rotation.

Units: metres, radians. Frames: ``base`` is the leg's base frame (``RobotModel.base_frame``).
The parameters, their order and the Jacobian columns: docs/factors.md, "Leg parameters";
docs/legs.md, "The model".
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

from graphcal.errors import ModelError
from graphcal.geometry import invert_pose, matrix_from_rpy
from graphcal.models.kinematics import as_batch, chain_frames, position_jacobian
from graphcal.models.perturb import LegPerturbation
from graphcal.models.robot import Leg, RobotModel

__all__ = [
    "ORIGIN_CHOICES",
    "LegModel",
    "PointKinematics",
    "leg_model",
    "point_kinematics",
    "fk_with_params",
    "param_jacobian",
    "fk_and_param_jacobian",
    "perturbation_from_theta",
    "theta_from_perturbation",
]

#: Which joints get a 3-D origin translation: none, the first moving joint (hip position), or all.
ORIGIN_CHOICES = ("none", "first", "all")
_AXES = ("dx_m", "dy_m", "dz_m")
_ZERO_LINK_M = 1e-12


def _readonly(a) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a



@dataclass(frozen=True, eq=False)
class LegModel:
    """Names and geometry of the kinematic parameters ``theta`` (k,) of one leg.

    Attributes:
        foot: foot frame of the leg (the frame a marker's position ``p_foot_marker`` is given in).
        joint_names: the leg's moving joints (base -> foot), to check that a :class:`Leg` matches.
        joint_types: ``"revolute"`` / ``"prismatic"`` per joint.
        names: the k parameter names, in ``theta`` order (offsets first, then translations).
        offset_joints: for each offset parameter, the index of its joint in ``joint_names`` (the
            first ``n_offsets`` entries of ``theta``).
        trans_joints: for each translation parameter, the index ``j`` of the :class:`Leg`
            placement it changes (``T_parent_joint[j]``, or ``n``, the number of moving joints,
            for ``T_lastjoint_foot``).
        trans_dirs: (n_trans, 3) unit directions, in the frame that placement is expressed in
            (the previous moving joint's frame; the base frame for j = 0).
        trans_urdf_joints: URDF joint whose ``<origin xyz>`` each translation parameter changes
            (None for a ``<foot>.delta_m`` without URDF joint).
        trans_dirs_urdf: (n_trans, 3) the directions in that URDF joint's parent link frame (equal
            to ``trans_dirs`` unless fixed joints sit between the moving joints); NaN where
            ``trans_urdf_joints`` is None.
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
        """Number of joint-offset parameters (they come first in ``theta``)."""
        return len(self.offset_joints)

    @property
    def n_trans(self) -> int:
        """Number of translation parameters (they follow the offsets in ``theta``)."""
        return len(self.trans_joints)

    def index(self, name: str) -> int:
        """Position of parameter ``name`` in ``theta``; ModelError if unknown."""
        try:
            return self.names.index(name)
        except ValueError:
            raise ModelError(
                f"{name!r} is not a parameter of the leg of {self.foot!r}; parameters: {', '.join(self.names)}"
            ) from None

    def is_angle(self, i: int) -> bool:
        """True when parameter ``i`` is in radians (a revolute joint's offset)."""
        return self.names[i].endswith(".offset_rad")

    def zeros(self) -> np.ndarray:
        """The nominal parameter vector (k,) of zeros."""
        return np.zeros(self.dim)

    def prior_sigmas(self, sigma_offset_rad: float, sigma_delta_m: float) -> np.ndarray:
        """(k,) prior standard deviations: ``sigma_offset_rad`` for offsets, ``sigma_delta_m`` for lengths.

        A prismatic joint's offset gets ``sigma_delta_m`` (it is a length).
        """
        return np.array(
            [sigma_offset_rad if name.endswith(".offset_rad") else sigma_delta_m for name in self.names], dtype=float
        )

    def check_leg(self, leg: Leg) -> None:
        """ModelError unless ``leg`` is the leg this model was built for."""
        if leg.foot != self.foot or tuple(leg.joint_names) != self.joint_names:
            raise ModelError(
                f"leg model of foot {self.foot!r} (joints {', '.join(self.joint_names)}) used with the "
                f"leg of foot {leg.foot!r} (joints {', '.join(leg.joint_names)})"
            )

    def check_theta(self, theta) -> np.ndarray:
        """``theta`` as a (k,) float array; ModelError on a wrong shape."""
        theta = np.asarray(theta, dtype=float)
        if theta.shape != (self.dim,):
            raise ModelError(
                f"leg of {self.foot!r} has {self.dim} kinematic parameters ({', '.join(self.names)}); "
                f"theta must have shape ({self.dim},), got {theta.shape}"
            )
        return theta

    def as_dict(self, theta) -> dict[str, float]:
        """name -> value of a parameter vector (k,)."""
        return {n: float(v) for n, v in zip(self.names, self.check_theta(theta))}


# ----------------------------------------------------------------------------- construction
def _urdf_joints(urdf_xml: str) -> dict[str, ET.Element]:
    try:
        root = ET.fromstring(urdf_xml)
    except ET.ParseError as exc:  # load_robot has parsed it already; kept for robustness
        raise ModelError(f"URDF is not valid XML: {exc}") from None
    return {j.get("name"): j for j in root.findall("joint")}


def _urdf_origin(joint: ET.Element) -> np.ndarray:
    """4x4 placement of a URDF joint's origin in its parent link frame."""
    o = joint.find("origin")
    T = np.eye(4)
    if o is None:
        return T
    xyz = o.get("xyz")
    rpy = o.get("rpy")
    if xyz and xyz.strip():
        T[:3, 3] = [float(x) for x in xyz.split()]
    if rpy and rpy.strip():
        T[:3, :3] = matrix_from_rpy([float(x) for x in rpy.split()])
    return T


def _foot_fixed_joint(joints: dict[str, ET.Element], foot: str) -> ET.Element | None:
    """The FIXED URDF joint whose child link is ``foot``, else None."""
    for j in joints.values():
        c = j.find("child")
        if c is not None and c.get("link") == foot and j.get("type") == "fixed":
            return j
    return None


def _foot_joint(joints: dict[str, ET.Element], foot: str) -> ET.Element | None:
    """The URDF joint whose child link is ``foot`` (or the joint named ``foot``), else None."""
    for j in joints.values():
        c = j.find("child")
        if c is not None and c.get("link") == foot:
            return j
    return joints.get(foot)


def _link_direction(T_leg: np.ndarray, T_origin: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
    """(u in the Leg placement's frame, u in the URDF parent link frame), or None without a link.

    ``T_leg`` is the :class:`Leg` placement (``T_parent_joint[j]`` or ``T_lastjoint_foot``); it equals
    ``T_prev_parentlink @ T_origin`` where ``T_prev_parentlink`` collects the fixed joints between
    the previous moving joint and the URDF joint. Adding ``delta * u_urdf`` to the origin translation
    adds ``delta * R_prev_parentlink @ u_urdf`` to the Leg placement's translation.
    """
    if T_origin is None:
        t = T_leg[:3, 3]
        n = np.linalg.norm(t)
        if n < _ZERO_LINK_M:
            return None
        return t / n, np.full(3, np.nan)
    xyz = T_origin[:3, 3]
    n = np.linalg.norm(xyz)
    if n < _ZERO_LINK_M:
        return None
    u_urdf = xyz / n
    T_prev_parent = T_leg @ invert_pose(T_origin)
    u = T_prev_parent[:3, :3] @ u_urdf
    return u / np.linalg.norm(u), u_urdf


def _link_parameters(leg: Leg, joints: dict[str, ET.Element], foot: str) -> list[tuple]:
    """(placement j, direction, URDF joint or None, URDF direction, name) of each link-length parameter."""
    out = []
    for j in range(1, leg.n_joints):
        jname = leg.joint_names[j]
        if jname not in joints:
            raise ModelError(f"joint {jname!r} of the leg of {foot!r} is not a URDF joint")
        res = _link_direction(leg.T_parent_joint[j], _urdf_origin(joints[jname]))
        if res is not None:
            out.append((j, res[0], jname, res[1], f"{jname}.delta_m"))
    fj = _foot_joint(joints, foot)
    if fj is not None and fj.get("type") == "fixed":
        res = _link_direction(leg.T_lastjoint_foot, _urdf_origin(fj))
        pname, urdf_name = f"{fj.get('name')}.delta_m", fj.get("name")
    elif fj is not None and fj.get("name") in leg.joint_names:
        res = None  # the foot is the child link of the last moving joint: no link after it
    else:
        res = _link_direction(leg.T_lastjoint_foot, None)
        pname, urdf_name = f"{foot}.delta_m", None
    if res is not None:
        out.append((leg.n_joints, res[0], urdf_name, res[1], pname))
    return out


def _origin_parameters(j: int, urdf_joint: ET.Element, T_leg: np.ndarray) -> list[tuple]:
    """(placement j, direction, URDF joint, URDF direction, name) of a joint's 3-D origin translation.

    ``T_leg`` (the :class:`Leg` placement) = ``T_prev_parentlink @ T_origin``: an origin change d
    (parent link frame) changes the placement's translation by ``R_prev_parentlink @ d``.
    """
    R = (T_leg @ invert_pose(_urdf_origin(urdf_joint)))[:3, :3]
    out = []
    for a, suffix in enumerate(_AXES):
        e = np.zeros(3)
        e[a] = 1.0
        out.append((j, R @ e, urdf_joint.get("name"), e, f"{urdf_joint.get('name')}.{suffix}"))
    return out


def leg_model(
    robot: RobotModel,
    foot: str,
    *,
    origins: str = "first",
    joint_offsets: bool = True,
    link_lengths: bool = True,
) -> LegModel:
    """The kinematic parameters of the leg of ``foot`` (see module docstring for names and order).

    Args:
        robot: the robot model (its URDF text names the joints and gives the link directions).
        foot: foot frame of the leg.
        origins: ``"first"`` (default): a 3-D translation of the first moving joint's origin (the
            hip position); ``"all"``: a 3-D translation of every moving joint's origin and of the
            fixed joint carrying the foot, replacing the link lengths; ``"none"``: neither (the
            calibration's model: offsets and link lengths).
        joint_offsets: include one offset per moving joint.
        link_lengths: include one length delta per link (moving joints after the first, and the
            joint attaching the foot frame); ignored with ``origins="all"``, which contains them.

    Raises:
        ModelError: unknown ``origins``, ``foot`` not a foot of ``robot``, a leg joint missing from the URDF.
    """
    if origins not in ORIGIN_CHOICES:
        raise ModelError(f"origins must be one of {', '.join(ORIGIN_CHOICES)}, got {origins!r}")
    leg = robot.leg(foot)
    joints = _urdf_joints(robot.urdf_xml)
    names: list[str] = []
    offset_joints: list[int] = []
    if joint_offsets:
        for j, (jname, jtype) in enumerate(zip(leg.joint_names, leg.joint_types)):
            names.append(f"{jname}.offset_m" if jtype == "prismatic" else f"{jname}.offset_rad")
            offset_joints.append(j)
    trans: list[tuple] = []
    n = leg.n_joints
    if origins in ("first", "all") and n > 0:
        for j in range(n if origins == "all" else 1):
            jname = leg.joint_names[j]
            if jname not in joints:
                raise ModelError(f"joint {jname!r} of the leg of {foot!r} is not a URDF joint")
            trans += _origin_parameters(j, joints[jname], leg.T_parent_joint[j])
    if link_lengths and origins != "all":
        trans += _link_parameters(leg, joints, foot)
    if origins == "all":
        fj = _foot_fixed_joint(joints, foot)
        if fj is not None:
            trans += _origin_parameters(n, fj, leg.T_lastjoint_foot)
    trans.sort(key=lambda t: t[0])  # translation parameters base -> foot (stable within one joint)
    names += [t[4] for t in trans]
    return LegModel(
        foot=foot,
        joint_names=tuple(leg.joint_names),
        joint_types=tuple(leg.joint_types),
        names=tuple(names),
        offset_joints=tuple(offset_joints),
        trans_joints=tuple(t[0] for t in trans),
        trans_dirs=_readonly(np.reshape([t[1] for t in trans], (len(trans), 3))),
        trans_urdf_joints=tuple(t[2] for t in trans),
        trans_dirs_urdf=_readonly(np.reshape([t[3] for t in trans], (len(trans), 3))),
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


def _chain(leg: Leg, model: LegModel, q: np.ndarray, theta: np.ndarray):
    """:func:`graphcal.models.kinematics.chain_frames` at ``q_true = q + offsets`` with the
    translation parameters applied."""
    n = leg.n_joints
    no = model.n_offsets
    offsets = np.zeros(n)
    offsets[list(model.offset_joints)] = theta[:no]
    tvals = theta[no:]
    # translation change of each placement (constant over the batch)
    dt = np.zeros((n + 1, 3))
    for i, j in enumerate(model.trans_joints):
        dt[j] += tvals[i] * model.trans_dirs[i]
    return chain_frames(leg, q + offsets, dt)


def _theta_jacobian(model: LegModel, J_q: np.ndarray, R_frames) -> np.ndarray:
    """d p / d theta (N, 3, k) from the point's joint Jacobian (N, 3, n) and the placement frames."""
    no = model.n_offsets
    J = np.empty((J_q.shape[0], 3, model.dim))
    if no:
        J[:, :, :no] = J_q[:, :, list(model.offset_joints)]
    for i, j in enumerate(model.trans_joints):
        J[:, :, no + i] = R_frames[j] @ model.trans_dirs[i]
    return J


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
    q, _ = as_batch(leg, q)
    m = np.zeros(3) if p_foot_point is None else np.asarray(p_foot_point, dtype=float).reshape(3)
    axes, origins, R_frames, R_foot, p_foot = _chain(leg, model, q, theta)
    point = p_foot + R_foot @ m
    J_q = position_jacobian(leg.joint_types, axes, origins, point)
    return PointKinematics(point, _theta_jacobian(model, J_q, R_frames), J_q, R_foot, p_foot)


def fk_with_params(leg: Leg, model: LegModel, q, theta) -> np.ndarray:
    """Foot positions of the leg with kinematic parameters ``theta``.

    Args:
        leg: the nominal leg.
        model: its :class:`LegModel` (built for this leg).
        q: (N, n) measured joint values (rad / m), :attr:`Leg.joint_names` order; (n,) for one.
        theta: (k,) parameter values, ``model.names`` order.

    Returns:
        p_base_foot (N, 3), m, in the leg's base frame ((3,) for a single configuration).
    """
    model.check_leg(leg)
    theta = model.check_theta(theta)
    q, single = as_batch(leg, q)
    p = _chain(leg, model, q, theta)[4]
    return p[0] if single else p


def fk_and_param_jacobian(leg: Leg, model: LegModel, q, theta) -> tuple[np.ndarray, np.ndarray]:
    """(:func:`fk_with_params`, :func:`param_jacobian`) in one pass over the chain."""
    model.check_leg(leg)
    theta = model.check_theta(theta)
    q, single = as_batch(leg, q)
    axes, origins, R_frames, _, p = _chain(leg, model, q, theta)
    J_off = position_jacobian(leg.joint_types, axes, origins, p)
    J = _theta_jacobian(model, J_off, R_frames)
    return (p[0], J[0]) if single else (p, J)


def param_jacobian(leg: Leg, model: LegModel, q, theta) -> np.ndarray:
    """d p_base_foot / d theta, (N, 3, k) ((3, k) for a single configuration); see module docstring."""
    return fk_and_param_jacobian(leg, model, q, theta)[1]


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
