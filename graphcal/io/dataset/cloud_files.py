"""The point clouds of a dataset: the ``clouds/<sensor>/<station>.ply`` files found and checked
(names, sensors, stations, links), one read with its unit check, and the laser scanner's
scan-plane check."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from graphcal.errors import DatasetError
from graphcal.io.dataset.model import (
    MIN_CLOUD_MEDIAN_M,
    MM_LIMIT_CLOUD_MEDIAN_M,
    SCAN_PLANE_MAX_Z_M,
    Dataset,
    SensorSpec,
)
from graphcal.io.dataset.paths import path_inside, resolved_or_none
from graphcal.io.dataset.text import MILLIMETRES_HINT
from graphcal.io.ply import read_ply


def station_clouds(
    root: Path, sensors: Mapping[str, SensorSpec], station_ids: np.ndarray | None, referenced: set[Path]
) -> dict[tuple[str, int], Path]:
    """(sensor, station) -> path of every ``clouds/<sensor>/<station>.ply`` of the dataset folder
    ``root``; checks names and links. ``sensors``: those of dataset.yaml; ``station_ids``: those of
    stations.csv (None without it); ``referenced``: the clouds named in timeseries.csv (allowed in
    clouds/ under other names)."""
    cdir = root / "clouds"
    out: dict[tuple[str, int], Path] = {}
    if not cdir.exists() and not cdir.is_symlink():
        return out
    if not cdir.is_dir():
        raise DatasetError(cdir, "file", "a folder clouds/<sensor>/<station>.ply", "not a folder")
    try:
        root_res = root.resolve()
    except (OSError, RuntimeError):
        root_res = None  # path_inside then reports the folder
    path_inside(root, "clouds", cdir, "folder", root_resolved=root_res)
    ids = set(station_ids.tolist()) if station_ids is not None else set()
    ref_resolved = {p.resolve() for p in referenced}
    for sdir in sorted(cdir.iterdir()):
        if sdir.name.startswith(".") or not sdir.is_dir():
            continue
        plys = sorted(
            f for f in sdir.iterdir()
            if f.suffix.lower() == ".ply" and not f.name.startswith(".") and not (f.is_dir() and not f.is_symlink())
        )  # fmt: skip
        for f in plys:  # a FIFO or device named .ply: refused by name, never opened (a read would block)
            if not f.is_symlink() and not f.is_file():
                raise DatasetError(f, "file", "a PLY file (a regular file)", "a named pipe, device or socket")
        # a file that is no link resolves within its folder: one resolve per folder, not per file
        sdir_res = sdir.resolve()
        resolved = {f: resolved_or_none(f) if f.is_symlink() else sdir_res / f.name for f in plys}
        if sdir.name not in sensors:
            if plys and not all(resolved[f] in ref_resolved for f in plys):
                raise DatasetError(sdir, "folder", f"a folder named after a sensor of dataset.yaml "
                                   f"({', '.join(sensors) or 'none'})", sdir.name)  # fmt: skip
            continue
        for f in plys:
            rel = f"clouds/{sdir.name}/{f.name}"
            path_inside(root, rel, f, "file", root_resolved=root_res, resolved=resolved[f])
            stem = f.stem
            sid = int(stem) if re.fullmatch(r"[+-]?[0-9]+", stem) else None
            if sid is not None and sid in ids:
                if (sdir.name, sid) in out:
                    other = out[(sdir.name, sid)].name
                    raise DatasetError(f, "file", "one cloud per station", f"{other} and {f.name} for station {sid}")
                out[(sdir.name, sid)] = f
            elif resolved[f] not in ref_resolved:
                expected = "<station>.ply with a station id of stations.csv"
                got = f"{f.name} ({'no stations.csv' if station_ids is None else 'no such station'})"
                if sid is None or station_ids is None:
                    expected += f", or a cloud named in a cloud_{sdir.name} cell of timeseries.csv"
                    if station_ids is None:
                        got = f"{f.name} (no stations.csv, and no row of timeseries.csv names it)"
                raise DatasetError(f, "file name", expected, got)
    return out


def cloud_paths(ds: Dataset) -> dict[tuple[str, int], Path]:
    """``(sensor, station) -> path`` of every station cloud ``clouds/<sensor>/<station>.ply`` of a
    dataset read from a folder (the timeseries' clouds are in its ``cloud_<sensor>`` columns)."""
    if ds.root is None:
        return {}
    ids = ds.stations["station"] if ds.stations is not None else None
    referenced: set[Path] = set()
    if ds.timeseries is not None:
        for s in ds.timeseries.suffixes("cloud_"):
            referenced.update(ds.root / r.replace("\\", "/") for r in ds.timeseries[f"cloud_{s}"].tolist() if r)
    return station_clouds(ds.root, ds.sensors, ids, referenced)


def load_cloud(ds: Dataset, sensor: str, station: int) -> np.ndarray:
    """Points ``(N, 3)`` of station ``station`` seen by ``sensor``, in the sensor frame, metres.

    Raises:
        DatasetError: no such cloud, an unreadable or empty PLY, non-finite points, or points that
            look like millimetres (median range above 100 m).
    """
    if ds.root is None:
        raise ValueError("load_cloud needs a dataset read from a folder (ds.root is None)")
    station = int(station)
    path = ds.root / "clouds" / sensor / f"{station}.ply"
    if path.is_file():
        path_inside(ds.root, f"clouds/{sensor}/{station}.ply", path, "file")
    else:  # another spelling of the id, e.g. 007.ply
        found = cloud_paths(ds).get((sensor, station))
        if found is None:
            raise DatasetError(path, "file", f"the cloud of station {station} seen by sensor {sensor!r}",
                               "no such file")  # fmt: skip
        path = found
    return read_cloud(path)


def read_cloud(path: Path) -> np.ndarray:
    """The points ``(N, 3)`` (sensor frame, m) of the PLY file ``path``; DatasetError if unreadable,
    empty, non-finite, in millimetres (median range above :data:`MM_LIMIT_CLOUD_MEDIAN_M`), huddled
    at the sensor origin (median range below :data:`MIN_CLOUD_MEDIAN_M`) or one point repeated."""
    pts = read_ply(path)
    sample = pts[:: max(1, len(pts) // 20000)]  # the unit check needs no more than ~20k points
    med = float(np.median(np.sqrt(np.einsum("ij,ij->i", sample, sample))))
    if med > MM_LIMIT_CLOUD_MEDIAN_M:
        raise DatasetError(path, "points", f"metres (median range <= {MM_LIMIT_CLOUD_MEDIAN_M:g} m); {MILLIMETRES_HINT}",
                           f"median range {med:.4g}")
    if med < MIN_CLOUD_MEDIAN_M:
        raise DatasetError(path, "points", f"metres (median range >= {MIN_CLOUD_MEDIAN_M:g} m: a sensor does not "
                           "measure its points at its own origin)", f"median range {med:.4g}")
    if len(pts) > 1 and not (pts != pts[0]).any():
        raise DatasetError(path, "points", "points spread over what the sensor saw (a sensor does not measure "
                           f"one point {len(pts)} times)", f"{len(pts)} copies of {pts[0].tolist()}")
    return pts


def scan_off_plane_m(points: np.ndarray) -> float:
    """How far a laser scanner's points ``(N, 3)`` (sensor frame, m) lie off its scan plane z = 0:
    the 90th percentile of |z| (m; 0 for a 2-D scan; the range noise of a 2-D scanner lies along
    its beams, in that plane)."""
    z = np.abs(np.asarray(points, dtype=float)[:, 2])
    return float(np.percentile(z, 90)) if len(z) else 0.0


def off_plane_scan_warning(sensor: str, off: Sequence[tuple[str, float]], n_clouds: int) -> str:
    """The warning for laser scanner ``sensor`` whose clouds ``off`` ((file, 90th percentile of |z|
    in m), at least one) of ``n_clouds`` lie off its scan plane (:data:`SCAN_PLANE_MAX_Z_M`)."""
    file, z90 = max(off, key=lambda x: x[1])
    return (f"sensor {sensor!r} is a laser_scanner, but {len(off)} of its {n_clouds} clouds do not lie in "
            f"its scan plane z = 0 (90% of |z| within {1e3 * SCAN_PLANE_MAX_Z_M:g} mm; {file}: "
            f"{1e3 * z90:.0f} mm): a 3-D cloud (a depth camera: type depth_camera) or a scan in another "
            "frame. A laser scanner's points are read as one scan line in the sensor's x-y plane")
