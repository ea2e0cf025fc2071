"""The fleet page (``fleet.html``) and table (``fleet.csv``) of ``graphcal batch``: every robot's
extrinsics and leg parameters with 1-sigma, the verdicts and warnings of its outputs, the diagnosis'
findings, and the robots whose values lie outside the fleet's spread with their leave-one-out t statistic
(:mod:`graphcal.batch.fleet`). One template and style sheet: :mod:`graphcal.report.page`."""

from __future__ import annotations

import csv
import io
import math

from graphcal.report.page import Markup, Section, esc, num, render_page, row, table

__all__ = ["fleet_html", "fleet_csv"]


def _keys(table_: dict) -> list[tuple[str, str]]:
    keys = sorted({k for vals in table_.values() for k in vals})
    order = {"x": 0, "y": 1, "z": 2, "rot x": 3, "rot y": 4, "rot z": 5}
    return sorted(keys, key=lambda k: (k[0].startswith("leg "), k[0], order.get(k[1], 9), k[1]))


def fleet_csv(robots, table_: dict, alpha: float) -> str:
    """One row per robot and degree of freedom: robot, group, dof, value, sigma, unit, t, p, flagged."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    buf.write("# graphcal fleet table: translation along body axes (mm), rotation vector about body axes relative "
              "to the fleet's medoid (deg), leg angles (deg) and lengths (mm); sigma 1-sigma in the same unit; "
              f"t leave-one-out Student t against the other robots, p its two-sided p-value (docs/batch.md), "
              f"flagged when p < {alpha:g}\n")
    w.writerow(["robot", "group", "dof", "value", "sigma", "unit", "t", "p", "flagged"])
    for r in robots:
        for key in _keys({r.name: table_.get(r.name, {})}):
            v, t, p = table_[r.name][key]
            w.writerow([r.name, v.group, v.name, f"{v.value:.6g}", f"{v.sigma:.6g}", v.unit,
                        "" if math.isnan(t) else f"{t:.3f}", "" if math.isnan(p) else f"{p:.3g}",
                        int(not math.isnan(p) and p < alpha)])
    return buf.getvalue()


def _value_cell(v, t: float, p: float, alpha: float) -> str:
    text = f"{num(v.value, '.2f')} ± {num(v.sigma, '.2g')}"
    if not math.isnan(p) and p < alpha:
        return f'<span class="flag">{text}<br>t {num(t, "+.1f")}</span>'
    return text


def _group_table(robots, table_: dict, group: str, keys: list, alpha: float) -> Markup:
    units = {}
    for vals in table_.values():
        for k, (v, _, _) in vals.items():
            units.setdefault(k, v.unit)
    rows = [row(["robot"] + [f"{esc(k[1])} ({esc(units[k])})" for k in keys], header=True)]
    for r in robots:
        vals = table_.get(r.name, {})
        if not any(k in vals for k in keys):
            continue
        cells = [str(esc(r.name))]
        for k in keys:
            cells.append(_value_cell(*vals[k], alpha) if k in vals else "–")
        rows.append(row(cells))
    return table(rows)


def _notes_list(robots) -> Markup:
    items = []
    for r in robots:
        lines = [f"finding: {f}" for f in r.findings] + [f"warning: {w}" for w in r.warnings] + list(r.notes)
        if not lines:
            items.append(f"<li><strong>{esc(r.name)}</strong>: <span class=\"ok\">no warnings or findings</span></li>")
            continue
        inner = "".join(f"<li>{esc(x)}</li>" for x in lines)
        items.append(f"<li><strong>{esc(r.name)}</strong> ({len(r.findings)} finding(s), {len(r.warnings)} "
                     f"warning(s))<ul>{inner}</ul></li>")
    return Markup('<ul class="facts">' + "".join(items) + "</ul>")


def fleet_html(robots, table_: dict, flags, *, title: str, alpha: float | None = None,
               unfinished: list[tuple[str, str, str]] = ()) -> str:
    """The page: flagged robots first, then one table per sensor and leg, then each robot's warnings
    and findings, then the tasks that did not finish (``unfinished``: (dataset, status, error)).
    ``table_`` and ``flags`` from :func:`graphcal.batch.fleet.fleet_flags`."""
    from graphcal.batch.fleet import ALPHA, MIN_OTHERS

    alpha = ALPHA if alpha is None else alpha
    stat = (f"Statistic: leave-one-out Student t per degree of freedom, t = (value − mean of the m other robots) / "
            f"(max(their standard deviation, the robot's own σ) · √(1 + 1/m)), with m − 1 degrees of freedom; "
            f"flagged when its two-sided p < {alpha:g} and m ≥ {MIN_OTHERS}. Translations along the body axes (mm); "
            "rotations as rotation vectors about the body axes relative to the fleet's medoid rotation (deg); "
            "leg angles (deg) and lengths (mm), as changes from the nominal URDF. Cells: value ± 1σ.")
    if flags:
        frows = [row(["robot", "group", "DoF", "value", "fleet mean", "spread", "t", "p", "others"], header=True)]
        frows += [row([str(esc(f.robot)), str(esc(f.group)), str(esc(f.name)), f"{num(f.value, '.3f')} {esc(f.unit)}",
                       f"{num(f.mean, '.3f')} {esc(f.unit)}", f"{num(f.spread, '.3g')} {esc(f.unit)}",
                       f'<span class="flag">{num(f.t, "+.1f")}</span>', num(f.p, ".1e"), str(f.n_others)])
                  for f in flags]
        flagged = table(frows)
    elif len(robots) < MIN_OTHERS + 1:  # no robot has MIN_OTHERS others to be judged against
        flagged = Markup(f'<p class="warn">Not tested: the leave-one-out test needs at least {MIN_OTHERS + 1} '
                         f'robots; this batch has {len(robots)}.</p>')
    else:
        flagged = Markup('<p class="ok">No robot lies outside the fleet\'s spread.</p>')
    sections = [Section("Robots outside the fleet's spread", flagged, Markup(f'<p class="small">{esc(stat)}</p>'))]
    keys = _keys(table_)
    for group in sorted({k[0] for k in keys}, key=lambda g: (g.startswith("leg "), g)):
        gk = [k for k in keys if k[0] == group]
        heading = f"Leg {group[4:]}" if group.startswith("leg ") else f"Sensor {group}: T_body_sensor"
        sections.append(Section(heading, _group_table(robots, table_, group, gk, alpha)))
    sections.append(Section("Verdicts, warnings and findings", _notes_list(robots)))
    if unfinished:
        urows = [row(["dataset", "status", "error"], header=True)]
        urows += [row([str(esc(d)), str(esc(st)), f'<span class="l">{esc(err)}</span>'], first_left=True)
                  for d, st, err in unfinished]
        sections.append(Section("Datasets without a result in this batch", table(urows)))
    names = ", ".join(sorted({f.robot for f in flags}))
    warn = [f"outside the fleet's spread: {names}"] if flags else []
    warn += [f"{len(unfinished)} dataset(s) without a result (failed or worker died): see the end"] if unfinished else []
    return render_page(title, sections, subtitle=f"{len(robots)} robot(s); {len(flags)} flag(s)",
                       warnings=warn,
                       footer="graphcal batch (docs/batch.md)")
