"""The import: samples (from a bag or a CSV log) -> stations, timeseries and the dataset folder,
written atomically through :func:`graphcal.io.dataset.write_dataset` with ``import_map.yaml`` and
``import_report.yaml`` beside it. Times in seconds, SI units throughout."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from graphcal.errors import DatasetError
from graphcal.io.dataset.model import Dataset, ImuSpec, RobotSpec, SensorSpec, Table
from graphcal.logs.stations import StationFinder, Window

__all__ = ["SampleSink", "StampCheck", "DatasetParts", "write_imported", "foot_thresholds"]

log = logging.getLogger(__name__)


class StampCheck:
    """Stamps of each topic/column must increase: a duplicated or backwards stamp is a DatasetError
    naming the source, the topic and the time; forward jumps (a gap of more than ``max(1 s, 50x the
    typical step)``) are kept in ``jumps`` (reported, not refused)."""

    def __init__(self, source: str | Path):
        self.source = source
        self._last: dict[str, float] = {}
        self._step: dict[str, float] = {}
        self.jumps: list[str] = []

    def __call__(self, topic: str, t: float, where: str = "") -> None:
        prev = self._last.get(topic)
        if prev is not None:
            dt = t - prev
            if dt <= 0:
                what = "a duplicated stamp" if dt == 0 else f"a stamp {-dt:.6f} s before the previous one"
                raise DatasetError(self.source, f"{topic}, {where or 'message'} at t = {t:.6f} s",
                                   "strictly increasing stamps", what)
            typical = self._step.get(topic)
            if typical is not None and dt > max(1.0, 50.0 * typical):
                self.jumps.append(f"{topic}: clock jump of {dt:.3f} s at t = {prev:.6f} s "
                                  f"(typical step {typical * 1e3:.3g} ms)")
            else:
                self._step[topic] = dt if typical is None else 0.95 * typical + 0.05 * dt
        self._last[topic] = t


def foot_thresholds(samples: dict[str, np.ndarray], specs: dict[str, dict], default: float) -> dict:
    """foot -> :class:`~graphcal.locomotion.contact_detection.ContactThresholds` (the unit of the
    samples: N after the map's offset/scale, or raw counts with ``threshold_raw``): the map's own
    ``threshold_n`` / ``threshold_raw`` of the foot when it gives one (on = off = it, source
    ``map``), else learned from the foot's samples (its swing and stance modes), else -- a foot that
    was never lifted, or never loaded -- ``default`` (``stations.force_threshold_n``, source
    ``fallback``)."""
    from graphcal.locomotion.contact_detection import ContactSignalError, ContactThresholds, learn_thresholds

    out = {}
    for foot, spec in specs.items():
        given = spec.get("threshold_raw", spec.get("threshold_n"))
        if given is not None:
            out[foot] = ContactThresholds(foot, float(given), float(given), source="map")
            continue
        try:
            out[foot] = learn_thresholds(np.asarray(samples.get(foot, ()), dtype=float), foot)
        except ContactSignalError:
            out[foot] = ContactThresholds(foot, float(default), float(default), source="fallback")
    return out


class SampleSink:
    """Where samples go, in time order: the :class:`StationFinder` and (with ``timeseries``) the
    rows of ``timeseries.csv`` (one per joint sample, the foot loads held, the IMU interpolated
    linearly to the joint stamp: holding the latest sample puts it up to one IMU period late, which
    alone turned a walk's stance verdict inconsistent).

    A foot is loaded above its ``on`` threshold and unloaded below its ``off`` one (a hysteresis;
    ``feet_thresholds`` foot -> ContactThresholds, or a number for on = off). The timeseries'
    ``contact_<foot>`` are decided at the end from the stored loads (``force_<foot>``, the unit of
    the map: N, or raw counts with ``threshold_raw``) with the same hysteresis and the minimum
    stance and swing durations ``min_stance_s``, ``min_swing_s`` (s); the joints' efforts, when
    every joint message had them, become ``tau_<joint>`` (N m)."""

    def __init__(self, finder: StationFinder, feet_thresholds: dict, timeseries: bool, *,
                 min_stance_s: float | None = None, min_swing_s: float | None = None):
        from graphcal.locomotion.contact_detection import MIN_STANCE_S, MIN_SWING_S, ContactThresholds

        self.finder = finder
        self.thresholds = {f: (t if isinstance(t, ContactThresholds) else ContactThresholds(f, float(t), float(t),
                                                                                              source="map"))
                           for f, t in feet_thresholds.items()}
        self.timeseries = timeseries
        self.min_stance_s = MIN_STANCE_S if min_stance_s is None else float(min_stance_s)
        self.min_swing_s = MIN_SWING_S if min_swing_s is None else float(min_swing_s)
        self.rows: list[np.ndarray] = []
        self._imu = np.full(6, np.nan)
        self._imu_t: list[float] = []
        self._imu_v: list[np.ndarray] = []
        self._force = np.full(len(self.thresholds), np.nan)
        self._loaded = np.zeros(len(self.thresholds), dtype=bool)
        self._foot_index = {f: i for i, f in enumerate(self.thresholds)}
        self._tau_ok: bool | None = None
        self.n_joint = 0
        self.n_imu = 0
        self._cols: dict = {}
        self._reported: set = set()  # the feet reported to the finder once (the first report always goes)
        #: the timeseries' ContactDetection, once timeseries_table made it
        self.contacts = None
        #: receive time minus header stamp of the first joint message (s), set by the bag reader
        self.receive_offset_s = 0.0

    def joints(self, t: float, q: np.ndarray, tau: np.ndarray | None = None) -> None:
        """Joint positions ``q`` (rad) and, when the message has them, efforts ``tau`` (N m) at ``t`` (s)."""
        self.n_joint += 1
        self.finder.joints(t, q)
        if not self.timeseries:
            return
        ok = tau is not None and len(tau) == len(q)
        self._tau_ok = ok if self._tau_ok is None else (self._tau_ok and ok)
        if np.isfinite(self._imu[0]) or not self.finder.has_imu:
            imu = self._imu if self.finder.has_imu else ()
            efforts = tau if ok else np.full(len(q), np.nan)
            self.rows.append(np.concatenate([[t], q, efforts, imu, self._force]))

    def imu(self, t: float, accel, gyro) -> None:
        """Specific force (m/s²) and rate (rad/s) at ``t`` (s), each three numbers."""
        self.n_imu += 1
        self.finder.imu(t, accel, gyro)
        if self.timeseries:
            self._imu = np.array([*accel, *gyro], dtype=np.float64)
            self._imu_t.append(float(t))
            self._imu_v.append(self._imu)

    def feet(self, t: float, forces: dict[str, float]) -> None:
        """Foot loads at ``t`` (s): foot -> force (N; raw counts with a raw threshold)."""
        self.feet_array(t, tuple(forces), np.array(list(forces.values()), dtype=np.float64))

    def feet_array(self, t: float, names: tuple[str, ...], forces: np.ndarray) -> None:
        """Loads ``forces`` (N, or raw counts with a raw threshold) of the feet ``names`` at ``t``
        (s); the finder hears of it only when a foot's state changes."""
        cols = self._cols.get(names)
        if cols is None:
            idx = np.array([self._foot_index[n] for n in names])
            on = np.array([self.thresholds[n].on for n in names])
            off = np.array([self.thresholds[n].off for n in names])
            cols = self._cols[names] = (idx, on, off)
        idx, on, off = cols
        self._force[idx] = forces
        prev = self._loaded[idx]
        now = np.where(forces > on, True, np.where(forces < off, False, prev))
        if np.array_equal(now, prev) and names in self._reported:
            return
        self._reported.add(names)
        self._loaded[idx] = now
        self.finder.feet(t, dict(zip(names, now.tolist())))

    def contact_detection(self, forces: np.ndarray, times: np.ndarray):
        """The timeseries' contacts: :func:`graphcal.locomotion.contact_detection.stance_mask` of the
        stored ``forces`` (N rows, n_feet) with the sink's thresholds and minimum durations."""
        from graphcal.locomotion.contact_detection import stance_mask

        return stance_mask(forces, times, list(self.thresholds.values()), min_stance_s=self.min_stance_s,
                           min_swing_s=self.min_swing_s)

    def timeseries_table(self, joint_names) -> Table | None:
        """timeseries.csv: time, q_*, tau_* (when every joint message had efforts), imu_*,
        force_<foot> (the map's unit), contact_<foot> (0/1)."""
        if not self.timeseries or not self.rows:
            return None
        a = np.vstack(self.rows)
        nj = len(joint_names)
        n_imu = 6 if self.finder.has_imu else 0
        data = {"time": a[:, 0]}
        data.update({f"q_{j}": a[:, 1 + i] for i, j in enumerate(joint_names)})
        if self._tau_ok:
            data.update({f"tau_{j}": a[:, 1 + nj + i] for i, j in enumerate(joint_names)})
        imu = ["imu_ax", "imu_ay", "imu_az", "imu_gx", "imu_gy", "imu_gz"][:n_imu]
        if n_imu and len(self._imu_t) >= 2:  # to the joint stamps (the rows keep their held values otherwise)
            ti, vi = np.asarray(self._imu_t), np.vstack(self._imu_v)
            data.update({c: np.interp(a[:, 0], ti, vi[:, i]) for i, c in enumerate(imu)})
        else:
            data.update({c: a[:, 1 + 2 * nj + i] for i, c in enumerate(imu)})
        if self.thresholds:
            forces = _backfilled(a[:, 1 + 2 * nj + n_imu:])
            det = self.contact_detection(forces, a[:, 0])
            self.contacts = det
            data.update({f"force_{f}": forces[:, i] for i, f in enumerate(self.thresholds)})
            data.update({f"contact_{f}": det.mask[:, i].astype(float) for i, f in enumerate(self.thresholds)})
        return Table(tuple(data), data)

    def contacts_report(self) -> dict:
        """foot -> thresholds used (the map's unit) and, with a timeseries, duty factor and runs."""
        det = self.contacts
        if det is not None:
            return {"min_stance_s": det.min_stance_s, "min_swing_s": det.min_swing_s, "feet": det.summary()}
        return {"feet": {f: {"source": t.source, "on": float(t.on), "off": float(t.off)}
                         for f, t in self.thresholds.items()}}


def _backfilled(x: np.ndarray) -> np.ndarray:
    """Columns with their leading NaN (rows before the first foot message) set to the first value
    (0 for a column without any)."""
    x = x.copy()
    for i in range(x.shape[1]):
        ok = np.flatnonzero(np.isfinite(x[:, i]))
        x[: ok[0] if len(ok) else len(x), i] = x[ok[0], i] if len(ok) else 0.0
    return x


@dataclass
class DatasetParts:
    """What an import gathered (SI units): the robot, sensor and IMU priors, the joint names, the
    finder's windows, the stations' points per sensor (``(sensor, window index) -> (N, 3)`` m in
    the sensor frame), notes for the report."""

    robot: RobotSpec
    urdf_xml: str | None
    joint_names: tuple[str, ...]
    sensors: dict[str, SensorSpec]
    imu: ImuSpec | None
    finder: StationFinder
    sink: SampleSink
    points: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    source: str = ""
    map_text: str = ""
    #: the clouds along the walk: sensor -> [(stamp s, staged PLY file)], in time order
    walk_clouds: dict = field(default_factory=dict)
    #: the rate they were thinned to (Hz), None when not asked (no timeseries)
    walk_cloud_rate_hz: float | None = None


def _window_dict(w: Window, station: int | None = None) -> dict:
    d: dict[str, Any] = {}
    if station is not None:
        d["station"] = station
    d.update({"start_s": round(w.start, 6), "end_s": round(w.end, 6), "duration_s": round(w.duration, 3)})
    if station is not None:
        d.update({"joint_samples": w.n_joint, "imu_samples": w.n_imu, "clouds": sorted(w.clouds)})
    else:
        d["reason"] = w.reason
    return d


def _stations_table(parts: DatasetParts, windows: list[Window]) -> tuple[Table, str]:
    """stations.csv from the accepted windows, and ``stance.feet_fixed_within``: windows between which
    no foot was lifted share a session; without foot topics every station is a stance of its own."""
    feet_known = bool(parts.finder.loaded)
    lifts = sorted({w.lifts for w in windows})
    session = [f"s{lifts.index(w.lifts) + 1}" if feet_known else f"s{i + 1}" for i, w in enumerate(windows)]
    data: dict[str, Any] = {"station": np.arange(1, len(windows) + 1), "session": np.array(session),
                            "time": np.array([w.centre for w in windows])}
    q = np.vstack([w.q for w in windows])
    for i, j in enumerate(parts.joint_names):
        data[f"q_{j}"] = q[:, i]
    if parts.imu is not None:
        acc = np.vstack([w.accel for w in windows])
        gyr = np.vstack([w.gyro for w in windows])
        for i, ax in enumerate("xyz"):
            data[f"imu_a{ax}"] = acc[:, i]
        for i, ax in enumerate("xyz"):
            data[f"imu_g{ax}"] = gyr[:, i]
    return Table(tuple(data), data), ("session" if feet_known else "station")


def _walk_cloud_columns(ts: Table | None, parts: DatasetParts, staging: Path | None) -> tuple[Table | None, dict]:
    """timeseries.csv with a ``cloud_<sensor>`` column per sensor that has clouds along the walk:
    each cloud's path (``clouds/<sensor>/walk/<n>.ply``, the staged file renamed there) on the
    joint row nearest its stamp; a cloud outside the joints' time span (by more than one joint step)
    or on a row another cloud of the sensor already took is dropped. Returns (table, report)."""
    if ts is None or not parts.walk_clouds or staging is None:
        return ts, {}
    t = np.asarray(ts["time"], dtype=float)
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    cols = {c: ts[c] for c in ts.columns}
    report: dict[str, Any] = {}
    for s, items in parts.walk_clouds.items():
        col = np.full(len(t), "", dtype=object)
        outside = shared = 0
        written = []
        for tc, src in items:
            i = int(np.clip(np.searchsorted(t, tc), 1, len(t) - 1)) if len(t) > 1 else 0
            i = i - 1 if len(t) > 1 and abs(t[i - 1] - tc) <= abs(t[i] - tc) else i
            if tc < t[0] - dt or tc > t[-1] + dt:
                outside += 1
                continue
            if col[i]:
                shared += 1
                continue
            rel = f"clouds/{s}/walk/{len(written) + 1:06d}.ply"
            target = staging / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            src.rename(target)
            col[i] = rel
            written.append(tc)
        if written:
            cols[f"cloud_{s}"] = col.astype(str)
        report[s] = {"clouds": len(written), "first_s": round(written[0], 6) if written else None,
                     "last_s": round(written[-1], 6) if written else None,
                     "dropped_outside_joint_times": outside, "dropped_sharing_a_row": shared}
    return Table(tuple(cols), cols), report


def write_imported(parts: DatasetParts, out_dir: Path, *, overwrite: bool = False, jumps=(),
                   staging: Path | None = None) -> tuple[Path, str]:
    """Write the dataset (stations from the accepted windows that have a cloud of every sensor,
    timeseries when gathered), ``import_map.yaml`` and ``import_report.yaml``; returns the folder
    and a summary. A window's cloud is (N, 3) points or a PLY file under ``staging`` (a folder on
    the same file system, renamed into ``staging/clouds`` and copied from there). DatasetError when
    there is neither a station nor a timeseries (with the hint that a walk needs ``--timeseries``
    when it was not asked for)."""
    from graphcal.io.dataset.write import write_dataset

    kept, rejected = [], list(parts.finder.rejected)
    for w in parts.finder.accepted:
        missing = [s for s in parts.sensors if s not in w.clouds]
        if missing:
            w.reason = f"no cloud of {', '.join(missing)} inside the window"
            rejected.append(w)
        else:
            kept.append(w)
    rejected.sort(key=lambda w: w.start)
    ts = parts.sink.timeseries_table(parts.joint_names)
    ts, walk_report = _walk_cloud_columns(ts, parts, staging)
    if not kept and ts is None:
        reasons = "; ".join(f"{w.start:.2f}-{w.end:.2f} s: {w.reason}" for w in rejected[:3])
        hint = "" if parts.sink.timeseries else ("; a walking log for graphcal track: import it with --timeseries "
                                 "(timeseries.csv, no stations needed)")
        raise DatasetError(parts.source, "stations", "at least one still window with every foot loaded "
                           f"(see the stations thresholds of the import map){hint}",
                           f"none ({len(rejected)} rejected{': ' + reasons if reasons else ''})")
    stations, within = _stations_table(parts, kept) if kept else (None, "session")
    clouds = {}
    for i, w in enumerate(kept):
        for s in parts.sensors:
            if isinstance(w.clouds[s], Path):
                target = staging / "clouds" / s / f"{i + 1}.ply"
                target.parent.mkdir(parents=True, exist_ok=True)
                w.clouds[s].rename(target)
            else:
                clouds[(s, i + 1)] = w.clouds[s]
    ds = Dataset(root=staging, robot=parts.robot, sensors=dict(parts.sensors), imu=parts.imu, stations=stations,
                 timeseries=ts, stance={"feet_fixed_within": within})
    report = {"format": "graphcal-import-report/1", "source": str(parts.source),
              "units": "times in s (the log's stamps); stations.csv, clouds and timeseries.csv in SI units",
              "stations": [_window_dict(w, i + 1) for i, w in enumerate(kept)],
              "rejected": [_window_dict(w) for w in rejected], "clock": list(jumps), "notes": list(parts.notes)}
    if parts.sink.thresholds:
        report["contacts"] = parts.sink.contacts_report()
    if parts.walk_cloud_rate_hz is not None and parts.sensors:
        report["walk_clouds"] = {"rate_hz": float(parts.walk_cloud_rate_hz), "sensors": walk_report}
    report_text = yaml.safe_dump(report, sort_keys=False, default_flow_style=None)
    out = write_dataset(ds, out_dir, clouds=clouds, robot_urdf_xml=parts.urdf_xml, overwrite=overwrite,
                        extra_files={"import_map.yaml": parts.map_text, "import_report.yaml": report_text})
    for i, w in enumerate(kept):
        log.info("station %d: %.3f-%.3f s (%.2f s, %d joint and %d IMU samples)", i + 1, w.start, w.end,
                 w.duration, w.n_joint, w.n_imu)
    for w in rejected:
        log.info("rejected %.3f-%.3f s: %s", w.start, w.end, w.reason)
    for j in jumps:
        log.warning("%s", j)
    lines = [f"imported {parts.source} -> {out}: {len(kept)} station(s), {len(rejected)} window(s) rejected"
             + (f", timeseries of {ts.n_rows if hasattr(ts, 'n_rows') else len(ts.data['time'])} samples" if ts else "")]
    lines += [f"  {r['clouds']} cloud(s) of {s} along the walk ({r['first_s']:.2f}-{r['last_s']:.2f} s, "
              f"thinned to {parts.walk_cloud_rate_hz:g} Hz) in timeseries.csv's cloud_{s}"
              for s, r in walk_report.items() if r["clouds"]]
    lines.append(f"  map: {out / 'import_map.yaml'}; report: {out / 'import_report.yaml'}")
    lines += [f"  warning: {j}" for j in jumps] + [f"  note: {n}" for n in parts.notes]
    return out, "\n".join(lines)
