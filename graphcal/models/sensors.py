"""Exteroceptive sensor models: depth camera (Kinect), 2D laser scanner (Hokuyo URG-04LX), stereo camera.

Each sensor casts rays in its own frame, intersects them with the world meshes (Open3D ray casting)
and perturbs the range along each ray with its noise model. Points come back in the sensor frame.

Sensor frames:
* cameras (depth, stereo): optical convention, z along the optical axis, x right, y down;
* laser scanner: the scan plane is the x-y plane, x along the centre beam, angles counter-clockwise
  about z.

Noise models (1-sigma, metres):
* depth camera: along the optical axis, sigma_z = 1.425e-3 * z**2 (Khoshelham & Elberink 2012, as Chai);
* laser scanner: along the beam, sigma_r = 0.01 (URG-04LX, 20-4000 mm range);
* stereo camera: along the optical axis, sigma_z = z**2 / (f_px * baseline_m) * sigma_disparity_px.
The ``range_scale`` argument multiplies every measured range (the ``sensor_range_scale`` effect).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.simulation.terrain import build_scene

SENSOR_TYPES = ("depth_camera", "laser_scanner", "stereo_camera")


@dataclass(frozen=True)
class DepthCamera:
    """Pinhole depth camera; defaults are the Kinect of Chai 2015 (57.5 x 43.5 deg, 0.8-4 m)."""

    width_px: int = 640
    height_px: int = 480
    hfov_deg: float = 57.5
    vfov_deg: float = 43.5
    min_range_m: float = 0.8
    max_range_m: float = 4.0
    noise_coeff_per_m: float = 1.425e-3
    type: str = "depth_camera"

    def ray_directions(self) -> np.ndarray:
        """Unit ray directions (H*W, 3) in the optical frame."""
        return _pinhole_rays(self.width_px, self.height_px, self.hfov_deg, self.vfov_deg)

    def sigma_along_axis(self, z_m: np.ndarray) -> np.ndarray:
        """Depth noise sigma (m) at depth ``z_m`` (m)."""
        return self.noise_coeff_per_m * np.asarray(z_m) ** 2


@dataclass(frozen=True)
class StereoCamera:
    """Stereo camera (STOC-like): depth noise grows with z**2 / baseline."""

    width_px: int = 320
    height_px: int = 240
    hfov_deg: float = 65.0
    vfov_deg: float = 50.0
    baseline_m: float = 0.09
    sigma_disparity_px: float = 0.15
    min_range_m: float = 0.4
    max_range_m: float = 4.0
    noise_focal_px: float | None = None
    type: str = "stereo_camera"

    @property
    def focal_px(self) -> float:
        """Focal length (px) that sets the disparity noise: that of the full-resolution sensor, kept
        when the simulator casts fewer rays (``noise_focal_px``)."""
        if self.noise_focal_px is not None:
            return self.noise_focal_px
        return self.width_px / 2.0 / np.tan(np.radians(self.hfov_deg) / 2.0)

    def ray_directions(self) -> np.ndarray:
        return _pinhole_rays(self.width_px, self.height_px, self.hfov_deg, self.vfov_deg)

    def sigma_along_axis(self, z_m: np.ndarray) -> np.ndarray:
        return np.asarray(z_m) ** 2 / (self.focal_px * self.baseline_m) * self.sigma_disparity_px


@dataclass(frozen=True)
class LaserScanner:
    """2D laser scanner, Hokuyo URG-04LX-like: 240 deg field, 0.36 deg step, 0.02-4 m, sigma 10 mm."""

    fov_deg: float = 240.0
    step_deg: float = 0.36
    min_range_m: float = 0.02
    max_range_m: float = 4.0
    sigma_m: float = 0.01
    type: str = "laser_scanner"

    def ray_directions(self) -> np.ndarray:
        n = int(round(self.fov_deg / self.step_deg)) + 1
        ang = np.radians(np.linspace(-self.fov_deg / 2, self.fov_deg / 2, n))
        return np.c_[np.cos(ang), np.sin(ang), np.zeros(n)]


Sensor = DepthCamera | StereoCamera | LaserScanner


def sensor_for_type(sensor_type: str) -> Sensor:
    """Default sensor model for a dataset sensor type."""
    if sensor_type == "depth_camera":
        return DepthCamera()
    if sensor_type == "laser_scanner":
        return LaserScanner()
    if sensor_type == "stereo_camera":
        return StereoCamera()
    raise GraphcalError(f"unknown sensor type {sensor_type!r}; expected one of {', '.join(SENSOR_TYPES)}")


def _pinhole_rays(width: int, height: int, hfov_deg: float, vfov_deg: float) -> np.ndarray:
    fx = width / 2.0 / np.tan(np.radians(hfov_deg) / 2.0)
    fy = height / 2.0 / np.tan(np.radians(vfov_deg) / 2.0)
    u = np.arange(width) + 0.5 - width / 2.0
    v = np.arange(height) + 0.5 - height / 2.0
    U, V = np.meshgrid(u, v)
    d = np.c_[U.ravel() / fx, V.ravel() / fy, np.ones(U.size)]
    return d / np.linalg.norm(d, axis=1, keepdims=True)


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
    if isinstance(sensor, LaserScanner):
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
