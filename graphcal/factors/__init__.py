"""graphcal's factors: error models of legged-robot self-calibration for GTSAM.

Each module holds one factor kind as (1) a pure numpy function ``<name>_error(...)`` that returns
the error and its analytic Jacobians from plain inputs (4x4 poses, arrays) and (2) a builder
``<name>_factor(keys..., measurement..., noise...)`` that returns a ``gtsam.NonlinearFactor``.
Python factors go through :func:`graphcal.factors.checked.checked_custom_factor`, which checks every
Jacobian's type and shape (GTSAM would crash or silently mis-solve); GTSAM's built-in factors are
used wherever they express the model exactly. Variable keys: :mod:`factors.keys`.

Jacobians are w.r.t. right perturbations: Pose3 ``T Exp([omega, v])`` (rotation first), Rot3
``R Exp(omega)``, Point3 / Vector ``x + dx``, OrientedPlane3 GTSAM's retract (normal along its
Unit3 basis, then ``d + dd``). World: z up, ground ``n_w = (0, 0, 1)``, ``d_w = 0`` unless a
ground variable G is estimated. Details and derivations: docs/factors.md.

============================  ===================  ================================================
module                        variables            error
============================  ===================  ================================================
:mod:`.plane_observation`     X, S [, G]           plane seen by a sensor vs. world plane (3)
:mod:`.point_to_plane`        X, S [, G]           ground points' distances to the plane (N)
:mod:`.stance_foot`           X, F [, L]           leg FK vs. planted foot in the body frame (3)
:mod:`.stance_foot_builtin`   X, F                 the same with the legs fixed, GTSAM's bearing-range
                                                   factor in C++ (3, first-order equivalent)
:mod:`.imu_attitude`          X [, M]              accelerometer "up" vs. predicted up (2)
:mod:`.foot_on_ground`        F [, G]              foot's distance to the ground plane (1)
:mod:`.priors`                X / S / L            CAD extrinsic, commanded pose, leg parameters
:mod:`.mocap_marker`          V [, L] [, K]        foot markers (mocap frame) vs. leg FK, N samples (3N)
============================  ===================  ================================================
"""

from graphcal.factors.checked import FactorShapeError, checked_custom_factor, tangent_basis
from graphcal.factors.foot_on_ground import foot_on_ground_error, foot_on_ground_factor
from graphcal.factors.imu_attitude import (
    imu_attitude_error,
    imu_attitude_factor,
    imu_attitude_misaligned_error,
    imu_attitude_misaligned_factor,
    imu_up_direction,
)
from graphcal.factors.mocap_marker import mocap_marker_error, mocap_marker_factor
from graphcal.factors.plane_observation import (
    plane_angle_distance_error,
    plane_cov3,
    plane_noise_model,
    plane_observation_error,
    plane_observation_factor,
)
from graphcal.factors.point_to_plane import point_to_plane_error, point_to_plane_factor, point_to_plane_noise_model
from graphcal.factors.priors import commanded_pose_prior, extrinsic_prior, leg_offset_prior, pose_prior_sigmas
from graphcal.factors.stance_foot import stance_foot_error, stance_foot_factor
from graphcal.factors.stance_foot_builtin import stance_foot_builtin_factor, stance_foot_builtin_factors, stance_foot_error_map

__all__ = [
    "FactorShapeError",
    "checked_custom_factor",
    "tangent_basis",
    "plane_observation_error",
    "plane_observation_factor",
    "plane_noise_model",
    "plane_cov3",
    "plane_angle_distance_error",
    "point_to_plane_error",
    "point_to_plane_factor",
    "point_to_plane_noise_model",
    "stance_foot_error",
    "stance_foot_factor",
    "stance_foot_builtin_factor",
    "stance_foot_builtin_factors",
    "stance_foot_error_map",
    "mocap_marker_error",
    "mocap_marker_factor",
    "imu_up_direction",
    "imu_attitude_error",
    "imu_attitude_factor",
    "imu_attitude_misaligned_error",
    "imu_attitude_misaligned_factor",
    "foot_on_ground_error",
    "foot_on_ground_factor",
    "extrinsic_prior",
    "commanded_pose_prior",
    "leg_offset_prior",
    "pose_prior_sigmas",
]
