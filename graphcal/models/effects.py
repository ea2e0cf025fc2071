"""The causes a calibration model can get wrong: the one list shared by ``graphcal diagnose`` and the simulator.

``graphcal diagnose`` names these causes in measured data (:mod:`graphcal.diagnosis.catalogue`),
and the simulator can hide each of them in a simulated dataset (:mod:`graphcal.simulation.effects`).
Names, parameters and units (SI) are those of the catalogue (docs/diagnosis.md):

==================== ======================================================= ==========================
cause                physical story                                          parameters
==================== ======================================================= ==========================
sensor_range_scale   range/depth scale error of one sensor                   scale (measured = scale*true)
session_offset       one session's body height differs (foot sinkage)        offset_m (feet sink by it)
ground_tilt          the floor is not level                                  tilt_rad, axis_rad
imu_misalignment     the IMU is mounted rotated                              angle_rad, axis_rad
joint_offset         an encoder zero is off                                  offset_rad at (leg, joint)
link_length          a link is longer/shorter than the URDF                  delta_m at (leg, joint)
extrinsic_change     the sensor was knocked during the run                   angle_rad, translation_m
                                                                             from station, sensor
outlier_stations     a few stations are wrong (sensor data under the wrong   stations
                     station label)
foot_radius          the feet are spheres: the contact point rolls with the  radius_m (every foot)
                     lower leg (the URDF foot frame is the lower leg's tip)
joint_compliance     one joint of every leg flexes under the foot's load     k_rad_per_m at joint_index
                     (deflection = k * lever, lever = torque per newton of   (rad per m of lever)
                     vertical load, m)
==================== ======================================================= ==========================
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["CAUSES", "Cause", "CAUSE_RECORDS", "cause_record"]


@dataclass(frozen=True)
class Cause:
    """One cause of the table above: what diagnose, the simulator and the reports read of it.

    Attributes:
        name: its name (``simulate --effect NAME``, diagnosis.json ``cause``).
        parameters: its estimated parameters, ``(name, unit)`` (SI; the name ends in its unit).
        where: the keys that locate it (``sensor``, ``session``, ``leg`` + ``joint``, ...).
        relevant_from: ``(parameter, reference, minimum)``: a finding matters when any
            ``|parameter - reference| >= minimum`` (below, a significant effect is real but does not
            matter for calibration); () = always.
        kinematic: it changes the legs' kinematics (the controller's commanded poses assumed the
            nominal legs).
        leg_parameter: its parameter is one of a leg model's (``<joint>.<name>``), reported under
            ``legs`` rather than as an extension.
    """

    name: str
    parameters: tuple[tuple[str, str], ...]
    where: tuple[str, ...]
    relevant_from: tuple[tuple[str, float, float], ...]
    kinematic: bool = False
    leg_parameter: bool = False

    @property
    def parameter(self) -> str:
        """Its first (main) parameter's name."""
        return self.parameters[0][0]

    def relevant(self, values: dict) -> bool:
        """Whether estimated parameter ``values`` (SI) reach a minimum of :attr:`relevant_from`."""
        return not self.relevant_from or any(abs(values[k] - ref) >= m for k, ref, m in self.relevant_from)


_DEG = math.pi / 180.0
#: The causes, in the catalogue's order. The minimum sizes: 0.5 deg of any rotation, 3 mm of a
#: height or 0.3 % of a range scale, 4 mm of a link, 5 mm of a foot radius or a knock's translation,
#: 0.08 rad per m of lever (0.5 deg at a 0.1 m lever); e.g. a station-averaged accelerometer bias of
#: 0.05 m/s^2 is a 0.3 deg "misalignment", not one worth naming.
CAUSE_RECORDS: dict[str, Cause] = {c.name: c for c in (
    Cause("sensor_range_scale", (("scale", "1"),), ("sensor",), (("scale", 1.0, 0.003),)),
    Cause("session_offset", (("offset_m", "m"),), ("session",), (("offset_m", 0.0, 0.003),)),
    Cause("ground_tilt", (("tilt_rad", "rad"), ("axis_rad", "rad")), (), (("tilt_rad", 0.0, 0.5 * _DEG),)),
    Cause("imu_misalignment", (("angle_rad", "rad"), ("axis_rad", "rad")), (), (("angle_rad", 0.0, 0.5 * _DEG),)),
    Cause("joint_offset", (("offset_rad", "rad"),), ("leg", "joint"), (("offset_rad", 0.0, 0.5 * _DEG),),
          kinematic=True, leg_parameter=True),
    Cause("link_length", (("delta_m", "m"),), ("leg", "joint"), (("delta_m", 0.0, 0.004),),
          kinematic=True, leg_parameter=True),
    Cause("extrinsic_change", (("angle_rad", "rad"), ("translation_m", "m")), ("sensor", "station"),
          (("angle_rad", 0.0, 0.5 * _DEG), ("translation_m", 0.0, 0.005))),
    Cause("outlier_stations", (), ("stations",), ()),
    Cause("foot_radius", (("radius_m", "m"),), (), (("radius_m", 0.0, 0.005),), kinematic=True),
    Cause("joint_compliance", (("k_rad_per_m", "rad/m"),), ("joint_index",), (("k_rad_per_m", 0.0, 0.08),),
          kinematic=True),
)}
#: The causes' names, in the catalogue's order.
CAUSES: tuple[str, ...] = tuple(CAUSE_RECORDS)


def cause_record(name: str) -> Cause:
    """The record of cause ``name`` (KeyError naming the known ones otherwise)."""
    try:
        return CAUSE_RECORDS[name]
    except KeyError:
        raise KeyError(f"unknown cause {name!r}; expected one of {', '.join(CAUSES)}") from None
