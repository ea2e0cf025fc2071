"""Bookkeeping finder (graphcal/diagnosis/bookkeeping.py): sensor planes and laser scans filed under
the wrong station (two stations' data exchanged, a plane under another station) and sign / convention / unit
errors of single planes (a normal component's sign, the opposite (n, d) convention, d in mm or cm).

Per camera, every plane is compared with the ground each station predicts without that camera's
planes (plane_corrections.py: the stance feet, or the commanded pose) at physical noise:

1. Gate (cheap): the extrinsic fitted to the planes as labelled (Gauss-Newton from the CAD prior,
   Huber-weighted), each plane's chi-square (3 dof) at its labelled station. Nothing more is done
   unless some plane fails at the Bonferroni level ``GATE_ALPHA / n_planes``.
2. Association: a cost matrix of every plane at every station of the dataset (rectangular: stations
   without this camera's data included), ``scipy.optimize.linear_sum_assignment``, alternating with
   the extrinsic re-fitted to the assigned inliers until the assignment is stable; started twice --
   from the labelled fit and from the CAD prior (with its covariance in the costs: when most labels
   are wrong the labelled fit is no start) -- the lower total cost kept.
3. Decisions, at the final extrinsic: every plane that fails at its label is matched (planes that
   pass keep their station) over the free stations and the variants of plane_corrections.PLANE_VARIANTS.
   A correction is made only when the corrected plane passes at physical noise
   (p >= ``PASS_P``) and beats every other (station, variant) by ``MIN_CONFIDENCE`` in chi-square;
   otherwise a note names the candidates the data cannot tell apart (e.g. poses differing only in
   yaw, which a ground plane cannot see). A plane that fits no station where the best association
   puts it (p < ``PASS_P``) is noted as an outlier without forcing it to its other places (they fit
   worse still).

Laser scans go through the same search with one variant (as given): their range errors at every
station (scan_association.py); swaps and misfiled scans are found, no sign or unit variants.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.stats import chi2 as chi2_dist

from graphcal.diagnosis.correction import Correction
from graphcal.diagnosis.plane_corrections import (
    PLANE_VARIANTS,
    StationGrounds,
    chi2_rows,
    fit_extrinsic,
    plane_rows,
    plane_variant,
    prior_residual,
    station_grounds,
)
from graphcal.diagnosis.scan_association import fit_scan_extrinsic, scan_beams, scan_chi2
from graphcal.factors.plane_observation import tangent_basis

__all__ = ["find_associations", "GATE_ALPHA", "PASS_P", "MIN_CONFIDENCE"]

log = logging.getLogger(__name__)

#: family-wise level of the gate: some plane fails at its labelled station at physical noise
GATE_ALPHA = 1e-3
#: a corrected plane passes at physical noise when its chi-square's tail probability is at least this
PASS_P = 1e-3
#: a correction beats the next-best explanation by at least this much chi-square (likelihood ratio e^6)
MIN_CONFIDENCE = 12.0
#: a measurement is an inlier of the extrinsic fit when its chi-square's tail probability is above
#: this (3 dof: chi-square 21)
INLIER_P = 1e-4
#: assignment costs are capped (+ a slow growth) so that gross outliers do not steer the others
COST_CAP = 60.0
#: assignment penalty of a plane moved off its label, and of a variant (chi-square units)
MOVE_PENALTY = 4.0
VARIANT_PENALTY = 6.0
MAX_ROUNDS = 12
#: when few planes fail at the labelled fit, only those below this p-value there may move or change
ACTIVE_P = 0.01
#: chi-square of a plane that may not move, anywhere but at its label
FAR = 1e6
#: beyond this share of planes failing under the best association, the model does not fit (a
#: physical cause for the diagnosis loop): nothing is corrected (measured: a joint compliance on the
#: qingzhui left 31 of 48 planes failing, and "corrected" the sign of a 0.0014 normal component)
MAX_FAIL_SHARE = 0.2
#: a normal component's sign is tested only when flipping it turns the normal by at least
#: 2 asin(this) (~6 deg): a smaller flip is within what a physical cause can mimic
MIN_SIGN_COMPONENT = 0.05
#: forced alternatives tried per changed plane (its next-best (station, variant) options)
N_OPTIONS = 6
#: times the decisions restart from a better solution found by a forced alternative
MAX_RESTARTS = 3


def find_associations(model, say, initial=None) -> tuple:
    """(corrections, corrected data, notes) for the nominal ``model`` (a DiagnosisModel with its
    noise learned); see the module docstring and graphcal/diagnosis/bookkeeping.py. ``initial``: not
    used (the association is searched in closed form, without a solve)."""
    from graphcal.calibration.calibrate import dataset_physical_noise
    from graphcal.diagnosis.model import model_options

    data, ds = model.data, model.ds
    physical, _ = dataset_physical_noise(ds, model.options)
    corrections: list = []
    notes: list = []
    out = {"planes": dict(data.planes), "scan_points": dict(data.scan_points)}
    grounds = None
    for sensor in model.sensors():
        for field, kind in (("planes", "plane"), ("scan_points", "scan")):
            keys = [(st.station, sensor) for st in data.stations if (st.station, sensor) in getattr(data, field)]
            if len(keys) < 3:
                continue
            if grounds is None:
                grounds = station_grounds(data, model.robot, physical)
            if kind == "plane":
                cam = _camera(ds, sensor, [data.planes[k] for k in keys], grounds)
            else:
                cam = _scanner(ds, sensor, data, keys, grounds, model_options(ds).sigma_scan_m)
            found, moved, said = search(sensor, cam, say)
            corrections += found
            notes += said
            if found:
                for k in keys:
                    out[field].pop(k, None)
                out[field].update(moved)
    if not corrections:
        return (), data, tuple(notes)
    return tuple(corrections), dataclasses.replace(data, **out), tuple(notes)


def _prior(ds, sensor: str) -> tuple:
    p = ds.sensors[sensor].T_body_sensor_prior
    return p.matrix, float(p.sigma_m), float(p.sigma_rad)


@dataclass(frozen=True, eq=False)
class _Camera:
    """One camera's planes: ``meas`` (N PlaneMeasurements), ``labels`` (N,) their stations' indices
    into ``g`` (StationGrounds, M stations), every variant's ``n`` (V, N, 3), ``d`` (V, N), ``cov3``
    (V, N, 3, 3); ``prior`` (T_cad, sigma_m, sigma_rad); ``B`` (V, N, 3, 2) the normals' tangent
    bases; ``active`` (N,) the planes that may move or change (the others stay as given at their
    label: their cost elsewhere is :data:`FAR`)."""

    meas: list
    labels: np.ndarray
    g: object
    n: np.ndarray
    d: np.ndarray
    cov3: np.ndarray
    prior: tuple
    B: np.ndarray
    active: np.ndarray
    kind: str = "plane"

    def at_labels(self, T, cov_S=None) -> np.ndarray:
        """(N,) chi-square of every plane as given at its label."""
        g, j = self.g, self.labels
        return chi2_rows(self.n[0], self.d[0], self.cov3[0], g.u[j], g.z[j], g.W[j], g.cov[j], T, cov_S, B=self.B[0])

    def chi(self, T, cov_S=None) -> np.ndarray:
        """(V, N, M) chi-square of every variant of every active plane at every station (:data:`FAR`
        for the others, except as given at their label)."""
        act = np.flatnonzero(self.active)
        v, n, m = self.d.shape[0], len(act), len(self.g.ids)
        full = np.full((v, len(self.meas), m), FAR)
        full[0, np.arange(len(self.meas)), self.labels] = self.at_labels(T, cov_S)
        if n:
            *rows, B = self._pairs
            full[:, act] = chi2_rows(*rows, T, cov_S, B=B).reshape(v, n, m)
        return full

    @functools.cached_property
    def _pairs(self) -> tuple:
        """chi2_rows' arguments but the extrinsic, then the planes' tangent bases, for every (variant,
        active plane, station): the planes repeated over the stations, the stations tiled over the
        planes (made once: every alternation round reads them)."""
        act = np.flatnonzero(self.active)
        v, n, m = self.d.shape[0], len(act), len(self.g.ids)
        rep = lambda a: np.repeat(a[:, act].reshape(v * n, *a.shape[2:]), m, axis=0)  # noqa: E731
        tile = lambda a: np.tile(a, (v * n,) + (1,) * (a.ndim - 1))  # noqa: E731
        return (rep(self.n), rep(self.d), rep(self.cov3), tile(self.g.u), tile(self.g.z), tile(self.g.W),
                tile(self.g.cov), rep(self.B))

    def score(self, chi: np.ndarray) -> np.ndarray:
        """(V, N, M) assignment cost: robust chi-square + the variant's and the move's penalty."""
        sc = np.where(chi < COST_CAP, chi, COST_CAP + np.sqrt(np.maximum(chi - COST_CAP, 0.0)))
        sc = sc + VARIANT_PENALTY + MOVE_PENALTY
        sc[0] -= VARIANT_PENALTY
        sc[:, np.arange(len(self.meas)), self.labels] -= MOVE_PENALTY
        for v, (cause, detail) in enumerate(PLANE_VARIANTS):
            if cause == "normal_sign":
                small = np.abs(self.n[0][:, "xyz".index(detail)]) < MIN_SIGN_COMPONENT
                sc[v, small] = 1e9
        return sc

    def prior_cost(self, T) -> float:
        return prior_cost(self.prior, T)

    @property
    def dof(self) -> np.ndarray:
        """(N,) degrees of freedom of each measurement's chi-square."""
        return np.full(len(self.meas), 3)

    def fit(self, var: np.ndarray, use: np.ndarray, assign: np.ndarray, T0) -> np.ndarray:
        """The extrinsic (4x4) fitted from ``T0`` to the planes ``use`` as variants ``var[use]`` at
        the stations ``assign[use]``."""
        T, _, _ = fit_extrinsic(self.n[var[use], use], self.d[var[use], use], self.cov3[var[use], use], self.g,
                                assign[use], T0, self.prior, B=self.B[var[use], use])
        return T

    def corrected(self, i: int, v: int, station: int):
        """Plane ``i`` as variant ``v`` at ``station`` (a new PlaneMeasurement)."""
        return dataclasses.replace(self.meas[i], station=station, n=self.n[v, i], d=float(self.d[v, i]))


def prior_cost(prior: tuple, T) -> float:
    """The CAD prior's chi-square (6 dof) of the extrinsic ``T`` (4x4); ``prior`` (T_cad, sigma_m,
    sigma_rad)."""
    T_cad, sig_m, sig_rad = prior
    r = prior_residual(T, T_cad) / np.repeat([max(sig_rad, 1e-4), max(sig_m, 1e-4)], 3)
    return float(r @ r)


def _camera(ds, sensor, meas, g) -> _Camera:
    index = {int(s): j for j, s in enumerate(g.ids)}
    ns, ds_, cs = [], [], []
    for v in PLANE_VARIANTS:
        nd = [plane_variant(m.n, m.d, v) for m in meas]
        n, d, c3 = plane_rows(np.array([x[0] for x in nd]), [x[1] for x in nd], [m.cov for m in meas])
        ns.append(n)
        ds_.append(d)
        cs.append(c3)
    B = np.array([[tangent_basis(x) for x in n] for n in ns])
    return _Camera(list(meas), np.array([index[m.station] for m in meas]), g, np.array(ns), np.array(ds_),
                   np.array(cs), _prior(ds, sensor), B, np.ones(len(meas), dtype=bool))


@dataclass(frozen=True, eq=False)
class _Scanner:
    """One laser scanner's scans, with :class:`_Camera`'s methods (one variant: as given):
    ``meas`` (N :class:`ScanMeasurement`), ``labels``, ``g``, ``beams`` [(D, rho), ...]
    (scan_association.scan_beams), ``sigma`` the range noise (m), ``prior``, ``active``."""

    meas: list
    labels: np.ndarray
    g: object
    beams: list
    sigma: float
    prior: tuple
    active: np.ndarray
    kind: str = "scan"

    @property
    def dof(self) -> np.ndarray:
        return np.array([len(r) for _, r in self.beams])

    def at_labels(self, T, cov_S=None) -> np.ndarray:
        g = self.g
        out = np.empty(len(self.meas))
        for i, ((D, rho), j) in enumerate(zip(self.beams, self.labels)):
            sub = StationGrounds(g.ids[j:j + 1], g.u[j:j + 1], g.z[j:j + 1], g.W[j:j + 1], g.cov[j:j + 1], ())
            out[i] = scan_chi2(D, rho, sub, T, self.sigma, cov_S)[0]
        return out

    def chi(self, T, cov_S=None) -> np.ndarray:
        full = np.full((1, len(self.meas), len(self.g.ids)), FAR)
        full[0, np.arange(len(self.meas)), self.labels] = self.at_labels(T, cov_S)
        for i in np.flatnonzero(self.active):
            full[0, i] = scan_chi2(*self.beams[i], self.g, T, self.sigma, cov_S)
        return full

    def score(self, chi: np.ndarray) -> np.ndarray:
        x = chi - self.dof[None, :, None]  # the chi-square beyond its expectation: scans differ in size
        sc = np.where(x < COST_CAP, x, COST_CAP + np.sqrt(np.maximum(x - COST_CAP, 0.0))) + MOVE_PENALTY
        sc[:, np.arange(len(self.meas)), self.labels] -= MOVE_PENALTY
        return sc

    def prior_cost(self, T) -> float:
        return prior_cost(self.prior, T)

    def fit(self, var, use, assign, T0) -> np.ndarray:
        return fit_scan_extrinsic([self.beams[i] for i in use], assign[use], self.g, T0, self.prior, self.sigma)

    def corrected(self, i: int, v: int, station: int):
        return self.meas[i].points


@dataclass(frozen=True, eq=False)
class ScanMeasurement:
    """A laser scan at ``station``: its points (K, 3) in the sensor frame (m)."""

    station: int
    points: np.ndarray


def _scanner(ds, sensor, data, keys, g, sigma: float) -> _Scanner:
    index = {int(s): j for j, s in enumerate(g.ids)}
    meas = [ScanMeasurement(k[0], data.scan_points[k]) for k in keys]
    return _Scanner(meas, np.array([index[m.station] for m in meas]), g, [scan_beams(m.points) for m in meas],
                    sigma, _prior(ds, sensor), np.ones(len(meas), dtype=bool))


def _assign(cam: _Camera, sc: np.ndarray, forced=None) -> tuple:
    """(station index (N,), variant index (N,), total cost) minimising ``sc`` (V, N, M); ``forced``
    (i, j, v): plane i at station j as variant v."""
    best_v = sc.argmin(axis=0)
    cm = sc.min(axis=0)
    if forced is not None:
        i, j, v = forced
        cm[i] = 1e12
        cm[i, j], best_v[i, j] = sc[v, i, j], v
    rows, cols = linear_sum_assignment(cm)
    assign = np.empty(len(cam.meas), dtype=int)
    assign[rows] = cols
    var = best_v[np.arange(len(assign)), assign]
    return assign, var, float(cm[rows, cols].sum())


def _alternate(cam: _Camera, T0, cov_S0, forced=None) -> tuple:
    """(T, assignment (N,), variants (N,), objective) of the alternation from (T0, cov_S0): assign
    at the current extrinsic, refit the extrinsic to the assigned inliers, until stable."""
    T, cov_S, prev = T0, cov_S0, None
    idx = np.arange(len(cam.meas))
    for _ in range(MAX_ROUNDS):
        chi = cam.chi(T, cov_S)
        assign, var, _ = _assign(cam, cam.score(chi), forced)
        if prev is not None and np.array_equal(assign, prev[0]) and np.array_equal(var, prev[1]):
            break
        prev = (assign, var)
        inl = chi2_dist.sf(chi[var, idx, assign], cam.dof) > INLIER_P
        if inl.sum() < 3:
            inl[:] = True
        use = np.flatnonzero(inl)
        T = cam.fit(var, use, assign, T)
        cov_S = None
    assign, var, total = _assign(cam, cam.score(cam.chi(T)), forced)
    return T, assign, var, total + cam.prior_cost(T)


def search(sensor, cam, say) -> tuple:
    """(corrections, {(station, sensor): corrected measurement}, notes) of one sensor's
    measurements ``cam`` (a :class:`_Camera`, or a scanner's with the same methods; module docstring)."""
    meas = cam.meas
    T_cad, sig_m, sig_rad = cam.prior
    n = len(meas)
    idx = np.arange(n)
    T = cam.fit(np.zeros(n, dtype=int), idx, cam.labels, T_cad)
    p_label = chi2_dist.sf(cam.at_labels(T), cam.dof)
    unchanged = {(m.station, sensor): cam.corrected(i, 0, m.station) for i, m in enumerate(meas)}
    failing = p_label < GATE_ALPHA / n
    if not failing.any():
        return [], unchanged, []
    say(f"association: {sensor}: {int(failing.sum())} of {n} measurements do not fit their labelled station "
        f"at physical noise; searching the association")
    if failing.mean() <= MAX_FAIL_SHARE:
        # the labelled fit is sound: only the planes it doubts may move or change
        cam = dataclasses.replace(cam, active=p_label < ACTIVE_P)
    cov_prior = np.diag([max(sig_rad, 1e-4) ** 2] * 3 + [max(sig_m, 1e-4) ** 2] * 3)
    best = min((_alternate(cam, T, None), _alternate(cam, T_cad, cov_prior)), key=lambda r: r[3])
    still = chi2_dist.sf(cam.chi(best[0])[best[2], idx, best[1]], cam.dof) < GATE_ALPHA / n
    if still.mean() > MAX_FAIL_SHARE:
        # most planes fit no station under any association: the model (a physical cause), not the labels
        say(f"association: {sensor}: {int(still.sum())} of {n} measurements fit no station at physical noise under "
            f"the best association: the model, not the bookkeeping; nothing corrected")
        return [], unchanged, []
    for attempt in range(MAX_RESTARTS + 1):  # a forced alternative better than the best restarts from it
        decisions, better = _decide(cam, best, restart=attempt < MAX_RESTARTS)
        if better is None:
            break
        best = better
    found, planes, notes = _report(sensor, cam, best, decisions)
    if decisions and not np.isfinite(_scatter(cam.chi(best[0])[best[2], idx, best[1]], cam.dof, len(decisions))):
        # every confidence is 0: nothing corrected; the per-plane notes and the association as a hypothesis
        return [], unchanged, notes + [_hypothesis_note(sensor, cam, best)]
    return found, planes, notes


def _hypothesis_note(sensor, cam: _Camera, best) -> str:
    """The best association as a hypothesis, when no redundancy is left to judge it by."""
    _, assign, var, _ = best
    moved = [f"{m.station} -> {_option(cam.g, assign[i], var[i])}" for i, m in enumerate(cam.meas)
             if assign[i] != cam.labels[i] or var[i]]
    return (f"{sensor}: the {cam.kind}s do not fit their labelled stations; the best association found relocates "
            f"{len(moved)} of {len(cam.meas)} ({'; '.join(moved)}) and leaves no redundancy to judge it "
            f"(each relocated plane is fitted about as well as by a free parameter, the extrinsic by the rest): "
            f"a hypothesis, not corrected")


def _decide(cam: _Camera, best, restart: bool = True) -> tuple:
    """({plane index: (confidence, alternatives [(station index, variant index), ...])} for every
    plane the best solution changes, a better solution found on the way or None). The confidence
    of a change is the objective's rise when the plane is forced to its next-best (station,
    variant) -- the plane as given at its label among them -- with the extrinsic and every other
    plane's association refitted, divided by the scatter of the best solution's inliers when it
    exceeds physical noise (chi-square per degree of freedom > 1: the data are never trusted more
    than their own scatter allows). Without ``restart`` a better solution counts as a rise of 0. A
    plane that fits no station where the best solution puts it (p < :data:`PASS_P`) is not forced
    anywhere: it is never corrected (:func:`_report` notes it as an outlier), so its confidence is 0."""
    T, assign, var, total = best
    chi = cam.chi(T)
    sc = cam.score(chi)
    changed = int(np.sum((assign != cam.labels) | (var != 0)))
    scale = _scatter(chi[var, np.arange(len(assign)), assign], cam.dof, changed)
    out = {}
    for i in range(len(cam.meas)):
        if assign[i] == cam.labels[i] and var[i] == 0:
            continue
        if chi2_dist.sf(chi[var[i], i, assign[i]], cam.dof[i]) < PASS_P:
            # it fits no station where the best solution puts it: an outlier, never corrected
            # (_report notes it whatever its confidence); its next-best places are worse still
            out[i] = (0.0, [])
            continue
        row = sc[:, i].copy()
        row[var[i], assign[i]] = np.inf
        flat = np.argsort(row, axis=None)[:N_OPTIONS]
        options = {tuple(int(x) for x in np.unravel_index(f, row.shape)) for f in flat}
        options.add((0, int(cam.labels[i])))
        rises, alts = [], []
        for v, j in sorted(options):
            alt = _alternate(cam, T, None, forced=(i, j, v))
            if alt[3] < total - 1e-6 and restart:
                return out, alt
            rise = max(alt[3] - total, 0.0)
            rises.append(rise / scale if np.isfinite(scale) else 0.0)
            if (rise / scale if np.isfinite(scale) else rise) < MIN_CONFIDENCE:
                alts.append((j, v))  # without redundancy: the candidates as the raw margin sees them
        out[i] = (float(min(rises)), alts)
    return out, None


def _scatter(chi: np.ndarray, dof: np.ndarray, changed: int) -> float:
    """max(1, chi-square per degree of freedom) of the inlier planes' ``chi`` (3 dof each; 6 taken
    by the extrinsic and 3 by each plane the association changed: a plane free to go to any station
    is fitted about as well as by a free parameter); ``inf`` when no degree of freedom is left (no
    redundancy to judge a change by: measured on Chai's six printed planes, five of them moved)."""
    inl = chi2_dist.sf(chi, dof) > INLIER_P
    left = int(dof[inl].sum()) - 6 - 3 * changed
    return max(1.0, float(chi[inl].sum()) / left) if left > 0 else np.inf


def _report(sensor, cam: _Camera, best, decisions) -> tuple:
    """Corrections, corrected planes and notes from the best solution and the decisions."""
    T, assign, var, _ = best
    g, meas = cam.g, cam.meas
    chi = cam.chi(T)
    idx = np.arange(len(meas))
    at_label = chi[0, idx, cam.labels]
    chi_new = chi[var, idx, assign]
    notes, accepted = [], {}
    for i, (conf, alts) in decisions.items():
        label = meas[i].station
        if chi2_dist.sf(chi_new[i], cam.dof[i]) < PASS_P:
            how = " as given or with a sign, convention or unit corrected" if cam.kind == "plane" else ""
            notes.append(f"{sensor}: the {cam.kind} labelled station {label} fits no free station at physical "
                         f"noise{how} (chi-square {at_label[i]:.0f} at its label): an outlier (or a copy of another "
                         f"station's data), or a cause of the model")
        elif conf < MIN_CONFIDENCE:
            cands = [(assign[i], var[i])] + alts
            txt = ", ".join(_option(g, j, v) for j, v in cands[:8])
            shared = {v for _, v in cands}
            also = ""
            if len(shared) == 1 and var[i]:
                also = f"; in every one {' '.join(PLANE_VARIANTS[var[i]])} (the station, not the variant, is unsure)"
            more = "" if len(cands) <= 8 else ", ..."
            notes.append(f"{sensor}: the {cam.kind} labelled station {label} (chi-square {at_label[i]:.0f} there) does "
                         f"not fit it; the data cannot tell between (the best found) {txt}{more}{also}: not corrected")
        else:
            accepted[i] = (conf, alts)
    accepted = _without_conflicts(cam, assign, accepted, notes, sensor)
    corrections, planes = _corrections(sensor, cam, assign, var, at_label, chi_new, accepted)
    return corrections, planes, notes


def _option(g, j, v) -> str:
    cause, detail = PLANE_VARIANTS[v]
    return f"station {int(g.ids[j])}" + (f" ({cause} {detail})" if cause else "")


def _without_conflicts(cam, assign, accepted, notes, sensor) -> dict:
    """The accepted changes less those whose station another plane keeps (its own change not made)."""
    while True:
        final = {i: (assign[i] if i in accepted else cam.labels[i]) for i in range(len(cam.meas))}
        taken: dict = {}
        for i, j in final.items():
            taken.setdefault(j, []).append(i)
        clash = [i for js in taken.values() if len(js) > 1 for i in js if i in accepted]
        if not clash:
            return accepted
        for i in clash:
            notes.append(f"{sensor}: the {cam.kind} labelled station {cam.meas[i].station} belongs to station "
                         f"{int(cam.g.ids[assign[i]])}, whose own {cam.kind} could not be placed: not corrected")
            accepted.pop(i)


def _corrections(sensor, cam, assign, var, at_label, chi_new, accepted) -> tuple:
    """(Corrections, corrected planes) of the accepted changes {plane index: (confidence, alternatives)}."""
    g, meas = cam.g, cam.meas
    planes = {(m.station, sensor): cam.corrected(i, 0, m.station) for i, m in enumerate(meas) if i not in accepted}
    station_of = {i: int(g.ids[assign[i]]) for i in accepted}
    corrections, done = [], set()
    for i, (conf, alts) in accepted.items():
        m = meas[i]
        new_station = station_of[i]
        drop = float(at_label[i] - chi_new[i])
        common = dict(statistic=drop, dof=3, p_value=float(chi2_dist.sf(max(drop, 0.0), 3)), confidence=conf,
                      alternatives=tuple(_option(g, j, v) for j, v in alts))
        if new_station != m.station and i not in done:
            partner = [k for k in accepted if k != i and meas[k].station == new_station and station_of[k] == m.station]
            if partner:
                k = partner[0]
                done |= {i, k}
                pair = tuple(sorted((m.station, new_station)))
                common.update(statistic=drop + float(at_label[k] - chi_new[k]), dof=6,
                              confidence=min(conf, accepted[k][0]))
                common["p_value"] = float(chi2_dist.sf(max(common["statistic"], 0.0), 6))
                corrections.append(Correction("stations_exchanged", (("sensor", sensor), ("stations", pair)),
                                              (("stations", pair),), note=f"{sensor}: the {cam.kind}s of stations "
                                              f"{pair[0]} and {pair[1]} are exchanged", **common))
            elif i not in done:
                corrections.append(Correction(
                    "station_mislabelled", (("from_station", m.station), ("sensor", sensor), ("station", new_station)),
                    (("station_given", m.station), ("station_corrected", new_station)),
                    note=f"{sensor}: the {cam.kind} labelled station {m.station} belongs to station {new_station}",
                    **common))
        if var[i]:
            n_new, d_new = cam.n[var[i], i], float(cam.d[var[i], i])
            cause, detail = PLANE_VARIANTS[var[i]]
            corrected = {"normal_sign": (("component", detail), ("n_given", tuple(m.n)), ("n_corrected", tuple(n_new))),
                         "plane_convention": (("n_given", tuple(m.n)), ("n_corrected", tuple(n_new))),
                         "distance_unit": (("unit_given", detail), ("d_given_m", m.d), ("d_corrected_m", d_new))}[cause]
            corrections.append(Correction(
                cause, (("sensor", sensor), ("station", new_station)), corrected,
                note=f"{sensor}: the plane of station {new_station}: {cause} ({detail}) corrected", **common))
        planes[(new_station, sensor)] = cam.corrected(i, var[i], new_station)
    return corrections, planes
