"""``graphcal validate DATASET``: check a dataset against the contract (docs/dataset.md)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from graphcal.io.dataset import validate_dataset
from graphcal.io.dataset.validate import ValidationReport

__all__ = ["run", "ValidateResult", "command_warnings"]


def command_warnings(report) -> tuple[str, ...]:
    """What the commands will refuse in a dataset the contract allows (``report``: a
    :class:`~graphcal.io.dataset.validate.ValidationReport`): stations without any sensor (a robot
    without camera or laser) give calibrate, diagnose and suggest-poses nothing to work on."""
    if report.n_sensors == 0 and report.n_stations > 0 and report.n_mocap_rows == 0:
        return ("stations but no sensor in dataset.yaml: calibrate, diagnose and suggest-poses need at least one "
                "camera or laser scanner and refuse this dataset (a leg measured by motion capture: mocap.csv, "
                "identify-legs)",)
    return ()


@dataclass(frozen=True)
class ValidateResult:
    """What ``graphcal validate`` found (bad input raises instead: a valid dataset only).

    Attributes:
        report: the library's :class:`~graphcal.io.dataset.validate.ValidationReport`, with the
            warnings of :func:`command_warnings` added.
        files: nothing is written (empty).
        warnings: the report's warnings.
        verdict: ``valid``.
    """

    report: ValidationReport
    files: tuple[Path, ...] = ()
    verdict: str | None = "valid"

    @property
    def warnings(self) -> tuple[str, ...]:
        return tuple(self.report.warnings)

    def summary_text(self) -> str:
        """The report's summary (:meth:`~graphcal.io.dataset.validate.ValidationReport.summary`)."""
        return self.report.summary()


def run(dataset: str | Path) -> ValidateResult:
    """Validate the dataset folder ``dataset``; returns a :class:`ValidateResult` (its report with a
    warning for what the commands would refuse, :func:`command_warnings`). Bad input raises
    :class:`~graphcal.errors.DatasetError` naming the file and field."""
    report = validate_dataset(dataset)
    extra = command_warnings(report)
    if extra:
        report = dataclasses.replace(report, warnings=tuple(report.warnings) + extra)
    return ValidateResult(report=report)
