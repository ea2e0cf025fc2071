"""The discrepancy catalogue as simulator options.

Each cause that ``graphcal diagnose`` can name (:data:`graphcal.models.effects.CAUSES`, whose
docstring tables the physical story and parameters of each) is something the simulator can hide
in the data. Names, parameters and units are those of the catalogue (SI units); :class:`Effects`
holds one value per cause.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Mapping

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.models.effects import CAUSES


def _frozen(mapping: Mapping | None) -> Mapping:
    return MappingProxyType(dict(mapping or {}))


@dataclass(frozen=True)
class ExtrinsicChange:
    """The sensor ``sensor`` is knocked just before station ``station`` (that station is the first
    with the new extrinsic): rotated by ``angle_rad`` about ``axis`` (body frame, unit) and shifted by
    ``translation_m`` (3,) in the body frame."""

    sensor: str
    station: int
    angle_rad: float
    axis: tuple[float, float, float]
    translation_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class OpenWorld:
    """Physical effects OUTSIDE the catalogue (``graphcal diagnose`` has no cause for them): the
    open-world battery (examples/diagnosis_openworld.py) hides them to check that diagnose either
    says structure remains or names a cause that explains them, never a confident wrong one. The
    default hides nothing.

    Attributes:
        range_quadratic: sensor -> k (1/m): every point of that sensor is read at range r (1 + k r)
            (a depth error growing with range^2, k r^2).
        plate: (session, feet, height_m): in that session the named feet stand on a plate
            ``height_m`` thick (the others on the floor).
        sinking: session -> depth_m: the feet sink steadily during that session, by ``depth_m`` at
            its last station (0 at its first).
        imu_drift: (angle_rad, axis_rad): the IMU mount tilts steadily during the run (a mount
            warming up), about the horizontal body axis at azimuth ``axis_rad``, by 0 at the first
            station and ``angle_rad`` at the last.
    """

    range_quadratic: Mapping[str, float] = field(default_factory=dict)
    plate: tuple | None = None
    sinking: Mapping[str, float] = field(default_factory=dict)
    imu_drift: tuple | None = None

    def __post_init__(self):
        for name in ("range_quadratic", "sinking"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))

    def active(self) -> tuple[str, ...]:
        """Names of the open-world effects hidden."""
        return tuple(n for n in ("range_quadratic", "plate", "sinking", "imu_drift") if getattr(self, n))

    def to_dict(self) -> dict:
        """Plain-YAML form (SI units) for truth.yaml."""
        d: dict = {}
        if self.range_quadratic:
            d["range_quadratic"] = {k: {"k_per_m": float(v)} for k, v in self.range_quadratic.items()}
        if self.plate:
            s, feet, h = self.plate
            d["plate"] = {"session": s, "feet": list(feet), "height_m": float(h)}
        if self.sinking:
            d["sinking"] = {k: {"depth_m": float(v)} for k, v in self.sinking.items()}
        if self.imu_drift:
            d["imu_drift"] = {"angle_rad": float(self.imu_drift[0]), "axis_rad": float(self.imu_drift[1])}
        return d


@dataclass(frozen=True)
class Effects:
    """Effects hidden in a simulated dataset. The default hides nothing.

    Attributes:
        sensor_range_scale: sensor name -> scale (1.02 = ranges read 2 % long).
        session_offset: session label -> offset_m (> 0: the feet sink that far below the surface).
        ground_tilt: (tilt_rad, axis_rad) or None.
        imu_misalignment: (angle_rad, axis_rad) or None; the axis is horizontal in the body frame at
            azimuth axis_rad (a vertical misalignment is yaw, which gravity cannot show).
        joint_offset: URDF joint name -> encoder zero error (rad): true angle = measured + offset.
        link_length: URDF joint name -> change (m) of the length of the link ending at that joint.
        extrinsic_change: an :class:`ExtrinsicChange` or None.
        outlier_stations: station ids whose sensor data are those of another station.
        foot_radius: radius_m of every foot (a sphere; the URDF foot frame is the lower leg's tip,
            the contact rolls with the leg; factors/stance_contact.py).
        joint_compliance: (joint_index, k_rad_per_m): the joint at that index of every leg flexes
            by ``k * lever`` (lever: torque per newton of vertical load on the foot, m); the
            encoder reads the true angle minus the deflection.
        open_world: effects outside the catalogue (:class:`OpenWorld`); not in :meth:`active`.
    """

    sensor_range_scale: Mapping[str, float] = field(default_factory=dict)
    session_offset: Mapping[str, float] = field(default_factory=dict)
    ground_tilt: tuple[float, float] | None = None
    imu_misalignment: tuple[float, float] | None = None
    joint_offset: Mapping[str, float] = field(default_factory=dict)
    link_length: Mapping[str, float] = field(default_factory=dict)
    extrinsic_change: ExtrinsicChange | None = None
    outlier_stations: tuple[int, ...] = ()
    foot_radius: float = 0.0
    joint_compliance: tuple[int, float] | None = None
    open_world: OpenWorld = field(default_factory=OpenWorld)

    def __post_init__(self):
        for name in ("sensor_range_scale", "session_offset", "joint_offset", "link_length"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))
        for sensor, scale in self.sensor_range_scale.items():
            if not (0.5 < scale < 2.0):
                raise GraphcalError(f"sensor_range_scale for {sensor!r} must be near 1, got {scale}")

    def active(self) -> tuple[str, ...]:
        """Names of the causes this object hides."""
        out = []
        if self.sensor_range_scale:
            out.append("sensor_range_scale")
        if self.session_offset:
            out.append("session_offset")
        if self.ground_tilt is not None and self.ground_tilt[0] != 0.0:
            out.append("ground_tilt")
        if self.imu_misalignment is not None and self.imu_misalignment[0] != 0.0:
            out.append("imu_misalignment")
        if self.joint_offset:
            out.append("joint_offset")
        if self.link_length:
            out.append("link_length")
        if self.extrinsic_change is not None:
            out.append("extrinsic_change")
        if self.outlier_stations:
            out.append("outlier_stations")
        if self.foot_radius:
            out.append("foot_radius")
        if self.joint_compliance is not None and self.joint_compliance[1] != 0.0:
            out.append("joint_compliance")
        return tuple(out)

    def to_dict(self) -> dict:
        """Plain-YAML form (SI units) for truth.yaml."""
        d: dict = {}
        if self.sensor_range_scale:
            d["sensor_range_scale"] = {k: {"scale": float(v)} for k, v in self.sensor_range_scale.items()}
        if self.session_offset:
            d["session_offset"] = {k: {"offset_m": float(v)} for k, v in self.session_offset.items()}
        if self.ground_tilt is not None:
            d["ground_tilt"] = {"tilt_rad": float(self.ground_tilt[0]), "axis_rad": float(self.ground_tilt[1])}
        if self.imu_misalignment is not None:
            d["imu_misalignment"] = {
                "angle_rad": float(self.imu_misalignment[0]),
                "axis_rad": float(self.imu_misalignment[1]),
            }
        if self.joint_offset:
            d["joint_offset"] = {k: {"offset_rad": float(v)} for k, v in self.joint_offset.items()}
        if self.link_length:
            d["link_length"] = {k: {"delta_m": float(v)} for k, v in self.link_length.items()}
        if self.extrinsic_change is not None:
            c = self.extrinsic_change
            d["extrinsic_change"] = {
                "sensor": c.sensor,
                "station": int(c.station),
                "angle_rad": float(c.angle_rad),
                "axis": [float(a) for a in c.axis],
                "translation_m": [float(t) for t in c.translation_m],
            }
        if self.outlier_stations:
            d["outlier_stations"] = {"stations": [int(s) for s in self.outlier_stations]}
        if self.foot_radius:
            d["foot_radius"] = {"radius_m": float(self.foot_radius)}
        if self.joint_compliance is not None:
            d["joint_compliance"] = {"joint_index": int(self.joint_compliance[0]),
                                     "k_rad_per_m": float(self.joint_compliance[1])}
        if self.open_world.active():
            d["open_world"] = self.open_world.to_dict()
        return d


# Realistic magnitudes of the hidden-effect battery (issue "graphcal diagnose").
MAGNITUDES = {
    "sensor_range_scale": (0.01, 0.03),  # |scale - 1|
    "session_offset": (0.010, 0.035),  # m
    "ground_tilt": (np.radians(1.0), np.radians(2.5)),
    "imu_misalignment": (np.radians(1.0), np.radians(3.0)),
    "joint_offset": (np.radians(1.5), np.radians(4.0)),
    "link_length": (0.010, 0.025),  # m
    "extrinsic_change": (np.radians(1.5), np.radians(3.0)),
    "outlier_stations": (3, 3),
    "foot_radius": (0.015, 0.030),  # m
    "joint_compliance": (0.15, 0.4),  # rad per m of lever: ~1-2.5 deg at a 0.1 m lever
}


def draw_effect(
    cause: str,
    rng: np.random.Generator,
    *,
    sensors: tuple[str, ...],
    sessions: tuple[str, ...],
    stations: tuple[int, ...],
    leg_joints: Mapping[str, tuple[str, ...]],
    link_joints: Mapping[str, tuple[str, ...]],
) -> tuple[Effects, dict]:
    """Draw one hidden effect of ``cause`` at a realistic magnitude and location.

    Args:
        cause: a name of :data:`CAUSES`.
        rng: random generator (the seed decides magnitude and location).
        sensors, sessions, stations: what the dataset has.
        leg_joints: foot frame -> moving joints of that leg (candidates for ``joint_offset``).
        link_joints: foot frame -> joints whose origin is a link length (candidates for ``link_length``).
    Returns:
        (effects, where): ``where`` names the location in the catalogue's terms.
    """
    if cause not in CAUSES:
        raise GraphcalError(f"unknown cause {cause!r}; expected one of {', '.join(CAUSES)}")
    lo, hi = MAGNITUDES[cause]
    mag = float(rng.uniform(lo, hi))
    sign = float(rng.choice([-1.0, 1.0]))
    if cause == "sensor_range_scale":
        s = str(rng.choice(sensors))
        return Effects(sensor_range_scale={s: 1.0 + sign * mag}), {"sensor": s}
    if cause == "session_offset":
        s = str(rng.choice(sessions))
        return Effects(session_offset={s: mag}), {"session": s}
    if cause == "ground_tilt":
        return Effects(ground_tilt=(mag, float(rng.uniform(-np.pi, np.pi)))), {}
    if cause == "imu_misalignment":
        return Effects(imu_misalignment=(mag, float(rng.uniform(-np.pi, np.pi)))), {}
    if cause == "joint_offset":
        leg = str(rng.choice(sorted(leg_joints)))
        joint = str(rng.choice(leg_joints[leg]))
        return Effects(joint_offset={joint: sign * mag}), {"leg": leg, "joint": joint}
    if cause == "link_length":
        leg = str(rng.choice(sorted(link_joints)))
        joint = str(rng.choice(link_joints[leg]))
        return Effects(link_length={joint: sign * mag}), {"leg": leg, "joint": joint}
    if cause == "extrinsic_change":
        s = str(rng.choice(sensors))
        ordered = sorted(stations)
        k = int(rng.integers(len(ordered) // 3, 2 * len(ordered) // 3))
        axis = rng.standard_normal(3)
        axis /= np.linalg.norm(axis)
        change = ExtrinsicChange(s, ordered[k], mag, tuple(float(a) for a in axis))
        return Effects(extrinsic_change=change), {"station": ordered[k], "sensor": s}
    if cause == "foot_radius":
        return Effects(foot_radius=mag), {}
    if cause == "joint_compliance":
        n = min(len(v) for v in leg_joints.values())
        j = int(rng.integers(1, n)) if n > 1 else 0  # not the hip yaw (no vertical lever)
        return Effects(joint_compliance=(j, mag)), {"joint_index": j}
    # outlier_stations
    picked = tuple(sorted(int(s) for s in rng.choice(sorted(stations), size=int(lo), replace=False)))
    return Effects(outlier_stations=picked), {"stations": list(picked)}


def merge(a: Effects, b: Effects) -> Effects:
    """Both sets of effects (b wins where both set the same single-valued effect)."""
    return replace(
        a,
        sensor_range_scale={**a.sensor_range_scale, **b.sensor_range_scale},
        session_offset={**a.session_offset, **b.session_offset},
        ground_tilt=b.ground_tilt if b.ground_tilt is not None else a.ground_tilt,
        imu_misalignment=b.imu_misalignment if b.imu_misalignment is not None else a.imu_misalignment,
        joint_offset={**a.joint_offset, **b.joint_offset},
        link_length={**a.link_length, **b.link_length},
        extrinsic_change=b.extrinsic_change if b.extrinsic_change is not None else a.extrinsic_change,
        outlier_stations=tuple(sorted(set(a.outlier_stations) | set(b.outlier_stations))),
        foot_radius=b.foot_radius or a.foot_radius,
        joint_compliance=b.joint_compliance if b.joint_compliance is not None else a.joint_compliance,
        open_world=b.open_world if b.open_world.active() else a.open_world,
    )
