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

__all__ = ["CAUSES"]

#: The causes, in the catalogue's order.
CAUSES = (
    "sensor_range_scale",
    "session_offset",
    "ground_tilt",
    "imu_misalignment",
    "joint_offset",
    "link_length",
    "extrinsic_change",
    "outlier_stations",
    "foot_radius",
    "joint_compliance",
)
