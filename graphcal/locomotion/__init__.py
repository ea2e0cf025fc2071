"""State estimation of a legged robot (EKF mode): support detection from joint torques, an
error-state EKF (IMU, stance kinematics, ICP between keyframe clouds), metrics against the truth,
and the ``graphcal track`` command (see docs/state_estimation.md)."""
