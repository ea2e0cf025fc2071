"""The graphcal dataset contract, ``graphcal-dataset/1``: dataclasses, reader, writer, validator.

A folder with ``dataset.yaml``, ``stations.csv`` and/or ``timeseries.csv``, optionally
``planes.csv``, ``mocap.csv``, ``clouds/<sensor>/<station>.ply`` and a URDF. Inside graphcal
everything is SI (m, rad, s); the only non-SI values are ``dataset.yaml`` keys whose name says so
(``rpy_deg``, ``sigma_rpy_deg``, ``sigma_mm``), converted on reading and writing.
:func:`read_dataset` parses and checks a dataset (all but the points in the PLY files),
:func:`validate_dataset` also reads every cloud, :func:`write_dataset` writes atomically and reads
the result back; every problem is one :class:`~graphcal.errors.DatasetError`.

One module per job (text, model, paths, schema, tables, checks, cloud_files, robot, read, validate,
write), their public names re-exported here. The contract, every check, the API: docs/dataset.md.
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
