"""graphcal factors: analytic Jacobians vs central differences through GTSAM's retract, GTSAM's
linearisation vs the pure numpy functions, shape checking, and one small optimisation each."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from graphcal.factors import (
    FactorShapeError,
    checked_custom_factor,
    commanded_pose_prior,
    extrinsic_prior,
    foot_on_ground_error,
    foot_on_ground_factor,
    imu_attitude_error,
    imu_attitude_factor,
    imu_attitude_misaligned_error,
    imu_attitude_misaligned_factor,
    leg_offset_prior,
    plane_angle_distance_error,
    plane_cov3,
    plane_noise_model,
    plane_observation_error,
    plane_observation_factor,
    point_to_plane_error,
    point_to_plane_factor,
    stance_foot_builtin_factor,
    stance_foot_builtin_factors,
    stance_foot_error,
    stance_foot_error_map,
    stance_foot_factor,
    tangent_basis,
)
from graphcal.factors.keys import F, G, L, M, S, X
from graphcal.geometry import matrix_from_rpy, pose_adjoint, pose_from_xyz_rpy, se3_exp
from graphcal.models.builtin import R_BODY_OPTICAL
from graphcal.models.kinematics import foot_positions, ik_leg
from graphcal.models.legs import fk_with_params, leg_model
from graphcal.models.robot import load_robot
from graphcal.testing import SPECIAL_ROTATIONS, assert_jacobians, gtsam_values, random_pose, random_rotation, random_unit

SEED = 4242
N_RANDOM = 25
UP = np.array([0.0, 0.0, 1.0])


# ----------------------------------------------------------------------------- helpers
def _pose3(T) -> gtsam.Pose3:
    T = np.asarray(T, dtype=float)
    return gtsam.Pose3(gtsam.Rot3(T[:3, :3]), T[:3, 3].copy())


def _random_plane(rng) -> gtsam.OrientedPlane3:
    n = random_unit(rng)
    return gtsam.OrientedPlane3(n[0], n[1], n[2], rng.normal())


def _plane(n, d) -> gtsam.OrientedPlane3:
    n = np.asarray(n, dtype=float)
    n = n / np.linalg.norm(n)
    return gtsam.OrientedPlane3(n[0], n[1], n[2], float(d))


def assert_linearize_matches(factor, values, e, Hs):
    """factor.linearize(values) gives A = R [H...] and b = -R e with R the noise model's sqrt information."""
    np.testing.assert_allclose(factor.unwhitenedError(values), e, atol=1e-12)
    A, b = factor.linearize(values).jacobian()
    R = factor.noiseModel().R()
    np.testing.assert_allclose(A, R @ np.hstack(Hs), rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(b, -R @ e, rtol=1e-10, atol=1e-9)


TIE_NORMALS = [
    np.array([0.0, 0.0, 1.0]),
    np.array([0.0, 0.0, -1.0]),
    np.array([1.0, 0.0, 0.0]),
    np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0),
    np.array([1.0, 1.0, 1.0]) / np.sqrt(3.0),
    np.array([1.0, 1.0 + 1e-12, 1.0]) / np.linalg.norm([1.0, 1.0 + 1e-12, 1.0]),
]


# ----------------------------------------------------------------------------- shared pieces
def test_tangent_basis_is_gtsam_unit3_basis():
    rng = np.random.default_rng(SEED)
    for n in [*TIE_NORMALS, *(random_unit(rng) for _ in range(50))]:
        B = tangent_basis(n)
        np.testing.assert_allclose(B, gtsam.Unit3(n).basis(), atol=1e-15)
        np.testing.assert_allclose(B.T @ B, np.eye(2), atol=1e-15)
        np.testing.assert_allclose(B.T @ n, 0.0, atol=1e-15)
        np.testing.assert_allclose(np.cross(B[:, 0], B[:, 1]), n, atol=1e-15)


def test_pose_adjoint_is_gtsam_adjoint():
    rng = np.random.default_rng(SEED)
    for _ in range(10):
        T = random_pose(rng)
        np.testing.assert_allclose(pose_adjoint(T), _pose3(T).AdjointMap(), atol=1e-12)
        xi = rng.normal(size=6) * 1e-3
        np.testing.assert_allclose(T @ se3_exp(xi), se3_exp(pose_adjoint(T) @ xi) @ T, atol=1e-12)


# ----------------------------------------------------------------------------- checked_custom_factor
def _make(error_fn, dims=(6,), kinds=("Pose3",), m=3, keys=None):
    keys = [X(0)] if keys is None else keys
    return checked_custom_factor(gtsam.noiseModel.Unit.Create(m), keys, error_fn, list(dims), m, kinds=list(kinds), name="probe")


def _pose_values(extra=None):
    v = gtsam.Values()
    v.insert(X(0), gtsam.Pose3(gtsam.Rot3.Rx(0.3), np.array([1.0, 2.0, 3.0])))
    if extra is not None:
        extra(v)
    return v


BAD_OUTPUTS = {
    "wrong rows": lambda: (np.ones(3), [np.zeros((4, 6))]),
    "wrong cols": lambda: (np.ones(3), [np.zeros((3, 5))]),
    "1-D jacobian": lambda: (np.ones(3), [np.zeros(18)]),
    "float32 jacobian": lambda: (np.ones(3), [np.zeros((3, 6), dtype=np.float32)]),
    "list jacobian": lambda: (np.ones(3), [[[0.0] * 6] * 3]),
    "missing jacobians": lambda: (np.ones(3), None),
    "too few jacobians": lambda: (np.ones(3), []),
    "nan jacobian": lambda: (np.ones(3), [np.full((3, 6), np.nan)]),
    "wrong error length": lambda: (np.ones(4), [np.zeros((3, 6))]),
    "2-D error": lambda: (np.ones((3, 1)), [np.zeros((3, 6))]),
    "int error": lambda: (np.ones(3, dtype=int), [np.zeros((3, 6))]),
    "nan error": lambda: (np.array([np.nan, 0.0, 0.0]), [np.zeros((3, 6))]),
    "not a tuple": lambda: np.ones(3),
}


@pytest.mark.parametrize("case", sorted(BAD_OUTPUTS))
def test_checked_factor_raises_instead_of_crashing(case):
    bad = BAD_OUTPUTS[case]
    f = _make(lambda T, want: bad())
    v = _pose_values()
    with pytest.raises(FactorShapeError, match="probe") as info:
        f.linearize(v)
    assert isinstance(info.value, AssertionError) and isinstance(info.value, ValueError)
    # also from inside GTSAM's own optimizer (the error is non-zero so it linearises)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(f)
    with pytest.raises(FactorShapeError):
        gtsam.LevenbergMarquardtOptimizer(graph, v).optimize()


def test_checked_factor_error_names_the_key():
    f = _make(lambda T, want: (np.ones(3), [np.zeros((3, 5))]))
    with pytest.raises(FactorShapeError, match=r"x0 \(Pose3\).*\(3, 6\)"):
        f.linearize(_pose_values())


def test_checked_factor_vector_length_checked():
    def fn(T, theta, want):
        return np.zeros(3), [np.zeros((3, 6)), np.zeros((3, 4))] if want else None

    f = _make(fn, dims=(6, 4), kinds=("Pose3", "Vector"), keys=[X(0), L(0)])
    v = _pose_values(lambda v: v.insert(L(0), np.zeros(5)))
    with pytest.raises(FactorShapeError, match="l0 has length 5"):
        f.unwhitenedError(v)


def test_checked_factor_construction_errors():
    fn = lambda T, want: (np.zeros(3), None)  # noqa: E731
    with pytest.raises(FactorShapeError, match="noise model has dimension"):
        checked_custom_factor(gtsam.noiseModel.Unit.Create(2), [X(0)], fn, [6], 3, kinds=["Pose3"])
    with pytest.raises(FactorShapeError, match="has dimension 6"):
        _make(fn, dims=(3,))
    with pytest.raises(FactorShapeError, match="unknown kind"):
        _make(fn, kinds=("Pose2",))
    with pytest.raises(FactorShapeError, match="must match"):
        _make(fn, dims=(6, 3))
    with pytest.raises(FactorShapeError, match="twice"):
        _make(fn, dims=(6, 6), kinds=("Pose3", "Pose3"), keys=[X(0), X(0)])


def test_checked_factor_jacobians_only_when_asked():
    asked = []

    def fn(T, want):
        asked.append(want)
        return np.ones(3), ([np.eye(3, 6)] if want else None)

    f = _make(fn)
    v = _pose_values()
    f.error(v)
    assert asked == [False]
    f.linearize(v)
    assert asked[-1] is True


# ----------------------------------------------------------------------------- plane_observation
def _plane_factor_values(Xm, Sm, Gp, n_m, d_m, cov4=None):
    cov4 = np.diag([1e-4, 2e-4, 3e-4, 1e-4]) if cov4 is None else cov4
    if Gp is None:
        f = plane_observation_factor(X(0), S(0), n_m, d_m, cov4)
        v = gtsam_values(x=(X(0), Xm), s=(S(0), Sm))
        e, H = plane_observation_error(Xm, Sm, n_m, d_m, None)
        return f, v, e, H[:2], [6, 6]
    f = plane_observation_factor(X(0), S(0), n_m, d_m, cov4, g_key=G(0))
    v = gtsam_values(x=(X(0), Xm), s=(S(0), Sm), g=(G(0), Gp))
    e, H = plane_observation_error(Xm, Sm, n_m, d_m, Gp.planeCoefficients())
    return f, v, e, H, [6, 6, 3]


@pytest.mark.parametrize("with_g", [False, True])
def test_plane_observation_jacobians_random(with_g):
    rng = np.random.default_rng(SEED)
    for i in range(N_RANDOM):
        Xm, Sm = random_pose(rng), random_pose(rng, 0.3)
        n_m = random_unit(rng)
        Gp = _random_plane(rng) if with_g else None
        f, v, e, H, dims = _plane_factor_values(Xm, Sm, Gp, n_m, abs(rng.normal()))
        assert_jacobians(f, v, dims, H, what=f"random point {i}")


def test_plane_observation_jacobians_near_singular():
    cases = 0
    for R_x in SPECIAL_ROTATIONS:
        for R_s in SPECIAL_ROTATIONS[:3] + [R_BODY_OPTICAL.copy()]:
            Xm = np.eye(4)
            Xm[:3, :3] = R_x
            Xm[:3, 3] = [0.1, -0.2, 0.4]
            Sm = np.eye(4)
            Sm[:3, :3] = R_s
            Sm[:3, 3] = [0.2, 0.0, 0.1]
            n_s = (Xm[:3, :3] @ Sm[:3, :3]).T @ UP  # exact prediction
            tilt = se3_exp(np.r_[1e-9, -1e-9, 0, 0, 0, 0])[:3, :3]
            near = tilt @ n_s / np.linalg.norm(tilt @ n_s)
            for n_m in [n_s, near, -n_s, TIE_NORMALS[0], TIE_NORMALS[3], TIE_NORMALS[4], TIE_NORMALS[5]]:
                for Gp in [None, _plane(UP, 0.0), _plane(TIE_NORMALS[4], 0.3)]:
                    f, v, e, H, dims = _plane_factor_values(Xm, Sm, Gp, n_m, 0.4)
                    assert_jacobians(f, v, dims, H, what=f"R_x={R_x.tolist()} R_s={R_s.tolist()} n_m={n_m}")
                    cases += 1
    assert cases > 100


def test_plane_parallel_to_sensor_axis():
    """A forward camera (optical z horizontal) sees the floor edge-on: n_s is orthogonal to z_s."""
    Sm = np.eye(4)
    Sm[:3, :3] = R_BODY_OPTICAL
    e, H = plane_observation_error(np.eye(4), Sm, np.array([0.0, -1.0, 0.0]), 0.0)
    np.testing.assert_allclose(e, 0.0, atol=1e-15)
    assert np.linalg.matrix_rank(H[1]) == 3  # still two tilt directions and the height


def test_plane_observation_linearize_matches_pure():
    rng = np.random.default_rng(SEED + 2)
    for _ in range(5):
        A = rng.normal(size=(4, 4)) * 0.01
        cov4 = A @ A.T + 1e-6 * np.eye(4)
        Xm, Sm, Gp, n_m = random_pose(rng), random_pose(rng, 0.3), _random_plane(rng), random_unit(rng)
        for g in (None, Gp):
            f, v, e, H, _ = _plane_factor_values(Xm, Sm, g, n_m, 0.7, cov4)
            assert_linearize_matches(f, v, e, H)


def test_plane_noise_model():
    n_m = np.array([0.0, 0.6, 0.8])
    cov4 = np.diag([1e-4, 2e-4, 3e-4, 4e-4])
    B = tangent_basis(n_m)
    Gm = np.zeros((4, 3))
    Gm[:3, :2] = B
    Gm[3, 2] = 1.0
    np.testing.assert_allclose(plane_cov3(n_m, cov4), Gm.T @ cov4 @ Gm)
    cov3 = plane_cov3(n_m, cov4, 0.01, 0.002)
    np.testing.assert_allclose(cov3, Gm.T @ cov4 @ Gm + np.diag([1e-4, 1e-4, 4e-6]))
    nm = plane_noise_model(n_m, cov4, 0.01, 0.002)
    np.testing.assert_allclose(nm.covariance(), cov3, rtol=1e-10)
    robust = plane_noise_model(n_m, cov4, robust=gtsam.noiseModel.mEstimator.Huber.Create(1.345))
    assert isinstance(robust, gtsam.noiseModel.Robust)
    # a fit covariance that is zero needs floors
    with pytest.raises(ValueError, match="singular"):
        plane_cov3(n_m, np.zeros((4, 4)))
    assert np.all(np.linalg.eigvalsh(plane_cov3(n_m, np.zeros((4, 4)), 0.01, 0.001)) > 0)
    # the covariance along the normal itself (unit-norm direction) does not enter
    cov_along_n = np.zeros((4, 4))
    cov_along_n[:3, :3] = np.outer(n_m, n_m)
    np.testing.assert_allclose(plane_cov3(n_m, cov_along_n + cov4), plane_cov3(n_m, cov4), atol=1e-15)
    for bad in (np.eye(3), -np.eye(4), np.triu(np.ones((4, 4)))):
        with pytest.raises(ValueError):
            plane_cov3(n_m, bad)


def test_plane_observation_input_errors():
    cov4 = np.eye(4) * 1e-4
    with pytest.raises(ValueError, match="unit"):
        plane_observation_factor(X(0), S(0), [0.0, 0.0, 2.0], 0.3, cov4)
    with pytest.raises(ValueError, match="canonical"):
        plane_observation_factor(X(0), S(0), [0.0, 0.0, 1.0], -0.3, cov4)
    with pytest.raises(ValueError, match="exactly one"):
        plane_observation_factor(X(0), S(0), [0.0, 0.0, 1.0], 0.3)
    robust = plane_observation_factor(
        X(0), S(0), [0.0, 0.0, 1.0], 0.3, cov4, robust=gtsam.noiseModel.mEstimator.Huber.Create(1.345)
    )
    assert isinstance(robust.noiseModel(), gtsam.noiseModel.Robust)


def test_plane_angle_distance_error():
    T_ws = pose_from_xyz_rpy([0.0, 0.0, 0.5], [0.0, 0.0, 0.3])
    n_s = T_ws[:3, :3].T @ UP
    assert plane_angle_distance_error(T_ws, n_s, 0.5) == pytest.approx((0.0, 0.0), abs=1e-12)
    n_tilted = matrix_from_rpy([0.1, 0.0, 0.0]) @ n_s
    ang, dist = plane_angle_distance_error(T_ws, n_tilted, 0.48)
    assert ang == pytest.approx(0.1, abs=1e-12)
    assert dist == pytest.approx(0.02, abs=1e-12)
    assert plane_angle_distance_error(T_ws, 1e-9 * np.array([1.0, 0, 0]) + n_s, 0.5)[0] == pytest.approx(1e-9, rel=1e-3)


def _tilted_stations(rng, n=10, max_tilt=0.3):
    out = []
    for _ in range(n):
        rpy = [rng.uniform(-max_tilt, max_tilt), rng.uniform(-max_tilt, max_tilt), rng.uniform(-np.pi, np.pi)]
        out.append(pose_from_xyz_rpy([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.25, 0.5)], rpy))
    return out


def _fixed_pose_prior(key, T):
    return gtsam.PriorFactorPose3(key, _pose3(T), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6))


def _optimize(graph, values):
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-14)
    params.setMaxIterations(100)
    return gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()


def _pose_error(Ta, Tb) -> tuple[float, float]:
    xi = _pose3(Ta).localCoordinates(_pose3(Tb))
    return float(np.linalg.norm(xi[:3])), float(np.linalg.norm(xi[3:]))


# the depth camera of a robot looking down and forward, and the same extrinsic 3 deg / 3 cm off
S_TRUE = pose_from_xyz_rpy([0.25, 0.02, 0.10], [-np.pi / 2 - 0.6, 0.0, -np.pi / 2])
S_GUESS = S_TRUE @ se3_exp([0.03, -0.04, 0.05, 0.03, -0.02, 0.03])


def test_plane_observation_recovers_extrinsic():
    rng = np.random.default_rng(SEED + 3)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    cov4 = np.eye(4) * 1e-10  # noiseless measurements: the loose CAD prior must not bias the result
    for i, Xm in enumerate(_tilted_stations(rng)):
        T_ws = Xm @ S_TRUE
        n_s, d_s = T_ws[:3, :3].T @ UP, UP @ T_ws[:3, 3]
        assert d_s > 0
        graph.add(plane_observation_factor(X(i), S(0), n_s, d_s, cov4))
        graph.add(_fixed_pose_prior(X(i), Xm))
        values.insert(X(i), _pose3(Xm))
    graph.add(extrinsic_prior(S(0), S_GUESS, 0.1, 0.2))
    values.insert(S(0), _pose3(S_GUESS))
    result = _optimize(graph, values)
    rot, trans = _pose_error(result.atPose3(S(0)).matrix(), S_TRUE)
    assert rot < 1e-5 and trans < 1e-5


# ----------------------------------------------------------------------------- point_to_plane
def _ground_points_in_sensor(rng, Xm, Sm, n, plane=None):
    """Points on the world plane (ground by default) around the sensor, expressed in the sensor frame."""
    T_ws = Xm @ Sm
    pts_w = np.column_stack([rng.uniform(-1, 1, n) + T_ws[0, 3], rng.uniform(-1, 1, n) + T_ws[1, 3], np.zeros(n)])
    if plane is not None:
        n_w, d_w = plane
        pts_w[:, 2] = -(pts_w[:, :2] @ n_w[:2] + d_w) / n_w[2]
    return (pts_w - T_ws[:3, 3]) @ T_ws[:3, :3]


def _p2p_factor_values(Xm, Sm, Gp, P, sigma=0.01):
    if Gp is None:
        f = point_to_plane_factor(X(0), S(0), P, sigma)
        v = gtsam_values(x=(X(0), Xm), s=(S(0), Sm))
        e, H = point_to_plane_error(Xm, Sm, P, None)
        return f, v, e, H[:2], [6, 6]
    f = point_to_plane_factor(X(0), S(0), P, sigma, g_key=G(0))
    v = gtsam_values(x=(X(0), Xm), s=(S(0), Sm), g=(G(0), Gp))
    e, H = point_to_plane_error(Xm, Sm, P, Gp.planeCoefficients())
    return f, v, e, H, [6, 6, 3]


@pytest.mark.parametrize("with_g", [False, True])
def test_point_to_plane_jacobians_random(with_g):
    rng = np.random.default_rng(SEED + 4)
    for i in range(N_RANDOM):
        Xm, Sm = random_pose(rng), random_pose(rng, 0.3)
        P = rng.normal(scale=2.0, size=(40, 3))
        Gp = _random_plane(rng) if with_g else None
        f, v, e, H, dims = _p2p_factor_values(Xm, Sm, Gp, P)
        assert_jacobians(f, v, dims, H, what=f"random point {i}")


def test_point_to_plane_jacobians_near_singular():
    P = np.vstack([np.zeros(3), np.eye(3), -np.eye(3), [[0.0, 0.0, 1e-9]], [[1e3, 0.0, 0.0]]])
    rng = np.random.default_rng(SEED + 5)
    for R_x in SPECIAL_ROTATIONS:
        for R_s in SPECIAL_ROTATIONS:
            Xm, Sm = np.eye(4), np.eye(4)
            Xm[:3, :3], Sm[:3, :3] = R_x, R_s
            Xm[:3, 3] = [0.0, 0.0, 0.3]
            for Gp in [None, _plane(UP, 0.0), _plane(TIE_NORMALS[3], -0.2), _random_plane(rng)]:
                f, v, e, H, dims = _p2p_factor_values(Xm, Sm, Gp, P)
                assert_jacobians(f, v, dims, H, what=f"R_x={R_x.tolist()} R_s={R_s.tolist()}")


def test_point_to_plane_many_points_and_linearize():
    rng = np.random.default_rng(SEED + 6)
    Xm, Sm, Gp = random_pose(rng), random_pose(rng, 0.3), _random_plane(rng)
    P = rng.normal(size=(3000, 3))
    sig = rng.uniform(0.005, 0.02, size=3000)
    f, v, e, H, dims = _p2p_factor_values(Xm, Sm, Gp, P, sig)
    assert e.shape == (3000,) and H[0].shape == (3000, 6)
    assert_linearize_matches(f, v, e, H)
    assert_jacobians(f, v, dims, H, what="3000 points")
    f1, v1, e1, H1, _ = _p2p_factor_values(Xm, Sm, None, P[:1], 0.01)
    assert_linearize_matches(f1, v1, e1, H1)


def test_point_to_plane_input_errors():
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        point_to_plane_factor(X(0), S(0), np.zeros((5, 2)), 0.01)
    with pytest.raises(ValueError, match="shape"):
        point_to_plane_factor(X(0), S(0), np.zeros((5, 3)), np.ones(4) * 0.01)
    with pytest.raises(ValueError, match="> 0"):
        point_to_plane_factor(X(0), S(0), np.zeros((5, 3)), 0.0)
    with pytest.raises(ValueError, match="NaN"):
        point_to_plane_factor(X(0), S(0), np.full((5, 3), np.nan), 0.01)


def test_point_to_plane_recovers_extrinsic():
    rng = np.random.default_rng(SEED + 7)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    huber = gtsam.noiseModel.mEstimator.Huber.Create(1.345)
    for i, Xm in enumerate(_tilted_stations(rng)):
        P = _ground_points_in_sensor(rng, Xm, S_TRUE, 200)
        graph.add(point_to_plane_factor(X(i), S(0), P, 0.005, robust=huber))
        graph.add(_fixed_pose_prior(X(i), Xm))
        values.insert(X(i), _pose3(Xm))
    graph.add(extrinsic_prior(S(0), S_GUESS, 0.1, 0.2))
    values.insert(S(0), _pose3(S_GUESS))
    result = _optimize(graph, values)
    rot, trans = _pose_error(result.atPose3(S(0)).matrix(), S_TRUE)
    assert rot < 1e-5 and trans < 1e-5


# ----------------------------------------------------------------------------- stance_foot
@pytest.fixture(scope="module")
def robots():
    return {"a1": load_robot(model="a1"), "octopus": load_robot(model="octopus")}


def _stance_factor_values(robot, foot, Xm, p_foot, q, theta=None, with_l=True):
    leg = robot.leg(foot)
    param = leg_model(robot, foot, origins="none")
    if with_l:
        theta = param.zeros() if theta is None else theta
        f = stance_foot_factor(X(0), F(0), q, leg, 0.003, param=param, l_key=L(0))
        v = gtsam_values(x=(X(0), Xm), f=(F(0), ("point3", p_foot)), l=(L(0), np.asarray(theta, dtype=float)))
        e, H = stance_foot_error(Xm, p_foot, q, leg, param, theta)
        return f, v, e, H, [6, 3, param.dim]
    f = stance_foot_factor(X(0), F(0), q, leg, 0.003)
    v = gtsam_values(x=(X(0), Xm), f=(F(0), ("point3", p_foot)))
    e, H = stance_foot_error(Xm, p_foot, q, leg)
    return f, v, e, H, [6, 3]


def _random_leg_q(leg, rng):
    lo = np.where(np.isfinite(leg.lower), leg.lower, -np.pi)
    hi = np.where(np.isfinite(leg.upper), leg.upper, np.pi)
    return rng.uniform(lo, hi)


@pytest.mark.parametrize("name", ["a1", "octopus"])
@pytest.mark.parametrize("with_l", [False, True])
def test_stance_foot_jacobians_random(robots, name, with_l):
    r = robots[name]
    rng = np.random.default_rng(SEED + 8)
    for i in range(N_RANDOM):
        foot = r.feet[i % len(r.feet)]
        q = _random_leg_q(r.leg(foot), rng)
        theta = rng.normal(scale=0.02, size=6) if with_l else None
        f, v, e, H, dims = _stance_factor_values(r, foot, random_pose(rng), rng.normal(size=3), q, theta, with_l)
        assert_jacobians(f, v, dims, H, what=f"{name} {foot} random point {i}")


def test_stance_foot_jacobians_near_singular(robots):
    a1, octo = robots["a1"], robots["octopus"]
    # a1 with a straight leg: the foot is right under the thigh joint
    q_straight = np.zeros(3)
    # octopus: the foot right under the coxa joint (found by IK)
    oleg = octo.leg("lf_foot")
    target = oleg.T_parent_joint[0][:3, 3] + np.array([0.0, 0.0, -0.5])
    q_under, ok = ik_leg(oleg, target, np.array([0.0, 1.0, -2.0]))
    assert ok
    for robot, foot, q in [(a1, "fl_foot", q_straight), (a1, "rr_foot", q_straight), (octo, "lf_foot", q_under)]:
        p_b = foot_positions(robot.leg(foot), q)
        for R_x in SPECIAL_ROTATIONS:
            Xm = np.eye(4)
            Xm[:3, :3] = R_x
            Xm[:3, 3] = [0.3, -0.1, 0.4]
            for p_foot in [Xm[:3, :3] @ p_b + Xm[:3, 3], Xm[:3, 3].copy(), np.zeros(3)]:  # exact, p_b = 0, origin
                for with_l in (False, True):
                    f, v, e, H, dims = _stance_factor_values(robot, foot, Xm, p_foot, q, None, with_l)
                    assert_jacobians(f, v, dims, H, what=f"{foot} q={q} R_x={R_x.tolist()}")
    # exact: zero error
    e, _ = stance_foot_error(np.eye(4), foot_positions(a1.leg("fl_foot"), q_straight), q_straight, a1.leg("fl_foot"))
    np.testing.assert_allclose(e, 0.0, atol=1e-15)


def test_stance_foot_x_jacobian_formula():
    rng = np.random.default_rng(SEED + 9)
    Xm, p = random_pose(rng), rng.normal(size=3)
    a1 = load_robot(model="a1")
    _, H = stance_foot_error(Xm, p, np.zeros(3), a1.leg("fl_foot"))
    p_b = Xm[:3, :3].T @ (p - Xm[:3, 3])
    np.testing.assert_allclose(H[0][:, 3:], np.eye(3))
    np.testing.assert_allclose(H[0][:, :3], -np.array([[0, -p_b[2], p_b[1]], [p_b[2], 0, -p_b[0]], [-p_b[1], p_b[0], 0]]))
    np.testing.assert_allclose(H[1], -Xm[:3, :3].T)


def test_stance_foot_linearize_matches_pure(robots):
    rng = np.random.default_rng(SEED + 10)
    r = robots["octopus"]
    for with_l in (False, True):
        q = _random_leg_q(r.leg("rm_foot"), rng)
        theta = rng.normal(scale=0.02, size=6) if with_l else None
        f, v, e, H, _ = _stance_factor_values(r, "rm_foot", random_pose(rng), rng.normal(size=3), q, theta, with_l)
        assert_linearize_matches(f, v, e, H)


def test_stance_foot_with_its_kinematics_given_linearises_as_computed_and_elsewhere_computes(robots):
    """kin_at (graph.py's batch per leg) is used at exactly its theta0 and gives the linearisation the
    factor computes itself; at another theta the factor computes as without it."""
    from graphcal.models.legs import fk_and_param_jacobian

    r = robots["octopus"]
    foot = r.feet[0]
    leg = r.leg(foot)
    param = leg_model(r, foot, origins="none")
    rng = np.random.default_rng(SEED + 23)
    q = _random_leg_q(leg, rng)
    Xm = pose_from_xyz_rpy([0.1, -0.2, 0.3], [0.05, -0.1, 0.3])
    p_foot = Xm[:3, :3] @ fk_and_param_jacobian(leg, param, q, param.zeros())[0] + Xm[:3, 3] + [0.004, -0.002, 0.001]
    theta0 = param.zeros()
    p0, J0 = fk_and_param_jacobian(leg, param, q, theta0)
    plain = stance_foot_factor(X(0), F(0), q, leg, 0.003, param=param, l_key=L(0))
    given = stance_foot_factor(X(0), F(0), q, leg, 0.003, param=param, l_key=L(0), kin_at=(theta0, p0, J0))
    wrong = stance_foot_factor(X(0), F(0), q, leg, 0.003, param=param, l_key=L(0), kin_at=(theta0, p0 + 1.0, J0))
    for theta, same in ((theta0, True), (rng.normal(scale=0.02, size=param.dim), False)):
        v = gtsam_values(x=(X(0), Xm), f=(F(0), ("point3", p_foot)), l=(L(0), theta))
        a, b = plain.linearize(v), given.linearize(v)
        np.testing.assert_allclose(b.jacobian()[0], a.jacobian()[0], atol=1e-12)
        np.testing.assert_allclose(b.jacobian()[1], a.jacobian()[1], atol=1e-12)
        # the cached kinematics are read only at theta0: a wrong cache shows there and nowhere else
        assert (abs(wrong.error(v) - plain.error(v)) > 1.0) == same


def test_stance_foot_input_errors(robots):
    leg = robots["a1"].leg("fl_foot")
    param = leg_model(robots["a1"], "fl_foot", origins="none")
    with pytest.raises(ValueError, match="joint values"):
        stance_foot_factor(X(0), F(0), np.zeros(2), leg)
    with pytest.raises(ValueError, match="param"):
        stance_foot_factor(X(0), F(0), np.zeros(3), leg, l_key=L(0))
    with pytest.raises(ValueError, match="sigma"):
        stance_foot_factor(X(0), F(0), np.zeros(3), leg, 0.0)
    # an L variable of the wrong length is caught at evaluation
    f = stance_foot_factor(X(0), F(0), np.zeros(3), leg, param=param, l_key=L(0))
    v = gtsam_values(x=(X(0), np.eye(4)), f=(F(0), ("point3", np.zeros(3))), l=(L(0), np.zeros(4)))
    with pytest.raises(FactorShapeError, match="length 4"):
        f.linearize(v)


def test_stance_foot_recovers_leg_parameters(robots):
    r = robots["a1"]
    foot = "fl_foot"
    leg = r.leg(foot)
    param = leg_model(r, foot, origins="none")
    rng = np.random.default_rng(SEED + 11)
    theta_true = np.r_[rng.normal(scale=0.03, size=3), rng.normal(scale=0.005, size=3)]
    F_true = np.array([0.4, 0.2, 0.0])
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for i in range(30):
        q = _random_leg_q(leg, rng)
        p_b = fk_with_params(leg, param, q, theta_true)
        R_x = matrix_from_rpy([rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), rng.uniform(-np.pi, np.pi)])
        Xm = np.eye(4)
        Xm[:3, :3] = R_x
        Xm[:3, 3] = F_true - R_x @ p_b
        graph.add(stance_foot_factor(X(i), F(0), q, leg, param=param, l_key=L(0)))
        graph.add(_fixed_pose_prior(X(i), Xm))
        values.insert(X(i), _pose3(Xm))
    # a weak prior (it only regularises): noiseless data must give the truth
    graph.add(leg_offset_prior(L(0), param.dim, param.prior_sigmas(10.0, 1.0)))
    graph.add(foot_on_ground_factor(F(0)))
    values.insert(L(0), param.zeros())
    values.insertPoint3(F(0), F_true + np.array([0.02, -0.03, 0.01]))
    result = _optimize(graph, values)
    np.testing.assert_allclose(result.atVector(L(0)), theta_true, atol=1e-6)
    np.testing.assert_allclose(result.atPoint3(F(0)), F_true, atol=1e-6)


# ----------------------------------------------------------------------------- stance_foot_builtin
def _builtin_case(robot, foot, q, Xm, cov):
    """The built-in factor and the Python factor of one foot at a body pose, with values that put
    the foot exactly where the leg says (zero error)."""
    leg = robot.leg(foot)
    p_b = foot_positions(leg, q)
    p_w = Xm[:3, :3] @ p_b + Xm[:3, 3]
    fb = stance_foot_builtin_factor(X(0), F(0), p_b, cov)
    fp = stance_foot_factor(X(0), F(0), q, leg, cov_m2=cov)
    v = gtsam_values(x=(X(0), Xm), f=(F(0), ("point3", p_w)))
    return fb, fp, v, p_b


def _random_cov(rng, scale=0.003):
    A = rng.normal(scale=scale, size=(3, 3))
    return A @ A.T + (0.3 * scale) ** 2 * np.eye(3)


def test_stance_foot_builtin_error_map_is_the_factor_derivative(robots):
    """At zero error GTSAM's bearing-range Jacobians are exactly J times the Cartesian factor's:
    d e_br / d(X, F) = -J [H_X, H_F] (J = stance_foot_error_map), checked numerically through GTSAM's
    retract, at random legs and poses and at the special rotations."""
    rng = np.random.default_rng(SEED + 31)
    cases = []
    for name in ("a1", "octopus"):
        r = robots[name]
        for i in range(N_RANDOM):
            foot = r.feet[i % len(r.feet)]
            cases.append((r, foot, _random_leg_q(r.leg(foot), rng), random_pose(rng)))
    for R_x in SPECIAL_ROTATIONS:
        Xm = np.eye(4)
        Xm[:3, :3] = R_x
        Xm[:3, 3] = [0.3, -0.1, 0.4]
        cases.append((robots["octopus"], "lf_foot", np.array([0.0, 1.0, -2.0]), Xm))
    for r, foot, q, Xm in cases:
        fb, _, v, p_b = _builtin_case(r, foot, q, Xm, _random_cov(rng))
        np.testing.assert_allclose(fb.unwhitenedError(v), 0.0, atol=1e-12)
        J = stance_foot_error_map(p_b)
        _, H = stance_foot_error(Xm, Xm[:3, :3] @ p_b + Xm[:3, 3], q, r.leg(foot))
        assert_jacobians(fb, v, [6, 3], [-J @ H[0], -J @ H[1]], what=f"{foot} q={q}")


def test_stance_foot_builtin_is_the_python_factor_to_first_order(robots):
    """Same noise after the map (the factor's covariance is J Sigma J^T), the same whitened normal
    equations at zero error, and chi-square values that differ only at order |e| / r."""
    rng = np.random.default_rng(SEED + 32)
    r = robots["octopus"]
    for i in range(N_RANDOM):
        foot = r.feet[i % len(r.feet)]
        q = _random_leg_q(r.leg(foot), rng)
        Xm, cov = random_pose(rng), _random_cov(rng)
        fb, fp, v, p_b = _builtin_case(r, foot, q, Xm, cov)
        J = stance_foot_error_map(p_b)
        np.testing.assert_allclose(fb.noiseModel().covariance(), J @ cov @ J.T, rtol=1e-10, atol=1e-18)
        (Ab, bb), (Ap, bp) = fb.linearize(v).jacobian(), fp.linearize(v).jacobian()
        np.testing.assert_allclose(Ab.T @ Ab, Ap.T @ Ap, rtol=1e-8, atol=1e-8 * np.abs(Ap.T @ Ap).max())
        np.testing.assert_allclose(bb, 0.0, atol=1e-9)
        np.testing.assert_allclose(bp, 0.0, atol=1e-9)
        # move the foot by ~3 mm: chi-square agrees to a few |e| / r (r >= 0.1 m here)
        dv = gtsam.VectorValues()
        dv.insert(F(0), rng.normal(scale=0.003, size=3))
        moved = v.retract(dv)
        chi_b, chi_p = 2 * fb.error(moved), 2 * fp.error(moved)
        e_over_r = np.linalg.norm(dv.at(F(0))) / np.linalg.norm(p_b)
        assert chi_p > 0.01
        assert abs(chi_b - chi_p) <= 4 * e_over_r * chi_p, (chi_b, chi_p, e_over_r)


def test_stance_foot_builtin_batch_maps_each_component(robots):
    """The batch builder: one factor per foot, each noise component mapped by its own foot's J; the
    components sum to the factor's covariance (what the variance-component estimation needs)."""
    rng = np.random.default_rng(SEED + 33)
    r = robots["octopus"]
    qs = [_random_leg_q(r.leg(f), rng) for f in r.feet]
    P = np.array([foot_positions(r.leg(f), q) for f, q in zip(r.feet, qs)])
    C1 = np.stack([_random_cov(rng) for _ in r.feet])
    C2 = np.broadcast_to(1e-6 * np.eye(3), C1.shape)
    factors, mapped = stance_foot_builtin_factors(X(0), [F(j) for j in range(len(P))], P, {"joint": C1, "contact": C2})
    assert len(factors) == len(P) and set(mapped) == {"joint", "contact"}
    for j, f in enumerate(factors):
        J = stance_foot_error_map(P[j])
        np.testing.assert_allclose(mapped["joint"][j], J @ C1[j] @ J.T, rtol=1e-10, atol=1e-12 * np.abs(mapped["joint"][j]).max())
        np.testing.assert_allclose(mapped["contact"][j], J @ C2[j] @ J.T, rtol=1e-10, atol=1e-12 * np.abs(mapped["contact"][j]).max())
        np.testing.assert_allclose(f.noiseModel().covariance(), mapped["joint"][j] + mapped["contact"][j], rtol=1e-9)
        assert [int(k) for k in f.keys()] == [X(0), F(j)]


def test_stance_foot_builtin_input_errors():
    cov = 1e-5 * np.eye(3)
    with pytest.raises(ValueError, match="from the body origin"):
        stance_foot_builtin_factor(X(0), F(0), [0.005, 0.0, 0.0], cov)
    with pytest.raises(ValueError, match="finite 3-vectors"):
        stance_foot_builtin_factor(X(0), F(0), [np.nan, 0.0, 0.2], cov)
    with pytest.raises(ValueError, match="positive definite"):
        stance_foot_builtin_factor(X(0), F(0), [0.1, 0.0, -0.2], -cov)
    with pytest.raises(ValueError, match="3x3"):
        stance_foot_builtin_factor(X(0), F(0), [0.1, 0.0, -0.2], np.eye(2))
    with pytest.raises(ValueError, match="2 foot keys for 1 feet"):
        stance_foot_builtin_factors(X(0), [F(0), F(1)], [[0.1, 0.0, -0.2]], {"c": cov[None]})


# ----------------------------------------------------------------------------- imu_attitude
def test_accelerometer_at_rest_points_up_and_builtin_factor_agrees():
    """f = R_wb^T (0, 0, +g): the specific force at rest points UP; with it the built-in factor is zeroed."""
    R_wb = matrix_from_rpy([0.3, -0.2, 0.5])
    f_body = R_wb.T @ np.array([0.0, 0.0, 9.81])
    assert (R_wb @ f_body)[2] > 0
    Xm = np.eye(4)
    Xm[:3, :3] = R_wb
    fac = imu_attitude_factor(X(0), f_body)
    assert isinstance(fac, gtsam.AttitudeFactorPose3)
    v = gtsam_values(x=(X(0), Xm))
    np.testing.assert_allclose(fac.unwhitenedError(v), 0.0, atol=1e-15)
    # a tilted body: the built-in error is the tilt (first order), and its sign follows the tilt
    axis = np.cross(f_body, [1.0, 0.0, 0.0])
    axis /= np.linalg.norm(axis)
    for tilt in (0.01, -0.01):
        Xt = Xm @ se3_exp(np.r_[tilt * axis, 0.0, 0.0, 0.0])
        e_t = fac.unwhitenedError(gtsam_values(x=(X(0), Xt)))
        assert np.linalg.norm(e_t) == pytest.approx(0.01, rel=1e-3)
        e_pure, _ = imu_attitude_misaligned_error(Xt, np.eye(3), f_body)
        assert np.linalg.norm(e_pure) == pytest.approx(0.01, rel=1e-3)
    # a 2-D direction error (GTSAM's and ours) also vanishes for the opposite direction, so a
    # sign error in f would not show as a residual but mirror the estimated tilt: the sign is
    # pinned here and by the tilt recovery below.
    np.testing.assert_allclose(imu_attitude_factor(X(0), -f_body).unwhitenedError(v), 0.0, atol=1e-12)
    Xt = Xm @ se3_exp(np.r_[0.01 * axis, 0.0, 0.0, 0.0])
    e_right = fac.unwhitenedError(gtsam_values(x=(X(0), Xt)))
    e_wrong = imu_attitude_factor(X(0), -f_body).unwhitenedError(gtsam_values(x=(X(0), Xt)))
    np.testing.assert_allclose(e_wrong, -e_right, atol=1e-12)


def test_imu_attitude_builtin_matches_pure_and_numerical():
    rng = np.random.default_rng(SEED + 12)
    cases = [(random_pose(rng), random_unit(rng) * 9.81, None) for _ in range(N_RANDOM)]
    cases += [(random_pose(rng), random_unit(rng) * 9.81, random_rotation(rng)) for _ in range(N_RANDOM)]
    for R in SPECIAL_ROTATIONS:
        for fvec in [UP, -UP, np.array([1.0, 1.0, 1.0]), np.array([1.0, 0.0, 0.0])]:
            Xm = np.eye(4)
            Xm[:3, :3] = R
            cases.append((Xm, fvec * 9.81, None))
    for Xm, fvec, R_bi in cases:
        fac = imu_attitude_factor(X(0), fvec, R_body_imu=R_bi)
        v = gtsam_values(x=(X(0), Xm))
        e, H = imu_attitude_error(Xm, fvec, R_bi)
        np.testing.assert_allclose(fac.unwhitenedError(v), e, atol=1e-12)
        assert_jacobians(fac, v, [6], H, what="built-in attitude")
        assert_linearize_matches(fac, v, e, H)


def _misaligned_factor_values(Xm, R_bi, fvec):
    f = imu_attitude_misaligned_factor(X(0), M(0), fvec)
    v = gtsam_values(x=(X(0), Xm), m=(M(0), R_bi))
    e, H = imu_attitude_misaligned_error(Xm, R_bi, fvec)
    return f, v, e, H


def test_imu_attitude_misaligned_jacobians_random():
    rng = np.random.default_rng(SEED + 13)
    for i in range(N_RANDOM):
        f, v, e, H = _misaligned_factor_values(random_pose(rng), random_rotation(rng), random_unit(rng) * 9.8)
        assert_jacobians(f, v, [6, 3], H, what=f"random point {i}")
        assert np.all(H[0][:, 3:] == 0.0)


def test_imu_attitude_misaligned_jacobians_near_singular():
    for R_x in SPECIAL_ROTATIONS:
        for R_bi in SPECIAL_ROTATIONS:
            Xm = np.eye(4)
            Xm[:3, :3] = R_x
            u = (R_x @ R_bi).T @ UP
            for fvec in [u, -u, u + 1e-9 * np.array([1.0, 0, 0]), *TIE_NORMALS]:
                f, v, e, H = _misaligned_factor_values(Xm, R_bi, fvec * 9.81)
                assert_jacobians(f, v, [6, 3], H, what=f"R_x={R_x.tolist()} R_bi={R_bi.tolist()} f={fvec}")


def test_imu_attitude_misaligned_linearize_matches_pure():
    rng = np.random.default_rng(SEED + 14)
    f, v, e, H = _misaligned_factor_values(random_pose(rng), random_rotation(rng), random_unit(rng))
    assert_linearize_matches(f, v, e, H)
    # default sigma: 0.5 deg
    np.testing.assert_allclose(f.noiseModel().sigmas(), np.deg2rad(0.5))


def test_imu_attitude_input_errors():
    with pytest.raises(ValueError, match="zero"):
        imu_attitude_factor(X(0), np.zeros(3))
    with pytest.raises(ValueError, match="rotation"):
        imu_attitude_factor(X(0), UP, R_body_imu=2 * np.eye(3))
    with pytest.raises(ValueError, match="sigma"):
        imu_attitude_misaligned_factor(X(0), M(0), UP, -1.0)


def test_imu_attitude_recovers_tilt_and_mounting():
    rng = np.random.default_rng(SEED + 15)
    # (a) built-in factor: the body's tilt from one accelerometer reading; the prior holds the rest
    R_true = matrix_from_rpy([0.2, -0.15, 1.0])
    X_true = pose_from_xyz_rpy([0.0, 0.0, 0.4], [0.2, -0.15, 1.0])
    X_guess = pose_from_xyz_rpy([0.0, 0.0, 0.4], [0.0, 0.0, 1.0])
    graph = gtsam.NonlinearFactorGraph()
    graph.add(imu_attitude_factor(X(0), R_true.T @ np.array([0.0, 0.0, 9.81])))
    graph.add(commanded_pose_prior(X(0), X_guess, sigma_rad=10.0, sigma_m=1e-3))
    result = _optimize(graph, gtsam_values(x=(X(0), X_guess)))
    R_opt = result.atPose3(X(0)).rotation().matrix()
    np.testing.assert_allclose(R_opt.T @ UP, X_true[:3, :3].T @ UP, atol=1e-5)
    # (b) misaligned factor: the mounting rotation from 10 tilted, known body poses
    R_bi_true = matrix_from_rpy([0.03, -0.02, 0.05])
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for i, Xm in enumerate(_tilted_stations(rng)):
        f_imu = (Xm[:3, :3] @ R_bi_true).T @ np.array([0.0, 0.0, 9.81])
        graph.add(imu_attitude_misaligned_factor(X(i), M(0), f_imu))
        graph.add(_fixed_pose_prior(X(i), Xm))
        values.insert(X(i), _pose3(Xm))
    values.insert(M(0), gtsam.Rot3())
    result = _optimize(graph, values)
    R_bi = result.atRot3(M(0)).matrix()
    assert gtsam.Rot3(R_bi).localCoordinates(gtsam.Rot3(R_bi_true)) == pytest.approx(np.zeros(3), abs=1e-8)


# ----------------------------------------------------------------------------- foot_on_ground
def _ground_factor_values(p, Gp):
    if Gp is None:
        f = foot_on_ground_factor(F(0))
        v = gtsam_values(f=(F(0), ("point3", p)))
        e, H = foot_on_ground_error(p)
        return f, v, e, H[:1], [3]
    f = foot_on_ground_factor(F(0), g_key=G(0))
    v = gtsam_values(f=(F(0), ("point3", p)), g=(G(0), Gp))
    e, H = foot_on_ground_error(p, Gp.planeCoefficients())
    return f, v, e, H, [3, 3]


def test_foot_on_ground_jacobians_random_and_singular():
    rng = np.random.default_rng(SEED + 16)
    cases = [(rng.normal(size=3), g) for _ in range(N_RANDOM) for g in (None, _random_plane(rng))]
    cases += [(p, _plane(n, d)) for n in TIE_NORMALS for d in (0.0, 0.3) for p in (np.zeros(3), np.array([1.0, 1.0, 1.0]))]
    cases += [(np.zeros(3), None), (np.array([0.0, 0.0, -0.01]), None)]
    for p, Gp in cases:
        f, v, e, H, dims = _ground_factor_values(p, Gp)
        assert_jacobians(f, v, dims, H, what=f"p={p}")
        assert_linearize_matches(f, v, e, H)
    assert foot_on_ground_error(np.array([0.3, 0.2, -0.004]))[0][0] == pytest.approx(-0.004)


def test_foot_on_ground_defaults_and_errors():
    f = foot_on_ground_factor(F(0))
    np.testing.assert_allclose(f.noiseModel().sigmas(), [0.003])
    with pytest.raises(ValueError):
        foot_on_ground_factor(F(0), 0.0)
    with pytest.raises(ValueError, match="plane_world"):
        foot_on_ground_factor(F(0), g_key=G(0), plane_world=[0, 0, 1, 0])
    fixed = foot_on_ground_factor(F(0), plane_world=[0.0, 0.0, 2.0, -0.2])  # z = 0.1, normalised
    assert fixed.unwhitenedError(gtsam_values(f=(F(0), ("point3", np.array([5.0, 1.0, 0.1])))))[0] == pytest.approx(0.0)


def test_foot_on_ground_recovers_ground_plane():
    n_true = np.array([0.05, -0.03, 1.0])
    n_true /= np.linalg.norm(n_true)
    d_true = 0.02
    rng = np.random.default_rng(SEED + 17)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for j in range(6):
        xy = rng.uniform(-0.5, 0.5, size=2)
        p = np.array([xy[0], xy[1], -(n_true[:2] @ xy + d_true) / n_true[2]])
        graph.add(foot_on_ground_factor(F(j), g_key=G(0)))
        graph.add(gtsam.PriorFactorPoint3(F(j), p, gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
        values.insertPoint3(F(j), p)
    values.insert(G(0), gtsam.OrientedPlane3(0.0, 0.0, 1.0, 0.0))
    result = _optimize(graph, values)
    c = result.atOrientedPlane3(G(0)).planeCoefficients()
    np.testing.assert_allclose(c, np.r_[n_true, d_true], atol=1e-7)


# ----------------------------------------------------------------------------- priors
def test_pose_priors_sigma_order_and_defaults():
    T = pose_from_xyz_rpy([0.1, 0.2, 0.3], [0.1, 0.0, -0.2])
    p = extrinsic_prior(S(0), T, sigma_m=[0.01, 0.02, 0.03], sigma_rad=0.05)
    assert isinstance(p, gtsam.PriorFactorPose3)
    np.testing.assert_allclose(p.noiseModel().sigmas(), [0.05, 0.05, 0.05, 0.01, 0.02, 0.03])
    c = commanded_pose_prior(X(0), T)
    np.testing.assert_allclose(c.noiseModel().sigmas(), [np.deg2rad(1.0)] * 3 + [0.01] * 3)
    # error order: a pure translation of the variable shows in the last three components
    v = gtsam_values(x=(X(0), T @ se3_exp([0, 0, 0, 0.001, 0, 0])))
    np.testing.assert_allclose(c.unwhitenedError(v), [0, 0, 0, 0.001, 0, 0], atol=1e-12)
    v = gtsam_values(s=(S(0), T @ se3_exp([0.002, 0, 0, 0, 0, 0])))
    np.testing.assert_allclose(p.unwhitenedError(v), [0.002, 0, 0, 0, 0, 0], atol=1e-12)
    with pytest.raises(ValueError):
        extrinsic_prior(S(0), T, 0.0, 0.1)
    with pytest.raises(ValueError):
        extrinsic_prior(S(0), np.eye(3), 0.1, 0.1)


def test_leg_offset_prior():
    p = leg_offset_prior(L(0), 6, [0.1, 0.1, 0.1, 0.01, 0.01, 0.01])
    assert isinstance(p, gtsam.PriorFactorVector)
    v = gtsam_values(l=(L(0), np.array([0.1, 0, 0, 0, 0, 0.01])))
    assert p.error(v) == pytest.approx(0.5 * (1.0 + 1.0))
    np.testing.assert_allclose(leg_offset_prior(L(1), 3, 0.2).noiseModel().sigmas(), [0.2] * 3)
    with pytest.raises(ValueError):
        leg_offset_prior(L(0), 3, [0.1, 0.1])
