"""Is the estimated trajectory physically possible? A verdict next to the filter's consistency one.

A filter can be consistent with its own covariance and still put the body through the floor (or,
inconsistent, say nothing about where the body went): issue 42's Go1 log sank 0.37 m below the
floor it stood on with a +-6 mm band. The checks here need no truth, only what the filter read and
what it estimated: the body poses ``T_world_body``, the stance mask, and the feet from the joint
angles (``p_body_foot(q)``, forward kinematics of the robot model). Each check is a named record
with its bound; each violation an episode with its time and size.

Checks (thresholds: :class:`PlausibilityConfig`, relative to the leg length ``L`` where a length is
the robot's own -- ``L`` is the median over the legs of the chain length from the first joint to
the foot: a1 0.48 m, qingzhui 0.75 m, a Go1 0.51 m):

* ``touchdown`` (declared level ground): the foot's world position at each touchdown,
  ``T_world_body @ p_body_foot(q)`` at the first stance sample, against the floor the robot stood
  on (the median foot height over the first window in which every foot is in stance, else over the
  first stance samples). Bound ``max(0.03 m, 0.1 L)`` (a1: 4.8 cm): the kinematic error of an
  uncalibrated leg (~1 cm), the foot's radius rolling (~1-2 cm) and the floor's own unevenness
  stay below it; issue 42's feet at -0.28 m are six times over.
* ``body_below_floor`` (level ground): the body origin below the floor it stood on by more than
  the same height bound -- it cannot be (the body rests on the floor at worst).
* ``body_above_reach`` (level ground, a foot in stance): the body origin higher above the floor than
  the highest stance leg reaches, ``max over the stance legs of (R p_body_hip)_z + chain length``
  (each leg straight down from its first joint), plus the height bound.
* ``attitude`` (level ground, a foot in stance): roll or pitch beyond ``max_tilt_deg`` (5 deg).
  On level ground with its feet on the floor a body tilts only as far as its legs' extensions
  differ (5 deg across the a1's 0.36 m hip base is 3 cm), and a level trot or walk is controlled
  to a level body: the simulator sways 1 deg and nods 0.5 deg (estimate: 1.1 deg at worst), issue
  42's Go1 stays under 0.5 deg once tracked right; its 6-13 deg with the default noise is over the
  bound everywhere. A robot that really tilts more on level ground (a controller's pitch at a
  start, a push) is named with the time: raise ``max_tilt_deg`` for it.
* ``slip`` (any ground): a stance foot's world position moving during its stance by more than
  ``max(0.02 m, 0.05 L)`` (a1: 2.4 cm) from where it stood after ``slip_trim_s`` of load transfer
  (until ``slip_trim_s`` before lift-off); stances shorter than ``min_stance_s`` are not checked.
  A planted foot's contact point moves by its radius times the shank's rotation (~1 cm) and the
  leg model's error over the stance; a leg model 20 % short moves it by about 20 % of the stride.

Samples can be left out of every check with ``active`` (e.g. where
:func:`graphcal.locomotion.phases.segment_phases` says the robot lies, stands up, lies down or is
lifted: feet slide there, the legs fold). Violations of one kind closer than ``merge_gap_s`` in
time are one failure (its first time, its end, its worst size and when). Verdict: ``implausible``
when any check fails, ``plausible`` when at least one check ran and none failed, ``not tested``
(with the reason) when none could run.

Units: SI (m, s) inside; attitudes reported in degrees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "PlausibilityConfig",
    "PlausibilityFailure",
    "PlausibilityCheck",
    "PlausibilityResult",
    "LegReach",
    "leg_reach",
    "feet_in_body",
    "check_plausibility",
    "track_plausibility",
    "plausibility_section",
]


@dataclass(frozen=True)
class PlausibilityConfig:
    """Thresholds of the checks (module docstring). Lengths as fractions of the leg length ``L``
    with a floor in metres: the bound is ``max(*_min_m, *_leg * L)``.

    Attributes:
        height_tolerance_leg, height_tolerance_min_m: touchdown heights and the body's height range.
        max_tilt_deg: roll or pitch bound on level ground (deg).
        slip_tolerance_leg, slip_tolerance_min_m: a stance foot's movement in the world (m).
        slip_trim_s: load transfer at each end of a stance not checked for slip (s).
        min_stance_s: stances shorter than this are not checked for slip (s).
        floor_window_s: the first window with every foot in stance this long gives the floor (s).
        merge_gap_s: violations of one kind closer in time than this are one failure (s).
    """

    height_tolerance_leg: float = 0.1
    height_tolerance_min_m: float = 0.03
    max_tilt_deg: float = 5.0
    slip_tolerance_leg: float = 0.05
    slip_tolerance_min_m: float = 0.02
    slip_trim_s: float = 0.03
    min_stance_s: float = 0.08
    floor_window_s: float = 0.2
    merge_gap_s: float = 0.5

    def height_tolerance_m(self, leg_length_m: float) -> float:
        return max(self.height_tolerance_min_m, self.height_tolerance_leg * leg_length_m)

    def slip_tolerance_m(self, leg_length_m: float) -> float:
        return max(self.slip_tolerance_min_m, self.slip_tolerance_leg * leg_length_m)


@dataclass(frozen=True)
class PlausibilityFailure:
    """One episode of one check's violations.

    Attributes:
        kind: ``touchdown``, ``body_below_floor``, ``body_above_reach``, ``attitude`` or ``slip``.
        time_s: first violation (s); end_s: last violation (s).
        size: the worst violation, in ``unit`` (``m`` or ``deg``): how far below / above the floor,
            beyond the reach, tilted, or how far the foot moved; peak_s: when (s).
        count: violating samples (touchdowns for ``touchdown``, stances for ``slip``).
        foot: the foot of the worst violation (touchdown, slip), else None.
        message: one line, e.g. "body 0.10 m below the floor it stood on at 48.2 s".
    """

    kind: str
    time_s: float
    end_s: float
    size: float
    unit: str
    peak_s: float
    count: int
    foot: str | None
    message: str


@dataclass(frozen=True)
class PlausibilityCheck:
    """One check: whether it ran (``reason`` says why not), its ``bound`` and the worst value seen
    (``worst``, in ``unit``; NaN when not tested or nothing to check), at ``worst_s``, and its
    number of failures (episodes)."""

    kind: str
    tested: bool
    reason: str
    bound: float
    unit: str
    worst: float
    worst_s: float
    n_failures: int


@dataclass(frozen=True)
class PlausibilityResult:
    """The verdict (``plausible`` / ``implausible`` / ``not tested``), its ``reason`` (one line),
    the ``failures`` (time order), every ``checks`` record, the floor height in the world
    ``floor_z_m`` (None off level ground) and the leg length ``leg_length_m`` the bounds used."""

    verdict: str
    reason: str
    failures: tuple
    checks: tuple
    floor_z_m: float | None
    leg_length_m: float


@dataclass(frozen=True, eq=False)
class LegReach:
    """Per foot (``feet`` order): ``p_body_hip`` (n_feet, 3) m, the first joint's origin, and
    ``chain_m`` (n_feet,) the chain length from it to the foot (link translations, plus the longest
    stroke of a prismatic joint); ``leg_length_m`` their median."""

    feet: tuple
    p_body_hip: np.ndarray
    chain_m: np.ndarray

    @property
    def leg_length_m(self) -> float:
        return float(np.median(self.chain_m))


def leg_reach(robot) -> LegReach:
    """:class:`LegReach` of a :class:`~graphcal.models.robot.RobotModel`'s legs."""
    hips, chains = [], []
    for f in robot.feet:
        leg = robot.leg(f)
        links = [np.linalg.norm(T[:3, 3]) for T in leg.T_parent_joint[1:]] + [np.linalg.norm(leg.T_lastjoint_foot[:3, 3])]
        stroke = [max(abs(lo), abs(hi)) for jt, lo, hi in zip(leg.joint_types, leg.lower, leg.upper)
                  if jt == "prismatic" and np.isfinite(lo) and np.isfinite(hi)]
        hips.append(leg.T_parent_joint[0][:3, 3] if leg.n_joints else leg.T_lastjoint_foot[:3, 3])
        chains.append(float(sum(links) + sum(stroke)))
    return LegReach(tuple(robot.feet), np.array(hips, dtype=float).reshape(-1, 3), np.array(chains))


def feet_in_body(robot, q: dict) -> np.ndarray:
    """p_body_foot (n_feet, N, 3) m of every foot (``robot.feet`` order) from joint angles ``q``
    (joint name -> (N,) rad / m), forward kinematics."""
    from graphcal.models.kinematics import foot_positions

    out = []
    for f in robot.feet:
        leg = robot.leg(f)
        out.append(foot_positions(leg, np.column_stack([np.asarray(q[j], dtype=float) for j in leg.joint_names])))
    return np.stack(out)


# ----------------------------------------------------------------------------- helpers
def _runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(starts, ends) index arrays of the True runs of a (N,) bool array, ends exclusive."""
    d = np.diff(np.r_[0, np.asarray(mask, dtype=np.int8), 0])
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


def _episodes(t: np.ndarray, size: np.ndarray, gap_s: float) -> list[tuple[int, int, int]]:
    """Violations at times ``t`` (K,) increasing with sizes ``size`` (K,) grouped into episodes
    (a gap longer than ``gap_s`` starts a new one): (first, last, worst) indices into them."""
    if len(t) == 0:
        return []
    cut = np.flatnonzero(np.diff(t) > gap_s) + 1
    bounds = np.r_[0, cut, len(t)]
    return [(int(a), int(b - 1), int(a + np.argmax(size[a:b]))) for a, b in zip(bounds[:-1], bounds[1:])]


def _roll_pitch_deg(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Roll and pitch (deg) of rotations R (N, 3, 3) (z-y-x Euler angles)."""
    roll = np.degrees(np.arctan2(R[:, 2, 1], R[:, 2, 2]))
    pitch = np.degrees(-np.arcsin(np.clip(R[:, 2, 0], -1.0, 1.0)))
    return roll, pitch


def _floor_z(t: np.ndarray, z_world_foot: np.ndarray, stance: np.ndarray, active: np.ndarray,
             window_s: float) -> float | None:
    """Floor height (m): the median stance-foot height over the first window (>= ``window_s``) of
    active samples with every foot in stance, else over the first 0.5 s of any stance; None when
    no foot is ever in stance. ``z_world_foot`` and ``stance`` are (N, n_feet)."""
    starts, ends = _runs(stance.all(axis=1) & active)
    for a, b in zip(starts, ends):
        if t[b - 1] - t[a] >= window_s:
            return float(np.median(z_world_foot[a:b]))
    any_st = stance & active[:, None]
    rows = np.flatnonzero(any_st.any(axis=1))
    if not len(rows):
        return None
    rows = rows[t[rows] <= t[rows[0]] + 0.5]
    return float(np.median(z_world_foot[rows][any_st[rows]]))


# ----------------------------------------------------------------------------- the checks
@dataclass(frozen=True, eq=False)
class _Data:
    """What the checks read: times (N,), body positions p (N, 3) and rotations R (N, 3, 3), feet in
    the world p_world_foot (N, n_feet, 3), stance (N, n_feet) and active (N,) masks."""

    t: np.ndarray
    p: np.ndarray
    R: np.ndarray
    p_world_foot: np.ndarray
    stance: np.ndarray
    active: np.ndarray
    feet: tuple


def _failures(kind: str, t: np.ndarray, size: np.ndarray, feet_of: np.ndarray | None, feet: tuple, unit: str,
              gap_s: float, describe) -> list[PlausibilityFailure]:
    """Episodes of the violations at times ``t`` of sizes ``size`` as failures; ``describe(size,
    peak_s, t0, t1, foot, w)`` writes the message (``w``: index of the worst violation)."""
    out = []
    for a, b, w in _episodes(t, size, gap_s):
        foot = feet[int(feet_of[w])] if feet_of is not None else None
        out.append(PlausibilityFailure(kind, float(t[a]), float(t[b]), float(size[w]), unit, float(t[w]), b - a + 1,
                                       foot, describe(float(size[w]), float(t[w]), float(t[a]), float(t[b]), foot, w)))
    return out


def _span(t0: float, t1: float) -> str:
    return f" (from {t0:.1f} s to {t1:.1f} s)" if t1 > t0 else ""


def _check(kind, bound, unit, values, times, failures) -> PlausibilityCheck:
    """The check record of ``kind`` from the values it measured (K,) at ``times`` (K,)."""
    if len(values) == 0:
        return PlausibilityCheck(kind, True, "nothing to check", bound, unit, math.nan, math.nan, 0)
    w = int(np.argmax(values))
    return PlausibilityCheck(kind, True, "", bound, unit, float(values[w]), float(times[w]), len(failures))


def _check_touchdowns(d: _Data, floor: float, tol: float, gap_s: float):
    """Touchdown heights against the floor: |z_foot - floor| at every stance start (not sample 0)."""
    k_all, f_all = [], []
    for i in range(len(d.feet)):
        starts, _ = _runs(d.stance[:, i])
        starts = starts[(starts > 0) & d.active[starts]]
        k_all.append(starts)
        f_all.append(np.full(len(starts), i))
    k = np.concatenate(k_all)
    fi = np.concatenate(f_all)
    order = np.argsort(k, kind="stable")
    k, fi = k[order], fi[order]
    dz = d.p_world_foot[k, fi, 2] - floor
    bad = np.abs(dz) > tol
    dz_bad = dz[bad]
    fails = _failures("touchdown", d.t[k[bad]], np.abs(dz_bad), fi[bad], d.feet, "m", gap_s,
                      lambda s, pk, t0, t1, foot, w: (f"{foot} touched down {s:.2f} m {'below' if dz_bad[w] < 0 else 'above'}"
                                                      f" the floor it stood on at {pk:.1f} s{_span(t0, t1)}"))
    return _check("touchdown", tol, "m", np.abs(dz), d.t[k], fails), fails


def _check_body_height(d: _Data, floor: float, tol: float, reach: LegReach, gap_s: float):
    """Body origin height above the floor: below it, or above the reach of the stance legs."""
    h = d.p[:, 2] - floor
    loaded = d.stance.any(axis=1) & d.active
    below = h < -tol
    below &= d.active
    fb = _failures("body_below_floor", d.t[below], -h[below], None, d.feet, "m", gap_s,
                   lambda s, pk, t0, t1, _f, _w: f"body {s:.2f} m below the floor it stood on at {pk:.1f} s{_span(t0, t1)}")
    hip_z = np.einsum("nj,fj->nf", d.R[:, 2, :], reach.p_body_hip) + reach.chain_m[None, :]
    top = np.where(d.stance, hip_z, -np.inf).max(axis=1)
    over = np.where(loaded, h - top, -np.inf)
    above = over > tol
    fa = _failures("body_above_reach", d.t[above], over[above], None, d.feet, "m", gap_s,
                   lambda s, pk, t0, t1, _f, _w: (f"body {s:.2f} m higher above the floor than its stance legs reach "
                                              f"at {pk:.1f} s{_span(t0, t1)}"))
    act = d.active
    c_below = _check("body_below_floor", tol, "m", -h[act], d.t[act], fb)
    c_above = _check("body_above_reach", tol, "m", over[loaded], d.t[loaded], fa)
    return [c_below, c_above], fb + fa


def _check_attitude(d: _Data, bound_deg: float, gap_s: float):
    """Roll and pitch on level ground while a foot is in stance."""
    roll, pitch = _roll_pitch_deg(d.R)
    tilt = np.maximum(np.abs(roll), np.abs(pitch))
    use = d.stance.any(axis=1) & d.active
    bad = use & (tilt > bound_deg)

    def describe(s, pk, t0, t1, _f, _w):
        k = int(np.argmin(np.abs(d.t - pk)))
        axis = "roll" if abs(roll[k]) >= abs(pitch[k]) else "pitch"
        return f"body {axis} {s:.1f} deg on level ground at {pk:.1f} s{_span(t0, t1)} (a level gait stays within {bound_deg:g} deg)"

    fails = _failures("attitude", d.t[bad], tilt[bad], None, d.feet, "deg", gap_s, describe)
    return _check("attitude", bound_deg, "deg", tilt[use], d.t[use], fails), fails


def _stance_slips(d: _Data, i: int, trim: int, min_n: int) -> tuple[np.ndarray, np.ndarray]:
    """(sample of the worst movement (S,), movement m (S,)) of foot i over each of its stances:
    the largest distance from its position ``trim`` samples after touchdown, until ``trim``
    samples before lift-off; stances shorter than ``min_n`` samples (or not active) skipped."""
    starts, ends = _runs(d.stance[:, i] & d.active)
    keep = (ends - starts >= max(min_n, 2 * trim + 2))
    starts, ends = starts[keep] + trim, ends[keep] - trim
    if not len(starts):
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    lengths = ends - starts
    run = np.repeat(np.arange(len(starts)), lengths)
    k = np.arange(lengths.sum()) - np.repeat(np.cumsum(lengths) - lengths, lengths) + np.repeat(starts, lengths)
    dist = np.linalg.norm(d.p_world_foot[k, i] - d.p_world_foot[starts[run], i], axis=1)
    first = np.cumsum(lengths) - lengths
    worst = np.maximum.reduceat(dist, first)
    at = np.array([k[a + int(np.argmax(dist[a:a + n]))] for a, n in zip(first, lengths)], dtype=np.int64)
    return at, worst


def _check_slip(d: _Data, tol: float, cfg: PlausibilityConfig):
    """Stance feet moving in the world."""
    dt = float(np.median(np.diff(d.t))) if len(d.t) > 1 else 1.0
    trim = int(round(cfg.slip_trim_s / dt))
    min_n = int(round(cfg.min_stance_s / dt))
    ks, sizes, fis = [], [], []
    for i in range(len(d.feet)):
        at, worst = _stance_slips(d, i, trim, min_n)
        ks.append(at)
        sizes.append(worst)
        fis.append(np.full(len(at), i))
    k, s, fi = np.concatenate(ks), np.concatenate(sizes), np.concatenate(fis)
    order = np.argsort(k, kind="stable")
    k, s, fi = k[order], s[order], fi[order]
    bad = s > tol
    fails = _failures("slip", d.t[k[bad]], s[bad], fi[bad], d.feet, "m", cfg.merge_gap_s,
                      lambda sz, pk, t0, t1, foot, _w: (f"{foot} moved {sz:.2f} m on the ground during its stance at "
                                                    f"{pk:.1f} s{_span(t0, t1)}"))
    return _check("slip", tol, "m", s, d.t[k], fails), fails


def _not_tested(kind: str, bound: float, unit: str, reason: str) -> PlausibilityCheck:
    return PlausibilityCheck(kind, False, reason, bound, unit, math.nan, math.nan, 0)


def check_plausibility(times, T_world_body, stance_mask, p_body_foot, reach: LegReach, *, level_ground: bool,
                       active=None, config: PlausibilityConfig = PlausibilityConfig()) -> PlausibilityResult:
    """The plausibility verdict of an estimated trajectory (module docstring).

    Args:
        times: (N,) s. T_world_body: (N, 4, 4) the estimate.
        stance_mask: (N, n_feet) bool, feet in stance (``reach.feet`` order).
        p_body_foot: (n_feet, N, 3) m, the feet from the joint angles (:func:`feet_in_body`).
        reach: the legs' :class:`LegReach` (:func:`leg_reach`).
        level_ground: the ground is declared level (dataset.yaml ``ground: {type: level}``): the
            floor checks run; otherwise only ``slip``.
        active: (N,) bool, samples the checks read (default all), e.g. phases' walking/standing.
        config: thresholds.
    """
    cfg = config
    t = np.asarray(times, dtype=float)
    T = np.asarray(T_world_body, dtype=float)
    N = len(t)
    stance = np.asarray(stance_mask, dtype=bool).reshape(N, -1)
    act = np.ones(N, dtype=bool) if active is None else np.asarray(active, dtype=bool)
    L = reach.leg_length_m
    tol_h, tol_s = cfg.height_tolerance_m(L), cfg.slip_tolerance_m(L)
    R, p = T[:, :3, :3], T[:, :3, 3]
    pwf = p[:, None, :] + np.einsum("nij,fnj->nfi", R, np.asarray(p_body_foot, dtype=float))
    d = _Data(t, p, R, pwf, stance, act, tuple(reach.feet))
    checks, failures = [], []
    floor = _floor_z(t, pwf[:, :, 2], stance, act, cfg.floor_window_s) if level_ground else None
    floor_kinds = (("touchdown", tol_h, "m"), ("body_below_floor", tol_h, "m"), ("body_above_reach", tol_h, "m"),
                   ("attitude", cfg.max_tilt_deg, "deg"))
    if floor is None:
        why = "the ground is not declared level" if not level_ground else "no foot in stance: no floor"
        checks += [_not_tested(k, b, u, why) for k, b, u in floor_kinds]
    else:
        for c, f in (_check_touchdowns(d, floor, tol_h, cfg.merge_gap_s), _check_attitude(d, cfg.max_tilt_deg,
                                                                                          cfg.merge_gap_s)):
            checks.append(c)
            failures += f
        cs, f = _check_body_height(d, floor, tol_h, reach, cfg.merge_gap_s)
        checks[1:1] = cs
        failures += f
    c, f = _check_slip(d, tol_s, cfg)
    checks.append(c)
    failures += f
    failures.sort(key=lambda x: x.time_s)
    return _verdict(tuple(failures), tuple(checks), floor, L)


def _verdict(failures: tuple, checks: tuple, floor: float | None, L: float) -> PlausibilityResult:
    ran = [c for c in checks if c.tested and c.reason == ""]
    if failures:
        first = failures[0]
        more = f" (and {len(failures) - 1} more)" if len(failures) > 1 else ""
        return PlausibilityResult("implausible", first.message + more, failures, checks, floor, L)
    if not ran:
        reasons = sorted({c.reason for c in checks if c.reason})
        return PlausibilityResult("not tested", "; ".join(reasons), failures, checks, floor, L)
    skipped = [c.kind for c in checks if not c.tested]
    note = f"; not tested: {', '.join(skipped)}" if skipped else ""
    return PlausibilityResult("plausible", f"{', '.join(c.kind for c in ran)} within bounds{note}", failures, checks,
                              floor, L)


def track_plausibility(result, inputs, *, level_ground: bool, active=None,
                       config: PlausibilityConfig = PlausibilityConfig()) -> PlausibilityResult:
    """:func:`check_plausibility` of a :class:`~graphcal.locomotion.estimator.TrackResult` and the
    :class:`~graphcal.locomotion.track_inputs.TrackInputs` it was run on (stance mask from the
    result, feet from the inputs' joint angles and robot model)."""
    reach = leg_reach(inputs.robot)
    if result.stance_mask is None:
        checks = tuple(_not_tested(k, math.nan, u, "no stance mask in the result")
                       for k, u in (("touchdown", "m"), ("body_below_floor", "m"), ("body_above_reach", "m"),
                                    ("attitude", "deg"), ("slip", "m")))
        return PlausibilityResult("not tested", "no stance mask in the result", (), checks, None, reach.leg_length_m)
    p_body_foot = getattr(inputs, "p_body_foot", None)  # measured foot points (a robot given by its feet)
    feet = p_body_foot if p_body_foot is not None else feet_in_body(inputs.robot, inputs.q)
    return check_plausibility(result.times, result.T_world_body, result.stance_mask, feet, reach, level_ground=level_ground,
                              active=active, config=config)


def _num(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), 6)


def plausibility_section(result: PlausibilityResult) -> dict:
    """The ``plausibility`` section of metrics.json (plain JSON types; NaN as null)."""
    return {
        "verdict": result.verdict,
        "reason": result.reason,
        "floor_z_m": _num(result.floor_z_m),
        "leg_length_m": _num(result.leg_length_m),
        "failures": [{"kind": f.kind, "time_s": _num(f.time_s), "end_s": _num(f.end_s), "size": _num(f.size),
                      "unit": f.unit, "peak_s": _num(f.peak_s), "count": f.count, "foot": f.foot,
                      "message": f.message} for f in result.failures],
        "checks": {c.kind: {"tested": c.tested, "reason": c.reason, "bound": _num(c.bound), "unit": c.unit,
                            "worst": _num(c.worst), "worst_s": _num(c.worst_s), "n_failures": c.n_failures}
                   for c in result.checks},
    }
