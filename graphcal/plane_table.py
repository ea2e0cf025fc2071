"""Clouds of a dataset -> ``planes.csv`` rows: plane extraction per (sensor, station) with the
sensor's noise model, in the contract's columns (plane in the sensor frame, canonical d >= 0,
covariance of (nx, ny, nz, d) stacked row-major)."""

from __future__ import annotations

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


def planes_rows(
    clouds: Mapping[tuple[str, int], np.ndarray] | Iterable[tuple[tuple[str, int], np.ndarray]],
    sensor_types: Mapping[str, str],
    *,
    max_planes: int = 1,
    seed: int = 0,
    progress: bool = False,
) -> dict[str, list]:
    """Fit planes to every cloud of a plane-capable sensor (cameras; a laser scanner's single scan
    line has no plane and is skipped).

    Args:
        clouds: (sensor, station) -> (N, 3) points in the sensor frame (m), or an iterable of such pairs.
        sensor_types: sensor name -> type.
        max_planes: planes per cloud (stairs: one per tread).
        seed: random seed of the RANSAC subsample.
    Returns:
        column -> list of values, columns :data:`PLANE_COLUMNS`.
    """
    from .planes import extract_planes

    items = clouds.items() if isinstance(clouds, Mapping) else clouds
    rows: dict[str, list] = {c: [] for c in PLANE_COLUMNS}
    if progress:
        from tqdm import tqdm

        items = tqdm(list(items), desc="planes: clouds", unit="cloud")
    rng = np.random.default_rng(seed)
    for (sensor, station), points in items:
        kind = sensor_types[sensor]
        if kind == "laser_scanner":
            continue
        try:
            fits = extract_planes(points, max_planes=max_planes, range_noise=range_noise_for(kind), rng=rng)
        except GraphcalError:
            continue  # too few or degenerate points: no plane from this station
        for fit in fits:
            rows["station"].append(int(station))
            rows["sensor"].append(sensor)
            rows["nx"].append(float(fit.n[0]))
            rows["ny"].append(float(fit.n[1]))
            rows["nz"].append(float(fit.n[2]))
            rows["d"].append(float(fit.d))
            rows["n_points"].append(float(fit.n_points))
            rows["rms"].append(float(fit.rms))
            for i in range(4):
                for j in range(4):
                    rows[f"cov_{i}{j}"].append(float(fit.cov[i, j]))
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
    pairs = ((key, load_cloud(ds, *key)) for key in sorted(paths))
    rows = planes_rows(pairs, types, max_planes=max_planes, progress=progress)
    atomic_write_text(out_path, table_csv_text(Table.from_columns(rows)), overwrite=False)
    return out_path
