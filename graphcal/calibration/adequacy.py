"""Does the model fit? The adequacy verdict of a calibration, judged against physical noise.

The noise learned from the residuals grows until any misfit looks like noise, so the verdict is
read *against the physically plausible noise*: the one dataset.yaml declares (``physical_noise:``,
deg and mm), else :data:`graphcal.models.sensors.PHYSICAL_NOISE_DEFAULTS`. Per noise group g with
redundancy ``r_g`` and learned sigma ``s_g`` against the physical ``p_g``:
``T_g = r_g (s_g / p_g)^2 ~ chi2(r_g)``; a group does not fit when ``s_g > RATIO_LIMIT p_g`` and
its p-value is below :data:`ALPHA` over the groups (Bonferroni). :func:`gross_stations` flags a
station whose factors' chi-square is far beyond the others'. Plain statistics on numbers a solver
reports (no graph), shared by calibrate and diagnose; sigmas in SI (m, rad) inside.

The test, the physical noise table and gross stations: docs/calibration.md, "Does the model fit?".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from graphcal import stats
from graphcal.errors import DatasetError
from graphcal.models.sensors import PHYSICAL_NOISE_DEFAULTS, PHYSICAL_NOISE_FLOORS, PHYSICAL_NOISE_KEYS

__all__ = ["RATIO_LIMIT", "ALPHA", "GROSS_ALPHA", "GROUP_PHYSICAL_KEYS", "GroupCheck", "StationCheck", "Adequacy",
           "physical_noise", "group_check", "group_checks", "gross_stations", "adequacy_verdict",
           "misfit_warning", "adequacy_dict", "FITS", "DOES_NOT_FIT"]

FITS, DOES_NOT_FIT = "fits", "does not fit"

#: a learned sigma more than this many times its physical value is a misfit of its group (when
#: significant); clean simulated runs learn less than that (docs/calibration.md, "The test")
RATIO_LIMIT = 1.5
#: family-wise false-alarm level of the group tests (Bonferroni over the groups)
ALPHA = 1e-3
#: family-wise level of the gross-station test (Bonferroni over the stations)
GROSS_ALPHA = 1e-3
#: a station's variance factor must also exceed the median one by this factor to be gross
GROSS_MIN_FACTOR = 5.0

#: noise group -> (CalibrationOptions field, physical_noise key) pairs
GROUP_PHYSICAL_KEYS: dict[str, tuple[tuple[str, str], ...]] = {
    "stance_foot/joint": (("sigma_joint_rad", "joint_deg"),),
    "stance_foot/contact": (("sigma_contact_m", "contact_mm"),),
    "foot_on_ground": (("sigma_ground_m", "ground_mm"),),
    "imu": (("sigma_imu_rad", "imu_deg"),),
    "commanded": (("sigma_commanded_rad", "commanded_deg"), ("sigma_commanded_m", "commanded_mm")),
}


def _si(key: str, value: float) -> float:
    """A physical_noise value (deg, mm or a scale) in SI (rad, m, scale)."""
    if key.endswith("_deg"):
        return float(np.radians(value))
    if key.endswith("_mm"):
        return 1e-3 * float(value)
    return float(value)


def physical_noise(declared: Mapping | None, *, ground_roughness_m: float = 0.0,
                   where: str = "dataset.yaml") -> tuple[dict[str, float], dict[str, str]]:
    """(key -> physical sigma in dataset.yaml's units (deg, mm), key -> where it comes from).

    Args:
        declared: dataset.yaml's ``physical_noise:`` mapping (None: absent). Keys
            :data:`~graphcal.models.sensors.PHYSICAL_NOISE_KEYS` (deg, mm), each a number >= 0.
        ground_roughness_m: ``--ground-roughness-mm`` (m): the feet-on-ground value is at least it.
        where: the file named in an error.

    Each value is at least its floor (:data:`~graphcal.models.sensors.PHYSICAL_NOISE_FLOORS`).
    Raises DatasetError for an unknown key or a value that is not a number >= 0.
    """
    declared = {} if declared is None else declared
    if not isinstance(declared, Mapping):
        raise DatasetError(where, "physical_noise", "a mapping of " + ", ".join(PHYSICAL_NOISE_KEYS), declared)
    for key, v in declared.items():
        if key not in PHYSICAL_NOISE_KEYS:
            raise DatasetError(where, f"physical_noise.{key}", "one of " + ", ".join(PHYSICAL_NOISE_KEYS), key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v < 0:
            raise DatasetError(where, f"physical_noise.{key}", "a number >= 0 (deg, mm or per cent, as its name says)", v)
    values, sources = {}, {}
    for key, default in PHYSICAL_NOISE_DEFAULTS.items():
        if key in declared:
            v, src = float(declared[key]), f"{where} physical_noise"
        else:
            v, src = default, "default (graphcal/models/sensors.py)"
        if key == "ground_mm" and 1e3 * ground_roughness_m > v:
            v, src = 1e3 * ground_roughness_m, "--ground-roughness-mm"
        if v < PHYSICAL_NOISE_FLOORS[key]:
            v, src = PHYSICAL_NOISE_FLOORS[key], src + " (at its floor)"
        values[key], sources[key] = v, src
    return values, sources


@dataclass(frozen=True)
class GroupCheck:
    """One noise group judged against its physical noise.

    Attributes:
        group: the noise group (``plane:<sensor>`` for a sensor's planes or scans).
        learned: (name, value) the sigma the residuals point to, SI (rad, m) or a plane scale.
        physical: (name, value) the physical sigma, dataset.yaml units (deg, mm) or a scale.
        source: where the physical value comes from.
        ratio: learned / physical (the largest over the group's fields).
        statistic, dof, p_value: ``T = dof ratio^2`` against ``chi2(dof)``, its upper tail.
        misfit: ratio above :data:`RATIO_LIMIT` and p below the Bonferroni level.
        model_ratio: the learned sigma over the sigma the model's solve *used* (the largest over
            the group's fields): the factor the residuals point to, about 1 for noise learned from
            them, the misfit of a given noise model otherwise (robust.py's variance factor).
    """

    group: str
    learned: tuple[tuple[str, float], ...]
    physical: tuple[tuple[str, float], ...]
    source: str
    ratio: float
    statistic: float
    dof: float
    p_value: float
    misfit: bool = False
    model_ratio: float = 1.0

    def learned_text(self) -> str:
        """The learned sigma in words, e.g. ``0.239 deg, 1.08 mm``."""
        return ", ".join(_value_text(n, v) for n, v in self.learned)

    def physical_text(self) -> str:
        """The physical sigma in words, e.g. ``0.02 deg, 0.1 mm``."""
        return ", ".join(_value_text(n, v) for n, v in self.physical)

    def text(self) -> str:
        """E.g. ``foot_on_ground: learned 6.23 mm, physical 0.5 mm (x12)``."""
        return f"{self.group}: learned {self.learned_text()}, physical {self.physical_text()} (x{self.ratio:.2g})"


def _value_text(name: str, v: float) -> str:
    """A value named by its unit suffix (``_rad``, ``_m`` SI; ``_deg``, ``_mm``; else a scale) in words."""
    if name.endswith("_rad"):
        return f"{np.degrees(v):.3g} deg"
    if name.endswith("_m"):
        return f"{1e3 * v:.3g} mm"
    if name.endswith("_deg"):
        return f"{v:.3g} deg"
    if name.endswith("_mm"):
        return f"{v:.3g} mm"
    return f"x{v:.3g}"


@dataclass(frozen=True)
class StationCheck:
    """One station's factors against the others: ``statistic`` (chi-square of its factors under
    the final noise, divided by the median variance factor of the stations when above 1), ``dof``
    and the upper tail ``p_value`` of ``chi2(dof)``; ``factor``: its chi-square per dof over the median."""

    station: int
    statistic: float
    dof: float
    p_value: float
    factor: float


@dataclass(frozen=True)
class Adequacy:
    """The verdict on a result.

    Attributes:
        verdict: ``fits`` or ``does not fit``.
        statistic, dof, reference, p_value: the worst group's ``T`` (see module docstring), its
            reference distribution (text, e.g. ``chi2(675)``) and Bonferroni-adjusted p-value.
        worst_group: the group with the smallest p-value ("" when none could be judged).
        groups: every group judged (:class:`GroupCheck`).
        gross: stations far beyond the others (:class:`StationCheck`); they were left out and the
            verdict is on the rest.
        covariance: ``model`` (the model's covariance governs ``sigma``) or ``robust``.
        next_steps: what to do, one sentence each (empty when the model fits).
    """

    verdict: str
    statistic: float
    dof: float
    reference: str
    p_value: float
    worst_group: str = ""
    groups: tuple[GroupCheck, ...] = ()
    gross: tuple[StationCheck, ...] = ()
    covariance: str = "model"
    next_steps: tuple[str, ...] = ()
    gross_left_out: bool = True

    @property
    def fits(self) -> bool:
        return self.verdict == FITS

    @property
    def misfit_groups(self) -> tuple[GroupCheck, ...]:
        return tuple(g for g in self.groups if g.misfit)


def group_check(group: str, fields: tuple[tuple[str, float], ...], data_scale: float, dof: float,
                physical: Mapping[str, float], sources: Mapping[str, str], n_groups: int,
                used: Mapping[str, float] | None = None) -> GroupCheck | None:
    """One group's :class:`GroupCheck`, or None when it carries under 1 dof (nothing to judge).

    Args:
        group: the noise group.
        fields: (CalibrationOptions field or ``plane_scale:<sensor>``, value SI) of the final solve.
        data_scale: the factor the residuals point to for the group's sigma (1 when learned).
        dof: the group's redundancy at the solution.
        physical, sources: :func:`physical_noise`.
        n_groups: groups tested together (the Bonferroni divisor).
        used: field -> the sigma (SI) the model's solve used, when it is not ``fields`` (noise given,
            not learned: ``fields`` are then what the residuals converge to); None: ``fields``.
    """
    if not np.isfinite(dof) or dof < 1.0 or not np.isfinite(data_scale):
        return None
    if group.startswith("plane:"):
        pairs = ((fields[0][0], "plane_scale"),)
    elif group in GROUP_PHYSICAL_KEYS:
        pairs = GROUP_PHYSICAL_KEYS[group]
    else:
        return None
    value = dict(fields)
    model = value if used is None else {**value, **used}
    learned, phys, ratios, model_ratios = [], [], [], []
    for field, key in pairs:
        s = float(value[field]) * float(data_scale)
        p = physical[key]
        learned.append((field, s))
        phys.append((key, p))
        ratios.append(s / _si(key, p))
        model_ratios.append(s / float(model[field]) if float(model[field]) > 0 else float(data_scale))
    ratio = float(max(ratios))
    T = float(dof * ratio * ratio)
    p_value = float(stats.sf(T, dof))
    misfit = bool(ratio > RATIO_LIMIT and p_value < ALPHA / max(n_groups, 1))
    source = sources[pairs[0][1]]
    return GroupCheck(group, tuple(learned), tuple(phys), source, ratio, T, float(dof), p_value, misfit,
                      float(max(model_ratios)))


#: a joint-angle error moves a foot by about this lever times the angle (m; legs of 0.15-0.3 m):
#: how a stance foot's joint and contact components are added into one foot sigma
STANCE_LEVER_M = 0.2


def stance_foot_check(joint, contact, physical: Mapping[str, float], sources: Mapping[str, str],
                      n_groups: int, used: Mapping[str, float] | None = None) -> GroupCheck | None:
    """The stance foot judged as one group: its joint and contact components (noise groups
    ``stance_foot/joint`` and ``stance_foot/contact``) added into a foot sigma,
    ``sqrt((STANCE_LEVER_M s_joint)^2 + s_contact^2)``, against the same sum of their physical
    values, over the components' summed dof. The data split a foot's noise between its two
    components poorly (the same unseen joint flex can be learned as contact or as joint noise):
    each alone would call a good split a misfit. ``used``: as
    :func:`group_check`'s (the foot sigma the model used is the same sum of its components)."""
    dof = float(joint.dof + contact.dof)
    if not np.isfinite(dof) or dof < 1.0:
        return None
    s_j = float(dict(joint.fields)["sigma_joint_rad"]) * float(joint.data_scale)
    s_c = float(dict(contact.fields)["sigma_contact_m"]) * float(contact.data_scale)
    p_j, p_c = physical["joint_deg"], physical["contact_mm"]
    learned = np.hypot(STANCE_LEVER_M * s_j, s_c)
    phys = np.hypot(STANCE_LEVER_M * _si("joint_deg", p_j), _si("contact_mm", p_c))
    ratio = float(learned / phys)
    T = float(dof * ratio * ratio)
    p_value = float(stats.sf(T, dof))
    misfit = bool(ratio > RATIO_LIMIT and p_value < ALPHA / max(n_groups, 1))
    u = {**dict(joint.fields), **dict(contact.fields), **(used or {})}
    model = np.hypot(STANCE_LEVER_M * float(u["sigma_joint_rad"]), float(u["sigma_contact_m"]))
    return GroupCheck("stance_foot", (("sigma_joint_rad", s_j), ("sigma_contact_m", s_c)),
                      (("joint_deg", p_j), ("contact_mm", p_c)), sources["joint_deg"], ratio, T, dof, p_value, misfit,
                      float(learned / model) if model > 0 else 1.0)


def group_checks(noise_groups, physical: Mapping[str, float], sources: Mapping[str, str],
                 used: Mapping[str, float] | None = None) -> tuple[GroupCheck, ...]:
    """Every judgeable group of ``noise_groups`` (:class:`~graphcal.calibration.result.NoiseGroupEstimate`);
    a stance foot's joint and contact components as one (:func:`stance_foot_check`). ``used``: field
    -> the sigma the model's solve used when the noise was given (:func:`group_check`)."""
    by = {g.group: g for g in noise_groups}
    joint, contact = by.get("stance_foot/joint"), by.get("stance_foot/contact")
    both = joint is not None and contact is not None
    rest = [g for g in noise_groups if not (both and g.group in ("stance_foot/joint", "stance_foot/contact"))]
    n = sum(1 for g in rest if np.isfinite(g.dof) and g.dof >= 1.0) + (1 if both else 0)
    out = [group_check(g.group, g.fields, g.data_scale, g.dof, physical, sources, n, used) for g in rest]
    if both:
        out.append(stance_foot_check(joint, contact, physical, sources, n, used))
    return tuple(sorted((c for c in out if c is not None), key=lambda c: c.group))


def gross_stations(chi2_by_station: Mapping[int, tuple[float, float]]) -> tuple[StationCheck, ...]:
    """Stations whose factors are far beyond the others'.

    Args:
        chi2_by_station: station -> (chi-square of the factors on its body pose under the final
            noise, their dof: rows less the 6 of the body pose). Stations under 1 dof are skipped.

    Each station's chi-square is divided by ``c = max(1, median_i(chi2_i / dof_i))``, the variance
    factor of a typical station (robust: a few gross stations do not move it); a station is gross
    when ``chi2_i / c`` has an upper tail below ``GROSS_ALPHA / n`` in ``chi2(dof_i)`` and its
    variance factor is over :data:`GROSS_MIN_FACTOR` times ``c``.
    """
    items = [(int(s), float(x), float(d)) for s, (x, d) in chi2_by_station.items() if d >= 1.0 and np.isfinite(x)]
    if len(items) < 3:
        return ()
    c = max(1.0, float(np.median([x / d for _, x, d in items])))
    out = []
    for s, x, d in items:
        t = x / c
        p = float(stats.sf(t, d))
        if p < GROSS_ALPHA / len(items) and t / d > GROSS_MIN_FACTOR:
            out.append(StationCheck(s, t, d, p, t / d))
    return tuple(sorted(out, key=lambda sc: sc.p_value))


def next_steps_for(misfit: tuple[GroupCheck, ...], gross: tuple[StationCheck, ...], legs: bool,
                   left_out: bool = True) -> tuple[str, ...]:
    """One sentence per next step for the misfit groups and gross stations."""
    names = {g.group for g in misfit}
    steps = []
    if names & {"stance_foot", "stance_foot/joint", "stance_foot/contact", "foot_on_ground"} and not legs:
        steps.append("calibrate --legs (joint offsets and link lengths: the legs may not be the URDF's)")
    if any(n.startswith("plane:") for n in names) or "commanded" in names or "imu" in names or names:
        steps.append("graphcal diagnose (names the unmodelled cause: range scale, ground tilt, an offset per "
                     "session, a knocked sensor, ...)")
    if any(n.startswith("plane:") for n in names):
        steps.append("calibrate --incremental (detects a sensor knocked during the run)")
    if gross:
        steps.append("check the data of station(s) " + ", ".join(str(s.station) for s in gross)
                     + (" (left out as gross errors)" if left_out else " (gross errors; calibrate in batch leaves them out)"))
    return tuple(steps)


def adequacy_verdict(groups: tuple[GroupCheck, ...], gross: tuple[StationCheck, ...] = (), *,
                     legs: bool = False, gross_left_out: bool = True) -> Adequacy:
    """The :class:`Adequacy` of judged groups and gross stations (``legs``: the legs were calibrated,
    so ``--legs`` is no next step; ``gross_left_out``: the gross stations were left out)."""
    misfit = tuple(g for g in groups if g.misfit)
    fits = not misfit  # gross stations were left out: the verdict is on the rest
    if groups:
        worst = min(groups, key=lambda g: (g.p_value, -g.ratio))
        p_adj = float(min(1.0, worst.p_value * len(groups)))
        stat, dof, ref, name = worst.statistic, worst.dof, f"chi2({worst.dof:.1f})", worst.group
    else:
        stat, dof, ref, name, p_adj = float("nan"), 0.0, "none (no group carries 1 dof)", "", float("nan")
    return Adequacy(FITS if fits else DOES_NOT_FIT, float(stat), float(dof), ref, p_adj, name, tuple(groups),
                    tuple(gross), "model" if fits else "robust",
                    next_steps_for(misfit, gross, legs, gross_left_out) if (misfit or gross) else (), gross_left_out)


def misfit_warning(a: Adequacy) -> str:
    """The warning printed first when the model does not fit or gross stations were found ("" otherwise)."""
    if a.fits and not a.gross:
        return ""
    parts = []
    if a.misfit_groups:
        parts.append("the model does not fit: " + "; ".join(g.text() for g in a.misfit_groups)
                     + f" (worst {a.worst_group}: {a.reference} statistic {a.statistic:.4g}, p = {a.p_value:.2g})")
    if a.gross:
        parts.append(f"gross station(s) {'left out' if a.gross_left_out else 'found (not left out)'}: " + ", ".join(
            f"{s.station} ({s.factor:.3g} times a typical station's chi-square per dof, p = {s.p_value:.2g})"
            for s in a.gross))
    robust = "" if a.fits else "; sigma is the robust one (sigma_model is the model's)"
    return "; ".join(parts) + robust + "; next: " + "; ".join(a.next_steps)


def _group_value_dict(pairs) -> dict:
    """(name, value) pairs of a group check as a mapping in the units their names say."""
    return {str(k): float(v) for k, v in pairs}


def adequacy_dict(a) -> dict:
    """The ``adequacy:`` block (docs/outputs.md) of an :class:`~graphcal.calibration.adequacy.Adequacy`."""
    return {
        "verdict": str(a.verdict),
        "statistic": float(a.statistic),
        "reference": str(a.reference),
        "p_value": float(a.p_value),
        "worst_group": str(a.worst_group),
        "test": ("each noise group's learned sigma s (the sigma of the final solve times the factor its residuals "
                 "point to) against its physical sigma p (dataset.yaml physical_noise:, else graphcal's defaults): "
                 "T = dof (s/p)^2 against chi2(dof); a group does not fit when s > "
                 f"{RATIO_LIMIT:g} p and its p-value is below {ALPHA:g} / groups; p_value is the worst group's "
                 "times the number of groups (Bonferroni)"),
        "sigma_from": str(a.covariance),
        "groups": {str(g.group): {"misfit": bool(g.misfit), "ratio": float(g.ratio), "statistic": float(g.statistic),
                                  "dof": float(g.dof), "p_value": float(g.p_value),
                                  "learned_si": _group_value_dict(g.learned),
                                  "physical": _group_value_dict(g.physical), "physical_from": str(g.source)}
                   for g in a.groups},
        "gross_stations": [{"station": int(s.station), "statistic": float(s.statistic), "dof": float(s.dof),
                            "p_value": float(s.p_value), "factor_over_median": float(s.factor)} for s in a.gross],
        "next_steps": [str(x) for x in a.next_steps],
    }
