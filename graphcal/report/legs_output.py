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
  (Yuan et al. Figs. 6 and 8: error norm per sample, and per body axis; :mod:`graphcal.report.legs_page`).

:func:`write_identification_outputs` writes the set atomically (a hidden sibling folder renamed
into place, :func:`graphcal.io.atomic.atomic_directory`); it replaces only an empty folder or the
outputs of a previous ``identify-legs``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from graphcal.io.atomic import atomic_directory, atomic_write_bytes, atomic_write_text, previous_output_files
from graphcal.io.atomic import check_output_folder as check_folder
from graphcal.io.calibration_yaml import pose_to_dict

__all__ = ["LEGS_FILES", "legs_yaml_dict", "legs_yaml_text", "write_identification_outputs"]

#: fixed output names (one PNG per foot is added: foot_errors_<foot>.png)
LEGS_FILES = {"legs": "legs.yaml", "urdf": "robot_calibrated.urdf", "report": "report.html"}

#: legs.yaml is not a calibration.yaml (no sensors, residuals or outliers): its own format id.
#: (Before 2026-11-21 it said graphcal-calibration/1 and failed that format's reader.)
LEGS_FORMAT = "graphcal-legs/1"


def _f(x) -> float:
    return float(x)


# ----------------------------------------------------------------------------- YAML
def legs_yaml_dict(result, *, dataset: str | None = None, output_files=None) -> dict:
    """The ``legs.yaml`` document (plain Python values)."""
    legs = {}
    aliased = _aliased(result)
    for foot, params in result.legs.items():
        legs[str(foot)] = {p.name: _parameter_entry(p, aliased) for p in params if p.free}
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
    }
    if result.adequacy is not None:
        doc["adequacy"] = result.adequacy.as_dict()
        doc["outlier_postures"] = [
            {"time": float(t.time), "f_statistic": float(t.f_statistic), "p_bonferroni": float(t.p_bonferroni),
             "deletion_chi2": float(t.statistic), "rows": int(t.rows), "position_error_mm": float(t.rms_mm)}
            for t in result.adequacy.postures if t.flagged]
    doc["sigma_note"] = SIGMA_NOTE
    doc.update({
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
    })
    if output_files is not None:
        doc["output_files"] = list(output_files)
    return doc


#: what the sigmas of legs.yaml are (written into the file)
SIGMA_NOTE = ("legs.<foot>.<parameter>.sigma governs: the larger of sigma_model (the model covariance, scaled by "
              "sigma0^2 of the fit) and sigma_jackknife (leave-one-posture-out jackknife, linearised at the "
              "solution); significance: |value| / sigma against a normal distribution (two-sided p); aliased_with / "
              "weakly_aliased_with: the parameters the identifiability analysis finds in an exact / a weakly determined "
              "combination with it. SI units (m, rad).")


def _aliased(result) -> dict[str, dict[str, list[str]]]:
    """parameter name -> {"aliased_with": exact (structural) partners, "weakly_aliased_with": partners
    of a combination these data determine only weakly} from the identifiability combinations."""
    out: dict[str, dict[str, set]] = {}
    for p in result.identifiability.parameters:
        names = [n for n, _ in p.combination]
        key = "aliased_with" if p.structural else "weakly_aliased_with"
        for n in names:
            out.setdefault(n, {}).setdefault(key, set()).update(x for x in names if x != n)
    return {k: {kk: sorted(vv) for kk, vv in v.items() if vv} for k, v in out.items()}


def _parameter_entry(p, aliased) -> dict:
    sig = p.significance
    e = {"value": _f(p.value), "sigma": _f(p.sigma), "sigma_model": _f(p.sigma_model),
         "sigma_jackknife": _f(p.sigma_jackknife),
         "significance": {"z": _f(sig["z"]), "p_value": _f(sig["p_value"]), "level": sig["level"]}}
    e.update(aliased.get(p.name, {}))
    return e


def legs_yaml_text(result, *, dataset: str | None = None, output_files=None) -> str:
    """``legs.yaml`` text with a leading comment line."""
    doc = legs_yaml_dict(result, dataset=dataset, output_files=output_files)
    ds = " ".join(str(doc["dataset"]).split())
    head = (f"# graphcal leg identification ({LEGS_FORMAT}): leg kinematic parameters (SI, change from the nominal URDF) "
            f"and their 1-sigma, written by graphcal identify-legs from dataset {ds}\n")
    return head + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, allow_unicode=True, width=200)


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
    from graphcal.report.legs_page import foot_error_figure, identification_html
    from graphcal.report.plots import figure_png
    from graphcal.report.urdf import calibrated_urdf

    out = Path(out_dir)
    check_output_folder(out)
    pngs = {foot: figure_png(foot_error_figure(result, foot)) for foot in result.legs}
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
