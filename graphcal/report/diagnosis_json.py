"""``diagnosis.json`` (format ``graphcal-diagnosis/1``, docs/diagnosis.md): a
:class:`~graphcal.diagnosis.diagnose.Diagnosis` as plain JSON-ready values (SI units unless a key
says otherwise; poses as ``{xyz: [m], quaternion_wxyz, rpy_deg}``, ``T_body_sensor`` maps sensor to
body coordinates)."""

from __future__ import annotations

from graphcal.calibration.result import calibration_result
from graphcal.diagnosis.diagnose import extended_calibration_note, extension_values, final_adequacy
from graphcal.report.calibration_yaml import calibration_to_dict

__all__ = ["diagnosis_to_dict"]


def diagnosis_to_dict(diag) -> dict:
    """The ``diagnosis.json`` document of ``diag``."""
    result = calibration_result(diag.model.ds, diag.model.robot, diag.model.data, diag.problem, diag.values,
                                set(), 0, diag.model.options)
    cal = calibration_to_dict(result)
    return {
        "format": "graphcal-diagnosis/1",
        "adequacy": final_adequacy(diag),
        "nominal": diag.nominal.to_dict(),
        "final": diag.final.to_dict(),
        "corrections": [c.to_dict() for c in diag.corrections],
        "findings": [f.to_dict() for f in diag.findings],
        "unexplained_structure": bool(diag.unexplained_structure),
        "structure_test": None if diag.structure_test is None else
        {"chi2": diag.structure_test[0], "redundancy": diag.structure_test[1], "p_value": diag.structure_test[2]},
        "extended_calibration": {"note": extended_calibration_note(diag.model.options),
                                 "sensors": cal.get("sensors", {}), "legs": cal.get("legs", {}),
                                 **extension_values(diag)},
        "screening": [[{"candidate": c, "log10_p_family": p, "statistic": s, "dof": d} for c, p, s, d in r]
                      for r in diag.screening],
        "screening_threshold_log10_p": list(diag.thresholds),
        "nuisance": list(diag.nuisance),
        "notes": list(diag.notes),
        "warnings": list(diag.warnings),
        "physical_noise_tests": {"nominal": [g.to_dict() for g in diag.nominal_groups],
                                 "final": [g.to_dict() for g in diag.groups]},
        "structure_remains_in": [g.group for g in diag.groups if g.structure],
        "answer": diag.answer,
    }

