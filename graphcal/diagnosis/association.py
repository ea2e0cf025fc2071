"""Bookkeeping finder (graphcal/diagnosis/bookkeeping.py): sensor planes filed under the wrong
station (two stations' data exchanged, a plane under another station) and sign / convention / unit
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
   yaw, which a ground plane cannot see).

Laser scans are not examined (their points fit no single plane variant; a note says so when the
scans fail at their stations).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.stats import chi2 as chi2_dist

from graphcal.diagnosis.bookkeeping import Correction
from graphcal.diagnosis.plane_corrections import (PLANE_VARIANTS, chi2_at_stations, fit_extrinsic, plane_variant,
                                                  station_grounds)

__all__ = ["find_associations", "GATE_ALPHA", "PASS_P", "MIN_CONFIDENCE"]

log = logging.getLogger(__name__)

#: family-wise level of the gate: some plane fails at its labelled station at physical noise
GATE_ALPHA = 1e-3
#: a corrected plane passes at physical noise when its chi-square's tail probability is at least this
PASS_P = 1e-3
#: a correction beats the next-best explanation by at least this much chi-square (likelihood ratio e^6)
MIN_CONFIDENCE = 12.0
#: a plane is an inlier of the extrinsic fit when its chi-square is below this (3 dof, p ~ 1e-4)
INLIER_CHI2 = 21.0
#: assignment costs are capped (+ a slow growth) so that gross outliers do not steer the others
COST_CAP = 60.0
#: assignment penalty of a plane moved off its label, and of a variant (chi-square units)
MOVE_PENALTY = 4.0
VARIANT_PENALTY = 6.0
MAX_ROUNDS = 12


def find_associations(model, say) -> tuple:
    """(corrections, corrected data, notes) for the nominal ``model`` (a DiagnosisModel with its
    noise learned); see the module docstring and graphcal/diagnosis/bookkeeping.py."""
    from graphcal.calibration.calibrate import dataset_physical_noise

    data, ds = model.data, model.ds
    physical, _ = dataset_physical_noise(ds, model.options)
    corrections: list = []
    notes: list = []
    planes = dict(data.planes)
    grounds = None
    for sensor in model.sensors():
        keys = [(st.station, sensor) for st in data.stations if (st.station, sensor) in data.planes]
        if len(keys) < 3:
            continue
        if grounds is None:
            grounds = station_grounds(data, model.robot, physical)
        found, moved, said = _sensor(ds, sensor, [data.planes[k] for k in keys], grounds, physical, say)
        corrections += found
        notes += said
        for k in keys:
            planes.pop(k, None)
        planes.update(moved)
    if any(k[1] for k in data.scan_points):
        log.debug("association: laser scans are not examined")
    if not corrections:
        return (), data, tuple(notes)
    return tuple(corrections), dataclasses.replace(data, planes=planes), tuple(notes)


def _prior(ds, sensor: str) -> tuple:
    p = ds.sensors[sensor].T_body_sensor_prior
    return p.matrix, float(p.sigma_m), float(p.sigma_rad)


def _costs(meas, g, T, cov_S, variant=("", "")) -> np.ndarray:
    """(N, M) chi-square of every plane (as ``variant`` corrects it) at every station."""
    out = np.empty((len(meas), len(g.ids)))
    for i, m in enumerate(meas):
        n, d = plane_variant(m.n, m.d, variant)
        out[i] = chi2_at_stations(n, d, m.cov, g, T, cov_S)
    return out


def _robust(c: np.ndarray) -> np.ndarray:
    return np.where(c < COST_CAP, c, COST_CAP + np.sqrt(np.maximum(c - COST_CAP, 0.0)))


def _alternate(meas, labels, g, T0, cov_S0, prior) -> tuple:
    """(T, cov_S, assignment (N,) station indices, total cost) of the alternation from (T0, cov_S0)."""
    T, cov_S, assign = T0, cov_S0, None
    total = np.inf
    for _ in range(MAX_ROUNDS):
        cost = _costs(meas, g, T, cov_S)
        rc = _robust(cost) + MOVE_PENALTY
        rc[np.arange(len(meas)), labels] -= MOVE_PENALTY
        rows, cols = linear_sum_assignment(rc)
        new = np.empty(len(meas), dtype=int)
        new[rows] = cols
        total = float(rc[rows, cols].sum())
        inl = cost[np.arange(len(meas)), new] < INLIER_CHI2
        if inl.sum() < 3:
            inl = np.ones(len(meas), dtype=bool)
        use = np.flatnonzero(inl)
        T, cov_S = fit_extrinsic([(meas[i].n, meas[i].d, meas[i].cov) for i in use], g, new[use], T, prior)
        if assign is not None and np.array_equal(new, assign):
            break
        assign = new
    return T, cov_S, assign, total


def _sensor(ds, sensor, meas, g, physical, say) -> tuple:
    """(corrections, {(station, sensor): corrected PlaneMeasurement}, notes) of one camera."""
    prior = _prior(ds, sensor)
    T_cad, sig_m, sig_rad = prior
    index = {int(s): j for j, s in enumerate(g.ids)}
    labels = np.array([index[m.station] for m in meas])
    n = len(meas)
    T, cov_S = fit_extrinsic([(m.n, m.d, m.cov) for m in meas], g, labels, T_cad, prior)
    at_label = _costs(meas, g, T, cov_S)[np.arange(n), labels]
    failing = chi2_dist.sf(at_label, 3) < GATE_ALPHA / n
    unchanged = {(m.station, sensor): m for m in meas}
    if not failing.any():
        return [], unchanged, []
    say(f"association: {sensor}: {int(failing.sum())} of {n} planes do not fit their labelled station at "
        f"physical noise; searching the association")
    cov_prior = np.diag([max(sig_rad, 1e-4) ** 2] * 3 + [max(sig_m, 1e-4) ** 2] * 3)
    runs = [_alternate(meas, labels, g, T, cov_S, prior), _alternate(meas, labels, g, T_cad, cov_prior, prior)]
    T, cov_S, _, _ = min(runs, key=lambda r: r[3])
    return _decide(sensor, meas, labels, g, T, cov_S)


def _decide(sensor, meas, labels, g, T, cov_S) -> tuple:
    """The corrections at the final extrinsic (module docstring, step 3)."""
    n, m_st = len(meas), len(g.ids)
    chi = np.array([_costs(meas, g, T, cov_S, v) for v in PLANE_VARIANTS])  # (V, N, M)
    at_label = chi[0, np.arange(n), labels]
    failing = chi2_dist.sf(at_label, 3) < GATE_ALPHA / n
    moved = {(m.station, sensor): m for m in meas}
    if not failing.any():
        return [], moved, []
    score = _robust(chi) + VARIANT_PENALTY
    score[0] -= VARIANT_PENALTY
    score += MOVE_PENALTY
    score[:, np.arange(n), labels] -= MOVE_PENALTY
    held = set(labels[~failing].tolist())
    free = np.array([j for j in range(m_st) if j not in held])
    fail_idx = np.flatnonzero(failing)
    best_v = score[:, fail_idx][:, :, free].argmin(axis=0)  # (F, free)
    best_s = score[:, fail_idx][:, :, free].min(axis=0)
    rows, cols = linear_sum_assignment(best_s)
    decisions = {}
    for r, c in zip(rows, cols):
        i, j, v = fail_idx[r], free[c], best_v[r, c]
        sc = score[:, i][:, free].copy()  # (V, free)
        best = sc[v, c]
        sc[v, c] = np.inf
        runner = float(sc.min())
        alts = [(int(g.ids[free[cc]]), PLANE_VARIANTS[vv]) for vv, cc in zip(*np.nonzero(sc - best < MIN_CONFIDENCE))]
        decisions[i] = (j, v, float(chi[v, i, j]), runner - best, alts)
    return _report(sensor, meas, labels, g, at_label, decisions)


def _report(sensor, meas, labels, g, at_label, decisions) -> tuple:
    """Corrections, corrected planes and notes from the decisions {plane index: (station index,
    variant index, chi-square, confidence, alternatives)}."""
    corrections, notes = [], []
    planes = {(m.station, sensor): m for i, m in enumerate(meas) if i not in decisions}
    accepted = {}
    for i, (j, v, chi2_new, conf, alts) in decisions.items():
        m = meas[i]
        ok = chi2_dist.sf(chi2_new, 3) >= PASS_P and conf >= MIN_CONFIDENCE
        if not ok:
            planes[(m.station, sensor)] = m
            if chi2_dist.sf(chi2_new, 3) < PASS_P:
                notes.append(f"{sensor}: the plane labelled station {m.station} fits no station at physical noise, "
                             f"as given or with a sign, convention or unit corrected (chi-square {at_label[i]:.0f} "
                             f"at its label): an outlier, or a cause of the model")
            else:
                cands = [(int(g.ids[j]), PLANE_VARIANTS[v])] + alts
                txt = ", ".join(f"station {s}" + (f" ({c} {d})" if c else "") for s, (c, d) in cands[:6])
                notes.append(f"{sensor}: the plane labelled station {m.station} does not fit it (chi-square "
                             f"{at_label[i]:.0f}); the data cannot tell between {txt}: not corrected")
            continue
        accepted[i] = (j, v, chi2_new, conf, alts)
    station_of = {i: int(g.ids[j]) for i, (j, *_rest) in accepted.items()}
    label_of = {i: meas[i].station for i in accepted}
    done = set()
    for i, (j, v, chi2_new, conf, alts) in accepted.items():
        m = meas[i]
        new_station = station_of[i]
        drop = float(at_label[i] - chi2_new)
        common = dict(statistic=drop, dof=3, p_value=float(chi2_dist.sf(max(drop, 0.0), 3)), confidence=conf,
                      alternatives=tuple(f"station {s}" + (f" {c} {d}" if c else "") for s, (c, d) in alts))
        if new_station != m.station and i not in done:
            partner = [k for k in accepted if k != i and label_of[k] == new_station and station_of[k] == m.station]
            if partner:
                k = partner[0]
                done |= {i, k}
                pair = tuple(sorted((m.station, new_station)))
                corrections.append(Correction(
                    "stations_exchanged", (("sensor", sensor), ("stations", pair)),
                    (("stations", pair),), note=f"{sensor}: the planes of stations {pair[0]} and {pair[1]} are "
                    f"exchanged", **{**common, "statistic": drop + float(at_label[k] - accepted[k][2]), "dof": 6,
                                     "confidence": min(conf, accepted[k][3])}))
            else:
                corrections.append(Correction(
                    "station_mislabelled", (("from_station", m.station), ("sensor", sensor), ("station", new_station)),
                    (("station_given", m.station), ("station_corrected", new_station)),
                    note=f"{sensor}: the plane labelled station {m.station} belongs to station {new_station}", **common))
        n_new, d_new = plane_variant(m.n, m.d, PLANE_VARIANTS[v])
        if v:
            cause, detail = PLANE_VARIANTS[v]
            corrected = {"normal_sign": (("component", detail), ("n_given", tuple(m.n)), ("n_corrected", tuple(n_new))),
                         "plane_convention": (("n_given", tuple(m.n)), ("n_corrected", tuple(n_new))),
                         "distance_unit": (("unit_given", detail), ("d_given_m", m.d), ("d_corrected_m", d_new))}[cause]
            corrections.append(Correction(
                cause, (("sensor", sensor), ("station", new_station)), corrected,
                note=f"{sensor}: the plane of station {new_station}: {cause} ({detail}) corrected", **common))
        planes[(new_station, sensor)] = dataclasses.replace(m, station=new_station, n=n_new, d=d_new)
    return corrections, planes, notes
