"""Files: atomic writes, point clouds (PLY) and the dataset contract (``graphcal-dataset/1``)."""

from graphcal.io.atomic import OutputExistsError, atomic_directory, atomic_write_bytes, atomic_write_text
from graphcal.io.dataset import (
    FORMAT,
    Dataset,
    ImuSpec,
    MarkerSpec,
    PosePrior,
    RobotSpec,
    SensorSpec,
    Table,
    ValidationReport,
    cloud_paths,
    load_cloud,
    load_dataset_robot,
    read_dataset,
    validate_dataset,
    write_dataset,
)
from graphcal.io.ply import read_ply, write_ply

__all__ = [
    "OutputExistsError",
    "atomic_directory",
    "atomic_write_bytes",
    "atomic_write_text",
    "FORMAT",
    "Dataset",
    "ImuSpec",
    "MarkerSpec",
    "PosePrior",
    "RobotSpec",
    "SensorSpec",
    "Table",
    "ValidationReport",
    "cloud_paths",
    "load_cloud",
    "load_dataset_robot",
    "read_dataset",
    "validate_dataset",
    "write_dataset",
    "read_ply",
    "write_ply",
]
