"""Write the calibration outputs as one atomic set.

``write_calibration_outputs(result, out_dir)`` writes

* ``calibration.yaml``       -- :mod:`graphcal.report.calibration_yaml` (format ``graphcal-calibration/1``)
* ``robot_calibrated.urdf``  -- :mod:`graphcal.report.urdf`
* ``static_transforms.sh``   -- :mod:`graphcal.report.ros` (executable)
* ``report.html``            -- :mod:`graphcal.report.calibration_page`
* ``scene.mcap``             -- :mod:`graphcal.report.scene_mcap` (ROS 2 MCAP: transforms, URDF, clouds)

into a hidden sibling temporary folder and renames it onto ``out_dir`` only when all five are
complete (:func:`graphcal.io.atomic.atomic_directory`): an exception or an interruption half-way
leaves the previous results (or nothing) in ``out_dir``, never a partial set or a half-written file.

It only ever replaces a folder that is empty or holds a previous graphcal calibration (its
``calibration.yaml`` has ``format: graphcal-calibration/...`` and the folder holds no file graphcal
did not write), so pointing ``--out`` at a dataset or home folder by mistake cannot delete anything.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from graphcal.io.atomic import atomic_directory, atomic_write_text, previous_output_files
from graphcal.io.atomic import check_output_folder as check_output_folder_of
from graphcal.report.calibration_yaml import calibration_yaml_text
from graphcal.report.ros import static_transforms_script
from graphcal.report.scene_mcap import DEFAULT_MAX_POINTS, readable_dataset, write_scene_mcap
from graphcal.report.urdf import calibrated_urdf

__all__ = ["OUTPUT_FILES", "write_calibration_outputs", "check_output_folder", "shown_dataset"]

#: output name -> file name inside the output folder.
OUTPUT_FILES: dict[str, str] = {
    "calibration": "calibration.yaml",
    "urdf": "robot_calibrated.urdf",
    "static_transforms": "static_transforms.sh",
    "report": "report.html",
    "scene": "scene.mcap",
}
_FORMAT_PREFIX = "graphcal-calibration/"


def check_output_folder(out_dir: str | Path, *, overwrite: bool = True) -> None:
    """Raise :class:`~graphcal.io.atomic.OutputExistsError` (a GraphcalError) unless ``out_dir`` is
    absent, an empty folder, or (with ``overwrite``) a folder holding only a previous graphcal
    calibration's files (graphcal.io.atomic.check_output_folder)."""
    check_output_folder_of(out_dir, lambda f: previous_output_files(f, OUTPUT_FILES["calibration"], OUTPUT_FILES.values(),
                                                                    _FORMAT_PREFIX),
                           what="graphcal calibration", overwrite=overwrite)


# ----------------------------------------------------------------------------- the writers
def _write_yaml(folder: Path, result) -> Path:
    text = calibration_yaml_text(result, extra={"output_files": list(OUTPUT_FILES.values())})
    return atomic_write_text(folder / OUTPUT_FILES["calibration"], text)


def _leg_parameters(result) -> dict | None:
    if not result.legs:
        return None
    return {foot: {str(n): float(v) for n, v in zip(leg.names, leg.values)} for foot, leg in result.legs.items()}


def uncertainty_note(result) -> str:
    """One sentence on the sensors' governing 1-sigma (body axes), and whether it is the model's or
    the robust one (the model does not fit: calibration.yaml adequacy:)."""
    parts = []
    for name, s in result.sensors.items():
        which = "model" if getattr(s, "covariance_model", None) is None else "robust (the model does not fit)"
        parts.append(f"{name} rot {' '.join(f'{x:.3g}' for x in s.sigma_rot_deg)} deg, xyz "
                     f"{' '.join(f'{x:.3g}' for x in s.sigma_xyz_mm)} mm ({which})")
    if not parts:
        return ""
    return "1-sigma about/along the body axes, as sigma in calibration.yaml: " + "; ".join(parts) + "."


def _write_urdf(folder: Path, result) -> Path:
    text = calibrated_urdf(
        result.robot_urdf_xml,
        result.base_frame,
        {name: s.T_body_sensor for name, s in result.sensors.items()},
        _leg_parameters(result),
        dataset=str(result.dataset),
        uncertainty=uncertainty_note(result),
    )
    return atomic_write_text(folder / OUTPUT_FILES["urdf"], text)


def _write_scene(folder: Path, result, dataset, max_points: int | None) -> Path:
    """scene.mcap: the clouds and station times read from ``dataset`` (the folder as given to
    calibrate; ``result.dataset`` is by then relative to the output folder)."""
    urdf = (folder / OUTPUT_FILES["urdf"]).read_text(encoding="utf-8")
    return write_scene_mcap(folder / OUTPUT_FILES["scene"], result, urdf, dataset=dataset, max_points=max_points)


def _write_static_transforms(folder: Path, result) -> Path:
    text = static_transforms_script(
        result.base_frame, {name: s.T_body_sensor for name, s in result.sensors.items()}, dataset=str(result.dataset),
        uncertainty=uncertainty_note(result),
    )
    path = atomic_write_text(folder / OUTPUT_FILES["static_transforms"], text)
    mode = path.stat().st_mode & 0o777
    os.chmod(path, mode | ((mode & 0o444) >> 2))  # executable wherever readable
    return path


def _scene(result, ds):
    """The report's 3-D scene (clouds and joint angles from ``ds``, a Dataset or None)."""
    from graphcal.errors import GraphcalError
    from graphcal.io.dataset import load_dataset_robot
    from graphcal.report.scene_3d import calibration_scene

    robot = None
    if ds is not None and ds.robot is not None:
        try:
            robot = load_dataset_robot(ds)
        except (GraphcalError, OSError, ValueError):
            robot = None  # the scene without the stick figure
    try:
        return calibration_scene(result, ds, robot)
    except (GraphcalError, OSError, ValueError):
        return calibration_scene(result, None, robot)  # a cloud unreadable since the calibration


def _write_report(folder: Path, result, title: str | None, ds) -> Path:
    from graphcal.report.calibration_page import report_html  # matplotlib: imported only when needed

    text = report_html(result, title=title or f"graphcal calibration: {Path(str(result.dataset)).name or result.dataset}",
                       scene=_scene(result, ds))
    return atomic_write_text(folder / OUTPUT_FILES["report"], text)


def shown_dataset(dataset, out_dir: Path) -> str:
    """The dataset as the output files name it: its path relative to the output folder
    (``../octopus-chai2015``), so that a folder of outputs can be shared or moved with its dataset;
    the dataset's folder name where no relative path exists (another drive)."""
    try:
        return os.path.relpath(Path(str(dataset)).resolve(), Path(out_dir).resolve())
    except ValueError:
        return Path(str(dataset)).name


def write_calibration_outputs(result, out_dir: str | Path, *, overwrite: bool = True, title: str | None = None,
                              scene_max_points: int | None = DEFAULT_MAX_POINTS) -> dict[str, Path]:
    """Write calibration.yaml, robot_calibrated.urdf, static_transforms.sh, report.html and
    scene.mcap into ``out_dir`` as one atomic set.

    Args:
        result: a :class:`~graphcal.calibration.result.CalibrationResult`.
        out_dir: the output folder (created, with its parents, if needed).
        overwrite: replace a previous graphcal calibration in ``out_dir`` (default). With False any
            non-empty ``out_dir`` is refused.
        title: title of the HTML report (default: names the dataset).
        scene_max_points: cap on the points of each cloud in scene.mcap (evenly thinned above it;
            default 20000; None or 0: all points).

    Returns:
        ``{"calibration": .../calibration.yaml, "urdf": .../robot_calibrated.urdf,
        "static_transforms": .../static_transforms.sh, "report": .../report.html,
        "scene": .../scene.mcap}``.

    Raises:
        OutputExistsError (a GraphcalError): ``out_dir`` is a file or symbolic link, or a non-empty
            folder that is not a previous graphcal calibration, or holds files graphcal did not
            write (checked before writing and again just before the swap).
        ModelError: the URDF cannot carry the calibration (see :func:`~graphcal.report.urdf.calibrated_urdf`).
        Any exception leaves ``out_dir`` exactly as it was.
    """
    out = Path(out_dir)
    check_output_folder(out, overwrite=overwrite)
    given = result.dataset or None  # where the clouds are, before it is made relative to out
    dataset, _ = readable_dataset(given)
    result = dataclasses.replace(result, dataset=shown_dataset(result.dataset, out))  # as written, shareable
    with atomic_directory(out, overwrite=True) as tmp:
        _write_yaml(tmp, result)
        _write_urdf(tmp, result)
        _write_static_transforms(tmp, result)
        _write_report(tmp, result, title, dataset)
        _write_scene(tmp, result, dataset if dataset is not None else given, scene_max_points)
        check_output_folder(out, overwrite=overwrite)  # nothing foreign appeared meanwhile
    return {key: out / name for key, name in OUTPUT_FILES.items()}
