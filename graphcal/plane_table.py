"""Clouds of a dataset -> ``planes.csv`` rows: plane extraction per (sensor, station) with the
sensor's noise model, in the contract's columns (plane in the sensor frame, canonical d >= 0,
covariance of (nx, ny, nz, d) stacked row-major)."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

from .errors import DatasetError, GraphcalError

PLANE_COLUMNS = ("station", "sensor", "nx", "ny", "nz", "d", "n_points", "rms") + tuple(
    f"cov_{i}{j}" for i in range(4) for j in range(4)
)


def range_noise_for(sensor_type: str):
    """The plane-extraction noise model of a sensor type (None: use the empirical rms)."""
    from .planes import depth_camera_distance_sigma
    from .simulation.sensors import DepthCamera, StereoCamera

    if sensor_type == "depth_camera":
        return depth_camera_distance_sigma(DepthCamera().sigma_along_axis)
    if sensor_type == "stereo_camera":
        return depth_camera_distance_sigma(StereoCamera().sigma_along_axis)
    return None


def cloud_rng(seed: int, sensor: str, station: int) -> np.random.Generator:
    """The random generator of one cloud's plane extraction: a function of (seed, sensor, station)
    only, so a cloud's planes do not depend on which other clouds are fitted, in what order or on
    how many threads."""
    import zlib

    return np.random.default_rng([int(seed) % 2**32, zlib.crc32(str(sensor).encode()), int(station) % 2**32])


def planes_rows(
    clouds: Mapping[tuple[str, int], np.ndarray] | Iterable[tuple[tuple[str, int], np.ndarray]],
    sensor_types: Mapping[str, str],
    *,
    max_planes: int = 1,
    seed: int = 0,
    progress: bool = False,
    workers: int | None = None,
    total: int | None = None,
) -> dict[str, list]:
    """Fit planes to every cloud of a plane-capable sensor (cameras; a laser scanner's single scan
    line has no plane and is skipped).

    Args:
        clouds: (sensor, station) -> (N, 3) points in the sensor frame (m), or an iterable of such
            pairs (consumed lazily: at most ``2 * workers`` clouds are held at once). A value may
            also be a function of no arguments returning the points (e.g. a file reader): it is
            called in the fitting thread, so reading overlaps fitting on every thread.
        sensor_types: sensor name -> type.
        max_planes: planes per cloud (stairs: one per tread).
        seed: random seed of the RANSAC subsamples (each cloud's: :func:`cloud_rng`).
        workers: threads fitting clouds side by side (default: up to 2 of the machine's cores;
            numpy releases the GIL in the per-point passes, but the Python steps between them
            hold it, ~25 % of a frame's time: 2 threads take ~0.7x the time of one).
        total: number of clouds, for the progress bar when ``clouds`` is an iterator.
    Returns:
        column -> list of values, columns :data:`PLANE_COLUMNS`, clouds in input order.
    """
    import os
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    import threading

    from .planes import PlaneWorkspace, extract_planes

    local = threading.local()  # one PlaneWorkspace per thread, freed with this call
    items = clouds.items() if isinstance(clouds, Mapping) else clouds
    rows: dict[str, list] = {c: [] for c in PLANE_COLUMNS}
    bar = None
    if progress:
        from tqdm import tqdm

        if total is None and hasattr(items, "__len__"):
            total = len(items)
        bar = tqdm(total=total, desc="planes: clouds", unit="cloud")

    def fit(key, points):
        sensor, station = key
        kind = sensor_types[sensor]
        if kind == "laser_scanner":
            return key, []
        if callable(points):
            points = points()  # its errors (an unreadable file) are the caller's, not "no plane"
        if not hasattr(local, "workspace"):
            local.workspace = PlaneWorkspace()
        try:
            return key, extract_planes(points, max_planes=max_planes, range_noise=range_noise_for(kind),
                                       rng=cloud_rng(seed, sensor, station), workspace=local.workspace)
        except GraphcalError:
            return key, []  # too few or degenerate points: no plane from this station

    def collect(key, fits):
        for fit_ in fits:
            rows["station"].append(int(key[1]))
            rows["sensor"].append(key[0])
            rows["nx"].append(float(fit_.n[0]))
            rows["ny"].append(float(fit_.n[1]))
            rows["nz"].append(float(fit_.n[2]))
            rows["d"].append(float(fit_.d))
            rows["n_points"].append(float(fit_.n_points))
            rows["rms"].append(float(fit_.rms))
            for i in range(4):
                for j in range(4):
                    rows[f"cov_{i}{j}"].append(float(fit_.cov[i, j]))
        if bar is not None:
            bar.update(1)

    n_workers = max(1, workers if workers is not None else min(2, os.cpu_count() or 1))
    try:
        if n_workers == 1:
            for key, points in items:
                collect(*fit(key, points))
        else:
            with ThreadPoolExecutor(n_workers) as pool:
                pending: deque = deque()
                for key, points in items:
                    pending.append(pool.submit(fit, key, points))
                    if len(pending) >= 2 * n_workers:
                        collect(*pending.popleft().result())
                while pending:
                    collect(*pending.popleft().result())
    finally:
        if bar is not None:
            bar.close()
    return rows


def extract_planes_to_csv(dataset: str | Path, out: str | Path | None = None, *, max_planes: int = 1,
                          progress: bool = False) -> Path:
    """Read a dataset's clouds, fit planes, and write ``planes.csv`` atomically.

    ``out`` defaults to ``DATASET/planes.csv``; an existing file is never replaced (give another
    ``out``).
    """
    from .io.atomic import atomic_write_text
    from .io.dataset import Table, cloud_paths, load_cloud, read_dataset, table_csv_text

    ds = read_dataset(dataset)
    out_path = Path(out) if out is not None else Path(dataset) / "planes.csv"
    if out_path.exists():
        raise DatasetError(out_path, "planes.csv", "a file that does not exist yet (graphcal never overwrites it); "
                           "pass --out to write elsewhere")
    paths = cloud_paths(ds)
    if not paths:
        raise DatasetError(Path(dataset) / "clouds", "clouds/<sensor>/<station>.ply", "at least one station cloud")
    types = {name: spec.type for name, spec in ds.sensors.items()}
    pairs = ((key, functools.partial(load_cloud, ds, *key)) for key in sorted(paths))  # read on the fitting threads
    rows = planes_rows(pairs, types, max_planes=max_planes, progress=progress)
    atomic_write_text(out_path, table_csv_text(Table.from_columns(rows)), overwrite=False)
    return out_path
