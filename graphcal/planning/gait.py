"""Gait parameters on stairs: feasible step length and step height of the tripod that steps next,
from the tread zones and the shin-cylinder / stair-edge-cylinder test (Zhao et al. 2020, section
3.3, Eqs. 11-12), intersected over the tripod.

Frames and units
----------------
World z up; poses ``T_world_body`` (4x4); foot positions ``p_world_<foot>`` (3,), metres. The stairs
come as a :class:`graphcal.locomotion.stairs.StairsModel`; its stairs frame (x up the stairs, z up) gives the
along-stairs coordinate ``s``, the lateral ``t`` and the height ``h``. Angles in radians, lengths in
metres; millimetres only in reports.

The step
--------
A step moves the *swing* tripod (the group not in ``stance_group``) by the step length ``L`` along
the horizontal heading, while the body moves ``L / 2`` along it, keeps its height above the line
fitted to the six footholds along the heading and pitches to that line's slope (max 30 deg; roll
and yaw kept) -- ours: Zhao gives no body motion; during the swing it moves at constant velocity
and turns about a fixed axis (:func:`body_path`). The swing foot follows a fixed path shape scaled
by the step height ``H`` (:func:`swing_trajectory`): it rises to ``max(z_lift, z_land) + H`` in the
first 30 % of the swing, moves horizontally between 15 % and 85 % (smoothstep), and descends in
the last 30 %. ``H`` is the clearance above the higher of the two footholds. The leg follows by a
batched Gauss-Newton IK warm-started at the leg's current configuration (the branch of the
zero configuration). The feet stand on the model's surfaces: a given foot within ``foot_snap_m``
of one is put on it (feet and model come from estimates with errors of their own).

Feasibility (Zhao's method, as we read it)
------------------------------------------
* **Tread zones.** Each surface along the heading (the floor before the stairs, each tread) is cut
  into a *near* zone (the first ``near_zone_m`` met when walking: the nosing when climbing), a *far*
  zone (the last ``far_zone_m``: at the next riser) and the *middle*. A foot may land only in a
  middle zone (exact intervals of ``L``), and laterally ``lateral_margin_m`` inside the tread.
* **Interference** (Zhao: the zones "can be changed by the interference model between legs and
  stairs"). For each ``L`` on a grid (``length_grid_m``): the leg must reach the foothold within its
  joint limits, and its shin must be collision-free, at touchdown and at the end of the following
  stance (the body ``L / 2`` further on; there only the clearance, where the leg reaches: that
  stance's reach is the next step's concern); the stance tripod must reach its feet at the end of
  the swing. Reaching means: IK converges, joints ``joint_limit_margin_rad`` inside their limits and
  the leg not stretched (smallest singular value of its Jacobian >= ``min_leg_singular_value``).
  Collision-free: the distance between the shin's axis (last joint origin -> foot, a
  segment) and every nosing's axis (a segment along the tread's visible width) is at least
  ``shin_radius_m + edge_radius_m`` (Zhao Eqs. 11-12, with segment-segment instead of line-line
  distances: infinite lines meet far outside the stairs), and the shin's capsule does not enter
  the staircase solid (each tread a box down to the floor). For the solid test the capsule runs
  from the knee to a ball of the shin's radius whose bottom is the foot point (its centre
  ``shin_radius_m`` above it), so a foot standing on a tread touches the solid exactly (1 mm
  tolerance). The solid test catches a foot or shin going through a riser or a tread, which the
  edge test alone misses; the edge test adds the margin ``edge_radius_m`` at the nosings, where
  the model is least certain.
* The feasible ``L`` of each swing foot is a union of intervals; the step's feasible ``L`` is their
  intersection with the stance tripod's reach. ``L`` is chosen closest to the length that brings
  the most lagging swing foot ``nominal_step_length_m / 4`` ahead of its nominal place under the
  body (a steady tripod gait's touchdown; from the nominal stance: half a step), at least
  ``length_margin_m`` inside its interval.
* **Step height.** For that ``L``, each swing foot's feasible ``H`` (on a grid ``height_grid_m``,
  refined once to half a grid step) keeps the whole swing (``swing_samples`` instants)
  reachable and collision-free; the intersection over the tripod is taken and ``H`` is its lowest
  value plus ``height_margin_m`` (kept inside the interval). If no ``H`` exists, the next ``L``
  candidate is tried.

Deviations from Zhao: segment-segment distance (see above), the solid test and the reach margin;
the zones are intervals of the *step length* computed from the current footholds (Zhao speaks of
feasible areas per foot, turned into step-length and step-height sections, the same thing); the
body motion, path shape and preferred length are ours; Zhao plans two steps ahead, we plan one.
Limitation: with one ``L`` per tripod and the body moving ``L / 2``, the rear tripod cannot climb
the first riser once the front feet are on the landing (docs/stairs_gait.md).

Measured (bench/gait.py): ~890 leg configurations per step, 56 ms median per step on 2 busy cores.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType
from typing import Mapping, Sequence

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.geometry import invert_pose, transform_points

__all__ = [
    "GaitError",
    "GaitConfig",
    "FootFeasibility",
    "GaitParameters",
    "SwingCheck",
    "gait_parameters",
    "swing_trajectory",
    "body_path",
    "swing_collides",
    "segment_distances",
    "feet_from_joint_angles",
]


class GaitError(GraphcalError):
    """Bad input to the gait planner, or no feasible step."""


@dataclass(frozen=True)
class GaitConfig:
    """Parameters of the gait planner (module docstring). Lengths in metres.

    Attributes:
        max_step_length_m: largest step length considered (the gait's, and the legs' reach).
        nominal_step_length_m: step length of the steady gait on level ground; the preferred
            length of a step brings the swing feet ``nominal / 4`` ahead of their nominal stance.
        max_step_height_m: largest step height considered.
        near_zone_m, far_zone_m: Zhao's near and far zones of each surface (default 5 cm).
        lateral_margin_m: a foothold this far inside the tread's visible lateral extent at least.
        shin_radius_m: radius of the shin cylinder.
        edge_radius_m: radius of the stair-edge cylinders (edge rounding and model error).
        length_grid_m: step-length grid for the interference test.
        height_grid_m: step-height grid (refined once to half of it).
        length_margin_m: chosen ``L`` at least this far inside its feasible interval.
        height_margin_m: chosen ``H`` is the lowest feasible plus this (inside the interval).
        swing_samples: instants of the swing checked (plus its two ends).
        shin_samples: points along the shin for the solid test.
        joint_limit_margin_rad: joints must stay this far inside their limits (rad; m for prismatic).
        min_leg_singular_value: smallest singular value of the leg's position Jacobian (m/rad)
            allowed: keeps the leg away from full stretch (qingzhui: 0.16 in the nominal stance,
            0.06 at 1.5 cm short of full reach), which estimation errors would otherwise push it past.
        lift_fraction: fraction of the swing spent rising (and descending) (path shape).
        foot_snap_m: a foot within this height of a modelled surface stands on it (its height
            is set to the model's: foot and model positions carry errors of their own).
    """

    max_step_length_m: float = 0.30
    nominal_step_length_m: float = 0.20
    max_step_height_m: float = 0.20
    near_zone_m: float = 0.05
    far_zone_m: float = 0.05
    lateral_margin_m: float = 0.03
    shin_radius_m: float = 0.025
    edge_radius_m: float = 0.015
    length_grid_m: float = 0.01
    height_grid_m: float = 0.02
    length_margin_m: float = 0.01
    height_margin_m: float = 0.01
    swing_samples: int = 16
    shin_samples: int = 8
    joint_limit_margin_rad: float = 0.02
    min_leg_singular_value: float = 0.06
    lift_fraction: float = 0.3
    foot_snap_m: float = 0.03


@dataclass(frozen=True, eq=False)
class FootFeasibility:
    """One swing foot: its feasible step lengths and (for the chosen length) step heights.

    Attributes:
        foot: foot frame name.
        zone_intervals_m: step lengths (m) that land in a middle zone (tread zones only).
        step_length_intervals_m: step lengths (m) that also pass the interference test.
        step_height_intervals_m: step heights (m) with a collision-free, reachable swing for the
            chosen step length (empty if that length was not reached).
        p_world_lift: (3,) the foot's current (lift-off) position.
    """

    foot: str
    zone_intervals_m: tuple
    step_length_intervals_m: tuple
    step_height_intervals_m: tuple
    p_world_lift: np.ndarray


@dataclass(frozen=True, eq=False)
class GaitParameters:
    """The next step of the tripod gait.

    Attributes:
        swing_feet, stance_feet: the tripod that steps and the one that supports.
        feet: swing foot -> :class:`FootFeasibility`.
        stance_step_length_intervals_m: step lengths the stance tripod can carry the body through.
        step_length_intervals_m: intersection over the swing tripod and the stance reach.
        step_height_intervals_m: intersection of the swing feet's step heights at the chosen length.
        step_length_m, step_height_m: the chosen parameters.
        heading_world: (3,) unit horizontal walking direction.
        body_rise_m: the body's rise during the step.
        T_world_body_end: (4, 4) the body pose at the end of the swing.
        p_world_land: swing foot -> (3,) its foothold (height from the stairs model).
        lengths_tried: step-length candidates tried before one had a feasible height.
    """

    swing_feet: tuple
    stance_feet: tuple
    feet: Mapping[str, FootFeasibility]
    stance_step_length_intervals_m: tuple
    step_length_intervals_m: tuple
    step_height_intervals_m: tuple
    step_length_m: float
    step_height_m: float
    heading_world: np.ndarray
    body_rise_m: float
    T_world_body_end: np.ndarray
    p_world_land: Mapping[str, np.ndarray]
    lengths_tried: int = 1


@dataclass(frozen=True)
class SwingCheck:
    """Result of :func:`swing_collides`.

    Attributes:
        collides: True if the shin hits a stair edge or enters the staircase solid, or the leg
            cannot follow the path.
        edge_collision: the edge test failed (Zhao Eqs. 11-12).
        solid_collision: the solid test failed.
        reachable: the leg reaches every sample within its joint limits.
        min_edge_clearance_m: smallest (axis distance - radii) over the swing and the edges.
        min_solid_clearance_m: smallest (distance to the solid - shin radius) of the shin capsule
            (knee to foot ball) over the swing; 0 when touching (a foot on a tread), negative inside.
        worst_tau: swing phase (0..1) of the smallest edge clearance.
    """

    collides: bool
    edge_collision: bool
    solid_collision: bool
    reachable: bool
    min_edge_clearance_m: float
    min_solid_clearance_m: float
    worst_tau: float


# ----------------------------------------------------------------------------- geometry helpers
def segment_distances(p0, p1, q0, q1) -> np.ndarray:
    """Distances (m) between segments [p0, p1] and [q0, q1]; arrays (..., 3) broadcast together.

    The closest points are found on the segments (not on their infinite lines: Zhao's Eq. 11 uses
    the lines). Degenerate (zero-length) and parallel segments are handled.
    """
    p0, p1, q0, q1 = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (p0, p1, q0, q1)))
    d1 = p1 - p0
    d2 = q1 - q0
    r = p0 - q0
    a = np.einsum("...i,...i->...", d1, d1)
    e = np.einsum("...i,...i->...", d2, d2)
    f = np.einsum("...i,...i->...", d2, r)
    c = np.einsum("...i,...i->...", d1, r)
    b = np.einsum("...i,...i->...", d1, d2)
    eps = 1e-15
    safe = lambda x: np.where(np.abs(x) > eps, x, 1.0)  # noqa: E731
    denom = a * e - b * b
    # general case (Ericson, Real-Time Collision Detection 5.1.9): s from the lines, clamped
    s = np.where(denom > eps * np.maximum(a * e, eps), np.clip((b * f - c * e) / safe(denom), 0.0, 1.0), 0.0)
    t = (b * s + f) / safe(e)
    s = np.where(t < 0.0, np.clip(-c / safe(a), 0.0, 1.0), np.where(t > 1.0, np.clip((b - c) / safe(a), 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    # degenerate segments (points)
    point_q = e <= eps
    s = np.where(point_q, np.clip(-c / safe(a), 0.0, 1.0), s)
    t = np.where(point_q, 0.0, t)
    point_p = a <= eps
    s = np.where(point_p, 0.0, s)
    t = np.where(point_p, np.clip(f / safe(e), 0.0, 1.0), t)
    both = point_p & point_q
    s = np.where(both, 0.0, s)
    t = np.where(both, 0.0, t)
    diff = (p0 + s[..., None] * d1) - (q0 + t[..., None] * d2)
    return np.sqrt(np.einsum("...i,...i->...", diff, diff))


def swing_trajectory(p_world_lift, p_world_land, step_height_m, tau, *, lift_fraction: float = 0.3) -> np.ndarray:
    """Swing-foot positions (m, world) at swing phases ``tau`` (array in [0, 1]).

    ``step_height_m`` may be an array (broadcast against ``tau``: e.g. (H, 1) with (T,) gives
    (H, T, 3)). Path shape: module docstring.
    """
    from graphcal.models.kinematics import smoothstep

    p0 = np.asarray(p_world_lift, dtype=float)
    p1 = np.asarray(p_world_land, dtype=float)
    tau = np.asarray(tau, dtype=float)
    H = np.asarray(step_height_m, dtype=float)
    a = float(lift_fraction)
    u = smoothstep((tau - a / 2) / (1.0 - a), degree=3)  # horizontal progress
    z_top = max(p0[2], p1[2]) + H
    rise = smoothstep(tau / a, degree=3)
    fall = smoothstep((tau - (1.0 - a)) / a, degree=3)
    z = np.where(tau < 1.0 - a, p0[2] + (z_top - p0[2]) * rise, z_top + (p1[2] - z_top) * fall)
    u, z = np.broadcast_arrays(u, z)
    xy = p0[:2] + u[..., None] * (p1[:2] - p0[:2])
    return np.concatenate([xy, z[..., None]], axis=-1)


def body_path(T_world_body_start: np.ndarray, T_world_body_end: np.ndarray, tau) -> tuple[np.ndarray, np.ndarray]:
    """Body orientations (T, 3, 3) and origins (T, 3) (world, m) at phases ``tau``: the origin at
    constant velocity, the rotation by constant angular velocity (geodesic) from start to end."""
    from graphcal.geometry import axis_angle_from_matrix, so3_exp

    tau = np.atleast_1d(np.asarray(tau, dtype=float))
    T0 = np.asarray(T_world_body_start, dtype=float)
    T1 = np.asarray(T_world_body_end, dtype=float)
    axis, angle = axis_angle_from_matrix(T0[:3, :3].T @ T1[:3, :3])
    R = np.stack([T0[:3, :3] @ so3_exp(axis * angle * t) for t in tau])
    o = T0[:3, 3] + tau[:, None] * (T1[:3, 3] - T0[:3, 3])
    return R, o


@dataclass(frozen=True, eq=False)
class _Stairs:
    """The stairs model as the planner uses it, in the stairs frame (s, t, h)."""

    T_stairs_world: np.ndarray
    T_world_stairs: np.ndarray
    box_lo: np.ndarray  # (K, 3) tread columns (and the floor)
    box_hi: np.ndarray
    edges0: np.ndarray  # (E, 3) nosing segments, stairs frame
    edges1: np.ndarray
    surfaces: tuple  # (s_a, s_b, h, t_min, t_max) per surface along s, floor first; inf allowed


def _stairs_boxes(model) -> _Stairs:
    treads = sorted(model.treads, key=lambda t: t.s_front_m)
    if not treads:
        raise GaitError("gait: the stairs model has no treads")
    big = 1e3
    lo = [[-big, -big, -big]]
    hi = [[big, big, 0.0]]  # the floor: everything below h = 0
    e0, e1, surfaces = [], [], []
    surfaces.append((-np.inf, treads[0].s_front_m, 0.0, -np.inf, np.inf))
    for k, t in enumerate(treads):
        s_back = t.s_back_m
        lo.append([t.s_front_m, t.t_min_m, -big])
        hi.append([s_back, t.t_max_m, t.height_m])
        e0.append([t.s_front_m, t.t_min_m, t.height_m])
        e1.append([t.s_front_m, t.t_max_m, t.height_m])
        surfaces.append((t.s_front_m, s_back, t.height_m, t.t_min_m, t.t_max_m))
    last = treads[-1]
    if last.depth_complete:  # the floor again behind a complete last tread
        surfaces.append((last.s_back_m, np.inf, 0.0, -np.inf, np.inf))
    T_ws = np.asarray(model.T_world_stairs, dtype=float)
    return _Stairs(invert_pose(T_ws), T_ws, np.array(lo), np.array(hi), np.array(e0), np.array(e1), tuple(surfaces))


def _solid_distance(st: _Stairs, X_stairs: np.ndarray) -> np.ndarray:
    """Signed distance (m) of points (..., 3) (stairs frame) to the staircase solid (negative inside)."""
    X = X_stairs[..., None, :]  # (..., 1, 3)
    below = st.box_lo - X  # (..., K, 3)
    above = X - st.box_hi
    m = np.maximum(below, above)
    outside = np.sqrt(np.sum(np.maximum(m, 0.0) ** 2, axis=-1))
    inside = np.minimum(np.max(m, axis=-1), 0.0)
    return np.min(np.where(np.max(m, axis=-1) > 0, outside, inside), axis=-1)


def _surface_height(st: _Stairs, s: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Height (m) of the known surface at (s, t) and its index in ``st.surfaces`` (-1: unknown)."""
    s = np.asarray(s, dtype=float)
    t = np.asarray(t, dtype=float)
    h = np.full(s.shape, np.nan)
    idx = np.full(s.shape, -1)
    for i, (a, b, hh, t0, t1) in enumerate(st.surfaces):
        inside = (s >= a) & (s < b) & (t >= t0) & (t <= t1)
        h = np.where(inside, hh, h)
        idx = np.where(inside, i, idx)
    return h, idx


# ----------------------------------------------------------------------------- intervals
def _intersect(a: Sequence, b: Sequence) -> tuple:
    out = []
    for lo1, hi1 in a:
        for lo2, hi2 in b:
            lo, hi = max(lo1, lo2), min(hi1, hi2)
            if hi >= lo:
                out.append((lo, hi))
    return tuple(sorted(out))


def _runs(values: np.ndarray, ok: np.ndarray, step: float | None = None) -> tuple:
    """Intervals covered by the feasible grid values: each run of feasible samples -> [first, last]."""
    out = []
    i, n = 0, len(values)
    while i < n:
        if ok[i]:
            j = i
            while j + 1 < n and ok[j + 1]:
                j += 1
            out.append((float(values[i]), float(values[j])))
            i = j + 1
        else:
            i += 1
    return tuple(out)


def _zone_intervals(st: _Stairs, s0: float, t0: float, ds: float, dt: float, cfg: GaitConfig, L_max: float) -> tuple:
    """Step lengths L in [0, L_max] whose foothold (s0 + L ds, t0 + L dt) is in a middle zone."""
    out = []
    for a, b, _, tmin, tmax in st.surfaces:
        if ds >= 0:
            lo_s, hi_s = a + cfg.near_zone_m, b - cfg.far_zone_m
        else:
            lo_s, hi_s = a + cfg.far_zone_m, b - cfg.near_zone_m
        if hi_s < lo_s:
            continue
        # s0 + L ds in [lo_s, hi_s]
        if abs(ds) < 1e-12:
            L_lo, L_hi = (0.0, L_max) if lo_s <= s0 <= hi_s else (1.0, 0.0)
        else:
            r = sorted(((lo_s - s0) / ds, (hi_s - s0) / ds))
            L_lo, L_hi = r
        # lateral: t0 + L dt in [tmin + margin, tmax - margin]
        if np.isfinite(tmin) or np.isfinite(tmax):
            t_lo, t_hi = tmin + cfg.lateral_margin_m, tmax - cfg.lateral_margin_m
            if abs(dt) < 1e-12:
                if not t_lo <= t0 <= t_hi:
                    continue
            else:
                r = sorted(((t_lo - t0) / dt, (t_hi - t0) / dt))
                L_lo, L_hi = max(L_lo, r[0]), min(L_hi, r[1])
        L_lo, L_hi = max(L_lo, 0.0), min(L_hi, L_max)
        if L_hi >= L_lo:
            out.append((float(L_lo), float(L_hi)))
    return tuple(sorted(out))


# ----------------------------------------------------------------------------- leg checks
@dataclass(frozen=True, eq=False)
class _LegCtx:
    leg: object
    q_ref: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


def _leg_ctx(robot, foot: str, p_body_foot: np.ndarray, cfg: GaitConfig) -> _LegCtx:
    leg = robot.leg(foot)
    lo = np.where(np.isfinite(leg.lower), leg.lower, -np.inf) + cfg.joint_limit_margin_rad
    hi = np.where(np.isfinite(leg.upper), leg.upper, np.inf) - cfg.joint_limit_margin_rad
    mid = np.where(np.isfinite(leg.lower) & np.isfinite(leg.upper), (leg.lower + leg.upper) / 2, 0.0)
    # the branch of the zero configuration first (the simulator's nominal stance), else mid-range
    for q0 in (np.zeros(leg.n_joints), mid):
        q, ok, _, _, _ = _leg_ik(leg, np.asarray(p_body_foot, dtype=float)[None], q0, iterations=40)
        if bool(ok[0]):
            return _LegCtx(leg, q[0], lo, hi)
    raise GaitError(f"gait: foot {foot} cannot reach its current position {np.round(p_body_foot, 3).tolist()} (body frame)")


def _leg_ik(leg, p_body: np.ndarray, q0: np.ndarray, *, iterations: int = 8, ok_tol: float = 1e-4):
    """Batch position IK from ``q0`` for every target (m, body frame):
    :func:`graphcal.models.kinematics.newton_ik`, damped Gauss-Newton (1e-6) with steps limited to
    0.3 rad (m), until every residual is below ``ok_tol / 10``. ``ik_leg`` with its line search costs
    ~3x more here, and a planner needs only ``ok_tol`` (0.1 mm).

    Returns q (N, n), ok (N,) (residual < ok_tol), joint origins (N, n, 3), feet (N, 3) and the
    smallest singular value of the position Jacobian (N,) (m/rad; 0 for a stretched leg) at q."""
    from graphcal.models.kinematics import newton_ik

    sol = newton_ik(leg, p_body, q0, iterations=iterations, stop_tol=0.1 * ok_tol, damping=1e-6, max_step=0.3)
    sigma_min = np.linalg.svd(sol.J, compute_uv=False)[:, -1]
    return sol.q, sol.err < ok_tol, sol.origins_base, sol.p_base_foot, sigma_min


_CONTACT_TOL_M = 1e-3  # a capsule may touch the solid by this much (the foot standing on a tread)


def _shin_check(ctx: _LegCtx, st: _Stairs, R_world_body: np.ndarray, p_world_body: np.ndarray, p_world_foot: np.ndarray,
                cfg: GaitConfig):
    """Leg reach and shin clearance for many configurations of one leg.

    Args:
        R_world_body: (N, 3, 3) body orientations (or one (3, 3)).
        p_world_body: (N, 3) body origins; p_world_foot: (N, 3) foot positions.

    Returns:
        reachable (N,), edge clearance (N,) m, solid clearance (N,) m.
    """
    R = np.broadcast_to(R_world_body, (len(p_world_body), 3, 3))
    p_body = np.einsum("nji,nj->ni", R, p_world_foot - p_world_body)  # R^T (p - o)
    q, ok, origins, p_foot_b, sigma_min = _leg_ik(ctx.leg, p_body, ctx.q_ref)
    inside = np.all((q >= ctx.lo) & (q <= ctx.hi), axis=1) & (sigma_min >= cfg.min_leg_singular_value)
    knee_b = origins[:, -1]
    # to the stairs frame
    T_sw = st.T_stairs_world
    R_sb = np.einsum("ij,njk->nik", T_sw[:3, :3], R)
    o_s = p_world_body @ T_sw[:3, :3].T + T_sw[:3, 3]
    knee_s = np.einsum("nij,nj->ni", R_sb, knee_b) + o_s
    foot_s = np.einsum("nij,nj->ni", R_sb, p_foot_b) + o_s
    # Zhao Eqs. 11-12: shin axis vs every nosing axis
    if len(st.edges0):
        d = segment_distances(knee_s[:, None, :], foot_s[:, None, :], st.edges0[None], st.edges1[None])
        edge_clear = d.min(axis=1) - (cfg.shin_radius_m + cfg.edge_radius_m)
    else:
        edge_clear = np.full(len(q), np.inf)
    # solid: the shin capsule from the knee to the foot ball (radius r, its bottom at the foot
    # point: centre r above it), sampled; a foot standing on a tread touches it exactly
    r = cfg.shin_radius_m
    ball = foot_s + np.array([0.0, 0.0, r])
    f = np.linspace(0.0, 1.0, cfg.shin_samples)
    pts = knee_s[:, None, :] + f[None, :, None] * (ball - knee_s)[:, None, :]  # (N, S, 3)
    solid_clear = np.min(_solid_distance(st, pts), axis=1) - r
    solid_clear = np.where(solid_clear >= -_CONTACT_TOL_M, np.maximum(solid_clear, 0.0), solid_clear)
    return ok & inside, edge_clear, solid_clear


# ----------------------------------------------------------------------------- public API
def feet_from_joint_angles(robot, T_world_body: np.ndarray, q_legs: Mapping[str, np.ndarray]) -> dict:
    """foot -> p_world_foot (3,) m from joint angles (foot -> (n,) rad, the leg's joint order)."""
    from graphcal.models.kinematics import foot_positions

    T = np.asarray(T_world_body, dtype=float)
    return {f: transform_points(T, foot_positions(robot.leg(f), np.asarray(q, dtype=float))[None])[0] for f, q in q_legs.items()}


def _groups_of(robot, stance_group, groups):
    if groups is None:
        from graphcal.models.builtin import BUILTIN_MODELS, builtin_info

        if robot.name not in BUILTIN_MODELS or not builtin_info(robot.name).gait_groups:
            raise GaitError(f"gait: robot {robot.name!r} has no built-in tripod groups; pass groups=(group_A, group_B)")
        groups = builtin_info(robot.name).gait_groups
    groups = tuple(tuple(g) for g in groups)
    if len(groups) != 2:
        raise GaitError(f"gait: groups must be two tuples of feet, got {groups!r}")
    if isinstance(stance_group, str) and stance_group.upper() in ("A", "B"):
        i = 0 if stance_group.upper() == "A" else 1
    else:
        g = tuple(stance_group)
        if set(g) == set(groups[0]):
            i = 0
        elif set(g) == set(groups[1]):
            i = 1
        else:
            raise GaitError(f"gait: stance_group must be 'A', 'B' or one of {groups}, got {stance_group!r}")
    for f in groups[0] + groups[1]:
        if f not in robot.feet:
            raise GaitError(f"gait: foot {f!r} of the groups is not a foot of {robot.name!r} ({', '.join(robot.feet)})")
    return groups[i], groups[1 - i]


def _nominal_stance(robot, feet, nominal, feet_w, T_wb) -> dict:
    if nominal is None:
        from graphcal.models.builtin import BUILTIN_MODELS, builtin_info

        if robot.name in BUILTIN_MODELS:
            nominal = builtin_info(robot.name).nominal_stance
        else:
            nominal = {f: T_wb[:3, :3].T @ (feet_w[f] - T_wb[:3, 3]) for f in feet}
    out = {}
    for f in feet:
        if f not in nominal:
            raise GaitError(f"gait: nominal_p_body_feet has no entry for foot {f!r}")
        out[f] = np.asarray(nominal[f], dtype=float)
    return out


def _feet_line(points: np.ndarray, hd: np.ndarray) -> tuple[float, float]:
    """Least-squares line ``z = a + b s`` through foot positions (N, 3), ``s = p . hd`` (m)."""
    s = points @ hd
    z = points[:, 2]
    if np.ptp(s) < 1e-6:
        return float(z.mean()), 0.0
    b = float(np.cov(s, z, bias=True)[0, 1] / np.var(s))
    return float(z.mean() - b * s.mean()), b


def _body_after(T_wb: np.ndarray, feet_now: np.ndarray, feet_after: np.ndarray, L: float, hd: np.ndarray,
                max_pitch_rad: float) -> np.ndarray:
    """The body pose at the end of a step (module docstring): ``L / 2`` along the heading, its
    height above the line fitted to the feet kept, pitched to that line's slope (roll, yaw kept)."""
    from graphcal.geometry import matrix_from_rpy, rpy_from_matrix

    a0, b0 = _feet_line(feet_now, hd)
    o0 = T_wb[:3, 3]
    h0 = o0[2] - (a0 + b0 * (o0 @ hd))
    a1, b1 = _feet_line(feet_after, hd)
    o1 = o0 + 0.5 * L * hd
    o1[2] = a1 + b1 * (o1 @ hd) + h0
    roll, _, yaw = rpy_from_matrix(T_wb[:3, :3])
    pitch = float(np.clip(-np.arctan(b1), -max_pitch_rad, max_pitch_rad))  # climbing: nose up (< 0)
    T = np.eye(4)
    T[:3, :3] = matrix_from_rpy([roll, pitch, yaw])
    T[:3, 3] = o1
    return T


def _feet_on_model(st, feet: tuple, p_world_feet: Mapping[str, np.ndarray], cfg: GaitConfig) -> dict:
    """foot -> (3,) world position (m) of each of ``feet``, checked; the feet stand on the model's
    surfaces: heights within ``cfg.foot_snap_m`` of one are set to it (the model and the feet come
    from estimates with errors of their own)."""
    feet_w = {}
    for f in feet:
        if f not in p_world_feet:
            raise GaitError(f"gait: p_world_feet has no position for foot {f!r}")
        p = np.asarray(p_world_feet[f], dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise GaitError(f"gait: p_world_feet[{f!r}] must be a finite 3-vector, got {p_world_feet[f]!r}")
        feet_w[f] = p
    for f, p in feet_w.items():
        s_f, t_f, h_f = (st.T_stairs_world @ np.r_[p, 1.0])[:3]
        h_model, _ = _surface_height(st, np.array([s_f]), np.array([t_f]))
        if np.isfinite(h_model[0]) and abs(h_model[0] - h_f) <= cfg.foot_snap_m:
            feet_w[f] = st.T_world_stairs[:3, :3] @ np.array([s_f, t_f, h_model[0]]) + st.T_world_stairs[:3, 3]
    return feet_w


def _horizontal_heading(T_wb: np.ndarray, heading_world) -> np.ndarray:
    """(3,) unit horizontal walking direction (world): ``heading_world`` or the body's x axis, made
    horizontal."""
    hd = T_wb[:3, 0] if heading_world is None else np.asarray(heading_world, dtype=float)
    hd = np.array([hd[0], hd[1], 0.0])
    if np.linalg.norm(hd) < 1e-9:
        raise GaitError("gait: the heading is vertical or zero")
    return hd / np.linalg.norm(hd)


def _foothold(st, p_world_foot: np.ndarray, ds: float, dt: float, L) -> np.ndarray:
    """World footholds (.., 3) m of a swing foot now at ``p_world_foot`` after a step ``L`` (m):
    ``ds``, ``dt`` the along-stairs and lateral change per metre of step; height from the model
    (NaN off it)."""
    L = np.asarray(L, dtype=float)
    s0, t0 = (st.T_stairs_world @ np.r_[p_world_foot, 1.0])[:2]
    h, _ = _surface_height(st, s0 + L * ds, t0 + L * dt)
    X = np.stack([s0 + L * ds, t0 + L * dt, h], axis=-1)
    return X @ st.T_world_stairs[:3, :3].T + st.T_world_stairs[:3, 3]


def _bodies_per_length(T_wb: np.ndarray, feet_w: dict, land: dict, stance: tuple, all_feet: tuple,
                       L_grid: np.ndarray, known: np.ndarray, hd: np.ndarray, max_pitch: float):
    """The body at the end of the swing (R_end (nL, 3, 3), o_end (nL, 3) m) and its origin at the
    end of the following stance (o_next (nL, 3) m), per step length of ``L_grid`` (the start pose
    where a foothold is ``known`` to be off the model). ``land``: swing foot -> (nL, 3) footholds."""
    nL = len(L_grid)
    R0 = T_wb[:3, :3]
    o0 = T_wb[:3, 3]
    feet_now = np.array([feet_w[f] for f in all_feet])
    R_end = np.empty((nL, 3, 3))
    o_end = np.empty((nL, 3))
    o_next = np.empty((nL, 3))
    for i, L in enumerate(L_grid):
        if not known[i]:
            R_end[i], o_end[i], o_next[i] = R0, o0, o0
            continue
        after = np.array([feet_w[f] if f in stance else land[f][i] for f in all_feet])
        T1 = _body_after(T_wb, feet_now, after, L, hd, max_pitch)
        R_end[i], o_end[i] = T1[:3, :3], T1[:3, 3]
        _, b1 = _feet_line(after, hd)
        o_next[i] = o_end[i] + 0.5 * L * hd + np.array([0.0, 0.0, b1 * 0.5 * L])
    return R_end, o_end, o_next


def gait_parameters(
    robot,
    T_world_body: np.ndarray,
    stance_group,
    stairs,
    p_world_feet: Mapping[str, np.ndarray],
    *,
    groups: Sequence[Sequence[str]] | None = None,
    heading_world: np.ndarray | None = None,
    nominal_p_body_feet: Mapping[str, np.ndarray] | None = None,
    config: GaitConfig = GaitConfig(),
) -> GaitParameters:
    """Step length and step height of the next step (module docstring).

    Args:
        robot: :class:`graphcal.models.robot.RobotModel` (legs from the body frame).
        T_world_body: (4, 4) the body pose now (start of the swing), m.
        stance_group: the tripod now in stance, ``"A"`` / ``"B"`` (Zhao: A = MF, RB, LB;
            B = MB, RF, LF) or a tuple of its feet; the other tripod steps.
        stairs: :class:`graphcal.locomotion.stairs.StairsModel` (estimated, or
            :func:`graphcal.locomotion.stairs.stairs_model_from_steps`).
        p_world_feet: foot -> (3,) world position now (m), every foot of both tripods (e.g.
            :func:`feet_from_joint_angles`).
        groups: the two tripods; default: the built-in model's ``gait_groups``.
        heading_world: (3,) walking direction; default: the body's x axis, made horizontal.
        nominal_p_body_feet: foot -> (3,) nominal stance in the body frame (m), which sets the
            preferred step length; default: the built-in model's nominal stance, else the feet's
            current places.
        config: :class:`GaitConfig`.

    Returns:
        :class:`GaitParameters`.

    Raises:
        GaitError: bad input (unknown feet, a foot out of reach), or no step length with a
            feasible step height.
    """
    cfg = config
    T_wb = np.asarray(T_world_body, dtype=float)
    if T_wb.shape != (4, 4) or not np.all(np.isfinite(T_wb)):
        raise GaitError(f"gait: T_world_body must be a finite 4x4 pose, got shape {T_wb.shape}")
    stance, swing = _groups_of(robot, stance_group, groups)
    st = _stairs_boxes(stairs)
    feet_w = _feet_on_model(st, stance + swing, p_world_feet, cfg)
    hd = _horizontal_heading(T_wb, heading_world)
    ds = float(hd @ st.T_world_stairs[:3, 0])  # along-stairs change per metre of step
    dt = float(hd @ st.T_world_stairs[:3, 1])
    R0 = T_wb[:3, :3]
    o0 = T_wb[:3, 3]
    max_pitch = np.radians(30.0)
    all_feet = stance + swing
    feet_now = np.array([feet_w[f] for f in all_feet])

    ctx = {f: _leg_ctx(robot, f, R0.T @ (feet_w[f] - o0), cfg) for f in all_feet}
    nominal = _nominal_stance(robot, all_feet, nominal_p_body_feet, feet_w, T_wb)
    L_grid = np.arange(0.0, cfg.max_step_length_m + 1e-9, cfg.length_grid_m)
    nL = len(L_grid)

    zone = {}
    land = {}
    for f in swing:
        s0, t0 = (st.T_stairs_world @ np.r_[feet_w[f], 1.0])[:2]
        zone[f] = _zone_intervals(st, s0, t0, ds, dt, cfg, cfg.max_step_length_m)
        land[f] = _foothold(st, feet_w[f], ds, dt, L_grid)  # (nL, 3)
    known = np.all([np.isfinite(land[f][:, 2]) for f in swing], axis=0)

    R_end, o_end, o_next = _bodies_per_length(T_wb, feet_w, land, stance, all_feet, L_grid, known, hd, max_pitch)
    feas_L = {}
    for f in swing:
        P = np.nan_to_num(np.vstack([land[f], land[f]]))
        reach, e_cl, s_cl = _shin_check(ctx[f], st, np.concatenate([R_end, R_end]), np.vstack([o_end, o_next]), P, cfg)
        clear = (e_cl >= 0) & (s_cl >= 0)
        # touchdown: reach and clearance; end of the next stance: clearance where reachable (its
        # reach is the next step's stance check, which also chooses how far the body goes)
        good = reach[:nL] & clear[:nL] & (clear[nL:] | ~reach[nL:]) & known
        feas_L[f] = _intersect(zone[f], _runs(L_grid, good, cfg.length_grid_m))
    stance_ok = known.copy()
    for f in stance:
        reach, e_cl, s_cl = _shin_check(ctx[f], st, R_end, o_end, np.repeat(feet_w[f][None], nL, axis=0), cfg)
        stance_ok &= reach & (e_cl >= 0) & (s_cl >= 0)
    stance_iv = _runs(L_grid, stance_ok, cfg.length_grid_m)
    common = stance_iv
    for f in swing:
        common = _intersect(common, feas_L[f])
    if not common:
        raise GaitError(
            "gait: no step length lands every swing foot in a middle zone without interference; "
            + "; ".join(f"{f}: {[(round(a, 3), round(b, 3)) for a, b in feas_L[f]]}" for f in swing)
            + f"; stance reach {[(round(a, 3), round(b, 3)) for a, b in stance_iv]}"
        )

    # preferred length: the swing feet end L_nom / 4 ahead of their nominal place under the body
    # (a steady tripod gait's touchdown), e = e0 + L / 2 = L_nom / 4; lagging feet catch up
    e0 = np.min([(feet_w[f] - o0 - R0 @ nominal[f]) @ hd for f in swing])
    L_pref = float(np.clip(cfg.nominal_step_length_m / 2 - 2 * e0, 0.0, cfg.max_step_length_m))
    cands = []
    for lo, hi in common:
        m = min(cfg.length_margin_m, (hi - lo) / 2)
        cands.append(float(np.clip(L_pref, lo + m, hi - m)))
    cands = sorted(set(cands), key=lambda L: (abs(L - L_pref), -L))

    tau = np.linspace(0.0, 1.0, cfg.swing_samples + 2)
    H_coarse = np.arange(0.0, cfg.max_step_height_m + 1e-9, cfg.height_grid_m)
    for n_try, L in enumerate(cands, start=1):
        p_land = {f: _foothold(st, feet_w[f], ds, dt, L) for f in swing}
        after = np.array([feet_w[f] if f in stance else p_land[f] for f in all_feet])
        T_end = _body_after(T_wb, feet_now, after, L, hd, max_pitch)
        R_path, o_path = body_path(T_wb, T_end, tau)
        H_iv = {f: _feasible_heights(ctx[f], st, R_path, o_path, feet_w[f], p_land[f], H_coarse, tau, cfg) for f in swing}
        H_common = H_iv[swing[0]]
        for f in swing[1:]:
            H_common = _intersect(H_common, H_iv[f])
        if not H_common:
            continue
        lo, hi = H_common[0]
        H = float(min(lo + cfg.height_margin_m, hi))
        feet = {f: FootFeasibility(f, zone[f], feas_L[f], H_iv[f], feet_w[f].copy()) for f in swing}
        return GaitParameters(
            swing_feet=tuple(swing),
            stance_feet=tuple(stance),
            feet=MappingProxyType(feet),
            stance_step_length_intervals_m=stance_iv,
            step_length_intervals_m=common,
            step_height_intervals_m=H_common,
            step_length_m=L,
            step_height_m=H,
            heading_world=hd,
            body_rise_m=float(T_end[2, 3] - o0[2]),
            T_world_body_end=T_end,
            p_world_land=MappingProxyType(p_land),
            lengths_tried=n_try,
        )
    raise GaitError(
        f"gait: no feasible step height up to {cfg.max_step_height_m} m for any of the step lengths "
        f"{[round(c, 3) for c in cands]} m"
    )


def _feasible_heights(ctx, st, R_path, o_path, p_lift, p_land, H_coarse, tau, cfg) -> tuple:
    """Intervals of step heights whose whole swing is reachable and collision-free: the coarse grid,
    then one refinement half a grid step below the start of each feasible run."""

    def check(Hs: np.ndarray) -> np.ndarray:
        P = swing_trajectory(p_lift, p_land, Hs[:, None], tau, lift_fraction=cfg.lift_fraction)  # (nH, T, 3)
        nH, T = P.shape[:2]
        R = np.broadcast_to(R_path, (nH, T, 3, 3)).reshape(-1, 3, 3)
        B = np.broadcast_to(o_path, P.shape).reshape(-1, 3)
        reach, e_cl, s_cl = _shin_check(ctx, st, R, B, P.reshape(-1, 3), cfg)
        return (reach & (e_cl >= 0) & (s_cl >= 0)).reshape(nH, T).all(axis=1)

    ok = check(H_coarse)
    extra = [h - cfg.height_grid_m / 2 for i, h in enumerate(H_coarse) if ok[i] and i > 0 and not ok[i - 1]]
    if extra:
        H_all = np.concatenate([H_coarse, extra])
        ok_all = np.concatenate([ok, check(np.array(extra))])
        order = np.argsort(H_all)
        return _runs(H_all[order], ok_all[order], cfg.height_grid_m / 2)
    return _runs(H_coarse, ok, cfg.height_grid_m)


def swing_collides(
    robot,
    foot: str,
    T_world_body_start: np.ndarray,
    T_world_body_end: np.ndarray,
    p_world_lift: np.ndarray,
    p_world_land: np.ndarray,
    step_height_m: float,
    stairs,
    *,
    config: GaitConfig = GaitConfig(),
    samples: int = 60,
) -> SwingCheck:
    """Check one swing of ``foot`` against the stairs: the shin (last joint origin -> foot, radius
    ``config.shin_radius_m``) against every nosing cylinder (Zhao Eqs. 11-12, segment distances)
    and against the staircase solid, at ``samples`` instants, the body moving along
    :func:`body_path` and the leg following the foot path (:func:`swing_trajectory`) by IK from its
    configuration at lift-off.

    Args:
        robot: the robot model. foot: the swinging foot.
        T_world_body_start, T_world_body_end: (4, 4) body poses at lift-off and touchdown.
        p_world_lift, p_world_land: (3,) footholds (m). step_height_m: H (m).
        stairs: a :class:`graphcal.locomotion.stairs.StairsModel` (e.g. the true one, to validate a plan).
        config: radii and path shape. samples: instants checked.

    Returns:
        :class:`SwingCheck`.
    """
    cfg = config
    T0 = np.asarray(T_world_body_start, dtype=float)
    T1 = np.asarray(T_world_body_end, dtype=float)
    p0 = np.asarray(p_world_lift, dtype=float)
    p1 = np.asarray(p_world_land, dtype=float)
    if foot not in robot.feet:
        raise GaitError(f"swing_collides: {foot!r} is not a foot of {robot.name!r} ({', '.join(robot.feet)})")
    st = _stairs_boxes(stairs)
    tau = np.linspace(0.0, 1.0, max(int(samples), 2))
    try:
        ctx = _leg_ctx(robot, foot, T0[:3, :3].T @ (p0 - T0[:3, 3]), cfg)
    except GaitError:  # the leg cannot even reach the lift-off point
        return SwingCheck(True, False, False, False, float("nan"), float("nan"), 0.0)
    P = swing_trajectory(p0, p1, float(step_height_m), tau, lift_fraction=cfg.lift_fraction)
    R, B = body_path(T0, T1, tau)
    reach, e_cl, s_cl = _shin_check(ctx, st, R, B, P, cfg)
    edge_hit = bool(np.any(e_cl < 0))
    solid_hit = bool(np.any(s_cl < 0))
    reachable = bool(np.all(reach))
    i = int(np.argmin(e_cl))
    return SwingCheck(
        collides=edge_hit or solid_hit or not reachable,
        edge_collision=edge_hit,
        solid_collision=solid_hit,
        reachable=reachable,
        min_edge_clearance_m=float(e_cl[i]),
        min_solid_clearance_m=float(np.min(s_cl)),
        worst_tau=float(tau[i]),
    )
