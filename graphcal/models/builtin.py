"""Built-in robots: URDFs generated in Python and their sensor CAD priors.

Every model has the base link ``body`` (x forward, y left, z up, REP 103, origin at the centre of
the hip plane), an ``imu`` link at the body origin (fixed joint ``imu_joint``), legs whose foot
frames are links ``<leg>_foot`` attached by FIXED joints ``<leg>_foot_joint`` whose origin is the
last link length (so a shank length error is a change of that joint's origin), and one link per
exteroceptive sensor attached by a fixed joint ``<sensor>_joint`` at its CAD pose.

Sensor frame conventions: cameras use the optical frame (z along the optical axis, x right, y
down), so a camera looking straight forward has ``R_body_optical = [[0,0,1],[-1,0,0],[0,-1,0]]``;
a 2D laser scanner has its scan plane = its x-y plane, x along the centre beam, z normal to the
scan plane.

Models (dimensions and their sources: docs/robots.md):

* ``octopus``  -- Chai et al. 2015, hexagonal 6-legged robot with a Kinect (``depth``);
* ``qingzhui`` -- Zhao et al. 2020, hexapod with an RGB-D camera (``depth``);
* ``messor``   -- Łabęcki et al. 2012, small hexapod with a laser scanner (``laser``) and a
  stereo camera (``stereo``);
* ``a1``       -- Yuan et al. (Unitree A1 numbers of their Table I), quadruped, no exteroceptive
  sensor;
* ``a1cam``    -- the same quadruped with a depth camera on its nose (``depth``, 0.25 m ahead of the
  body origin and 0.05 m above it, looking 30 deg down: a Go1's or A1's front camera).

Units: metres, radians.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Mapping

import numpy as np

from graphcal.errors import ModelError
from graphcal.geometry import pose_matrix, rot_x, rot_y, rot_z, rpy_from_matrix

__all__ = [
    "BUILTIN_MODELS",
    "R_BODY_OPTICAL",
    "SensorCAD",
    "BuiltinInfo",
    "builtin_urdf",
    "builtin_info",
    "zhao_toe_position",
    "OCTOPUS",
    "QINGZHUI",
    "MESSOR",
    "A1",
]

BUILTIN_MODELS: tuple[str, ...] = ("octopus", "qingzhui", "messor", "a1", "a1cam")

#: Rotation of a forward-looking camera's optical frame (z forward, x right, y down) in the body.
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
R_BODY_OPTICAL.setflags(write=False)

_SIGMA_M = 0.05
_SIGMA_RAD = float(np.deg2rad(5.0))


@dataclass(frozen=True, eq=False)
class SensorCAD:
    """CAD prior of an exteroceptive sensor.

    Attributes:
        type: ``"depth_camera"``, ``"laser_scanner"`` or ``"stereo_camera"``.
        T_body_sensor: (4, 4) sensor frame in the body frame (optical frame for cameras, scan
            frame for laser scanners), metres.
        sigma_m: prior standard deviation of each translation component, m.
        sigma_rad: prior standard deviation of each rotation component, rad.
    """

    type: str
    T_body_sensor: np.ndarray
    sigma_m: float = _SIGMA_M
    sigma_rad: float = _SIGMA_RAD


@dataclass(frozen=True, eq=False)
class BuiltinInfo:
    """What the simulator and the dataset writer need to know about a built-in model.

    Attributes:
        name: model name.
        base_frame: ``"body"``.
        feet: foot frame names (default feet of the model).
        default_body_height_m: height of the body origin above level ground in the nominal stance, m.
        nominal_stance: foot -> p_body_foot (3,), m: the feet at the default height on level
            ground with the body level.
        sensors: sensor name -> :class:`SensorCAD`.
        T_body_imu: (4, 4) IMU frame in the body frame (identity: the ``imu`` link).
        gait_groups: tripod groups (tuples of feet) where the source paper defines them, else ().
    """

    name: str
    base_frame: str
    feet: tuple[str, ...]
    default_body_height_m: float
    nominal_stance: dict
    sensors: dict
    T_body_imu: np.ndarray = field(default_factory=lambda: np.eye(4))
    gait_groups: tuple = ()


# ----------------------------------------------------------------------------- dimensions
# Every number here is listed in docs/robots.md with its source (paper or "chosen: plausible").
OCTOPUS: Mapping[str, float] = MappingProxyType(
    {
        "hip_radius": 0.40,  # chosen: hexagonal body, hip circle radius
        "coxa": 0.10,  # chosen
        "femur": 0.45,  # chosen
        "tibia": 0.75,  # chosen; body heights 0.615..0.75 m of Chai Table A1
        "body_height": 0.68,  # chosen inside Chai Table A1's 0.615..0.75 m
        "stance_radius": 0.95,  # chosen: hip_radius + coxa + femur (femur ~horizontal)
    }
)
QINGZHUI: Mapping[str, float] = MappingProxyType(
    {
        "hip_radius": 0.35,  # chosen: body ~0.7 m long (mf to mb hip)
        "l_ab": 0.30,  # thigh, chosen (Zhao gives no number)
        "l_be": 0.45,  # shank, chosen
        "body_height": 0.45,  # chosen
        "stance_reach": 0.45,  # chosen: foot 0.45 m radially out of the hip
    }
)
MESSOR: Mapping[str, float] = MappingProxyType(
    {
        "hip_x_front": 0.13,  # chosen: body ~0.3 m long
        "hip_y_front": 0.075,  # chosen
        "hip_y_middle": 0.10,  # chosen
        "coxa": 0.055,  # chosen (plausible)
        "femur": 0.16,  # chosen (plausible)
        "tibia": 0.23,  # chosen (plausible)
        "body_height": 0.12,  # chosen (plausible)
    }
)
A1: Mapping[str, float] = MappingProxyType(
    {
        "l_b": 0.361,  # Yuan Table I: body length between hips
        "w_b": 0.094,  # Yuan Table I: body width between hips
        "omega": 0.08,  # Yuan Table I |omega| (lateral hip offset), outward per side
        "l1": 0.2,  # Yuan Table I thigh
        "l2": 0.2,  # Yuan Table I calf
        "body_height": 0.28,  # chosen (typical A1 standing height)
    }
)


# ----------------------------------------------------------------------------- URDF writer
def _f(x: float) -> str:
    """Shortest round-trip text of a float (no precision lost through the URDF)."""
    x = float(x)
    if x == 0.0:
        return "0"
    return repr(x)


def _v(v) -> str:
    return " ".join(_f(x) for x in v)


class _Urdf:
    """Tiny URDF string builder (links without inertia: kinematics only)."""

    def __init__(self, name: str):
        self.name = name
        self.parts: list[str] = []

    def link(self, name: str) -> None:
        self.parts.append(f'  <link name="{name}"/>')

    def joint(
        self,
        name: str,
        jtype: str,
        parent: str,
        child: str,
        xyz=(0.0, 0.0, 0.0),
        R=None,
        axis=None,
        limits: tuple[float, float] | None = None,
    ) -> None:
        rpy = (0.0, 0.0, 0.0) if R is None else rpy_from_matrix(R)
        s = [f'  <joint name="{name}" type="{jtype}">']
        s.append(f'    <parent link="{parent}"/>')
        s.append(f'    <child link="{child}"/>')
        s.append(f'    <origin xyz="{_v(xyz)}" rpy="{_v(rpy)}"/>')
        if axis is not None:
            s.append(f'    <axis xyz="{_v(axis)}"/>')
        if limits is not None:
            s.append(f'    <limit lower="{_f(limits[0])}" upper="{_f(limits[1])}" effort="100" velocity="10"/>')
        s.append("  </joint>")
        self.parts.append("\n".join(s))

    def fixed(self, name: str, parent: str, child: str, xyz=(0.0, 0.0, 0.0), R=None) -> None:
        """A child link attached by a fixed joint."""
        self.link(child)
        self.joint(name, "fixed", parent, child, xyz, R)

    def text(self) -> str:
        return f'<?xml version="1.0"?>\n<robot name="{self.name}">\n' + "\n".join(self.parts) + "\n</robot>\n"


def _common(u: _Urdf, sensors: Mapping[str, SensorCAD]) -> None:
    u.link("body")
    u.fixed("imu_joint", "body", "imu")
    for name, cad in sensors.items():
        T = cad.T_body_sensor
        u.fixed(f"{name}_joint", "body", name, T[:3, 3], T[:3, :3])


def _ro(a) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


# ----------------------------------------------------------------------------- octopus
_OCTOPUS_LEGS = (("lf", 30.0), ("lm", 90.0), ("lr", 150.0), ("rf", -30.0), ("rm", -90.0), ("rr", -150.0))


def _octopus_sensors() -> dict:
    # Chai 2015 Eq. (32) (their y-up robot frame, Z = our -y): p = (527.9, 364.8, -33.4) mm,
    # beta = -37.4 deg -> ours: xyz (0.528, 0.033, 0.365), optical frame pitched down 37.4 deg.
    T = pose_matrix(rot_y(np.deg2rad(37.4)) @ R_BODY_OPTICAL, [0.528, 0.033, 0.365])
    return {"depth": SensorCAD("depth_camera", _ro(T))}


def _hexapod_3dof(u: _Urdf, legs, hips, coxa, femur, tibia, lim_coxa, lim_femur, lim_tibia) -> None:
    """Coxa yaw (z) at the hip, femur pitch (y) at ``coxa`` radially out, tibia pitch (y) at the
    femur end; zero configuration: coxa and femur horizontal radially out, tibia straight down."""
    for (leg, az_deg), hip in zip(legs, hips):
        az = np.deg2rad(az_deg)
        u.link(f"{leg}_coxa")
        u.joint(f"{leg}_coxa_joint", "revolute", "body", f"{leg}_coxa", hip, rot_z(az), (0, 0, 1), lim_coxa)
        u.link(f"{leg}_femur")
        u.joint(f"{leg}_femur_joint", "revolute", f"{leg}_coxa", f"{leg}_femur", (coxa, 0, 0), None, (0, 1, 0), lim_femur)
        u.link(f"{leg}_tibia")
        u.joint(f"{leg}_tibia_joint", "revolute", f"{leg}_femur", f"{leg}_tibia", (femur, 0, 0), None, (0, 1, 0), lim_tibia)
        u.fixed(f"{leg}_foot_joint", f"{leg}_tibia", f"{leg}_foot", (0, 0, -tibia))


def _octopus() -> tuple[str, BuiltinInfo]:
    d = OCTOPUS
    sensors = _octopus_sensors()
    u = _Urdf("octopus")
    _common(u, sensors)
    hips = [(d["hip_radius"] * np.cos(np.deg2rad(a)), d["hip_radius"] * np.sin(np.deg2rad(a)), 0.0) for _, a in _OCTOPUS_LEGS]
    _hexapod_3dof(
        u, _OCTOPUS_LEGS, hips, d["coxa"], d["femur"], d["tibia"],
        (-np.pi / 3, np.pi / 3), (-np.pi / 2, np.pi / 2), (-2.5, 2.5),
    )
    feet = tuple(f"{leg}_foot" for leg, _ in _OCTOPUS_LEGS)
    stance = {
        f"{leg}_foot": _ro([d["stance_radius"] * np.cos(np.deg2rad(a)), d["stance_radius"] * np.sin(np.deg2rad(a)), -d["body_height"]])
        for leg, a in _OCTOPUS_LEGS
    }
    info = BuiltinInfo("octopus", "body", feet, d["body_height"], stance, sensors, _ro(np.eye(4)))
    return u.text(), info


# ----------------------------------------------------------------------------- qingzhui
# Zhao 2020 Fig. 1 / Fig. 4: middle front (mf) on the front centre, middle back (mb) on the back
# centre, lf/lb/rf/rb at the corners; hips on a circle, legs radial.
_QINGZHUI_LEGS = (("lf", 60.0), ("lb", 120.0), ("rf", -60.0), ("rb", -120.0), ("mf", 0.0), ("mb", 180.0))


def zhao_toe_position(theta_a, theta_t, theta_s, l_ab: float, l_be: float) -> np.ndarray:
    """Zhao 2020 Eqs. (1)-(3): toe position in Zhao's hip frame.

    Zhao's hip frame (Fig. 1b): x radially out of the body along the abduction axis (horizontal),
    y down (in the leg plane at theta_a = 0), z = x cross y (horizontal). In graphcal's hip frame
    ``<leg>_hip`` (x radial out, y tangential, z up) the same point is
    ``(x_Z, z_Z, -y_Z)``.

    Args:
        theta_a: hip abduction angle (rad), rotation about x.
        theta_t: thigh angle (rad) from x towards y.
        theta_s: ABSOLUTE shank angle (rad) from x towards y (the URDF knee joint value is the
            relative angle theta_s - theta_t).
        l_ab: thigh length, m.  l_be: shank length, m.

    Returns:
        (..., 3) toe position in Zhao's hip frame, m (broadcast over the angle arrays).
    """
    ta, tt, ts = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (theta_a, theta_t, theta_s)))
    x = l_ab * np.cos(tt) + l_be * np.cos(ts)
    r = l_ab * np.sin(tt) + l_be * np.sin(ts)
    return np.stack([x, r * np.cos(ta), r * np.sin(ta)], axis=-1)


#: R_hip_zhao: Zhao's hip-frame axes in graphcal's ``<leg>_hip`` frame (columns x_Z, y_Z, z_Z).
R_HIP_ZHAO = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
R_HIP_ZHAO.setflags(write=False)


def _qingzhui() -> tuple[str, BuiltinInfo]:
    d = QINGZHUI
    T_cam = pose_matrix(rot_y(np.deg2rad(30.0)) @ R_BODY_OPTICAL, [0.33, 0.0, 0.12])
    sensors = {"depth": SensorCAD("depth_camera", _ro(T_cam))}
    u = _Urdf("qingzhui")
    _common(u, sensors)
    for leg, az_deg in _QINGZHUI_LEGS:
        az = np.deg2rad(az_deg)
        hip = (d["hip_radius"] * np.cos(az), d["hip_radius"] * np.sin(az), 0.0)
        # <leg>_hip_joint: abduction theta_a about the radial axis x (Zhao's x)
        u.link(f"{leg}_hip")
        u.joint(f"{leg}_hip_joint", "revolute", "body", f"{leg}_hip", hip, rot_z(az), (1, 0, 0), (-0.6, 0.6))
        # <leg>_thigh_joint: theta_t about y (= Zhao's z); positive moves the thigh down
        u.link(f"{leg}_thigh")
        u.joint(f"{leg}_thigh_joint", "revolute", f"{leg}_hip", f"{leg}_thigh", (0, 0, 0), None, (0, 1, 0), (-1.2, 1.2))
        # <leg>_knee_joint: relative shank angle theta_s - theta_t, at the thigh end
        u.link(f"{leg}_shank")
        u.joint(f"{leg}_knee_joint", "revolute", f"{leg}_thigh", f"{leg}_shank", (d["l_ab"], 0, 0), None, (0, 1, 0), (-0.5, 2.8))
        u.fixed(f"{leg}_foot_joint", f"{leg}_shank", f"{leg}_foot", (d["l_be"], 0, 0))
    feet = tuple(f"{leg}_foot" for leg, _ in _QINGZHUI_LEGS)
    reach = d["hip_radius"] + d["stance_reach"]
    stance = {
        f"{leg}_foot": _ro([reach * np.cos(np.deg2rad(a)), reach * np.sin(np.deg2rad(a)), -d["body_height"]])
        for leg, a in _QINGZHUI_LEGS
    }
    groups = (("mf_foot", "rb_foot", "lb_foot"), ("mb_foot", "rf_foot", "lf_foot"))
    info = BuiltinInfo("qingzhui", "body", feet, d["body_height"], stance, sensors, _ro(np.eye(4)), groups)
    return u.text(), info


# ----------------------------------------------------------------------------- messor
_MESSOR_LEGS = (("lf", 45.0), ("lm", 90.0), ("lr", 135.0), ("rf", -45.0), ("rm", -90.0), ("rr", -135.0))

#: Łabęcki's robot frame (x right, y forward, z up) -> ours: p_ours = C p_theirs, C = Rz(-90 deg).
C_OURS_LABECKI = rot_z(-np.pi / 2)
#: Their scanner frame (scan plane x_S-y_S, y_S = centre beam, z_S normal) -> ours (x = centre
#: beam, z normal, y = z x x = -x_S): R_theirS_ourS = Rz(+90 deg).
R_LABECKI_SCAN_OURS = rot_z(np.pi / 2)


def _labecki_to_ours(p_mm, R_theirs) -> tuple[np.ndarray, np.ndarray]:
    """Łabęcki robot-frame CAD (mm, rotation) -> our body frame (m, rotation)."""
    p = C_OURS_LABECKI @ (np.asarray(p_mm, dtype=float) / 1000.0)
    return p, C_OURS_LABECKI @ R_theirs


def _messor_sensors() -> dict:
    # Table 1 (laser): x, y, z = 0, 202, 175 mm; alpha = -45 deg about their x.
    p_l, R_l = _labecki_to_ours([0.0, 202.0, 175.0], rot_x(np.deg2rad(-45.0)))
    R_l = R_l @ R_LABECKI_SCAN_OURS
    # Table 2 (stereo): -30, 180, 230 mm; alpha = -115 deg about their x, used as the optical frame.
    p_c, R_c = _labecki_to_ours([-30.0, 180.0, 230.0], rot_x(np.deg2rad(-115.0)))
    return {
        "laser": SensorCAD("laser_scanner", _ro(pose_matrix(R_l, p_l))),
        "stereo": SensorCAD("stereo_camera", _ro(pose_matrix(R_c, p_c))),
    }


def _messor() -> tuple[str, BuiltinInfo]:
    d = MESSOR
    sensors = _messor_sensors()
    u = _Urdf("messor")
    _common(u, sensors)
    hips = [
        (d["hip_x_front"], d["hip_y_front"], 0.0),
        (0.0, d["hip_y_middle"], 0.0),
        (-d["hip_x_front"], d["hip_y_front"], 0.0),
        (d["hip_x_front"], -d["hip_y_front"], 0.0),
        (0.0, -d["hip_y_middle"], 0.0),
        (-d["hip_x_front"], -d["hip_y_front"], 0.0),
    ]
    _hexapod_3dof(
        u, _MESSOR_LEGS, hips, d["coxa"], d["femur"], d["tibia"],
        (-1.0, 1.0), (-np.pi / 2, np.pi / 2), (-2.5, 2.5),
    )
    feet = tuple(f"{leg}_foot" for leg, _ in _MESSOR_LEGS)
    reach = d["coxa"] + d["femur"]
    stance = {}
    for (leg, a), hip in zip(_MESSOR_LEGS, hips):
        az = np.deg2rad(a)
        stance[f"{leg}_foot"] = _ro([hip[0] + reach * np.cos(az), hip[1] + reach * np.sin(az), -d["body_height"]])
    info = BuiltinInfo("messor", "body", feet, d["body_height"], stance, sensors, _ro(np.eye(4)))
    return u.text(), info


# ----------------------------------------------------------------------------- a1
_A1_LEGS = (("fl", 1, 1), ("fr", 1, -1), ("rl", -1, 1), ("rr", -1, -1))


def _a1(name: str = "a1", sensors: Mapping[str, SensorCAD] | None = None) -> tuple[str, BuiltinInfo]:
    d = A1
    sensors = dict(sensors or {})
    u = _Urdf(name)
    _common(u, sensors)
    stance = {}
    for leg, sx, sy in _A1_LEGS:
        hip = (sx * d["l_b"] / 2, sy * d["w_b"] / 2, 0.0)
        u.link(f"{leg}_hip")
        u.joint(f"{leg}_hip_joint", "revolute", "body", f"{leg}_hip", hip, None, (1, 0, 0), (-0.802851, 0.802851))
        u.link(f"{leg}_thigh")
        u.joint(f"{leg}_thigh_joint", "revolute", f"{leg}_hip", f"{leg}_thigh", (0, sy * d["omega"], 0), None, (0, 1, 0),
                (-1.0472, 4.18879))
        u.link(f"{leg}_calf")
        u.joint(f"{leg}_calf_joint", "revolute", f"{leg}_thigh", f"{leg}_calf", (0, 0, -d["l1"]), None, (0, 1, 0), (-2.69653, -0.916298))
        u.fixed(f"{leg}_foot_joint", f"{leg}_calf", f"{leg}_foot", (0, 0, -d["l2"]))
        stance[f"{leg}_foot"] = _ro([hip[0], hip[1] + sy * d["omega"], -d["body_height"]])
    feet = tuple(f"{leg}_foot" for leg, _, _ in _A1_LEGS)
    info = BuiltinInfo(name, "body", feet, d["body_height"], stance, sensors, _ro(np.eye(4)))
    return u.text(), info


def _a1cam() -> tuple[str, BuiltinInfo]:
    T = pose_matrix(rot_y(np.deg2rad(30.0)) @ R_BODY_OPTICAL, [0.25, 0.0, 0.05])
    return _a1("a1cam", {"depth": SensorCAD("depth_camera", _ro(T))})


# ----------------------------------------------------------------------------- public API
_BUILDERS = {"octopus": _octopus, "qingzhui": _qingzhui, "messor": _messor, "a1": _a1, "a1cam": _a1cam}


def _get(name: str) -> tuple[str, BuiltinInfo]:
    if name not in _BUILDERS:
        import difflib

        close = difflib.get_close_matches(str(name), BUILTIN_MODELS, n=3, cutoff=0.4)
        hint = f"; did you mean {', '.join(repr(c) for c in close)}?" if close else ""
        raise ModelError(f"unknown built-in robot model {name!r} (built-in: {', '.join(BUILTIN_MODELS)}){hint}")
    return _BUILDERS[name]()  # cheap; a fresh BuiltinInfo each call (its dicts are the caller's)


def builtin_urdf(name: str) -> str:
    """URDF text of built-in model ``name`` (one of :data:`BUILTIN_MODELS`); ModelError otherwise."""
    return _get(name)[0]


def builtin_info(name: str) -> BuiltinInfo:
    """:class:`BuiltinInfo` of built-in model ``name``: feet, nominal stance, sensor CAD priors."""
    return _get(name)[1]
