"""Clouds of a dataset -> ``planes.csv`` rows: plane extraction per (sensor, station) with the
sensor's noise model, in the contract's columns (plane in the sensor frame, canonical d >= 0,
covariance of (nx, ny, nz, d) stacked row-major)."""

from __future__ import annotations

import itertools
from typing import Iterable, Mapping

import numpy as np

from graphcal.errors import GraphcalError

PLANE_COLUMNS = ("station", "sensor", "nx", "ny", "nz", "d", "n_points", "rms") + tuple(
    f"cov_{i}{j}" for i in range(4) for j in range(4)
)


def range_noise_for(sensor_type: str):
    """The plane-extraction noise model of a sensor type (None: use the empirical rms)."""
    from graphcal.clouds.planes import depth_camera_distance_sigma
    from graphcal.models.sensors import sensor_type as record

    t = record(sensor_type)
    return depth_camera_distance_sigma(t.model().sigma_along_axis) if t.fits_planes else None


def cloud_rng(seed: int, sensor: str, station: int) -> np.random.Generator:
    """The random generator of one cloud's plane extraction: a function of (seed, sensor, station)
    only, so a cloud's planes do not depend on which other clouds are fitted, in what order or on
    how many threads."""
    import zlib

    return np.random.default_rng([int(seed) % 2**32, zlib.crc32(str(sensor).encode()), int(station) % 2**32])


def thin_cloud(points: np.ndarray, max_points: int | None) -> np.ndarray:
    """Every k-th point of a cloud (N, 3), k = ceil(N / max_points): at most ``max_points`` points,
    spread evenly over the frame (a depth image's pixels keep their row-major order).
    ``max_points`` None, or a cloud no larger: the cloud itself."""
    if max_points is None or len(points) <= max_points:
        return points
    return np.ascontiguousarray(points[:: -(-len(points) // max_points)])


def check_max_points(max_points, what: str = "max_points") -> int | None:
    """``max_points`` as an int >= 100, or None; otherwise a GraphcalError naming ``what``."""
    if max_points is None:
        return None
    if isinstance(max_points, bool) or not isinstance(max_points, (int, np.integer)) or max_points < 100:
        raise GraphcalError(f"{what} must be a whole number of points >= 100 (or None: every point), "
                            f"got {max_points!r}")
    return int(max_points)


def _fit_cloud(key: tuple[str, int], points, kind: str, max_planes: int, seed: int, workspace,
               max_points: int | None = None) -> list[tuple]:
    """The planes of one cloud as ``(n (3,), d, n_points, rms, cov (4, 4))``, sensor frame (m).

    ``points``: (N, 3) array, or a function of no arguments returning it (read here; its errors,
    e.g. an unreadable file, are the caller's). ``max_points``: fit on :func:`thin_cloud` of it.
    Too few or degenerate points: no plane (``[]``).
    """
    from graphcal.clouds.planes import extract_planes
    from graphcal.models.sensors import sensor_type

    if not sensor_type(kind).fits_planes:
        return []
    if callable(points):
        points = points()
    points = thin_cloud(points, max_points)
    try:
        fits = extract_planes(points, max_planes=max_planes, range_noise=range_noise_for(kind),
                              rng=cloud_rng(seed, *key), workspace=workspace)
    except GraphcalError:
        return []
    return [(f.n, f.d, f.n_points, f.rms, f.cov) for f in fits]


#: the clouds of the planes_rows calls running on worker processes, by call: set before the workers
#: fork (they inherit it, so no cloud or reader is ever pickled) and removed when the call ends
_FORK_JOBS: dict = {}
_TOKENS = itertools.count()
_CHILD_WORKSPACE = None


def _fit_in_worker(task: tuple[int, int]):
    """Worker process: fit cloud ``i`` of call ``token``; returns (i, rows, None) or (i, None,
    (exception, traceback text)) so that any error reaches the parent, which raises it."""
    global _CHILD_WORKSPACE
    from graphcal.clouds.planes import PlaneWorkspace

    token, i = task
    items, types, max_planes, seed, max_points = _FORK_JOBS[token]
    key, points = items[i]
    try:
        if _CHILD_WORKSPACE is None:
            _CHILD_WORKSPACE = PlaneWorkspace()
        return i, _fit_cloud(key, points, types[key[0]], max_planes, seed, _CHILD_WORKSPACE, max_points), None
    except Exception as exc:  # noqa: BLE001 - handed to the parent, which raises it
        import pickle
        import traceback

        text = traceback.format_exc()
        try:
            pickle.loads(pickle.dumps(exc))
        except Exception:  # noqa: BLE001 - an exception that does not survive pickling: its text
            exc = GraphcalError(f"plane extraction of {key[0]} station {key[1]}: {type(exc).__name__}: {exc}")
        return i, None, (exc, text)


def _can_fork_workers() -> bool:
    """Whether worker processes may be forked here: Linux (macOS offers fork, but its system
    libraries are not fork-safe), this process no daemon (those cannot have children), and no other
    Python thread running (a lock another thread holds at the fork would stay held in the child)."""
    import multiprocessing
    import sys
    import threading

    return (sys.platform.startswith("linux") and "fork" in multiprocessing.get_all_start_methods()
            and not multiprocessing.current_process().daemon and threading.active_count() == 1)


def planes_rows(
    clouds: Mapping[tuple[str, int], np.ndarray] | Iterable[tuple[tuple[str, int], np.ndarray]],
    sensor_types: Mapping[str, str],
    *,
    max_planes: int = 1,
    seed: int = 0,
    progress: bool = False,
    workers: int | None = None,
    total: int | None = None,
    processes: bool | None = None,
    max_points: int | None = None,
) -> dict[str, list]:
    """Fit planes to every cloud of a plane-capable sensor (cameras; a laser scanner's single scan
    line has no plane and is skipped).

    Args:
        clouds: (sensor, station) -> (N, 3) points in the sensor frame (m), or an iterable of such
            pairs (an iterator is consumed lazily: at most ``2 * workers`` clouds are held at once).
            A value may also be a function of no arguments returning the points (e.g. a file
            reader): it is called by the worker, so reading overlaps fitting on every worker.
        sensor_types: sensor name -> type.
        max_planes: planes per cloud (stairs: one per tread).
        seed: random seed of the RANSAC subsamples (each cloud's: :func:`cloud_rng`).
        workers: clouds fitted side by side (default: up to 2 of the machine's cores).
        total: number of clouds, for the progress bar when ``clouds`` is an iterator.
        processes: run the workers as forked processes (True) or threads (False). Default: processes
            when ``clouds`` is a mapping or a list (already in memory or cheap readers: the workers
            inherit it, nothing is pickled but the planes), there are at least ``2 * workers``
            clouds, and fork is safe here (Linux, see :func:`_can_fork_workers`); otherwise threads. Threads
            share the GIL with the Python steps of a fit (~25 % of its time): on Chai's 52 Kinect
            clouds read from a dataset, two threads took 0.74x the time of one, two processes
            0.56x (medians of 5 passes: 1.66 s on one, 1.23 s on two threads, 0.93 s on two
            processes).
        max_points: fit each cloud on at most this many of its points, every k-th one
            (:func:`thin_cloud`; None: all). ``n_points`` then counts the inliers among those. On
            Chai's 52 Kinect clouds of 258k points, 50000 took 0.5-0.6x the calibration's time and the
            extrinsic's translation error grew 35 % (RMS over 24 datasets, docs/calibration.md).
    Returns:
        column -> list of values, columns :data:`PLANE_COLUMNS`, clouds in input order.
    Raises:
        Whatever a reader raises (e.g. :class:`~graphcal.errors.DatasetError`), also from a worker
        process; ``processes=True`` where workers cannot be forked (:func:`_can_fork_workers`):
        GraphcalError.
    """
    import os
    import threading
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    from graphcal.clouds.planes import PlaneWorkspace

    max_points = check_max_points(max_points)
    items = clouds.items() if isinstance(clouds, Mapping) else clouds
    rows: dict[str, list] = {c: [] for c in PLANE_COLUMNS}
    n_workers = max(1, workers if workers is not None else min(2, os.cpu_count() or 1))
    in_memory = isinstance(clouds, (Mapping, list, tuple))
    if processes is None:
        processes = (n_workers > 1 and in_memory and len(clouds) >= 2 * n_workers and _can_fork_workers())
    elif processes:
        if not in_memory:
            raise GraphcalError("planes_rows: processes=True needs the clouds as a mapping or a list")
        if not _can_fork_workers():
            raise GraphcalError("planes_rows: processes=True, but worker processes cannot be forked here "
                                "(not Linux, a daemon process, or other Python threads running)")
    pool = futures = token = None
    if processes:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        from graphcal.clouds.planes import import_fit_modules

        import_fit_modules()  # here, once, not in every worker at every call
        for kind in set(sensor_types.values()):
            range_noise_for(kind)
        items = list(items)
        token = next(_TOKENS)
        _FORK_JOBS[token] = (items, dict(sensor_types), max_planes, seed, max_points)
        try:
            pool = ProcessPoolExecutor(n_workers, mp_context=multiprocessing.get_context("fork"))
            # the workers fork at the first submit, before the progress bar's thread starts
            futures = [pool.submit(_fit_in_worker, (token, i)) for i in range(len(items))]
        except BaseException:
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
            del _FORK_JOBS[token]
            raise
    bar = None
    local = threading.local()  # one PlaneWorkspace per thread, freed with this call

    def fit(key, points):
        if not hasattr(local, "workspace"):
            local.workspace = PlaneWorkspace()
        return key, _fit_cloud(key, points, sensor_types[key[0]], max_planes, seed, local.workspace, max_points)

    def collect(key, fits):
        for n, d, n_points, rms, cov in fits:
            rows["station"].append(int(key[1]))
            rows["sensor"].append(key[0])
            rows["nx"].append(float(n[0]))
            rows["ny"].append(float(n[1]))
            rows["nz"].append(float(n[2]))
            rows["d"].append(float(d))
            rows["n_points"].append(float(n_points))
            rows["rms"].append(float(rms))
            for i in range(4):
                for j in range(4):
                    rows[f"cov_{i}{j}"].append(float(cov[i, j]))
        if bar is not None:
            bar.update(1)

    try:
        if progress:
            from graphcal.progress import ProgressBar

            if total is None and hasattr(items, "__len__"):
                total = len(items)
            bar = ProgressBar(total=total, desc="planes: clouds", unit="cloud")
        if futures is not None:
            from concurrent.futures.process import BrokenProcessPool

            for future in futures:  # in input order
                try:
                    i, fits, error = future.result()
                except BrokenProcessPool as exc:
                    raise GraphcalError(
                        "plane extraction: a worker process died (killed, or out of memory?); "
                        "planes_rows(..., processes=False) fits the clouds in this process") from exc
                if error is not None:
                    exc, text = error
                    raise exc from _WorkerTraceback(text)
                collect(items[i][0], fits)
        elif n_workers == 1:
            for key, points in items:
                collect(*fit(key, points))
        else:
            with ThreadPoolExecutor(n_workers) as executor:
                pending: deque = deque()
                for key, points in items:
                    pending.append(executor.submit(fit, key, points))
                    if len(pending) >= 2 * n_workers:
                        collect(*pending.popleft().result())
                while pending:
                    collect(*pending.popleft().result())
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)  # after an error: the clouds not yet started are dropped
            del _FORK_JOBS[token]
        if bar is not None:
            bar.close()
    return rows


class _WorkerTraceback(Exception):
    """The traceback of an error raised in a plane-extraction worker process (shown as its cause)."""

    def __str__(self) -> str:
        return "in the plane-extraction worker process:\n" + str(self.args[0])


def camera_clouds_without_planes(ds, have) -> dict[str, tuple[list[int], int]]:
    """Sensor -> (the stations whose camera cloud has no plane in ``have``, the sensor's number of
    clouds), for the cameras with such stations. ``have``: the ``(sensor, station)`` pairs with a
    plane (from planes.csv, or fitted)."""
    from graphcal.io.dataset import cloud_paths
    from graphcal.models.sensors import sensor_type

    have = {(str(sn), int(st)) for sn, st in have}
    cameras = {n for n, spec in ds.sensors.items() if sensor_type(spec.type).fits_planes}
    clouds = [key for key in cloud_paths(ds) if key[0] in cameras]
    out = {}
    for sensor in sorted({k[0] for k in clouds}):
        missing = sorted(st for sn, st in clouds if sn == sensor and (sn, st) not in have)
        if missing:
            out[sensor] = (missing, sum(1 for sn, _ in clouds if sn == sensor))
    return out


def stations_text(stations: list[int], at_most: int = 8) -> str:
    """``1, 2, 3, ...``: the first ``at_most`` station ids of a warning."""
    return ", ".join(map(str, stations[:at_most])) + (", ..." if len(stations) > at_most else "")


def no_plane_found_warning(sensor: str, missing: list[int], total: int, consequence: str) -> str:
    """The warning for clouds in which no plane was found (stations ``missing`` of ``total``)."""
    shown = stations_text(missing)
    return (f"{sensor}: no plane found in the clouds of {len(missing)} of the {total} stations ({shown}; "
            f"clouds/{sensor}/<station>.ply: too few points, collinear points or no plane among them); {consequence}")
