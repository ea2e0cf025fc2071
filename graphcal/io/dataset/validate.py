"""Validating a dataset: :func:`validate_dataset` reads it
(:func:`~graphcal.io.dataset.read.read_dataset`), then every cloud, and returns counts and warnings
(:class:`ValidationReport`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from graphcal.io.dataset.cloud_files import cloud_paths, off_plane_scan_warning, read_cloud, scan_off_plane_m
from graphcal.io.dataset.model import FEET_FIXED_WITHIN, FORMAT, SCAN_PLANE_MAX_Z_M
from graphcal.io.dataset.paths import shown_path
from graphcal.io.dataset.read import read_dataset_parts
from graphcal.models.sensors import sensor_type


@dataclass(frozen=True)
class ValidationReport:
    """What :func:`validate_dataset` found in a valid dataset. Times in seconds.

    Attributes:
        path: the dataset folder.
        robot: ``"model octopus"``, ``"URDF robot.urdf"`` or ``"none"``.
        n_stations, n_sessions: rows of stations.csv; distinct session labels (stations and
            timeseries; 0 without a ``session`` column).
        sensors: sensor names.
        n_clouds, n_cloud_points: PLY files read (station clouds and the timeseries' clouds) and
            their total number of points.
        n_planes, n_mocap_rows, n_timeseries_rows: rows of planes.csv, mocap.csv, timeseries.csv.
        time_start_s, time_end_s: smallest and largest ``time`` over all files (None: no time).
        warnings: things that are legal but suspicious.
    """

    path: str
    robot: str
    n_stations: int
    n_sessions: int
    sensors: tuple[str, ...]
    n_clouds: int
    n_cloud_points: int
    n_planes: int
    n_mocap_rows: int
    n_timeseries_rows: int
    time_start_s: float | None
    time_end_s: float | None
    warnings: tuple[str, ...] = ()

    @property
    def n_sensors(self) -> int:
        """Number of sensors in dataset.yaml."""
        return len(self.sensors)

    @property
    def time_span_s(self) -> float | None:
        """``time_end_s - time_start_s`` (None without any time)."""
        if self.time_start_s is None or self.time_end_s is None:
            return None
        return self.time_end_s - self.time_start_s

    def summary(self) -> str:
        """A few human-readable lines."""
        span = "no time" if self.time_span_s is None else (
            f"{self.time_span_s:.3f} s ({self.time_start_s:.3f} .. {self.time_end_s:.3f} s)"
        )
        lines = [
            f"{self.path}: valid {FORMAT} dataset",
            f"  robot: {self.robot}",
            f"  sensors: {self.n_sensors} ({', '.join(self.sensors) or 'none'})",
            f"  stations: {self.n_stations} in "
            f"{self.n_sessions if self.n_sessions or not self.n_stations else 'an unknown number of'} session(s); "
            f"timeseries samples: {self.n_timeseries_rows}",
            f"  clouds: {self.n_clouds} ({self.n_cloud_points} points); planes: {self.n_planes}; "
            f"mocap rows: {self.n_mocap_rows}",
            f"  time span: {span}",
        ]
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)


def validate_dataset(path: str | Path) -> ValidationReport:
    """:func:`~graphcal.io.dataset.read.read_dataset` plus every cloud read; counts and warnings of a valid dataset.

    Raises:
        DatasetError: the first problem found (see docs/dataset.md for every rule).
    """
    ds, robot, parsed, referenced = read_dataset_parts(path)
    clouds = cloud_paths(ds)
    n_points = 0
    files = list(clouds.values()) + sorted(set(referenced) - set(clouds.values()))
    sensor_of = {f: s for (s, _), f in clouds.items()}
    off_plane: dict[str, list] = {}
    for f in files:
        pts = read_cloud(f)
        n_points += len(pts)
        sensor = sensor_of.get(f)
        if sensor in ds.sensors and not sensor_type(ds.sensors[sensor].type).fits_planes:
            z90 = scan_off_plane_m(pts)
            if z90 > SCAN_PLANE_MAX_Z_M:
                off_plane.setdefault(sensor, []).append((shown_path(ds.root, f), z90))

    warnings: list[str] = []
    times = [t["time"] for t in (ds.stations, ds.timeseries, ds.mocap) if t is not None and t.has("time") and len(t)]
    t0 = float(min(t.min() for t in times)) if times else None
    t1 = float(max(t.max() for t in times)) if times else None
    sessions: set[str] = set()
    for t in (ds.stations, ds.timeseries):
        if t is not None and t.has("session"):
            sessions.update(t["session"].tolist())
    if ds.stations is not None and not len(ds.stations):
        warnings.append("stations.csv has a header but no rows: nothing to calibrate (calibrate refuses it)")
    in_the_air = ds.mocap is not None and not ds.sensors  # a leg measured by markers: no foot is planted
    if ds.stations is not None and not ds.stations.has("session") and len(ds.stations) and not in_the_air:
        warnings.append("stations.csv has no session column (which stations share a stance is unknown)")
    if str(ds.ground.get("type", "level")) != "level":
        warnings.append(f"dataset.yaml ground.type {ds.ground['type']!r}: graphcal models a level ground (type: level) "
                        "and reads it as one; a tilted or uneven floor shows in graphcal diagnose and is "
                        "allowed for with calibrate --ground-roughness-mm")
    fixed = str(ds.stance.get("feet_fixed_within", "session"))
    if fixed not in FEET_FIXED_WITHIN:
        warnings.append(f"dataset.yaml stance.feet_fixed_within {fixed!r}: graphcal knows "
                        f"{', '.join(FEET_FIXED_WITHIN[:-1])} and {FEET_FIXED_WITHIN[-1]}; it is read as session")
    for name in ds.sensors:
        has_planes = ds.planes is not None and name in set(ds.planes["sensor"].tolist())
        has_clouds = any(s == name for s, _ in clouds) or (
            ds.timeseries is not None and ds.timeseries.has(f"cloud_{name}")
        )
        if not (has_planes or has_clouds):
            warnings.append(f"sensor {name!r} has no cloud and no plane")
        if name in off_plane:
            warnings.append(off_plane_scan_warning(name, off_plane[name], sum(s == name for s, _ in clouds)))
    if robot is not None:
        for kind in ("stations", "timeseries"):
            t = getattr(ds, kind)
            if t is None or not len(t):
                continue
            for foot in robot.feet:
                leg = robot.legs[foot]
                if not leg.n_joints:
                    continue
                outside = leg.outside_limits(np.stack([t[f"q_{j}"] for j in leg.joint_names], axis=-1))
                for j, lo, hi, out in zip(leg.joint_names, leg.lower, leg.upper, outside.sum(axis=0).tolist()):
                    if out:
                        warnings.append(
                            f"{kind}.csv: q_{j} outside the URDF limits [{lo:.4g}, {hi:.4g}] on {out} row(s)"
                        )
    if ds.robot is None:
        desc = "none"
    elif ds.robot.model is not None:
        desc = f"model {ds.robot.model}"
    else:
        desc = f"URDF {ds.robot.urdf}"
    return ValidationReport(
        path=str(ds.root),
        robot=desc,
        n_stations=len(ds.stations) if ds.stations is not None else 0,
        n_sessions=len(sessions),
        sensors=tuple(ds.sensors),
        n_clouds=len(files),
        n_cloud_points=n_points,
        n_planes=len(ds.planes) if ds.planes is not None else 0,
        n_mocap_rows=len(ds.mocap) if ds.mocap is not None else 0,
        n_timeseries_rows=len(ds.timeseries) if ds.timeseries is not None else 0,
        time_start_s=t0,
        time_end_s=t1,
        warnings=tuple(warnings),
    )
