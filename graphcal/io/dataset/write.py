"""Writing a dataset: :func:`write_dataset` writes a :class:`Dataset` atomically (a folder appears
complete or not at all) and reads it back before committing it."""

from __future__ import annotations

import shutil
from pathlib import Path, PurePosixPath
from typing import Any, Mapping

import numpy as np

from graphcal.errors import DatasetError
from graphcal.io.atomic import atomic_directory, atomic_write_bytes, atomic_write_text
from graphcal.io.dataset.cloud_files import cloud_paths
from graphcal.io.dataset.model import FORMAT, Dataset
from graphcal.io.dataset.paths import path_inside
from graphcal.io.dataset.read import read_dataset_parts
from graphcal.io.dataset.schema import dataset_yaml_text
from graphcal.io.dataset.tables import check_table_text, table_csv_text
from graphcal.io.ply import write_ply

#: the names at the top of a dataset folder that only the contract's files may take
_RESERVED = {"dataset.yaml", "stations.csv", "timeseries.csv", "planes.csv", "mocap.csv", "mocap_poses.csv", "clouds"}


def write_dataset(
    ds: Dataset,
    out_dir: str | Path,
    *,
    clouds: Mapping[tuple[str, int], Any] | None = None,
    robot_urdf_xml: str | None = None,
    overwrite: bool = False,
    extra_files: Mapping[str, str | bytes] | None = None,
    timeseries_clouds: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``ds`` as a ``graphcal-dataset/1`` folder ``out_dir``, atomically.

    Args:
        ds: the dataset (SI units). ``ds.root``, if set, is where files not given here come from:
            the URDF, the station clouds not in ``clouds`` (for stations and sensors of ``ds``) and
            the clouds named in the timeseries' ``cloud_<sensor>`` columns (copied byte for byte).
        out_dir: the folder to create. An existing non-empty folder is refused unless ``overwrite``.
        clouds: ``(sensor, station) -> (N, 3)`` points in the sensor frame (m), written as binary
            PLY ``clouds/<sensor>/<station>.ply`` (exact float64).
        robot_urdf_xml: URDF text written to ``ds.robot.urdf`` (required when ``ds.robot.urdf`` is
            set and ``ds.root`` does not hold it).
        overwrite: replace an existing non-empty ``out_dir`` (the old one is deleted only after the
            new one is in place).
        extra_files: more files to put in the folder (relative name -> text or bytes), e.g.
            ``{"truth.yaml": ...}``; they must not collide with the contract's files.
        timeseries_clouds: relative PLY path (as named in a ``cloud_<sensor>`` column of the
            timeseries) -> (N, 3) points in that sensor's frame (m), written as binary PLY.

    ``dataset.yaml`` is written with ``xyz`` in metres and ``rpy_deg``, ``sigma_mm``,
    ``sigma_rpy_deg``, as the contract says; each such number is the shortest decimal that
    converts back to the exact SI value when there is one (otherwise it is 1 ulp off). CSV numbers
    are written with Python's shortest ``repr``, so they read back bit for bit.

    The folder is built next to ``out_dir`` and read back with
    :func:`~graphcal.io.dataset.read.read_dataset` before it is renamed into place: what cannot be
    read is not written.

    Returns:
        ``out_dir`` as a Path.

    Raises:
        DatasetError: ``ds`` or the clouds would make a dataset graphcal refuses (the message
            names the file, marked "(not written)").
        OutputExistsError: ``out_dir`` exists and is not empty, and ``overwrite`` is False.
    """
    out = Path(out_dir)
    if ds.format != FORMAT:
        raise ValueError(f"write_dataset writes {FORMAT}, got Dataset.format={ds.format!r}")
    if ds.stations is None and ds.timeseries is None:
        raise DatasetError(out, "files", "a dataset with stations or a timeseries (or both)", "neither")
    yaml_text = dataset_yaml_text(ds, out)
    urdf_rel, urdf_bytes = _urdf_to_write(ds, out, robot_urdf_xml)
    station_ids = set(ds.stations["station"].tolist()) if ds.stations is not None else set()
    new_clouds = _station_clouds_to_write(ds, out, clouds or {}, station_ids)
    new_ts_clouds = _timeseries_clouds_to_write(ds, out, timeseries_clouds or {})
    copies = _clouds_to_copy(ds, new_clouds, new_ts_clouds, station_ids)
    for name in extra_files or {}:
        top = PurePosixPath(name.replace("\\", "/")).parts[0] if name else ""
        if not name or top in _RESERVED or (urdf_rel and name.replace("\\", "/") == urdf_rel):
            raise ValueError(f"extra_files: {name!r} collides with a file of the dataset")

    with atomic_directory(out, overwrite=overwrite) as tmp:

        def dest(rel: str) -> Path:
            p = path_inside(tmp, rel, f"{out / rel} (not written)", "path")
            p.parent.mkdir(parents=True, exist_ok=True)
            return p

        atomic_write_text(tmp / "dataset.yaml", yaml_text)
        for name, t in (("stations.csv", ds.stations), ("timeseries.csv", ds.timeseries),
                        ("planes.csv", ds.planes), ("mocap.csv", ds.mocap), ("mocap_poses.csv", ds.mocap_poses)):  # fmt: skip
            if t is not None:
                check_table_text(t, f"{out / name} (not written)")
                atomic_write_text(tmp / name, table_csv_text(t))
        if urdf_rel is not None:
            atomic_write_bytes(dest(urdf_rel), urdf_bytes)
        for (sensor, station), a in new_clouds.items():
            write_ply(dest(f"clouds/{sensor}/{station}.ply"), a, binary=True)
        for rel, a in new_ts_clouds.items():
            write_ply(dest(rel), a, binary=True)
        for rel, src in copies.items():
            target = dest(rel)
            if not target.exists():
                try:
                    shutil.copyfile(src, target)
                except OSError as exc:
                    raise DatasetError(f"{out / rel} (not written)", "file", f"a copy of {src}",
                                       exc.strerror or str(exc)) from None  # fmt: skip
        for name, content in (extra_files or {}).items():
            data = content.encode("utf-8") if isinstance(content, str) else bytes(content)
            atomic_write_bytes(dest(name.replace("\\", "/")), data)
        try:
            read_dataset_parts(tmp)
        except DatasetError as exc:
            f = str(exc.file)
            f = str(out) + f[len(str(tmp)) :] if f.startswith(str(tmp)) else f
            raise DatasetError(f"{f} (not written)", exc.where, exc.expected, exc.got) from None
    return out


def _urdf_to_write(ds: Dataset, out: Path, robot_urdf_xml: str | None) -> tuple[str | None, bytes | None]:
    """``(path relative to the dataset folder, bytes)`` of the URDF to write (``(None, None)``: the
    robot is a built-in model or there is none): ``robot_urdf_xml``, else the file in ``ds.root``."""
    if ds.robot is not None and ds.robot.urdf is not None:
        urdf_rel = ds.robot.urdf.replace("\\", "/")
        if robot_urdf_xml is not None:
            return urdf_rel, robot_urdf_xml.encode("utf-8")
        if ds.root is not None and (ds.root / urdf_rel).is_file():
            return urdf_rel, (ds.root / urdf_rel).read_bytes()
        raise DatasetError(out / urdf_rel, "robot.urdf", "the URDF text (robot_urdf_xml=...) or a dataset "
                           "root that holds the file", "none given")  # fmt: skip
    if robot_urdf_xml is not None:
        raise ValueError("robot_urdf_xml given but the dataset's robot does not name a URDF file (robot.urdf)")
    return None, None


def _points_to_write(pts: Any, target: str) -> np.ndarray:
    """``pts`` as a non-empty, finite ``(N, 3)`` float64 array (m); DatasetError naming ``target``
    (the file not written) otherwise."""
    a = np.asarray(pts, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or len(a) == 0:
        raise DatasetError(target, "points", "a non-empty (N, 3) array", f"shape {a.shape}")
    if not np.isfinite(a).all():
        raise DatasetError(target, "points", "finite coordinates", "nan or inf")
    return a


def _station_clouds_to_write(
    ds: Dataset, out: Path, clouds: Mapping[tuple[str, int], Any], station_ids: set[int]
) -> dict[tuple[str, int], np.ndarray]:
    """``clouds`` (``(sensor, station) -> (N, 3)`` points, sensor frame, m) checked against the
    sensors of ``ds`` and its ``station_ids``, keyed by ``(sensor, int station)``."""
    new_clouds: dict[tuple[str, int], np.ndarray] = {}
    for key, pts in clouds.items():
        sensor, station = key
        target = out / "clouds" / str(sensor) / f"{int(station)}.ply"
        if sensor not in ds.sensors:
            raise DatasetError(f"{target} (not written)", "clouds",
                               f"a sensor of the dataset ({', '.join(ds.sensors) or 'none'})", sensor)  # fmt: skip
        if int(station) not in station_ids:
            raise DatasetError(f"{target} (not written)", "clouds", "a station of stations", int(station))
        new_clouds[(sensor, int(station))] = _points_to_write(pts, f"{target} (not written)")
    return new_clouds


def _timeseries_clouds_to_write(
    ds: Dataset, out: Path, timeseries_clouds: Mapping[str, Any]
) -> dict[str, np.ndarray]:
    """``timeseries_clouds`` (relative path -> (N, 3) points, sensor frame, m) checked to be named in
    a ``cloud_<sensor>`` column of ``ds.timeseries``, keyed by the path with ``/``."""
    new_ts_clouds: dict[str, np.ndarray] = {}
    if not timeseries_clouds:
        return new_ts_clouds
    named = set()
    if ds.timeseries is not None:
        for s in ds.timeseries.suffixes("cloud_"):
            named |= {r.replace("\\", "/") for r in ds.timeseries[f"cloud_{s}"].tolist()} - {""}
    for rel, pts in timeseries_clouds.items():
        rel = str(rel).replace("\\", "/")
        target = f"{out / rel} (not written)"
        if rel not in named:
            raise DatasetError(target, "timeseries_clouds", "a cloud named in a cloud_<sensor> column of the "
                               "timeseries", rel)  # fmt: skip
        new_ts_clouds[rel] = _points_to_write(pts, target)
    return new_ts_clouds


def _clouds_to_copy(
    ds: Dataset,
    new_clouds: Mapping[tuple[str, int], np.ndarray],
    new_ts_clouds: Mapping[str, np.ndarray],
    station_ids: set[int],
) -> dict[str, Path]:
    """Relative destination -> source file of the clouds of ``ds.root`` (a dataset read from a
    folder) kept in the new one: those of its stations and sensors, and those its timeseries names,
    unless new points are given for them."""
    copies: dict[str, Path] = {}
    if ds.root is None:
        return copies
    for (sensor, station), src in cloud_paths(ds).items():
        if (sensor, station) not in new_clouds and station in station_ids and sensor in ds.sensors:
            copies[f"clouds/{sensor}/{station}.ply"] = src
    if ds.timeseries is not None:
        for s in ds.timeseries.suffixes("cloud_"):
            for rel in set(ds.timeseries[f"cloud_{s}"].tolist()) - {""}:
                rel = rel.replace("\\", "/")
                if rel not in new_ts_clouds:
                    copies[rel] = ds.root / rel
    return copies
