"""Write the calibration outputs as one atomic set.

``write_calibration_outputs(result, out_dir)`` writes

* ``calibration.yaml``       -- :mod:`graphcal.report.calibration_yaml` (format ``graphcal-calibration/1``)
* ``robot_calibrated.urdf``  -- :mod:`graphcal.report.urdf`
* ``static_transforms.sh``   -- :mod:`graphcal.report.ros` (executable)
* ``report.html``            -- :mod:`graphcal.report.html`

into a hidden sibling temporary folder and renames it onto ``out_dir`` only when all four are
complete (:func:`graphcal.io.atomic.atomic_directory`): an exception or an interruption half-way
leaves the previous results (or nothing) in ``out_dir``, never a partial set or a half-written file.

It only ever replaces a folder that is empty or holds a previous graphcal calibration (its
``calibration.yaml`` has ``format: graphcal-calibration/...`` and the folder holds no file graphcal
did not write), so pointing ``--out`` at a dataset or home folder by mistake cannot delete anything.
"""

from __future__ import annotations

import os
from pathlib import Path

import yaml

from graphcal.io.atomic import OutputExistsError, atomic_directory, atomic_write_text
from graphcal.report.calibration_yaml import calibration_yaml_text
from graphcal.report.ros import static_transforms_script
from graphcal.report.urdf import calibrated_urdf

__all__ = ["OUTPUT_FILES", "write_calibration_outputs", "check_output_folder"]

#: output name -> file name inside the output folder.
OUTPUT_FILES: dict[str, str] = {
    "calibration": "calibration.yaml",
    "urdf": "robot_calibrated.urdf",
    "static_transforms": "static_transforms.sh",
    "report": "report.html",
}
_FORMAT_PREFIX = "graphcal-calibration/"


def _previous_calibration_files(folder: Path) -> set[str] | None:
    """The file names a previous graphcal calibration in ``folder`` wrote, or None when ``folder``
    holds no graphcal calibration.yaml."""
    path = folder / OUTPUT_FILES["calibration"]
    if not path.is_file() or path.is_symlink():
        return None
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError, ValueError, TypeError, RecursionError):
        return None
    if not isinstance(doc, dict) or not str(doc.get("format", "")).startswith(_FORMAT_PREFIX):
        return None
    names = set(OUTPUT_FILES.values())
    listed = doc.get("output_files")
    if isinstance(listed, list):
        names |= {n for n in listed if isinstance(n, str) and n and "/" not in n and "\\" not in n and n not in (".", "..")}
    return names


def check_output_folder(out_dir: str | Path, *, overwrite: bool = True) -> None:
    """Raise :class:`~graphcal.io.atomic.OutputExistsError` (a GraphcalError) unless ``out_dir`` is
    absent, an empty folder, or (with ``overwrite``) a folder holding only a previous graphcal
    calibration's files."""
    out = Path(out_dir)
    if out.is_symlink():
        raise OutputExistsError(f"{out}: is a symbolic link; refusing to write calibration results there")
    if not out.exists():
        return
    if not out.is_dir():
        raise OutputExistsError(f"{out}: exists and is not a folder; refusing to write calibration results there")
    entries = sorted(os.listdir(out))
    if not entries:
        return
    if not overwrite:
        raise OutputExistsError(f"{out}: folder exists and is not empty; refusing to replace it (overwrite=False)")
    ours = _previous_calibration_files(out)
    if ours is None:
        shown = ", ".join(entries[:5]) + (", ..." if len(entries) > 5 else "")
        raise OutputExistsError(
            f"{out}: folder is not empty and holds no graphcal calibration ({shown}); refusing to replace "
            f"it: choose an empty or new output folder"
        )
    foreign = [e for e in entries if e not in ours]
    if foreign:
        shown = ", ".join(foreign[:5]) + (", ..." if len(foreign) > 5 else "")
        raise OutputExistsError(
            f"{out}: folder holds a previous graphcal calibration but also files graphcal did not write "
            f"({shown}); refusing to replace it: move those files or choose another output folder"
        )


# ----------------------------------------------------------------------------- the writers
def _write_yaml(folder: Path, result) -> Path:
    text = calibration_yaml_text(result, extra={"output_files": list(OUTPUT_FILES.values())})
    return atomic_write_text(folder / OUTPUT_FILES["calibration"], text)


def _leg_parameters(result) -> dict | None:
    if not result.legs:
        return None
    return {foot: {str(n): float(v) for n, v in zip(leg.names, leg.values)} for foot, leg in result.legs.items()}


def _write_urdf(folder: Path, result) -> Path:
    text = calibrated_urdf(
        result.robot_urdf_xml,
        result.base_frame,
        {name: s.T_body_sensor for name, s in result.sensors.items()},
        _leg_parameters(result),
        dataset=str(result.dataset),
    )
    return atomic_write_text(folder / OUTPUT_FILES["urdf"], text)


def _write_static_transforms(folder: Path, result) -> Path:
    text = static_transforms_script(
        result.base_frame, {name: s.T_body_sensor for name, s in result.sensors.items()}, dataset=str(result.dataset)
    )
    path = atomic_write_text(folder / OUTPUT_FILES["static_transforms"], text)
    mode = path.stat().st_mode & 0o777
    os.chmod(path, mode | ((mode & 0o444) >> 2))  # executable wherever readable
    return path


def _write_report(folder: Path, result, title: str | None) -> Path:
    from graphcal.report.html import report_html  # matplotlib: imported only when needed

    text = report_html(result, title=title or f"graphcal calibration: {Path(str(result.dataset)).name or result.dataset}")
    return atomic_write_text(folder / OUTPUT_FILES["report"], text)


def write_calibration_outputs(result, out_dir: str | Path, *, overwrite: bool = True, title: str | None = None) -> dict[str, Path]:
    """Write calibration.yaml, robot_calibrated.urdf, static_transforms.sh and report.html into
    ``out_dir`` as one atomic set.

    Args:
        result: a :class:`~graphcal.calibration.result.CalibrationResult`.
        out_dir: the output folder (created, with its parents, if needed).
        overwrite: replace a previous graphcal calibration in ``out_dir`` (default). With False any
            non-empty ``out_dir`` is refused.
        title: title of the HTML report (default: names the dataset).

    Returns:
        ``{"calibration": .../calibration.yaml, "urdf": .../robot_calibrated.urdf,
        "static_transforms": .../static_transforms.sh, "report": .../report.html}``.

    Raises:
        OutputExistsError (a GraphcalError): ``out_dir`` is a file or symbolic link, or a non-empty
            folder that is not a previous graphcal calibration, or holds files graphcal did not
            write (checked before writing and again just before the swap).
        ModelError: the URDF cannot carry the calibration (see :func:`~graphcal.report.urdf.calibrated_urdf`).
        Any exception leaves ``out_dir`` exactly as it was.
    """
    out = Path(out_dir)
    check_output_folder(out, overwrite=overwrite)
    with atomic_directory(out, overwrite=True) as tmp:
        _write_yaml(tmp, result)
        _write_urdf(tmp, result)
        _write_static_transforms(tmp, result)
        _write_report(tmp, result, title)
        check_output_folder(out, overwrite=overwrite)  # nothing foreign appeared meanwhile
    return {key: out / name for key, name in OUTPUT_FILES.items()}
