"""``graphcal extract-planes DATASET``: fit planes to a dataset's clouds and write ``planes.csv``
(:mod:`graphcal.clouds.plane_table`).

Where it writes (nothing the user has is ever lost):

* ``--out FILE``: there; an existing FILE is refused unless ``--overwrite``.
* no ``--out``: ``DATASET/planes.csv`` when the dataset has none; when it has one (every simulated
  dataset does), beside it as ``DATASET/planes-extracted.csv`` (refused if that exists too), and the
  summary says how to use it. ``--overwrite`` replaces ``DATASET/planes.csv`` instead.
* whatever ``--overwrite`` replaces is first kept as ``NAME.bak`` (``NAME.bak-2``, ... when taken).
"""

from __future__ import annotations

import functools
import os
import shutil
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from graphcal.clouds.plane_table import camera_clouds_without_planes, check_max_points, no_plane_found_warning, planes_rows
from graphcal.errors import DatasetError, GraphcalError
from graphcal.io.atomic import atomic_write_text, check_output_location, make_parent_folder
from graphcal.io.dataset import Dataset, Table, cloud_paths, load_cloud, read_dataset, table_csv_text
from graphcal.models.sensors import sensor_type

__all__ = ["run", "ExtractPlanesResult", "EXTRACTED_NAME", "output_path", "summary_lines"]

#: the file written beside a dataset's own planes.csv when no --out is given
EXTRACTED_NAME = "planes-extracted.csv"


def output_path(dataset: Path, out: Path | None, overwrite: bool) -> Path:
    """The file to write (see the module docstring); DatasetError when it exists and may not be replaced."""
    if out is not None:
        target = Path(out)
    else:
        target = dataset / "planes.csv"
        if target.exists() and not overwrite:
            target = dataset / EXTRACTED_NAME
    if (target.exists() or target.is_symlink()) and not overwrite:
        if out is None:
            raise DatasetError(target, "default output", "a file that does not exist yet (beside the dataset's own "
                               "planes.csv; graphcal never overwrites it): pass --out FILE, or --overwrite to replace "
                               "planes.csv (the old one is kept as planes.csv.bak)")
        raise DatasetError(target, "--out", "a file that does not exist yet (graphcal never overwrites it); pass "
                           "--out to write elsewhere, or --overwrite to replace it (the old one is kept as .bak)")
    if target.is_symlink() or (target.exists() and not target.is_file()):
        raise DatasetError(target, "--out", "a regular file (not a link or a folder) to replace")
    return target


def _keep_backup(path: Path) -> Path | None:
    """Keep the file ``path`` is about to replace as ``path.bak`` (or the first free ``.bak-N``)."""
    if not path.exists():
        return None
    bak = path.with_name(path.name + ".bak")
    n = 2
    while bak.exists() or bak.is_symlink():
        bak = path.with_name(f"{path.name}.bak-{n}")
        n += 1
    try:
        os.link(path, bak)  # the old content stays reachable under the new name; replaced atomically below
    except OSError:
        shutil.copy2(path, bak)
    return bak


def summary_lines(rows: dict, ds, max_planes: int) -> list[str]:
    """Per plane-capable sensor: clouds read, planes found, inlier counts (min / median / max of
    ``n_points``), and the clouds without a plane (rejected: too few inliers)."""
    paths = cloud_paths(ds)
    clouds = Counter(sensor for sensor, _ in paths)
    lines = []
    for sensor in sorted(clouds):
        if not sensor_type(ds.sensors[sensor].type).fits_planes:
            lines.append(f"  {sensor}: {clouds[sensor]} clouds skipped ({ds.sensors[sensor].type}: a scan line has "
                         "no plane)")
            continue
        n = np.array([p for s, p in zip(rows["sensor"], rows["n_points"]) if s == sensor], dtype=float)
        stations = {st for s, st in zip(rows["sensor"], rows["station"]) if s == sensor}
        inliers = (f"; inliers per plane {n.min():.0f} / {np.median(n):.0f} / {n.max():.0f} (min / median / max)"
                   if len(n) else "")
        rejected = clouds[sensor] - len(stations)
        lines.append(f"  {sensor}: {len(n)} plane(s) from {len(stations)} of {clouds[sensor]} clouds"
                     f"{' (at most ' + str(max_planes) + ' per cloud)' if max_planes > 1 else ''}{inliers}; "
                     f"{rejected} cloud(s) without a plane")
    return lines


@dataclass(frozen=True)
class ExtractPlanesResult:
    """What ``graphcal extract-planes`` wrote.

    Attributes:
        dataset: the dataset folder, as given.
        ds: the dataset read.
        rows: the planes table's columns (:func:`graphcal.clouds.plane_table.planes_rows`).
        out: the planes file written.
        backup: the previous file kept (``NAME.bak``), or None.
        beside: no ``out`` was given and the dataset has its own planes.csv (kept): written beside
            it as :data:`EXTRACTED_NAME`.
        max_planes: planes per cloud at most.
        files: the planes file (and the backup, when one was kept).
        warnings: one per camera with clouds in which no plane was found.
        verdict: none (None).
    """

    dataset: str
    ds: Dataset
    rows: dict
    out: Path
    backup: Path | None
    beside: bool
    max_planes: int
    files: tuple[Path, ...]
    warnings: tuple[str, ...]
    verdict: str | None = None

    @property
    def n_planes(self) -> int:
        """Rows of the planes file written."""
        return len(self.rows["sensor"])

    def summary_text(self) -> str:
        """Per sensor the planes and inliers (:func:`summary_lines`), the warnings, the file written."""
        lines = [f"extracted planes from {self.dataset}:", *summary_lines(self.rows, self.ds, self.max_planes)]
        lines += [f"warning: {w}" for w in self.warnings]
        lines.append(f"wrote {self.out}" + (f" (the previous file kept as {self.backup.name})" if self.backup else ""))
        if self.beside:
            lines.append(f"  {Path(self.dataset) / 'planes.csv'} exists and was kept; calibrate reads planes.csv: to "
                         f"use these, move {EXTRACTED_NAME} over it, or run extract-planes --overwrite")
        return "\n".join(lines)


def run(dataset: str | Path, out: str | Path | None = None, *, max_planes: int = 1,
        progress: bool = False, max_points: int | None = None, overwrite: bool = False) -> ExtractPlanesResult:
    """Read a dataset's clouds, fit planes, and write a planes table atomically; returns an
    :class:`ExtractPlanesResult` (its summary: per sensor planes found, inlier counts, clouds without
    a plane; a ``warning:`` line per camera with clouds in which no plane was found; then ``wrote OUT``).

    ``out``: the file to write; None: ``DATASET/planes.csv``, or ``DATASET/planes-extracted.csv`` when
    the dataset already has a planes.csv (see the module docstring). ``overwrite``: replace ``out``
    (None: the dataset's planes.csv), keeping the old file as ``.bak``. A missing parent folder is
    created. ``max_points``: fit each cloud on at most this many of its points
    (:func:`graphcal.clouds.plane_table.planes_rows`; None: all), as ``graphcal calibrate
    --plane-points`` does.
    """
    max_points = check_max_points(max_points, "max_points (--plane-points)")
    if isinstance(max_planes, bool) or not isinstance(max_planes, (int, np.integer)) or max_planes < 1:
        raise GraphcalError(f"max_planes (--max-planes) must be a whole number >= 1, got {max_planes!r}")
    ds = read_dataset(dataset)
    out_path = output_path(Path(dataset), None if out is None else Path(out), overwrite)
    check_output_location(out_path)  # before the work
    paths = cloud_paths(ds)
    if not paths:
        raise DatasetError(Path(dataset) / "clouds", "clouds/<sensor>/<station>.ply", "at least one station cloud")
    types = {name: spec.type for name, spec in ds.sensors.items()}
    pairs = [(key, functools.partial(load_cloud, ds, *key)) for key in sorted(paths)]  # read by the workers
    rows = planes_rows(pairs, types, max_planes=max_planes, progress=progress, max_points=max_points)
    have = zip(rows["sensor"], rows["station"])
    warnings = tuple(no_plane_found_warning(sensor, missing, total, "the planes file has no row for them")
                     for sensor, (missing, total) in camera_clouds_without_planes(ds, have).items())
    make_parent_folder(out_path)
    backup = _keep_backup(out_path) if overwrite else None
    atomic_write_text(out_path, table_csv_text(Table.from_columns(rows)), overwrite=overwrite)
    return ExtractPlanesResult(dataset=str(dataset), ds=ds, rows=rows, out=out_path, backup=backup,
                               beside=out is None and out_path.name == EXTRACTED_NAME, max_planes=int(max_planes),
                               files=(out_path,) + ((backup,) if backup else ()),
                               warnings=warnings)
