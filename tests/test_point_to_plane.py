"""The shared Gauss-Newton core of the two ICPs (graphcal.solvers.point_to_plane)."""

import gtsam
import numpy as np

from graphcal.geometry import se3_exp
from graphcal.solvers.point_to_plane import constrained_step, point_to_plane_jacobian
from graphcal.testing import numerical_jacobian


def _residuals(T, s, n, q):
    return np.einsum("ij,ij->i", n, s @ T[:3, :3].T + T[:3, 3] - q)


def test_jacobian_matches_numerical_derivative_of_the_right_perturbation():
    rng = np.random.default_rng(0)
    s = rng.normal(0, 1.0, (20, 3))
    n = rng.normal(0, 1.0, (20, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    q = rng.normal(0, 1.0, (20, 3))
    T = se3_exp(rng.normal(0, 0.5, 6))
    J = point_to_plane_jacobian(s, n, T[:3, :3])
    # Pose3's retract is the right perturbation T Exp(xi), xi = [omega, v]
    Jn = numerical_jacobian(lambda P: _residuals(P.matrix(), s, n, q), gtsam.Pose3(T), 1e-6)
    np.testing.assert_allclose(J, Jn, atol=1e-7)


def _floor(rng, N=500):
    s = np.c_[rng.uniform(-1, 1, N), rng.uniform(-1, 1, N), np.full(N, 2.0)]
    return s, np.tile([0.0, 0.0, -1.0], (N, 1))


def test_full_rank_step_is_the_newton_step_and_a_floor_leaves_three_directions_alone():
    rng = np.random.default_rng(1)
    # a box corner: three planes constrain all six directions
    s = rng.uniform(-1, 1, (900, 3))
    s[:300, 2], s[300:600, 0], s[600:, 1] = 2.0, 1.0, 1.0
    n = np.zeros_like(s)
    n[:300, 2], n[300:600, 0], n[600:, 1] = -1.0, 1.0, 1.0
    J = point_to_plane_jacobian(s, n, np.eye(3))
    r = rng.normal(0, 0.01, len(s))
    H, g = J.T @ J, J.T @ r
    cs = constrained_step(H, g, scale=np.ones(6), degeneracy_ratio=1e-3)
    assert cs.n_degenerate == 0
    np.testing.assert_allclose(cs.step, -np.linalg.solve(H, g), rtol=1e-9, atol=1e-12)
    # a floor: z, roll and pitch are measured; x, y and yaw are not and get no update
    s, n = _floor(rng)
    J = point_to_plane_jacobian(s, n, np.eye(3))
    r = rng.normal(0, 0.01, len(s))
    cs = constrained_step(J.T @ J, J.T @ r, scale=np.ones(6), degeneracy_ratio=1e-3)
    assert cs.n_degenerate == 3
    assert np.allclose(cs.step[[2, 3, 4]], 0.0, atol=1e-12)  # yaw, x, y
    assert np.abs(cs.step[[0, 1, 5]]).max() > 1e-4


def test_prior_regularises_the_step_and_is_projected_on_the_measured_directions():
    rng = np.random.default_rng(2)
    s, n = _floor(rng)
    J = point_to_plane_jacobian(s, n, np.eye(3))
    r = rng.normal(0.02, 0.005, len(s))  # the floor is 2 cm off
    H, g = J.T @ J, J.T @ r
    free = constrained_step(H, g, scale=np.ones(6), degeneracy_ratio=1e-3)
    prior = np.full(6, 1.0 / 0.001**2)  # 1 mm / 1 mrad: the prior pulls the step towards 0
    held = constrained_step(H, g, scale=np.ones(6), degeneracy_ratio=1e-3, prior_information=prior)
    assert held.n_degenerate == 3
    assert np.allclose(held.step[[2, 3, 4]], 0.0, atol=1e-12)
    assert 0 < abs(held.step[5]) < 0.5 * abs(free.step[5])
    # a prior gradient along an unmeasured direction (the stitching's accumulated step) moves nothing there
    delta = np.array([0.0, 0.0, 0.01, 0.03, 0.0, 0.0])  # yaw and x so far
    pulled = constrained_step(H, g + prior * delta, scale=np.ones(6), degeneracy_ratio=1e-3, prior_information=prior)
    assert np.allclose(pulled.step[[2, 3, 4]], 0.0, atol=1e-12)
    np.testing.assert_allclose(free.step[5], 0.02, rtol=0.2)
