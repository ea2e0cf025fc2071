"""Robot models: any URDF through Pinocchio (fixed base); legs are chains base frame -> foot frame.

A :class:`Leg` is the chain of moving 1-DOF joints (revolute, continuous, prismatic) from the base
frame down to a foot frame. Fixed joints are folded into the placements, so a leg is fully described
by, for each moving joint ``j`` (base -> foot order):

* ``T_parent_joint[j]`` (4x4): the fixed placement of joint frame ``j`` at zero joint value, in the
  previous joint's frame (the first one in the *base frame*, which may itself sit anywhere below
  the URDF root);
* ``axes[j]`` (3,): the unit joint axis in joint frame ``j`` (rotation axis of a revolute joint,
  translation direction of a prismatic one);

plus ``T_lastjoint_foot`` (4x4), the foot frame in the last joint frame. With ``M_j(q_j)`` the joint
motion (``Rot(axis, q_j)`` or ``Trans(axis * q_j)``):

    T_base_foot(q) = T_parent_joint[0] M_0(q_0) T_parent_joint[1] M_1(q_1) ... T_lastjoint_foot

Units: metres and radians. Poses are 4x4 numpy arrays, ``T_a_b`` maps b-coordinates to a
(see :mod:`graphcal.geometry`). :meth:`RobotModel.fk_pinocchio` is the reference implementation
used to test the vectorised kinematics in :mod:`graphcal.models.kinematics`.
"""

from __future__ import annotations

import contextlib
import difflib
import os
import stat
import sys
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from graphcal.errors import ModelError, excerpt
from graphcal.geometry import from_pinocchio_se3, invert_pose, tangent_from_pinocchio

__all__ = ["Leg", "RobotModel", "load_robot"]

_REVOLUTE_SHORTNAMES = ("JointModelRX", "JointModelRY", "JointModelRZ", "JointModelRevoluteUnaligned")
_UNBOUNDED_SHORTNAMES = ("JointModelRUBX", "JointModelRUBY", "JointModelRUBZ", "JointModelRevoluteUnboundedUnaligned")
_PRISMATIC_SHORTNAMES = ("JointModelPX", "JointModelPY", "JointModelPZ", "JointModelPrismaticUnaligned")
#: what an origin of a URDF may hold: a robot is smaller than a kilometre, and an angle is written
#: within a few turns (an origin at 1e300 reached the solvers as a noise error)
_MAX_URDF_XYZ_M = 1e3
_MAX_URDF_RPY_RAD = 8 * np.pi


def _readonly(a) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


def _suggest(name: str, candidates: Sequence[str], n: int = 4) -> str:
    """' (close: a, b)' or ' (available: ...)' text for error messages."""
    close = difflib.get_close_matches(name, list(candidates), n=n, cutoff=0.5)
    if close:
        return "; did you mean " + ", ".join(repr(c) for c in close) + "?"
    shown = list(candidates)[:12]
    more = ", ..." if len(candidates) > 12 else ""
    return "; available: " + ", ".join(repr(c) for c in shown) + more


@dataclass(frozen=True, eq=False)
class Leg:
    """One leg: the moving joints from the base frame to a foot frame (see module docstring).

    Attributes:
        foot: foot frame name (a URDF link or joint name).
        joint_names: moving joint names, base -> foot order.
        joint_types: ``"revolute"`` (also URDF ``continuous``) or ``"prismatic"`` per joint.
        axes: (n, 3) unit joint axes, each in its own joint frame.
        T_parent_joint: (n, 4, 4) placement of each joint frame (at q_j = 0) in the previous joint
            frame; the first one in the base frame. Metres.
        T_lastjoint_foot: (4, 4) foot frame in the last joint frame (in the base frame if n = 0).
        lower, upper: (n,) joint limits (rad or m); -inf/+inf where the URDF has none
            (continuous joints).
        base_frame: the frame the leg hangs from.
    """

    foot: str
    joint_names: tuple[str, ...]
    joint_types: tuple[str, ...]
    axes: np.ndarray
    T_parent_joint: np.ndarray
    T_lastjoint_foot: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    base_frame: str = "body"

    @property
    def n_joints(self) -> int:
        """Number of moving joints of the leg."""
        return len(self.joint_names)

    def outside_limits(self, q, tol: float = 1e-3) -> np.ndarray:
        """Which joint values ``q`` (..., n) (rad or m) lie more than ``tol`` outside the URDF's limits;
        joints without usable limits (infinite, or ``lower >= upper`` as a URDF without a ``<limit>``
        gives) are never outside."""
        q = np.asarray(q, dtype=float)
        known = np.isfinite(self.lower) & np.isfinite(self.upper) & (self.lower < self.upper)
        return known & ((q < self.lower - tol) | (q > self.upper + tol))

    def joint_index(self, joint: str) -> int:
        """Position of ``joint`` in :attr:`joint_names`; ModelError if it is not in this leg."""
        try:
            return self.joint_names.index(joint)
        except ValueError:
            raise ModelError(
                f"joint {joint!r} is not in the leg of foot {self.foot!r}{_suggest(joint, self.joint_names)}"
            ) from None


@dataclass(frozen=True, eq=False)
class RobotModel:
    """A URDF robot with a fixed base and its legs.

    Attributes:
        name: built-in model name, or the URDF ``<robot name>``.
        urdf_xml: the URDF text the model was built from.
        base_frame: frame the legs hang from (usually the ``body`` link).
        feet: foot frame names, in the order given.
        pin_model: ``pinocchio.Model`` (fixed base). Never mutated.
        joint_names: every moving 1-DOF joint of the URDF, Pinocchio order.
        frame_names: every Pinocchio frame name (links, joints, fixed joints).
        legs: foot -> :class:`Leg`.
    """

    name: str
    urdf_xml: str
    base_frame: str
    feet: tuple[str, ...]
    pin_model: object
    joint_names: tuple[str, ...]
    frame_names: tuple[str, ...]
    legs: dict

    def leg(self, foot: str) -> Leg:
        """The :class:`Leg` ending at foot frame ``foot``; ModelError if it is not one of the feet."""
        try:
            return self.legs[foot]
        except KeyError:
            raise ModelError(f"{foot!r} is not a foot of robot {self.name!r}{_suggest(foot, self.feet)}") from None

    def neutral_q(self) -> dict[str, float]:
        """joint name -> 0.0 for every moving joint of the URDF."""
        return {j: 0.0 for j in self.joint_names}

    def leg_of_joint(self, joint: str) -> Leg:
        """The leg containing moving joint ``joint``; ModelError if none does."""
        for leg in self.legs.values():
            if joint in leg.joint_names:
                return leg
        raise ModelError(f"joint {joint!r} belongs to no leg of robot {self.name!r}{_suggest(joint, self.joint_names)}")

    # ------------------------------------------------------------------ Pinocchio reference
    def _pin_q(self, foot: str, q_leg) -> np.ndarray:
        import pinocchio as pin

        leg = self.leg(foot)
        q_leg = np.asarray(q_leg, dtype=float).reshape(-1)
        if q_leg.shape != (leg.n_joints,):
            raise ModelError(f"foot {foot!r}: expected {leg.n_joints} joint values, got shape {q_leg.shape}")
        m = self.pin_model
        q = pin.neutral(m)
        for name, val in zip(leg.joint_names, q_leg):
            jm = m.joints[m.getJointId(name)]
            if jm.nq == 2:  # continuous joint: (cos, sin)
                q[jm.idx_q] = np.cos(val)
                q[jm.idx_q + 1] = np.sin(val)
            else:
                q[jm.idx_q] = val
        return q

    def fk_pinocchio(self, foot: str, q_leg) -> np.ndarray:
        """Reference forward kinematics with Pinocchio, one configuration.

        Args:
            foot: foot frame name.
            q_leg: (n,) joint values of that leg (rad / m), :attr:`Leg.joint_names` order; every
                other joint of the robot at zero.

        Returns:
            T_base_foot (4x4), metres.
        """
        import pinocchio as pin

        m = self.pin_model
        data = m.createData()
        q = self._pin_q(foot, q_leg)
        pin.forwardKinematics(m, data, q)
        pin.updateFramePlacements(m, data)
        T_world_base = from_pinocchio_se3(data.oMf[_frame_id(m, self.base_frame)])
        T_world_foot = from_pinocchio_se3(data.oMf[_frame_id(m, foot)])
        return invert_pose(T_world_base) @ T_world_foot

    def jacobian_pinocchio(self, foot: str, q_leg) -> np.ndarray:
        """Reference foot position Jacobian with Pinocchio: (3, n) d p_base_foot / d q_leg.

        Uses the frame Jacobian in LOCAL_WORLD_ALIGNED (linear rows), rotated into the base frame.
        """
        import pinocchio as pin

        m = self.pin_model
        leg = self.leg(foot)
        data = m.createData()
        q = self._pin_q(foot, q_leg)
        pin.computeJointJacobians(m, data, q)
        pin.updateFramePlacements(m, data)
        J6 = pin.getFrameJacobian(m, data, _frame_id(m, foot), pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        J_lin_world = tangent_from_pinocchio(J6)[3:6]  # [omega, v] -> v rows
        R_world_base = from_pinocchio_se3(data.oMf[_frame_id(m, self.base_frame)])[:3, :3]
        cols = [m.joints[m.getJointId(name)].idx_v for name in leg.joint_names]
        return R_world_base.T @ J_lin_world[:, cols]


# ----------------------------------------------------------------------------- loading
def _frame_id(m, name: str) -> int:
    """Pinocchio frame id of ``name``, preferring the link (BODY) frame."""
    import pinocchio as pin

    if m.existFrame(name, pin.FrameType.BODY):
        return m.getFrameId(name, pin.FrameType.BODY)
    return m.getFrameId(name)


def _read_urdf_text(urdf, urdf_xml, model) -> tuple[str, str | None, str]:
    """(xml text, built-in name or None, description for messages)."""
    given = sum(x is not None for x in (urdf, urdf_xml, model))
    if given != 1:
        raise ModelError(
            f"load_robot needs exactly one of urdf (file path), urdf_xml (string) or model (built-in name); got {given}"
        )
    if model is not None:
        from graphcal.models.builtin import BUILTIN_MODELS, builtin_urdf

        if model not in BUILTIN_MODELS:
            raise ModelError(f"unknown built-in robot model {model!r}{_suggest(str(model), BUILTIN_MODELS)}")
        return builtin_urdf(model), model, f"built-in model {model!r}"
    if urdf is not None:
        path = Path(urdf)
        try:
            if path.exists() and not stat.S_ISREG(os.stat(path).st_mode):  # a FIFO would block the read
                raise OSError(f"{str(path)!r} is not a regular file (a named pipe, device or folder)")
            return path.read_text(encoding="utf-8"), None, f"URDF file {str(path)!r}"
        except (OSError, UnicodeDecodeError) as exc:
            raise ModelError(f"cannot read URDF file {str(path)!r}: {exc}") from None
    return str(urdf_xml), None, "URDF string"


def _check_urdf_numbers(root: ET.Element, what: str) -> None:
    """Every ``origin`` (xyz, rpy) and joint ``axis`` (xyz) of a URDF holds three finite numbers and
    an axis is not zero: :class:`ModelError` naming the joint or link (urdfdom would print a page of
    C++ errors and say only that the model is invalid; a zero axis became NaN)."""
    for parent in root.iter():
        owner = excerpt(parent.get("name") or parent.tag, 60)
        for child in parent:
            if child.tag == "origin":
                attrs = ("xyz", "rpy")
            elif child.tag == "axis" and parent.tag == "joint":
                attrs = ("xyz",)
            else:
                continue
            for attr in attrs:
                raw = child.get(attr)
                if raw is None:
                    continue
                try:
                    v = [float(x) for x in raw.split()]
                except ValueError:
                    v = []
                if len(v) != 3 or not all(np.isfinite(v)):
                    raise ModelError(f"{what}: {parent.tag} {owner!r}: <{child.tag} {attr}>: expected three finite "
                                     f"numbers, got {excerpt(repr(raw), 60)}")
                limit = _MAX_URDF_RPY_RAD if attr == "rpy" else _MAX_URDF_XYZ_M
                if child.tag == "origin" and max(abs(x) for x in v) > limit:
                    unit = "rad, a few turns" if attr == "rpy" else "m, a robot's size"
                    raise ModelError(f"{what}: {parent.tag} {owner!r}: <origin {attr}>: expected values within "
                                     f"+-{limit:g} ({unit}), got {excerpt(repr(raw), 60)}")
                if child.tag == "axis" and not any(v) and parent.get("type") in ("revolute", "continuous", "prismatic"):
                    raise ModelError(f"{what}: joint {owner!r}: <axis xyz>: expected a nonzero axis, got {raw!r}")


@contextlib.contextmanager
def _parser_stderr() -> Iterator[list[str]]:
    """Hold what the URDF parser (urdfdom, C++) writes to the process's standard error, file
    descriptor 2, during the block (it prints 2-8 lines per error, before graphcal's own line):
    yields a list that holds the text once the block is over. Python's ``sys.stderr`` is flushed
    first, so nothing of graphcal's own is caught."""
    said: list[str] = []
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no fd 2 (an embedded interpreter): leave it
        yield said
        return
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            yield said
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            held.seek(0)
            said.append(held.read(1 << 16).decode("utf-8", "replace"))


def _parser_errors(text: str) -> str:
    """The urdfdom messages of ``text`` in one line, most specific first ('Joint [j] is of type
    REVOLUTE but it does not specify limits; joint xml is not initialized correctly'), without the
    C++ source lines ('at line 607 in .../joint.cpp')."""
    lines = [ln.strip() for ln in text.splitlines()]
    errors = [ln[len("Error:"):].strip() for ln in lines if ln.startswith("Error:")]
    return "; ".join(dict.fromkeys(e for e in errors if e))


def load_robot(
    urdf: str | Path | None = None,
    *,
    model: str | None = None,
    base_frame: str = "body",
    feet: Sequence[str] = (),
    urdf_xml: str | None = None,
) -> RobotModel:
    """Load a robot (fixed base) from a URDF file, a URDF string or a built-in model name.

    Args:
        urdf: path of a URDF file.
        model: built-in model name (see :data:`graphcal.models.builtin.BUILTIN_MODELS`).
        base_frame: the frame the legs hang from (link or joint frame name).
        feet: foot frame names; empty for a built-in model means its default feet; empty for a
            URDF means no legs.
        urdf_xml: URDF text.

    Exactly one of ``urdf``, ``urdf_xml``, ``model`` is given.

    Raises:
        ModelError: unknown built-in model, unreadable or invalid URDF, base frame or a foot frame
            absent, a foot not below the base frame, or an unsupported (multi-DOF) joint in a leg.
    """
    import pinocchio as pin

    text, builtin_name, what = _read_urdf_text(urdf, urdf_xml, model)
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ModelError(f"{what} is not valid XML: {exc}") from None
    if root.tag != "robot":
        raise ModelError(f"{what} is not a URDF: root element is <{root.tag}>, expected <robot>")
    _check_urdf_numbers(root, what)
    try:
        with _parser_stderr() as parser_said:
            m = pin.buildModelFromXML(text)
    except (ValueError, RuntimeError) as exc:
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        said = _parser_errors(parser_said[0] if parser_said else "")
        raise ModelError(f"{what} is not a valid URDF model: {excerpt(said or msg, 200)}") from None

    frame_names = tuple(f.name for f in m.frames)
    link_names = tuple(f.name for f in m.frames if f.type == pin.FrameType.BODY)
    if not m.existFrame(base_frame):
        raise ModelError(f"base frame {base_frame!r} is not in the {what}{_suggest(base_frame, link_names)}")

    if builtin_name is not None and not feet:
        from graphcal.models.builtin import builtin_info

        feet = builtin_info(builtin_name).feet
    feet = tuple(feet)
    if len(set(feet)) != len(feet):
        raise ModelError(f"foot frames listed twice in {feet!r}")

    legs = {foot: _extract_leg(m, base_frame, foot, what, link_names) for foot in feet}
    joint_names = tuple(m.names[i] for i in range(1, m.njoints) if m.joints[i].nv == 1)
    name = builtin_name if builtin_name is not None else (root.get("name") or m.name)
    return RobotModel(
        name=name,
        urdf_xml=text,
        base_frame=base_frame,
        feet=feet,
        pin_model=m,
        joint_names=joint_names,
        frame_names=frame_names,
        legs=legs,
    )


def _frame_ancestors(m, fid: int) -> list[int]:
    """Frame ids from ``fid`` up to the universe frame through parentFrame (the link tree)."""
    out = [fid]
    seen = {fid}
    while fid != 0:
        fid = m.frames[fid].parentFrame
        if fid in seen:
            break
        out.append(fid)
        seen.add(fid)
    return out


def _extract_leg(m, base_frame: str, foot: str, what: str, link_names: Sequence[str]) -> Leg:
    """Build the :class:`Leg` from ``base_frame`` to ``foot`` in Pinocchio model ``m``."""
    import pinocchio as pin

    if not m.existFrame(foot):
        raise ModelError(f"foot frame {foot!r} is not in the {what}{_suggest(foot, link_names)}")
    base_id = _frame_id(m, base_frame)
    foot_id = _frame_id(m, foot)
    # the base must be an ancestor (in the link/frame tree) of the foot; same-joint frames that are
    # not in the base's subtree are rejected too.
    anc = set(_frame_ancestors(m, foot_id))
    same_name_ancestor = any(m.frames[a].name == base_frame for a in anc)
    if base_id not in anc and not same_name_ancestor:
        links = [m.frames[a].name for a in _frame_ancestors(m, foot_id)[1:] if m.frames[a].type == pin.FrameType.BODY]
        raise ModelError(
            f"foot frame {foot!r} is not below base frame {base_frame!r} in the {what} "
            f"(links above it: {', '.join(repr(x) for x in links) or 'none'})"
        )
    jb = m.frames[base_id].parentJoint
    chain: list[int] = []
    j = m.frames[foot_id].parentJoint
    while j != jb:
        if j == 0:  # should not happen after the frame-tree check
            raise ModelError(f"foot frame {foot!r} is not below base frame {base_frame!r} in the {what}")
        chain.append(j)
        j = m.parents[j]
    chain.reverse()

    q0 = pin.neutral(m)
    names, types, axes, T_pj, lower, upper = [], [], [], [], [], []
    T_jb_base = from_pinocchio_se3(m.frames[base_id].placement)
    for k, jid in enumerate(chain):
        jm = m.joints[jid]
        short = jm.shortname()
        jname = m.names[jid]
        if short in _REVOLUTE_SHORTNAMES or short in _UNBOUNDED_SHORTNAMES:
            jtype = "revolute"
        elif short in _PRISMATIC_SHORTNAMES:
            jtype = "prismatic"
        else:
            raise ModelError(
                f"joint {jname!r} in the leg of foot {foot!r} has Pinocchio type {short}; only 1-DOF "
                f"revolute, continuous and prismatic joints are supported"
            )
        jd = jm.createData()
        jm.calc(jd, q0)
        S = tangent_from_pinocchio(np.asarray(jd.S, dtype=float).reshape(6))  # [omega, v]
        axis = S[:3] if jtype == "revolute" else S[3:]
        if not np.linalg.norm(axis) > 1e-12:
            raise ModelError(f"joint {jname!r} in the {what} has a zero axis: expected <axis xyz> of nonzero length")
        axis = axis / np.linalg.norm(axis)
        T = from_pinocchio_se3(m.jointPlacements[jid])
        if k == 0:
            T = invert_pose(T_jb_base) @ T
        if short in _UNBOUNDED_SHORTNAMES:
            lo, hi = -np.inf, np.inf
        else:
            lo, hi = float(m.lowerPositionLimit[jm.idx_q]), float(m.upperPositionLimit[jm.idx_q])
        names.append(jname)
        types.append(jtype)
        axes.append(axis)
        T_pj.append(T)
        lower.append(lo)
        upper.append(hi)
    T_last_foot = from_pinocchio_se3(m.frames[foot_id].placement)
    if not chain:
        T_last_foot = invert_pose(T_jb_base) @ T_last_foot
    return Leg(
        foot=foot,
        joint_names=tuple(names),
        joint_types=tuple(types),
        axes=_readonly(np.reshape(axes, (len(chain), 3))),
        T_parent_joint=_readonly(np.reshape(T_pj, (len(chain), 4, 4))),
        T_lastjoint_foot=_readonly(T_last_foot),
        lower=_readonly(lower),
        upper=_readonly(upper),
        base_frame=base_frame,
    )
