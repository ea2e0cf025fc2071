"""``graphcal extract-planes DATASET``: fit planes to a dataset's clouds and write ``planes.csv``
(:mod:`graphcal.clouds.plane_table`)."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from graphcal.clouds.plane_table import (camera_clouds_without_planes, check_max_points, no_plane_found_warning,
                                         planes_rows)
from graphcal.errors import DatasetError, GraphcalError
from graphcal.io.atomic import atomic_write_text, check_output_location, make_parent_folder
from graphcal.io.dataset import Table, cloud_paths, load_cloud, read_dataset, table_csv_text

__all__ = ["run"]


def run(dataset: str | Path, out: str | Path | None = None, *, max_planes: int = 1,
        progress: bool = False, max_points: int | None = None) -> str:
    """Read a dataset's clouds, fit planes, and write ``planes.csv`` atomically; returns the summary
    (a ``warning:`` line per camera with clouds in which no plane was found, then ``wrote OUT``).

    ``out`` defaults to ``DATASET/planes.csv``; an existing file is never replaced (give another
    ``out``); a missing parent folder is created. ``max_points``: fit each cloud on at most this
    many of its points (:func:`graphcal.clouds.plane_table.planes_rows`; None: all), as
    ``graphcal calibrate --plane-points`` does.
    """
    max_points = check_max_points(max_points, "max_points (--plane-points)")
    if isinstance(max_planes, bool) or not isinstance(max_planes, (int, np.integer)) or max_planes < 1:
        raise GraphcalError(f"max_planes (--max-planes) must be a whole number >= 1, got {max_planes!r}")
    ds = read_dataset(dataset)
    out_path = Path(out) if out is not None else Path(dataset) / "planes.csv"
    if out_path.exists():
        raise DatasetError(out_path, "--out", "a file that does not exist yet (graphcal never overwrites it); "
                           "pass --out to write elsewhere")
    check_output_location(out_path)  # before the work
    paths = cloud_paths(ds)
    if not paths:
        raise DatasetError(Path(dataset) / "clouds", "clouds/<sensor>/<station>.ply", "at least one station cloud")
    types = {name: spec.type for name, spec in ds.sensors.items()}
    pairs = [(key, functools.partial(load_cloud, ds, *key)) for key in sorted(paths)]  # read by the workers
    rows = planes_rows(pairs, types, max_planes=max_planes, progress=progress, max_points=max_points)
    have = zip(rows["sensor"], rows["station"])
    lines = [f"warning: {no_plane_found_warning(sensor, missing, total, 'the planes file has no row for them')}"
             for sensor, (missing, total) in camera_clouds_without_planes(ds, have).items()]
    make_parent_folder(out_path)
    atomic_write_text(out_path, table_csv_text(Table.from_columns(rows)), overwrite=False)
    lines.append(f"wrote {out_path}")
    return "\n".join(lines)
