"""Variable keys of graphcal's factor graphs: one letter per variable kind, documented once.

========  ===================  ==========================================================  =========
key       variable             meaning                                                     type
========  ===================  ==========================================================  =========
X(i)      T_world_body         body pose at station i (station id from stations.csv)        Pose3
S(k)      T_body_sensor        extrinsic of sensor k (index in dataset.yaml order), or of   Pose3
                               its extrinsic segment k (after a detected change)
F(j)      p_world_foot         a planted foot: one per (session, foot), j = index           Point3
L(l)      theta_leg            kinematic parameters of leg l (index in robot.feet order)   Vector
G(0)      plane_world          the ground plane, when estimated                             OrientedPlane3
M(0)      R_body_imu           the IMU mounting rotation, when estimated                    Rot3
C(k)      [scale]              range scale of sensor k (diagnosis: sensor_range_scale)      Vector 1
Z(j)      [offset_m]           the feet of session j stand this far below the ground        Vector 1
                               (diagnosis: session_offset)
V(0)      T_body_mocap         the motion-capture frame (or Yuan's virtual base) in the     Pose3
                               body frame (leg identification, factors/mocap_marker.py)
K(j)      p_foot_marker        position of motion-capture marker j on its foot (foot        Point3
                               frame), when dataset.yaml does not give it
========  ===================  ==========================================================  =========

Every Pose3 is perturbed on the right, ``T = T_hat * Exp(xi)``, ``xi = [omega, v]`` (GTSAM).
"""

from __future__ import annotations

from gtsam import symbol_shorthand as _s

X = _s.X  #: body pose T_world_body of station i
S = _s.S  #: sensor extrinsic T_body_sensor (segment) k
F = _s.F  #: planted foot p_world_foot j
L = _s.L  #: leg parameter vector of leg l
G = _s.G  #: ground plane (OrientedPlane3)
M = _s.M  #: IMU mounting rotation R_body_imu
C = _s.C  #: range scale of sensor k
Z = _s.Z  #: offset of session j's feet below the ground
V = _s.V  #: motion-capture frame (or virtual base) T_body_mocap
K = _s.K  #: motion-capture marker position p_foot_marker j

__all__ = ["X", "S", "F", "L", "G", "M", "C", "Z", "V", "K"]
