"""Kinematic parameters of a leg (joint offsets, link lengths) and their analytic Jacobian.

A :class:`LegParameterization` names the calibration parameters ``theta`` (k,) of one leg:

* ``<joint>.offset_rad`` for each moving joint (``<joint>.offset_m`` for a prismatic one): the
  encoder zero error, ``q_true = q_measured + offset`` -- the same model as
  :func:`graphcal.models.perturb.apply_perturbation`'s ``joint_offsets_rad``;
* ``<joint>.delta_m`` for each link-length joint: every moving joint after the first (its origin
  translation is the previous link) and the FIXED URDF joint whose child link is the foot (the
  last link, e.g. ``<leg>_foot_joint`` of the built-in models). The link ending at joint ``j`` is
  lengthened by ``delta`` metres along its own direction ``u_j`` (the unit vector of the nominal
  URDF origin translation, in its parent frame) -- the same model as
  :func:`graphcal.models.perturb.link_length_delta`. If the foot frame is not the child of a
  URDF joint (e.g. a frame that is not a link), the parameter is called ``<foot>.delta_m`` and
  lengthens the translation of ``Leg.T_lastjoint_foot``. A joint whose origin has no translation
  (no link ends at it, e.g. two joint axes through one point) gets no ``delta_m`` parameter.

Parameter order: all offsets (base -> foot), then all link deltas (base -> foot, foot link last).
``theta = 0`` is the nominal URDF.

Forward kinematics with parameters (:func:`fk_with_params`) and its Jacobian with respect to
``theta`` (:func:`param_jacobian`) are vectorised over N configurations and expressed in the leg's
base frame (usually ``body``). Jacobian columns:

* offset of joint j: the joint's Jacobian column at ``q_true`` (``axis_j x (p_foot - origin_j)``
  for a revolute joint, ``axis_j`` for a prismatic one, in the base frame);
* delta of link j: ``R_base_parent(j) @ u_j``, the direction of the link in the base frame, where
  ``R_base_parent(j)`` is the rotation of the frame that link's origin translation is expressed in
  (the previous joint frame, after its motion). The foot position is linear in each link
  translation, so this column is exact.

Units: metres, radians.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

from graphcal.errors import ModelError
from graphcal.geometry import invert_pose, matrix_from_rpy
from graphcal.models.perturb import LegPerturbation
from graphcal.models.robot import Leg, RobotModel

__all__ = [
    "LegParameterization",
    "leg_parameterization",
    "fk_with_params",
    "param_jacobian",
    "fk_and_param_jacobian",
    "perturbation_from_params",
]

_ZERO_LINK_M = 1e-12


def _readonly(a) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class LegParameterization:
    """Names and geometry of the kinematic parameters ``theta`` (k,) of one leg.

    Attributes:
        foot: foot frame of the leg.
        joint_names: the leg's moving joints (base -> foot), to check that a :class:`Leg` matches.
        names: the k parameter names, in ``theta`` order (offsets first, then link deltas).
        offset_joints: for each offset parameter, the index of its joint in ``joint_names``.
        link_joints: for each link-delta parameter, the index ``j`` of the moving joint whose
            origin translation (``Leg.T_parent_joint[j]``) it changes, or ``n`` (the number of
            moving joints) for the foot link (``Leg.T_lastjoint_foot``).
        link_urdf_joints: for each link-delta parameter, the URDF joint whose ``<origin xyz>`` it
            changes, or ``None`` for a ``<foot>.delta_m`` parameter without a URDF joint.
        directions: (n_links, 3) unit link directions ``u_j`` in the frame of the :class:`Leg`
            placement they change (the previous moving joint's frame; the base frame for j = 0).
        directions_urdf: (n_links, 3) the same directions in the URDF joint's parent link frame
            (equal to ``directions`` unless fixed joints sit between the moving joints); NaN
            where ``link_urdf_joints`` is ``None``.
    """

    foot: str
    joint_names: tuple[str, ...]
    names: tuple[str, ...]
    offset_joints: tuple[int, ...]
    link_joints: tuple[int, ...]
    link_urdf_joints: tuple[str | None, ...]
    directions: np.ndarray
    directions_urdf: np.ndarray

    @property
    def dim(self) -> int:
        """Number of parameters k."""
        return len(self.names)

    @property
    def n_offsets(self) -> int:
        """Number of joint-offset parameters (they come first in ``theta``)."""
        return len(self.offset_joints)

    @property
    def n_links(self) -> int:
        """Number of link-delta parameters (they follow the offsets in ``theta``)."""
        return len(self.link_joints)

    def index(self, name: str) -> int:
        """Position of parameter ``name`` in ``theta``; ModelError if unknown."""
        try:
            return self.names.index(name)
        except ValueError:
            raise ModelError(
                f"{name!r} is not a parameter of the leg of {self.foot!r}; parameters: {', '.join(self.names)}"
            ) from None

    def zeros(self) -> np.ndarray:
        """The nominal parameter vector (k,) of zeros."""
        return np.zeros(self.dim)

    def prior_sigmas(self, sigma_offset_rad: float, sigma_delta_m: float) -> np.ndarray:
        """(k,) prior standard deviations: ``sigma_offset_rad`` for offsets, ``sigma_delta_m`` for links.

        A prismatic joint's offset gets ``sigma_delta_m`` (it is a length).
        """
        return np.array(
            [sigma_offset_rad if name.endswith(".offset_rad") else sigma_delta_m for name in self.names], dtype=float
        )

    def check_leg(self, leg: Leg) -> None:
        """ModelError unless ``leg`` is the leg this parameterization was built for."""
        if leg.foot != self.foot or tuple(leg.joint_names) != self.joint_names:
            raise ModelError(
                f"leg parameterization of foot {self.foot!r} (joints {', '.join(self.joint_names)}) used with the "
                f"leg of foot {leg.foot!r} (joints {', '.join(leg.joint_names)})"
            )

    def as_dict(self, theta) -> dict[str, float]:
        """name -> value of a parameter vector (k,)."""
        theta = self._check_theta(theta)
        return {n: float(v) for n, v in zip(self.names, theta)}

    def _check_theta(self, theta) -> np.ndarray:
        theta = np.asarray(theta, dtype=float)
        if theta.shape != (self.dim,):
            raise ModelError(
                f"leg of {self.foot!r} has {self.dim} kinematic parameters ({', '.join(self.names)}); "
                f"theta must have shape ({self.dim},), got {theta.shape}"
            )
        return theta


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


def leg_parameterization(
    robot: RobotModel,
    foot: str,
    *,
    joint_offsets: bool = True,
    link_lengths: bool = True,
) -> LegParameterization:
    """The kinematic parameters of the leg of ``foot`` (see module docstring for names and order).

    Args:
        robot: the robot model (its URDF text names the joints and gives the link directions).
        foot: foot frame of the leg.
        joint_offsets: include one offset per moving joint.
        link_lengths: include one length delta per link (moving joints after the first, and the
            joint attaching the foot frame).

    Raises:
        ModelError: ``foot`` is not a foot of ``robot``, or a joint of the leg is not in the URDF.
    """
    leg = robot.leg(foot)
    joints = _urdf_joints(robot.urdf_xml)
    names: list[str] = []
    offset_joints: list[int] = []
    if joint_offsets:
        for j, (jname, jtype) in enumerate(zip(leg.joint_names, leg.joint_types)):
            names.append(f"{jname}.offset_m" if jtype == "prismatic" else f"{jname}.offset_rad")
            offset_joints.append(j)
    link_joints: list[int] = []
    link_urdf: list[str | None] = []
    dirs: list[np.ndarray] = []
    dirs_urdf: list[np.ndarray] = []
    if link_lengths:
        for j in range(1, leg.n_joints):
            jname = leg.joint_names[j]
            if jname not in joints:
                raise ModelError(f"joint {jname!r} of the leg of {foot!r} is not a URDF joint")
            res = _link_direction(leg.T_parent_joint[j], _urdf_origin(joints[jname]))
            if res is None:
                continue
            names.append(f"{jname}.delta_m")
            link_joints.append(j)
            link_urdf.append(jname)
            dirs.append(res[0])
            dirs_urdf.append(res[1])
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
            names.append(pname)
            link_joints.append(leg.n_joints)
            link_urdf.append(urdf_name)
            dirs.append(res[0])
            dirs_urdf.append(res[1])
    return LegParameterization(
        foot=foot,
        joint_names=tuple(leg.joint_names),
        names=tuple(names),
        offset_joints=tuple(offset_joints),
        link_joints=tuple(link_joints),
        link_urdf_joints=tuple(link_urdf),
        directions=_readonly(np.reshape(dirs, (len(dirs), 3))),
        directions_urdf=_readonly(np.reshape(dirs_urdf, (len(dirs_urdf), 3))),
    )


def perturbation_from_params(param: LegParameterization, theta) -> LegPerturbation:
    """The :class:`~graphcal.models.perturb.LegPerturbation` equal to ``theta`` (for writing a URDF).

    Raises:
        ModelError: a non-zero ``<foot>.delta_m`` parameter has no URDF joint to carry it.
    """
    theta = param._check_theta(theta)
    offs = {param.joint_names[j]: float(theta[i]) for i, j in enumerate(param.offset_joints)}
    deltas = {}
    for i, (urdf_joint, u) in enumerate(zip(param.link_urdf_joints, param.directions_urdf)):
        val = float(theta[param.n_offsets + i])
        if urdf_joint is None:
            if val != 0.0:
                raise ModelError(
                    f"parameter {param.names[param.n_offsets + i]!r} has no URDF joint: cannot write it as an origin delta"
                )
            continue
        deltas[urdf_joint] = tuple(val * u)
    return LegPerturbation(offs, deltas)


# ----------------------------------------------------------------------------- kinematics
def _prepare(leg: Leg, param: LegParameterization, q, theta) -> tuple[np.ndarray, np.ndarray, bool]:
    from graphcal.models.kinematics import as_batch

    param.check_leg(leg)
    theta = param._check_theta(theta)
    q, single = as_batch(leg, q)
    return q, theta, single


def _fk(leg: Leg, param: LegParameterization, q: np.ndarray, theta: np.ndarray, want_jacobian: bool):
    """p_base_foot (N, 3) and, if asked, d p / d theta (N, 3, k)."""
    from graphcal.models.kinematics import rodrigues_batch

    N, n = q.shape
    offsets = np.zeros(n)
    offsets[list(param.offset_joints)] = theta[: param.n_offsets]
    q_true = q + offsets
    link_of = {j: i for i, j in enumerate(param.link_joints)}
    deltas = theta[param.n_offsets :]

    R = np.broadcast_to(np.eye(3), (N, 3, 3)).copy()
    p = np.zeros((N, 3))
    axes_base = np.empty((N, n, 3))
    origins = np.empty((N, n, 3))
    link_cols = np.empty((N, 3, param.n_links)) if want_jacobian else None
    for j in range(n):
        T = leg.T_parent_joint[j]
        t = T[:3, 3]
        if j in link_of:
            i = link_of[j]
            u = param.directions[i]
            t = t + deltas[i] * u
            if want_jacobian:
                link_cols[:, :, i] = R @ u
        p = p + R @ t
        R = R @ T[:3, :3]
        a = leg.axes[j]
        axes_base[:, j] = R @ a
        origins[:, j] = p
        if leg.joint_types[j] == "revolute":
            R = R @ rodrigues_batch(a, q_true[:, j])
        else:
            p = p + q_true[:, j, None] * axes_base[:, j]
    t = leg.T_lastjoint_foot[:3, 3]
    if n in link_of:
        i = link_of[n]
        u = param.directions[i]
        t = t + deltas[i] * u
        if want_jacobian:
            link_cols[:, :, i] = R @ u
    p_foot = p + R @ t
    if not want_jacobian:
        return p_foot, None
    J = np.empty((N, 3, param.dim))
    for i, j in enumerate(param.offset_joints):
        if leg.joint_types[j] == "revolute":
            J[:, :, i] = np.cross(axes_base[:, j], p_foot - origins[:, j])
        else:
            J[:, :, i] = axes_base[:, j]
    J[:, :, param.n_offsets :] = link_cols
    return p_foot, J


def fk_with_params(leg: Leg, param: LegParameterization, q, theta) -> np.ndarray:
    """Foot positions of the leg with kinematic parameters ``theta``.

    Args:
        leg: the nominal leg.
        param: its parameterization (built for this leg).
        q: (N, n) measured joint values (rad / m), :attr:`Leg.joint_names` order; (n,) for one.
        theta: (k,) parameter values, ``param.names`` order.

    Returns:
        p_base_foot (N, 3), m, in the leg's base frame ((3,) for a single configuration).
    """
    q, theta, single = _prepare(leg, param, q, theta)
    p, _ = _fk(leg, param, q, theta, False)
    return p[0] if single else p


def param_jacobian(leg: Leg, param: LegParameterization, q, theta) -> np.ndarray:
    """d p_base_foot / d theta, (N, 3, k) ((3, k) for a single configuration); see module docstring."""
    q, theta, single = _prepare(leg, param, q, theta)
    _, J = _fk(leg, param, q, theta, True)
    return J[0] if single else J


def fk_and_param_jacobian(leg: Leg, param: LegParameterization, q, theta) -> tuple[np.ndarray, np.ndarray]:
    """(:func:`fk_with_params`, :func:`param_jacobian`) in one pass over the chain."""
    q, theta, single = _prepare(leg, param, q, theta)
    p, J = _fk(leg, param, q, theta, True)
    return (p[0], J[0]) if single else (p, J)
