"""The ``report.html`` of ``graphcal plan-gait`` and its two figures: the perceived stairs, the planned
footholds, the swing paths and the body path, in side view and top view (the stairs frame of the
model: x up the stairs from the foot of the first riser, y left, z up from the floor; metres). One
page of :mod:`graphcal.report.page`; the same PNGs are written beside it."""

from __future__ import annotations

import numpy as np

from graphcal.geometry import invert_pose
from graphcal.planning.gait import GaitConfig, swing_trajectory
from graphcal.report.page import Section, esc, figure_png_html, num, render_page, row, table
from graphcal.report.plots import figure_png, new_figure

__all__ = ["gait_figures", "gait_html", "FIGURE_CAPTIONS"]

#: caption of each figure file
FIGURE_CAPTIONS = {
    "side.png": "side view (stairs frame: x up the stairs from the foot of the first riser, z up from the floor): "
                "the perceived stairs, the zones where no foot may land (red), the planned footholds (numbered by "
                "step), the swing paths and the body path (the tracked trajectory in grey)",
    "top.png": "top view (stairs frame: x up the stairs, y left): the treads' seen extents, the nosings, the planned "
               "footholds (numbered by step) and the body path (the tracked trajectory in grey)",
}
_TRIPOD_COLOURS = {"A": "C0", "B": "C1"}


def _to_stairs(stairs, P: np.ndarray) -> np.ndarray:
    T = invert_pose(stairs.T_world_stairs)
    return np.asarray(P, dtype=float) @ T[:3, :3].T + T[:3, 3]


def _stairs_side(ax, stairs, gait: GaitConfig, s_lo: float, s_hi: float) -> None:
    treads = sorted(stairs.treads, key=lambda t: t.height_m)
    xs, zs = [s_lo, treads[0].s_front_m], [0.0, 0.0]
    for t in treads:
        xs += [t.s_front_m, t.s_back_m]
        zs += [t.height_m, t.height_m]
        if t is not treads[-1]:
            nxt = treads[treads.index(t) + 1]
            xs += [nxt.s_front_m]
            zs += [t.height_m]
    ax.plot(xs, zs, "k-", lw=1.5, label="stairs model (seen)")
    top = treads[-1]
    if not top.depth_complete:
        ax.plot([top.s_back_m, max(s_hi, top.s_back_m + 0.2)], [top.height_m] * 2, "k:", lw=1.2,
                label="not seen (the top tread's depth is incomplete)")
    zone = {"color": "#d62728", "alpha": 0.6, "lw": 4, "solid_capstyle": "butt"}
    surfaces = [(s_lo, treads[0].s_front_m, 0.0)] + [(t.s_front_m, t.s_back_m, t.height_m) for t in treads]
    for i, (a, b, h) in enumerate(surfaces):
        if i > 0:
            ax.plot([a, a + gait.near_zone_m], [h, h], **zone)
        ax.plot([b - gait.far_zone_m, b], [h, h], **zone, label="near / far zone (no foothold)" if i == 0 else None)
    for t in treads:
        ax.plot([t.s_front_m], [t.height_m], "ko", ms=3)


def _steps_feet(plan):
    """Per step: (tripod, foot, lift (3,), land (3,), H, T0, T1) for every swing foot."""
    for st in plan.steps:
        tripod = "B" if st.stance_group == "A" else "A"
        for fc in st.footholds:
            yield st.index, tripod, fc, st.params.step_height_m, st.T_world_body_start, st.params.T_world_body_end


def _body_points(plan) -> np.ndarray:
    pts = [st.T_world_body_start[:3, 3] for st in plan.steps] + [plan.T_world_body_end[:3, 3]]
    return np.array(pts)


def gait_figures(stairs, plan, *, gait: GaitConfig = GaitConfig(), p_world_track: np.ndarray | None = None,
                 start_feet: dict | None = None) -> dict[str, bytes]:
    """The two figures, file name -> PNG: ``side.png`` and ``top.png`` (module docstring).

    Args:
        stairs: the stairs model. plan: the :class:`graphcal.planning.climb.ClimbPlan`.
        gait: the planner's config (its zones and path shape). p_world_track: (N, 3) the tracked body
            positions (world, m), drawn in grey, or None. start_feet: foot -> (3,) the feet at the start.
    """
    tau = np.linspace(0.0, 1.0, 40)
    body = _to_stairs(stairs, _body_points(plan))
    track = _to_stairs(stairs, p_world_track) if p_world_track is not None and len(p_world_track) else None
    starts = _to_stairs(stairs, np.array(list(start_feet.values()))) if start_feet else np.zeros((0, 3))
    feet = list(_steps_feet(plan))
    lands = np.array([_to_stairs(stairs, fc.p_world_foot[None])[0] for _, _, fc, _, _, _ in feet]) if feet else np.zeros((0, 3))
    s_all = np.r_[body[:, 0], starts[:, 0], lands[:, 0] if len(lands) else []]
    s_lo, s_hi = float(s_all.min()) - 0.2, float(max(s_all.max(), max(t.s_back_m for t in stairs.treads))) + 0.1
    h_hi = max(float(body[:, 2].max()), max(t.height_m for t in stairs.treads)) + 0.15
    out = {}

    fig = new_figure(10, 1.9 + 9.0 * (h_hi + 0.05) / (s_hi - s_lo))
    ax = fig.add_subplot(1, 1, 1)
    _stairs_side(ax, stairs, gait, s_lo, s_hi)
    if track is not None:
        keep = (track[:, 0] >= s_lo) & (track[:, 0] <= s_hi)
        ax.plot(track[keep, 0], track[keep, 2], "-", color="0.6", lw=0.8, label="tracked body (estimate)")
    for _, tripod, fc, H, _, _ in feet:
        path = _to_stairs(stairs, swing_trajectory(fc.p_world_lift, fc.p_world_foot, H, tau, lift_fraction=gait.lift_fraction))
        ax.plot(path[:, 0], path[:, 2], "-", color=_TRIPOD_COLOURS[tripod], lw=0.6, alpha=0.7)
    for tripod in ("A", "B"):
        sel = [i for i, f in enumerate(feet) if f[1] == tripod]
        if sel:
            ax.plot(lands[sel, 0], lands[sel, 2], "v", color=_TRIPOD_COLOURS[tripod], ms=6,
                    label=f"footholds, tripod {tripod} swinging")
    if len(starts):
        ax.plot(starts[:, 0], starts[:, 2], "s", mfc="none", mec="k", ms=5, label="feet at the start")
    ax.plot(body[:, 0], body[:, 2], "k.-", lw=1.2, ms=5, label="planned body path")
    for st, (s, _, h) in zip(plan.steps, body[1:]):
        ax.annotate(str(st.index), (s, h), textcoords="offset points", xytext=(0, 5), fontsize=7, ha="center")
    ax.set_xlim(s_lo, s_hi)
    ax.set_ylim(-0.05, h_hi)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x, stairs frame (m)")
    ax.set_ylabel("z above the floor (m)")
    ax.set_title("side view: stairs model, footholds, swing paths, body path")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.22), fontsize=7, ncol=4, frameon=False)
    out["side.png"] = figure_png(fig)

    t_ext = max(t.t_max_m for t in stairs.treads) - min(t.t_min_m for t in stairs.treads) + 0.4
    fig = new_figure(10, 1.5 + 9.0 * t_ext / (s_hi - s_lo))
    ax = fig.add_subplot(1, 1, 1)
    for t in sorted(stairs.treads, key=lambda t: t.height_m):
        ax.fill([t.s_front_m, t.s_back_m, t.s_back_m, t.s_front_m], [t.t_min_m, t.t_min_m, t.t_max_m, t.t_max_m],
                color="0.85", lw=0)
        ax.plot([t.s_front_m] * 2, [t.t_min_m, t.t_max_m], "k-", lw=1.5)
        ax.text(t.s_front_m + 0.02, 0.5 * (t.t_min_m + t.t_max_m) + 0.3, f"tread {t.index}\n{t.height_m:.3f} m",
                fontsize=7, va="center")
    if track is not None:
        keep = (track[:, 0] >= s_lo) & (track[:, 0] <= s_hi)
        ax.plot(track[keep, 0], track[keep, 1], "-", color="0.6", lw=0.8, label="tracked body (estimate)")
    for tripod in ("A", "B"):
        sel = [i for i, f in enumerate(feet) if f[1] == tripod]
        if sel:
            ax.plot(lands[sel, 0], lands[sel, 1], "o", color=_TRIPOD_COLOURS[tripod], ms=5,
                    label=f"footholds, tripod {tripod} swinging")
    for (k, _, _, _, _, _), p in zip(feet, lands):
        ax.annotate(str(k), (p[0], p[1]), textcoords="offset points", xytext=(4, 3), fontsize=6)
    if len(starts):
        ax.plot(starts[:, 0], starts[:, 1], "s", mfc="none", mec="k", ms=5, label="feet at the start")
    ax.plot(body[:, 0], body[:, 1], "k.-", lw=1.2, ms=5, label="planned body path")
    t_all = np.r_[[t.t_min_m for t in stairs.treads], [t.t_max_m for t in stairs.treads], body[:, 1],
                  starts[:, 1], lands[:, 1] if len(lands) else []]
    t_lo, t_hi = float(t_all.min()) - 0.1, float(t_all.max()) + 0.1
    ax.set_xlim(s_lo, s_hi)
    ax.set_ylim(t_lo, t_hi)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x, stairs frame (m)")
    ax.set_ylabel("y, stairs frame (m)")
    ax.set_title("top view: treads (seen extent), nosings, footholds, body path")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), fontsize=7, ncol=5, frameon=False)
    out["top.png"] = figure_png(fig)
    return out


def _m(x, fmt=".3f"):
    return num(x, fmt) if x is not None else "–"


def _mm(x):
    return num(1e3 * x, ".1f") if x is not None else "–"


def _min(values):
    vals = [v for v in values if v is not None]
    return min(vals) if vals else None


def _scene_section(scene) -> Section:
    from graphcal.report.scene_view import scene_html

    return Section("3-D scene", scene_html(scene),
                   f'<p class="small">World frame (the track\'s estimate), m, z up. {esc(scene.note)}</p>')


def gait_html(doc: dict, pngs: dict[str, bytes], *, title: str = "graphcal plan-gait", scene=None) -> str:
    """The page of a plan-gait output: ``doc`` is gait.yaml's document, ``pngs`` the figures, ``scene``
    the 3-D view (:func:`graphcal.report.scene_3d.gait_scene`) or None."""
    s = doc["summary"]
    facts = [
        f"outcome: {s['outcome']} after {s['steps']} steps ({s['reason']})",
        f"feet on the top tread at the end: {s['feet_on_top']} of {s['feet']}",
        f"smallest distance of a foothold to a nosing {_mm(s['min_nosing_distance_m'])} mm, to a riser "
        f"{_mm(s['min_riser_distance_m'])} mm (stairs model; side view)",
        f"smallest swing clearance over a nosing {_mm(s['min_edge_clearance_m'])} mm (shin axis to nosing axis minus "
        f"the shin and edge radii, {_mm(doc['config']['gait']['shin_radius_m'])} + "
        f"{_mm(doc['config']['gait']['edge_radius_m'])} mm: Zhao Eqs. 11-12)",
        f"smallest static stability margin {_mm(s['min_stability_margin_m'])} mm (body origin as the centre of mass)",
        f"planning time per step: median {_m(s['planning_ms']['median'], '.0f')} ms, max "
        f"{_m(s['planning_ms']['max'], '.0f')} ms (Zhao's budget: 100 ms)",
    ]
    summary = Section("Summary", "<ul class='facts'>" + "".join(f"<li>{esc(f)}</li>" for f in facts) + "</ul>")
    rows = [row(["step", "swing tripod", "feet", "L (m)", "H (m)", "body height (m)", "pitch (deg)", "rise (m)",
                 "stability margin (mm)", "nosing dist. min (mm)", "riser dist. min (mm)", "clearance min (mm)",
                 "planning (ms)"], header=True)]
    for st in doc["steps"]:
        fh = st["footholds"].values()
        rows.append(row([str(st["step"]), esc(st["swing_tripod"]), esc(", ".join(st["swing_feet"])),
                         _m(st["step_length_m"]), _m(st["step_height_m"]), _m(st["body"]["height_m"]),
                         _m(st["body"]["pitch_deg"], ".1f"), _m(st["body"]["rise_m"]),
                         _mm(st["stability_margin_m"]), _mm(_min(f["nosing_distance_m"] for f in fh)),
                         _mm(_min(f["riser_distance_m"] for f in fh)),
                         _mm(_min(f["swing"]["min_clearance_over_nosings_m"] for f in fh)),
                         _m(st["planning_ms"], ".0f")]))
    steps = Section("Steps (Zhao's gait parameters per step)", table(rows))
    rows = [row(["step", "foot", "surface", "x (m)", "y (m)", "z (m)", "nosing (mm)", "riser (mm)", "lateral (mm)",
                 "clearance over each nosing (mm)"], header=True)]
    for st in doc["steps"]:
        for foot, f in st["footholds"].items():
            p = f["p_stairs_foot"]
            clear = ", ".join(f"{k}: {_mm(v)}" for k, v in f["swing"]["clearance_over_nosing_m"].items())
            rows.append(row([str(st["step"]), esc(foot), esc(f["surface"]), _m(p[0]), _m(p[1]), _m(p[2]),
                             _mm(f["nosing_distance_m"]), _mm(f["riser_distance_m"]), _mm(f.get("lateral_margin_m")),
                             esc(clear)]))
    footholds = Section("Footholds (p_stairs_foot; world coordinates in gait.yaml)", table(rows))
    rows = [row(["tread", "height (m)", "depth (m)", "depth complete", "seen x from (m)", "to (m)", "points",
                 "trust"], header=True)]
    for t in doc["treads"]:
        rows.append(row([str(t["index"]), _m(t["height_m"]), _m(t["depth_m"]), esc(t["depth_complete"]),
                         _m(t["s_front_m"]), _m(t["s_back_m"]), str(t["n_inliers"]),
                         esc(t["trust"] + (f": {t['note']}" if t.get("note") else ""))]))
    treads = Section("Stairs model (from the track's stairs.json)", table(rows))
    figures = Section("Figures", *(figure_png_html(png, f"{name}: {FIGURE_CAPTIONS.get(name, '')}")
                                   for name, png in pngs.items()))
    st0 = doc["start"]
    subtitle = (f"Track: {doc['track_dir']}; robot {doc['robot']}; start at t = {st0['time_s']:.2f} s of the track "
                f"({st0['selection']}), tripod {st0['stance_tripod']} in stance. Planner: "
                "graphcal.planning.gait (Zhao et al. 2020, section 3.3), one step at a time from the previous plan "
                "(docs/stairs_gait.md).")
    scenes = [_scene_section(scene)] if scene is not None else []
    return render_page(title, [summary, figures, *scenes, steps, footholds, treads], subtitle=subtitle,
                       warnings=doc.get("warnings", ()),
                       footer="Frames: world = the track's estimate (z up); stairs = x up the stairs from the foot of "
                              "the first riser, y left, z up from the floor. Lengths in m (tables in mm where "
                              "marked), angles in deg. Every number: gait.yaml.")
