"""``graphcal diagnose DATASET --out DIR``: run the diagnosis and write its files atomically.

Files: ``diagnosis.json`` (format ``graphcal-diagnosis/1``, docs/diagnosis.md) and ``report.html``
(findings, evidence, held-out gain, and per finding the residuals against the covariate that reveals
its cause, before and after). ``DIR`` must be new, empty, or a previous diagnosis (replaced only
once the new one is complete); anything else is refused, so nothing the user made is overwritten.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from graphcal.diagnosis.diagnose import Diagnosis, diagnose
from graphcal.io.atomic import atomic_directory, atomic_write_text, check_command_output
from graphcal.report.diagnosis_json import diagnosis_to_dict
from graphcal.report.diagnosis_page import diagnosis_html, parameter_text, where_text

__all__ = ["run", "DiagnoseResult", "write_diagnosis", "summary_text", "DIAGNOSIS_FILES"]

DIAGNOSIS_FILES = ("diagnosis.json", "report.html")


def _check_out(out: Path) -> None:
    """The output-folder policy of graphcal.io.atomic.check_output_folder, for a diagnosis."""
    check_command_output(out, "diagnosis.json", DIAGNOSIS_FILES, "graphcal-diagnosis/", what="graphcal diagnosis")


def summary_text(doc: dict, out: Path | None = None) -> str:
    """The console summary of diagnosis.json's document ``doc`` (and the files in ``out``)."""
    n = doc["nominal"]
    lines = [f"warning: {w}" for w in doc.get("warnings", [])]
    lines.append(f"nominal model: theta RMS {n['normal_rms_deg']:.4f} deg, e_d RMS {n['distance_rms_mm']:.3f} mm, "
                 f"chi2/dof {n['chi2_per_dof']:.2f}")
    for c in doc.get("corrections", []):
        corr = ", ".join(f"{k} {v}" for k, v in c["corrected"].items())
        alt = f"; cannot be told from {', '.join(c['alternatives'])}" if c["alternatives"] else ""
        lines.append(f"corrected {c['cause']} ({where_text(c['where'])})" + (f": {corr}" if corr else "")
                     + f"; chi2 drop {c['statistic']:.1f} on {c['dof']} dof, p = {c['p_value']:.2g}{alt}")
    if not doc["findings"]:
        lines.append("findings: none (no catalogued effect is significant)")
    for fd in doc["findings"]:
        where = where_text(fd["where"]) if fd["where"] else ""
        params = ", ".join(parameter_text(k, v, fd["sigma"].get(k, float("nan"))) for k, v in fd["parameters"].items()
                           if isinstance(v, float))
        g = fd["gain"]
        gain = (f"; held-out RMS {g['heldout_rms_before']:.3g} -> {g['heldout_rms_after']:.3g} sigma (whitened)"
                if g else "")
        if g and g.get("p_value") is not None:
            gain += f" (paired test p = {g['p_value']:.2g})"
        lines.append(("found " if fd.get("supported", True) else "tentative (held-out gain not significant): ")
                     + f"{fd['cause']}" + (f" ({where})" if where else "") + (f": {params}" if params else "")
                     + f"; LR {fd['evidence']['statistic']:.1f} on {fd['evidence']['dof']} dof{gain}")
    if doc["unexplained_structure"]:
        where = ", ".join(doc.get("structure_remains_in", []))
        lines.append("structure remains that no supported catalogued cause explains" + (f" (in {where})" if where else ""))
    if doc.get("answer") == "neither":
        lines.append("the extended model does not fit at physical noise either: its extrinsic is not the answer")
    for name, sensor in (doc.get("extended_calibration") or {}).get("sensors", {}).items():
        sig = sensor.get("sigma", {})
        lines.append(f"sensor pose of the diagnosis model: {name} xyz "
                     f"{[round(v, 4) for v in sensor['T_body_sensor']['xyz']]} m, sigma rot "
                     f"{[float(f'{v:.2g}') for v in sig.get('rot_deg', [])]} deg, xyz "
                     f"{[float(f'{v:.2g}') for v in sig.get('xyz_mm', [])]} mm (noise held at physical defaults, "
                     "not calibrate's learned noise: its sigma is larger; for the extrinsic use calibrate's "
                     "calibration.yaml; diagnosis.json extended_calibration.note)")
    if out is not None:
        lines.append(f"wrote {out / 'diagnosis.json'} and {out / 'report.html'}")
    return "\n".join(lines)


def write_diagnosis(diag: Diagnosis, out_dir, *, title: str | None = None) -> dict:
    """Write diagnosis.json and report.html into ``out_dir`` as one atomic set; returns the JSON."""
    out = Path(out_dir)
    _check_out(out)
    doc = diagnosis_to_dict(diag)
    text = json.dumps(doc, indent=1, default=float)
    page = diagnosis_html(diag, doc, title or f"graphcal diagnosis of {Path(str(diag.model.ds.root)).name}")
    with atomic_directory(out, overwrite=True) as tmp:
        atomic_write_text(tmp / "diagnosis.json", text)
        atomic_write_text(tmp / "report.html", page)
        _check_out(out)
    return doc


@dataclass(frozen=True)
class DiagnoseResult:
    """What ``graphcal diagnose`` did.

    Attributes:
        diagnosis: the library's :class:`~graphcal.diagnosis.diagnose.Diagnosis`.
        doc: diagnosis.json's document (:func:`graphcal.report.diagnosis_json.diagnosis_to_dict`).
        out: the output folder.
        files: diagnosis.json and report.html.
        warnings: the diagnosis's warnings (diagnosis.json ``warnings``).
        verdict: whose extrinsic is the answer (diagnosis.json ``answer``: extended, nominal,
            neither, corrected).
    """

    diagnosis: Diagnosis
    doc: dict
    out: Path
    files: tuple[Path, ...]
    warnings: tuple[str, ...]
    verdict: str | None

    @property
    def causes(self) -> tuple[str, ...]:
        """The causes found (supported or tentative), in the order found."""
        return tuple(f["cause"] for f in self.doc["findings"])

    def summary_text(self) -> str:
        """The console summary (:func:`summary_text`)."""
        return summary_text(self.doc, self.out)


def run(dataset, out_dir, *, progress: bool = True) -> DiagnoseResult:
    """``graphcal diagnose``: diagnose ``dataset`` (a dataset folder) and write diagnosis.json and
    report.html into ``out_dir`` (new, empty, or a previous diagnosis); ``progress``: tqdm bars and one
    log line (INFO) per step. Returns a :class:`DiagnoseResult` (its summary: RMS in deg and mm, one
    line per finding)."""
    out = Path(out_dir)
    _check_out(out)  # refuse early, before the work
    diag = diagnose(dataset, progress=progress)
    doc = write_diagnosis(diag, out)
    return DiagnoseResult(diagnosis=diag, doc=doc, out=out, files=tuple(out / name for name in DIAGNOSIS_FILES),
                          warnings=tuple(doc.get("warnings", [])), verdict=doc.get("answer"))
