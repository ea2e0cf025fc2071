"""Tests of graphcal.solvers.closed_form: exact and noisy recovery of T_body_sensor from ground
planes (Wahba + linear least squares) and from laser-scanner / 3D points; independence from the
prior (Łabęcki 2012 Sec. 3.2: random starts with sigma_d = 0.2 m, sigma_a = 50 deg, and a 180 deg
yaw error); degenerate station sets (no tilt variation) report their rank and take the free
directions from the prior.

Frames: body z up; u_i = R_world_body^T e_z; the ground in the body frame is u_i . x + z_i = 0;
the sensor sees it as (n_i, d_i) = (R^T u_i, z_i + u_i . t).
"""

from __future__ import annotations

import numpy as np
import pytest

from graphcal.errors import GraphcalError
from graphcal.geometry import (
    matrix_from_rpy,
    pose_from_xyz_rpy,
    pose_matrix,
    rot_z,
    rotation_angle_between,
    so3_exp,
)
from graphcal.solvers.closed_form import (
    extrinsic_from_scan_points,
    project_to_so3,
    rotation_from_normals,
    translation_from_distances,
)

# a depth camera looking forward-down (optical frame), like Chai 2015's 3D vision sensor
T_CAM = pose_from_xyz_rpy([0.25, -0.04, 0.12], np.radians([-110.0, 3.0, -88.0]))
# a laser scanner tilted down 45 deg (Łabęcki 2012: x 0, y 202 mm, z 175 mm, alpha -45 deg)
T_LRF = pose_from_xyz_rpy([0.0, 0.202, 0.175], np.radians([-45.0, 0.0, 90.0]))


def _stations(rng, n, *, roll_deg=12.0, pitch_deg=12.0):
    rpy = np.column_stack([
        rng.uniform(-1, 1, n) * np.radians(roll_deg),
        rng.uniform(-1, 1, n) * np.radians(pitch_deg),
        rng.uniform(-np.pi, np.pi, n),
    ])
    R_wb = matrix_from_rpy(rpy)
    u = R_wb[:, 2, :]  # R_world_body^T e_z = third row
    z = rng.uniform(0.30, 0.60, n)
    return u, z


def _planes(T, u, z):
    R, t = T[:3, :3], T[:3, 3]
    return u @ R, z + u @ t  # n_i = R^T u_i, d_i = z_i + u_i . t


def _random_rotation_noise(rng, n, sigma_rad):
    return np.array([so3_exp(rng.normal(scale=sigma_rad, size=3)) for _ in range(n)])


def _scan_points(rng, T, u, z, *, noise_m=0.0, half_len=0.3, n_pts=40):
    """Points of the scan line where the scanner's x-y plane meets the ground (sensor frame)."""
    R, t = T[:3, :3], T[:3, 3]
    out = []
    for ui, zi in zip(u, z):
        a = R.T @ ui
        c = ui @ t + zi
        # line a_x x + a_y y + c = 0 in the scan plane
        direction = np.array([-a[1], a[0]]) / np.linalg.norm(a[:2])
        p0 = -c * a[:2] / (a[:2] @ a[:2])
        s = np.linspace(-half_len, half_len, n_pts)
        P = p0[None, :] + s[:, None] * direction[None, :]
        if noise_m:
            rng_ = np.linalg.norm(P, axis=1, keepdims=True)
            P = P + noise_m * rng.normal(size=(len(P), 1)) * P / rng_  # range noise along the beam
        out.append(np.column_stack([P, np.zeros(len(P))]))
    return out


def _ground_points_3d(rng, T, u, z, n_pts=60):
    R, t = T[:3, :3], T[:3, 3]
    out = []
    for ui, zi in zip(u, z):
        e1 = np.cross(ui, [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(ui, e1)
        q = -zi * ui + 0.9 * e1 + rng.uniform(-0.4, 0.4, (n_pts, 1)) * e1 + rng.uniform(-0.4, 0.4, (n_pts, 1)) * e2
        out.append((q - t) @ R)  # body -> sensor: R^T (q - t)
    return out


def _random_priors(rng, T, n, sigma_d=0.2, sigma_a_deg=50.0):
    priors = []
    for _ in range(n):
        dR = so3_exp(rng.normal(scale=np.radians(sigma_a_deg), size=3))
        priors.append(pose_matrix(T[:3, :3] @ dR, T[:3, 3] + rng.normal(scale=sigma_d, size=3)))
    # 180 deg yaw error about the body z (the worst case for a gradient method)
    priors.append(pose_matrix(rot_z(np.pi) @ T[:3, :3], T[:3, 3] + [0.2, -0.2, 0.1]))
    # and 180 deg about the sensor's own axis
    priors.append(pose_matrix(T[:3, :3] @ rot_z(np.pi), T[:3, 3]))
    return priors


# ----------------------------------------------------------------------------- planes, exact
def test_exact_data_recovers_extrinsic():
    rng = np.random.default_rng(1)
    u, z = _stations(rng, 12)
    n, d = _planes(T_CAM, u, z)
    R, rank_r = rotation_from_normals(u, n)
    t, rank_t = translation_from_distances(u, d, z)
    assert rank_r == 3 and rank_t == 3
    np.testing.assert_allclose(R, T_CAM[:3, :3], atol=1e-9)
    np.testing.assert_allclose(t, T_CAM[:3, 3], atol=1e-9)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    # weights do not change an exact answer
    w = rng.uniform(0.1, 3.0, len(u))
    np.testing.assert_allclose(rotation_from_normals(u, n, w)[0], T_CAM[:3, :3], atol=1e-9)
    np.testing.assert_allclose(translation_from_distances(u, d, z, w)[0], T_CAM[:3, 3], atol=1e-9)


def test_minimal_station_sets():
    rng = np.random.default_rng(2)
    u, z = _stations(rng, 3)
    n, d = _planes(T_CAM, u, z)
    R, rank = rotation_from_normals(u[:2], n[:2])  # two non-parallel directions fix a rotation
    assert rank == 3
    np.testing.assert_allclose(R, T_CAM[:3, :3], atol=1e-9)
    t, rank = translation_from_distances(u, d, z)  # three independent directions fix t
    assert rank == 3
    np.testing.assert_allclose(t, T_CAM[:3, 3], atol=1e-9)


# ----------------------------------------------------------------------------- planes, noisy
def test_noisy_data_close():
    rng = np.random.default_rng(3)
    u, z = _stations(rng, 60)
    n, d = _planes(T_CAM, u, z)
    n_noisy = np.einsum("nij,nj->ni", _random_rotation_noise(rng, len(n), np.radians(0.1) / np.sqrt(2)), n)
    d_noisy = d + rng.normal(scale=1e-3, size=len(d))
    R, _ = rotation_from_normals(u, n_noisy)
    t, _ = translation_from_distances(u, d_noisy, z)
    assert np.degrees(rotation_angle_between(R, T_CAM[:3, :3])) < 0.05
    assert np.linalg.norm(t - T_CAM[:3, 3]) < 3e-3


# ----------------------------------------------------------------------------- independence of the prior
def test_any_prior_gives_the_same_answer():
    """Łabęcki 2012 Sec. 3.2 lost LM to local minima from sigma_d = 0.2 m / sigma_a = 50 deg starts;
    the closed form does not use the prior when the data determine everything."""
    rng = np.random.default_rng(4)
    u, z = _stations(rng, 30)
    n, d = _planes(T_CAM, u, z)
    n = np.einsum("nij,nj->ni", _random_rotation_noise(rng, len(n), np.radians(0.07)), n)
    d = d + rng.normal(scale=1e-3, size=len(d))
    R0, _ = rotation_from_normals(u, n)
    t0, _ = translation_from_distances(u, d, z)
    for Tp in _random_priors(rng, T_CAM, 25):
        R, rank_r = rotation_from_normals(u, n, R_prior=Tp[:3, :3])
        t, rank_t = translation_from_distances(u, d, z, t_prior=Tp[:3, 3])
        assert rank_r == 3 and rank_t == 3
        np.testing.assert_allclose(R, R0, atol=1e-12)
        np.testing.assert_allclose(t, t0, atol=1e-12)
    assert np.degrees(rotation_angle_between(R0, T_CAM[:3, :3])) < 0.1


def test_scanner_any_prior_gives_the_same_answer():
    rng = np.random.default_rng(5)
    u, z = _stations(rng, 25)
    pts = _scan_points(rng, T_LRF, u, z, noise_m=1e-3)
    results = []
    for Tp in _random_priors(rng, T_LRF, 25):
        T, rank = extrinsic_from_scan_points(u, z, pts, T_prior=Tp)
        assert rank == 6
        results.append(T)
    for T in results:
        np.testing.assert_allclose(T, results[0], atol=1e-9)
    assert np.degrees(rotation_angle_between(results[0][:3, :3], T_LRF[:3, :3])) < 0.2
    assert np.linalg.norm(results[0][:3, 3] - T_LRF[:3, 3]) < 3e-3



def _lift_onto_boxes(rng, pts, u, z, T, fraction=0.15, heights=(0.05, 0.25)):
    """Move a share of every scan's points along their beams onto box tops ``heights`` m above the
    floor: points off the ground, as in Łabęcki's scene."""
    out = []
    for ui, zi, P in zip(u, z, pts):
        H = ui @ T[:3, 3] + zi  # the scanner's height above the ground
        P = P.copy()
        k = rng.random(len(P)) < fraction
        P[k] *= (1.0 - rng.uniform(*heights, k.sum()) / H)[:, None]
        out.append(P)
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_scanner_small_tilts_boxes_any_prior(seed):
    """Łabęcki's setting: body tilts of only a few degrees and boxes in the scans. A 2D scan then fits
    the floor almost as well from the scanner turned about the vertical or reflected through the
    ground (under it, looking up), and least squares preferred such a copy from about half of the
    50 deg starts. Every start now gives the truth; the reflection is refused because the scanner is
    above the ground."""
    rng = np.random.default_rng(100 + seed)
    u, z = _stations(rng, 40, roll_deg=4.0, pitch_deg=4.0)
    pts = _lift_onto_boxes(rng, _scan_points(rng, T_LRF, u, z, noise_m=1e-3), u, z, T_LRF)
    for Tp in _random_priors(rng, T_LRF, 8):
        T, _ = extrinsic_from_scan_points(u, z, pts, T_prior=Tp)
        assert np.degrees(rotation_angle_between(T[:3, :3], T_LRF[:3, :3])) < 0.3, Tp
        assert np.linalg.norm(T[:3, 3] - T_LRF[:3, 3]) < 5e-3, Tp
        assert np.median(u @ T[:3, 3] + z) > 0.0  # above the ground

# ----------------------------------------------------------------------------- degenerate station sets
def test_no_tilt_variation_reports_rank_and_takes_yaw_from_prior():
    rng = np.random.default_rng(6)
    u, z = _stations(rng, 15, roll_deg=0.0, pitch_deg=0.0)  # level body: u_i = e_z at every station
    np.testing.assert_allclose(u, np.tile([0.0, 0.0, 1.0], (15, 1)), atol=1e-12)
    n, d = _planes(T_CAM, u, z)
    for yaw_err in (0.3, -1.2, np.pi):
        R_prior = rot_z(yaw_err) @ T_CAM[:3, :3]  # wrong only about the undetermined axis
        R, rank = rotation_from_normals(u, n, R_prior=R_prior)
        assert rank == 2
        np.testing.assert_allclose(R, R_prior, atol=1e-9)  # the free yaw comes from the prior
    # a prior also wrong in the determined directions: those still come from the data
    R_prior = so3_exp([0.3, -0.2, 0.5]) @ T_CAM[:3, :3]
    R, rank = rotation_from_normals(u, n, R_prior=R_prior)
    assert rank == 2
    np.testing.assert_allclose(R @ n.T, u.T, atol=1e-9)  # R n_i = u_i still holds exactly
    # translation: only the height component is determined
    t_prior = T_CAM[:3, 3] + np.array([0.1, -0.07, 0.2])
    t, rank = translation_from_distances(u, d, z, t_prior=t_prior)
    assert rank == 1
    np.testing.assert_allclose(t[:2], t_prior[:2], atol=1e-9)
    assert t[2] == pytest.approx(T_CAM[2, 3], abs=1e-9)


def test_pitch_only_variation():
    rng = np.random.default_rng(7)
    _, z = _stations(rng, 15)
    # pitch only (and a fixed heading, which does not change u): u stays in the body x-z plane
    rpy = np.column_stack([np.zeros(15), np.radians(np.linspace(-15, 15, 15)), np.zeros(15)])
    u = matrix_from_rpy(rpy)[:, 2, :]
    n, d = _planes(T_CAM, u, z)
    R, rank_r = rotation_from_normals(u, n, R_prior=np.eye(3))
    assert rank_r == 3  # two non-parallel directions determine the rotation
    np.testing.assert_allclose(R, T_CAM[:3, :3], atol=1e-9)
    t_prior = T_CAM[:3, 3] + [0.05, 0.05, 0.05]
    t, rank_t = translation_from_distances(u, d, z, t_prior=t_prior)
    assert rank_t == 2  # pitch variation determines x and z, not y
    np.testing.assert_allclose(t[[0, 2]], T_CAM[[0, 2], 3], atol=1e-9)
    assert t[1] == pytest.approx(t_prior[1], abs=1e-9)


def test_no_data_returns_prior_with_rank_zero():
    R, rank = rotation_from_normals(np.zeros((0, 3)), np.zeros((0, 3)), R_prior=T_CAM[:3, :3])
    assert rank == 0
    np.testing.assert_allclose(R, T_CAM[:3, :3], atol=1e-12)


# ----------------------------------------------------------------------------- points
def test_scanner_exact_recovery():
    rng = np.random.default_rng(8)
    u, z = _stations(rng, 10)
    pts = _scan_points(rng, T_LRF, u, z)
    T, rank = extrinsic_from_scan_points(u, z, pts)
    assert rank == 6
    np.testing.assert_allclose(T, T_LRF, atol=1e-9)
    # (N, 2) arrays mean the same
    T2, _ = extrinsic_from_scan_points(u, z, [p[:, :2] for p in pts])
    np.testing.assert_allclose(T2, T_LRF, atol=1e-9)
    # the linear solution alone (no Gauss-Newton polish) is exact too
    T3, _ = extrinsic_from_scan_points(u, z, pts, gauss_newton_iterations=0)
    np.testing.assert_allclose(T3, T_LRF, atol=1e-9)


def test_3d_points_exact_recovery():
    rng = np.random.default_rng(9)
    u, z = _stations(rng, 10)
    pts = _ground_points_3d(rng, T_CAM, u, z)
    T, rank = extrinsic_from_scan_points(u, z, pts, T_prior=pose_matrix(rot_z(np.pi) @ T_CAM[:3, :3], [0, 0, 0]))
    assert rank == 6
    np.testing.assert_allclose(T, T_CAM, atol=1e-9)


def test_scanner_noisy_close():
    rng = np.random.default_rng(10)
    u, z = _stations(rng, 40)
    pts = _scan_points(rng, T_LRF, u, z, noise_m=2e-3)
    T, rank = extrinsic_from_scan_points(u, z, pts, T_prior=np.eye(4))
    assert rank == 6
    assert np.degrees(rotation_angle_between(T[:3, :3], T_LRF[:3, :3])) < 0.2
    assert np.linalg.norm(T[:3, 3] - T_LRF[:3, 3]) < 3e-3


def test_scanner_level_body_is_rank_deficient():
    rng = np.random.default_rng(11)
    u, z = _stations(rng, 12, roll_deg=0.0, pitch_deg=0.0)
    pts = _scan_points(rng, T_LRF, u, z)
    T_prior = pose_matrix(rot_z(0.2) @ T_LRF[:3, :3], T_LRF[:3, 3] + [0.03, -0.02, 0.0])
    T, rank = extrinsic_from_scan_points(u, z, pts, T_prior=T_prior)
    assert rank == 3  # roll, pitch and height of the scanner only
    # the determined part matches the data: every point lies on the ground
    for ui, zi, P in zip(u, z, pts):
        np.testing.assert_allclose(ui @ (P @ T[:3, :3].T + T[:3, 3]).T + zi, 0.0, atol=1e-9)
    # the rest is the prior's: its yaw (not one of the floor's equally good turned copies) and x, y
    assert np.degrees(rotation_angle_between(T[:3, :3], T_prior[:3, :3])) < 1e-6
    np.testing.assert_allclose(T[:2, 3], T_prior[:2, 3], atol=1e-9)


# ----------------------------------------------------------------------------- misc
def test_project_to_so3():
    rng = np.random.default_rng(12)
    R = so3_exp(rng.normal(size=3))
    M = R + 1e-3 * rng.normal(size=(3, 3))
    Rp = project_to_so3(M)
    np.testing.assert_allclose(Rp @ Rp.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(Rp) == pytest.approx(1.0)
    assert rotation_angle_between(Rp, R) < 3e-3
    assert np.linalg.det(project_to_so3(-np.eye(3))) == pytest.approx(1.0)


def test_bad_input_raises_graphcal_error():
    with pytest.raises(GraphcalError):
        rotation_from_normals(np.ones((3, 3)), np.ones((4, 3)))
    with pytest.raises(GraphcalError):
        rotation_from_normals(np.zeros((3, 3)), np.ones((3, 3)))
    with pytest.raises(GraphcalError):
        translation_from_distances(np.ones((3, 3)), [1.0, 2.0], [0.0, 0.0, 0.0])
    with pytest.raises(GraphcalError):
        rotation_from_normals(np.ones((2, 3)), np.ones((2, 3)), weights=[1.0, -1.0])
    with pytest.raises(GraphcalError):
        extrinsic_from_scan_points(np.ones((2, 3)), [0.3, 0.3], [np.zeros((5, 3))])
