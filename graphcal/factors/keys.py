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
W(0)      R_ground_level       gravity's frame in the ground frame (diagnosis: ground_tilt)  Rot3
G(1+j)    plane_world          the ground the sensors see in session j, when it differs      OrientedPlane3
                               (diagnosis: session_offset)
M(0)      R_body_imu           the IMU mounting rotation, when estimated                    Rot3
C(k)      [scale]              range scale of sensor k (diagnosis: sensor_range_scale)      Vector 1
V(0)      T_body_mocap         the motion-capture frame (or Yuan's virtual base) in the     Pose3
                               body frame (leg identification, factors/mocap_marker.py)
K(j)      p_foot_marker        position of motion-capture marker j on its foot (foot        Point3
                               frame), when dataset.yaml does not give it
R(0)      [radius]             foot radius, every foot (diagnosis: foot_radius,             Vector 1
                               factors/stance_contact.py)
Q(j)      [compliance]         compliance of joint index j of every leg, rad per m of       Vector 1
                               lever (diagnosis: joint_compliance)
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
W = _s.W  #: R_ground_level, gravity against a tilted floor
V = _s.V  #: motion-capture frame (or virtual base) T_body_mocap
K = _s.K  #: motion-capture marker position p_foot_marker j
R = _s.R  #: foot radius (diagnosis)
Q = _s.Q  #: joint compliance of joint index j of every leg (diagnosis)

__all__ = ["X", "S", "F", "L", "G", "M", "C", "W", "V", "K", "R", "Q"]
