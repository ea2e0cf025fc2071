"""Helpers shared by the tests and the benches; the library never imports this module.

- one numerical Jacobian (:func:`numerical_jacobian`, central differences through GTSAM's
  retract and localCoordinates, ``gtsam.utils.numerical_derivative``), applied to a factor's keys by
  :func:`factor_jacobians` and compared with analytic blocks by :func:`assert_jacobians`;
- random rotations, poses and unit vectors, the rotations where conversions tend to break, and a
  ``gtsam.Values`` builder;
- a simulated calibration: a dataset folder and its hidden truth (:func:`simulated_dataset`), the
  true extrinsic (:func:`true_extrinsic`), an estimate's errors against it (:func:`extrinsic_error_scores`)
  and the simulator's noise model as calibration options (:data:`SIMULATOR_NOISE`);
- a hexapod graphcal does not ship (:func:`custom_hexapod`), written by hand as an outside user would:
  rectangular body, legs pointing sideways, an IMU mounted turned by 90 degrees, and a depth camera
  on the front;
- the 1,000-variable graph of Python CustomFactors that tests/test_batch_solver.py solves and
  bench/batch_solver.py times (:func:`custom_point_graph`).

It may import the simulator (tests/test_architecture.py allows it here and in the command layer).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import gtsam
import numpy as np
from gtsam.utils.numerical_derivative import numericalDerivative11

from graphcal.calibration.graph import CalibrationOptions
from graphcal.geometry import pose_from_xyz_quat_wxyz, pose_matrix, rot_y, rot_z
from graphcal.models.builtin import R_BODY_OPTICAL, BuiltinInfo, SensorCAD
from graphcal.simulation.session import CustomRobot, SimulationConfig, simulate
from graphcal.simulation.write import write_simulation
from graphcal.solvers.covariance import extrinsic_errors

H_STEP = 1e-6


# ----------------------------------------------------------------------------- numerical Jacobians
def numerical_jacobian(f: Callable, x, delta: float = H_STEP) -> np.ndarray:
    """Central-difference Jacobian of ``f`` at ``x``: column j is
    ``(local(f(x), f(retract(x, +delta e_j))) - local(f(x), f(retract(x, -delta e_j)))) / (2 delta)``
    (GTSAM's ``numericalDerivative11``).

    x: a 1-D numpy array (retract is ``x + xi``) or a GTSAM manifold value (``Pose3``, ``Rot3``,
        ``OrientedPlane3``, ...: retract is the value's own, for ``Pose3`` the right perturbation
        ``x Exp(xi)`` with ``xi = [omega (rad), v (m)]``).
    f: maps such an ``x`` to a numpy array of any shape (differences ``f(b) - f(a)``) or to a GTSAM
        manifold value (differences ``f(a).localCoordinates(f(b))``).
    delta: the step in ``x``'s tangent coordinates (its units: rad, m, ...).
    Returns: ``f(x).shape + (dim x,)`` for an array output, ``(dim f, dim x)`` for a manifold output.
    """
    y = f(x)
    if not isinstance(y, np.ndarray):
        return numericalDerivative11(f, x, delta)
    J = numericalDerivative11(lambda xi: np.ravel(np.asarray(f(xi), dtype=float)), x, delta)
    return J.reshape(*y.shape, J.shape[1])


def factor_jacobians(factor, values: gtsam.Values, dims, delta: float = H_STEP, whitened: bool = False) -> list[np.ndarray]:
    """Numerical Jacobians of a factor's error, one block per key in ``factor.keys()`` order, each
    through ``Values.retract`` of that key alone (GTSAM's retract: its tangent order and side).

    dims: the tangent dimension of each key's variable (6 for a Pose3, 3 for a Point3, ...).
    whitened: differentiate ``factor.whitenedError`` instead of ``factor.unwhitenedError``.
    """
    error = factor.whitenedError if whitened else factor.unwhitenedError

    def at_key(key):
        def f(xi):
            step = gtsam.VectorValues()
            step.insert(key, xi)
            return error(values.retract(step))
        return f

    return [numerical_jacobian(at_key(key), np.zeros(d), delta) for key, d in zip(factor.keys(), dims)]


def assert_jacobians(factor, values: gtsam.Values, dims, analytic, atol: float = 2e-7, what: str = "") -> None:
    """Compare analytic Jacobians of ``factor.unwhitenedError`` with :func:`factor_jacobians`, block
    by block, within ``atol`` times ``max(1, max |numerical block|)``."""
    numeric = factor_jacobians(factor, values, dims)
    assert len(numeric) == len(analytic)
    for i, (Hn, Ha) in enumerate(zip(numeric, analytic)):
        assert Ha.shape == Hn.shape, f"{what}: block {i} shape {Ha.shape} vs {Hn.shape}"
        scale = max(1.0, float(np.abs(Hn).max()))
        np.testing.assert_allclose(Ha, Hn, atol=atol * scale, err_msg=f"{what}: Jacobian block {i}")


# ----------------------------------------------------------------------------- random draws, gtsam values
def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation matrix drawn uniformly (a normalised Gaussian quaternion)."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return gtsam.Rot3.Quaternion(*q).matrix()


def random_pose(rng: np.random.Generator, t_scale: float = 1.0) -> np.ndarray:
    """A 4x4 pose: uniform rotation, translation N(0, t_scale^2) per axis (t_scale in m)."""
    T = np.eye(4)
    T[:3, :3] = random_rotation(rng)
    T[:3, 3] = rng.normal(scale=t_scale, size=3)
    return T


def random_unit(rng: np.random.Generator) -> np.ndarray:
    """A unit 3-vector drawn uniformly on the sphere."""
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


#: rotations where conversions tend to break: identity, half turns, just below a half turn about a
#: diagonal, and the body-from-optical rotation of a camera
SPECIAL_ROTATIONS = [
    np.eye(3),
    gtsam.Rot3.Rx(np.pi).matrix(),
    gtsam.Rot3.Rz(np.pi).matrix(),
    gtsam.Rot3.AxisAngle(np.array([1.0, 1.0, 1.0]) / np.sqrt(3.0), np.pi - 1e-9).matrix(),
    R_BODY_OPTICAL.copy(),
]


def gtsam_values(**items) -> gtsam.Values:
    """Values from keyword items: name -> (key, object); a 4x4 array is a Pose3, a 3x3 array a Rot3,
    ``("point3", xyz)`` a Point3, anything else is inserted as it is."""
    v = gtsam.Values()
    for key, obj in items.values():
        if isinstance(obj, tuple) and obj[0] == "point3":
            v.insertPoint3(key, np.asarray(obj[1], dtype=float))
        elif isinstance(obj, np.ndarray) and obj.shape == (4, 4):
            T = np.asarray(obj, dtype=float)
            v.insert(key, gtsam.Pose3(gtsam.Rot3(T[:3, :3]), T[:3, 3].copy()))
        elif isinstance(obj, np.ndarray) and obj.shape == (3, 3):
            v.insert(key, gtsam.Rot3(obj))
        else:
            v.insert(key, obj)
    return v


# ----------------------------------------------------------------------------- simulated calibration
#: the simulator's noise (SimulationConfig defaults): encoder 0.02 deg; feet exactly on the floor;
#: IMU: station-average noise 0.005 m/s^2 (0.03 deg) and a constant 0.02 m/s^2 bias per axis, which
#: the estimated mounting rotation absorbs only up to its change with tilt, b sin(20 deg) / g ~
#: 0.04 deg over Chai's poses -> sqrt(0.03^2 + 0.04^2) = 0.05 deg; servo tracking ~0.1 deg / a few
#: mm between the commanded and the real pose
SIMULATOR_NOISE = CalibrationOptions(
    estimate_noise=False, sigma_joint_rad=np.radians(0.02), sigma_contact_m=1e-6, sigma_ground_m=1e-6,
    sigma_imu_rad=np.radians(0.05), sigma_commanded_rad=np.radians(0.1), sigma_commanded_m=0.003)


def simulated_dataset(folder: Path, name: str, output: str = "planes", **config) -> tuple[Path, dict]:
    """Simulate a session (``SimulationConfig(**config)``, clouds thinned to every 8th point unless
    ``cloud_stride`` is given) and write it to ``folder / name``; returns (that path, the truth)."""
    res = simulate(SimulationConfig(**{"cloud_stride": 8, **config}))
    write_simulation(res, folder / name, output=output)
    return folder / name, res.truth


def true_extrinsic(truth: dict, sensor: str) -> np.ndarray:
    """T_body_sensor (4x4, m) of ``sensor`` from a simulation's truth (truth.yaml's layout)."""
    t = truth["sensors"][sensor]["T_body_sensor"]
    return pose_from_xyz_quat_wxyz(t["xyz"], t["quaternion_wxyz"])


def extrinsic_error_scores(est, T_true: np.ndarray) -> tuple[float, float, np.ndarray]:
    """Errors of an estimated extrinsic (``T_body_sensor``, ``sigma_rot_deg``, ``sigma_xyz_mm``)
    against ``T_true`` (T_body_sensor, m) (:func:`graphcal.solvers.covariance.extrinsic_errors`):
    (angle deg, translation mm, per-axis error / sigma in body axes [rx, ry, rz, x, y, z], the
    estimate's rotation error ``R_est = Exp(dphi) R_true`` and ``t_est - t_true``)."""
    e = extrinsic_errors(est.T_body_sensor, T_true)
    z = np.r_[e["dphi_deg"] / est.sigma_rot_deg, e["dt_mm"] / est.sigma_xyz_mm]
    return e["angle_deg"], e["distance_mm"], z


# ----------------------------------------------------------------------------- a hexapod graphcal does not ship
HEXAPOD_BODY_HEIGHT_M = 0.30
HEXAPOD_COXA_M, HEXAPOD_FEMUR_M, HEXAPOD_TIBIA_M = 0.08, 0.25, 0.35
HEXAPOD_LEGS = {  # name: (hip x m, hip y m, yaw of the leg's outward direction deg), body frame
    "front_left": (0.28, 0.14, 90.0),
    "middle_left": (0.0, 0.16, 90.0),
    "rear_left": (-0.28, 0.14, 90.0),
    "front_right": (0.28, -0.14, -90.0),
    "middle_right": (0.0, -0.16, -90.0),
    "rear_right": (-0.28, -0.14, -90.0),
}
HEXAPOD_T_BODY_CAMERA = pose_matrix(rot_y(np.radians(32.0)) @ R_BODY_OPTICAL, [0.36, 0.02, 0.12])
HEXAPOD_T_BODY_IMU = pose_matrix(rot_z(np.radians(90.0)), [0.05, 0.0, 0.02])


def _origin(xyz, rpy=(0.0, 0.0, 0.0)) -> str:
    x, r = [float(v) for v in xyz], [float(v) for v in rpy]
    return f'<origin xyz="{x[0]!r} {x[1]!r} {x[2]!r}" rpy="{r[0]!r} {r[1]!r} {r[2]!r}"/>'


def hexapod_urdf_xml() -> str:
    """The hexapod's URDF ("sidewinder"): yaw, lift and knee joints per leg, a toe frame per foot,
    and the IMU link."""
    parts = ['<?xml version="1.0"?>', '<robot name="sidewinder">', '<link name="base_link"/>']
    for leg, (x, y, yaw) in HEXAPOD_LEGS.items():
        a = np.radians(yaw)
        parts += [
            f'<link name="{leg}_hip"/><link name="{leg}_thigh"/><link name="{leg}_shin"/><link name="{leg}_toe"/>',
            f'<joint name="{leg}_yaw" type="revolute"><parent link="base_link"/><child link="{leg}_hip"/>'
            f'{_origin((x, y, 0.0), (0.0, 0.0, a))}<axis xyz="0 0 1"/>'
            '<limit lower="-1.0" upper="1.0" effort="50" velocity="5"/></joint>',
            f'<joint name="{leg}_lift" type="revolute"><parent link="{leg}_hip"/><child link="{leg}_thigh"/>'
            f'{_origin((HEXAPOD_COXA_M, 0.0, 0.0))}<axis xyz="0 -1 0"/>'
            '<limit lower="-1.6" upper="1.6" effort="50" velocity="5"/></joint>',
            f'<joint name="{leg}_knee" type="revolute"><parent link="{leg}_thigh"/><child link="{leg}_shin"/>'
            f'{_origin((HEXAPOD_FEMUR_M, 0.0, 0.0))}<axis xyz="0 -1 0"/>'
            '<limit lower="-2.6" upper="2.6" effort="50" velocity="5"/></joint>',
            f'<joint name="{leg}_toe_fixed" type="fixed"><parent link="{leg}_shin"/><child link="{leg}_toe"/>'
            f'{_origin((0.0, 0.0, -HEXAPOD_TIBIA_M))}</joint>',
        ]
    parts += [
        '<link name="imu_link"/>',
        f'<joint name="imu_mount" type="fixed"><parent link="base_link"/><child link="imu_link"/>'
        f'{_origin(HEXAPOD_T_BODY_IMU[:3, 3], (0.0, 0.0, np.pi / 2))}</joint>',
        "</robot>",
    ]
    return "\n".join(parts)


def hexapod_info() -> BuiltinInfo:
    """What the simulator needs to know about the hexapod: base frame, feet, standing height, nominal
    stance (feet in the body frame, m), the depth camera "front_cam" with its CAD pose, the IMU pose."""
    stance = {}
    for leg, (x, y, yaw) in HEXAPOD_LEGS.items():
        out = np.array([np.cos(np.radians(yaw)), np.sin(np.radians(yaw)), 0.0])
        stance[f"{leg}_toe"] = np.array([x, y, -HEXAPOD_BODY_HEIGHT_M]) + (HEXAPOD_COXA_M + HEXAPOD_FEMUR_M) * out
    return BuiltinInfo(
        name="sidewinder",
        base_frame="base_link",
        feet=tuple(f"{leg}_toe" for leg in HEXAPOD_LEGS),
        default_body_height_m=HEXAPOD_BODY_HEIGHT_M,
        nominal_stance=stance,
        sensors={"front_cam": SensorCAD("depth_camera", HEXAPOD_T_BODY_CAMERA, 0.03, np.radians(3.0))},
        T_body_imu=HEXAPOD_T_BODY_IMU,
    )


def custom_hexapod() -> CustomRobot:
    """The hexapod as the simulator's custom robot (``SimulationConfig(robot="sidewinder",
    custom_robot=custom_hexapod())``)."""
    return CustomRobot(hexapod_urdf_xml(), hexapod_info())


# ----------------------------------------------------------------------------- a graph of Python factors
def custom_point_graph(n: int = 1000, seed: int = 0) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """n Point3 variables (keys 0..n-1, m) on a random walk, all factors Python CustomFactors: a prior
    on the first (sigma 0.05 m), relative offsets between neighbours (0.05 m) and ranges between every
    second (0.02 m); the initial values are the truth plus N(0, 0.1 m) per axis."""
    rng = np.random.default_rng(seed)
    truth = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    graph, initial = gtsam.NonlinearFactorGraph(), gtsam.Values()
    nm3 = gtsam.noiseModel.Isotropic.Sigma(3, 0.05)
    nm1 = gtsam.noiseModel.Isotropic.Sigma(1, 0.02)
    eye3 = np.eye(3)

    def prior(m):
        def f(this, values, H):
            if H is not None:
                H[0] = eye3
            return values.atPoint3(this.keys()[0]) - m
        return f

    def offset(m):
        def f(this, values, H):
            k = this.keys()
            if H is not None:
                H[0] = -eye3
                H[1] = eye3
            return values.atPoint3(k[1]) - values.atPoint3(k[0]) - m
        return f

    def distance(m):
        def f(this, values, H):
            k = this.keys()
            d = values.atPoint3(k[1]) - values.atPoint3(k[0])
            r = np.linalg.norm(d)
            if H is not None:
                H[0] = -(d / r)[None, :]
                H[1] = (d / r)[None, :]
            return np.array([r - m])
        return f

    graph.add(gtsam.CustomFactor(nm3, [0], prior(truth[0])))
    for i in range(n - 1):
        m = truth[i + 1] - truth[i] + rng.normal(scale=0.05, size=3)
        graph.add(gtsam.CustomFactor(nm3, [i, i + 1], offset(m)))
    for i in range(n - 2):
        m = np.linalg.norm(truth[i + 2] - truth[i]) + rng.normal(scale=0.02)
        graph.add(gtsam.CustomFactor(nm1, [i, i + 2], distance(m)))
    for i in range(n):
        initial.insert(i, truth[i] + rng.normal(scale=0.1, size=3))
    return graph, initial


def max_local_difference(a: gtsam.Values, b: gtsam.Values) -> float:
    """The largest |component| of ``a.localCoordinates(b)`` (each variable's tangent units)."""
    return float(np.max(np.abs(a.localCoordinates(b).vector())))
