"""The graphcal dataset contract, ``graphcal-dataset/1``: dataclasses, reader, writer, validator.

The contract is documented in ``docs/dataset.md`` (layout, files, columns, units, every check
with an example message). In short: a folder with ``dataset.yaml`` (robot, sensor priors), one
or both of ``stations.csv`` (static stations) and ``timeseries.csv`` (samples), and optionally
``planes.csv``, ``mocap.csv``, ``clouds/<sensor>/<station>.ply`` and a URDF.

Inside graphcal everything is SI: metres, radians, seconds. The only non-SI values live in
``dataset.yaml`` keys whose name says so (``rpy_deg``, ``sigma_rpy_deg``, ``sigma_mm``); they are
converted on reading and writing.

* :func:`read_dataset` parses and checks a dataset (everything except the points inside the
  PLY files, whose names and locations it does check) and returns a :class:`Dataset`.
* :func:`validate_dataset` does the same, then reads every cloud, and returns counts and warnings
  (:class:`ValidationReport`).
* :func:`write_dataset` writes a :class:`Dataset` atomically (a folder appears complete or not at
  all); it reads the result back before committing it, so it never produces a dataset graphcal
  would refuse.

Every problem is one :class:`~graphcal.errors.DatasetError` naming the file, the row (``row k``
is the k-th data row, 1-based, not counting the header; ``line n`` is the line of the file as a
text editor numbers it, so ``line = row + 1`` for a file without blank or multi-line rows) or
the key (``sensors.depth.T_body_sensor_prior.xyz``), and what was expected. Nothing is unpickled
or executed: YAML is read with a subclass of ``yaml.SafeLoader``.

The modules, each one job (a module imports only those above it):

* ``text``: a file's bytes decoded; the pieces of messages.
* ``model``: the contract's constants and frozen dataclasses.
* ``paths``: paths written in the files, kept inside the dataset folder.
* ``schema``: ``dataset.yaml``, its keys and types, read and written.
* ``tables``: the CSV files read (header, cells) and written (``table_csv_text``).
* ``checks``: the value checks of each CSV file.
* ``cloud_files``: the ``clouds/`` files found, checked and read.
* ``robot``: the robot of ``dataset.yaml`` loaded (``load_dataset_robot``).
* ``read``: ``read_dataset``.
* ``validate``: ``validate_dataset``, ``ValidationReport``.
* ``write``: ``write_dataset``.

This file re-exports the public names, so ``from graphcal.io.dataset import X`` works for each.
"""

from graphcal.io.dataset.cloud_files import cloud_paths, load_cloud, off_plane_scan_warning, scan_off_plane_m
from graphcal.io.dataset.model import (
    BODY_POSE_COLUMNS,
    FEET_FIXED_WITHIN,
    FEET_REPLANTED_AT_EACH_STATION,
    FORMAT,
    IMU_ACCEL_COLUMNS,
    IMU_GYRO_COLUMNS,
    MM_LIMIT_BODY_M,
    MM_LIMIT_CLOUD_MEDIAN_M,
    MM_LIMIT_MOCAP_M,
    MM_LIMIT_PLANE_D_M,
    MM_LIMIT_PRIOR_M,
    MOCAP_COLUMNS,
    PLANE_COV_COLUMNS,
    PLANE_REQUIRED_COLUMNS,
    SCAN_PLANE_MAX_Z_M,
    SENSOR_TYPES,
    UNIT_NORM_TOL,
    Dataset,
    ImuSpec,
    MarkerSpec,
    PosePrior,
    RobotSpec,
    SensorSpec,
    Table,
    is_string_column,
)
from graphcal.io.dataset.paths import shown_path
from graphcal.io.dataset.read import read_dataset
from graphcal.io.dataset.robot import load_dataset_robot
from graphcal.io.dataset.tables import table_csv_text
from graphcal.io.dataset.validate import ValidationReport, validate_dataset
from graphcal.io.dataset.write import write_dataset

__all__ = [
    "FORMAT",
    "SENSOR_TYPES",
    "BODY_POSE_COLUMNS",
    "IMU_ACCEL_COLUMNS",
    "IMU_GYRO_COLUMNS",
    "PLANE_REQUIRED_COLUMNS",
    "PLANE_COV_COLUMNS",
    "MOCAP_COLUMNS",
    "UNIT_NORM_TOL",
    "MM_LIMIT_BODY_M",
    "MM_LIMIT_PRIOR_M",
    "MM_LIMIT_PLANE_D_M",
    "MM_LIMIT_MOCAP_M",
    "MM_LIMIT_CLOUD_MEDIAN_M",
    "SCAN_PLANE_MAX_Z_M",
    "FEET_FIXED_WITHIN",
    "FEET_REPLANTED_AT_EACH_STATION",
    "PosePrior",
    "RobotSpec",
    "SensorSpec",
    "ImuSpec",
    "MarkerSpec",
    "Table",
    "Dataset",
    "ValidationReport",
    "read_dataset",
    "write_dataset",
    "validate_dataset",
    "load_cloud",
    "cloud_paths",
    "load_dataset_robot",
    "is_string_column",
    "table_csv_text",
    "shown_path",
    "scan_off_plane_m",
    "off_plane_scan_warning",
]
