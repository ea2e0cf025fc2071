"""``graphcal identify-legs DATASET --out DIR``: leg kinematic identification from motion capture.

Reads the dataset (``mocap.csv`` with foot markers, optionally Yuan's body markers), identifies the
parameters of every leg that carries a marker (:func:`graphcal.legs.identify.identify_legs_dataset`)
and writes ``legs.yaml``, ``robot_calibrated.urdf``, ``report.html`` and one PNG per foot
(:func:`graphcal.report.legs_output.write_identification_outputs`). Bad input raises
:class:`~graphcal.errors.DatasetError` (the command line prints it and exits with code 2).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.legs.identify import MOCAP_COMPONENTS, IdentifyOptions, LegIdentificationResult, identify_legs_dataset

__all__ = ["run", "IdentifyLegsResult", "parse_mocap_free", "summary_lines", "parameter_text"]

_STAGES = 7  # read, start, before, identifiability, after, covariance, write


def parse_mocap_free(text: str | None) -> tuple[str, ...]:
    """``"rz,z"`` -> ("rz", "z"); None or "all" -> every component. GraphcalError on unknown names."""
    if text is None or text.strip().lower() == "all":
        return MOCAP_COMPONENTS
    comps = tuple(c.strip() for c in text.split(",") if c.strip())
    bad = [c for c in comps if c not in MOCAP_COMPONENTS]
    if bad or not comps:
        raise GraphcalError(f"--mocap-free: expected a comma-separated subset of {', '.join(MOCAP_COMPONENTS)} or 'all', got {text!r}")
    return comps


@dataclass(frozen=True)
class IdentifyLegsResult:
    """What ``graphcal identify-legs`` did.

    Attributes:
        identification: the library's :class:`~graphcal.legs.identify.LegIdentificationResult`.
        dataset: the dataset folder, as given.
        out: the output folder.
        files: legs.yaml, robot_calibrated.urdf, report.html and a PNG per foot.
        warnings: the identification's warnings (the adequacy message first when it does not fit).
        verdict: the model's adequacy (``fits`` / ``does not fit``), or None when not judged.
    """

    identification: LegIdentificationResult
    dataset: str
    out: Path
    files: tuple[Path, ...]
    warnings: tuple[str, ...]
    verdict: str | None

    def summary_text(self) -> str:
        """The console summary (:func:`summary_lines`)."""
        return summary_lines(self.identification, self.dataset, self.out, {p.name: p for p in self.files})


def run(dataset: str | Path, out: str | Path, *, progress: bool = True, mocap_free: str | None = None,
        origins: str = "first", sigma_marker_mm: float | None = None, sigma_joint_deg: float | None = None,
        robust: str = "none") -> IdentifyLegsResult:
    """Run the identification on ``dataset`` and write the outputs into ``out``; returns an
    :class:`IdentifyLegsResult` (its summary's first line is the model-adequacy verdict).

    Args:
        dataset: dataset folder.
        out: output folder (created; replaces only a previous identify-legs output).
        progress: progress bar on stderr (tqdm).
        mocap_free: components of T_body_mocap that are unknown ("rx,ry,rz,x,y,z" default; Yuan: "rz,z").
        origins: leg model (``first``, ``all``, ``none``; :func:`graphcal.models.legs.leg_model`).
        sigma_marker_mm, sigma_joint_deg: the physical noise (mm per marker coordinate, deg per
            encoder) the verdict is judged against; None: dataset.yaml's ``mocap.sigma_mm`` /
            ``mocap.sigma_joint_deg``, else 1 mm / 0 deg. The covariance is scaled by sigma0^2.
        robust: robust loss per sample (``none``, ``huber``, ``cauchy``).
    """
    import math

    from graphcal.report.legs_output import check_output_folder, write_identification_outputs

    if sigma_marker_mm is not None and not (math.isfinite(sigma_marker_mm) and sigma_marker_mm > 0):
        raise GraphcalError(f"--sigma-marker-mm must be a finite number > 0 (mm), got {sigma_marker_mm}")
    if sigma_marker_mm is not None and sigma_marker_mm > 1e6:
        raise GraphcalError(f"--sigma-marker-mm must be at most 1e6 (mm), got {sigma_marker_mm}")
    if sigma_joint_deg is not None and not (math.isfinite(sigma_joint_deg) and 0 <= sigma_joint_deg <= 360.0):
        raise GraphcalError(f"--sigma-joint-deg must be a number from 0 to 360 (deg), got {sigma_joint_deg}")
    check_output_folder(Path(out))  # fail before the work, not after
    given = sigma_marker_mm is not None or sigma_joint_deg is not None
    options = IdentifyOptions(sigma_marker_m=(1.0 if sigma_marker_mm is None else sigma_marker_mm) / 1000.0,
                              sigma_joint_rad=math.radians(0.0 if sigma_joint_deg is None else sigma_joint_deg),
                              origins=origins, mocap_free=parse_mocap_free(mocap_free), robust=robust,
                              noise_source="command line" if given else "dataset")
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=_STAGES, desc="identify-legs", unit="stage", file=sys.stderr, leave=False)

    def say(stage: str) -> None:
        if bar is not None:
            bar.set_postfix_str(stage[:40])
            bar.update(1)

    try:
        result = identify_legs_dataset(dataset, options=options, progress=say)
        say("write outputs")
        written = write_identification_outputs(result, out, dataset=str(dataset))
    finally:
        if bar is not None:
            bar.close()
    a = result.adequacy
    return IdentifyLegsResult(identification=result, dataset=str(dataset), out=Path(out),
                              files=tuple(written.values()), warnings=tuple(result.warnings),
                              verdict=a.verdict if a is not None else None)


def summary_lines(result, dataset, out, written) -> str:
    """The console summary: the verdict first, flagged postures, then the parameters with their
    governing sigma and significance, warnings and files."""
    a = result.adequacy
    lines = []
    if a is not None:
        head = "WARNING: " if not a.fits or a.flagged else ""
        lines.append(f"{head}adequacy: {a.verdict} ({a.message})")
        for t in a.postures:
            if t.flagged:
                lines.append(f"  outlier posture t = {t.time:g}: F = {t.f_statistic:.1f}, Bonferroni p = {t.p_bonferroni:.2g}, "
                             f"position error {t.rms_mm:.1f} mm")
    lines.append(f"identified the legs of {', '.join(result.legs)} from {dataset} "
                 f"({'virtual base' if result.frame == 'vbase' else 'mocap frame fixed to the base'}); wrote {out}:")
    for foot, params in result.legs.items():
        b, aft = result.rmse_mm(foot)
        lines.append(f"  {foot}: marker RMSE {b:.2f} mm (nominal legs) -> {aft:.2f} mm (identified)")
        for p in params:
            if p.free:
                sig = p.significance
                lvl = "not significant" if sig["level"] == "not significant" else f"significant at {sig['level']}"
                scale = np.degrees(1.0) if p.name.endswith("_rad") else 1e3
                lines.append(f"    {parameter_text(p.name, p.value, p.sigma)} (model {scale * p.sigma_model:.3f}, "
                             f"jackknife {scale * p.sigma_jackknife:.3f}; {lvl})")
    held = [p for p in result.identifiability.parameters if not p.free]
    if held:
        lines.append("  held at their nominal value: " + ", ".join(f"{p.name} ({p.status})" for p in held))
    for w in result.warnings:
        if a is None or w != a.message:
            lines.append(f"  warning: {w}")
    lines.append("  files: " + ", ".join(sorted(p.name for p in written.values())))
    return "\n".join(lines)


def parameter_text(name: str, value: float, sigma: float) -> str:
    """``name`` (a legs.yaml key, SI: ``..._rad`` or ``..._m``) with ``value`` ± ``sigma`` in deg or mm,
    the unit suffix of the name changed with them (it printed degrees under ``offset_rad``)."""
    base, _, unit = name.rpartition("_")
    if unit == "rad":
        return f"{base}_deg = {np.degrees(value):+.3f} ± {np.degrees(sigma):.3f} deg"
    if unit == "m":
        return f"{base}_mm = {1e3 * value:+.3f} ± {1e3 * sigma:.3f} mm"
    return f"{name} = {value:+.4g} ± {sigma:.2g}"
