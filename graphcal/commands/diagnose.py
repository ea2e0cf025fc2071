"""``graphcal diagnose DATASET --out DIR``: run the diagnosis and write its files atomically.

Files: ``diagnosis.json`` (format ``graphcal-diagnosis/1``, docs/diagnosis.md) and ``report.html``
(findings, evidence, held-out gain, and per finding the residuals against the covariate that reveals
its cause, before and after). ``DIR`` must be new, empty, or a previous diagnosis (replaced only
once the new one is complete); anything else is refused, so nothing the user made is overwritten.
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

from graphcal.io.atomic import atomic_directory, atomic_write_text, check_output_folder, previous_output_files
from graphcal.diagnosis.diagnose import Diagnosis, diagnose

__all__ = ["run", "write_diagnosis", "summary_text", "DIAGNOSIS_FILES"]

DIAGNOSIS_FILES = ("diagnosis.json", "report.html")


def _check_out(out: Path) -> None:
    """The output-folder policy of graphcal.io.atomic.check_output_folder, for a diagnosis."""
    check_output_folder(out, lambda f: previous_output_files(f, "diagnosis.json", DIAGNOSIS_FILES, "graphcal-diagnosis/"),
                        what="graphcal diagnosis")


def _fmt(v) -> str:
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, float):
        return f"{v:.4g}"
    return html.escape(str(v))


def report_html(diag: Diagnosis, doc: dict, title: str) -> str:
    from graphcal.report.plots import figure_png
    from graphcal.diagnosis.plots import diagnosis_figures

    e = html.escape
    out = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">', f"<title>{e(title)}</title>",
           "<style>body{font-family:sans-serif;max-width:1000px;margin:2em auto;line-height:1.4}"
           "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:3px 8px;font-size:90%}"
           ".warn{background:#fff3cd;padding:.5em 1em}img{max-width:100%}</style></head><body>",
           f"<h1>{e(title)}</h1>"]
    n, f = doc["nominal"], doc["final"]
    out.append("<h2>Residuals</h2><table><tr><th>model</th><th>theta RMS [deg]</th><th>e_d RMS [mm]</th>"
               "<th>chi2 / dof</th></tr>")
    for name, m in (("nominal", n), ("with the findings", f)):
        out.append(f"<tr><td>{name}</td><td>{_fmt(m['normal_rms_deg'])}</td><td>{_fmt(m['distance_rms_mm'])}</td>"
                   f"<td>{_fmt(m['chi2_per_dof'])}</td></tr>")
    out.append("</table>")
    out.append("<h2>Findings</h2>")
    if not doc["findings"]:
        out.append("<p>None: no catalogued effect is significant; the nominal model is adequate.</p>")
    else:
        out.append("<table><tr><th>cause</th><th>where</th><th>parameters (± 1σ)</th><th>evidence</th>"
                   "<th>held-out RMS before → after</th></tr>")
        for fd in doc["findings"]:
            params = "<br>".join(f"{e(k)} = {_fmt(v)} ± {_fmt(fd['sigma'].get(k, float('nan')))}"
                                 for k, v in fd["parameters"].items())
            ev = fd["evidence"]
            g = fd["gain"]
            gain = f"{_fmt(g['heldout_rms_before'])} → {_fmt(g['heldout_rms_after'])} ({_fmt(g['relative'])})" if g else "-"
            out.append(f"<tr><td><b>{e(fd['cause'])}</b></td><td>{_fmt(fd['where'])}</td><td>{params}</td>"
                       f"<td>LR {_fmt(ev['statistic'])} on {ev['dof']} dof, p(family) = {_fmt(ev['p_family'])}, "
                       f"ΔBIC {_fmt(ev['delta_bic'])}</td><td>{gain}</td></tr>")
        out.append("</table>")
    if doc["unexplained_structure"]:
        out.append('<p class="warn">The final residuals still fail their chi-square test: structure remains that no '
                   "catalogued effect explains.</p>")
    if doc["notes"]:
        out.append("<h3>Notes</h3><ul>" + "".join(f"<li>{e(x)}</li>" for x in doc["notes"]) + "</ul>")
    out.append("<h2>Residuals against the revealing covariate, before and after</h2>")
    for caption, fig in diagnosis_figures(diag):
        data = base64.b64encode(figure_png(fig)).decode("ascii")
        out.append(f'<figure><img src="data:image/png;base64,{data}" alt="{e(caption)}"><figcaption>{e(caption)}'
                   "</figcaption></figure>")
    if doc["screening"]:
        out.append("<h2>Screening (score tests), first round</h2><table><tr><th>candidate</th><th>statistic</th>"
                   "<th>dof</th><th>log10 p (family)</th></tr>")
        for row in doc["screening"][0]:
            out.append(f"<tr><td>{e(row['candidate'])}</td><td>{_fmt(row['statistic'])}</td><td>{row['dof']}</td>"
                       f"<td>{_fmt(row['log10_p_family'])}</td></tr>")
        out.append("</table>")
    out.append('<p style="font-size:80%">Written by graphcal diagnose. Method: docs/diagnosis.md.</p></body></html>')
    return "\n".join(out)


def summary_text(doc: dict, out: Path | None = None) -> str:
    n = doc["nominal"]
    lines = [f"nominal model: theta RMS {n['normal_rms_deg']:.4f} deg, e_d RMS {n['distance_rms_mm']:.3f} mm, "
             f"chi2/dof {n['chi2_per_dof']:.2f}"]
    if not doc["findings"]:
        lines.append("findings: none (no catalogued effect is significant)")
    for fd in doc["findings"]:
        where = ", ".join(f"{k}={v}" for k, v in fd["where"].items())
        params = ", ".join(f"{k}={v:.4g}±{fd['sigma'].get(k, float('nan')):.2g}" for k, v in fd["parameters"].items()
                           if isinstance(v, float))
        g = fd["gain"]
        gain = f"; held-out RMS {g['heldout_rms_before']:.3g} -> {g['heldout_rms_after']:.3g}" if g else ""
        lines.append(f"found {fd['cause']}" + (f" ({where})" if where else "") + (f": {params}" if params else "")
                     + f"; LR {fd['evidence']['statistic']:.1f} on {fd['evidence']['dof']} dof{gain}")
    if doc["unexplained_structure"]:
        lines.append("structure remains that no catalogued effect explains")
    if out is not None:
        lines.append(f"wrote {out / 'diagnosis.json'} and {out / 'report.html'}")
    return "\n".join(lines)


def write_diagnosis(diag: Diagnosis, out_dir, *, title: str | None = None) -> dict:
    """Write diagnosis.json and report.html into ``out_dir`` as one atomic set; returns the JSON."""
    out = Path(out_dir)
    _check_out(out)
    doc = diag.to_json()
    text = json.dumps(doc, indent=1, default=float)
    page = report_html(diag, doc, title or f"graphcal diagnosis of {diag.model.ds.root}")
    with atomic_directory(out, overwrite=True) as tmp:
        atomic_write_text(tmp / "diagnosis.json", text)
        atomic_write_text(tmp / "report.html", page)
        _check_out(out)
    return doc


def run(dataset, out_dir, *, progress: bool = True) -> str:
    """``graphcal diagnose``: diagnose ``dataset`` and write ``out_dir``; returns the summary."""
    out = Path(out_dir)
    _check_out(out)  # refuse early, before the work
    diag = diagnose(dataset, progress=progress)
    doc = write_diagnosis(diag, out)
    return summary_text(doc, out)
