"""A climb up perceived stairs planned step by step with :func:`graphcal.planning.gait.gait_parameters`
(Zhao et al. 2020, section 3.3), and the numbers a plan is judged by: each foothold's distance to
the nearest nosing and riser, the swing's clearance over each nosing, the static stability margin.
What ``graphcal plan-gait`` runs (:mod:`graphcal.commands.plan_gait`, docs/stairs_gait.md).

Frames and units
----------------
World z up (the frame of the estimate the stairs model was built in); the stairs frame of the
model (:class:`graphcal.locomotion.stairs.StairsModel` ``T_world_stairs``): x (``s``) up the stairs
from the foot of the first riser, y (``t``) left when climbing, z (``h``) up from the floor. Metres
and radians; poses 4x4.

The climb
---------
:func:`plan_climb` calls the planner once per step, tripods alternating, each step starting where
the previous one ended (the planned footholds and body pose: a plan, not a simulation), walking
along the stairs x axis. It stops when every foot stands on the top tread (``climbed``), when two
steps in a row (one per tripod) are shorter than ``min_step_length_m`` (``stalled``: the planner's
known limit, the rear tripod does not climb the first riser once the front feet are on the
landing; docs/stairs_gait.md), when the planner finds no feasible step (``no feasible step``), or
after ``max_steps``. The non-advancing steps of a stall are not part of the plan.

What is trusted (:func:`tread_trust`)
-------------------------------------
A foothold must never rest on a guessed edge. A tread of the model is ``seen`` when its depth is
complete (both its risers fitted) and it has at least ``min_tread_points`` inliers and a visible
width. The *top* tread with an incomplete depth but a fitted front riser (the landing: nothing
behind it to see) is ``seen part only``: the planner places feet only on its seen part, at least
``GaitConfig.far_zone_m`` inside the end of what was seen (its true back edge lies beyond that
end), and the plan carries a warning naming it. Any other incomplete tread (its back riser, hence
the next tread's nosing, not seen), and any tread with too few points or no visible width, is
``refused``: :func:`plan_climb` raises, naming the tread (its edges would be guesses).

Checks (per swing foot, against the model the plan was made on)
---------------------------------------------------------------
* **Edge distances** (:func:`edge_distances`), in the side view (the vertical plane along the
  stairs): the foothold's distance to every nosing (a point ``(s_front, h)``) and every riser (the
  segment ``s = s_front``, ``h`` from the level below to the tread), the smallest of each.
* **Clearance over each nosing** (:func:`swing_edge_clearances`): the smallest distance over the
  swing between the shin's axis (last joint origin -> foot) and each nosing segment, minus the shin
  and edge radii (Zhao Eqs. 11-12, segment distances as in the planner), the leg following the
  planned path by IK (:func:`graphcal.models.kinematics.ik_leg`) at ``check_samples`` instants;
  with :func:`graphcal.planning.gait.swing_collides` for the staircase solid.
* **Static stability margin** (:func:`stability_margin`): the smallest signed distance (positive
  inside) of the centre of mass's ground projection to the edges of the stance tripod's support
  triangle over the swing (the body moving along :func:`graphcal.planning.gait.body_path`). The
  models carry no mass distribution: the body origin stands for the centre of mass.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from types import MappingProxyType
from typing import Mapping, Sequence

import numpy as np

from graphcal.geometry import invert_pose, rpy_from_matrix
from graphcal.planning.gait import (
    GaitConfig,
    GaitError,
    GaitParameters,
    SwingCheck,
    body_path,
    gait_parameters,
    segment_distances,
    swing_collides,
    swing_trajectory,
)

__all__ = [
    "ClimbConfig",
    "TreadTrust",
    "FootholdCheck",
    "ClimbStep",
    "ClimbPlan",
    "stairs_model_from_json",
    "tread_trust",
    "trust_warnings",
    "refuse_untrusted",
    "plan_climb",
    "edge_distances",
    "swing_edge_clearances",
    "stability_margin",
    "body_height_over_feet",
    "choose_start",
    "first_swing_group",
    "OUTCOMES",
]

#: how a climb ends (:func:`plan_climb`)
OUTCOMES = ("climbed", "stalled", "no feasible step", "max steps")


@dataclass(frozen=True)
class ClimbConfig:
    """The climb around the planner (module docstring).

    Attributes:
        max_steps: most steps planned.
        min_step_length_m: a step shorter than this does not advance; two in a row: stalled.
        min_tread_points: a tread with fewer inliers is not trusted (the stairs model needs 150 to
            find a plane at all: ``StairsModelConfig.min_plane_points``).
        check_samples: swing instants of the clearance checks.
        on_tread_tol_m: a foot this close to a tread's height (and within its extent) stands on it.
    """

    max_steps: int = 40
    min_step_length_m: float = 0.02
    min_tread_points: int = 150
    check_samples: int = 60
    on_tread_tol_m: float = 0.01


@dataclass(frozen=True)
class TreadTrust:
    """How far a tread of the model is trusted (:func:`tread_trust`).

    Attributes:
        index: the tread's index (0 lowest). status: ``seen``, ``seen part only`` or ``refused``.
        reason: why it is not ``seen`` (empty when it is).
    """

    index: int
    status: str
    reason: str


@dataclass(frozen=True, eq=False)
class FootholdCheck:
    """One swing foot of a step, checked against the model (module docstring).

    Attributes:
        foot: the foot. p_world_lift, p_world_foot: (3,) lift-off point and foothold (world, m).
        p_stairs_foot: (3,) the foothold in the stairs frame (m).
        surface: the tread it stands on (index), -1 for the floor, None off the model.
        nosing_distance_m, nearest_nosing: distance (m) to the nearest nosing and that tread's index.
        riser_distance_m, nearest_riser: the same for the risers (riser k is below tread k).
        lateral_margin_m: distance to the nearer lateral end of its tread's visible extent (inf on
            the floor).
        seen_end_distance_m: on a ``seen part only`` tread, the distance to the end of what was
            seen (NaN elsewhere).
        edge_clearances_m: (E,) the swing's clearance over each nosing (tread order; m; NaN where
            the leg cannot follow the path).
        swing: :func:`graphcal.planning.gait.swing_collides` on the model.
    """

    foot: str
    p_world_lift: np.ndarray
    p_world_foot: np.ndarray
    p_stairs_foot: np.ndarray
    surface: int | None
    nosing_distance_m: float
    nearest_nosing: int
    riser_distance_m: float
    nearest_riser: int
    lateral_margin_m: float
    seen_end_distance_m: float
    edge_clearances_m: np.ndarray
    swing: SwingCheck


@dataclass(frozen=True, eq=False)
class ClimbStep:
    """One planned step.

    Attributes:
        index: 0 for the first. stance_group: ``A`` or ``B`` (the tripod in stance; the other swings).
        params: the planner's :class:`graphcal.planning.gait.GaitParameters`.
        T_world_body_start: (4, 4) the body at lift-off. p_world_feet_start: foot -> (3,) every foot then.
        planning_s: the planner's time for this step (s).
        footholds: the swing feet's :class:`FootholdCheck`.
        stability_margin_m: smallest static stability margin over the swing (m; module docstring).
        body_height_m: the body origin's height above the line fitted to the six feet along the
            heading, at the end of the swing (what the planner keeps; m).
        body_pitch_rad: the body's pitch at the end of the swing, in the stairs frame (rad; the
            rotation about y: climbing nose up is negative).
    """

    index: int
    stance_group: str
    params: GaitParameters
    T_world_body_start: np.ndarray
    p_world_feet_start: Mapping[str, np.ndarray]
    planning_s: float
    footholds: tuple
    stability_margin_m: float
    body_height_m: float
    body_pitch_rad: float


@dataclass(frozen=True, eq=False)
class ClimbPlan:
    """A planned climb (:func:`plan_climb`).

    Attributes:
        steps: the :class:`ClimbStep` s, in order.
        outcome: one of :data:`OUTCOMES`. reason: what stopped it, one sentence.
        T_world_body_end: (4, 4) the body after the last step. p_world_feet_end: foot -> (3,).
        trust: the :class:`TreadTrust` of every tread.
        heading_world: (3,) the walking direction (the stairs x axis, horizontal).
    """

    steps: tuple
    outcome: str
    reason: str
    T_world_body_end: np.ndarray
    p_world_feet_end: Mapping[str, np.ndarray]
    trust: tuple
    heading_world: np.ndarray


# ----------------------------------------------------------------------------- the model
def _vec(doc: Mapping, key: str, n: int, where: str) -> np.ndarray:
    v = np.asarray(doc.get(key), dtype=float) if doc.get(key) is not None else np.full(n, np.nan)
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise GaitError(f"{where}: {key} must be {n} finite numbers, got {doc.get(key)!r}")
    return v


def _num(doc: Mapping, key: str, where: str) -> float:
    v = doc.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise GaitError(f"{where}: {key} must be a finite number, got {v!r}")
    return float(v)


def _plane(doc: Mapping, key: str, where: str) -> tuple:
    p = doc.get(key)
    if not isinstance(p, Mapping):
        raise GaitError(f"{where}: {key} must be a plane {{n, d_m}}, got {p!r}")
    return _vec(p, "n", 3, f"{where} {key}"), _num(p, "d_m", f"{where} {key}")


def stairs_model_from_json(doc: Mapping, *, source: str = "stairs.json"):
    """The :class:`graphcal.locomotion.stairs.StairsModel` of a ``stairs.json`` document
    (:func:`graphcal.report.stairs_json.stairs_to_json`). The treads' extents in the stairs frame,
    which the file does not hold, are recovered: ``s_front`` from the nosing point (at the tread's
    lateral middle), ``s_back = s_front + depth`` (the visible end when the depth is incomplete),
    ``t`` from the nosing point +- half the visible width.

    Raises:
        GaitError: the document has an ``error`` (the model failed), no treads, or a malformed field
            (``source`` and the field named).
    """
    from graphcal.locomotion.stairs import Riser, StairsModel, Tread

    if not isinstance(doc, Mapping):
        raise GaitError(f"{source}: expected a JSON object, got {type(doc).__name__}")
    if doc.get("error"):
        raise GaitError(f"{source}: graphcal track could not model the stairs: {doc['error']}")
    T = np.asarray(doc.get("T_world_stairs"), dtype=float) if doc.get("T_world_stairs") is not None else None
    if T is None or T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise GaitError(f"{source}: T_world_stairs must be a 4x4 pose, got {doc.get('T_world_stairs')!r}")
    T_sw = invert_pose(T)
    treads = []
    raw = doc.get("treads")
    if not isinstance(raw, list) or not raw:
        raise GaitError(f"{source}: no treads (the stairs model found no step)")
    for k, t in enumerate(raw):
        where = f"{source}: treads[{k}]"
        if not isinstance(t, Mapping):
            raise GaitError(f"{where}: expected an object, got {t!r}")
        p_e = _vec(t, "p_world_edge_m", 3, where)
        s_e, t_e, _ = (T_sw @ np.r_[p_e, 1.0])[:3]
        depth, width = _num(t, "depth_m", where), _num(t, "width_m", where)
        complete = t.get("depth_complete")
        if not isinstance(complete, bool):
            raise GaitError(f"{where}: depth_complete must be true or false, got {complete!r}")
        n_in = t.get("n_inliers")
        if isinstance(n_in, bool) or not isinstance(n_in, int):
            raise GaitError(f"{where}: n_inliers must be an integer, got {n_in!r}")
        treads.append(Tread(
            index=int(t.get("index", k)), height_m=_num(t, "height_m", where), depth_m=depth,
            depth_complete=complete, width_m=width, p_world_edge=p_e,
            edge_direction_world=_vec(t, "edge_direction_world", 3, where),
            edge_from_riser=bool(t.get("edge_from_riser", False)), plane_world=_plane(t, "plane_world", where),
            n_inliers=n_in, s_front_m=float(s_e), s_back_m=float(s_e + depth),
            t_min_m=float(t_e - width / 2), t_max_m=float(t_e + width / 2)))
    risers = []
    for k, r in enumerate(doc.get("risers") or []):
        where = f"{source}: risers[{k}]"
        risers.append(Riser(_plane(r, "plane_world", where), _num(r, "s_m", where), _num(r, "h_low_m", where),
                            _num(r, "h_high_m", where), int(r.get("n_inliers", 0))))
    return StairsModel(tuple(sorted(treads, key=lambda t: t.height_m)), tuple(risers),
                       _plane(doc, "floor_plane_world", source), 0, T)


def tread_trust(stairs, *, min_tread_points: int = 150) -> tuple[TreadTrust, ...]:
    """:class:`TreadTrust` per tread of the model, lowest first (module docstring)."""
    treads = sorted(stairs.treads, key=lambda t: t.height_m)
    out = []
    for k, t in enumerate(treads):
        top = k == len(treads) - 1
        problems = []
        if t.n_inliers < min_tread_points:
            problems.append(f"{t.n_inliers} points (fewer than {min_tread_points})")
        if not t.width_m > 0:
            problems.append("no visible width")
        if not t.edge_from_riser:
            problems.append("its nosing comes from its points, not from a fitted riser")
        if problems:
            out.append(TreadTrust(t.index, "refused", "; ".join(problems)))
        elif not t.depth_complete and not top:
            out.append(TreadTrust(t.index, "refused", "depth incomplete: the riser behind it, and so the next "
                                                      "tread's nosing, was not seen"))
        elif not t.depth_complete:
            out.append(TreadTrust(t.index, "seen part only",
                                  f"depth incomplete: its back edge was not seen (seen {t.depth_m:.3f} m deep)"))
        else:
            out.append(TreadTrust(t.index, "seen", ""))
    return tuple(out)


def trust_warnings(trust: Sequence[TreadTrust], gait: GaitConfig = GaitConfig()) -> tuple[str, ...]:
    """One warning per ``seen part only`` tread: what was not seen and the margin the plan keeps."""
    return tuple(
        f"tread {t.index} (the top one): {t.reason}; footholds only on its seen part, at least "
        f"{gait.far_zone_m:.3f} m inside the end of what was seen (the margin the plan can guarantee there)"
        for t in trust if t.status == "seen part only")


def refuse_untrusted(trust: Sequence[TreadTrust], *, source: str = "the stairs model") -> None:
    """Raise :class:`graphcal.planning.gait.GaitError` naming the first ``refused`` tread of ``source`` (one line)."""
    bad = [t for t in trust if t.status == "refused"]
    if bad:
        t = bad[0]
        more = f" (and tread{'s' if len(bad) > 2 else ''} {', '.join(str(b.index) for b in bad[1:])})" if len(bad) > 1 else ""
        raise GaitError(f"tread {t.index} of {source} is not seen well enough to step on: {t.reason}{more}; "
                        "refusing to place footholds on a guessed edge (track a walk whose views show it)")


# ----------------------------------------------------------------------------- checks
def _side_view(stairs):
    """Treads lowest first, nosings (E, 2) (s, h), risers (E, 2, 2) ((s, h_low), (s, h_high))."""
    treads = sorted(stairs.treads, key=lambda t: t.height_m)
    nos = np.array([[t.s_front_m, t.height_m] for t in treads])
    lows = np.r_[0.0, nos[:-1, 1]]
    ris = np.stack([np.c_[nos[:, 0], lows], nos], axis=1)
    return treads, nos, ris


def edge_distances(stairs, p_world: np.ndarray) -> tuple[float, int, float, int]:
    """Side-view distances (m) of a point to the model's nearest nosing and riser, and their
    indices (module docstring): ``(nosing_m, nosing_index, riser_m, riser_index)``."""
    treads, nos, ris = _side_view(stairs)
    s, _, h = (invert_pose(stairs.T_world_stairs) @ np.r_[np.asarray(p_world, dtype=float), 1.0])[:3]
    d_n = np.hypot(nos[:, 0] - s, nos[:, 1] - h)
    h_c = np.clip(h, ris[:, 0, 1], ris[:, 1, 1])
    d_r = np.hypot(ris[:, 0, 0] - s, h_c - h)
    i, j = int(np.argmin(d_n)), int(np.argmin(d_r))
    return float(d_n[i]), treads[i].index, float(d_r[j]), treads[j].index


def _surface(stairs, p_stairs: np.ndarray, tol: float):
    """(surface index or -1 floor or None, the tread or None)."""
    s, t, h = p_stairs
    treads = sorted(stairs.treads, key=lambda tr: tr.height_m)
    for tr in treads:
        if tr.s_front_m <= s <= tr.s_back_m and tr.t_min_m <= t <= tr.t_max_m and abs(h - tr.height_m) <= tol:
            return tr.index, tr
    if abs(h) <= tol and (s < treads[0].s_front_m or (treads[-1].depth_complete and s > treads[-1].s_back_m)):
        return -1, None
    return None, None


def swing_edge_clearances(robot, foot: str, T_world_body_start, T_world_body_end, p_world_lift, p_world_land,
                          step_height_m: float, stairs, *, config: GaitConfig = GaitConfig(),
                          samples: int = 60) -> np.ndarray:
    """(E,) the swing's clearance (m) over each nosing of the model, lowest tread first: the smallest
    distance over ``samples`` instants between the shin's axis (last joint origin -> foot) and the
    nosing segment, minus ``shin_radius_m + edge_radius_m`` (module docstring); NaN for every edge
    when the leg cannot follow the path (IK)."""
    from graphcal.models.kinematics import ik_leg, joint_frames

    cfg = config
    treads = sorted(stairs.treads, key=lambda t: t.height_m)
    tau = np.linspace(0.0, 1.0, max(int(samples), 2))
    P = swing_trajectory(p_world_lift, p_world_land, float(step_height_m), tau, lift_fraction=cfg.lift_fraction)
    R, O = body_path(np.asarray(T_world_body_start, dtype=float), np.asarray(T_world_body_end, dtype=float), tau)
    p_body = np.einsum("nji,nj->ni", R, P - O)
    leg = robot.leg(foot)
    q0, ok0 = ik_leg(leg, p_body[0], np.zeros(leg.n_joints))
    q, ok = ik_leg(leg, p_body, q0)
    if not (bool(ok0) and bool(np.all(ok))):
        return np.full(len(treads), np.nan)
    _, origins, _, feet_b = joint_frames(leg, q)
    T_sw = invert_pose(stairs.T_world_stairs)
    knee = np.einsum("nij,nj->ni", R, origins[:, -1]) + O
    foot_w = np.einsum("nij,nj->ni", R, feet_b) + O
    knee_s = knee @ T_sw[:3, :3].T + T_sw[:3, 3]
    foot_s = foot_w @ T_sw[:3, :3].T + T_sw[:3, 3]
    e0 = np.array([[t.s_front_m, t.t_min_m, t.height_m] for t in treads])
    e1 = np.array([[t.s_front_m, t.t_max_m, t.height_m] for t in treads])
    d = segment_distances(knee_s[:, None], foot_s[:, None], e0[None], e1[None])  # (T, E)
    return d.min(axis=0) - (cfg.shin_radius_m + cfg.edge_radius_m)


def stability_margin(p_world_support: np.ndarray, p_world_com: np.ndarray) -> np.ndarray:
    """Signed distance (m) of the centre of mass's ground projection to the edges of the support
    polygon (the convex hull of the stance feet, projected along world z): positive inside, negative
    outside (the distance to the nearest edge's line). ``p_world_com`` (3,) or (T, 3) -> () or (T,)."""
    pts = np.asarray(p_world_support, dtype=float)[:, :2]
    c = np.atleast_2d(np.asarray(p_world_com, dtype=float))[:, :2]
    order = sorted(map(tuple, pts))
    if len(order) < 3:
        return np.full(len(c), -np.inf) if np.ndim(p_world_com) > 1 else np.array(-np.inf)

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list = []
    upper: list = []
    for p in order:  # Andrew's monotone chain, counter-clockwise
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    for p in reversed(order):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    hull = np.array(lower[:-1] + upper[:-1])
    a, b = hull, np.roll(hull, -1, axis=0)
    edge = b - a
    n = np.c_[-edge[:, 1], edge[:, 0]] / np.linalg.norm(edge, axis=1)[:, None]  # inward (CCW)
    m = np.min(np.einsum("tek,ek->te", c[:, None, :] - a[None], n), axis=1)
    return m if np.ndim(p_world_com) > 1 else np.array(m[0])


def body_height_over_feet(T_world_body: np.ndarray, p_world_feet: np.ndarray, heading_world: np.ndarray) -> float:
    """Height (m) of the body origin above the least-squares line ``z = a + b s`` through the feet
    (``s`` along the horizontal heading), evaluated below the body: the height the planner keeps."""
    s = p_world_feet @ heading_world
    z = p_world_feet[:, 2]
    b = 0.0 if np.ptp(s) < 1e-6 else float(np.cov(s, z, bias=True)[0, 1] / np.var(s))
    a = float(z.mean() - b * s.mean())
    o = np.asarray(T_world_body, dtype=float)[:3, 3]
    return float(o[2] - (a + b * (o @ heading_world)))


def _check_foot(robot, stairs, trust, step_T0, gp: GaitParameters, foot: str, p_lift, cfg: ClimbConfig,
                gait: GaitConfig) -> FootholdCheck:
    p = np.asarray(gp.p_world_land[foot], dtype=float)
    T_sw = invert_pose(stairs.T_world_stairs)
    p_s = T_sw[:3, :3] @ p + T_sw[:3, 3]
    d_n, i_n, d_r, i_r = edge_distances(stairs, p)
    surf, tread = _surface(stairs, p_s, cfg.on_tread_tol_m)
    lateral = float(min(p_s[1] - tread.t_min_m, tread.t_max_m - p_s[1])) if tread is not None else float("inf")
    seen_part = {t.index for t in trust if t.status == "seen part only"}
    seen_end = float(tread.s_back_m - p_s[0]) if tread is not None and tread.index in seen_part else float("nan")
    clear = swing_edge_clearances(robot, foot, step_T0, gp.T_world_body_end, p_lift, p, gp.step_height_m, stairs,
                                  config=gait, samples=cfg.check_samples)
    sw = swing_collides(robot, foot, step_T0, gp.T_world_body_end, p_lift, p, gp.step_height_m, stairs,
                        config=gait, samples=cfg.check_samples)
    return FootholdCheck(foot, np.asarray(p_lift, dtype=float).copy(), p, p_s, surf, d_n, i_n, d_r, i_r, lateral,
                         seen_end, clear, sw)


# ----------------------------------------------------------------------------- the climb
def _on_top(stairs, feet: Mapping[str, np.ndarray], tol: float) -> bool:
    top = max(stairs.treads, key=lambda t: t.height_m)
    T_sw = invert_pose(stairs.T_world_stairs)
    for p in feet.values():
        s, _, h = T_sw[:3, :3] @ p + T_sw[:3, 3]
        if not (abs(h - top.height_m) <= tol and s >= top.s_front_m):
            return False
    return True


def plan_climb(robot, stairs, T_world_body: np.ndarray, p_world_feet: Mapping[str, np.ndarray], stance_group: str,
               *, config: ClimbConfig = ClimbConfig(), gait: GaitConfig = GaitConfig(),
               groups: Sequence[Sequence[str]] | None = None) -> ClimbPlan:
    """Plan the climb step by step (module docstring).

    Args:
        robot: the robot model (:func:`graphcal.planning.gait.gait_parameters`).
        stairs: the stairs model (e.g. :func:`stairs_model_from_json`).
        T_world_body: (4, 4) the body at the start. p_world_feet: foot -> (3,) every foot then (m).
        stance_group: the tripod in stance for the first step (``A`` / ``B``).
        config: :class:`ClimbConfig`. gait: the planner's :class:`graphcal.planning.gait.GaitConfig`.
        groups: the two tripods (default: the built-in model's).

    Raises:
        GaitError: a tread not seen well enough (named; :func:`tread_trust`), bad input to the planner.
    """
    trust = tread_trust(stairs, min_tread_points=config.min_tread_points)
    refuse_untrusted(trust)
    hd = np.array([stairs.T_world_stairs[0, 0], stairs.T_world_stairs[1, 0], 0.0])
    hd /= np.linalg.norm(hd)
    T = np.asarray(T_world_body, dtype=float).copy()
    feet = {f: np.asarray(p, dtype=float).copy() for f, p in p_world_feet.items()}
    stance = str(stance_group).upper()
    steps: list[ClimbStep] = []
    short = 0
    outcome, reason = "max steps", f"the plan reached {config.max_steps} steps"
    R_ws = stairs.T_world_stairs[:3, :3]
    for k in range(config.max_steps):
        if _on_top(stairs, feet, config.on_tread_tol_m):
            outcome, reason = "climbed", "every foot stands on the top tread"
            break
        t0 = time.perf_counter()
        try:
            gp = gait_parameters(robot, T, stance, stairs, feet, groups=groups, heading_world=hd, config=gait)
        except GaitError as exc:
            if k == 0:
                raise
            outcome, reason = "no feasible step", f"step {k}: {exc}"
            break
        dt = time.perf_counter() - t0
        short = short + 1 if gp.step_length_m < config.min_step_length_m else 0
        if short >= 2:
            popped = steps.pop()  # the first of the two: neither advances
            feet, T = dict(popped.p_world_feet_start), popped.T_world_body_start.copy()
            outcome = "stalled"
            reason = (f"steps {k - 1} and {k} (one per tripod) would advance less than {config.min_step_length_m} m: "
                      "the planner finds no step that carries the rear tripod on (docs/stairs_gait.md, limitations)")
            break
        checks = tuple(_check_foot(robot, stairs, trust, T, gp, f, feet[f], config, gait) for f in gp.swing_feet)
        tau = np.linspace(0.0, 1.0, 21)
        _, O = body_path(T, gp.T_world_body_end, tau)
        margin = float(np.min(stability_margin(np.array([feet[f] for f in gp.stance_feet]), O)))
        after = {**feet, **{f: np.asarray(p, dtype=float) for f, p in gp.p_world_land.items()}}
        pitch = float(rpy_from_matrix(R_ws.T @ gp.T_world_body_end[:3, :3])[1])
        steps.append(ClimbStep(k, stance, gp, T.copy(), MappingProxyType(dict(feet)), dt, checks, margin,
                               body_height_over_feet(gp.T_world_body_end, np.array(list(after.values())), hd), pitch))
        feet, T = after, gp.T_world_body_end.copy()
        stance = "B" if stance == "A" else "A"
    else:
        if _on_top(stairs, feet, config.on_tread_tol_m):
            outcome, reason = "climbed", "every foot stands on the top tread"
    return ClimbPlan(tuple(steps), outcome, reason, T, MappingProxyType(feet), trust, hd)


# ----------------------------------------------------------------------------- the start
def choose_start(times: np.ndarray, p_world_feet: np.ndarray, stairs, *, gap_m: float = 0.10,
                 window_s: float = 1.5) -> int:
    """The sample to start the plan from: among the samples of the last ``window_s`` before the
    first time a foot comes within ``gap_m`` of the first riser (stairs frame, along x), the one
    whose highest foot is lowest above the floor (all feet down: a double support).

    Args:
        times: (N,) s. p_world_feet: (N, F, 3) every foot at every sample (world, m).
        stairs: the stairs model. gap_m, window_s: see above (m, s).

    Raises:
        GaitError: no sample has every foot at least ``gap_m`` in front of the first riser.
    """
    T_sw = invert_pose(stairs.T_world_stairs)
    S = np.asarray(p_world_feet, dtype=float) @ T_sw[:3, :3].T + T_sw[:3, 3]  # (N, F, 3)
    s0 = min(t.s_front_m for t in stairs.treads)
    before = np.all(S[:, :, 0] < s0 - gap_m, axis=1)
    if not before[0]:
        raise GaitError(f"the track does not start with the robot in front of the stairs (every foot {gap_m} m "
                        f"before the first riser): give the start time")
    end = int(np.argmin(before)) - 1 if not before.all() else len(before) - 1
    cand = np.flatnonzero((times > times[end] - window_s) & (np.arange(len(times)) <= end))
    h_max = np.max(np.abs(S[cand, :, 2]), axis=1)
    return int(cand[np.argmin(h_max)])


def first_swing_group(times: np.ndarray, p_world_feet: np.ndarray, start: int, feet: Sequence[str],
                      groups: Sequence[Sequence[str]], *, lift_m: float = 0.015, horizon_s: float = 1.5) -> str:
    """The tripod in stance for the first planned step (``A`` / ``B``): the other one is the tripod the
    log lifted next after ``start`` (the first foot more than ``lift_m`` above its place then,
    within ``horizon_s``); ``A`` when none lifts."""
    P = np.asarray(p_world_feet, dtype=float)
    after = np.flatnonzero((times > times[start]) & (times <= times[start] + horizon_s))
    for i in after:
        up = np.flatnonzero(P[i, :, 2] - P[start, :, 2] > lift_m)
        if len(up):
            foot = feet[int(up[np.argmax(P[i, up, 2] - P[start, up, 2])])]
            return "B" if foot in groups[0] else "A"
    return "A"
