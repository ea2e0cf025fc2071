"""The page of ``graphcal study`` (``report.html``): per sensor the NEES verdict and, per body axis,
the RMS error, the mean reported sigma and the mean (error/sigma)^2, with the plots. One template
and style sheet: :mod:`graphcal.report.page`."""

from __future__ import annotations

from graphcal.report.page import Section, esc, figure_png_html, num, render_page, row, table

__all__ = ["study_html"]


def study_html(doc: dict, pngs: dict[str, bytes], *, title: str) -> str:
    """``doc`` the study.yaml document (graphcal.commands.study), ``pngs`` its plots by file name."""
    sections = []
    for name, s in doc["sensors"].items():
        lo, hi = s["nees_interval_95"]
        lo1, hi1 = s["z2_interval_95"]
        rows = [row(["axis", "unit", "RMS error", "mean error", "mean sigma", "mean (error/sigma)²"], header=True)]
        for a, e in s["per_axis"].items():
            z = num(e["mean_z2"], ".2f")
            if not lo1 <= e["mean_z2"] <= hi1:
                z = f'<span class="flag">{z}</span>'
            rows.append(row([str(esc(a)), e["unit"], num(e["rms_error"], ".4f"), num(e["mean_error"], ".4f"),
                             num(e["mean_sigma"], ".4f"), z]))
        facts = (f'<ul class="facts"><li>{s["runs"]} runs; mean NEES {num(s["nees_mean"], ".2f")} (6 dof; 95 % '
                 f'interval for an honest mean [{num(lo, ".2f")}, {num(hi, ".2f")}]): <strong>{esc(s["nees_verdict"])}'
                 f'</strong></li><li>mean (error/sigma)² per body axis: honest 1, 95 % interval '
                 f'[{num(lo1, ".2f")}, {num(hi1, ".2f")}] (outside in red)</li></ul>')
        parts = [facts, table(rows)]
        for key, cap in ((f"nees_{name}.png", "NEES of each run against chi2(6)"),
                         (f"errors_{name}.png", "error of each run (blue) and ±2 reported sigma (grey), body axes")):
            if key in pngs:
                parts.append(figure_png_html(pngs[key], cap))
        sections.append(Section(f"Sensor {name}", *parts))
    st = doc["setup"]
    sub = (f"{st['robot']}, program {st['program']}, seeds {st['seeds'][0]}..{st['seeds'][1]}, "
           f"{doc['runs_done']} runs done, {len(doc['runs_failed'])} failed; {doc['wall_s']:.0f} s wall on "
           f"{doc['executor']['kind']} ({doc['executor']['workers']} workers); calibrate "
           f"{doc['calibrate_s_mean']:.2f} s per run")
    warn = [f"seed {f['seed']}: {f['status']}: {f['error']}" for f in doc["runs_failed"]]
    return render_page(title, sections, subtitle=sub, warnings=warn, footer="graphcal study (docs/batch.md)")
