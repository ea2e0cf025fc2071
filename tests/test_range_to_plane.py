"""The range-to-plane factor: analytic Jacobians against central differences through gtsam's
retract, and the reason it exists: no errors-in-variables bias with noise along the beams."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from scipy.optimize import least_squares

from graphcal.factors.range_to_plane import range_to_plane_error, range_to_plane_factor
from graphcal.geometry import pose_from_xyz_rpy, rotation_angle_between, se3_exp, transform_points
from graphcal.testing import numerical_jacobian

EPS = 1e-7  # central-difference step (rad, m)


def _scan(rng, T_world_sensor, n=150, sigma=0.0):
    """Beams of a 2D scanner (x-y plane) that hit the ground z = 0, with range noise."""
    ang = rng.uniform(-1.2, 1.2, 4 * n)
    d = np.c_[np.cos(ang), np.sin(ang), np.zeros_like(ang)]
    dw = d @ T_world_sensor[:3, :3].T
    down = dw[:, 2] < -0.05
    d, dw = d[down][:n], dw[down][:n]
    r = -T_world_sensor[2, 3] / dw[:, 2]
    return d * (r + rng.normal(0, sigma, len(r)))[:, None]


@pytest.mark.parametrize("seed", range(25))
def test_jacobians_match_central_differences(seed):
    rng = np.random.default_rng(seed)
    X = pose_from_xyz_rpy([0, 0, rng.uniform(0.1, 0.6)], rng.uniform(-0.3, 0.3, 3))
    S = pose_from_xyz_rpy(rng.uniform(-0.3, 0.3, 3) + [0, 0, 0.2], [rng.uniform(-0.2, 0.2), rng.uniform(0.4, 1.2), rng.uniform(-3, 3)])
    P = _scan(rng, X @ S, n=40, sigma=0.01)
    e, (H_X, H_S) = range_to_plane_error(X, S, P)
    assert np.allclose(H_X, numerical_jacobian(lambda Xp: range_to_plane_error(Xp.matrix(), S, P, want_jacobians=False)[0],
                                               gtsam.Pose3(X), EPS), atol=1e-6)
    assert np.allclose(H_S, numerical_jacobian(lambda Sp: range_to_plane_error(X, Sp.matrix(), P, want_jacobians=False)[0],
                                               gtsam.Pose3(S), EPS), atol=1e-6)


def test_near_grazing_beams_and_identity_rotation():
    X = np.eye(4)
    X[2, 3] = 0.3
    S = pose_from_xyz_rpy([0, 0, 0], [0, 0.05, 0])  # scan plane nearly parallel to the ground
    P = _scan(np.random.default_rng(1), X @ S, n=30)
    e, (H_X, H_S) = range_to_plane_error(X, S, P)
    assert np.all(np.isfinite(H_X)) and np.allclose(e, 0.0, atol=1e-9)
    assert np.allclose(H_S, numerical_jacobian(lambda Sp: range_to_plane_error(X, Sp.matrix(), P, want_jacobians=False)[0],
                                               gtsam.Pose3(S), EPS), atol=1e-5)


def test_factor_linearizes_like_the_pure_function():
    rng = np.random.default_rng(3)
    X = pose_from_xyz_rpy([0, 0, 0.3], [0.05, -0.04, 0.2])
    S = pose_from_xyz_rpy([0.2, 0, 0.17], [0, 0.78, 0])
    P = _scan(rng, X @ S, n=50, sigma=0.01)
    f = range_to_plane_factor(1, 2, P, 0.01)
    v = gtsam.Values()
    v.insert(1, gtsam.Pose3(X))
    v.insert(2, gtsam.Pose3(S))
    A, b = f.linearize(v).jacobian()
    e, (H_X, H_S) = range_to_plane_error(X, S, P)
    assert np.allclose(A, np.hstack([H_X, H_S]) / 0.01) and np.allclose(b, -e / 0.01)


def test_no_bias_where_point_heights_are_biased():
    """Small body tilts, 10 mm range noise: least squares on point heights is pulled degrees away;
    the range residual is not."""
    rng = np.random.default_rng(7)
    S_true = pose_from_xyz_rpy([0.2, 0.0, 0.175], [0.0, np.radians(45.0), 0.0])
    bodies = [pose_from_xyz_rpy([0, 0, 0.12], np.radians([rng.uniform(-6, 6), rng.uniform(-6, 6), 0.0])) for _ in range(40)]
    scans = [_scan(rng, X @ S_true, n=200, sigma=0.01) for X in bodies]

    def fit(residual):
        sol = least_squares(lambda xi: np.concatenate([residual(X, S_true @ se3_exp(xi), P) for X, P in zip(bodies, scans)]),
                            np.zeros(6))
        T = S_true @ se3_exp(sol.x)
        return np.degrees(rotation_angle_between(T[:3, :3], S_true[:3, :3]))

    heights = fit(lambda X, S, P: transform_points(X @ S, P)[:, 2])
    ranges = fit(lambda X, S, P: range_to_plane_error(X, S, P, want_jacobians=False)[0])
    assert heights > 1.0  # the bias this factor exists to remove
    assert ranges < 0.2
