"""The ``report.html`` of ``graphcal diagnose``: findings, evidence, held-out gain, and per finding the
residuals against the covariate that reveals its cause, before and after; the calibration of the
extended model with why it differs from calibrate's; the screening with its threshold (one page of
:mod:`graphcal.report.page`)."""

from __future__ import annotations

import math

import numpy as np

from graphcal.report.page import Section, esc, figure, render_page

__all__ = ["diagnosis_html", "where_text", "parameter_text", "HELDOUT_UNITS"]

#: what the held-out RMS is measured in (heldout.py: whitened prediction errors)
HELDOUT_UNITS = "whitened: in sigmas of the held-out measurements"


def _fmt(v) -> str:
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(esc(v))


def where_text(where: dict) -> str:
    """A finding's location as words (``joint rm_tibia_joint, leg rm_foot``; "—" for none), plain text."""
    if not where:
        return "—"
    return ", ".join(f"{k} {', '.join(map(str, v)) if isinstance(v, (list, tuple)) else v}" for k, v in where.items())


def _scaled(v, f: float):
    if isinstance(v, (list, tuple)):
        return [_scaled(x, f) for x in v]
    return f * v if isinstance(v, (int, float)) else v


def _num(v, spec: str) -> str:
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_num(x, spec) for x in v) + "]"
    if isinstance(v, (int, float)) and math.isfinite(v):
        return format(v, spec)
    return str(v)


def parameter_text(name: str, value, sigma=None) -> str:
    """``name = value ± sigma unit`` (plain text): SI values (``_rad``, ``_m``) also in deg and mm,
    the name's unit suffix changed with them (``offset_deg = 2.17 ± 0.03 (0.0379 rad)``)."""
    base, _, unit = name.rpartition("_")
    conv = {"rad": ("deg", 180.0 / math.pi), "m": ("mm", 1000.0)}.get(unit)
    sig = "" if sigma is None else f" ± {_num(sigma, '.2g')}"
    if conv is None or not base:
        return f"{name} = {_num(value, '.4g')}{sig}"
    new_unit, f = conv
    sig_new = "" if sigma is None else f" ± {_num(_scaled(sigma, f), '.2g')}"
    return f"{base}_{new_unit} = {_num(_scaled(value, f), '.4g')}{sig_new} {new_unit} ({_num(value, '.4g')} {unit})"


def _verdict(doc: dict) -> list[str]:
    """Warnings first, then whose extrinsic is the answer and where structure remains."""
    out = [f'<div class="warn">{esc(w)}</div>' for w in doc.get("warnings", [])]
    answer = doc.get("answer", "nominal")
    text = {"extended": "the extended model fits at physical noise: its extrinsic (below) is the answer.",
            "nominal": "no cause is named: the nominal calibration (graphcal calibrate) is the answer.",
            "corrected": "the data hold bookkeeping errors (below); corrected, the model fits at physical noise: the "
                         "extrinsic below, fitted to the corrected measurements, is the answer (not graphcal calibrate's "
                         "on the files as given).",
            "neither": "structure remains: neither model fits at physical noise; the extended model's extrinsic is "
                       "not the answer."}[answer]
    out.append(f"<p><b>Answer:</b> {esc(text)}</p>")
    if doc.get("corrections"):
        out.append(f'<div class="warn">{len(doc["corrections"])} bookkeeping error(s) found in the data and corrected '
                   "before the causes were looked for (below): the models were fitted to the corrected measurements; "
                   "the files were not changed.</div>")
    out.extend(_adequacy_line(doc.get("adequacy") or {}))
    groups = doc.get("physical_noise_tests", {}).get("final", [])
    if groups:
        out.append('<table><tr><th class="l">group</th><th>chi2 / dof at physical noise</th><th>p</th>'
                   '<th class="l">correlates with</th></tr>')
        for g in groups:
            cor = f"{esc(g['regressor'])} (r = {g['correlation']:+.2f}, p = {_fmt(g['regressor_p'])})" if g["regressor"] else "-"
            flag = " <b>structure remains</b>" if g["structure"] else ""
            out.append(f'<tr><td class="l">{esc(g["group"])}{flag}</td><td>{_fmt(g["chi2_per_dof"])}</td>'
                       f'<td>{_fmt(g["p_value"])}</td><td class="l">{cor}</td></tr>')
        out.append("</table>")
    return out


def _adequacy_line(a: dict) -> list[str]:
    """The final model's adequacy verdict at physical noise (diagnosis.json ``adequacy``)."""
    if not a:
        return []
    if a.get("verdict") == "not judged":
        return [f"<p><b>Final model:</b> not judged ({esc(a.get('reason', ''))}).</p>"]
    text = (f"{a['verdict']} (statistic {_fmt(a['statistic'])} against {esc(a['reference'])}, p = {_fmt(a['p_value'])}; "
            f"worst group {esc(a['worst_group'])})")
    from graphcal.calibration.adequacy import ALPHA, RATIO_LIMIT

    if a["verdict"] == "fits" and float(a.get("p_value", 1.0)) < ALPHA:
        text += (f"; the p-value is small but every group's learned σ is within {RATIO_LIMIT:g}× its physical one, "
                 "which calibrate's rule calls a fit")
    model = str(a.get("model", "final (extended)"))
    again = model.split(", ", 1)[1] if ", " in model else ""  # judged again: with what noise
    how = f" ({esc(again)})" if again else ""
    return [f"<p><b>Final model, judged as calibrate judges it{how}:</b> {text}.</p>"]


def _corrections(doc: dict) -> list[str]:
    """The bookkeeping errors found and corrected (diagnosis.json ``corrections``)."""
    out = ['<table><tr><th class="l">cause</th><th class="l">where</th><th class="l">the data hold → corrected</th>'
           '<th class="l">evidence</th><th>confidence (χ² margin to the next best)</th><th class="l">note</th></tr>']
    for c in doc["corrections"]:
        corr = "<br>".join(f"{esc(k)} = {_fmt(v)}" for k, v in c["corrected"].items()) or "-"
        alt = f"<br>cannot be told from: {esc(', '.join(c['alternatives']))}" if c["alternatives"] else ""
        out.append(f'<tr><td class="l"><b>{esc(c["cause"])}</b></td><td class="l">{esc(where_text(c["where"]))}</td>'
                   f'<td class="l">{corr}</td><td class="l">χ² drop {_fmt(c["statistic"])} on {c["dof"]} dof, '
                   f'p = {_fmt(c["p_value"])}</td><td>{_fmt(c["confidence"])}{alt}</td><td class="l">{esc(c["note"])}</td></tr>')
    out.append("</table>")
    out.append('<p class="small">Stations numbered as in stations.csv; values in SI (m, rad) as in diagnosis.json. '
               "Method: docs/diagnosis.md, \"Bookkeeping errors\".</p>")
    return out


def _findings(doc: dict) -> list[str]:
    out = _findings_table(doc)
    if doc["unexplained_structure"]:
        out.append('<div class="warn">Structure remains that no supported catalogued cause explains (a group fails '
                   "at physical noise, a finding is tentative, or the planes fail their chi-square test).</div>")
    if doc["notes"]:
        out.append("<h3>Notes</h3><ul>" + "".join(f"<li>{esc(x)}</li>" for x in doc["notes"]) + "</ul>")
    return out


def _findings_table(doc: dict) -> list[str]:
    if not doc["findings"]:
        return ["<p>None: no catalogued effect is significant; the nominal model is adequate.</p>"]
    out = ['<table><tr><th class="l">cause</th><th class="l">where</th><th class="l">parameters (± 1σ)</th>'
           '<th class="l">evidence</th><th>held-out RMS before → after [σ] (after / before)</th></tr>']
    for fd in doc["findings"]:
        params = "<br>".join(esc(parameter_text(k, v, fd["sigma"].get(k, float("nan"))))
                             for k, v in fd["parameters"].items())
        ev = fd["evidence"]
        g = fd["gain"]
        gain = (f"{_fmt(g['heldout_rms_before'])} → {_fmt(g['heldout_rms_after'])} ({_fmt(g['relative'])}); "
                f"paired test p = {_fmt(g.get('p_value', float('nan')))}") if g else "-"
        tentative = "" if fd.get("supported", True) else " (tentative)"
        out.append(f'<tr><td class="l"><b>{esc(fd["cause"])}</b>{tentative}</td><td class="l">{esc(where_text(fd["where"]))}</td>'
                   f'<td class="l">{params}</td><td class="l">LR {_fmt(ev["statistic"])} on {ev["dof"]} dof, '
                   f"p(family) = {_fmt(ev['p_family'])}, ΔBIC {_fmt(ev['delta_bic'])}</td><td>{gain}</td></tr>")
    out.append("</table>")
    out.append(f'<p class="small">Parameters in SI as in diagnosis.json (rad, m), with deg and mm. Held-out RMS: '
               f"{HELDOUT_UNITS}, predicted by a model fitted without them (two folds by station), before and "
               "after the finding is modelled; below 1 in the last column: it predicts unseen data better.</p>")
    return out


def _extended_calibration(doc: dict) -> list[str]:
    ext = doc.get("extended_calibration") or {}
    sensors = ext.get("sensors") or {}
    if not sensors:
        return []
    out = ['<table><tr><th class="l">sensor</th><th>x [mm]</th><th>y [mm]</th><th>z [mm]</th><th>roll [deg]</th>'
           "<th>pitch [deg]</th><th>yaw [deg]</th><th>1-σ rot about body x/y/z [deg]</th>"
           "<th>1-σ along body x/y/z [mm]</th></tr>"]
    for name, s in sensors.items():
        pose, sig = s.get("T_body_sensor", {}), s.get("sigma", {})
        xyz = [1000.0 * v for v in pose.get("xyz", [])]
        cells = [f"{v:.2f}" for v in xyz] + [f"{v:.3f}" for v in pose.get("rpy_deg", [])]
        out.append(f'<tr><td class="l"><code>{esc(name)}</code></td>' + "".join(f"<td>{c}</td>" for c in cells)
                   + f"<td>{' / '.join(f'{v:.2g}' for v in sig.get('rot_deg', []))}</td>"
                   + f"<td>{' / '.join(f'{v:.2g}' for v in sig.get('xyz_mm', []))}</td></tr>")
    out.append("</table>")
    if ext.get("note"):
        out.append(f'<div class="warn">{esc(ext["note"])}</div>')
    return out


def _screening(doc: dict) -> list[str]:
    thresholds = doc.get("screening_threshold_log10_p") or []
    t = thresholds[0] if thresholds else None
    rows = ['<table><tr><th class="l">candidate</th><th>statistic</th><th>dof</th><th>log10 p (family)</th>'
            + ("<th>below the threshold</th>" if t is not None else "") + "</tr>"]
    for r in doc["screening"][0]:
        below = "" if t is None else f"<td>{'yes' if r['log10_p_family'] < t else 'no'}</td>"
        rows.append(f'<tr><td class="l">{esc(r["candidate"])}</td><td>{_fmt(r["statistic"])}</td><td>{r["dof"]}</td>'
                    f"<td>{_fmt(r['log10_p_family'])}</td>{below}</tr>")
    rows.append("</table>")
    if t is not None:
        rows.append(f'<p class="small">The eight strongest candidates of the first round (score tests: chi-square '
                    f"statistic on dof, p multiplied by the locations tested for that cause). Threshold: log10 p "
                    f"(family) &lt; {t:.2f}, i.e. alpha = 0.001 divided by the causes tested; the strongest candidate "
                    "below it is fitted, and named when its likelihood-ratio test agrees and its size reaches the "
                    "catalogue's minimum (docs/diagnosis.md).</p>")
    return rows


def diagnosis_scene_of(diag, doc: dict):
    """The 3-D scene of the diagnosis model (its body poses and sensor poses, the clouds of its
    dataset) with each finding's place marked; None when it cannot be drawn."""
    from graphcal.geometry import from_gtsam_pose
    from graphcal.report.scene_3d import PosedModel, PosedSensor, diagnosis_scene

    problem, values, ds = diag.problem, diag.values, diag.model.ds
    try:
        poses = {int(st): from_gtsam_pose(values.atPose3(k)) for st, k in problem.station_keys.items()}
        sensors = {name: PosedSensor(from_gtsam_pose(values.atPose3(k)), np.asarray(problem.sensor_priors[name][0]),
                                     np.full((6, 6), np.nan)) for name, k in problem.sensor_keys.items()}
    except (RuntimeError, KeyError, AttributeError):
        return None
    stations_of = {int(st.station): st.session for st in diag.model.data.stations}
    findings = [f for f in doc.get("findings", []) if isinstance(f, dict)]
    return diagnosis_scene(PosedModel(poses, sensors), ds if getattr(ds, "root", None) else None, diag.model.robot,
                           findings, stations_of)


def _scene_parts(scene) -> list:
    from graphcal.report.scene_view import scene_figure, scene_html

    collapse = "".join(
        f"<p>Ground points of <code>{esc(c.sensor)}</code> ({c.points} of {c.stations} stations): RMS height above "
        f"the floor {c.rms_prior_m * 1e3:.2f} mm with the CAD prior, {c.rms_calibrated_m * 1e3:.2f} mm with the "
        "diagnosis model's extrinsic.</p>" for c in scene.collapse)
    return [collapse, scene_html(scene),
            f'<p class="small">World frame, m. The finding\'s place, where it has one (its stations\' body frames, its '
            f"leg), in magenta. {esc(scene.note)}</p>",
            figure(scene_figure(scene), "The same scene, for printing.")]


def diagnosis_html(diag, doc: dict, title: str) -> str:
    """The page of a :class:`~graphcal.diagnosis.diagnose.Diagnosis` and its JSON document ``doc``
    (:meth:`Diagnosis.to_json`; RMS in deg and mm, chi-square per degree of freedom)."""
    from graphcal.report.diagnosis_plots import diagnosis_figures

    n, f = doc["nominal"], doc["final"]
    res = ['<table><tr><th class="l">model</th><th>theta RMS [deg]</th><th>e_d RMS [mm]</th><th>chi2 / dof</th></tr>']
    for name, m in (("nominal (before the corrections)", n), ("with the corrections and findings", f)):
        res.append(f'<tr><td class="l">{name}</td><td>{_fmt(m["normal_rms_deg"])}</td><td>{_fmt(m["distance_rms_mm"])}</td>'
                   f"<td>{_fmt(m['chi2_per_dof'])}</td></tr>")
    res.append("</table>")
    sections = [
        Section("Verdict", *_verdict(doc)),
        *([Section("Bookkeeping errors found and corrected", *_corrections(doc))] if doc.get("corrections") else []),
        Section("Residuals", *res),
        Section("Findings", *_findings(doc)),
        Section("Residuals against the revealing covariate, before and after; where structure remains",
                '<p class="small">θ and e_d here compare each measured plane with the one the model predicts from '
                "the legs alone (the kinematic body pose), not with the fitted one of the Residuals table: the fitted "
                "body poses absorb most of a discrepancy. Stations numbered as in stations.csv.</p>"
                if doc["findings"] else '<p class="small">Stations numbered as in stations.csv.</p>',
                *(figure(fig, caption) for caption, fig in diagnosis_figures(diag))),
    ]
    scene = diagnosis_scene_of(diag, doc)
    if scene is not None and scene.groups:
        sections.append(Section("3-D scene of the diagnosis model", *_scene_parts(scene)))
    ext = _extended_calibration(doc)
    if ext:
        sections.append(Section("Sensor poses of the diagnosis model (not calibrate's)", *ext))
    if doc["screening"]:
        sections.append(Section("Screening (score tests), first round", *_screening(doc)))
    return render_page(title, sections, footer="Written by graphcal diagnose. Method: docs/diagnosis.md.")
