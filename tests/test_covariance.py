"""Tests of graphcal.solvers.covariance: named unobservable directions on synthetic extrinsic
graphs built from gtsam built-in factors only, the QR fallback when gtsam's Marginals refuses an
ill-conditioned graph, singular graphs (no crash, inf along the free directions), body-axis
sigmas against a Monte Carlo sample of right perturbations, and NEES of Gaussian samples.

The extrinsic graphs: X0 (body pose, tight prior) -> S0 (T_body_sensor) through a
BetweenFactorPose3 that plays the data, with a covariance given in BODY axes (so a direction such
as "yaw about body z" can be made uninformative), plus the CAD prior on S0 (PriorFactorPose3).
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import S, X

from graphcal.geometry import pose_from_xyz_rpy, se3_exp, to_gtsam_pose
from graphcal.solvers.covariance import (
    MarginalCovariances,
    body_axis_sigmas,
    marginal_covariances,
    nees,
    unobservable_directions,
)

T_BS = pose_from_xyz_rpy([0.30, -0.02, 0.20], np.radians([-110.0, 2.0, -90.0]))
SIG_R, SIG_T = np.radians(5.0), 0.05  # CAD prior: 5 deg, 5 cm
COV_PRIOR = np.diag([SIG_R**2] * 3 + [SIG_T**2] * 3)
TIGHT = 1e-3  # data sigma along determined directions (rad or m)
NONE = 10.0  # data sigma along an "undetermined" direction


def _J(R):
    J = np.zeros((6, 6))
    J[:3, :3] = R
    J[3:, 3:] = R
    return J


def _extrinsic_graph(body_sigmas=None, body_cov=None):
    """Graph X0 -- S0 with the data covariance in body axes [rx, ry, rz, x, y, z]."""
    Cb = np.diag(np.square(body_sigmas)) if body_cov is None else body_cov
    J = _J(T_BS[:3, :3])
    Cs = J.T @ Cb @ J  # to the sensor-frame tangent of S0
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-5)))
    graph.add(gtsam.BetweenFactorPose3(X(0), S(0), to_gtsam_pose(T_BS), gtsam.noiseModel.Gaussian.Covariance(Cs)))
    graph.add(gtsam.PriorFactorPose3(S(0), to_gtsam_pose(T_BS), gtsam.noiseModel.Diagonal.Sigmas([SIG_R] * 3 + [SIG_T] * 3)))
    values.insert(X(0), gtsam.Pose3())
    values.insert(S(0), to_gtsam_pose(T_BS))
    return graph, values


def _posterior(body_sigmas=None, body_cov=None):
    graph, values = _extrinsic_graph(body_sigmas, body_cov)
    covs = marginal_covariances(graph, values, [S(0)])
    return covs, covs[S(0)]


# ----------------------------------------------------------------------------- unobservable directions
def test_yaw_not_determined_is_named_and_finite():
    covs, cov = _posterior([TIGHT, TIGHT, NONE, TIGHT, TIGHT, TIGHT])
    assert covs.method == "cholesky" and not covs.singular
    assert np.all(np.isfinite(cov))
    s_rot, s_xyz, _, _ = body_axis_sigmas(T_BS, cov)
    assert s_rot[2] == pytest.approx(5.0, rel=0.01)  # the prior's 5 deg: finite, and honest
    assert np.all(s_rot[:2] < 0.1) and np.all(s_xyz < 1.1)
    sentences = unobservable_directions(T_BS, cov, COV_PRIOR)
    assert len(sentences) == 1
    s = sentences[0]
    assert "rotation about the ground normal (yaw about body z)" in s
    assert "not determined by the data" in s
    assert "add roll and pitch variation" in s


def test_fully_observed_gives_no_sentence():
    _, cov = _posterior([TIGHT] * 6)
    assert unobservable_directions(T_BS, cov, COV_PRIOR) == ()


@pytest.mark.parametrize(
    "axis, words, motion",
    [
        (3, "translation along body x", "add pitch variation"),
        (4, "translation along body y", "add roll variation"),
        (5, "height (translation along body z)", "vary the body height"),
        (0, "rotation about body x (roll)", "sees the ground"),
    ],
)
def test_each_axis_has_its_words(axis, words, motion):
    sig = [TIGHT] * 6
    sig[axis] = NONE
    _, cov = _posterior(sig)
    sentences = unobservable_directions(T_BS, cov, COV_PRIOR)
    assert len(sentences) == 1
    assert words in sentences[0] and motion in sentences[0]


def test_several_directions_one_sentence_each():
    _, cov = _posterior([TIGHT, TIGHT, NONE, NONE, NONE, TIGHT])  # level body: yaw, x, y free
    sentences = unobservable_directions(T_BS, cov, COV_PRIOR)
    assert len(sentences) == 3
    text = " | ".join(sentences)
    for words in ("yaw about body z", "translation along body x", "translation along body y"):
        assert words in text


def test_mixed_direction_gets_percentages():
    """Data blind to one combination of yaw and x (equal parts in prior-sigma units)."""
    sig = np.array([SIG_R] * 3 + [SIG_T] * 3)
    v = np.zeros(6)
    v[2] = v[3] = 1.0 / np.sqrt(2.0)
    info_scaled = 1e6 * (np.eye(6) - np.outer(v, v)) + 1e-4 * np.outer(v, v)
    Cb = np.linalg.inv(info_scaled / np.outer(sig, sig))
    _, cov = _posterior(body_cov=Cb)
    sentences = unobservable_directions(T_BS, cov, COV_PRIOR)
    assert len(sentences) == 1
    s = sentences[0]
    assert s.startswith("a combination of")
    assert "translation along body x (50 %)" in s and "yaw about body z) (50 %)" in s
    assert "add roll and pitch variation" in s


def test_partly_determined_direction_is_not_reported():
    """Data sigma along yaw equal to the prior's: posterior sigma 71 % > 0.5 -> reported; data
    three times better than the prior: 32 % -> not reported."""
    _, cov = _posterior([TIGHT, TIGHT, SIG_R, TIGHT, TIGHT, TIGHT])
    assert len(unobservable_directions(T_BS, cov, COV_PRIOR)) == 1
    _, cov = _posterior([TIGHT, TIGHT, SIG_R / 3, TIGHT, TIGHT, TIGHT])
    assert unobservable_directions(T_BS, cov, COV_PRIOR) == ()


def test_infinite_posterior_component_is_reported():
    cov = np.diag([1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6])
    R = T_BS[:3, :3]
    # the sensor-frame axis that maps to body z rotation gets infinite variance
    a = R.T @ np.array([0.0, 0.0, 1.0])
    i = int(np.argmax(np.abs(a)))
    cov_s = _J(R).T @ cov @ _J(R)
    cov_s[i, i] = np.inf
    sentences = unobservable_directions(T_BS, cov_s, COV_PRIOR)
    assert sentences and all(isinstance(s, str) for s in sentences)


# ----------------------------------------------------------------------------- marginals: QR fallback
def _ill_conditioned_chain(n=20, eps=1e-8):
    """A Pose3 chain whose first prior correlates omega_x and v_y at 1 - eps: gtsam's Marginals
    throws "Indeterminant linear system" (its Cholesky requires rcond >= sqrt(machine eps))."""
    C = np.diag([0.01**2] * 3 + [0.1**2] * 3)
    C[0, 4] = C[4, 0] = (1 - eps) * 0.01 * 0.1
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Gaussian.Covariance(C)))
    pose = gtsam.Pose3()
    values.insert(X(0), pose)
    step = gtsam.Pose3(gtsam.Rot3.Rz(0.1), np.array([1.0, 0.0, 0.0]))
    for i in range(n):
        graph.add(gtsam.BetweenFactorPose3(X(i), X(i + 1), step, gtsam.noiseModel.Isotropic.Sigma(6, 0.01)))
        pose = pose.compose(step)
        values.insert(X(i + 1), pose)
    return graph, values


def test_qr_fallback_matches_dense_inverse():
    n = 20
    graph, values = _ill_conditioned_chain(n)
    with pytest.raises(RuntimeError, match="Indetermin"):
        gtsam.Marginals(graph, values).marginalCovariance(X(0))
    keys = [X(0), X(7), X(n)]
    covs = marginal_covariances(graph, values, keys)
    assert isinstance(covs, MarginalCovariances)
    assert covs.method == "qr" and not covs.singular and covs.warnings == []
    lin = graph.linearize(values)
    ordering = gtsam.Ordering()
    for i in range(n + 1):
        ordering.push_back(X(i))
    H, _ = lin.hessian(ordering)
    dense = np.linalg.inv(H)
    for k, i in zip(keys, (0, 7, n)):
        ref = dense[6 * i : 6 * i + 6, 6 * i : 6 * i + 6]
        assert np.all(np.isfinite(covs[k]))
        assert np.max(np.abs(covs[k] - ref)) / np.max(np.abs(ref)) < 1e-6


def test_singular_graph_never_crashes():
    """S0 and S1 are tied only to each other (a free pair), S3 is in no factor: inf along the
    free directions, finite and right elsewhere, flagged; the dense and the regularised paths
    agree."""
    graph, values = _ill_conditioned_chain(5)
    graph.add(gtsam.BetweenFactorPose3(S(0), S(1), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.1)))
    for k in (S(0), S(1), S(3)):
        values.insert(k, gtsam.Pose3())
    ref = marginal_covariances(_ill_conditioned_chain(5)[0], _ill_conditioned_chain(5)[1], [X(0), X(5)])
    results = [marginal_covariances(graph, values, [X(0), X(5), S(0), S(3)], dense_max_dim=dm) for dm in (2000, 10)]
    assert [r.method for r in results] == ["dense", "regularised"]
    for r in results:
        assert r.singular
        assert set(r.null_directions) == {S(0), S(3)}
        assert r.null_directions[S(0)].shape == (6, 6)
        assert np.all(np.isinf(np.diag(r[S(0)]))) and np.all(np.isinf(np.diag(r[S(3)])))
        assert len(r.warnings) == 2 and any("S0" in w for w in r.warnings)
        for k in (X(0), X(5)):
            assert np.all(np.isfinite(r[k]))
            assert np.max(np.abs(r[k] - ref[k])) / np.max(np.abs(ref[k])) < 1e-4


def test_partly_free_variable():
    """A pose with only an attitude factor: 4 free directions, 2 determined (dense path)."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.AttitudeFactorPose3(S(0), gtsam.Unit3(np.array([0.0, 0.0, -1.0])),
                                        gtsam.noiseModel.Isotropic.Sigma(2, 0.01),
                                        gtsam.Unit3(np.array([0.0, 0.0, -1.0]))))
    values.insert(S(0), gtsam.Pose3())
    covs = marginal_covariances(graph, values, [S(0)])
    assert covs.singular and covs.null_directions[S(0)].shape == (6, 4)
    d = np.diag(covs[S(0)])
    assert np.sum(np.isinf(d)) == 4
    np.testing.assert_allclose(d[np.isfinite(d)], [1e-4, 1e-4], rtol=1e-6)  # roll, pitch: 0.01 rad


# ----------------------------------------------------------------------------- body axes, Monte Carlo
def _random_cov(rng, sig_r=np.radians(1.0), sig_t=0.01):
    A = rng.normal(size=(6, 6))
    C = A @ A.T + 3 * np.eye(6)
    d = np.sqrt(np.diag(C))
    corr = C / np.outer(d, d)
    s = np.array([sig_r, 0.5 * sig_r, 2 * sig_r, sig_t, 2 * sig_t, 0.5 * sig_t])
    return corr * np.outer(s, s)


def test_body_axis_sigmas_against_monte_carlo():
    rng = np.random.default_rng(0)
    cov6 = _random_cov(rng)
    s_rot, s_xyz, corr, cov_body = body_axis_sigmas(T_BS, cov6)
    L = np.linalg.cholesky(cov6)
    xi = rng.normal(size=(20000, 6)) @ L.T
    R_hat, t_hat = T_BS[:3, :3], T_BS[:3, 3]
    err = np.empty((len(xi), 6))
    for i, x in enumerate(xi):
        T = T_BS @ se3_exp(x)  # right perturbation
        err[i, :3] = gtsam.Rot3.Logmap(gtsam.Rot3(T[:3, :3] @ R_hat.T))  # rotation error about body axes
        err[i, 3:] = T[:3, 3] - t_hat  # error of t_body_sensor, body axes
    mc_std = err.std(axis=0)
    np.testing.assert_allclose(s_rot, np.degrees(mc_std[:3]), rtol=0.05)
    np.testing.assert_allclose(s_xyz, 1e3 * mc_std[3:], rtol=0.05)
    np.testing.assert_allclose(corr, np.corrcoef(err.T), atol=0.05)
    np.testing.assert_allclose(np.diag(corr), 1.0)
    np.testing.assert_allclose(cov_body, _J(R_hat) @ cov6 @ _J(R_hat).T, rtol=1e-12, atol=1e-18)
    # gtsam.Pose3 input gives the same
    np.testing.assert_allclose(body_axis_sigmas(to_gtsam_pose(T_BS), cov6)[0], s_rot)


def test_body_axis_sigmas_with_infinite_component():
    cov6 = np.diag([1e-6] * 6)
    cov6[2, 2] = np.inf
    s_rot, s_xyz, corr, _ = body_axis_sigmas(T_BS, cov6)
    assert np.any(np.isinf(s_rot)) and np.all(np.isfinite(s_xyz))
    assert np.all(np.isfinite(corr))


# ----------------------------------------------------------------------------- NEES
def test_nees_of_gaussian_samples_averages_six():
    rng = np.random.default_rng(1)
    cov6 = _random_cov(rng)
    L = np.linalg.cholesky(cov6)
    T_est = T_BS
    values = []
    for _ in range(5000):
        xi = L @ rng.normal(size=6)
        T_true = T_est @ se3_exp(xi)  # the truth is a right perturbation of the estimate
        values.append(nees(T_true, T_est, cov6))
    values = np.array(values)
    assert values.mean() == pytest.approx(6.0, abs=0.3)
    assert np.var(values) == pytest.approx(12.0, rel=0.15)  # chi-square(6): variance 12
    # gtsam poses are accepted too
    assert nees(to_gtsam_pose(T_BS @ se3_exp(L @ np.ones(6))), to_gtsam_pose(T_BS), cov6) == pytest.approx(6.0, rel=1e-6)
