"""Exteroceptive sensor models: depth camera (Kinect), 2D laser scanner (Hokuyo URG-04LX), stereo camera.

Each model gives its field of view (the unit ray directions in its own frame) and its range noise;
the real-data path (plane extraction, ICP weights, suggest-poses) and the simulator
(:mod:`graphcal.simulation.sensors`, which casts the rays into a scene) share them.

Sensor frames:
* cameras (depth, stereo): optical convention, z along the optical axis, x right, y down;
* laser scanner: the scan plane is the x-y plane, x along the centre beam, angles counter-clockwise
  about z.

Noise models (1-sigma, metres):
* depth camera: along the optical axis, sigma_z = 1.425e-3 * z**2 (Khoshelham & Elberink 2012, as Chai);
* laser scanner: along the beam, sigma_r = 0.01 (URG-04LX, 20-4000 mm range);
* stereo camera: along the optical axis, sigma_z = z**2 / (f_px * baseline_m) * sigma_disparity_px.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graphcal.errors import GraphcalError

__all__ = [
    "SENSOR_TYPES",
    "SensorType",
    "SENSOR_TYPE_RECORDS",
    "sensor_type",
    "KINECT_NOISE_COEFF_PER_M",
    "DepthCamera",
    "StereoCamera",
    "LaserScanner",
    "Sensor",
    "sensor_for_type",
    "PHYSICAL_NOISE_DEFAULTS",
    "PHYSICAL_NOISE_FLOORS",
    "PHYSICAL_NOISE_KEYS",
    "RANGE_SCALE_CHECK_PCT",
]

#: Kinect depth noise: sigma_z = KINECT_NOISE_COEFF_PER_M * z**2 (m), Khoshelham & Elberink 2012,
#: as used by Chai 2015.
KINECT_NOISE_COEFF_PER_M = 1.425e-3


@dataclass(frozen=True)
class DepthCamera:
    """Pinhole depth camera; defaults are the Kinect of Chai 2015 (57.5 x 43.5 deg, 0.8-4 m)."""

    width_px: int = 640
    height_px: int = 480
    hfov_deg: float = 57.5
    vfov_deg: float = 43.5
    min_range_m: float = 0.8
    max_range_m: float = 4.0
    noise_coeff_per_m: float = KINECT_NOISE_COEFF_PER_M
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


@dataclass(frozen=True)
class SensorType:
    """One exteroceptive sensor type (dataset.yaml ``sensors.<name>.type``): everything graphcal
    does differently per type is read from here.

    Attributes:
        name: the type's name in datasets and import maps.
        model: its default sensor model (field of view, range noise in m), a class of this module.
        measures: ``"planes"`` (3-D clouds, fitted with planes into planes.csv, Chai's factor) or
            ``"scans"`` (2-D scan points, each against the floor, Łabęcki's factor).
        log_messages: the ROS message types ``graphcal import`` reads it from (() = not importable).
        range_scale_check_pct: how well the data must determine its range scale, per cent of the
            range (:data:`RANGE_SCALE_CHECK_PCT`).
    """

    name: str
    model: type
    measures: str
    log_messages: tuple[str, ...]
    range_scale_check_pct: float

    @property
    def fits_planes(self) -> bool:
        """Its clouds are fitted with planes (a camera); else its scans are used point by point."""
        return self.measures == "planes"


def sensor_type(name: str) -> SensorType:
    """The record of sensor type ``name``; GraphcalError naming the known ones otherwise."""
    try:
        return SENSOR_TYPE_RECORDS[name]
    except (KeyError, TypeError):
        raise GraphcalError(f"unknown sensor type {name!r}; expected one of {', '.join(SENSOR_TYPES)}") from None


def sensor_for_type(name: str) -> Sensor:
    """Default sensor model for a dataset sensor type."""
    return sensor_type(name).model()


def _pinhole_rays(width: int, height: int, hfov_deg: float, vfov_deg: float) -> np.ndarray:
    fx = width / 2.0 / np.tan(np.radians(hfov_deg) / 2.0)
    fy = height / 2.0 / np.tan(np.radians(vfov_deg) / 2.0)
    u = np.arange(width) + 0.5 - width / 2.0
    v = np.arange(height) + 0.5 - height / 2.0
    U, V = np.meshgrid(u, v)
    d = np.c_[U.ravel() / fx, V.ravel() / fy, np.ones(U.size)]
    return d / np.linalg.norm(d, axis=1, keepdims=True)


#: Physically plausible noise of each measurement group, used to judge whether a calibration's
#: model fits (graphcal/calibration/adequacy.py) when dataset.yaml declares none
#: (``physical_noise:``, docs/calibration.md). Keys and units as in dataset.yaml (deg, mm). Where
#: they come from:
#:
#: * ``joint_deg`` 0.1: a servo's joint reading, encoder plus gear backlash (a 12-bit encoder has a
#:   0.088 deg step, 0.025 deg RMS; hobby-servo backlash is a few tenths of a degree); the
#:   calibration's own default joint sigma;
#: * ``contact_mm`` 0.5: where a rubber-tipped point foot touches, about its nominal point (a tip
#:   radius of a few mm deforming under load);
#: * ``ground_mm`` 2.0: an indoor floor's flatness under the feet (DIN 18202 allows 2-4 mm over
#:   0.1-1 m); ``--ground-roughness-mm`` replaces it;
#: * ``imu_deg`` 0.3: gravity direction from a MEMS accelerometer's station average, dominated by
#:   its bias (0.02-0.05 m/s^2 is 0.1-0.3 deg);
#: * ``commanded_deg`` 1.0, ``commanded_mm`` 10.0: how far a position-controlled body ends up from
#:   its set pose (the calibration's default commanded-pose sigma);
#: * a sensor's planes or scans: scale 1 of the sensor model above (sigma_z of the depth camera,
#:   10 mm of the laser scanner, the stereo disparity noise): ``plane_scale`` 1.
PHYSICAL_NOISE_DEFAULTS: dict[str, float] = {
    "joint_deg": 0.1,
    "contact_mm": 0.5,
    "ground_mm": 2.0,
    "imu_deg": 0.3,
    "commanded_deg": 1.0,
    "commanded_mm": 10.0,
    "plane_scale": 1.0,
}

#: The smallest physical value a group is judged against (a declared 0, e.g. the simulator's point
#: feet on an exact floor, is this): a learned sigma below about twice these is numerically nothing.
PHYSICAL_NOISE_FLOORS: dict[str, float] = {
    "joint_deg": 0.005,
    "contact_mm": 0.1,
    "ground_mm": 0.5,
    "imu_deg": 0.01,
    "commanded_deg": 0.02,
    "commanded_mm": 0.2,
    "plane_scale": 1.0,
}

_CLOUD = "sensor_msgs/msg/PointCloud2"
#: every sensor type, in dataset.yaml's order
SENSOR_TYPE_RECORDS: dict[str, SensorType] = {t.name: t for t in (
    SensorType("depth_camera", DepthCamera, "planes", (_CLOUD, "sensor_msgs/msg/Image"), 0.5),
    SensorType("laser_scanner", LaserScanner, "scans", ("sensor_msgs/msg/LaserScan", _CLOUD), 0.5),
    SensorType("stereo_camera", StereoCamera, "planes", (), 0.5),
)}
#: The exteroceptive sensor types of a dataset (dataset.yaml ``sensors.<name>.type``).
SENSOR_TYPES: tuple[str, ...] = tuple(SENSOR_TYPE_RECORDS)
#: How well calibrate's data must determine a sensor's range (depth) scale, per sensor type, in per
#: cent of the range (graphcal/calibration/range_observability.py, docs/calibration.md): the 1-sigma
#: of the scale from the data alone above this is a warning that the data cannot check the
#: assumption that the range is exact. Half of the scale error the class may have, so that such an
#: error stands 2 sigma out of the data:
#:
#: * ``laser_scanner`` 0.5: the Hokuyo URG-04LX's datasheet gives its accuracy as +-10 mm up to 1 m
#:   and +-1 % of the range beyond;
#: * ``depth_camera`` 0.5: a structured-light or time-of-flight depth is ``f b / disparity`` (or a
#:   phase) whose scale is the relative error of its factory calibration (focal length times
#:   baseline, modulation frequency): of the order of 1 %;
#: * ``stereo_camera`` 0.5: depth ``f b / d``: its scale is off by the relative error of the
#:   calibrated focal length times baseline (a checkerboard calibration: a few tenths of 1 %).
#:
#: dataset.yaml ``physical_noise: {range_scale_pct: ...}`` replaces it for every sensor.
RANGE_SCALE_CHECK_PCT: dict[str, float] = {t.name: t.range_scale_check_pct for t in SENSOR_TYPE_RECORDS.values()}

#: The keys dataset.yaml's ``physical_noise:`` may hold (the others are errors); ``range_scale_pct``
#: (per cent) is read by range_observability.py, not judged as a noise group.
PHYSICAL_NOISE_KEYS: tuple[str, ...] = tuple(k for k in PHYSICAL_NOISE_DEFAULTS if k != "plane_scale") + (
    "range_scale_pct",)
