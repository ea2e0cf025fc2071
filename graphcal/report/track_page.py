"""The ``report.html`` of ``graphcal track`` and its plots (trajectory, errors with the filter's
3 sigma, NIS / NEES): one page of :mod:`graphcal.report.page` with the same PNGs the command writes
beside it."""

from __future__ import annotations

import numpy as np

from graphcal.report.page import Section, esc, figure, figure_png_html, num, render_page, row, table
from graphcal.report.plots import figure_png, new_figure

__all__ = ["track_figures", "track_html"]

#: caption of each plot file
FIGURE_CAPTIONS = {
    "trajectory.png": "body trajectory: top view (world) and height",
    "errors.png": "estimate - truth (solid) and the filter's 3 sigma (dotted), position (mm) and orientation (deg)",
    "nis.png": "normalised innovation squared: stance kinematics, ICP, and the pose NEES against the truth",
    "contacts.png": "stance diagram: each foot's stance (bars) with its duty factor, over the log's phases",
}


def _contacts_figure(result, feet: tuple) -> bytes:
    """The stance diagram: a bar per foot where it is in stance (``result.stance_mask``), its duty
    factor, the log's phases shaded behind (``result.phases``)."""
    mask = np.asarray(result.stance_mask, dtype=bool)
    t = np.asarray(result.times, dtype=float)
    fig = new_figure(10, 1.2 + 0.45 * len(feet))
    ax = fig.add_subplot(1, 1, 1)
    if result.phases is not None:
        colours = {"lying": "0.75", "standing_up": "C2", "standing": "C9", "walking": "w", "lying_down": "C1",
                   "lifted": "C3"}
        for seg in result.phases.segments:
            if seg.phase != "walking":
                ax.axvspan(seg.start_s, seg.end_s, color=colours.get(seg.phase, "0.9"), alpha=0.25, lw=0)
                ax.text(0.5 * (seg.start_s + seg.end_s), len(feet) - 0.35, seg.phase.replace("_", " "), ha="center",
                        fontsize=7)
    for i, f in enumerate(feet):
        on = np.flatnonzero(np.diff(np.r_[0, mask[:, i].astype(int), 0]) == 1)
        off = np.flatnonzero(np.diff(np.r_[0, mask[:, i].astype(int), 0]) == -1) - 1
        ax.broken_barh([(t[a], max(t[b] - t[a], 1e-3)) for a, b in zip(on, off)], (i - 0.35, 0.7), color="C0")
        ax.text(t[-1], i, f"  duty {mask[:, i].mean():.2f}", va="center", fontsize=8)
    ax.set_yticks(range(len(feet)), labels=list(feet))
    ax.set_ylim(-0.6, len(feet) - 0.1)
    ax.set_xlim(t[0], t[-1] + 0.12 * (t[-1] - t[0]))
    ax.set_xlabel("time (s)")
    ax.set_title("stance per foot (the filter's contact decision)")
    return figure_png(fig)


def track_figures(result, truth, nees_t, nees, nees_dof, feet: tuple | None = None) -> dict[str, bytes]:
    """The plots of a track output, file name -> PNG: ``trajectory.png`` (top view and height, with the
    truth when there is one), ``errors.png`` (estimate - truth with the filter's 3 sigma, mm and deg)
    and ``nis.png`` (stance NIS, ICP NIS and the pose NEES against ``nees_dof``).

    Args:
        result: a :class:`~graphcal.locomotion.estimator.TrackResult` (T_world_body, times in s).
        truth: the :class:`~graphcal.locomotion.metrics.Truth` beside the dataset, or None.
        nees_t, nees: the pose NEES against the truth (times in s, values), or None.
        nees_dof: its degrees of freedom.
    """
    from graphcal.locomotion.metrics import chi2_band, interp_truth, pose_errors

    est = result.T_world_body[:, :3, 3]
    t = result.times
    out = {}
    # trajectory: top view and height
    fig = new_figure(10, 4.2)
    ax1, ax2 = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    if truth is not None:
        ax1.plot(truth.T_world_body[:, 0, 3], truth.T_world_body[:, 1, 3], "k-", lw=2.5, alpha=0.35, label="truth")
        # thin: a trot's bob at 2 Hz drawn 2.5 pt wide over a minute is a solid block
        ax2.plot(truth.times, truth.T_world_body[:, 2, 3], "k-", lw=0.8, alpha=0.6, label="truth")
    ax1.plot(est[:, 0], est[:, 1], "C0-", lw=1, label="estimate")
    ax1.set_xlabel("x (m)")
    ax1.set_ylabel("y (m)")
    ax1.set_aspect("equal", adjustable="datalim")
    ax1.set_title("body trajectory, top view (world)")
    ax1.legend(loc="best")
    ax2.plot(t, est[:, 2], "C0-", lw=1, label="estimate")
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("z (m)")
    ax2.set_title("body height")
    out["trajectory.png"] = figure_png(fig)

    # errors with the filter's 3-sigma
    fig = new_figure(10, 6)
    ci = result.cov_index
    sig = np.sqrt(np.maximum(np.diagonal(result.cov_pose, axis1=1, axis2=2), 0.0))
    axp, axr = fig.add_subplot(2, 1, 1), fig.add_subplot(2, 1, 2)
    labels = ("x", "y", "z")
    if truth is not None:
        e = pose_errors(result.T_world_body[ci], interp_truth(truth, t[ci]))
        for k in range(3):
            axp.plot(t[ci], 1e3 * e[:, k], f"C{k}-", lw=0.8, label=f"{labels[k]} error")
            axr.plot(t[ci], np.degrees(e[:, 3 + k]), f"C{k}-", lw=0.8, label=f"rot {labels[k]} error")
    for k in range(3):
        axp.plot(t[ci], 3e3 * sig[:, k], f"C{k}:", lw=0.8)
        axp.plot(t[ci], -3e3 * sig[:, k], f"C{k}:", lw=0.8)
        axr.plot(t[ci], 3 * np.degrees(sig[:, 3 + k]), f"C{k}:", lw=0.8)
        axr.plot(t[ci], -3 * np.degrees(sig[:, 3 + k]), f"C{k}:", lw=0.8)
    axp.set_ylabel("position (mm)")
    axr.set_ylabel("orientation (deg)")
    axr.set_xlabel("time (s)")
    axp.set_title("estimate - truth (solid) and the filter's 3 sigma (dotted)" if truth is not None
                  else "the filter's 3 sigma (no truth)")
    if truth is not None:
        axp.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)  # beside: inside it hid the 3 sigma
        axr.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    out["errors.png"] = figure_png(fig)

    # NIS
    fig = new_figure(10, 5)
    ax = fig.add_subplot(2, 1, 1)
    if len(result.stance_nis):
        dofs = result.stance_dofs
        nis, dof = result.stance_nis, result.stance_dof
        if dofs is not None and len(dofs) and np.ptp(dofs) > 0:  # feet in stance vary: NIS scaled to the largest dof
            nis = result.stance_nis * result.stance_dof / dofs
        lo, hi = chi2_band(dof)
        ax.plot(result.stance_times, nis, ".", ms=1.5, alpha=0.4, color="C0",
                label="stance NIS" if nis is result.stance_nis else f"stance NIS x {dof} / dof")
        w = max(1, len(nis) // 200)
        if w > 1:
            m = np.convolve(nis, np.ones(w * 5) / (w * 5), mode="same")
            ax.plot(result.stance_times, m, "C1-", lw=1, label="running mean")
        ax.axhline(dof, color="k", lw=0.8, label=f"dof {dof}")
        ax.axhspan(lo, hi, color="g", alpha=0.1, label="95 % band")
        top = float(np.nanpercentile(nis, 99)) if len(nis) else 0.0
        if top > 3 * hi:  # far outside the band: a log scale shows how far (a linear one would cut it off)
            ax.set_yscale("log")
            ax.set_ylim(max(1e-2, float(np.nanmin(nis[nis > 0])) if np.any(nis > 0) else 1e-2), 2 * float(np.nanmax(nis)))
            ax.set_title("log scale: the NIS is far above its band", fontsize=8, loc="right")
        else:
            ax.set_ylim(0, max(3 * hi, 1))
    ax.set_ylabel("NIS")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title("normalised innovation squared (stance kinematics; ICP and the pose NEES below)")
    ax = fig.add_subplot(2, 1, 2)
    if len(result.icp_nis):
        ax.plot(result.icp_times, result.icp_nis, "o", ms=3, label="ICP NIS")
        ax.plot(result.icp_times, result.icp_dof, "k_", ms=8, label="dof (directions fused)")
    if nees is not None and len(nees):
        ax.plot(nees_t, nees, "-", color="C3", lw=0.8, label=f"pose NEES (dof {nees_dof})")
    shown = np.concatenate([np.asarray(v, dtype=float).ravel() for v in (result.icp_nis, result.icp_dof,
                                                                          [] if nees is None else nees)])
    shown = shown[np.isfinite(shown)]
    if shown.size:  # a start-up transient of the NEES must not squash the ICP values: clip at 3x its 99th percentile
        top = max(3.0 * float(np.percentile(shown, 99)), 2.0 * nees_dof)
        if top < shown.max():
            ax.set_ylim(0.0, top)
            ax.set_title("clipped at 3x the 99th percentile", fontsize=8, loc="right")
    ax.set_xlabel("time (s)")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper right", fontsize=8)
    else:
        ax.text(0.5, 0.5, "no ICP updates, no truth", ha="center", va="center", transform=ax.transAxes)
    out["nis.png"] = figure_png(fig)
    if feet and result.stance_mask is not None:
        out["contacts.png"] = _contacts_figure(result, tuple(feet))
    return out


def _value(v, fmt: str, scale: float = 1.0, unit: str = "") -> str:
    return "n/a (no truth)" if v is None else f"{format(v * scale, fmt)}{unit}"


def _facts(items) -> str:
    return '<ul class="facts">' + "".join(f"<li>{x}</li>" for x in items) + "</ul>"


def _stairs_section(stairs_doc: dict) -> Section:
    if "error" in stairs_doc:
        return Section("Stairs", f"<p>stairs model failed: {esc(stairs_doc['error'])}</p>")
    kf = stairs_doc.get("keyframes", {})
    parts = [f"<p>{stairs_doc.get('n_clouds_used')} of {stairs_doc.get('n_clouds_available')} clouds "
             f"({esc(kf.get('method', ''))}), placed with the estimate, stitched by ICP (graphcal.locomotion.stairs).</p>"]
    treads = []
    for t in stairs_doc.get("treads", []):
        line = (f"tread {t.get('index')}: height {1e3 * t['height_m']:.1f} mm, depth "
                f"{1e3 * t['depth_m']:.1f} mm{'' if t.get('depth_complete') else ' (visible extent)'}, "
                f"width {1e3 * t['width_m']:.1f} mm (visible)")
        e = t.get("errors")
        if e and e.get("true_index", -1) >= 0:
            dep = e.get("depth_error_m")
            line += (f"; against true tread {e['true_index']}: height {1e3 * e['height_error_m']:+.1f} mm, "
                     f"depth {'n/a' if dep is None else format(1e3 * dep, '+.1f') + ' mm'}")
        elif e:
            line += "; no true tread within 5 cm of its height"
        treads.append(esc(line))
    parts.append(_facts(treads))
    tc = stairs_doc.get("truth_compared")
    if tc:
        parts.append(f"<p>Compared with the truth's {esc(tc['flight'])} flight ({esc(tc['selection'])}); all its treads "
                     f"found: {'yes' if tc.get('all_true_treads_found') else 'NO'}. {esc(tc['note'])}.</p>")
    return Section("Stairs", *parts)


def _verdict_section(c: dict | None) -> Section:
    """The filter-consistency verdict (metrics.json ``consistency``): overall, then per update kind
    the statistic, its reference distribution and p-value."""
    if not c:
        return Section("Filter consistency", "<p>not computed</p>")
    rows = [row(["update kind", "verdict", "mean NIS per dof", "windows outside / windows", "reference",
                 "p-value"], header=True)]
    for name, r in c["kinds"].items():
        if r["verdict"] == "not tested":
            rows.append(row([esc(name), "not tested (no update)", "–", "–", "–", "–"]))
            continue
        rows.append(row([esc(name), esc(r["verdict"]), num(r["mean_nis_per_dof"]),
                         f"{r['statistic']} / {r['n_windows']}", esc(r["reference"]), num(r["p_value"], ".3g")]))
    first = next((r for r in c["kinds"].values() if r["verdict"] != "not tested"), None)
    how = (f"Windows of {first['window_s']:g} s; each window's mean NIS per dof against its chi-square "
           f"{100 * first['interval_probability']:g} % interval; inconsistent when p < {first['alpha']:g} or the "
           f"whole-run mean lies outside its interval widened by {100 * first['tolerance']:g} %.") if first else ""
    return Section("Filter consistency: " + c["verdict"], f"<p>{esc(how)}</p>", table(rows))


def _bias_fact(b: dict | None) -> str:
    if not b or not b.get("worst"):
        return "stance innovation bias: not tested"
    w = b["worst"]
    return (f"stance innovation bias: {b['verdict']} (worst {w['slot']} along body {w['axis']}: mean "
            f"{w['mean_sigma']:+.2f} sigma, t = {w['t']:.1f}; biased from 0.3 sigma and t = 5: a leg model off by a "
            "constant)")


def _floor_fact(f: dict | None) -> str:
    if not f or not (f["updates"] or f["zero_velocity_updates"]):
        return "level floor: not used (the ground is not declared level); no zero-velocity update"
    nis = "n/a" if f["nis_per_dof"] is None else format(f["nis_per_dof"], ".3g")
    return (f"level floor: {f['updates']} touchdown updates ({f['feet_measured']} feet), NIS per dof {nis}; "
            f"{f['zero_velocity_updates']} zero-velocity updates while lying")


def _plausibility_section(p: dict | None) -> Section:
    """The plausibility verdict (metrics.json ``plausibility``): each check's bound and worst value,
    then the failures with their times."""
    if not p:
        return Section("Physical plausibility", "<p>not computed</p>")
    rows = [row(["check", "ran", "bound", "worst", "at (s)", "failures"], header=True)]
    for kind, c in p["checks"].items():
        rows.append(row([esc(kind), "yes" if c["tested"] else esc(f"no: {c['reason']}"), num(c["bound"], ".3g") +
                         f" {esc(c['unit'])}", num(c["worst"], ".3g"), num(c["worst_s"], ".1f"), str(c["n_failures"])]))
    fails = _facts(esc(f["message"]) for f in p["failures"][:12]) if p["failures"] else "<p>no failure</p>"
    how = ("Against what the robot's legs and a level floor allow, with no truth (docs/state_estimation.md, "
           "'Plausibility'): touchdown and body heights against the floor it stood on, body within its legs' reach, "
           "attitude on level ground, stance-foot slip.")
    return Section("Physical plausibility: " + p["verdict"], f"<p>{esc(how)}</p>", table(rows), fails)


def _noise_section(noise: dict | None) -> Section:
    """The noise the filter used (metrics.json ``noise``), each value with its unit and source."""
    if not noise:
        return Section("Noise", "<p>not recorded</p>")
    rows = [row(["value", "", "unit", "source"], header=True)]
    for k, v in noise["values"].items():
        rows.append(row([esc(k), num(v, ".4g"), esc(noise["units"].get(k, "")), esc(noise["sources"].get(k, ""))]))
    return Section("Noise (noise.yaml; give it back with --noise)", table(rows))


def _contacts_section(c: dict | None, phases: dict | None) -> Section:
    """The contact decision per foot (metrics.json ``contacts``) and the log's phases."""
    parts = []
    if phases:
        parts.append(_facts(esc(f"{s['phase'].replace('_', ' ')}: {s['start_s']:.2f}-{s['end_s']:.2f} s")
                            for s in phases["segments"]))
    if c:
        rows = [row(["foot", "thresholds", "on", "off", "low mode", "high mode", "duty factor", "stances",
                     "short removed"], header=True)]
        for f, r in c["feet"].items():
            rows.append(row([esc(f), esc(r["source"]), num(r["on"], ".3g"), num(r["off"], ".3g"), num(r["low_mode"], ".3g"),
                             num(r["high_mode"], ".3g"), num(r["duty_factor"], ".2f"), str(r["n_stances"]),
                             str(r["n_short_stances_removed"] + r["n_short_swings_removed"])]))
        source = esc(f"from {c['signal']}")
        parts.append(f"<p>{source}; minimum stance {c['min_stance_s']:g} s, swing {c['min_swing_s']:g} s.</p>")
        parts.append(table(rows))
    return Section("Contacts and phases", *(parts or ["<p>the two-tripod support model (no per-foot thresholds)</p>"]))


def _scene_section(scene) -> Section:
    from graphcal.report.scene_view import scene_figure, scene_html

    return Section("3-D scene", scene_html(scene),
                   f'<p class="small">World frame, m (z up, the floor at z = 0). {esc(scene.note)}</p>',
                   figure(scene_figure(scene, elev=24.0), "The same scene, for printing."))


def track_html(m: dict, stairs_doc: dict | None, pngs: dict[str, bytes], *, title: str = "graphcal track",
               scene=None) -> str:
    """The page of a track output: ``m`` is metrics.json (SI units; null without truth), ``stairs_doc``
    stairs.json or None, ``pngs`` the plots (file name -> PNG, :func:`track_figures`), ``scene`` the
    3-D view (:func:`graphcal.report.scene_3d.track_scene`) or None."""
    w = m.get("innovation_whiteness") or {}
    subtitle = (f"Dataset: {m['dataset']}; {m['n_samples']} samples over {m['duration_s']:.2f} s, processed in "
                f"{m['processing_s']:.2f} s ({m['real_time_factor']:.1f}x real time). Filter: error-state EKF "
                "(filterpy), IMU propagation, stance-foot kinematics (support from joint torques or foot forces), ICP between "
                "keyframe clouds as relative-pose measurements (docs/state_estimation.md).")
    accuracy = _facts(esc(x) for x in (
        f"distance: {m['distance_m']:.2f} m ({m['distance_source']})",
        f"APE (RMS, no alignment): {_value(m.get('ape_rmse_m'), '.2f', 1e3, ' mm')}",
        f"RPE over {m.get('rpe_delta_m', 1.0)} m (RMS): {_value(m.get('rpe_rmse_m'), '.2f', 1e3, ' mm')}",
        f"drift (final error / distance): {_value(m.get('drift_percent'), '.3f', 1.0, ' %')}",
        f"pose NEES mean: {_value(m.get('nees_mean'), '.2f')} (dof 6; fraction of samples inside the single-sample "
        f"95 % band: {_value(m.get('nees_fraction_in_band'), '.3f')})",
    ))
    consistency = _facts(esc(x) for x in (
        f"stance NIS mean {_value(m.get('stance_nis_mean'), '.2f')} (dof {_value(m.get('stance_nis_dof_mean'), '.3g')}), "
        f"{m['stance_updates']} updates, {m['support_switches']} support switches",
        f"innovation whiteness: {_value(w.get('fraction_inside'), '.3f')} of the autocorrelations at lags "
        f"1..{w.get('lags')} inside ±1.96/sqrt(n) (white: 0.95); max |rho| {_value(w.get('max_abs_autocorr'), '.3f')}",
        (f"ICP: {m['icp_updates']} fused (mean NIS {_value(m.get('icp_nis_mean'), '.2f')}, "
         f"{_value(m.get('icp_dof_mean'), '.1f')} directions on average), {m['icp_rejected']} rejected"
         if m["icp_updates"] or m["icp_rejected"] else "ICP: no update (no clouds in the dataset, or --no-icp)"),
        _floor_fact(m.get("floor")),
        _bias_fact(m.get("innovation_bias")),
    ))
    heading = "Accuracy" + ("" if m["truth"] else " (no truth.yaml beside the dataset: the keys that need it are null)")
    sections = [_plausibility_section(m.get("plausibility")), _verdict_section(m.get("consistency")),
                Section(heading, accuracy), Section("Consistency", consistency),
                _contacts_section(m.get("contacts"), m.get("phases")), _noise_section(m.get("noise"))]
    if stairs_doc is not None:
        sections.append(_stairs_section(stairs_doc))
    if scene is not None:
        sections.append(_scene_section(scene))
    sections.append(Section("Figures", *(figure_png_html(png, f"{name}: {FIGURE_CAPTIONS.get(name, '')}")
                                         for name, png in pngs.items()),
                            "<p class='small'>Trajectory: trajectory.tum (TUM: t x y z qx qy qz qw); every number "
                            "above: metrics.json.</p>"))
    c = m.get("consistency") or {}
    p = m.get("plausibility") or {}
    warn = ([f"The trajectory is physically implausible: {p['failures'][0]['message']}."]
            if p.get("verdict") == "implausible" and p.get("failures") else [])
    b = m.get("innovation_bias") or {}
    if b.get("verdict") == "biased":
        warn.append(f"The stance innovations of {b['worst']['slot']} are biased along body {b['worst']['axis']}: "
                    "the leg model is off by a constant (joint offsets, link lengths); the trajectory drifts with it.")
    warn += ([f"The filter's innovations are inconsistent with its covariance ({', '.join(c['inconsistent_kinds'])}): "
             "the noise settings or the model do not fit the data; the trajectory's sigma are not to be trusted."]
            if c.get("verdict") == "inconsistent" else [])
    return render_page(title, sections, subtitle=subtitle, warnings=warn, footer="Written by graphcal track.")
