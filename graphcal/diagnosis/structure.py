"""Structure left in a model, judged against PHYSICAL noise, in every measurement group.

The diagnosis loop learns noise from the residuals (model.py); a learned sigma swallows exactly
the misfit a missing cause leaves (measured: a 20 mm plate under two feet left the learned
foot-height group at chi2/dof ~1, and was named a 6.7 mm session offset). Here the model is solved
again with the noise fixed at its physical values -- the sigmas dataset.yaml declares, else the
documented defaults of :class:`graphcal.calibration.graph.CalibrationOptions` (joint 0.1 deg,
contact 1 mm, foot height 3 mm, IMU 0.5 deg, commanded pose 1 deg / 10 mm, laser 10 mm; planes:
their own covariance from planes.csv, else the plane group's default) -- and each group's
chi-square is tested against its redundancy (the variance-component statistics of
noise_estimation.py, Bonferroni over the groups). The defaults are conservative (on clean
simulated data every group's chi2/dof is 0.01-0.15, measured), so a group that fails this test
carries misfit no honest noise explains; planes without covariance are covered like any group.

For each group its whitened residual components are correlated with physically meaningful
regressors (:data:`REGRESSORS`): station order (drift), each session and each leg (one-hot), the
plane's range and range^2 (sensor error models), the foot's horizontal reach (the lever of the
weight on the leg's joints: compliance) and the body tilt (the contact point rolling on a round
foot). The strongest correlation (Bonferroni over components and regressors) is reported with its
p-value: it points to the cause a model lacks, without claiming one. A group whose strongest
correlation passes :data:`REGRESSOR_ALPHA` (times the groups) carries structure too, even when its
chi-square passes: a depth error growing with range^2 (k = 0.01/m) left the plane group at chi2/dof
0.44 but its residuals correlated with the range at r = -0.7 (measured).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy.special import stdtr
from scipy.stats import chi2 as chi2_dist

__all__ = ["GroupTest", "physical_structure", "STRUCTURE_ALPHA", "MIN_EXCESS", "REGRESSOR_ALPHA", "REGRESSORS"]

#: family-wise level of the per-group test (divided by the number of groups)
STRUCTURE_ALPHA = 1e-3
#: a group fails only when its chi2/dof also exceeds this (a significant but tiny excess over
#: conservative defaults is not structure worth reporting)
MIN_EXCESS = 1.5
#: family-wise level of the regressor test (its Bonferroni p over components x regressors, times
#: the groups): a group whose whitened residuals correlate with a regressor this strongly carries
#: structure even where its chi-square passes (conservative noise defaults hide small misfits)
REGRESSOR_ALPHA = 1e-3
#: the regressors tried for each group
REGRESSORS = ("station order", "session", "leg", "range", "range^2", "reach", "tilt")


@dataclass(frozen=True)
class GroupTest:
    """One measurement group's test at physical noise.

    Attributes:
        group: noise group ("plane:<sensor>", "stance_foot", "foot_on_ground", "imu", "commanded").
        chi2, redundancy: its chi-square and degrees of freedom (redundancy numbers) at the fit.
        p_value: chi-square upper tail; structure: fails at STRUCTURE_ALPHA / groups and chi2/dof >
            MIN_EXCESS, or its best regressor passes REGRESSOR_ALPHA / groups.
        regressor: the best-correlated regressor ("" if none), correlation: its Pearson r,
            regressor_p: its Bonferroni p-value (over components x regressors), component: which
            whitened component of the group's residual.
        points: (regressor value, whitened residual) pairs of that best correlation, for the plot.
    """

    group: str
    chi2: float
    redundancy: float
    p_value: float
    structure: bool
    regressor: str = ""
    correlation: float = float("nan")
    regressor_p: float = float("nan")
    component: int = -1
    points: tuple = ()

    @property
    def ratio(self) -> float:
        return float(self.chi2 / self.redundancy) if self.redundancy > 0 else float("nan")

    def to_dict(self) -> dict:
        return {"group": self.group, "chi2": float(self.chi2), "redundancy": float(self.redundancy),
                "chi2_per_dof": self.ratio, "p_value": float(self.p_value), "structure": bool(self.structure),
                "regressor": self.regressor, "correlation": float(self.correlation),
                "regressor_p": float(self.regressor_p), "component": int(self.component)}


def physical_structure(model, values, problem_fit=None) -> tuple[tuple[GroupTest, ...], object, object]:
    """(one :class:`GroupTest` per group, problem, values) of ``model`` (a DiagnosisModel) solved
    from ``values`` with its noise at the physical values (module docstring). The regressors are
    correlated with the residuals of ``problem_fit`` at ``values`` (the fit the findings were made
    in, its noise learned: there the sensors' planes place the body no more than they should) when
    given, else with those of the physical-noise fit."""
    from graphcal.calibration.noise_estimation import group_variances
    from graphcal.diagnosis.model import model_options

    phys = dataclasses.replace(model, options=model_options(model.ds))
    problem, vals = phys.solve(initial=values)
    stats = group_variances(problem.graph, vals, problem.factor_groups)
    n_groups = max(sum(1 for v in stats.values() if v.redundancy >= 1.0), 1)
    out = []
    for g, v in sorted(stats.items()):
        if v.redundancy < 1.0:
            continue
        p = float(chi2_dist.sf(v.chi2, v.redundancy))
        bad = p * n_groups < STRUCTURE_ALPHA and v.chi2 / v.redundancy > MIN_EXCESS
        test = GroupTest(g, float(v.chi2), float(v.redundancy), p, bool(bad))
        test = _best_regressor(test, model, problem_fit, values) if problem_fit is not None else \
            _best_regressor(test, phys, problem, vals)
        if test.regressor_p * n_groups < REGRESSOR_ALPHA:  # a pattern no honest noise makes, whatever its size
            test = dataclasses.replace(test, structure=True)
        out.append(test)
    return tuple(out), problem, vals


def _factor_table(model, problem, values, group: str):
    """(whitened residuals (n, dim), regressors: name -> (n,) values) of the group's factors."""
    from graphcal.calibration.kinematic_pose import leg_kinematics
    from graphcal.factors.keys import F
    from graphcal.geometry import from_gtsam_pose

    idx = [i for i, g in problem.factor_groups.items() if g == group]
    x_station = {int(k): st for st, k in problem.station_keys.items()}
    order = {st.station: j for j, st in enumerate(model.data.stations)}
    session_of = {st.station: st.session for st in model.data.stations}
    from graphcal.calibration.graph import planted_foot_index

    sessions = list(dict.fromkeys(session_of.values()))
    foot_of = {int(F(j)): (s, f) for (s, f), j in planted_foot_index(model.data, model.robot).items()}
    kin = leg_kinematics(model.data, model.robot) if group == "stance_foot" else {}
    rows, reg = [], {}
    for i in idx:
        fac = problem.graph.at(i)
        w = np.asarray(fac.noiseModel().whiten(np.asarray(fac.unwhitenedError(values), float).reshape(-1)), float)
        keys = [int(k) for k in fac.keys()]
        st = next((x_station[k] for k in keys if k in x_station), None)
        sf = next((foot_of[k] for k in keys if k in foot_of), None)
        if st is None and i in problem.plane_factors:
            st = problem.plane_factors[i][0]
        r = {}
        if st is not None:
            r["station order"] = float(order[st])
            for s in sessions:
                r[f"session={s}"] = float(session_of[st] == s)
            T = from_gtsam_pose(values.atPose3(problem.station_keys[st]))
            r["tilt"] = float(np.degrees(np.arccos(np.clip(T[2, 2], -1.0, 1.0))))
        elif sf is not None:
            for s in sessions:
                r[f"session={s}"] = float(sf[0] == s)
        if sf is not None:
            for f in model.robot.feet:
                r[f"leg={f}"] = float(sf[1] == f)
            if st is not None and (st, sf[1]) in kin:
                r["reach"] = float(np.linalg.norm(kin[(st, sf[1])][0][:2]))
        if i in problem.plane_factors and problem.plane_factors[i] in model.data.planes:
            d = float(model.data.planes[problem.plane_factors[i]].d)
            r["range"], r["range^2"] = d, d * d
        rows.append(w)
        for k, v in r.items():
            reg.setdefault(k, {})[len(rows) - 1] = v
    dim = max((len(w) for w in rows), default=0)
    W = np.full((len(rows), dim), np.nan)
    for a, w in enumerate(rows):
        W[a, :len(w)] = w
    regs = {}
    for k, m in reg.items():
        if len(m) == len(rows):
            regs[k] = np.array([m[a] for a in range(len(rows))])
    return W, regs


def _best_regressor(test: GroupTest, model, problem, values) -> GroupTest:
    """``test`` with the regressor its whitened residual components correlate with most."""
    W, regs = _factor_table(model, problem, values, test.group)
    if W.shape[0] < 5 or not regs:
        return test
    best = None
    n_tests = 0
    for name, x in regs.items():
        if np.std(x) <= 0:
            continue
        for c in range(W.shape[1]):
            y = W[:, c]
            ok = np.isfinite(y)
            if ok.sum() < 5 or np.std(y[ok]) <= 0:
                continue
            n_tests += 1
            r = float(np.corrcoef(x[ok], y[ok])[0, 1])
            n = int(ok.sum())
            tstat = r * np.sqrt(max(n - 2, 1) / max(1.0 - r * r, 1e-12))
            p = float(2.0 * stdtr(max(n - 2, 1), -abs(tstat)))  # Student's t upper tail, as scipy.stats.t.sf
            if best is None or p < best[0]:
                best = (p, name, r, c, tuple(zip(x[ok].tolist(), y[ok].tolist())))
    if best is None:
        return test
    p, name, r, c, pts = best
    return dataclasses.replace(test, regressor=name, correlation=r, regressor_p=min(1.0, p * n_tests), component=c,
                               points=pts)
