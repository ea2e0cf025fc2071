"""The ``report.html`` of ``graphcal calibrate``: one self-contained page (:mod:`graphcal.report.page`)
summarising a calibration for a human."""

from __future__ import annotations

import numpy as np

from graphcal.geometry import rotation_angle_between, rpy_from_matrix, so3_log
from graphcal.report.calibration_yaml import residual_summary
from graphcal.report.page import Markup, Section, esc, figure, num, render_page
from graphcal.report.plots import report_figures
from graphcal.report.ros import static_transform_publisher_command

__all__ = ["report_html"]

_e = esc
_n = num


def _row(cells, header: bool = False, first_left: bool = True) -> str:
    tag = "th" if header else "td"
    out = []
    for i, c in enumerate(cells):
        cls = ' class="l"' if (i == 0 and first_left) else ""
        out.append(f"<{tag}{cls}>{c}</{tag}>")
    return "<tr>" + "".join(out) + "</tr>"


def _sensor_section(name: str, s, base_frame: str) -> str:
    T, P = np.asarray(s.T_body_sensor, dtype=float), np.asarray(s.T_body_sensor_prior, dtype=float)
    xyz, xyz0 = T[:3, 3] * 1000.0, P[:3, 3] * 1000.0
    rpy, rpy0 = np.rad2deg(rpy_from_matrix(T[:3, :3])), np.rad2deg(rpy_from_matrix(P[:3, :3]))
    parts = [f"<h3>Sensor <code>{_e(name)}</code> ({_e(s.type)})</h3>"]
    parts.append(
        f'<p class="small">T_{_e(base_frame)}_{_e(name)}: translation in mm, ROS roll/pitch/yaw in deg '
        f"(R = Rz(yaw) Ry(pitch) Rx(roll)).</p>"
    )
    head = _row(["", "x [mm]", "y [mm]", "z [mm]", "roll [deg]", "pitch [deg]", "yaw [deg]"], header=True)
    rows = [head]
    for lab, t, r in (("prior (CAD)", xyz0, rpy0), ("estimate", xyz, rpy)):
        rows.append(_row([lab] + [_n(v, ".2f") for v in t] + [_n(v, ".3f") for v in r]))
    parts.append("<table>" + "".join(rows) + "</table>")
    # change and uncertainty along / about the body axes (left perturbation, same axes as sigma)
    d_rot = np.rad2deg(so3_log(T[:3, :3] @ P[:3, :3].T))
    head = _row(["body axes", "along x [mm]", "along y [mm]", "along z [mm]", "about x [deg]", "about y [deg]",
                 "about z [deg]"], header=True)  # fmt: skip
    rows = [
        head,
        _row(["estimate − prior"] + [_n(v, "+.2f") for v in xyz - xyz0] + [_n(v, "+.3f") for v in d_rot]),
        _row(["1-σ" if getattr(s, "covariance_model", None) is None else "1-σ robust (governs)"]
             + [_n(v, ".3f") for v in s.sigma_xyz_mm] + [_n(v, ".4f") for v in s.sigma_rot_deg]),
    ]
    if getattr(s, "covariance_model", None) is not None:
        from graphcal.solvers.covariance import body_axis_sigmas

        rot_m, xyz_m, _, _ = body_axis_sigmas(T, s.covariance_model)
        rows.append(_row(["1-σ model (the model does not fit)"] + [_n(v, ".3f") for v in xyz_m]
                         + [_n(v, ".4f") for v in rot_m]))
    parts.append("<table>" + "".join(rows) + "</table>")
    dang = np.rad2deg(rotation_angle_between(P[:3, :3], T[:3, :3]))
    parts.append(
        f'<p class="small">Change from the prior: {_n(np.linalg.norm(xyz - xyz0), ".2f")} mm, '
        f"{_n(dang, '.3f')} deg.</p>"
    )
    scale = float(getattr(s, "covariance_scale", 1.0))
    if scale > 1.0:
        parts.append(
            f'<p class="small">The covariance (and every σ) includes a factor of {_n(scale, ".3g")} '
            f"(σ ×{_n(np.sqrt(scale), '.3g')}): the plane residuals of this run scatter more than the given noise "
            "model predicts.</p>"
        )
    if s.unobservable:
        items = "".join(f"<li>{_e(u)}</li>" for u in s.unobservable)
        parts.append(
            f'<div class="warn"><strong>Not determined by the data ({len(s.unobservable)} '
            f"direction{'s' if len(s.unobservable) != 1 else ''}):</strong><ul>{items}</ul>"
            f"The data does not support the estimate along these directions; each entry names the "
            f"motion that would determine it.</div>"
        )
    elif getattr(s, "range_scale_check", None) is not None and not s.range_scale_check.determined:
        parts.append('<p>All six directions are determined by the data <b>if the range is exact</b>: these data do not '
                     'determine its range scale (section "Does the model fit?").</p>')
    else:
        parts.append('<p class="ok">All six directions are determined by the data.</p>')
    if len(s.segments) > 1 or s.change_stations:
        rows = [_row(["stations", "x [mm]", "y [mm]", "z [mm]", "roll [deg]", "pitch [deg]", "yaw [deg]"], header=True)]
        for seg in s.segments:
            Ts = np.asarray(seg.T_body_sensor, dtype=float)
            r = np.rad2deg(rpy_from_matrix(Ts[:3, :3]))
            rows.append(_row([f"{int(seg.first_station)}–{int(seg.last_station)}"]
                             + [_n(v * 1000.0, ".2f") for v in Ts[:3, 3]] + [_n(v, ".3f") for v in r]))  # fmt: skip
        chg = ", ".join(str(int(c)) for c in s.change_stations) or "none"
        parts.append(
            f'<div class="warn"><strong>The sensor moved during the session</strong> (change detected at '
            f"station{'s' if len(s.change_stations) != 1 else ''} {_e(chg)}). The estimate above is the last "
            f"segment's.</div><table>{''.join(rows)}</table>"
        )
    return "\n".join(parts)


def _legs_section(result) -> str:
    if not result.legs:
        return '<p class="small">Leg kinematics were not calibrated (run with <code>--legs</code>).</p>'
    rows = [_row(["foot", "parameter", "value", "1-σ", "unit"], header=True)]
    for foot, leg in result.legs.items():
        for n, v, sg in zip(leg.names, leg.values, leg.sigmas):
            n = str(n)
            if n.endswith("_rad"):
                val, sig, unit = _n(np.rad2deg(v), "+.4f"), _n(np.rad2deg(sg), ".4f"), "deg"
            elif n.endswith("_m"):
                val, sig, unit = _n(v * 1000.0, "+.3f"), _n(sg * 1000.0, ".3f"), "mm"
            else:
                val, sig, unit = _n(v, "+.6g"), _n(sg, ".3g"), ""
            rows.append("<tr>" + f'<td class="l">{_e(foot)}</td><td class="l"><code>{_e(n)}</code></td>'
                        f"<td>{val}</td><td>{sig}</td><td class=\"l\">{unit}</td></tr>")  # fmt: skip
    return "<table>" + "".join(rows) + "</table>"


def _residual_section(result) -> str:
    rows = [
        _row(["sensor", "stations", "θ RMS before [deg]", "θ RMS after [deg]", "e_d RMS before [mm]",
              "e_d RMS after [mm]", "θ mean / max after [deg]", "e_d mean / max after [mm]"], header=True)  # fmt: skip
    ]
    names = list(result.sensors) + sorted({r.sensor for r in result.residuals} - set(result.sensors))
    for s in names:
        sm = residual_summary(result, s)
        if sm["stations"] == 0 and sm["outlier_rows"] == 0:
            continue
        rows.append(_row([
            f"<code>{_e(s)}</code>", f"{sm['stations']} (+{sm['outlier_rows']} outl.)",
            _n(sm["normal_rms_deg_before"], ".4f"), _n(sm["normal_rms_deg_after"], ".4f"),
            _n(sm["distance_rms_mm_before"], ".3f"), _n(sm["distance_rms_mm_after"], ".3f"),
            f"{_n(sm['angle_mean_deg_after'], '.4f')} / {_n(sm['angle_max_deg_after'], '.4f')}",
            f"{_n(sm['distance_mean_mm_after'], '.3f')} / {_n(sm['distance_max_mm_after'], '.3f')}",
        ]))  # fmt: skip
    total = residual_summary(result)
    # as calibration.yaml's residuals.stations: every station with residuals, outliers included
    every = {int(r.station) for r in result.residuals}
    n_out = len(every & {int(s) for s in result.outliers})
    rows.append(_row([
        "<strong>all (solver)</strong>", f"{len(every) - n_out} (+{n_out} outl.)",
        _n(total["normal_rms_deg_before"], ".4f"), _n(result.normal_rms_deg, ".4f"),
        _n(total["distance_rms_mm_before"], ".3f"), _n(result.distance_rms_mm, ".3f"), "", "",
    ]))  # fmt: skip
    return (
        "<table>" + "".join(rows) + "</table>"
        '<p class="small">θ: angle between the measured and the predicted ground plane; e_d = |d_T − d_M|: '
        "difference of their distances from the sensor (Chai et al. 2015, Sec. 5.2). Before: CAD prior; "
        "after: calibrated model. Statistics over the non-outlier stations; the last row's “after” values "
        "are the solver's own RMS.</p>"
    )


def _noise_section(result) -> str:
    groups = getattr(result, "noise_groups", ()) or ()
    if not groups:
        source = getattr(result, "noise_source", "") or ""
        where = f" (read from <code>{_e(source)}</code>)" if source else ""
        return f'<p class="small">The noise model was given{where}, not learned from the data.</p>'
    rows = [_row(["group", "σ", "status", "dof", "residuals point to", "χ² p (upper)"], header=True)]
    for g in groups:
        shared = getattr(g, "shared_with", ())
        status = g.status + (f" (scaled with {', '.join(shared)})" if shared else "")
        rows.append(_row([f"<code>{_e(g.group)}</code>", _e(g.values_text()), _e(status), _n(g.dof, ".1f"),
                          f"x{_n(g.data_scale, '.3g')}", _n(g.p_high, ".2g")]))  # fmt: skip
    if all(g.status == "given" for g in groups):
        source = getattr(result, "noise_source", "") or ""
        where = f" read from <code>{_e(source)}</code>" if source else " (the defaults)"
        return (
            "<table>" + "".join(rows) + "</table>"
            f'<p class="small">The noise model was given{where}, not learned from the data. The table shows '
            "the factor each group's residuals point to for its σ at the solution. With a noise model read from "
            "an earlier calibration, each sensor's covariance is multiplied by its planes' factor squared when "
            "that is above 1 (the sensor section says so).</p>"
        )
    return (
        "<table>" + "".join(rows) + "</table>"
        '<p class="small">σ of each noise group learned from the residuals (variance-component estimation). '
        "<em>too few dof</em>: the group's rows carry too little redundancy for its σ to be estimated; it was "
        "held and the residuals only hint at the factor shown. Held above what the residuals point to, it makes "
        "the covariance conservative; a small upper χ² p means its σ is too small (then a warning above). "
        "<em>scaled with</em>: the data do not separate the components of a sum (a foot's joint and contact "
        "noise), so they keep their ratio and share one scale; dof and χ² are those of their sum.</p>"
    )


def _adequacy_section(result) -> str:
    """The verdict on the model (calibration.yaml ``adequacy:``): one line, then a row per group."""
    a = getattr(result, "adequacy", None)
    if a is None:
        return "<p>Not judged.</p>"
    cls = "" if a.fits else ' class="warn"'
    out = [f"<p{cls}><b>The model {_e(a.verdict)}</b>: worst group <code>{_e(a.worst_group or 'none')}</code>, "
           f"statistic {_n(a.statistic, '.4g')} against {_e(a.reference)}, p = {_n(a.p_value, '.2g')} "
           "(Bonferroni over the groups). Each group's learned σ is judged against its physical σ "
           "(dataset.yaml <code>physical_noise:</code>, else graphcal's defaults), not against the noise "
           "learned from the same residuals. "
           + ("σ in this report is the model's." if a.fits else
              "σ in this report is the robust one (model covariance scaled by the misfit, plus a jackknife "
              "over stations, plus the shift to <code>--legs</code> where a leg's group does not fit and the "
              "shift to a solution with a range scale where a sensor's planes do not fit); "
              "the model's is beside it.") + "</p>"]
    for name, s in result.sensors.items():
        terms = getattr(s, "robust_terms", ())
        if terms:
            out.append(f"<p>Robust covariance of <code>{_e(name)}</code>, the sum of: "
                       + "; ".join(f"<b>{_e(k)}</b>: {_e(v)}" for k, v in terms) + ".</p>")
    rows = [_row(["group", "learned", "physical", "ratio", "T", "dof", "p", "misfit"], header=True)]
    for g in a.groups:
        rows.append(_row([g.group, g.learned_text(), g.physical_text(), _n(g.ratio, ".3g"), _n(g.statistic, ".4g"),
                          _n(g.dof, ".1f"), _n(g.p_value, ".2g"), "yes" if g.misfit else "no"]))
    out.append("<table>" + "".join(rows) + "</table>")
    if a.gross:
        out.append(f"<p>Gross stations {'left out' if a.gross_left_out else 'found (not left out)'}: " + ", ".join(
            f"{int(s.station)} (χ² per dof {_n(s.factor, '.3g')} times a typical station's, p = {_n(s.p_value, '.2g')})"
            for s in a.gross) + ".</p>")
    if a.next_steps:
        out.append("<p>Next: " + "; ".join(_e(x) for x in a.next_steps) + ".</p>")
    out.append(_range_scale_paragraph(result))
    return "".join(out)


def _range_scale_paragraph(result) -> str:
    """Whether the data determine each sensor's range scale (calibration.yaml ``range_scale_check``)."""
    from graphcal.calibration.range_observability import range_scale_warning

    items = []
    for name, s in result.sensors.items():
        c = getattr(s, "range_scale_check", None)
        if c is None:
            continue
        w = range_scale_warning(c)
        if w:
            items.append(f'<p class="warn">{_e(w)}.</p>')
        else:
            items.append(f"<p><code>{_e(name)}</code>: the data determine its range scale to "
                         f"±{_n(100.0 * c.sigma_from_data, '.2g')} % (checked to {_n(c.limit_pct, '.2g')} %); a scale "
                         f"error of 1 % would move its translation by {_n(c.translation_mm, '.2g')} mm and show "
                         "in the planes' fit.</p>")
    if not items:
        return ""
    return ("<p>The σ assume each sensor's range is exact. Whether these data could see a range scale "
            "(measured / true range), from the final graph with a scale added:</p>" + "".join(items))


def _scene_section(scene) -> list:
    """The 3-D view, its printable PNG, and the floor's collapse per sensor."""
    from graphcal.report.scene_3d import ELLIPSOID_SCALE
    from graphcal.report.scene_view import floor_figure, scene_figure, scene_html

    if scene is None or not scene.groups:
        return ['<p class="small">No 3-D scene: the calibration has no body poses.</p>']
    parts = []
    for c in scene.collapse:
        thinner = c.rms_calibrated_m < c.rms_prior_m
        parts.append(
            ("<p><b>The floor collapses</b>" if thinner else
             '<p class="warn"><b>The floor does not collapse: it is thicker with the calibrated extrinsic than '
             "with the CAD prior</b>")
            + f" (<code>{_e(c.sensor)}</code>): the RMS distance of the "
            f"{int(c.points)} ground points of {int(c.stations)} stations to the floor the feet stand on (world "
            f"z = 0) is "
            f"<b>{_n(c.rms_prior_m * 1e3, '.2f')} mm with the CAD prior</b> and "
            f"<b>{_n(c.rms_calibrated_m * 1e3, '.2f')} mm with the calibrated extrinsic</b> "
            "(the same points and body poses).</p>")
    parts.append(scene_html(scene))
    parts.append(f'<p class="small">World frame, m. {_e(scene.note)} Body poses: x red, y green, z blue. '
                 "Sensor frames: the longer triad is the calibrated pose, the shorter the CAD prior; the violet "
                 "rings the principal sections of the calibrated position's 3σ ellipsoid, drawn "
                 f"×{ELLIPSOID_SCALE:g}.</p>")
    parts.append(figure(scene_figure(scene), "The same scene, for printing (every group shown)."))
    if scene.ground:
        parts.append(figure(floor_figure(scene), "Height above the floor of every ground point (mm): the same "
                            "points under the CAD prior and under the calibrated extrinsic."))
    return parts


def report_html(result, *, title: str = "graphcal calibration report", scene=None) -> str:
    """The HTML report of ``result`` (a CalibrationResult) as one self-contained page.

    Sections: summary per sensor (prior vs estimate, σ per body axis in mm/deg, undetermined
    directions in a warning box, segments when the sensor moved), legs, outliers, the noise model
    (how each group's σ was set), residual RMS
    before/after, the figures of :func:`graphcal.report.plots.report_figures` (one ``<img>`` each,
    PNG data URI), warnings and the ROS 2 static_transform_publisher lines; with ``scene`` (a
    :class:`~graphcal.report.scene_3d.Scene`) its 3-D view, printable PNG and floor collapse.
    """
    from graphcal.report.walk_section import walk_section

    base = str(result.base_frame)
    subtitle = Markup(
        f"Dataset: <code>{_e(result.dataset)}</code> · base frame <code>{_e(base)}</code> · "
        f"solver: {_e(result.solver)} ({int(result.iterations)} "
        f"{'iterations' if result.solver == 'batch' else 'stations'}) · "
        f"sensors: {', '.join(f'<code>{_e(s)}</code>' for s in result.sensors) or 'none'}")
    if result.outliers:
        outliers = (f"<p>{len(result.outliers)} station{'s' if len(result.outliers) != 1 else ''} down-weighted by the "
                    f"robust loss: {_e(', '.join(str(int(s)) for s in sorted(result.outliers)))}.</p>")
    else:
        outliers = "<p>None: no station was down-weighted by the robust loss.</p>"
    cmds = "\n".join(static_transform_publisher_command(base, str(n), s.T_body_sensor, sep=" \\\n    ")
                     for n, s in result.sensors.items())  # over four lines: one overflowed its box
    sections = [
        Section("Does the model fit?", _adequacy_section(result)),
        Section("Sensors", *(_sensor_section(str(name), s, base) for name, s in result.sensors.items())),
        *([Section("Walk", *walk_section(result))] if getattr(result, "walk", None) else []),
        *([Section("3-D scene", *_scene_section(scene))] if scene is not None else []),
        Section("Legs", _legs_section(result)),
        Section("Outliers", outliers),
        Section("Noise model", _noise_section(result)),
        Section("Plane residuals", _residual_section(result)),
        Section("Figures", *(figure(fig, caption) for caption, fig in report_figures(result))),
        Section("ROS 2 static transforms",
                '<p class="small">ROS 2 Humble or newer; also written to <code>static_transforms.sh</code>. '
                "Alternatively load <code>robot_calibrated.urdf</code> in robot_state_publisher (not both).</p>",
                f"<pre>{_e(cmds)}</pre>"),
    ]
    return render_page(title, sections, subtitle=subtitle, warnings=result.warnings, footer="Written by graphcal calibrate.")
