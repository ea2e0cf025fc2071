"""A hexapod that is not one of graphcal's built-in models, written by hand as an outside user
would: rectangular body, legs pointing sideways, an IMU mounted turned by 90 degrees, and a depth
camera on the front. Used by tests that must not rely on the built-in robots."""

from __future__ import annotations

import numpy as np

from graphcal.geometry import pose_matrix, rot_y, rot_z
from graphcal.models.builtin import BuiltinInfo, SensorCAD

BODY_HEIGHT_M = 0.30
COXA_M, FEMUR_M, TIBIA_M = 0.08, 0.25, 0.35
LEGS = {  # name: (hip x, hip y, yaw of the leg's outward direction, deg)
    "front_left": (0.28, 0.14, 90.0),
    "middle_left": (0.0, 0.16, 90.0),
    "rear_left": (-0.28, 0.14, 90.0),
    "front_right": (0.28, -0.14, -90.0),
    "middle_right": (0.0, -0.16, -90.0),
    "rear_right": (-0.28, -0.14, -90.0),
}
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
T_BODY_CAMERA = pose_matrix(rot_y(np.radians(32.0)) @ R_BODY_OPTICAL, [0.36, 0.02, 0.12])
T_BODY_IMU = pose_matrix(rot_z(np.radians(90.0)), [0.05, 0.0, 0.02])


def _origin(xyz, rpy=(0.0, 0.0, 0.0)) -> str:
    x, r = [float(v) for v in xyz], [float(v) for v in rpy]
    return f'<origin xyz="{x[0]!r} {x[1]!r} {x[2]!r}" rpy="{r[0]!r} {r[1]!r} {r[2]!r}"/>'


def urdf_xml() -> str:
    parts = ['<?xml version="1.0"?>', '<robot name="sidewinder">', '<link name="base_link"/>']
    for leg, (x, y, yaw) in LEGS.items():
        a = np.radians(yaw)
        parts += [
            f'<link name="{leg}_hip"/><link name="{leg}_thigh"/><link name="{leg}_shin"/><link name="{leg}_toe"/>',
            f'<joint name="{leg}_yaw" type="revolute"><parent link="base_link"/><child link="{leg}_hip"/>'
            f'{_origin((x, y, 0.0), (0.0, 0.0, a))}<axis xyz="0 0 1"/>'
            '<limit lower="-1.0" upper="1.0" effort="50" velocity="5"/></joint>',
            f'<joint name="{leg}_lift" type="revolute"><parent link="{leg}_hip"/><child link="{leg}_thigh"/>'
            f'{_origin((COXA_M, 0.0, 0.0))}<axis xyz="0 -1 0"/>'
            '<limit lower="-1.6" upper="1.6" effort="50" velocity="5"/></joint>',
            f'<joint name="{leg}_knee" type="revolute"><parent link="{leg}_thigh"/><child link="{leg}_shin"/>'
            f'{_origin((FEMUR_M, 0.0, 0.0))}<axis xyz="0 -1 0"/>'
            '<limit lower="-2.6" upper="2.6" effort="50" velocity="5"/></joint>',
            f'<joint name="{leg}_toe_fixed" type="fixed"><parent link="{leg}_shin"/><child link="{leg}_toe"/>'
            f'{_origin((0.0, 0.0, -TIBIA_M))}</joint>',
        ]
    parts += [
        '<link name="imu_link"/>',
        f'<joint name="imu_mount" type="fixed"><parent link="base_link"/><child link="imu_link"/>'
        f'{_origin(T_BODY_IMU[:3, 3], (0.0, 0.0, np.pi / 2))}</joint>',
        "</robot>",
    ]
    return "\n".join(parts)


def info() -> BuiltinInfo:
    stance = {}
    for leg, (x, y, yaw) in LEGS.items():
        out = np.array([np.cos(np.radians(yaw)), np.sin(np.radians(yaw)), 0.0])
        stance[f"{leg}_toe"] = np.array([x, y, -BODY_HEIGHT_M]) + (COXA_M + FEMUR_M) * out
    return BuiltinInfo(
        name="sidewinder",
        base_frame="base_link",
        feet=tuple(f"{leg}_toe" for leg in LEGS),
        default_body_height_m=BODY_HEIGHT_M,
        nominal_stance=stance,
        sensors={"front_cam": SensorCAD("depth_camera", T_BODY_CAMERA, 0.03, np.radians(3.0))},
        T_body_imu=T_BODY_IMU,
    )
