"""Variance-component estimation: the dense and the factor-by-factor (gtsam.Marginals) paths give
the same group scales, and a noise model that fits gives scales near 1."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

import graphcal.calibration.noise_estimation as ne
from graphcal.calibration.calibrate import solve_problem
from graphcal.calibration.graph import CalibrationOptions, build_problem
from graphcal.calibration.measurements import calibration_data
from graphcal.io.dataset import load_dataset_robot, read_dataset
from graphcal.simulation.session import SimulationConfig, simulate
from graphcal.simulation.write import write_simulation


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    res = simulate(SimulationConfig(robot="octopus", program="random", n_stations=15, seed=71, cloud_stride=8))
    folder = tmp_path_factory.mktemp("vce") / "ds"
    write_simulation(res, folder, output="planes")
    ds = read_dataset(folder)
    robot = load_dataset_robot(ds)
    return ds, robot, calibration_data(ds, robot)


@pytest.fixture(scope="module")
def problem(dataset):
    pb = build_problem(*dataset, CalibrationOptions())
    return pb, solve_problem(pb).values


def test_dense_and_marginals_paths_agree(problem, monkeypatch):
    pb, values = problem
    dense = ne.group_variances(pb.graph, values, pb.factor_groups, pb.factor_components)
    monkeypatch.setattr(ne, "DENSE_MAX_DIM", 0)
    sparse = ne.group_variances(pb.graph, values, pb.factor_groups, pb.factor_components)
    assert dense.keys() == sparse.keys()
    for g in dense:
        assert dense[g].scale == pytest.approx(sparse[g].scale, rel=1e-6)
        assert dense[g].redundancy == pytest.approx(sparse[g].redundancy, rel=1e-6)


def test_a_group_over_factors_of_different_variables(dataset, monkeypatch):
    """One leg's parameters estimated, the others fixed: the stance-foot group holds Python factors
    on (X, F, L) and built-in ones on (X, F). The per-block algebra of converged_scales gives the
    factor-by-factor (gtsam.Marginals) path's statistics, and its iterated scales are finite."""
    from graphcal.diagnosis.extensions import ModelExtensions

    ds, robot, data = dataset
    ext = ModelExtensions(leg_sigmas=((robot.feet[0], (0.01,) * 6),))
    mixed = build_problem(ds, robot, data, CalibrationOptions(), extensions=ext)
    kinds = {type(mixed.graph.at(i)).__name__ for i, g in mixed.factor_groups.items() if g == "stance_foot"}
    assert kinds == {"CustomFactor", "BearingRangeFactor3D"}
    v = solve_problem(mixed).values
    dense = ne.converged_scales(mixed.graph, v, mixed.factor_groups, mixed.factor_components,
                                eligible=lambda s: True, max_iterations=1).first
    monkeypatch.setattr(ne, "DENSE_MAX_DIM", 0)
    sparse = ne.group_variances(mixed.graph, v, mixed.factor_groups, mixed.factor_components)
    assert dense.keys() == sparse.keys() and "stance_foot/joint" in dense
    for g in dense:
        assert dense[g].scale == pytest.approx(sparse[g].scale, rel=1e-6), g
        assert dense[g].redundancy == pytest.approx(sparse[g].redundancy, rel=1e-6), g
    monkeypatch.undo()
    scale = ne.converged_scales(mixed.graph, v, mixed.factor_groups, mixed.factor_components,
                                   eligible=lambda s: s.redundancy > 3).scales
    assert scale and all(np.isfinite(x) and x > 0 for x in scale.values())


def test_default_noise_is_far_too_large_for_the_simulator(problem):
    """The defaults (0.1 deg joints, 1 mm contact, 0.5 deg IMU) are 5-15x the simulator's noise:
    every well-determined group's scale says so (and redundancies are positive, below the rows)."""
    pb, values = problem
    stats = ne.group_variances(pb.graph, values, pb.factor_groups, pb.factor_components)
    for g in ("stance_foot/joint", "imu"):
        assert 0.0 < stats[g].redundancy < stats[g].rows
        assert stats[g].scale < 0.5


# ----------------------------------------------------------------------------- two components, known truth
def _two_component_data(rng, n=600):
    """A Point3 measured ``n`` times with noise ``0.25 Sigma_joint_i + 4 Sigma_contact`` (Sigma_joint_i
    a random rank-2, leg-Jacobian-like covariance; Sigma_contact isotropic): (x_true, z, Sigma_joint,
    Sigma_contact)."""
    x_true = np.array([0.3, -0.2, 0.5])
    J = rng.normal(size=(n, 3, 2))
    S_joint = J @ np.swapaxes(J, 1, 2) * 1e-4  # (n, 3, 3), rank 2
    S_contact = np.broadcast_to(np.eye(3) * 1e-4, (n, 3, 3))
    true_cov = 0.25 * S_joint + 4.0 * S_contact  # truth: scales 0.5 (joint) and 2 (contact)
    z = x_true + np.einsum("nij,nj->ni", np.linalg.cholesky(true_cov), rng.normal(size=(n, 3)))
    return (x_true, z, S_joint, S_contact)


def _build(data, theta):
    """The graph of :func:`_two_component_data` believing the variances ``theta`` x the components:
    (graph, solved values, groups, components)."""
    import gtsam

    x_true, z, S_joint, S_contact = data
    graph, groups, comps = gtsam.NonlinearFactorGraph(), {}, {}
    for i in range(len(z)):
        Sj, Sc = theta[0] * S_joint[i], theta[1] * S_contact[i]
        groups[graph.size()] = "foot"
        comps[graph.size()] = {"joint": Sj, "contact": Sc}
        graph.add(gtsam.PriorFactorPoint3(0, z[i], gtsam.noiseModel.Gaussian.Covariance(Sj + Sc)))
    values = gtsam.Values()
    values.insert(0, np.asarray(z.mean(axis=0)))
    values = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    return graph, values, groups, comps


def _always(v):
    return True


def test_two_components_recovered_from_a_known_mixture():
    """The variance components of a sum of two covariances (joint noise through a Jacobian plus
    isotropic contact noise) are recovered (truth: sigma scales 0.5 and 2). A component must be
    carried into the whitened space with the whitening the linearisation used (GTSAM's R, not
    another square root of the information): with another root this fails."""
    data = _two_component_data(np.random.default_rng(3))
    graph, values, groups, comps = _build(data, (1.0, 1.0))
    scale = ne.converged_scales(graph, values, groups, comps, eligible=_always).scales
    assert scale["foot/joint"] == pytest.approx(0.5, rel=0.1)
    assert scale["foot/contact"] == pytest.approx(2.0, rel=0.1)


def test_components_read_a_correct_model_as_correct_when_factors_share_variables(monkeypatch):
    """Helmert's matrix summed from each factor's own block of R misses the blocks between factors
    of the group that share a variable (three feet on one body pose): 200 points each measured
    three times with the true two-component noise then read the contact component's theta 2.00
    (joint 1.01) where it is 1, as the Octopus's stance feet learned a contact noise the simulator
    does not have (docs/calibration.md, "Clean NEES"). With its rows scaled to the redundancies the
    fixed point is Förstner's: measured 1.02 and 1.08, dense and sparse paths alike."""
    rng = np.random.default_rng(5)
    n, k = 200, 3
    J = rng.normal(size=(n * k, 3, 2))
    S_joint = J @ np.swapaxes(J, 1, 2) * 1e-4
    S_contact = np.broadcast_to(np.eye(3) * 1e-4, (n * k, 3, 3))
    graph, groups, comps = gtsam.NonlinearFactorGraph(), {}, {}
    values = gtsam.Values()
    for s in range(n):
        x = rng.normal(size=3)
        for j in range(s * k, (s + 1) * k):
            cov = S_joint[j] + S_contact[j]
            z = x + np.linalg.cholesky(cov) @ rng.normal(size=3)
            groups[graph.size()] = "foot"
            comps[graph.size()] = {"joint": S_joint[j], "contact": S_contact[j]}
            graph.add(gtsam.PriorFactorPoint3(s, z, gtsam.noiseModel.Gaussian.Covariance(cov)))
        values.insert(s, x)
    values = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    dense = ne.group_variances(graph, values, groups, comps)
    for key in ("foot/joint", "foot/contact"):
        assert 0.85 < dense[key].helmert_theta < 1.15, (key, dense[key])
    monkeypatch.setattr(ne, "DENSE_MAX_DIM", 0)
    sparse = ne.group_variances(graph, values, groups, comps)
    for key in ("foot/joint", "foot/contact"):
        assert sparse[key].helmert_theta == pytest.approx(dense[key].helmert_theta, rel=1e-6)


def _mixture(rng, n, theta_joint, theta_contact, joint_size):
    """Like :func:`_two_component_data`, with the truth's variance factors and the joint
    component's size (variance per unit of its random rank-2 factor) as arguments."""
    x_true = np.array([0.3, -0.2, 0.5])
    J = rng.normal(size=(n, 3, 2))
    S_joint = J @ np.swapaxes(J, 1, 2) * joint_size
    S_contact = np.broadcast_to(np.eye(3) * 1e-4, (n, 3, 3))
    true_cov = theta_joint * S_joint + theta_contact * S_contact + 1e-14 * np.eye(3)
    z = x_true + np.einsum("nij,nj->ni", np.linalg.cholesky(true_cov), rng.normal(size=(n, 3)))
    return (x_true, z, S_joint, S_contact)


_BOUNDS = {"foot/joint": (0.02, 50.0), "foot/contact": (0.02, 50.0)}


def test_an_undetermined_split_shares_one_scale(monkeypatch):
    """A foot whose noise is all joint noise, 100x smaller than the assumed contact noise, seen 40
    times: the data cannot tell the two apart (Helmert's theta of the joint component has a
    standard deviation > SPLIT_MAX_THETA_STD), so both keep their ratio and share one scale, and
    each names the other. Split anyway, the joint component lands on its bound (0.02), where it
    carries no redundancy and stays (the audit's false 'covariance may be too small')."""
    graph, values, groups, comps = _build(_mixture(np.random.default_rng(0), 40, 1.0, 0.0, 1e-5), (1.0, 1.0))
    res = ne.converged_scales(graph, values, groups, comps, eligible=_always, bounds=_BOUNDS)
    assert res.scales["foot/joint"] == pytest.approx(res.scales["foot/contact"], rel=1e-12)
    assert 0.1 < res.scales["foot/joint"] < 0.9  # learned down from the defaults, not to a bound
    assert res.first["foot/joint"].shared_with == ("foot/contact",)
    assert res.first["foot/contact"].shared_with == ("foot/joint",)
    # the sparse (gtsam.Marginals) path decides the same
    monkeypatch.setattr(ne, "DENSE_MAX_DIM", 0)
    sparse = ne.group_variances(graph, values, groups, comps)
    assert sparse["foot/joint"].shared_with == ("foot/contact",)
    assert sparse["foot/joint"].helmert_theta == pytest.approx(res.first["foot/joint"].helmert_theta, rel=1e-6)
    monkeypatch.undo()
    monkeypatch.setattr(ne, "SPLIT_MAX_THETA_STD", np.inf)
    forced = ne.converged_scales(graph, values, groups, comps, eligible=_always, bounds=_BOUNDS)
    assert forced.first["foot/joint"].shared_with == ()
    assert min(forced.scales.values()) == pytest.approx(0.02)


def test_converged_scales_are_the_fixed_point_of_repeated_solves(monkeypatch):
    """Iterating on one linearisation reaches what repeated one-step updates with a re-solve of
    the graph reach (a linear problem: the two must agree). The split is held determined in both:
    each one-step call decides it afresh, and this mixture's first step overshoots (joint 0.33)
    to a ratio where it looks undetermined, while the iteration decides once, at the start."""
    monkeypatch.setattr(ne, "split_determined", lambda N: True)
    data = _two_component_data(np.random.default_rng(4))
    graph, values, groups, comps = _build(data, (1.0, 1.0))
    scale = ne.converged_scales(graph, values, groups, comps, eligible=_always, tolerance=1e-6, max_iterations=200).scales
    theta = np.array([1.0, 1.0])
    for _ in range(300):
        g, v, gr, co = _build(data, tuple(theta))
        step = ne.converged_scales(g, v, gr, co, eligible=_always, max_iterations=1).scales
        theta *= np.array([step["foot/joint"], step["foot/contact"]]) ** 2
    assert np.sqrt(theta) == pytest.approx([scale["foot/joint"], scale["foot/contact"]], rel=1e-3)
    # and one step alone is not there yet (the iteration is needed)
    one = ne.converged_scales(graph, values, groups, comps, eligible=_always, max_iterations=1).scales
    assert abs(one["foot/contact"] / scale["foot/contact"] - 1.0) > 0.01


def test_settled_ends_the_iteration_after_the_first_update(monkeypatch):
    """``settled(first) -> True`` stops after the first iteration with no scale updated and the
    first iteration's statistics unchanged (calibrate's confirming call reads only those);
    ``settled -> False`` changes nothing."""
    data = _two_component_data(np.random.default_rng(6))
    graph, values, groups, comps = _build(data, (1.0, 1.0))
    solves = []
    solve = ne._ArrowLayout.solve
    monkeypatch.setattr(ne._ArrowLayout, "solve", lambda *a: solves.append(1) or solve(*a))
    full = ne.converged_scales(graph, values, groups, comps, eligible=_always)
    n_full = len(solves)
    assert n_full > 2  # this mixture needs several iterations
    seen = []
    stopped = ne.converged_scales(graph, values, groups, comps, eligible=_always,
                                  settled=lambda first: seen.append(first) or True)
    assert len(solves) - n_full == 1 and stopped.scales == {}
    assert seen == [stopped.first]
    for k, v in full.first.items():
        assert stopped.first[k] == v
    kept = ne.converged_scales(graph, values, groups, comps, eligible=_always, settled=lambda first: False)
    assert kept.scales == full.scales


def test_the_step_is_the_optimum_with_the_new_weights():
    """converged_scales' step from ``values`` lands on the optimum of the graph re-weighted with its
    scales (this graph is linear in its variable, so exactly); calibrate starts its re-solve there."""
    data = _two_component_data(np.random.default_rng(5))
    graph, values, groups, comps = _build(data, (1.0, 1.0))
    res = ne.converged_scales(graph, values, groups, comps, eligible=_always, tolerance=1e-9, max_iterations=500)
    _, reweighted, _, _ = _build(data, (res.scales["foot/joint"] ** 2, res.scales["foot/contact"] ** 2))
    moved = np.asarray(reweighted.atPoint3(0)) - np.asarray(values.atPoint3(0))
    assert np.linalg.norm(moved) > 1e-5  # the weights do move the optimum
    np.testing.assert_allclose(np.asarray(values.retract(res.step).atPoint3(0)), np.asarray(reweighted.atPoint3(0)),
                               rtol=0, atol=1e-6 * np.linalg.norm(moved))


def test_large_graphs_fall_back_to_one_update_from_the_marginals(problem, monkeypatch):
    """Above DENSE_MAX_DIM converged_scales makes the single update of the factor-by-factor
    marginals (gtsam.Marginals), and that update equals the dense first iteration."""
    pb, values = problem
    dense_one = ne.converged_scales(pb.graph, values, pb.factor_groups, pb.factor_components,
                                       eligible=_always, max_iterations=1).scales
    monkeypatch.setattr(ne, "DENSE_MAX_DIM", 0)
    fallback = ne.converged_scales(pb.graph, values, pb.factor_groups, pb.factor_components,
                                      eligible=_always, max_iterations=50).scales
    assert fallback.keys() == dense_one.keys()
    assert fallback == pytest.approx(dense_one, rel=1e-6)


# ----------------------------------------------------------------------------- the arrow-shaped inverse
def _arrow_matrix(rng, m=7, d=6, g=5):
    """A random positive-definite normal matrix of m local variables (d columns each, coupled only
    through g global columns), its local column indices (shuffled among the globals) and globals."""
    n = m * d + g
    cols = rng.permutation(n)
    local, glob = cols[: m * d].reshape(m, d), np.sort(cols[m * d:])
    rows = []
    for i in range(m):  # each local variable's factors: its own columns and the globals
        A = np.zeros((d + 4, n))
        A[:, local[i]] = rng.normal(size=(d + 4, d))
        A[:, glob] = rng.normal(size=(d + 4, g))
        rows.append(A)
    prior = np.zeros((g, n))
    prior[:, glob] = np.eye(g)
    A = np.vstack(rows + [prior])
    return A.T @ A, local, glob


def _arrow_inverse(H, rhs, local, global_cols):
    """``(H^-1, H^-1 rhs)`` of a dense normal matrix through ne._ArrowLayout (what converged_scales
    computes in blocks, scattered back into n x n; the blocks between two local variables, which no
    factor reads, stay zero)."""
    n = len(H)
    lay = ne._ArrowLayout(n, local, global_cols)
    cols = np.arange(n)[None, :]
    tgt = lay.h_target(cols)[0]
    keep = tgt >= 0
    H_flat = np.zeros(lay.size)
    H_flat[tgt[keep]] = H[keep]
    Sigma_flat, delta = lay.solve(H_flat, rhs)
    src = lay.sigma_source(cols)[0]
    return np.where(src >= 0, Sigma_flat[np.maximum(src, 0)], 0.0), delta


def test_arrow_inverse_equals_the_dense_inverse_where_factors_read_it():
    rng = np.random.default_rng(11)
    H, local, glob = _arrow_matrix(rng)
    rhs = rng.normal(size=len(H))
    Sigma, delta = _arrow_inverse(H, rhs, {local.shape[1]: local}, glob)
    dense = np.linalg.inv(H)
    np.testing.assert_allclose(delta, dense @ rhs, rtol=1e-9, atol=1e-12)
    for i in range(len(local)):  # every block a factor can read: its local variable and the globals
        cols = np.r_[local[i], glob]
        np.testing.assert_allclose(Sigma[np.ix_(cols, cols)], dense[np.ix_(cols, cols)], rtol=1e-9, atol=1e-12)
    # the split finds the locals of such a graph: no two share a factor, the shared ones are global
    columns = {k: list(range(6 * k, 6 * k + 6)) for k in range(7)}
    columns.update({7 + j: [42 + j] for j in range(5)})
    factor_keys = [(i, 7 + j) for i in range(7) for j in range(5)]
    by_dim, g = ne._arrow_split(columns, factor_keys)
    assert sorted(map(tuple, by_dim[6].tolist())) == [tuple(c) for c in list(columns.values())[:7]]
    assert g.tolist() == list(range(42, 47))
    # no locals at all: the dense inverse
    Sigma0, delta0 = _arrow_inverse(H, rhs, {}, np.arange(len(H)))
    np.testing.assert_allclose(Sigma0, dense, rtol=1e-9, atol=1e-12)


def test_arrow_inverse_refuses_an_undetermined_variable():
    rng = np.random.default_rng(12)
    H, local, glob = _arrow_matrix(rng)
    H = H.copy()
    c = local[2, 0]
    H[c, :] = H[:, c] = 0.0  # a local variable's direction without information
    with pytest.raises(ne.GraphcalError, match="undetermined"):
        _arrow_inverse(H, np.ones(len(H)), {local.shape[1]: local}, glob)
    H2, local2, glob2 = _arrow_matrix(rng)
    H2 = H2.copy()
    H2[np.ix_(glob2, glob2)] -= 1e3 * np.eye(len(glob2))  # the globals' Schur complement is not positive
    with pytest.raises(ne.GraphcalError, match="undetermined"):
        _arrow_inverse(H2, np.ones(len(H2)), {local2.shape[1]: local2}, glob2)


def test_noise_groups_report_names_how_each_sigma_was_set():
    """The status of every group and the warning only where a held sigma is too small for its
    residuals (the covariance could then be too small); a held sigma that is too large is not."""
    import dataclasses

    from graphcal.calibration.noise_estimation import VCE_FLOOR, noise_groups_report

    opts = dataclasses.replace(CalibrationOptions(), sigma_contact_m=VCE_FLOOR["sigma_contact_m"])
    stats = {
        "imu": ne.GroupVariance("imu", chi2=100.0, redundancy=100.0, rows=104),  # fits
        "foot_on_ground": ne.GroupVariance("foot_on_ground", chi2=0.2, redundancy=2.7, rows=6),  # few dof, small
        "commanded": ne.GroupVariance("commanded", chi2=30.0, redundancy=2.5, rows=6),  # few dof, large
        "stance_foot/contact": ne.GroupVariance("stance_foot/contact", 1.0, 100.0, 900, helmert_theta=0.25),
        "stance_foot/joint": ne.GroupVariance("stance_foot/joint", 1.0, 400.0, 900, helmert_theta=2.25),
        "plane:depth": ne.GroupVariance("plane:depth", chi2=80.0, redundancy=80.0, rows=156),
    }
    groups, warnings = noise_groups_report(stats, opts)
    by = {g.group: g for g in groups}
    assert {k: g.status for k, g in by.items()} == {
        "imu": "learned", "foot_on_ground": "too few dof", "commanded": "too few dof",
        "stance_foot/contact": "at floor", "stance_foot/joint": "not converged", "plane:depth": "learned"}
    assert by["foot_on_ground"].data_scale == pytest.approx(np.sqrt(0.2 / 2.7))
    assert by["stance_foot/joint"].data_scale == pytest.approx(1.5)
    assert by["commanded"].fields == (("sigma_commanded_rad", opts.sigma_commanded_rad),
                                      ("sigma_commanded_m", opts.sigma_commanded_m))
    assert by["plane:depth"].fields == (("plane_scale:depth", 1.0),)
    assert by["imu"].p_high == pytest.approx(0.48, abs=0.02)
    # the held group with residuals 3.5x its sigma (p ~ 1e-6) and the joint component 1.5x its sigma
    # over 400 dof are warned about; the held group below its sigma and the floored one are not
    assert len(warnings) == 2
    assert warnings[0].startswith("noise group commanded (too few dof, 2.5 dof)")
    assert "stance_foot/joint (not converged" in warnings[1]
    assert all("may be too small" in w for w in warnings)
    # a group with ~0 dof (one station: its plane's 3 rows are spent on the body pose) and residuals
    # below its sigma: a chi-square of 2e-5 dof puts its mass at 0, p_high is tiny whatever the scale,
    # and it was warned about ("0.058 times its sigma ... may be too small"); now not
    stats0 = {"plane:depth": ne.GroupVariance("plane:depth", chi2=0.058**2 * 2e-5, redundancy=2e-5, rows=3)}
    groups0, warnings0 = noise_groups_report(stats0, opts)
    assert groups0[0].status == "too few dof" and groups0[0].p_high < 1e-3
    assert warnings0 == []


def test_components_scaled_together_are_reported_as_one():
    """Components that share one scale (an undetermined split) are learned together: status
    'learned', each names the other, no warning; the console says so in words and
    calibration.yaml records ``scaled_with``."""
    from graphcal.calibration.noise_estimation import noise_groups_report

    N = np.array([[7.3, 35.9], [35.9, 288.8]])  # the audit's hexapod at its fixed point
    assert not ne.split_determined(N)  # joint: sqrt(2 (N^-1)_00) = 0.84
    assert ne.split_determined(N * 20)  # 20x the data: 0.19
    red = [2.0, 80.0]
    Nc = ne.consistent_helmert_matrix(N, red)  # rows scaled to the redundancies (Förstner's fixed point)
    np.testing.assert_allclose(Nc.sum(axis=1), red)
    q = Nc @ [1.0, 1.02]
    stats = ne.helmert_components("stance_foot", ["joint", "contact"], N, q, red, 720, split=False)
    # shared: the single-component formula for their sum, chi-square over redundancy
    assert stats["stance_foot/joint"].helmert_theta == pytest.approx(q.sum() / 82.0)
    assert stats["stance_foot/joint"].chi2 == stats["stance_foot/contact"].chi2 == pytest.approx(q.sum())
    groups, warnings = noise_groups_report(stats, CalibrationOptions())
    by = {g.group: g for g in groups}
    assert by["stance_foot/joint"].status == by["stance_foot/contact"].status == "learned"
    assert by["stance_foot/joint"].dof == pytest.approx(82.0)
    assert by["stance_foot/joint"].shared_with == ("stance_foot/contact",)
    assert warnings == []


def test_calibrate_reports_components_scaled_together(tmp_path):
    """End to end on 8 simulated stations (planes only), where the feet's joint and contact noise
    are not separated by the data: the console says so, calibration.yaml records ``scaled_with``
    for both components, and nothing warns that the covariance may be too small."""
    import yaml

    from graphcal.cli import main

    res = simulate(SimulationConfig(robot="octopus", program="random", n_stations=8, seed=71, cloud_stride=8))
    write_simulation(res, tmp_path / "ds", output="planes")
    import contextlib
    import io
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["calibrate", str(tmp_path / "ds"), "--out", str(tmp_path / "cal"), "--quiet"]) == 0
    text = out.getvalue()
    assert "contact and joints noise scaled together: the data do not separate them" in text
    doc = yaml.safe_load((tmp_path / "cal" / "calibration.yaml").read_text())
    est = doc["noise_estimation"]
    assert est["stance_foot/joint"]["scaled_with"] == ["stance_foot/contact"]
    assert est["stance_foot/contact"]["scaled_with"] == ["stance_foot/joint"]
    assert est["stance_foot/joint"]["status"] == "learned"
    assert "scaled_with" not in est["imu"]
    assert not any("may be too small" in w for w in doc["warnings"])



@pytest.mark.parametrize("dense", [True, False])
def test_redundancy_and_chi2_of_two_groups_measuring_one_point(dense, monkeypatch):
    """Absolute numbers, computed here in closed form: one 3-D point measured n_a times with sigma_a
    and n_b times with sigma_b. Each coordinate's hat diagonal is w_i / W (w = 1 / sigma^2,
    W = n_a w_a + n_b w_b), so a group's redundancy is 3 n_g (1 - w_g / W) (together 3 (n - 1)),
    and its chi-square the sum of its squared whitened residuals at the weighted mean."""
    monkeypatch.setattr(ne, "_is_dense", lambda graph, values: dense)
    rng = np.random.default_rng(5)
    n_a, n_b, s_a, s_b = 7, 4, 0.01, 0.03
    z = np.r_[rng.normal(scale=s_a, size=(n_a, 3)), rng.normal(scale=s_b, size=(n_b, 3))] + [1.0, 2.0, 3.0]
    sig = np.r_[np.full(n_a, s_a), np.full(n_b, s_b)]
    graph, groups = gtsam.NonlinearFactorGraph(), {}
    for i, (zi, si) in enumerate(zip(z, sig)):
        groups[i] = "a" if i < n_a else "b"
        graph.add(gtsam.PriorFactorPoint3(0, zi, gtsam.noiseModel.Isotropic.Sigma(3, si)))
    w = 1.0 / sig**2
    x_hat = (w[:, None] * z).sum(axis=0) / w.sum()
    values = gtsam.Values()
    values.insert(0, x_hat)
    out = ne.group_variances(graph, values, groups)
    W = w.sum()
    for g, sl, wg in (("a", slice(0, n_a), 1 / s_a**2), ("b", slice(n_a, None), 1 / s_b**2)):
        n_g = sl.indices(len(z))[1] - sl.indices(len(z))[0]
        assert out[g].redundancy == pytest.approx(3 * n_g * (1 - wg / W), rel=1e-9)
        assert out[g].chi2 == pytest.approx(float((((z[sl] - x_hat) / sig[sl, None]) ** 2).sum()), rel=1e-9)
        assert out[g].rows == 3 * n_g
    assert out["a"].redundancy + out["b"].redundancy == pytest.approx(3 * (len(z) - 1), rel=1e-9)
