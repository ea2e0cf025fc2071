"""Simulated depth clouds of the stairs seen from a robot walking towards and up them, with pose
errors of the size a state estimate has: the test data of :mod:`graphcal.locomotion.stairs` and
:mod:`graphcal.planning.gait` (and a quick way to try them by hand).

The body follows the terrain: its height is ``body_height_m`` above the mean terrain height under
its front and back hips (``hip_offset_m`` ahead of and behind the body origin along world x), its
pitch the slope between those two heights (nose up on the stairs), no roll, no yaw. The camera is
the robot's depth camera at ``T_body_sensor``; clouds are ray cast from the *true* poses with the
sensor's noise model (:func:`graphcal.simulation.sensors.capture`); the poses handed to the stairs
model are the true ones perturbed on the right, ``T_world_body_est = T_world_body @ Exp(xi)``,
``xi ~ N(0, diag(sigma_rad^2 I3, sigma_m^2 I3))`` (GTSAM order ``[omega, v]``, body frame).

Frames and units: world z up, floor z = 0, stairs rising along +x (see
:func:`graphcal.simulation.terrain.make_terrain`); metres, radians.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.geometry import matrix_from_rpy, pose_matrix, se3_exp

__all__ = ["StairsCloudSequence", "stairs_height", "body_poses_along_x", "simulate_stairs_clouds"]


@dataclass(frozen=True, eq=False)
class StairsCloudSequence:
    """Clouds of one approach to the stairs.

    Attributes:
        clouds_sensor: (N_k, 3) points per cloud in the sensor (optical) frame, m.
        T_world_sensor_est: (4, 4) per cloud: the estimated (perturbed) sensor poses.
        T_world_sensor_true: (4, 4) per cloud: the true sensor poses.
        T_world_body_true: (4, 4) per cloud: the true body poses.
        T_world_body_est: (4, 4) per cloud: the estimated (perturbed) body poses.
        T_body_sensor: (4, 4) the sensor extrinsic used for both.
        terrain: the :class:`graphcal.simulation.terrain.Terrain` (its ``stairs`` are the truth).
    """

    clouds_sensor: tuple
    T_world_sensor_est: tuple
    T_world_sensor_true: tuple
    T_world_body_true: tuple
    T_world_body_est: tuple
    T_body_sensor: np.ndarray
    terrain: object


def stairs_height(steps: Sequence, x_world: np.ndarray) -> np.ndarray:
    """Height (m) of an untilted staircase (``steps``: records with ``x_start_m``, ``depth_m``,
    ``height_m``) at world x (array, m): the top of the highest step whose tread starts at or
    before x and whose box still covers x; 0 (the floor) elsewhere."""
    x = np.asarray(x_world, dtype=float)
    h = np.zeros_like(x)
    for s in steps:
        inside = (x >= s.x_start_m) & (x <= s.x_start_m + s.depth_m)
        h = np.where(inside, np.maximum(h, s.height_m), h)
    return h


def body_poses_along_x(
    steps: Sequence,
    x_body_m: Sequence[float],
    *,
    body_height_m: float = 0.45,
    hip_offset_m: float = 0.35,
    y_m: float = 0.0,
) -> list[np.ndarray]:
    """True body poses T_world_body (4x4) at the given body-origin x positions (m), following the
    stairs as the module docstring says."""
    out = []
    for x in np.asarray(x_body_m, dtype=float):
        h_front, h_back = stairs_height(steps, np.array([x + hip_offset_m, x - hip_offset_m]))
        pitch = -np.arctan2(h_front - h_back, 2.0 * hip_offset_m)  # nose up = negative pitch (ROS)
        z = 0.5 * (h_front + h_back) + body_height_m
        out.append(pose_matrix(matrix_from_rpy([0.0, pitch, 0.0]), [x, y_m, z]))
    return out


def simulate_stairs_clouds(
    *,
    x_body_m: Sequence[float] = tuple(np.linspace(-0.4, 1.0, 10)),
    pose_sigma_m: float = 0.01,
    pose_sigma_rad: float = float(np.radians(0.3)),
    stride: int = 4,
    seed: int = 0,
    stairs_start_x_m: float = 1.2,
    robot: str = "qingzhui",
    sensor: str = "depth",
    y_m: float = 0.0,
) -> StairsCloudSequence:
    """Depth clouds of the ``stairs`` terrain from body poses along x, and perturbed pose estimates.

    Args:
        x_body_m: body-origin x positions (m) of the captures (the stairs start at
            ``stairs_start_x_m``).
        pose_sigma_m, pose_sigma_rad: std of each translation / rotation component of the pose error
            (body frame, right perturbation). Defaults: 1 cm and 0.3 deg per axis, i.e. ~1.7 cm and
            ~0.5 deg in norm.
        stride: cast every ``stride``-th pixel row and column of the 640x480 camera (noise model of the
            full-resolution sensor kept).
        seed: seed of the depth noise and of the pose errors.
        robot, sensor: built-in robot whose sensor CAD pose ``T_body_sensor`` is used.
        y_m: lateral body position (m).
    """
    from graphcal.models.builtin import builtin_info
    from graphcal.models.sensors import DepthCamera
    from graphcal.simulation.sensors import capture
    from graphcal.simulation.terrain import build_scene, make_terrain

    if stride < 1:
        raise GraphcalError(f"simulate_stairs_clouds: stride must be >= 1, got {stride}")
    info = builtin_info(robot)
    if sensor not in info.sensors or info.sensors[sensor].type != "depth_camera":
        raise GraphcalError(f"simulate_stairs_clouds: robot {robot!r} has no depth camera named {sensor!r}")
    T_body_sensor = np.array(info.sensors[sensor].T_body_sensor, dtype=float)
    terrain = make_terrain("stairs", stairs_start_x_m=stairs_start_x_m)
    cam = DepthCamera(width_px=640 // stride, height_px=480 // stride)
    scene = build_scene(terrain.meshes)
    rng = np.random.default_rng(seed)
    T_body_true = body_poses_along_x(terrain.stairs, x_body_m, body_height_m=info.default_body_height_m, y_m=y_m)
    clouds, Ts_est, Ts_true, Tb_est = [], [], [], []
    for T_wb in T_body_true:
        T_ws = T_wb @ T_body_sensor
        scan = capture(cam, None, T_ws, rng, scene=scene)
        xi = np.concatenate([rng.normal(0.0, pose_sigma_rad, 3), rng.normal(0.0, pose_sigma_m, 3)])
        T_wb_est = T_wb @ se3_exp(xi)
        clouds.append(scan.points_sensor)
        Ts_true.append(T_ws)
        Tb_est.append(T_wb_est)
        Ts_est.append(T_wb_est @ T_body_sensor)
    return StairsCloudSequence(
        tuple(clouds), tuple(Ts_est), tuple(Ts_true), tuple(T_body_true), tuple(Tb_est), T_body_sensor, terrain
    )
