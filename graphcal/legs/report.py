"""Outputs of ``graphcal identify-legs``: legs.yaml, robot_calibrated.urdf, report.html and figures.

* ``legs.yaml`` (format ``graphcal-legs/1``): the ``legs`` section with the schema of
  ``calibration.yaml`` -- ``legs: {<foot frame>: {<parameter>: {value: v, sigma: s}}}`` (SI units;
  only the parameters that were estimated; the held ones are listed under ``identifiability``) --
  plus ``mocap`` (the estimated ``T_body_mocap`` / ``T_body_vbase`` and marker positions),
  ``identifiability`` (per candidate parameter: status, free, combination), ``foot_error_mm``
  (RMSE before / after per foot), ``solver`` and ``warnings``.
* ``robot_calibrated.urdf``: the nominal URDF with the estimated leg parameters
  (:func:`graphcal.report.urdf.calibrated_urdf`).
* ``report.html`` + ``foot_errors_<foot>.png``: the foot-marker error before and after per sample
  (Yuan et al. Figs. 6 and 8: error norm per sample, and per body axis).

:func:`write_identification_outputs` writes the set atomically (a hidden sibling folder renamed
into place, :func:`graphcal.io.atomic.atomic_directory`); it replaces only an empty folder or the
outputs of a previous ``identify-legs``.
"""

from __future__ import annotations

import base64
import html
import math
from pathlib import Path

import numpy as np
import yaml

from graphcal.io.atomic import atomic_directory, atomic_write_bytes, atomic_write_text
from graphcal.io.atomic import check_output_folder as check_folder
from graphcal.io.atomic import previous_output_files
from graphcal.report.calibration_yaml import pose_to_dict

__all__ = ["LEGS_FILES", "legs_yaml_dict", "legs_yaml_text", "foot_error_figure", "identification_html",
           "write_identification_outputs"]

#: fixed output names (one PNG per foot is added: foot_errors_<foot>.png)
LEGS_FILES = {"legs": "legs.yaml", "urdf": "robot_calibrated.urdf", "report": "report.html"}

#: legs.yaml is not a calibration.yaml (no sensors, residuals or outliers): its own format id.
#: (Before 2026-11-21 it said graphcal-calibration/1 and failed that format's reader.)
LEGS_FORMAT = "graphcal-legs/1"


def _f(x) -> float:
    return float(x)


def _unit(name: str) -> tuple[float, str]:
    """(factor SI -> report unit, unit) of a parameter name."""
    if name.endswith("_rad") or name.split(".")[-1] in ("rx", "ry", "rz"):
        return 180.0 / math.pi, "deg"
    return 1000.0, "mm"


# ----------------------------------------------------------------------------- YAML
def legs_yaml_dict(result, *, dataset: str | None = None, output_files=None) -> dict:
    """The ``legs.yaml`` document (plain Python values)."""
    legs = {}
    for foot, params in result.legs.items():
        legs[str(foot)] = {p.name: {"value": _f(p.value), "sigma": _f(p.sigma)} for p in params if p.free}
    cov = np.asarray(result.T_body_mocap_covariance, dtype=float)
    s = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    pose = pose_to_dict(result.T_body_mocap)
    pose["sigma"] = {"rot_deg": [float(np.degrees(v)) for v in s[:3]], "xyz_mm": [float(1e3 * v) for v in s[3:]],
                     "axes": result.pose_name.split("_")[-1] + " frame (right perturbation)"}
    markers = {}
    for tr in result.residuals:
        name = tr.marker
        pos = result.marker_positions[name]
        entry = {"foot": tr.foot, "xyz": [float(v) for v in pos]}
        if name in result.markers:
            entry["sigma_mm"] = [float(1e3 * p.sigma) for p in result.markers[name]]
        else:
            entry["known"] = True
        markers[name] = entry
    ident = {}
    for p in result.identifiability.parameters:
        e = {"status": p.status, "free": bool(p.free)}
        if p.combination:
            e["combination"] = {n: float(c) for n, c in p.combination}
        ident[p.name] = e
    r = result.identifiability
    errs = {}
    for foot in result.legs:
        b, a = result.rmse_mm(foot)
        rs = [x for x in result.residuals if x.foot == foot]
        e = {"rmse_before": float(b), "rmse_after": float(a), "samples": int(sum(len(x.time) for x in rs))}
        nom = [x.rmse_nominal_mm for x in rs if x.rmse_nominal_mm is not None]
        if len(nom) == len(rs) and rs:
            allnom = np.concatenate([x.nominal for x in rs])
            e["rmse_nominal"] = float(1e3 * np.sqrt(np.mean(np.sum(allnom**2, axis=1))))
        errs[str(foot)] = e
    doc = {
        "format": LEGS_FORMAT,
        "dataset": str(dataset if dataset is not None else result.source),
        "base_frame": str(result.base_frame),
        "legs": legs,
        "mocap": {"frame": result.frame, result.pose_name: pose, "markers": markers},
        "identifiability": {
            "tolerances": {"rtol": float(r.rtol), "s_min": float(r.s_min), "f_identifiable": float(r.f_identifiable),
                           "threshold": float(r.threshold), "rank": int(r.rank)},
            "parameters": ident,
        },
        "foot_error_mm": errs,
        "solver": {"kind": "levenberg-marquardt", "iterations": int(result.iterations), "converged": bool(result.converged),
                   "sigma0": float(result.sigma0), "dof": int(result.dof)},
        "warnings": [str(w) for w in result.warnings],
    }
    if output_files is not None:
        doc["output_files"] = list(output_files)
    return doc


def legs_yaml_text(result, *, dataset: str | None = None, output_files=None) -> str:
    """``legs.yaml`` text with a leading comment line."""
    doc = legs_yaml_dict(result, dataset=dataset, output_files=output_files)
    ds = " ".join(str(doc["dataset"]).split())
    head = (f"# graphcal leg identification ({LEGS_FORMAT}): leg kinematic parameters (SI, change from the nominal URDF) "
            f"and their 1-sigma, written by graphcal identify-legs from dataset {ds}\n")
    return head + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, allow_unicode=True, width=200)


# ----------------------------------------------------------------------------- figures
def foot_error_figure(result, foot: str):
    """Figure of one foot's marker errors before / after (Yuan Figs. 6 and 8): the error norm per
    sample, then the error along body x, y, z per sample (mm)."""
    from matplotlib.figure import Figure

    rs = [r for r in result.residuals if r.foot == foot]
    fig = Figure(figsize=(9, 8), dpi=90)
    axs = fig.subplots(4, 1, sharex=True)
    off = 0
    for r in rs:
        idx = off + np.arange(len(r.time))
        off += len(r.time)
        eb, ea = 1e3 * r.before, 1e3 * r.after
        axs[0].plot(idx, np.linalg.norm(eb, axis=1), color="#999999", lw=0.7,
                    label="before (nominal legs)" if r is rs[0] else None)
        axs[0].plot(idx, np.linalg.norm(ea, axis=1), color="#1f77b4", lw=0.7,
                    label="after (identified)" if r is rs[0] else None)
        for a in range(3):
            axs[a + 1].plot(idx, eb[:, a], color="#999999", lw=0.6)
            axs[a + 1].plot(idx, ea[:, a], color="#1f77b4", lw=0.6)
    b, a = result.rmse_mm(foot)
    axs[0].set_title(f"{foot}: marker error per sample, RMSE {b:.2f} mm before, {a:.2f} mm after")
    axs[0].set_ylabel("|e| [mm]")
    axs[0].legend(loc="upper right", fontsize=8)
    for k, lab in enumerate("xyz"):
        axs[k + 1].set_ylabel(f"e_{lab} [mm]")
        axs[k + 1].axhline(0.0, color="k", lw=0.5)
    axs[3].set_xlabel("sample")
    fig.tight_layout()
    return fig


def _png(fig) -> bytes:
    from graphcal.report.plots import figure_png

    return figure_png(fig)


# ----------------------------------------------------------------------------- HTML
_CSS = """
body{font-family:-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:2em auto;max-width:1000px;color:#222;padding:0 1em}
h1{font-size:1.6em}h2{font-size:1.25em;border-bottom:1px solid #ddd;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.5em 0 1em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:right}th{background:#f3f3f3}td.l,th.l{text-align:left}
.warn{background:#fff4e5;border:1px solid #f0a030;border-left:6px solid #f0a030;padding:.6em 1em;margin:.6em 0}
figure{margin:1em 0}figure img{max-width:100%;border:1px solid #eee}figcaption{font-size:.85em;color:#555}
.small{font-size:.85em;color:#555}
"""


_FRAME_TEXT = {"vbase": "Yuan virtual base (body markers)", "mocap": "motion-capture frame fixed to the base"}


def _e(x) -> str:
    return html.escape(str(x), quote=True)


def _n(x, fmt=".3f") -> str:
    x = float(x)
    if math.isnan(x):
        return "–"
    return format(x, fmt)


def identification_html(result, pngs: dict[str, bytes], *, title: str) -> str:
    """One self-contained page: foot errors, parameters, pose, markers, identifiability, figures."""
    out = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{_e(title)}</title><style>{_CSS}</style></head><body>",
           f"<h1>{_e(title)}</h1>",
           f"<p class='small'>Robot <code>{_e(result.robot_name)}</code>, base frame <code>{_e(result.base_frame)}</code>; "
           f"measurement frame: {_FRAME_TEXT.get(result.frame, result.frame)}; "
           f"{result.iterations} LM iterations ({'converged' if result.converged else 'NOT converged'}), "
           f"σ0 = {_n(result.sigma0, '.3f')} (a-posteriori noise / a-priori noise).</p>"]
    out.append("<h2>Foot marker error (3-D RMSE)</h2><table><tr><th class='l'>foot</th><th>samples</th>"
               "<th>everything nominal [mm]</th><th>before: nominal legs [mm]</th><th>after [mm]</th></tr>")
    for foot in result.legs:
        rs = [r for r in result.residuals if r.foot == foot]
        b, a = result.rmse_mm(foot)
        nom = [r.rmse_nominal_mm for r in rs]
        nomtxt = _n(np.sqrt(np.mean(np.square(nom))), ".2f") if all(v is not None for v in nom) else "–"
        out.append(f"<tr><td class='l'><code>{_e(foot)}</code></td><td>{sum(len(r.time) for r in rs)}</td>"
                   f"<td>{nomtxt}</td><td>{_n(b, '.2f')}</td><td>{_n(a, '.2f')}</td></tr>")
    out.append("</table><p class='small'>Before: the nominal URDF with the pose of the measurement frame (and "
               "unknown marker positions) fitted; after: the identified parameters. Errors are measured minus "
               "predicted marker positions.</p>")
    out.append("<h2>Leg parameters</h2><table><tr><th class='l'>foot</th><th class='l'>parameter</th><th>value</th>"
               "<th>1-σ</th><th class='l'>unit</th><th class='l'>status</th></tr>")
    for foot, params in result.legs.items():
        for p in params:
            f, u = _unit(p.name)
            val = _n(f * p.value, "+.4f") if p.free else "held 0"
            sig = _n(f * p.sigma, ".4f") if p.free else ""
            out.append(f"<tr><td class='l'>{_e(foot)}</td><td class='l'><code>{_e(p.name)}</code></td><td>{val}</td>"
                       f"<td>{sig}</td><td class='l'>{u}</td><td class='l'>{_e(p.status)}</td></tr>")
    out.append("</table>")
    out.append(f"<h2>{_e(result.pose_name)}</h2><table><tr><th class='l'>component</th><th>change from reference</th>"
               "<th>1-σ</th><th class='l'>unit</th><th class='l'>status</th></tr>")
    for p in result.mocap:
        f, u = _unit(p.name)
        out.append(f"<tr><td class='l'><code>{_e(p.name)}</code></td><td>{_n(f * p.value, '+.4f')}</td>"
                   f"<td>{_n(f * p.sigma, '.4f') if p.free else ''}</td><td class='l'>{u}</td><td class='l'>{_e(p.status)}</td></tr>")
    out.append("</table>")
    if result.markers:
        out.append("<h2>Marker positions on the foot</h2><table><tr><th class='l'>marker</th><th>x [mm]</th><th>y [mm]</th>"
                   "<th>z [mm]</th><th>1-σ [mm]</th></tr>")
        for name, ps in result.markers.items():
            out.append(f"<tr><td class='l'><code>{_e(name)}</code></td>" + "".join(f"<td>{_n(1e3 * p.value, '+.2f')}</td>" for p in ps)
                       + f"<td>{' / '.join(_n(1e3 * p.sigma, '.2f') for p in ps)}</td></tr>")
        out.append("</table>")
    out.append("<h2>Identifiability</h2>")
    r = result.identifiability
    out.append(f"<p class='small'>Scaled whitened Jacobian: rank {r.rank} of {len(r.names)}; threshold "
               f"max({r.rtol:g}·s_max, {r.s_min:g}) = {_n(r.threshold, '.3g')} (s in noise standard deviations for an "
               f"error of the a-priori size); identifiable when less than {r.f_identifiable:g} of the parameter lies in "
               f"the null space.</p><ul>")
    out += [f"<li>{_e(line)}</li>" for line in r.lines()]
    out.append("</ul>")
    for foot, png in pngs.items():
        data = base64.b64encode(png).decode("ascii")
        out.append(f"<figure><img alt='foot errors {_e(foot)}' src='data:image/png;base64,{data}'>"
                   f"<figcaption>{_e(foot)}: marker error per sample before (grey) and after (blue) identification, "
                   f"norm and body axes (Yuan et al. Figs. 6 and 8).</figcaption></figure>")
    if result.warnings:
        out.append("<div class='warn'><strong>Warnings</strong><ul>" + "".join(f"<li>{_e(w)}</li>" for w in result.warnings)
                   + "</ul></div>")
    out.append("</body></html>\n")
    return "\n".join(out)


# ----------------------------------------------------------------------------- writing
def _png_name(foot: str) -> str:
    safe = "".join(c if (c.isalnum() or c in "._-") else "_" for c in foot)
    return f"foot_errors_{safe}.png"


def check_output_folder(out: Path) -> None:
    """OutputExistsError unless ``out`` is absent, empty, or holds only a previous identify-legs output
    (graphcal.io.atomic.check_output_folder)."""
    def previous(folder):  # legs.yaml of this version, or of one that wrote the calibration format id
        return (previous_output_files(folder, LEGS_FILES["legs"], LEGS_FILES.values(), "graphcal-legs/")
                or previous_output_files(folder, LEGS_FILES["legs"], LEGS_FILES.values(), "graphcal-calibration/"))

    check_folder(out, previous, what="graphcal leg identification")


def write_identification_outputs(result, out_dir, *, dataset: str | None = None) -> dict[str, Path]:
    """Write legs.yaml, robot_calibrated.urdf, report.html and one PNG per foot into ``out_dir``,
    atomically (see module docstring). Returns name -> path.

    Raises:
        OutputExistsError: ``out_dir`` is a file, a link, or a folder with other files.
        ModelError: the URDF cannot carry the parameters.
    """
    from graphcal.report.urdf import calibrated_urdf

    out = Path(out_dir)
    check_output_folder(out)
    pngs = {foot: _png(foot_error_figure(result, foot)) for foot in result.legs}
    files = dict(LEGS_FILES)
    for foot in result.legs:
        files[f"png:{foot}"] = _png_name(foot)
    ds = str(dataset if dataset is not None else result.source)
    urdf = calibrated_urdf(result.urdf_xml, result.base_frame, {}, result.leg_values(), dataset=ds, command="identify-legs")
    page = identification_html(result, pngs, title=f"graphcal leg identification: {Path(ds).name or ds}")
    with atomic_directory(out, overwrite=True) as tmp:
        atomic_write_text(tmp / files["legs"], legs_yaml_text(result, dataset=ds, output_files=list(files.values())))
        atomic_write_text(tmp / files["urdf"], urdf)
        atomic_write_text(tmp / files["report"], page)
        for foot, png in pngs.items():
            atomic_write_bytes(tmp / _png_name(foot), png)
        check_output_folder(out)
    return {k: out / v for k, v in files.items()}
