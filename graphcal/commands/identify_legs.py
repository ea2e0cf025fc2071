"""``graphcal identify-legs DATASET --out DIR``: leg kinematic identification from motion capture.

Reads the dataset (``mocap.csv`` with foot markers, optionally Yuan's body markers), identifies the
parameters of every leg that carries a marker (:func:`graphcal.legs.identify.identify_legs_dataset`)
and writes ``legs.yaml``, ``robot_calibrated.urdf``, ``report.html`` and one PNG per foot
(:func:`graphcal.legs.report.write_identification_outputs`). Bad input raises
:class:`~graphcal.errors.DatasetError` (the command line prints it and exits with code 2).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.legs.identify import MOCAP_COMPONENTS, IdentifyOptions, identify_legs_dataset

__all__ = ["run", "parse_mocap_free", "parameter_text"]

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


def run(dataset: str | Path, out: str | Path, *, progress: bool = True, mocap_free: str | None = None,
        origins: str = "first", sigma_marker_mm: float = 1.0, sigma_joint_deg: float = 0.0) -> str:
    """Run the identification on ``dataset`` and write the outputs into ``out``; returns a summary.

    Args:
        dataset: dataset folder.
        out: output folder (created; replaces only a previous identify-legs output).
        progress: progress bar on stderr (tqdm).
        mocap_free: components of T_body_mocap that are unknown ("rx,ry,rz,x,y,z" default; Yuan: "rz,z").
        origins: leg model (``first``, ``all``, ``none``; :func:`graphcal.models.legs.leg_model`).
        sigma_marker_mm, sigma_joint_deg: a-priori noise (the covariance is scaled by sigma0^2).
    """
    from graphcal.legs.report import check_output_folder, write_identification_outputs

    import math

    if not (math.isfinite(sigma_marker_mm) and sigma_marker_mm > 0):
        raise GraphcalError(f"--sigma-marker-mm must be a finite number > 0 (mm), got {sigma_marker_mm}")
    if not (math.isfinite(sigma_joint_deg) and 0 <= sigma_joint_deg <= 360.0):
        raise GraphcalError(f"--sigma-joint-deg must be a number from 0 to 360 (deg), got {sigma_joint_deg}")
    if sigma_marker_mm > 1e6:
        raise GraphcalError(f"--sigma-marker-mm must be at most 1e6 (mm), got {sigma_marker_mm}")
    check_output_folder(Path(out))  # fail before the work, not after
    options = IdentifyOptions(sigma_marker_m=sigma_marker_mm / 1000.0, sigma_joint_rad=sigma_joint_deg * 3.141592653589793 / 180.0,
                              origins=origins, mocap_free=parse_mocap_free(mocap_free))
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
    lines = [f"identified the legs of {', '.join(result.legs)} from {dataset} "
             f"({'virtual base' if result.frame == 'vbase' else 'mocap frame fixed to the base'}); wrote {out}:"]
    for foot, params in result.legs.items():
        b, a = result.rmse_mm(foot)
        lines.append(f"  {foot}: marker RMSE {b:.2f} mm (nominal legs) -> {a:.2f} mm (identified)")
        for p in params:
            if p.free:
                lines.append(f"    {parameter_text(p.name, p.value, p.sigma)}")
    held = [p for p in result.identifiability.parameters if not p.free]
    if held:
        lines.append("  held at their nominal value: " + ", ".join(f"{p.name} ({p.status})" for p in held))
    for w in result.warnings:
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
