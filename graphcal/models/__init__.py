"""Robot models: URDF loading (Pinocchio), built-in robots, vectorised leg kinematics, perturbations."""

from graphcal.models.builtin import BUILTIN_MODELS, BuiltinInfo, SensorCAD, builtin_info, builtin_urdf
from graphcal.models.kinematics import fk_leg, foot_positions, ik_leg, leg_jacobian
from graphcal.models.perturb import LegPerturbation, apply_perturbation, hip_offset_delta, link_length_delta
from graphcal.models.robot import Leg, RobotModel, load_robot

__all__ = [
    "BUILTIN_MODELS",
    "BuiltinInfo",
    "SensorCAD",
    "builtin_info",
    "builtin_urdf",
    "fk_leg",
    "foot_positions",
    "ik_leg",
    "leg_jacobian",
    "LegPerturbation",
    "apply_perturbation",
    "hip_offset_delta",
    "link_length_delta",
    "Leg",
    "RobotModel",
    "load_robot",
]
