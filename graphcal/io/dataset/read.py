"""Reading a dataset folder: :func:`read_dataset` parses and checks everything except the points
inside the PLY files (whose names and locations it does check)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from graphcal.errors import DatasetError
from graphcal.io.dataset.checks import (
    check_joint_columns,
    check_magnitudes,
    check_mocap,
    check_mocap_poses,
    check_planes,
    check_stations,
    check_timeseries,
)
from graphcal.io.dataset.cloud_files import station_clouds
from graphcal.io.dataset.model import FORMAT, Dataset
from graphcal.io.dataset.paths import path_inside
from graphcal.io.dataset.robot import load_robot_spec
from graphcal.io.dataset.schema import parse_dataset_yaml
from graphcal.io.dataset.tables import CSV_FILES, ParsedCsv, read_csv
from graphcal.io.dataset.text import did_you_mean
from graphcal.io.files import check_regular_file


def _dataset_root(path: str | Path) -> Path:
    """The dataset folder of ``path`` (the folder or its dataset.yaml), checked to hold dataset.yaml."""
    root = Path(path)
    if root.name == "dataset.yaml" and (root.is_file() or root.is_symlink()):
        root = root.parent
    if not root.exists():
        raise DatasetError(root, "folder", "a dataset folder containing dataset.yaml", "no such folder")
    if not root.is_dir():
        raise DatasetError(root, "folder", "a dataset folder containing dataset.yaml", "not a folder")
    yaml_file = root / "dataset.yaml"
    if not yaml_file.exists() and not yaml_file.is_symlink():
        raise DatasetError(yaml_file, "file", f"dataset.yaml (required by {FORMAT})", "missing")
    _check_dataset_file(root, yaml_file)
    return root


def _check_dataset_file(root: Path, f: Path) -> None:
    """A file of the dataset folder ``root`` (dataset.yaml, a CSV file): a regular file, and a link
    only to a file inside the folder (a link leading out would let a dataset read, and a message
    show, any file of the machine); DatasetError naming it otherwise. A FIFO or device is refused
    here, unopened (reading one would block forever)."""
    if f.is_symlink():
        try:
            path_inside(root, f.name, f, "file")
        except DatasetError:
            raise DatasetError(f, "file", "a file of the dataset folder, or a link to one inside it",
                               "a link leading out of the dataset folder") from None
    try:
        check_regular_file(f)
    except OSError as exc:
        raise DatasetError(f, "file", f"a regular file ({f.name} of the dataset)", exc.strerror or str(exc)) from None


def read_dataset_parts(path: str | Path, *, keep_unit_slips: bool = False
                       ) -> tuple[Dataset, object | None, dict[str, ParsedCsv], set[Path]]:
    """:func:`read_dataset` and what it found on the way: ``(dataset, robot, parsed, referenced)``
    with the loaded :class:`~graphcal.models.robot.RobotModel` (None without a robot), the CSV files
    read by kind (rows with their file lines) and the cloud files named in timeseries.csv.
    ``keep_unit_slips``: see :func:`read_dataset`."""
    root = _dataset_root(path)
    yaml_file = root / "dataset.yaml"
    header = parse_dataset_yaml(yaml_file)
    if header.robot is not None and header.robot.urdf is not None:
        urdf = path_inside(root, header.robot.urdf, yaml_file, "robot.urdf")
        if not urdf.exists():
            raise DatasetError(yaml_file, "robot.urdf", "an existing URDF file inside the dataset folder",
                               f"{header.robot.urdf} (no such file)")  # fmt: skip
        try:
            check_regular_file(urdf)
        except OSError as exc:
            raise DatasetError(yaml_file, "robot.urdf", "a URDF file (a regular file)",
                               f"{header.robot.urdf}: {exc.strerror}") from None  # fmt: skip

    robot = None
    if header.robot is not None:
        robot = load_robot_spec(root, header.robot, yaml_file)
        frames = set(robot.frame_names)
        for name, m in header.mocap_markers.items():
            if m.link not in frames:
                raise DatasetError(yaml_file, f"mocap.markers.{name}.link", "a frame of the URDF",
                                   f"{m.link!r}{did_you_mean(m.link, frames)}")  # fmt: skip

    parsed: dict[str, ParsedCsv] = {}
    for kind, name in CSV_FILES.items():
        f = root / name
        if f.exists() or f.is_symlink():
            _check_dataset_file(root, f)
            parsed[kind] = read_csv(f, kind)
            check_magnitudes(parsed[kind])
    if "stations" not in parsed and "timeseries" not in parsed:
        raise DatasetError(root, "files", "stations.csv or timeseries.csv (or both)", "neither")
    check_joint_columns(robot, parsed)

    station_ids = None
    if "stations" in parsed:
        check_stations(parsed["stations"])
        station_ids = parsed["stations"].table["station"]
    referenced: set[Path] = set()
    if "timeseries" in parsed:
        referenced = check_timeseries(parsed["timeseries"], header, root)
    if "planes" in parsed:
        check_planes(parsed["planes"], header, station_ids, keep_unit_slips=keep_unit_slips)
    if "mocap" in parsed:
        times = [
            parsed[k].table["time"] for k in ("stations", "timeseries") if k in parsed and parsed[k].table.has("time")
        ]
        check_mocap(parsed["mocap"], header, np.concatenate(times) if times else None)
    if "mocap_poses" in parsed:
        times = [
            parsed[k].table["time"] for k in ("stations", "timeseries") if k in parsed and parsed[k].table.has("time")
        ]
        check_mocap_poses(parsed["mocap_poses"], header, np.concatenate(times) if times else None)
    station_clouds(root, header.sensors, station_ids, referenced)

    ds = Dataset(
        root=root,
        format=header.format,
        robot=header.robot,
        sensors=header.sensors,
        imu=header.imu,
        ground=header.ground,
        stance=header.stance,
        extra=header.extra,
        stations=parsed["stations"].table if "stations" in parsed else None,
        timeseries=parsed["timeseries"].table if "timeseries" in parsed else None,
        planes=parsed["planes"].table if "planes" in parsed else None,
        mocap=parsed["mocap"].table if "mocap" in parsed else None,
        mocap_markers=header.mocap_markers,
        mocap_poses=parsed["mocap_poses"].table if "mocap_poses" in parsed else None,
        mocap_noise=header.mocap_noise,
    )
    return ds, robot, parsed, referenced


def read_dataset(path: str | Path, *, keep_unit_slips: bool = False) -> Dataset:
    """Read and check a ``graphcal-dataset/1`` folder (or its ``dataset.yaml``).

    Checks everything in docs/dataset.md except the points inside the PLY files (their names,
    sensors, stations and locations are checked; :func:`~graphcal.io.dataset.validate.validate_dataset` reads them). The robot
    is loaded to check joint columns, feet and marker links.

    Args:
        path: the folder or its dataset.yaml.
        keep_unit_slips: keep a few planes.csv rows whose distance looks like millimetres (a
            warning each time; :func:`~graphcal.io.dataset.checks.check_planes`): only ``graphcal
            diagnose`` asks for it, to name and correct them; every other command refuses them.

    Returns:
        The :class:`Dataset`, SI units.

    Raises:
        DatasetError: the first problem found, naming file, row or key, and what was expected.
    """
    return read_dataset_parts(path, keep_unit_slips=keep_unit_slips)[0]
