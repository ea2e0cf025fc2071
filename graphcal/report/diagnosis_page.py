"""The ``report.html`` of ``graphcal diagnose``: findings, evidence, held-out gain, and per finding the
residuals against the covariate that reveals its cause, before and after (one page of
:mod:`graphcal.report.page`)."""

from __future__ import annotations

from graphcal.report.page import Section, esc, figure, render_page

__all__ = ["diagnosis_html"]


def _fmt(v) -> str:
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(esc(v))


def _verdict(doc: dict) -> list[str]:
    """Warnings first, then whose extrinsic is the answer and where structure remains."""
    out = [f'<div class="warn">{esc(w)}</div>' for w in doc.get("warnings", [])]
    answer = doc.get("answer", "nominal")
    text = {"extended": "the extended model fits at physical noise: its extrinsic (below) is the answer.",
            "nominal": "no cause is named: the nominal calibration (graphcal calibrate) is the answer.",
            "neither": "structure remains: neither model fits at physical noise; the extended model's extrinsic is "
                       "not the answer."}[answer]
    out.append(f"<p><b>Answer:</b> {esc(text)}</p>")
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
           '<th class="l">evidence</th><th>held-out RMS before → after</th></tr>']
    for fd in doc["findings"]:
        params = "<br>".join(f"{esc(k)} = {_fmt(v)} ± {_fmt(fd['sigma'].get(k, float('nan')))}"
                             for k, v in fd["parameters"].items())
        ev = fd["evidence"]
        g = fd["gain"]
        gain = (f"{_fmt(g['heldout_rms_before'])} → {_fmt(g['heldout_rms_after'])} ({_fmt(g['relative'])}); "
                f"paired test p = {_fmt(g.get('p_value', float('nan')))}") if g else "-"
        tentative = "" if fd.get("supported", True) else " (tentative)"
        out.append(f'<tr><td class="l"><b>{esc(fd["cause"])}</b>{tentative}</td><td class="l">{_fmt(fd["where"])}</td>'
                   f'<td class="l">{params}</td><td class="l">LR {_fmt(ev["statistic"])} on {ev["dof"]} dof, '
                   f"p(family) = {_fmt(ev['p_family'])}, ΔBIC {_fmt(ev['delta_bic'])}</td><td>{gain}</td></tr>")
    out.append("</table>")
    return out


def diagnosis_html(diag, doc: dict, title: str) -> str:
    """The page of a :class:`~graphcal.diagnosis.diagnose.Diagnosis` and its JSON document ``doc``
    (:meth:`Diagnosis.to_json`; RMS in deg and mm, chi-square per degree of freedom)."""
    from graphcal.diagnosis.plots import diagnosis_figures

    n, f = doc["nominal"], doc["final"]
    res = ['<table><tr><th class="l">model</th><th>theta RMS [deg]</th><th>e_d RMS [mm]</th><th>chi2 / dof</th></tr>']
    for name, m in (("nominal", n), ("with the findings", f)):
        res.append(f'<tr><td class="l">{name}</td><td>{_fmt(m["normal_rms_deg"])}</td><td>{_fmt(m["distance_rms_mm"])}</td>'
                   f"<td>{_fmt(m['chi2_per_dof'])}</td></tr>")
    res.append("</table>")
    sections = [
        Section("Verdict", *_verdict(doc)),
        Section("Residuals", *res),
        Section("Findings", *_findings(doc)),
        Section("Residuals against the revealing covariate, before and after; where structure remains",
                *(figure(fig, caption) for caption, fig in diagnosis_figures(diag))),
    ]
    if doc["screening"]:
        rows = ['<table><tr><th class="l">candidate</th><th>statistic</th><th>dof</th><th>log10 p (family)</th></tr>']
        for r in doc["screening"][0]:
            rows.append(f'<tr><td class="l">{esc(r["candidate"])}</td><td>{_fmt(r["statistic"])}</td><td>{r["dof"]}</td>'
                        f"<td>{_fmt(r['log10_p_family'])}</td></tr>")
        rows.append("</table>")
        sections.append(Section("Screening (score tests), first round", *rows))
    return render_page(title, sections, footer="Written by graphcal diagnose. Method: docs/diagnosis.md.")
