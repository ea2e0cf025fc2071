"""The ``report.html`` of ``graphcal identify-legs`` and its figure: foot-marker errors before and after
per sample (Yuan et al. Figs. 6 and 8), the identified parameters, the measurement frame's pose, the
markers and the identifiability analysis (one page of :mod:`graphcal.report.page`)."""

from __future__ import annotations

import math

import numpy as np

from graphcal.report.page import Markup, Section, esc, figure_png_html, num, render_page
from graphcal.report.plots import AFTER_COLOR, BEFORE_COLOR, new_figure

__all__ = ["foot_error_figure", "identification_html"]

_FRAME_TEXT = {"vbase": "Yuan virtual base (body markers)", "mocap": "motion-capture frame fixed to the base"}


def _unit(name: str) -> tuple[float, str]:
    """(factor SI -> report unit, unit) of a parameter name."""
    if name.endswith("_rad") or name.split(".")[-1] in ("rx", "ry", "rz"):
        return 180.0 / math.pi, "deg"
    return 1000.0, "mm"


def foot_error_figure(result, foot: str):
    """Figure of one foot's marker errors before / after (Yuan Figs. 6 and 8): the error norm per
    sample, then the error along body x, y, z per sample (mm)."""
    rs = [r for r in result.residuals if r.foot == foot]
    fig = new_figure(9.0, 8.0)
    axs = fig.subplots(4, 1, sharex=True)
    off = 0
    for r in rs:
        idx = off + np.arange(len(r.time))
        off += len(r.time)
        eb, ea = 1e3 * r.before, 1e3 * r.after
        axs[0].plot(idx, np.linalg.norm(eb, axis=1), color=BEFORE_COLOR, lw=0.7,
                    label="before (nominal legs)" if r is rs[0] else None)
        axs[0].plot(idx, np.linalg.norm(ea, axis=1), color=AFTER_COLOR, lw=0.7,
                    label="after (identified)" if r is rs[0] else None)
        for a in range(3):
            axs[a + 1].plot(idx, eb[:, a], color=BEFORE_COLOR, lw=0.6)
            axs[a + 1].plot(idx, ea[:, a], color=AFTER_COLOR, lw=0.6)
    b, a = result.rmse_mm(foot)
    axs[0].set_title(f"{foot}: marker error per sample, RMSE {b:.2f} mm before, {a:.2f} mm after")
    axs[0].set_ylabel("|e| [mm]")
    axs[0].legend(loc="upper right", fontsize=8)
    for k, lab in enumerate("xyz"):
        axs[k + 1].set_ylabel(f"e_{lab} [mm]")
        axs[k + 1].axhline(0.0, color="k", lw=0.5)
    axs[3].set_xlabel("sample")
    return fig


def _rmse_table(result) -> list[str]:
    out = ["<table><tr><th class='l'>foot</th><th>samples</th><th>everything nominal [mm]</th>"
           "<th>before: nominal legs [mm]</th><th>after [mm]</th></tr>"]
    for foot in result.legs:
        rs = [r for r in result.residuals if r.foot == foot]
        b, a = result.rmse_mm(foot)
        nom = [r.rmse_nominal_mm for r in rs]
        nomtxt = num(np.sqrt(np.mean(np.square(nom))), ".2f") if all(v is not None for v in nom) else "–"
        out.append(f"<tr><td class='l'><code>{esc(foot)}</code></td><td>{sum(len(r.time) for r in rs)}</td>"
                   f"<td>{nomtxt}</td><td>{num(b, '.2f')}</td><td>{num(a, '.2f')}</td></tr>")
    out.append("</table><p class='small'>Before: the nominal URDF with the pose of the measurement frame (and "
               "unknown marker positions) fitted; after: the identified parameters. Errors are measured minus "
               "predicted marker positions.</p>")
    return out


def _adequacy_section(result) -> list[str]:
    """The verdict (declared noise), the flagged postures and the test used."""
    a = result.adequacy
    if a is None:
        return ["<p>No verdict.</p>"]
    cls = "ok" if a.fits and not a.flagged else "warn"
    out = [f"<p class='{cls}'><b>{esc(a.verdict)}</b>: {esc(a.message)}</p>",
           "<table><tr><th class='l'>statistic</th><th class='l'>reference</th><th>p-value</th><th>σ0</th>"
           "<th>σ0 limit</th><th class='l'>group</th><th class='l'>judged against</th></tr>",
           f"<tr><td class='l'>χ² = {num(a.statistic, '.1f')}</td><td class='l'>{esc(a.reference)}</td>"
           f"<td>{num(a.p_value, '.3g')}</td><td>{num(a.sigma0, '.3f')}</td><td>{num(a.sigma0_limit, '.3f')}</td>"
           f"<td class='l'>{esc(a.group or '–')}</td><td class='l'>{esc(str(a.noise.get('source', '')))}</td></tr></table>"]
    flagged = [t for t in a.postures if t.flagged]
    if flagged:
        out.append("<table><tr><th>outlier posture t [s]</th><th>F</th><th>Bonferroni p</th><th>deletion χ²</th>"
                   "<th>position error [mm]</th></tr>")
        out += [f"<tr><td>{num(t.time, 'g')}</td><td>{num(t.f_statistic, '.1f')}</td><td>{num(t.p_bonferroni, '.2g')}</td>"
                f"<td>{num(t.statistic, '.1f')}</td><td>{num(t.rms_mm, '.1f')}</td></tr>" for t in flagged]
        out.append("</table>")
        if a.without_flagged is not None:
            s, dof, p, v = a.without_flagged
            out.append(f"<p>Without the flagged postures: χ² = {num(s, '.1f')} for {dof} dof, p = {num(p, '.3g')}: "
                       f"<b>{esc(v)}</b>.</p>")
    else:
        out.append(f"<p>No posture flagged ({len(a.postures)} tested).</p>")
    out.append("<p class='small'>Verdict: χ² of the residuals whitened by the declared physical noise against χ²(dof), "
               f"fits when p ≥ {a.alpha:g}. Postures: deletion χ² in an F test against the other postures, "
               f"Bonferroni over the postures at {a.alpha:g}. σ of each parameter: the larger of the model σ and the "
               "leave-one-posture-out jackknife σ (docs/legs.md).</p>")
    return out


def _parameter_tables(result) -> tuple[list[str], list[str], list[str]]:
    legs = ["<table><tr><th class='l'>foot</th><th class='l'>parameter</th><th>value</th>"
            "<th>1-σ</th><th>model σ</th><th>jackknife σ</th><th class='l'>unit</th><th class='l'>significant at</th>"
            "<th class='l'>status</th></tr>"]
    for foot, params in result.legs.items():
        for p in params:
            f, u = _unit(p.name)
            val = num(f * p.value, "+.4f") if p.free else "held 0"
            sig = num(f * p.sigma, ".4f") if p.free else ""
            sm = num(f * p.sigma_model, ".4f") if p.free else ""
            sj = num(f * p.sigma_jackknife, ".4f") if p.free else ""
            lvl = p.significance["level"]
            legs.append(f"<tr><td class='l'>{esc(foot)}</td><td class='l'><code>{esc(p.name)}</code></td><td>{val}</td>"
                        f"<td>{sig}</td><td>{sm}</td><td>{sj}</td><td class='l'>{u}</td><td class='l'>{esc(lvl)}</td>"
                        f"<td class='l'>{esc(p.status)}</td></tr>")
    legs.append("</table>")
    pose = ["<table><tr><th class='l'>component</th><th>change from reference</th>"
            "<th>1-σ</th><th class='l'>unit</th><th class='l'>status</th></tr>"]
    for p in result.mocap:
        f, u = _unit(p.name)
        pose.append(f"<tr><td class='l'><code>{esc(p.name)}</code></td><td>{num(f * p.value, '+.4f')}</td>"
                    f"<td>{num(f * p.sigma, '.4f') if p.free else ''}</td><td class='l'>{u}</td>"
                    f"<td class='l'>{esc(p.status)}</td></tr>")
    pose.append("</table>")
    markers = []
    if result.markers:
        markers = ["<table><tr><th class='l'>marker</th><th>x [mm]</th><th>y [mm]</th><th>z [mm]</th>"
                   "<th>1-σ [mm]</th></tr>"]
        for name, ps in result.markers.items():
            markers.append(f"<tr><td class='l'><code>{esc(name)}</code></td>"
                           + "".join(f"<td>{num(1e3 * p.value, '+.2f')}</td>" for p in ps)
                           + f"<td>{' / '.join(num(1e3 * p.sigma, '.2f') for p in ps)}</td></tr>")
        markers.append("</table>")
    return legs, pose, markers


def identification_html(result, pngs: dict[str, bytes], *, title: str) -> str:
    """One self-contained page: foot errors, parameters, pose, markers, identifiability, figures.
    ``pngs``: foot -> PNG of :func:`foot_error_figure`."""
    subtitle = Markup(
        f"Robot <code>{esc(result.robot_name)}</code>, base frame <code>{esc(result.base_frame)}</code>; "
        f"measurement frame: {esc(_FRAME_TEXT.get(result.frame, result.frame))}; "
        f"{result.iterations} LM iterations ({'converged' if result.converged else 'NOT converged'}), "
        f"σ0 = {num(result.sigma0, '.3f')} (a-posteriori noise / a-priori noise).")
    legs, pose, markers = _parameter_tables(result)
    r = result.identifiability
    ident = [f"<p class='small'>Scaled whitened Jacobian: rank {r.rank} of {len(r.names)}; threshold "
             f"max({r.rtol:g}·s_max, {r.s_min:g}) = {num(r.threshold, '.3g')} (s in noise standard deviations for an "
             f"error of the a-priori size); identifiable when less than {r.f_identifiable:g} of the parameter lies in "
             f"the null space.</p>",
             "<ul>" + "".join(f"<li>{esc(line)}</li>" for line in r.lines()) + "</ul>"]
    sections = [Section("Model adequacy", *_adequacy_section(result)),
                Section("Foot marker error (3-D RMSE)", *_rmse_table(result)),
                Section("Leg parameters", *legs),
                Section(result.pose_name, *pose)]
    if markers:
        sections.append(Section("Marker positions on the foot", *markers))
    sections.append(Section("Identifiability", *ident))
    sections.append(Section("Figures", *(
        figure_png_html(png, f"{foot}: marker error per sample before (grey) and after (blue) identification, "
                             "norm and body axes (Yuan et al. Figs. 6 and 8).") for foot, png in pngs.items())))
    return render_page(title, sections, subtitle=subtitle, warnings=result.warnings,
                       footer="Written by graphcal identify-legs. Method: docs/legs.md.")
