"""Leg kinematic perturbations applied to a URDF: the "true" robot of a simulation.

Perturbation model (see docs/robots.md):

* **joint offset** ``theta`` on a revolute/continuous joint J with unit axis ``a`` (encoder zero
  error): the true angle is ``q_true = q_measured + theta``. It is baked into the URDF as
  ``origin_R <- origin_R @ Rot(a, theta)``, so the perturbed URDF evaluated at the *measured* q gives
  the true pose: ``T_origin Rot(a, theta) Rot(a, q) = T_origin Rot(a, q + theta)``. On a prismatic
  joint the offset (m) moves the origin along the axis: ``origin_xyz <- origin_xyz + origin_R a theta``.
* **origin delta** ``d`` (3,) m on any joint (fixed ones included, e.g. ``<leg>_foot_joint``):
  ``origin_xyz <- origin_xyz + d``, expressed in the joint's parent frame.
* :func:`link_length_delta` turns a scalar link-length error into an origin delta along the link
  that ends at the joint; :func:`hip_offset_delta` does the same for a lateral hip offset (the
  component of the origin along the joint's own axis, e.g. the A1 thigh joint's ``omega``).
"""

from __future__ import annotations

import difflib
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Iterator

import numpy as np

from graphcal.errors import ModelError
from graphcal.geometry import matrix_from_axis_angle, matrix_from_rpy, rpy_from_matrix
from graphcal.models.urdf_xml import parse_urdf, urdf_to_text

__all__ = [
    "FrozenMap",
    "LegPerturbation",
    "apply_perturbation",
    "link_length_delta",
    "hip_offset_delta",
    "joint_origin",
]


class FrozenMap(Mapping):
    """An immutable, hashable mapping (insertion order kept; equality and hash ignore order)."""

    __slots__ = ("_d",)

    def __init__(self, items: Mapping | None = None):
        object.__setattr__(self, "_d", dict(items or {}))

    def __getitem__(self, key):
        return self._d[key]

    def __iter__(self) -> Iterator:
        return iter(self._d)

    def __len__(self) -> int:
        return len(self._d)

    def __hash__(self) -> int:
        return hash(frozenset(self._d.items()))

    def __setattr__(self, name, value):
        raise AttributeError("FrozenMap is immutable")

    def __repr__(self) -> str:
        return f"FrozenMap({self._d!r})"


@dataclass(frozen=True)
class LegPerturbation:
    """Kinematic errors of the true robot with respect to its nominal URDF.

    Attributes:
        joint_offsets_rad: URDF joint name -> encoder zero error (rad; m for a prismatic joint):
            true joint value = measured + offset.
        origin_deltas_m: URDF joint name -> (dx, dy, dz) change of the joint's ``<origin xyz>``,
            m, in the joint's parent frame.

    Both are stored as immutable :class:`FrozenMap` (values: float, and tuples of 3 floats), so a
    perturbation is hashable and can be compared.
    """

    joint_offsets_rad: Mapping[str, float] = field(default_factory=FrozenMap)
    origin_deltas_m: Mapping[str, tuple[float, float, float]] = field(default_factory=FrozenMap)

    def __post_init__(self):
        offs = {}
        for k, v in dict(self.joint_offsets_rad).items():
            v = float(v)
            if not np.isfinite(v):
                raise ModelError(f"joint offset of {k!r} must be finite, got {v}")
            offs[str(k)] = v
        deltas = {}
        for k, v in dict(self.origin_deltas_m).items():
            arr = np.asarray(v, dtype=float).reshape(-1)
            if arr.shape != (3,) or not np.all(np.isfinite(arr)):
                raise ModelError(f"origin delta of joint {k!r} must be 3 finite numbers (m), got {v!r}")
            deltas[str(k)] = tuple(float(x) for x in arr)
        object.__setattr__(self, "joint_offsets_rad", FrozenMap(offs))
        object.__setattr__(self, "origin_deltas_m", FrozenMap(deltas))

    @property
    def joints(self) -> tuple[str, ...]:
        """Every joint named by the perturbation (offsets first)."""
        names = list(self.joint_offsets_rad)
        names += [j for j in self.origin_deltas_m if j not in self.joint_offsets_rad]
        return tuple(names)

    def __add__(self, other: "LegPerturbation") -> "LegPerturbation":
        """Sum of two perturbations (offsets and deltas of the same joint add)."""
        offs = dict(self.joint_offsets_rad)
        for k, v in other.joint_offsets_rad.items():
            offs[k] = offs.get(k, 0.0) + v
        deltas = {k: np.asarray(v) for k, v in self.origin_deltas_m.items()}
        for k, v in other.origin_deltas_m.items():
            deltas[k] = deltas.get(k, np.zeros(3)) + np.asarray(v)
        return LegPerturbation(offs, {k: tuple(v) for k, v in deltas.items()})


# ----------------------------------------------------------------------------- URDF helpers
def _fmt(x: float) -> str:
    x = float(x)
    return "0" if x == 0.0 else repr(x)


def _parse(urdf_xml: str) -> ET.Element:
    return parse_urdf(urdf_xml)


def _joints(root: ET.Element) -> dict[str, ET.Element]:
    return {j.get("name"): j for j in root.findall("joint")}


def _find_joint(joints: Mapping[str, ET.Element], name: str) -> ET.Element:
    if name not in joints:
        close = difflib.get_close_matches(name, list(joints), n=4, cutoff=0.5)
        hint = ("; did you mean " + ", ".join(repr(c) for c in close) + "?") if close else ""
        raise ModelError(f"joint {name!r} is not in the URDF{hint}")
    return joints[name]


def _floats(text: str | None, default) -> np.ndarray:
    if text is None or not text.strip():
        return np.array(default, dtype=float)
    return np.array([float(x) for x in text.split()], dtype=float)


def _origin(joint: ET.Element) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (3,) m, R (3,3)) of a URDF joint's origin (parent frame)."""
    o = joint.find("origin")
    if o is None:
        return np.zeros(3), np.eye(3)
    return _floats(o.get("xyz"), [0, 0, 0]), matrix_from_rpy(_floats(o.get("rpy"), [0, 0, 0]))


def _axis(joint: ET.Element) -> np.ndarray:
    a = joint.find("axis")
    v = _floats(None if a is None else a.get("xyz"), [1, 0, 0])
    n = np.linalg.norm(v)
    if n == 0:
        raise ModelError(f"joint {joint.get('name')!r} has a zero axis")
    return v / n


def _set_origin(joint: ET.Element, xyz, R) -> None:
    o = joint.find("origin")
    if o is None:
        o = ET.SubElement(joint, "origin")
    o.set("xyz", " ".join(_fmt(x) for x in xyz))
    o.set("rpy", " ".join(_fmt(x) for x in rpy_from_matrix(R)))


def _urdf_text(robot: Any) -> str:
    if isinstance(robot, str):
        return robot
    text = getattr(robot, "urdf_xml", None)
    if not isinstance(text, str):
        raise ModelError(f"expected a RobotModel or URDF text, got {type(robot).__name__}")
    return text


def joint_origin(robot: Any, joint: str) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (3,) m, R (3, 3)) of URDF joint ``joint``'s origin in its parent link frame.

    ``robot`` is a :class:`~graphcal.models.robot.RobotModel` or URDF text.
    """
    return _origin(_find_joint(_joints(_parse(_urdf_text(robot))), joint))


# ----------------------------------------------------------------------------- API
def apply_perturbation(urdf_xml: str, pert: LegPerturbation) -> str:
    """The perturbed ("true") robot's URDF text.

    Args:
        urdf_xml: nominal URDF text.
        pert: the perturbation (joint names must exist in the URDF).

    Returns:
        URDF text in which the origins of the named joints carry the perturbation (see module
        docstring). Evaluated at measured joint values it gives the true robot's kinematics.

    Raises:
        ModelError: invalid XML, unknown joint name, or a joint offset on a joint that is not
            revolute/continuous/prismatic.
    """
    root = _parse(urdf_xml)
    joints = _joints(root)
    for name in pert.joints:
        _find_joint(joints, name)
    for name, delta in pert.origin_deltas_m.items():
        j = joints[name]
        xyz, R = _origin(j)
        _set_origin(j, xyz + np.asarray(delta), R)
    for name, theta in pert.joint_offsets_rad.items():
        j = joints[name]
        jtype = j.get("type")
        xyz, R = _origin(j)
        a = _axis(j) if jtype in ("revolute", "continuous", "prismatic") else None
        if jtype in ("revolute", "continuous"):
            R = R @ matrix_from_axis_angle(a, theta)
        elif jtype == "prismatic":
            xyz = xyz + R @ a * theta
        else:
            raise ModelError(
                f"joint offset on joint {name!r} of type {jtype!r}: only revolute, continuous and prismatic joints have one"
            )
        _set_origin(j, xyz, R)
    return urdf_to_text(root, urdf_xml)


def link_length_delta(robot: Any, joint: str, delta_m: float) -> np.ndarray:
    """Origin delta (3,) m that lengthens the link ending at ``joint`` by ``delta_m``.

    The link is the translation of ``joint``'s origin (in its parent frame): the delta is
    ``delta_m * xyz / |xyz|``. For the built-in models the shank length is the origin of
    ``<leg>_foot_joint``, the thigh length the origin of the knee/tibia joint.

    Args:
        robot: :class:`~graphcal.models.robot.RobotModel` or URDF text.
        joint: URDF joint name (fixed joints included).
        delta_m: change of the link length, m.

    Raises:
        ModelError: unknown joint, or its origin has no translation (no link to lengthen).
    """
    xyz, _ = joint_origin(robot, joint)
    n = np.linalg.norm(xyz)
    if n < 1e-12:
        raise ModelError(f"joint {joint!r} has a zero origin translation: no link ends at it")
    return float(delta_m) * xyz / n


def hip_offset_delta(robot: Any, joint: str, delta_m: float) -> np.ndarray:
    """Origin delta (3,) m that increases the lateral offset of ``joint`` by ``delta_m``.

    The lateral offset is the component of the joint's origin translation along its own rotation
    axis (expressed in the parent frame), e.g. the A1 thigh joint sits ``omega`` = 0.08 m outward
    along its pitch axis from the hip abduction joint. The delta points outward (away from the
    parent joint), so a positive ``delta_m`` makes ``|omega|`` larger.

    Raises:
        ModelError: unknown joint, a joint without axis (fixed), or no offset along the axis.
    """
    j = _find_joint(_joints(_parse(_urdf_text(robot))), joint)
    if j.get("type") not in ("revolute", "continuous", "prismatic"):
        raise ModelError(f"joint {joint!r} of type {j.get('type')!r} has no axis: no lateral hip offset")
    xyz, R = _origin(j)
    a = R @ _axis(j)
    along = float(xyz @ a)
    if abs(along) < 1e-12:
        raise ModelError(f"joint {joint!r} has no origin offset along its axis: no lateral hip offset to change")
    return float(delta_m) * np.sign(along) * a
