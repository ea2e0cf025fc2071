"""``graphcal plan-gait TRACK_DIR --out DIR``: Zhao's gait adaptation on the stairs a ``graphcal track``
perceived -- step by step up the stairs model of ``TRACK_DIR/stairs.json``, from the robot's tracked
state in front of the stairs, the gait parameters the planner chooses (step length, step height,
body height and pitch, which tripod swings) and the footholds with their distances to the nosings
and risers, the swings' clearance over each nosing and the static stability margin
(:mod:`graphcal.planning.climb` around :func:`graphcal.planning.gait.gait_parameters`).

Reads ``TRACK_DIR``: ``metrics.json`` (format ``graphcal-track/1``: which dataset), ``stairs.json``
(the stairs model; written by track on a stairs dataset), ``trajectory.tum`` (the estimate); and the
dataset it names (or ``dataset=``): the robot model and the joint angles, for the feet at the start.

The start: the tracked sample in the last 1.5 s before a foot first comes within 10 cm of the first
riser whose highest foot is lowest (every foot down), or the sample nearest ``start_time_s``; the feet
from the joint angles there (forward kinematics placed with the estimated pose); the tripod in stance
is the one the log did not lift next.

Writes, as one atomic set (:func:`graphcal.io.atomic.atomic_directory`):

* ``gait.yaml`` -- format ``graphcal-plan-gait/1``; a ``frames:`` and a ``units:`` block first; the
  treads and how far each is trusted, the start, per step the gait parameters and per swing foot
  ``p_world_foot`` / ``p_stairs_foot``, distances and clearances; the summary and the warnings;
* ``side.png``, ``top.png`` -- the stairs, the planned feet and the body path (stairs frame);
* ``report.html`` -- the page (:func:`graphcal.report.gait_page.gait_html`).

An existing ``DIR`` is replaced only if it is empty or holds a previous plan-gait output (gait.yaml
with ``format: graphcal-plan-gait/1`` and nothing else graphcal did not write); ``DIR`` may not lie
inside ``TRACK_DIR``. A tread not seen well enough is refused by name (one line; docs/stairs_gait.md).
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import yaml

from graphcal.errors import GraphcalError
from graphcal.io.atomic import atomic_directory, atomic_write_bytes, check_command_output, check_output_outside
from graphcal.planning.climb import (
    ClimbConfig,
    ClimbPlan,
    choose_start,
    first_swing_group,
    plan_climb,
    refuse_untrusted,
    stairs_model_from_json,
    tread_trust,
    trust_warnings,
)
from graphcal.planning.gait import GaitConfig
from graphcal.report.gait_page import gait_figures, gait_html
from graphcal.report.scene_3d import gait_scene

__all__ = ["PLAN_FORMAT", "OUTPUT_FILES", "run", "PlanGaitResult", "summary_lines"]

log = logging.getLogger(__name__)

PLAN_FORMAT = "graphcal-plan-gait/1"
OUTPUT_FILES = ("gait.yaml", "report.html", "side.png", "top.png")
_FRAMES = {
    "world": "the frame of the track's estimate (trajectory.tum, stairs.json), z up; p_world_* and T_world_*",
    "stairs": "the stairs model's frame (T_world_stairs below, from stairs.json): x up the stairs (horizontal) from "
              "the foot of the first riser, y left when climbing, z up from the floor; p_stairs_*",
    "body": "the robot's base frame (x forward, z up)",
}
_UNITS = {
    "length": "m (keys ending _m; p_* and T_* translations)",
    "angle": "deg (keys ending _deg; body pitch is the rotation about the stairs y axis: nose up is negative); "
             "rad where a key ends _rad",
    "time": "s (keys ending _s); planning times in ms (keys ending _ms)",
}


def _check_out(out: Path, overwrite: bool) -> None:
    """The output-folder policy of graphcal.io.atomic.check_output_folder, for a plan-gait output."""
    check_command_output(out, "gait.yaml", OUTPUT_FILES, PLAN_FORMAT, what="graphcal plan-gait output",
                         overwrite=overwrite)


# ----------------------------------------------------------------------------- inputs
def _read_track(track_dir: Path) -> tuple[dict, dict, np.ndarray]:
    """metrics.json, stairs.json and trajectory.tum (N, 8) of a track output; GraphcalError naming the
    missing or malformed file."""
    if not track_dir.is_dir():
        raise GraphcalError(f"{track_dir}: no such folder (TRACK_DIR: the output folder of graphcal track)")
    metrics_path = track_dir / "metrics.json"
    try:
        metrics = json.loads(metrics_path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise GraphcalError(f"{metrics_path}: not readable ({type(exc).__name__}): TRACK_DIR must be a graphcal "
                            "track output") from None
    if not isinstance(metrics, dict) or not str(metrics.get("format", "")).startswith("graphcal-track/"):
        raise GraphcalError(f"{metrics_path}: not a graphcal track manifest (format graphcal-track/1)")
    stairs_path = track_dir / "stairs.json"
    if not stairs_path.is_file():
        raise GraphcalError(f"{stairs_path}: no such file: TRACK_DIR must be a graphcal track output of a stairs "
                            "dataset (track writes stairs.json when dataset.yaml's ground type is stairs)")
    try:
        stairs_doc = json.loads(stairs_path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise GraphcalError(f"{stairs_path}: not readable JSON ({exc})") from None
    tum_path = track_dir / "trajectory.tum"
    try:
        tum = np.loadtxt(tum_path, comments="#", ndmin=2)
    except (OSError, ValueError) as exc:
        raise GraphcalError(f"{tum_path}: not a readable TUM trajectory ({type(exc).__name__}: {exc})") from None
    if tum.shape[1] != 8 or len(tum) < 2 or not np.all(np.isfinite(tum)):
        raise GraphcalError(f"{tum_path}: expected rows 't x y z qx qy qz qw' (at least two), got shape {tum.shape}")
    return metrics, stairs_doc, tum


def _dataset_path(metrics: dict, track_dir: Path, dataset) -> Path:
    if dataset is not None:
        return Path(dataset)
    named = metrics.get("dataset")
    if not isinstance(named, str) or not named:
        raise GraphcalError(f"{track_dir / 'metrics.json'}: names no dataset: give it with --dataset")
    p = Path(named)
    for cand in ((p,) if p.is_absolute() else (p, track_dir.parent / p)):
        if (cand / "dataset.yaml").is_file():
            return cand
    raise GraphcalError(f"the dataset {named} named in {track_dir / 'metrics.json'} is not there: give it with "
                        "--dataset (the robot model and the joint angles are read from it)")


def _feet_series(inp, times: np.ndarray, T_world_body: np.ndarray) -> np.ndarray:
    """(N, F, 3) every foot at every trajectory sample (world, m): joint angles of the nearest log
    sample, forward kinematics, placed with the estimated pose."""
    from graphcal.models.kinematics import foot_positions

    idx = np.clip(np.searchsorted(inp.times, times), 0, len(inp.times) - 1)
    prev = np.clip(idx - 1, 0, len(inp.times) - 1)
    idx = np.where(np.abs(inp.times[prev] - times) < np.abs(inp.times[idx] - times), prev, idx)
    out = []
    for f in inp.robot.feet:
        leg = inp.robot.leg(f)
        if inp.p_body_foot is not None or not leg.joint_names:
            raise GraphcalError(f"robot {inp.robot.name}: foot {f} has no leg joints: the gait planner needs legs "
                                "with joints (IK)")
        q = np.column_stack([np.asarray(inp.q[j], dtype=float)[idx] for j in leg.joint_names])
        p_body = foot_positions(leg, q)
        out.append(np.einsum("nij,nj->ni", T_world_body[:, :3, :3], p_body) + T_world_body[:, :3, 3])
    return np.stack(out, axis=1)


def _poses(tum: np.ndarray) -> np.ndarray:
    from graphcal.geometry import pose_from_xyz_quat_wxyz

    return np.array([pose_from_xyz_quat_wxyz(r[1:4], [r[7], r[4], r[5], r[6]]) for r in tum])


# ----------------------------------------------------------------------------- gait.yaml
def _r(x, nd: int = 6):
    """Plain YAML numbers: rounded floats (1 um / 1e-6 deg), NaN and infinities as null."""
    if isinstance(x, dict):
        return {k: _r(v, nd) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_r(v, nd) for v in x]
    if isinstance(x, np.ndarray):
        return _r(x.tolist(), nd)
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return round(float(x), nd) + 0.0 if np.isfinite(x) else None  # + 0.0: no -0.0
    return x


class _Dumper(yaml.SafeDumper):
    """gait.yaml's dumper: a list of numbers (a vector, a matrix row) on one line."""


def _represent_list(dumper, data):
    flat = all(not isinstance(v, (dict, list)) for v in data) or all(
        isinstance(v, list) and all(not isinstance(w, (dict, list)) for w in v) for v in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=bool(data) and flat)


_Dumper.add_representer(list, _represent_list)


def _stairs_xyz(stairs, p) -> np.ndarray:
    from graphcal.geometry import invert_pose

    T = invert_pose(stairs.T_world_stairs)
    return T[:3, :3] @ np.asarray(p, dtype=float) + T[:3, 3]


def _surface_name(k) -> str:
    return "off the model" if k is None else "floor" if k < 0 else f"tread {k}"


def _foothold_doc(stairs, fc) -> dict:
    treads = sorted(stairs.treads, key=lambda t: t.height_m)
    clear = {f"tread {t.index}": float(c) for t, c in zip(treads, fc.edge_clearances_m)}
    d = {
        "p_world_foot": fc.p_world_foot, "p_stairs_foot": fc.p_stairs_foot, "p_world_lift": fc.p_world_lift,
        "surface": _surface_name(fc.surface),
        "nosing_distance_m": fc.nosing_distance_m, "nearest_nosing": f"tread {fc.nearest_nosing}",
        "riser_distance_m": fc.riser_distance_m, "nearest_riser": f"below tread {fc.nearest_riser}",
    }
    if np.isfinite(fc.lateral_margin_m):  # the floor has no lateral end
        d["lateral_margin_m"] = fc.lateral_margin_m
    if np.isfinite(fc.seen_end_distance_m):
        d["seen_end_distance_m"] = fc.seen_end_distance_m
    d["swing"] = {
        "clearance_over_nosing_m": clear,
        "min_clearance_over_nosings_m": float(np.nanmin(fc.edge_clearances_m)) if np.any(np.isfinite(fc.edge_clearances_m)) else None,
        "min_solid_clearance_m": fc.swing.min_solid_clearance_m,
        "reachable": fc.swing.reachable, "collides": fc.swing.collides,
    }
    return d


def _step_doc(stairs, st) -> dict:
    gp = st.params
    T1 = gp.T_world_body_end
    return {
        "step": st.index,
        "swing_tripod": "B" if st.stance_group == "A" else "A",
        "swing_feet": list(gp.swing_feet), "stance_feet": list(gp.stance_feet),
        "step_length_m": gp.step_length_m, "step_height_m": gp.step_height_m,
        "step_length_intervals_m": [list(iv) for iv in gp.step_length_intervals_m],
        "step_height_intervals_m": [list(iv) for iv in gp.step_height_intervals_m],
        "lengths_tried": gp.lengths_tried,
        "planning_ms": round(1e3 * st.planning_s, 2),
        "body": {"height_m": st.body_height_m, "pitch_deg": float(np.degrees(st.body_pitch_rad)),
                 "rise_m": gp.body_rise_m, "p_world_body_end": T1[:3, 3], "p_stairs_body_end": _stairs_xyz(stairs, T1[:3, 3]),
                 "T_world_body_end": T1},
        "stability_margin_m": st.stability_margin_m,
        "footholds": {fc.foot: _foothold_doc(stairs, fc) for fc in st.footholds},
    }


def _summary(plan: ClimbPlan, stairs) -> dict:
    fcs = [fc for st in plan.steps for fc in st.footholds]
    clear = [float(np.nanmin(fc.edge_clearances_m)) for fc in fcs if np.any(np.isfinite(fc.edge_clearances_m))]
    ms = [1e3 * st.planning_s for st in plan.steps]
    top = max(stairs.treads, key=lambda t: t.height_m)
    on_top = sum(abs(_stairs_xyz(stairs, p)[2] - top.height_m) <= 0.01 for p in plan.p_world_feet_end.values())
    return {
        "outcome": plan.outcome, "reason": plan.reason, "steps": len(plan.steps),
        "feet_on_top": int(on_top), "feet": len(plan.p_world_feet_end),
        "min_nosing_distance_m": min((fc.nosing_distance_m for fc in fcs), default=None),
        "min_riser_distance_m": min((fc.riser_distance_m for fc in fcs), default=None),
        "min_edge_clearance_m": min(clear, default=None),
        "min_solid_clearance_m": min((fc.swing.min_solid_clearance_m for fc in fcs), default=None),
        "min_stability_margin_m": min((st.stability_margin_m for st in plan.steps), default=None),
        "max_step_height_m": max((st.params.step_height_m for st in plan.steps), default=None),
        "planning_ms": {"median": float(np.median(ms)) if ms else None, "max": max(ms, default=None),
                        "total": float(sum(ms))},
    }


def _treads_doc(stairs, plan: ClimbPlan) -> list:
    trust = {t.index: t for t in plan.trust}
    out = []
    for t in sorted(stairs.treads, key=lambda t: t.height_m):
        out.append({"index": t.index, "height_m": t.height_m, "depth_m": t.depth_m, "depth_complete": t.depth_complete,
                    "s_front_m": t.s_front_m, "s_back_m": t.s_back_m, "t_min_m": t.t_min_m, "t_max_m": t.t_max_m,
                    "n_inliers": t.n_inliers, "edge_from_riser": t.edge_from_riser,
                    "trust": trust[t.index].status, "note": trust[t.index].reason})
    return out


def _plan_warnings(plan: ClimbPlan, gait: GaitConfig) -> list[str]:
    out = list(trust_warnings(plan.trust, gait))
    if plan.outcome != "climbed":
        out.append(f"the plan does not reach the top: it stops after {len(plan.steps)} steps ({plan.outcome}: "
                   f"{plan.reason})")
    for st in plan.steps:
        for fc in st.footholds:
            if fc.swing.collides:
                what = "cannot follow its path" if not fc.swing.reachable else "touches the stairs model"
                out.append(f"step {st.index}: the swing of {fc.foot} {what} in the 60-instant check "
                           f"(edge clearance {1e3 * fc.swing.min_edge_clearance_m:.1f} mm, solid "
                           f"{1e3 * fc.swing.min_solid_clearance_m:.1f} mm)")
        if not st.stability_margin_m > 0:
            out.append(f"step {st.index}: the static stability margin is {1e3 * st.stability_margin_m:.1f} mm (the "
                       "body origin leaves the stance tripod's support triangle)")
    return out


# ----------------------------------------------------------------------------- the command
@dataclass(frozen=True)
class PlanGaitResult:
    """What ``graphcal plan-gait`` did.

    Attributes:
        plan: the :class:`graphcal.planning.climb.ClimbPlan`.
        stairs: the stairs model it was made on (from stairs.json).
        doc: gait.yaml's document.
        track_dir: TRACK_DIR, as given. out: the output folder.
        files: the files written. warnings: the plan's warnings (top tread seen in part, stops
            before the top, a swing touching the model, a non-positive stability margin).
        verdict: the plan's outcome (``climbed``, ``stalled``, ``no feasible step``, ``max steps``).
    """

    plan: ClimbPlan
    stairs: object
    doc: dict
    track_dir: str
    out: Path
    files: tuple[Path, ...]
    warnings: tuple[str, ...]
    verdict: str | None

    def summary_text(self) -> str:
        return "\n".join(summary_lines(self.doc, self.out))


def run(track_dir: str | Path, out: str | Path, *, dataset: str | Path | None = None, overwrite: bool = True,
        start_time_s: float | None = None, climb: ClimbConfig = ClimbConfig(),
        gait: GaitConfig = GaitConfig()) -> PlanGaitResult:
    """The ``graphcal plan-gait`` command (module docstring). Returns a :class:`PlanGaitResult`.

    Args:
        track_dir: a graphcal track output with stairs.json and trajectory.tum.
        out: output folder (replaces only an empty folder or a previous plan-gait output).
        dataset: the dataset the track ran on (default: the one metrics.json names).
        overwrite: replace a previous plan-gait output in ``out``.
        start_time_s: start at the tracked sample nearest this time (s) instead of the automatic start.
        climb: :class:`graphcal.planning.climb.ClimbConfig` (steps, stall, trusted treads).
        gait: the planner's :class:`graphcal.planning.gait.GaitConfig`.

    Raises:
        GraphcalError: TRACK_DIR is no track output of a stairs dataset (file named), a tread is not
            seen well enough (named), the start is not in front of the stairs, the output is refused.
    """
    from graphcal.io.dataset import read_dataset
    from graphcal.locomotion.track_inputs import inputs_from_dataset

    track_dir, out = Path(track_dir), Path(out)
    check_output_outside(out, track_dir, what="the track output")
    _check_out(out, overwrite)
    metrics, stairs_doc, tum = _read_track(track_dir)
    stairs = stairs_model_from_json(stairs_doc, source=str(track_dir / "stairs.json"))
    refuse_untrusted(tread_trust(stairs, min_tread_points=climb.min_tread_points),  # before the long reads
                     source=str(track_dir / "stairs.json"))
    ds_path = _dataset_path(metrics, track_dir, dataset)
    inp = inputs_from_dataset(read_dataset(ds_path))
    if not inp.groups:
        raise GraphcalError(f"robot {inp.robot.name}: no tripod groups (dataset.yaml gait.groups or the built-in "
                            "model's): the planner plans a two-tripod gait")
    times, T_wb = tum[:, 0], _poses(tum)
    P = _feet_series(inp, times, T_wb)
    if start_time_s is None:
        i0 = choose_start(times, P, stairs)
        selection = "every foot down, in front of the first riser (automatic)"
    else:
        if not np.isfinite(start_time_s):
            raise GraphcalError(f"--start-time must be a finite time (s), got {start_time_s}")
        i0 = int(np.argmin(np.abs(times - start_time_s)))
        selection = f"the sample nearest --start-time {start_time_s} s"
    stance = first_swing_group(times, P, i0, inp.robot.feet, inp.groups)
    feet0 = {f: P[i0, k] for k, f in enumerate(inp.robot.feet)}
    plan = plan_climb(inp.robot, stairs, T_wb[i0], feet0, stance, config=climb, gait=gait, groups=inp.groups)
    warnings = _plan_warnings(plan, gait)

    doc: dict = {
        "format": PLAN_FORMAT, "frames": _FRAMES, "units": _UNITS,
        "track_dir": str(track_dir), "dataset": str(ds_path), "robot": inp.robot.name,
        "planner": "graphcal.planning.gait.gait_parameters (Zhao et al. 2020, section 3.3), one step at a time "
                   "from the previous plan (graphcal.planning.climb); docs/stairs_gait.md",
        "T_world_stairs": stairs.T_world_stairs,
        "config": {"gait": asdict(gait), "climb": asdict(climb)},
        "treads": _treads_doc(stairs, plan),
        "start": {"time_s": float(times[i0]), "selection": selection, "stance_tripod": stance,
                  "groups": {"A": list(inp.groups[0]), "B": list(inp.groups[1])},
                  "T_world_body": T_wb[i0], "p_stairs_body": _stairs_xyz(stairs, T_wb[i0][:3, 3]),
                  "feet": {f: {"p_world_foot": p, "p_stairs_foot": _stairs_xyz(stairs, p)} for f, p in feet0.items()}},
        "steps": [_step_doc(stairs, st) for st in plan.steps],
        "end": {"T_world_body": plan.T_world_body_end,
                "feet": {f: {"p_world_foot": p, "p_stairs_foot": _stairs_xyz(stairs, p)}
                         for f, p in plan.p_world_feet_end.items()}},
        "summary": _summary(plan, stairs),
        "warnings": warnings,
        "output_files": sorted(OUTPUT_FILES),
    }
    doc = _r(doc)
    pngs = gait_figures(stairs, plan, gait=gait, p_world_track=T_wb[:, :3, 3], start_feet=feet0)
    head = ("# graphcal plan-gait: Zhao's gait parameters and footholds up the perceived stairs "
            "(docs/stairs_gait.md)\n# frames and units: the frames: and units: blocks below\n")
    files: dict[str, bytes] = {"gait.yaml": (head + yaml.dump(doc, Dumper=_Dumper, sort_keys=False, width=120)).encode(), **pngs}
    scene = gait_scene(doc, stairs_doc, T_wb[:, :3, 3])
    files["report.html"] = gait_html(doc, pngs, title=f"graphcal plan-gait: {track_dir.name}", scene=scene).encode()
    with atomic_directory(out, overwrite=True) as tmp:
        for name, data in files.items():
            atomic_write_bytes(tmp / name, data)
        _check_out(out, overwrite)
    for w in warnings:
        log.warning("WARNING: %s", w)
    return PlanGaitResult(plan=plan, stairs=stairs, doc=doc, track_dir=str(track_dir), out=out,
                          files=tuple(out / n for n in sorted(files)), warnings=tuple(warnings), verdict=plan.outcome)


def summary_lines(doc: dict, out) -> list[str]:
    """The console summary of a plan: the outcome, the margins, the planning time."""
    s = doc["summary"]

    def mm(x):
        return "n/a" if x is None else f"{1e3 * x:.1f} mm"

    lines = [f"planned {s['steps']} steps up the stairs of {doc['track_dir']} ({doc['robot']}): {s['outcome']} "
             f"({s['feet_on_top']} of {s['feet']} feet on the top tread); wrote {out}"]
    lines.append(f"  footholds: nearest nosing {mm(s['min_nosing_distance_m'])}, nearest riser "
                 f"{mm(s['min_riser_distance_m'])}; swing clearance over the nosings >= {mm(s['min_edge_clearance_m'])}; "
                 f"static stability margin >= {mm(s['min_stability_margin_m'])}")
    pm = s["planning_ms"]
    if pm["median"] is not None:
        lines.append(f"  planning: median {pm['median']:.0f} ms per step, max {pm['max']:.0f} ms (Zhao's budget 100 ms)")
    return lines
