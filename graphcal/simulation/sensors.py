"""Simulated exteroceptive sensors: cast a sensor model's rays into the world meshes and add its noise.

The sensor models (field of view, noise) are :mod:`graphcal.models.sensors`; here each sensor casts
its rays in its own frame, intersects them with the world meshes (Open3D ray casting) and perturbs
the range along each ray with its noise model. Points come back in the sensor frame. The
``range_scale`` argument multiplies every measured range (the ``sensor_range_scale`` effect).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graphcal.models.sensors import Sensor, sensor_type
from graphcal.simulation.terrain import build_scene

__all__ = ["Scan", "capture"]


@dataclass(frozen=True)
class Scan:
    """One capture: ``points_sensor`` (N, 3) m in the sensor frame, ``labels`` (N,) int (see terrain),
    ``true_points_sensor`` (N, 3) the noise-free hits (for evaluation only)."""

    points_sensor: np.ndarray
    labels: np.ndarray
    true_points_sensor: np.ndarray


def capture(
    sensor: Sensor,
    meshes,
    T_world_sensor: np.ndarray,
    rng: np.random.Generator,
    *,
    range_scale: float = 1.0,
    scene=None,
) -> Scan:
    """Cast the sensor's rays into ``meshes`` from pose ``T_world_sensor`` (4x4) and add noise.

    Args:
        sensor: a sensor model.
        meshes: world-frame meshes (ignored when ``scene`` = (RaycastingScene, labels) is given).
        T_world_sensor: pose of the sensor frame in the world (4x4, m).
        rng: random generator for the noise.
        range_scale: measured range = range_scale * true range (1 = no scale error).
    """
    import open3d as o3d

    if scene is None:
        scene = build_scene(meshes)
    rc_scene, labels_by_id = scene
    dirs_sensor = sensor.ray_directions()
    R = T_world_sensor[:3, :3]
    dirs_world = dirs_sensor @ R.T
    rays = np.empty((len(dirs_sensor), 6), dtype=np.float32)
    rays[:, :3] = T_world_sensor[:3, 3]
    rays[:, 3:] = dirs_world
    hit = rc_scene.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy().astype(float)
    gid = hit["geometry_ids"].numpy()
    ok = np.isfinite(t)
    t, gid, dirs = t[ok], gid[ok], dirs_sensor[ok]
    true_pts = dirs * t[:, None]
    if not sensor_type(sensor.type).fits_planes:  # a scanner: noise along the beam
        keep = (t >= sensor.min_range_m) & (t <= sensor.max_range_m)
        t, gid, dirs, true_pts = t[keep], gid[keep], dirs[keep], true_pts[keep]
        r = t + rng.normal(0.0, sensor.sigma_m, size=t.shape)
        pts = dirs * (range_scale * r)[:, None]
    else:
        z = true_pts[:, 2]
        keep = (z >= sensor.min_range_m) & (z <= sensor.max_range_m)
        z, gid, dirs, true_pts = z[keep], gid[keep], dirs[keep], true_pts[keep]
        z_meas = z + rng.normal(0.0, 1.0, size=z.shape) * sensor.sigma_along_axis(z)
        pts = dirs * (range_scale * z_meas / dirs[:, 2])[:, None]
    label_lut = np.full(int(gid.max()) + 1 if len(gid) else 1, -1, dtype=np.int16)
    for k, lab in labels_by_id.items():
        if k < len(label_lut):
            label_lut[k] = lab
    labels = label_lut[gid] if len(gid) else np.zeros(0, dtype=np.int16)
    return Scan(pts, labels.astype(np.int16), true_pts)
