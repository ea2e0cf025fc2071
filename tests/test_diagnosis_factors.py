"""The factors of the diagnosis extensions (range scale, ground-plane prior):
analytic Jacobians vs central differences through GTSAM's retract, at random and near-singular points,
and the physical meaning of each (a scaled sensor, a tilted floor)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from graphcal.factors.keys import G, S, X
from graphcal.factors.plane_observation import plane_observation_error
from graphcal.factors.plane_prior import plane_prior_factor
from graphcal.factors.range_scale import scaled_plane_error, scaled_plane_factor, scaled_range_error, scaled_range_factor
from graphcal.factors.range_to_plane import range_to_plane_error
from graphcal.geometry import pose_from_xyz_rpy
from graphcal.testing import SPECIAL_ROTATIONS, assert_jacobians, factor_jacobians, gtsam_values, random_pose, random_rotation, random_unit

C = gtsam.symbol_shorthand.C


def _camera_looking_down(rng):
    X_ = pose_from_xyz_rpy([rng.normal(scale=0.1), rng.normal(scale=0.1), 0.3 + 0.05 * rng.random()],
                           rng.normal(scale=0.2, size=3))
    S_ = pose_from_xyz_rpy([0.2, 0.0, 0.1], [np.pi + rng.normal(scale=0.3), rng.normal(scale=0.3), rng.normal()])
    return X_, S_


@pytest.mark.parametrize("seed", range(6))
def test_scaled_plane_jacobians(seed):
    rng = np.random.default_rng(seed)
    X_, S_ = random_pose(rng, 0.3), random_pose(rng, 0.3)
    if seed < len(SPECIAL_ROTATIONS):
        S_[:3, :3] = SPECIAL_ROTATIONS[seed]
    n_m, d_m = random_unit(rng), 0.2 + rng.random()
    scale = 1.0 + rng.normal(scale=0.03)
    plane = random_unit(rng)
    for g in (None, np.append(plane, rng.normal())):
        if g is None:
            f = scaled_plane_factor(X(1), S(0), C(0), n_m, d_m, np.eye(4) * 1e-6)
            v = gtsam_values(x=(X(1), X_), s=(S(0), S_), c=(C(0), np.array([scale])))
            e, H = scaled_plane_error(X_, S_, [scale], n_m, d_m)
            H, dims = H[:3], [6, 6, 1]
        else:
            f = scaled_plane_factor(X(1), S(0), C(0), n_m, d_m, np.eye(4) * 1e-6, g_key=G(0))
            v = gtsam_values(x=(X(1), X_), s=(S(0), S_), c=(C(0), np.array([scale])),
                        g=(G(0), gtsam.OrientedPlane3(*g)))
            e, H = scaled_plane_error(X_, S_, [scale], n_m, d_m, g)
            dims = [6, 6, 1, 3]
        np.testing.assert_allclose(f.unwhitenedError(v), e, atol=1e-12)
        assert_jacobians(f, v, dims, H, what=f"scaled plane seed {seed}")


def test_scaled_plane_reads_a_scaled_sensor_as_zero_error():
    rng = np.random.default_rng(3)
    X_, S_ = _camera_looking_down(rng)
    e_true, _ = plane_observation_error(X_, S_, [0, 0, 1], 1.0, want_jacobians=False)
    T_ws = X_ @ S_
    n_s = T_ws[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    d_s = T_ws[2, 3]
    scale = 1.025
    e, _ = scaled_plane_error(X_, S_, [scale], n_s, scale * d_s, want_jacobians=False)
    np.testing.assert_allclose(e, 0.0, atol=1e-12)
    e1, _ = scaled_plane_error(X_, S_, [1.0], n_s, scale * d_s, want_jacobians=False)
    assert e1[2] == pytest.approx(-(scale - 1.0) * d_s, rel=1e-9)  # the unscaled model sees the error


@pytest.mark.parametrize("seed", range(4))
def test_scaled_range_jacobians_and_meaning(seed):
    rng = np.random.default_rng(10 + seed)
    X_, S_ = _camera_looking_down(rng)
    T_ws = X_ @ S_
    D = rng.normal(size=(40, 3))
    D[:, 2] = np.abs(D[:, 2]) + 0.3  # mostly forward (sensor z) ...
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    b = D @ (T_ws[:3, :3].T @ np.array([0.0, 0.0, 1.0]))
    D = D[b < -0.1]
    r_true = -T_ws[2, 3] / (D @ (T_ws[:3, :3].T @ np.array([0.0, 0.0, 1.0])))
    scale = 0.98 + 0.04 * rng.random()
    P = D * (scale * r_true)[:, None]
    e, _ = scaled_range_error(X_, S_, [scale], P, want_jacobians=False)
    np.testing.assert_allclose(e, 0.0, atol=1e-10)
    e0, _ = range_to_plane_error(X_, S_, P, want_jacobians=False)
    assert np.abs(e0).max() > 1e-3  # unscaled: the error is visible
    f = scaled_range_factor(X(1), S(0), C(0), P * 1.01, 0.01)
    v = gtsam_values(x=(X(1), X_), s=(S(0), S_), c=(C(0), np.array([scale])))
    e, H = scaled_range_error(X_, S_, [scale], P * 1.01)
    np.testing.assert_allclose(f.unwhitenedError(v), e, atol=1e-12)
    assert_jacobians(f, v, [6, 6, 1], H, what=f"scaled range seed {seed}")


@pytest.mark.parametrize("tilt", [0.0, 1e-9, 0.03, 1.2])
def test_plane_prior_factor(tilt):
    n0 = np.array([0.0, 0.0, 1.0])
    n = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    f = plane_prior_factor(G(0), np.append(n0, 0.0), 0.01, 0.001)
    v = gtsam_values(g=(G(0), gtsam.OrientedPlane3(n[0], n[1], n[2], 0.004)))
    e = f.unwhitenedError(v)
    assert np.hypot(e[0], e[1]) == pytest.approx(np.sin(tilt), abs=1e-12)
    assert e[2] == pytest.approx(0.004)
    A, _ = f.linearize(v).jacobian()
    Hn = factor_jacobians(f, v, [3])[0] / np.array([0.01, 0.01, 0.001])[:, None]
    np.testing.assert_allclose(A, Hn, atol=1e-5)


def test_bad_inputs_raise():
    with pytest.raises(ValueError):
        scaled_plane_error(np.eye(4), np.eye(4), [0.0], [0, 0, 1], 1.0)
    with pytest.raises(ValueError):
        plane_prior_factor(G(0), [0, 0, 1, 0], -1.0, 0.1)


@pytest.mark.parametrize("seed", range(5))
def test_imu_tilted_jacobians_and_meaning(seed):
    from graphcal.factors.gravity_tilt import imu_attitude_tilted_error, imu_attitude_tilted_factor
    from graphcal.factors.keys import M
    from graphcal.geometry import matrix_from_axis_angle

    W_ = gtsam.symbol_shorthand.W
    rng = np.random.default_rng(20 + seed)
    X_ = random_pose(rng, 0.3) if seed else np.eye(4)
    R_bi = random_rotation(rng) if seed > 1 else np.eye(3)
    R_tilt = matrix_from_axis_angle([np.cos(seed), np.sin(seed), 0.0], 0.03 * (seed + 1))
    W = R_tilt.T
    # the accelerometer of a body X on a floor tilted by R_tilt (level world) reads up = (R_tilt X R_bi)^T e_z
    f = (R_tilt @ X_[:3, :3] @ R_bi).T @ np.array([0.0, 0.0, 9.81])
    e, _ = imu_attitude_tilted_error(X_, R_bi, W, f, want_jacobians=False)
    np.testing.assert_allclose(e, 0.0, atol=1e-12)
    e_level, _ = imu_attitude_tilted_error(X_, R_bi, np.eye(3), f, want_jacobians=False)
    assert np.linalg.norm(e_level) == pytest.approx(0.03 * (seed + 1), rel=0.02)  # the level model sees the tilt
    f_meas = f + rng.normal(scale=0.05, size=3)
    fac = imu_attitude_tilted_factor(X(1), M(0), W_(0), f_meas, 0.01)
    v = gtsam_values(x=(X(1), X_), m=(M(0), R_bi), w=(W_(0), W))
    e, H = imu_attitude_tilted_error(X_, R_bi, W, f_meas)
    np.testing.assert_allclose(fac.unwhitenedError(v), e, atol=1e-12)
    assert_jacobians(fac, v, [6, 3, 3], H, what=f"imu tilted seed {seed}")


def test_the_family_p_value_is_bonferroni():
    """A finding's family p-value is its p-value times the number of candidates tested."""
    from scipy.stats import chi2

    from graphcal.diagnosis.scores import evidence

    ev = evidence("score", 9.0, 1, family_size=10, n_rows=100)
    assert ev.p_value == pytest.approx(chi2.sf(9.0, 1), rel=1e-9)
    assert ev.log10_p_family == pytest.approx(np.log10(10 * chi2.sf(9.0, 1)), abs=1e-9)


def test_a_link_change_beyond_half_the_link_is_implausible():
    """60 % of a link's length is wrong data, not a calibration; 40 % is a (large) plausible error."""
    from graphcal.diagnosis.catalogue import Candidate
    from graphcal.diagnosis.diagnose import implausible_size
    from graphcal.models.perturb import joint_origin
    from graphcal.models.robot import load_robot

    robot = load_robot(model="octopus")
    joint = "rf_tibia_joint"
    L = float(np.linalg.norm(joint_origin(robot, joint)[0]))
    cand = Candidate("link_length", (("joint", joint), ("leg", "rf_foot")))
    assert implausible_size(cand, {"delta_m": -0.6 * L}, robot)
    assert implausible_size(cand, {"delta_m": 0.4 * L}, robot) == ""
