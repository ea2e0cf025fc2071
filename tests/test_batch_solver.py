"""Tests of graphcal.solvers.batch: the Python-driven Levenberg–Marquardt reaches gtsam's LM
optimum (Pose3 SLAM with a loop, gtsam's Pose2 example graphs, Huber factors with outliers, an
ill-conditioned but determined graph), refuses under-constrained graphs with a GraphcalError that
names the free variable, and lists outliers by a chi-square test on the unweighted Mahalanobis
distance. The 1,000-variable CustomFactor graph is timed in bench/batch_solver.py; here only its
optimum is checked.
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import S, X

from graphcal.errors import GraphcalError
from graphcal.solvers.batch import (
    LMResult,
    UnderdeterminedError,
    key_name,
    outlier_factors,
    solve_lm,
    whitened_errors,
)
from graphcal.testing import custom_point_graph, max_local_difference


def _gtsam_lm(graph, initial, max_iterations=200):
    p = gtsam.LevenbergMarquardtParams()
    p.setRelativeErrorTol(1e-15)
    p.setAbsoluteErrorTol(1e-15)
    p.setMaxIterations(max_iterations)
    return gtsam.LevenbergMarquardtOptimizer(graph, initial, p).optimize()


def _tight(graph, initial, **kw):
    return solve_lm(graph, initial, relative_tol=1e-15, absolute_tol=1e-15, **kw)


# ----------------------------------------------------------------------------- graphs
def _pose3_loop(n=12, seed=0):
    rng = np.random.default_rng(seed)
    graph, initial = gtsam.NonlinearFactorGraph(), gtsam.Values()
    odo = gtsam.noiseModel.Diagonal.Sigmas([0.02, 0.02, 0.02, 0.05, 0.05, 0.05])
    step = gtsam.Pose3(gtsam.Rot3.Ypr(2 * np.pi / n, 0.02, -0.01), np.array([1.0, 0.0, 0.05]))
    truth = [gtsam.Pose3()]
    for _ in range(n - 1):
        truth.append(truth[-1].compose(step))
    graph.add(gtsam.PriorFactorPose3(X(0), truth[0], gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))
    for i in range(n):
        j = (i + 1) % n  # the last one closes the loop
        meas = truth[i].between(truth[j]).compose(gtsam.Pose3.Expmap(rng.normal(scale=0.02, size=6)))
        graph.add(gtsam.BetweenFactorPose3(X(i), X(j), meas, odo))
    for i in range(n):
        initial.insert(X(i), truth[i].compose(gtsam.Pose3.Expmap(rng.normal(scale=0.15, size=6))))
    return graph, initial


def _pose2_example():
    """gtsam's Pose2SLAMExample_g2o data (noisyToyGraph.txt) with a prior on the first pose."""
    graph, initial = gtsam.readG2o(gtsam.findExampleDataFile("noisyToyGraph.txt"), False)
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), gtsam.noiseModel.Diagonal.Variances([1e-6, 1e-6, 1e-8])))
    return graph, initial


def _pose3_example():
    """gtsam's Pose3SLAMExample_g2o data (pose3example.txt) with a prior on the first pose."""
    graph, initial = gtsam.readG2o(gtsam.findExampleDataFile("pose3example.txt"), True)
    first = initial.atPose3(0)
    graph.add(gtsam.PriorFactorPose3(0, first, gtsam.noiseModel.Isotropic.Sigma(6, 1e-4)))
    return graph, initial


def _huber_graph(seed=3, n=30, outliers=(7, 15, 22)):
    """Pose2 chain with loop closures every 5 poses under a Huber loss; some closures are wrong."""
    rng = np.random.default_rng(seed)
    graph, initial = gtsam.NonlinearFactorGraph(), gtsam.Values()
    base = gtsam.noiseModel.Diagonal.Sigmas([0.05, 0.05, 0.02])
    huber = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.345), base)
    truth = [gtsam.Pose2(0.0, 0.0, 0.0)]
    for i in range(n - 1):
        truth.append(truth[-1].compose(gtsam.Pose2(1.0, 0.0, 0.21 * np.sin(0.3 * i))))
    graph.add(gtsam.PriorFactorPose2(0, truth[0], gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)))
    closure_index = {}
    for i in range(n - 1):
        meas = truth[i].between(truth[i + 1]).compose(gtsam.Pose2(*rng.normal(scale=[0.05, 0.05, 0.02])))
        graph.add(gtsam.BetweenFactorPose2(i, i + 1, meas, huber))
    for i in range(0, n - 5):
        meas = truth[i].between(truth[i + 5]).compose(gtsam.Pose2(*rng.normal(scale=[0.05, 0.05, 0.02])))
        if i in outliers:
            meas = meas.compose(gtsam.Pose2(1.5, -1.0, 0.6))
        closure_index[i] = graph.size()
        graph.add(gtsam.BetweenFactorPose2(i, i + 5, meas, huber))
    for i, T in enumerate(truth):
        initial.insert(i, T.compose(gtsam.Pose2(*rng.normal(scale=[0.2, 0.2, 0.05]))))
    return graph, initial, [closure_index[i] for i in outliers], closure_index


# ----------------------------------------------------------------------------- optimum = gtsam's
@pytest.mark.parametrize("make", [_pose3_loop, _pose2_example, _pose3_example], ids=["pose3-loop", "pose2-toy", "pose3-example"])
def test_matches_gtsam_lm(make):
    graph, initial = make()
    ref = _gtsam_lm(graph, initial)
    res = _tight(graph, initial)
    assert isinstance(res, LMResult)
    assert res.converged, res.message
    assert res.error_final <= res.error_initial
    assert res.error_final == pytest.approx(graph.error(ref), rel=1e-9, abs=1e-12)
    assert max_local_difference(ref, res.values) < 1e-6
    # the input is untouched
    assert initial.equals(make()[1], 1e-12)


def test_matches_gtsam_lm_with_huber_outliers():
    graph, initial, _, _ = _huber_graph()
    ref = _gtsam_lm(graph, initial)
    res = _tight(graph, initial)
    assert res.converged, res.message
    assert max_local_difference(ref, res.values) < 1e-6
    assert res.error_final == pytest.approx(graph.error(ref), rel=1e-9)


def test_default_tolerances_are_close_to_the_optimum():
    graph, initial = _pose3_loop(seed=5)
    ref = _gtsam_lm(graph, initial)
    res = solve_lm(graph, initial)
    assert res.converged
    assert max_local_difference(ref, res.values) < 1e-6


def test_ill_conditioned_but_determined_graph_is_solved():
    """gtsam's Cholesky refuses this clique (correlation 1 - 1e-9): the QR rank test must not
    call it under-constrained."""
    C = np.diag([0.01**2] * 3 + [0.1**2] * 3)
    C[0, 4] = C[4, 0] = (1 - 1e-9) * 0.01 * 0.1
    target = gtsam.Pose3(gtsam.Rot3.Rz(0.3), np.array([1.0, 2.0, 3.0]))
    graph, initial = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(X(0), target, gtsam.noiseModel.Gaussian.Covariance(C)))
    initial.insert(X(0), gtsam.Pose3())
    with pytest.raises(RuntimeError, match="Indetermin"):
        graph.linearize(initial).optimize()
    res = solve_lm(graph, initial)
    assert res.converged
    assert res.values.atPose3(X(0)).equals(target, 1e-9)


def test_progress_callback_sees_non_increasing_errors():
    graph, initial = _pose3_loop(seed=2)
    seen = []
    res = solve_lm(graph, initial, progress=lambda it, err: seen.append((it, err)))
    assert seen[0] == (0, pytest.approx(res.error_initial))
    assert [it for it, _ in seen] == list(range(len(seen)))
    errs = [e for _, e in seen]
    assert all(b <= a for a, b in zip(errs, errs[1:]))
    assert errs[-1] == pytest.approx(res.error_final)
    assert res.iterations == len(seen) - 1


def test_max_iterations_reported():
    graph, initial = _pose3_loop(seed=4)
    res = solve_lm(graph, initial, max_iterations=1)
    assert res.iterations == 1 and not res.converged
    assert "maximum iterations" in res.message


# ----------------------------------------------------------------------------- under-constrained
def test_under_constrained_variable_is_named():
    """S0 only has an attitude factor (2 of its 6 directions): a GraphcalError names "S0"."""
    graph, initial = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.01)))
    graph.add(gtsam.BetweenFactorPose3(X(0), X(1), gtsam.Pose3(gtsam.Rot3(), np.array([1.0, 0, 0])),
                                       gtsam.noiseModel.Isotropic.Sigma(6, 0.01)))
    graph.add(gtsam.AttitudeFactorPose3(S(0), gtsam.Unit3(np.array([0.0, 0.0, -1.0])),
                                        gtsam.noiseModel.Isotropic.Sigma(2, 0.01),
                                        gtsam.Unit3(np.array([0.0, 0.0, -1.0]))))
    for k in (X(0), X(1), S(0)):
        initial.insert(k, gtsam.Pose3())
    with pytest.raises(GraphcalError, match=r"\bS0\b") as info:
        solve_lm(graph, initial)
    assert isinstance(info.value, UnderdeterminedError)
    assert info.value.name == "S0" and info.value.key == S(0)
    assert "sensor extrinsic" in str(info.value)


def test_gauge_freedom_is_refused():
    """A pose loop without a prior: every pose is free up to a common transform."""
    graph, initial = gtsam.NonlinearFactorGraph(), gtsam.Values()
    noise = gtsam.noiseModel.Diagonal.Sigmas([0.2, 0.2, 0.1])
    for i in range(5):
        graph.add(gtsam.BetweenFactorPose2(X(i), X((i + 1) % 5), gtsam.Pose2(2.0, 0.0, 2 * np.pi / 5), noise))
        initial.insert(X(i), gtsam.Pose2(float(i), 0.1 * i, 0.3 * i))
    with pytest.raises(UnderdeterminedError, match=r"\bX[0-4]\b"):
        solve_lm(graph, initial)


def test_missing_initial_value():
    graph, initial = _pose3_loop()
    initial.erase(X(3))
    with pytest.raises(GraphcalError, match="X3"):
        solve_lm(graph, initial)


def test_key_name():
    assert key_name(S(0)) == "S0"
    assert key_name(X(12)) == "X12"
    assert key_name(5) == "5"


# ----------------------------------------------------------------------------- chi-square
def test_whitened_errors_undo_the_robust_loss():
    graph, initial, outlier_idx, closures = _huber_graph()
    values = _tight(graph, initial).values
    e = whitened_errors(graph, values)
    assert e.shape == (graph.size(),)
    for i in range(graph.size()):
        f = graph.at(i)
        nm = f.noiseModel()
        r = f.unwhitenedError(values)
        if isinstance(nm, gtsam.noiseModel.Robust):
            w = nm.noise().whiten(r)
            assert e[i] == pytest.approx(float(w @ w), rel=1e-12)
            assert e[i] >= 2 * f.error(values) - 1e-12  # Huber grows slower than the square
        else:
            assert e[i] == pytest.approx(2 * f.error(values), rel=1e-12)
    flagged = outlier_factors(graph, values, list(closures.values()), 3)
    assert set(outlier_idx) <= set(flagged)
    assert len(flagged) <= len(outlier_idx) + 2  # neighbours of a wrong closure may be pulled too
    # dof=None uses each factor's dimension (3 here): same answer
    assert outlier_factors(graph, values, list(closures.values()), None) == flagged
    # a subset of indices, in order
    sub = list(closures.values())[:3]
    np.testing.assert_allclose(whitened_errors(graph, values, sub), e[sub])


def test_whitened_errors_of_custom_factors():
    noise = gtsam.noiseModel.Isotropic.Sigma(2, 0.5)
    robust = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.0), noise)

    def err(this, values, H):
        x = values.atVector(this.keys()[0])
        if H is not None:
            H[0] = np.eye(2)
        return x - np.array([1.0, 2.0])

    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.CustomFactor(noise, [0], err))
    graph.add(gtsam.CustomFactor(robust, [0], err))
    values = gtsam.Values()
    values.insert(0, np.array([4.0, 2.0]))
    e = whitened_errors(graph, values)
    np.testing.assert_allclose(e, [36.0, 36.0])  # (3 / 0.5)^2 both, before the Huber loss
    assert 2 * graph.at(1).error(values) < 36.0


# ----------------------------------------------------------------------------- the graph bench/batch_solver.py times
@pytest.mark.slow
def test_same_optimum_as_gtsam_lm_on_1000_python_factors():
    """The graph of bench/batch_solver.py (which times the two): same optimum as gtsam's LM."""
    graph, initial = custom_point_graph()
    res = solve_lm(graph, initial)
    p = gtsam.LevenbergMarquardtParams()
    p.setRelativeErrorTol(1e-9)
    p.setAbsoluteErrorTol(1e-12)
    ref = gtsam.LevenbergMarquardtOptimizer(graph, initial, p).optimize()
    diff = max_local_difference(ref, res.values)
    assert res.converged
    assert diff < 1e-5  # both stop at relative error decrease 1e-9
