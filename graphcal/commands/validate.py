"""``graphcal validate DATASET``: check a dataset against the contract (docs/dataset.md)."""

from __future__ import annotations

from pathlib import Path

from graphcal.io.dataset import validate_dataset

__all__ = ["run"]


def run(dataset: str | Path) -> str:
    """Validate the dataset folder ``dataset``; returns the report's summary. Bad input raises
    :class:`~graphcal.errors.DatasetError` naming the file and field."""
    return validate_dataset(dataset).summary()
