"""``graphcal import LOG --out DATASET``: a robot log (ROS 1 bag, ROS 2 bag in sqlite3 or MCAP, bare
MCAP, CSV export with a column map) becomes a dataset folder, written atomically, with the import
map (``import_map.yaml``) and the import report (``import_report.yaml``) beside it (docs/import.md)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from graphcal.commands.result import folder_files
from graphcal.errors import DatasetError
from graphcal.io.atomic import check_output_location
from graphcal.logs.reader import log_kind

__all__ = ["run", "ImportResult"]


@dataclass(frozen=True)
class ImportResult:
    """What ``graphcal import`` wrote.

    Attributes:
        out: the dataset folder written.
        report: import_report.yaml's document (the stations found, the windows rejected and why,
            the clock jumps, the notes).
        files: the dataset folder's entries (dataset.yaml, stations.csv, clouds, import_map.yaml,
            import_report.yaml, ...).
        warnings: the clock jumps found in the log.
        summary: the import's own summary (:func:`graphcal.logs.assemble.write_imported`).
        verdict: none (None).
    """

    out: Path
    report: dict
    files: tuple[Path, ...]
    warnings: tuple[str, ...]
    summary: str
    verdict: str | None = None

    @property
    def n_stations(self) -> int:
        """Stations written (still windows with every foot loaded and a cloud of every sensor)."""
        return len(self.report.get("stations", []))

    @property
    def n_rejected(self) -> int:
        """Still windows rejected (each with its reason in ``report["rejected"]``)."""
        return len(self.report.get("rejected", []))

    def summary_text(self) -> str:
        return self.summary


def _result(out: Path, summary: str) -> ImportResult:
    import yaml

    report = yaml.safe_load((out / "import_report.yaml").read_text(encoding="utf-8"))
    return ImportResult(out=out, report=report, files=folder_files(out), warnings=tuple(report.get("clock", [])),
                        summary=summary)


def run(log: str | Path, out_dir: str | Path, *, map_path: str | Path | None = None, urdf: str | Path | None = None,
        receive_time: bool = False, msg_dir: str | Path | None = None, timeseries: bool = False,
        progress: bool = True, overwrite: bool = False, cloud_rate_hz: float | None = None) -> ImportResult:
    """The ``graphcal import`` command; returns an :class:`ImportResult`.

    Args:
        log: the log: a ``.bag`` file, a ROS 2 bag folder, a ``.mcap`` file, a ``.csv`` file, or a
            folder of IMU and body-frame foot points (``imu.csv``, ``contacts.csv``, ``metadata.csv``:
            :mod:`graphcal.logs.foot_points`).
        out_dir: the dataset folder to write (must not exist or be empty unless ``overwrite``).
        map_path: an import map (``import_map.yaml`` of an earlier import, edited); required for CSV.
        urdf: the robot's URDF file (instead of the log's ``/robot_description``).
        receive_time: time messages by their receive (log) time instead of their header stamps.
        msg_dir: a folder of ``.msg`` definitions for message types rosbags does not know.
        timeseries: also write ``timeseries.csv`` (every joint sample; memory grows with the log)
            and, from a bag, the clouds along the walk (``cloud_<sensor>`` cells).
        cloud_rate_hz: with ``timeseries``, the rate (Hz) the bag's depth images / PointCloud2
            messages along the walk are thinned to (None: 5 Hz; 0: none). Ignored for CSV logs
            and foot-point folders (no clouds).
        progress: tqdm progress bars.
        overwrite: replace an existing dataset folder.
    """
    log, out_dir = Path(log), Path(out_dir)
    check_output_location(out_dir)
    from graphcal.logs.foot_points import import_foot_points, is_foot_point_folder

    if is_foot_point_folder(log):  # IMU and body-frame foot points (GTSAM's legged sample's form)
        out, summary = import_foot_points(log, out_dir, overwrite=overwrite)
        return _result(Path(out), summary)
    kind = log_kind(log)
    if kind == "csv":
        from graphcal.logs.csv_log import import_csv

        if map_path is None:
            raise DatasetError(log, "--map", "a column map YAML for a CSV log (docs/import.md)", None)
        out, summary = import_csv(log, out_dir, map_path=Path(map_path), urdf_file=Path(urdf) if urdf else None,
                                  timeseries=timeseries, progress=progress, overwrite=overwrite)
        return _result(Path(out), summary)
    from graphcal.logs.bag import import_bag

    out, summary = import_bag(log, out_dir, map_path=Path(map_path) if map_path else None,
                              urdf_file=Path(urdf) if urdf else None, receive_time=receive_time,
                              msg_dir=Path(msg_dir) if msg_dir else None, timeseries=timeseries,
                              progress=progress, overwrite=overwrite,
                              **({} if cloud_rate_hz is None else {"cloud_rate_hz": float(cloud_rate_hz)}))
    return _result(Path(out), summary)
