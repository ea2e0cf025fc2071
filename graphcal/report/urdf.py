"""The calibrated URDF: the nominal robot with the calibrated sensor poses and leg parameters baked in.

* Sensor ``s``: the fixed joint whose child link is ``s`` (normally ``<s>_joint``) gets the origin
  ``T_parent_s = T_base_parent^-1 T_base_s`` where ``T_base_s`` is the calibrated ``T_body_sensor``
  and ``T_base_parent`` the (fixed) placement of the joint's parent link relative to the base frame,
  taken from Pinocchio. A sensor without a link in the URDF gets a new link ``<s>`` and a fixed
  joint ``<s>_joint`` from the base frame.
* Leg parameters (named as in :mod:`graphcal.models.legs`, model of
  :mod:`graphcal.models.perturb`): ``<joint>.offset_rad`` is an encoder zero offset
  (``origin_R <- origin_R Rot(axis, offset)``; ``<joint>.offset_m`` on a prismatic joint moves the
  origin along the axis), ``<joint>.delta_m`` a link-length change (``origin_xyz += delta
  xyz / |xyz|``), ``<joint>.dx_m`` / ``.dy_m`` / ``.dz_m`` a change of one component of the origin
  (parent link frame; :mod:`graphcal.models.legs`, e.g. the hip position). All are applied by
  :func:`graphcal.models.perturb.apply_perturbation`.

The rest of the URDF (and its comments) is left as it was. Angles written with ``repr`` precision.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from typing import Mapping

import numpy as np

from graphcal.errors import ModelError
from graphcal.geometry import from_pinocchio_se3, invert_pose, rpy_from_matrix
from graphcal.models.perturb import LegPerturbation, apply_perturbation, link_length_delta
from graphcal.models.urdf_xml import parse_urdf, urdf_to_text

__all__ = ["calibrated_urdf", "leg_perturbation_from_parameters", "LEG_PARAMETER_KINDS"]

#: Supported leg parameter suffixes (``<joint>.<kind>``), as named by graphcal.models.legs.
LEG_PARAMETER_KINDS = ("offset_rad", "offset_m", "delta_m", "dx_m", "dy_m", "dz_m")
_ORIGIN_AXIS = {"dx_m": 0, "dy_m": 1, "dz_m": 2}


def _fmt(x: float) -> str:
    x = float(x)
    return "0" if x == 0.0 else repr(x)


def _parse(urdf_xml: str) -> ET.Element:
    return parse_urdf(urdf_xml, comments=True)


def leg_perturbation_from_parameters(urdf_xml: str, legs: Mapping[str, Mapping[str, float]]) -> LegPerturbation:
    """The :class:`~graphcal.models.perturb.LegPerturbation` of calibrated leg parameters.

    Args:
        urdf_xml: the nominal URDF (``delta_m`` is along its origin translation).
        legs: foot -> {parameter name: value (SI)}, names as in :mod:`graphcal.models.legs`:
            ``<joint>.offset_rad`` (revolute/continuous joint), ``<joint>.offset_m`` (prismatic
            joint), ``<joint>.delta_m`` (link ending at the joint). ``<foot>.delta_m`` of a foot frame
            that is no URDF joint has nothing to carry it: accepted only when it is 0.

    Raises:
        ModelError: a parameter name without a known suffix, an unknown joint, an offset whose unit
            does not match the joint type, a joint without origin translation for ``delta_m``, a
            non-zero delta without URDF joint, or the same parameter given twice with different values.
    """
    joints = {j.get("name"): j for j in _parse(urdf_xml).findall("joint")}
    offsets: dict[str, float] = {}
    lengths: dict[str, float] = {}
    components: dict[str, np.ndarray] = {}
    for foot, params in legs.items():
        for name, value in params.items():
            joint, _, kind = str(name).rpartition(".")
            if not joint or kind not in LEG_PARAMETER_KINDS:
                raise ModelError(
                    f"leg parameter {name!r} of foot {foot!r}: expected '<joint>.offset_rad', '<joint>.offset_m' "
                    f"or '<joint>.delta_m' (or '<joint>.dx_m', '.dy_m', '.dz_m')"
                )
            value = float(value)
            if not np.isfinite(value):
                raise ModelError(f"leg parameter {name!r} of foot {foot!r} is not finite: {value}")
            if kind == "delta_m" and joint not in joints:
                if value == 0.0:
                    continue
                raise ModelError(
                    f"leg parameter {name!r} of foot {foot!r}: {joint!r} is not a URDF joint, so the URDF cannot "
                    f"carry a link length change there"
                )
            if kind in _ORIGIN_AXIS:
                if joint not in joints:
                    if value == 0.0:
                        continue
                    raise ModelError(f"leg parameter {name!r} of foot {foot!r}: {joint!r} is not a URDF joint")
                comp = components.setdefault(joint, np.full(3, np.nan))
                a = _ORIGIN_AXIS[kind]
                if not np.isnan(comp[a]) and comp[a] != value:
                    raise ModelError(f"leg parameter {name!r} given twice with different values ({comp[a]} and {value})")
                comp[a] = value
                continue
            if kind.startswith("offset") and joint in joints:
                jtype = joints[joint].get("type")
                want = "offset_m" if jtype == "prismatic" else "offset_rad"
                if jtype in ("revolute", "continuous", "prismatic") and kind != want:
                    raise ModelError(f"leg parameter {name!r}: joint {joint!r} is {jtype}, its offset is '{joint}.{want}'")
            table = lengths if kind == "delta_m" else offsets
            if joint in table and table[joint] != value:
                raise ModelError(f"leg parameter {name!r} given twice with different values ({table[joint]} and {value})")
            table[joint] = value
    deltas = {j: tuple(link_length_delta(urdf_xml, j, d)) for j, d in lengths.items()}
    for j, comp in components.items():
        deltas[j] = tuple(np.asarray(deltas.get(j, (0.0, 0.0, 0.0))) + np.nan_to_num(comp, nan=0.0))
    return LegPerturbation(joint_offsets_rad=offsets, origin_deltas_m=deltas)


def _copy_origins(root: ET.Element, perturbed_xml: str, joints) -> None:
    """Copy the ``<origin>`` of ``joints`` from the perturbed URDF text into ``root`` (which keeps
    its comments, unlike the text apply_perturbation returns)."""
    src = {j.get("name"): j for j in ET.fromstring(perturbed_xml).findall("joint")}
    dst = {j.get("name"): j for j in root.findall("joint")}
    for name in joints:
        o_src = src[name].find("origin")
        o_dst = dst[name].find("origin")
        if o_dst is None:
            o_dst = ET.SubElement(dst[name], "origin")
        for k in ("xyz", "rpy"):
            if o_src is not None and o_src.get(k) is not None:
                o_dst.set(k, o_src.get(k))


def _frame_id(m, name: str):
    import pinocchio as pin

    if m.existFrame(name, pin.FrameType.BODY):
        return m.getFrameId(name, pin.FrameType.BODY)
    if m.existFrame(name):
        return m.getFrameId(name)
    return None


def _comment_text(text: str) -> str:
    """Text safe inside an XML comment (no ``--``, no trailing ``-``)."""
    text = " ".join(str(text).split())
    while "--" in text:
        text = text.replace("--", "- -")
    # no ": " either, so `-p robot_description:="$(cat file)"` (parsed as YAML) keeps working
    return text.replace(": ", ":")


def _indent_of(root: ET.Element) -> tuple[str, str]:
    """(indent of the robot's children, tail of the last child) as found in the file."""
    kids = list(root)
    child_indent = "\n  "
    if root.text and root.text.strip() == "" and "\n" in root.text:
        child_indent = root.text
    last_tail = kids[-1].tail if kids and kids[-1].tail is not None else "\n"
    return child_indent, last_tail


def calibrated_urdf(
    urdf_xml: str,
    base_frame: str,
    sensors: Mapping[str, np.ndarray],
    legs: Mapping[str, Mapping[str, float]] | None = None,
    *,
    dataset: str | None = None,
    command: str = "calibrate",
    uncertainty: str = "",
) -> str:
    """URDF text of the calibrated robot (``uncertainty``: a sentence on the sensors' 1-sigma, put in
    the provenance comment).

    Args:
        urdf_xml: the nominal URDF text.
        base_frame: the body frame the ``T_body_sensor`` are expressed in (a URDF link, or a joint
            whose child link then carries new sensors).
        sensors: sensor name -> calibrated ``T_body_sensor`` (4x4, m).
        legs: foot -> {``"<joint>.offset_rad"`` / ``"<joint>.offset_m"`` / ``"<joint>.delta_m"``: value}, or None.
        dataset: the dataset path, named in the provenance comment at the top.
        command: the graphcal command named in that comment (``calibrate``, ``identify-legs``).

    Returns:
        URDF text (UTF-8, with an ``<?xml?>`` declaration and a provenance comment).

    Raises:
        ModelError: invalid URDF, unknown base frame or joint, a sensor link attached by a moving
            joint, or a sensor link that moves relative to the base frame (a moving joint between them).
    """
    import pinocchio as pin

    root = _parse(urdf_xml)

    # ---- legs first (they may move links the sensors hang from)
    if legs:
        pert = leg_perturbation_from_parameters(urdf_xml, legs)
        if pert.joints:
            _copy_origins(root, apply_perturbation(urdf_xml, pert), pert.joints)
    text = urdf_to_text(root, urdf_xml)

    try:
        m = pin.buildModelFromXML(text)
    except (ValueError, RuntimeError) as exc:
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ModelError(f"URDF is not a valid model: {msg}") from None
    base_id = _frame_id(m, base_frame)
    if base_id is None:
        raise ModelError(f"base frame {base_frame!r} is not in the URDF")
    base_fr = m.frames[base_id]
    T_joint_base = from_pinocchio_se3(base_fr.placement)

    links = {lk.get("name") for lk in root.findall("link")}
    joints = root.findall("joint")
    joint_names = {j.get("name") for j in joints}
    by_child = {}
    for j in joints:
        c = j.find("child")
        if c is not None:
            by_child[c.get("link")] = j

    if base_frame in links:
        base_link = base_frame
    elif base_frame in joint_names:
        cj = next(j for j in joints if j.get("name") == base_frame).find("child")
        base_link = cj.get("link") if cj is not None else None
        if base_link is None:
            raise ModelError(f"base frame {base_frame!r} is a joint without child link")
    else:
        raise ModelError(f"base frame {base_frame!r} is neither a link nor a joint of the URDF")

    child_indent, last_tail = _indent_of(root)
    for name, T in sensors.items():
        name = str(name)
        T_base_sensor = np.asarray(T, dtype=float)
        if T_base_sensor.shape != (4, 4) or not np.all(np.isfinite(T_base_sensor)):
            raise ModelError(f"sensor {name!r}: T_body_sensor must be a finite 4x4 pose")
        if name == base_link or name == base_frame:
            raise ModelError(f"sensor {name!r} is the base frame itself")
        if name in links:
            j = by_child.get(name)
            if j is None:
                raise ModelError(f"sensor link {name!r} is the root of the URDF; it needs a fixed joint from {base_frame!r}")
            if j.get("type") != "fixed":
                raise ModelError(
                    f"sensor link {name!r} is attached by joint {j.get('name')!r} of type {j.get('type')!r}; "
                    f"a calibrated extrinsic needs a fixed joint"
                )
            parent = j.find("parent").get("link")
            pid = _frame_id(m, parent)
            if pid is None:  # pragma: no cover - Pinocchio has a frame for every link
                raise ModelError(f"link {parent!r} not found by Pinocchio")
            p_fr = m.frames[pid]
            if p_fr.parentJoint != base_fr.parentJoint:
                raise ModelError(
                    f"sensor {name!r} hangs from link {parent!r}, which moves relative to the base frame "
                    f"{base_frame!r} (a moving joint lies between them); cannot write a fixed T_body_sensor"
                )
            T_base_parent = invert_pose(T_joint_base) @ from_pinocchio_se3(p_fr.placement)
            T_parent_sensor = invert_pose(T_base_parent) @ T_base_sensor
        else:
            jname = f"{name}_joint"
            if jname in joint_names:
                raise ModelError(f"cannot add sensor link {name!r}: a joint named {jname!r} already exists")
            if len(root):
                root[-1].tail = child_indent
            lk = ET.SubElement(root, "link", {"name": name})
            lk.tail = child_indent
            j = ET.SubElement(root, "joint", {"name": jname, "type": "fixed"})
            inner = child_indent + "  "
            j.text = inner
            ET.SubElement(j, "parent", {"link": base_link}).tail = inner
            ET.SubElement(j, "child", {"link": name}).tail = inner
            ET.SubElement(j, "origin").tail = child_indent
            j.tail = last_tail
            links.add(name)
            joint_names.add(jname)
            by_child[name] = j
            # the new joint hangs from base_link, whose frame is the base frame (a URDF joint frame
            # coincides with its child link frame)
            T_parent_sensor = T_base_sensor
        o = j.find("origin")
        if o is None:
            o = ET.SubElement(j, "origin")
        o.set("xyz", " ".join(_fmt(x) for x in T_parent_sensor[:3, 3]))
        o.set("rpy", " ".join(_fmt(x) for x in rpy_from_matrix(T_parent_sensor[:3, :3])))

    ds = _comment_text(dataset) if dataset is not None else "(unknown dataset)"
    sensor_list = ", ".join(str(s) for s in sensors) or "none"
    comment = (
        f"<!-- Calibrated robot model written by graphcal {_comment_text(command)} from dataset {ds}. "
        f"Calibrated sensor joints of ({_comment_text(sensor_list)}), "
        f"{'with' if legs else 'without'} calibrated leg parameters."
        + (f" {_comment_text(uncertainty)}" if uncertainty else "") + " -->"
    )
    body = urdf_to_text(root, urdf_xml)
    return f'<?xml version="1.0" encoding="utf-8"?>\n{comment}\n{body}\n'
