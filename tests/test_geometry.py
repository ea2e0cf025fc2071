"""The frame rules, checked against the libraries they must agree with (GTSAM, Pinocchio)."""

from __future__ import annotations

import gtsam
import numpy as np
import pinocchio as pin
import pytest

from graphcal import geometry as g


@pytest.fixture
def rng():
    return np.random.default_rng(42)


def random_pose(rng):
    return g.se3_exp(np.r_[rng.normal(0, 1.0, 3), rng.normal(0, 1.0, 3)])


def test_rpy_is_ros_convention_and_round_trips(rng):
    for _ in range(50):
        rpy = rng.uniform([-np.pi, -1.5, -np.pi], [np.pi, 1.5, np.pi])
        R = g.matrix_from_rpy(rpy)
        assert np.allclose(R, g.rot_z(rpy[2]) @ g.rot_y(rpy[1]) @ g.rot_x(rpy[0]))
        assert np.allclose(g.rpy_from_matrix(R), rpy)
        # same as GTSAM's Rot3.RzRyRx (ypr)
        assert np.allclose(R, gtsam.Rot3.Ypr(rpy[2], rpy[1], rpy[0]).matrix())
    batch = rng.uniform(-1, 1, (20, 3))
    assert np.allclose(g.matrix_from_rpy(batch), np.array([g.matrix_from_rpy(r) for r in batch]))


def test_rpy_round_trips_at_and_near_pitch_90(rng):
    """Near pitch +-90 deg (a scanner looking straight down) the matrix from a quaternion has
    R20 = -1 + 2e-16: arcsin read cos(pitch) as 1e-8 and roll and yaw came from rounding noise
    (the round trip was off by 0.8, and calibration.yaml failed its own reader). Every rotation
    within 1e-4 rad of the singularity, both signs, through a quaternion as the writer does it."""
    worst = 0.0
    for _ in range(2000):
        sign = rng.choice([-1.0, 1.0])
        rpy = np.r_[rng.uniform(-np.pi, np.pi), sign * (np.pi / 2 - 10.0 ** rng.uniform(-16, -4)), rng.uniform(-np.pi, np.pi)]
        R = g.matrix_from_quat_wxyz(g.quat_wxyz_from_matrix(g.matrix_from_rpy(rpy)))
        worst = max(worst, g.rotation_angle_between(g.matrix_from_rpy(g.rpy_from_matrix(R)), R))
    assert worst < 2e-6  # the reader of calibration.yaml allows 1e-4 rad


def test_quaternion_round_trip_and_sign(rng):
    for _ in range(50):
        R = random_pose(rng)[:3, :3]
        q = g.quat_wxyz_from_matrix(R)
        assert q[0] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)
        assert np.allclose(g.matrix_from_quat_wxyz(q), R)
        gq = gtsam.Rot3(R).toQuaternion()
        assert np.allclose(abs(q @ [gq.w(), gq.x(), gq.y(), gq.z()]), 1.0)
    # a rotation of ~pi exercises the other branches of Shepperd's method
    for axis in np.eye(3):
        R = g.matrix_from_axis_angle(axis, np.pi - 1e-3)
        assert np.allclose(g.matrix_from_quat_wxyz(g.quat_wxyz_from_matrix(R)), R)


def test_T_a_b_maps_b_to_a_and_composes(rng):
    T_a_b, T_b_c = random_pose(rng), random_pose(rng)
    p_c = rng.normal(size=(5, 3))
    p_b = g.transform_points(T_b_c, p_c)
    assert np.allclose(g.transform_points(T_a_b, p_b), g.transform_points(T_a_b @ T_b_c, p_c))
    assert np.allclose(g.invert_pose(T_a_b) @ T_a_b, np.eye(4))
    batch = np.stack([T_a_b, T_b_c])
    assert np.allclose(g.invert_pose(batch)[1], g.invert_pose(T_b_c))


def test_se3_exp_matches_gtsam_expmap_in_omega_v_order(rng):
    for _ in range(20):
        xi = rng.normal(0, 0.8, 6)
        assert np.allclose(g.se3_exp(xi), gtsam.Pose3.Expmap(xi).matrix())
    xi = np.r_[1e-12, 0, 0, 1.0, 2.0, 3.0]  # near-zero rotation branch
    assert np.allclose(g.se3_exp(xi), gtsam.Pose3.Expmap(xi).matrix())


def test_gtsam_boundary_round_trip(rng):
    T = random_pose(rng)
    assert np.allclose(g.from_gtsam_pose(g.to_gtsam_pose(T)), T)


def test_pinocchio_boundary_reorders_tangents(rng):
    T = random_pose(rng)
    M = g.to_pinocchio_se3(T)
    assert np.allclose(g.from_pinocchio_se3(M), T)
    # the same twist: Pinocchio's log6 is [v, omega], GTSAM's Logmap is [omega, v]
    v_pin = pin.log6(M).vector
    xi = gtsam.Pose3.Logmap(g.to_gtsam_pose(T))
    assert np.allclose(g.tangent_from_pinocchio(v_pin), xi)
    assert np.allclose(g.tangent_to_pinocchio(xi), v_pin)
    J = rng.normal(size=(6, 4))
    assert np.allclose(g.tangent_to_pinocchio(g.tangent_from_pinocchio(J)), J)


def test_transform_plane_keeps_points_on_the_plane(rng):
    T_a_b = random_pose(rng)
    n_b, d_b = g.canonical_plane(rng.normal(size=3), 0.7)
    t1 = np.cross(n_b, [1, 0, 0])
    t2 = np.cross(n_b, t1)
    p_b = -d_b * n_b + rng.normal(size=(10, 1)) * t1 + rng.normal(size=(10, 1)) * t2
    n_a, d_a = g.transform_plane(T_a_b, n_b, d_b)
    assert np.allclose(g.transform_points(T_a_b, p_b) @ n_a + d_a, 0.0)
    # the same as GTSAM's OrientedPlane3.transform (which maps a plane into the pose's frame)
    plane = gtsam.OrientedPlane3(*n_b, d_b).transform(g.to_gtsam_pose(g.invert_pose(T_a_b)))
    assert np.allclose(plane.planeCoefficients(), np.r_[n_a, d_a])


def test_canonical_plane_points_to_origin():
    n, d = g.canonical_plane([0, 0, -2.0], 3.0)  # the plane z = 1.5, not of unit scale
    assert np.allclose(n, [0, 0, -1]) and d == pytest.approx(1.5)
    n, d = g.canonical_plane([0, 0, 1.0], -1.5)
    assert d == pytest.approx(1.5) and np.allclose(n, [0, 0, -1])


def test_fit_rigid_transform_recovers_a_pose(rng):
    T = random_pose(rng)
    p_b = rng.normal(size=(6, 3))
    assert np.allclose(g.fit_rigid_transform(p_b, g.transform_points(T, p_b)), T)
    # with noise the fit is the least-squares one: better than the truth on the noisy data
    p_a = g.transform_points(T, p_b) + rng.normal(0, 1e-3, (6, 3))
    T_fit = g.fit_rigid_transform(p_b, p_a)
    cost = lambda X: np.sum((g.transform_points(X, p_b) - p_a) ** 2)  # noqa: E731
    assert cost(T_fit) <= cost(T)
    assert np.linalg.det(T_fit[:3, :3]) == pytest.approx(1.0)


def test_axis_angle_round_trip(rng):
    for angle in (1e-3, 0.5, 2.0, np.pi - 1e-8):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        a, t = g.axis_angle_from_matrix(g.matrix_from_axis_angle(axis, angle))
        assert t == pytest.approx(angle, abs=1e-6)
        assert np.allclose(g.matrix_from_axis_angle(a, t), g.matrix_from_axis_angle(axis, angle), atol=1e-6)


def _pca_centred(P):  # the textbook form
    c = P.mean(axis=0)
    w, V = np.linalg.eigh((P - c).T @ (P - c) / len(P))
    return g.canonical_plane(V[:, 0], -V[:, 0] @ c), w


@pytest.mark.parametrize("offset_m", [0.0, 2.0, 1e5])
def test_plane_from_points_pca_equals_the_centred_pca(rng, offset_m):
    """The one-pass moments give the centred PCA's plane; far from the origin (map coordinates)
    the cancellation of P^T P / N - c c^T would not, and the centred form is used."""
    n_true = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0])
    t1 = np.cross(n_true, [1.0, 0.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n_true, t1)
    uv = rng.uniform(-1.0, 1.0, size=(20000, 2))
    P = uv[:, :1] * t1 + uv[:, 1:] * t2 + 1e-3 * rng.standard_normal((20000, 1)) * n_true
    P += offset_m * np.array([0.6, 0.8, 0.0]) + np.array([0.0, 0.0, -1.2])
    n, d, w = g.plane_from_points_pca(P)
    (n_ref, d_ref), w_ref = _pca_centred(P)
    assert np.allclose(n, n_ref, atol=1e-9) and abs(d - d_ref) < 1e-9 * max(1.0, offset_m)
    assert np.allclose(w, w_ref, rtol=1e-6, atol=1e-15)
    # the plane found is the true one (noise 1 mm over 20k points)
    assert np.degrees(np.arccos(min(1.0, abs(n @ n_true)))) < 0.01


def test_so3_log_batch_exp_and_skew_agree_with_gtsam(rng):
    phis = np.vstack([rng.normal(0, 1.0, (20, 3)), rng.normal(0, 1e-7, (5, 3)), np.zeros((1, 3))])
    Rb = g.so3_exp_batch(phis)
    for phi, R in zip(phis, Rb):
        assert np.allclose(R, gtsam.Rot3.Expmap(phi).matrix(), atol=1e-14)
        assert np.allclose(R, g.so3_exp(phi), atol=1e-14)
        if np.linalg.norm(phi) < 3.0:
            assert np.allclose(g.so3_log(R), gtsam.Rot3.Logmap(gtsam.Rot3(R)), atol=1e-12)
            assert np.allclose(g.so3_log(R), phi, atol=1e-12)
    S = g.skew_batch(phis.reshape(2, 13, 3))
    assert np.array_equal(S.reshape(26, 3, 3), np.stack([g.skew(p) for p in phis]))


def test_batch_quaternions_and_body_rates_from_rpy_rates(rng):
    rpy = rng.uniform([-np.pi, -1.4, -np.pi], [np.pi, 1.4, np.pi], (30, 3))
    R = g.matrix_from_rpy(rpy)
    q = g.quat_wxyz_from_matrix_batch(R)
    assert np.allclose(q, np.stack([g.quat_wxyz_from_matrix(r) for r in R]), atol=1e-12)
    # body rates: R^T dR/dt = [w]x, by central differences of R(rpy + t rpy_dot)
    rpy_dot = rng.normal(0, 1.0, (30, 3))
    h = 1e-6
    dR = (g.matrix_from_rpy(rpy + h * rpy_dot) - g.matrix_from_rpy(rpy - h * rpy_dot)) / (2 * h)
    W = np.swapaxes(R, 1, 2) @ dR
    w_num = np.c_[W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]]
    assert np.allclose(g.body_rates_from_rpy_rates(rpy, rpy_dot), w_num, atol=1e-8)


def _random_rotvecs(rng, n: int, max_angle: float) -> np.ndarray:
    axes = rng.normal(size=(n, 3))
    return axes / np.linalg.norm(axes, axis=1, keepdims=True) * rng.uniform(0.0, max_angle, (n, 1))


def test_so3_log_batch_agrees_with_gtsam_and_the_single_form(rng):
    from scipy.spatial.transform import Rotation

    phis = np.vstack([_random_rotvecs(rng, 30, 3.1), rng.normal(0, 1e-8, (3, 3)), np.zeros((1, 3))])
    R = np.stack([gtsam.Rot3.Expmap(p).matrix() for p in phis])
    logs = g.so3_log_batch(R)
    assert logs.shape == phis.shape
    np.testing.assert_allclose(logs, [gtsam.Rot3.Logmap(gtsam.Rot3(r)) for r in R], atol=1e-12)
    np.testing.assert_allclose(logs, [g.so3_log(r) for r in R], atol=1e-12)
    np.testing.assert_allclose(logs, phis, atol=1e-12)
    # near pi: the batch form (scipy) keeps the axis; exp(log) is the rotation again
    near = np.array([[0.0, 0.0, np.pi - 1e-9], [np.pi / np.sqrt(2), -np.pi / np.sqrt(2), 0.0]])
    Rn = Rotation.from_rotvec(near).as_matrix()
    np.testing.assert_allclose(g.so3_exp_batch(g.so3_log_batch(Rn)), Rn, atol=1e-12)


def test_so3_log_near_pi_keeps_the_angle_the_axis_and_its_sign(rng):
    """Near pi ``v = vee(R - R^T)`` vanishes: the axis is read from the symmetric part, its sign from ``v``
    (``v / (2 sin th)`` was off by 2e-4 rad at 2e-6 rad from pi)."""
    for gap in (0.0, 1e-12, 1e-9, 3e-7, 2e-6, 1e-4, 1e-2, 1.0, 1.5, 1.6):
        for _ in range(20):
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            phi = axis * (np.pi - gap)
            R = gtsam.Rot3.Expmap(phi).matrix()
            log = g.so3_log(R)
            if gap > 0.0:  # the sign is defined (rotation by pi - gap about +axis, not -axis)
                np.testing.assert_allclose(log, phi, atol=1e-12)
                np.testing.assert_allclose(log, gtsam.Rot3.Logmap(gtsam.Rot3(R)), atol=1e-12)
            else:
                assert abs(abs(log @ axis) - np.pi) < 1e-12
                np.testing.assert_allclose(g.so3_exp(log), R, atol=1e-12)


def test_so3_exp_axis_batch_is_exp_of_axis_times_angle(rng):
    from scipy.spatial.transform import Rotation

    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angles = np.r_[rng.uniform(-np.pi, np.pi, 40), 0.0, 1e-9, np.pi]
    R = g.so3_exp_axis_batch(axis, angles)
    assert R.shape == (len(angles), 3, 3)
    np.testing.assert_allclose(R, Rotation.from_rotvec(axis[None] * angles[:, None]).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(R, g.so3_exp_batch(axis[None] * angles[:, None]), atol=1e-14)


def test_so3_right_jacobian_inverse_batch_inverts_gtsams_right_jacobian(rng):
    x = np.vstack([_random_rotvecs(rng, 20, 3.0), rng.normal(0, 1e-8, (2, 3)), np.zeros((1, 3))])
    Jri = g.so3_right_jacobian_inverse_batch(x)
    for xi, J in zip(x, Jri):
        np.testing.assert_allclose(J @ gtsam.Rot3.ExpmapDerivative(xi), np.eye(3), atol=1e-9)
        np.testing.assert_allclose(J, gtsam.Rot3.LogmapDerivative(xi), atol=1e-9)
    # first order: Log(Exp(x) Exp(d)) = x + Jr^-1(x) d
    d = 1e-7 * rng.normal(size=3)
    y = gtsam.Rot3.Logmap(gtsam.Rot3.Expmap(x[0]) * gtsam.Rot3.Expmap(d))
    np.testing.assert_allclose(y - x[0], Jri[0] @ d, atol=1e-12)


def test_nearest_rotation_is_the_polar_factor_with_det_plus_one(rng):
    import scipy.linalg

    for _ in range(20):
        R = g.so3_exp(_random_rotvecs(rng, 1, 3.0)[0])
        M = R + 0.2 * rng.normal(size=(3, 3))
        Q = g.nearest_rotation(M)
        assert g.is_rotation(Q, tol=1e-12)
        U, _ = scipy.linalg.polar(M)  # the orthogonal factor: the nearest orthogonal matrix
        if np.linalg.det(U) > 0:
            np.testing.assert_allclose(Q, U, atol=1e-12)
        # no rotation nearby is closer in the Frobenius norm
        others = Q @ g.so3_exp_batch(1e-3 * rng.normal(size=(50, 3)))
        assert np.linalg.norm(M - Q) < np.linalg.norm(M - others, axis=(1, 2)).min()
    # a reflection gets the det fix; a rotation is returned as it is (to rounding)
    assert g.is_rotation(g.nearest_rotation(np.diag([1.0, 1.0, -1.0])))
    assert g.is_rotation(g.nearest_rotation(-np.eye(3)))
    R = g.so3_exp([0.3, -1.2, 2.0])
    np.testing.assert_allclose(g.nearest_rotation(R), R, atol=1e-15)
    # a drifted rotation (the EKF's renormalisation): U V^T without a reflection
    drift = R + 1e-9 * rng.normal(size=(3, 3))
    U, _, Vt = np.linalg.svd(drift)
    assert np.array_equal(g.nearest_rotation(drift), U @ Vt)


def test_extrinsic_errors_signs_axes_and_nees(rng):
    from graphcal.solvers.covariance import extrinsic_errors, nees

    T_true = g.se3_exp(np.r_[_random_rotvecs(rng, 1, 2.0)[0], rng.normal(0, 0.3, 3)])
    dphi = np.radians([0.05, -0.02, 0.1])  # R_est = Exp(dphi) R_true (body axes)
    dt = np.array([1e-3, -2e-3, 0.5e-3])
    T_est = g.pose_matrix(g.so3_exp(dphi) @ T_true[:3, :3], T_true[:3, 3] + dt)
    cov6 = np.diag(np.r_[np.radians([0.1, 0.2, 0.3]) ** 2, [1e-6, 4e-6, 9e-6]])
    e = extrinsic_errors(T_est, T_true, cov6)
    np.testing.assert_allclose(e["dphi_deg"], np.degrees(dphi), rtol=1e-9)
    np.testing.assert_allclose(e["dt_mm"], 1e3 * dt, rtol=1e-12)
    assert e["angle_deg"] == pytest.approx(np.degrees(np.linalg.norm(dphi)), rel=1e-9)
    assert e["distance_mm"] == pytest.approx(1e3 * np.linalg.norm(dt), rel=1e-12)
    # error: the truth relative to the estimate, xi = Log(T_est^-1 T_true), rotated to the body axes
    xi = gtsam.Pose3.Logmap(gtsam.Pose3(T_est).between(gtsam.Pose3(T_true)))
    R = T_est[:3, :3]
    np.testing.assert_allclose(e["error"], np.r_[np.degrees(R @ xi[:3]), 1e3 * R @ xi[3:]], atol=1e-12)
    np.testing.assert_allclose(e["error"][:3], -np.degrees(dphi), rtol=1e-9)
    # sigma, z2 along the body axes: cov_body = blockdiag(R, R) cov6 blockdiag(R, R)^T
    B = np.kron(np.eye(2), R)
    var = np.diag(B @ cov6 @ B.T)
    np.testing.assert_allclose(e["sigma"], np.r_[np.degrees(np.sqrt(var[:3])), 1e3 * np.sqrt(var[3:])], rtol=1e-12)
    np.testing.assert_allclose(e["z2"], (B @ xi) ** 2 / var, rtol=1e-9)
    assert e["nees"] == pytest.approx(float(xi @ np.linalg.solve(cov6, xi)), rel=1e-12)
    assert e["nees"] == nees(T_true, T_est, cov6)
    assert "nees" not in extrinsic_errors(T_est, T_true)
