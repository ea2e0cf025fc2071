"""Logs of IMU and body-frame foot contact points (no joint angles): the folder form of GTSAM's
legged sample (``gtsam/Data/legged_staircase``: ``metadata.csv`` with the foot names,
``imu.csv`` -- timestamp_s, omega_x..z (rad/s), acc_x..z (m/s^2), IMU frame -- and
``contacts.csv`` -- one row per foot in stance per contact event: event_index, timestamp_s,
foot_index, foot_name, is_new_contact, body_x..z (m, body frame)).

:func:`foot_point_inputs` makes graphcal's filter inputs of such a folder; :func:`import_foot_points`
writes it as a dataset (docs/dataset.md, "A robot given by its feet"): ``timeseries.csv`` with the
IMU, ``contact_<foot>`` and ``p_body_<foot>_x/_y/_z`` at every sample, and a ``robot.urdf`` of the
feet only (each foot a fixed frame of the body at its mean stance point: legs without joints).

Samples: the IMU's times and the contact events' (as GTSAM's example replays them), the IMU reading
held from its last sample; a foot is in stance from an event that lists it to the next that does
not; its point is measured at the events only (``p_body_measured``); between two events of one
stance it is interpolated linearly in time (held after the last, and before its first) for the
phases and checks that read every sample, never fused by the filter.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from graphcal.errors import DatasetError

__all__ = ["FootPointLog", "is_foot_point_folder", "read_foot_point_folder", "foot_point_inputs",
           "feet_only_urdf", "import_foot_points", "DEFAULT_T_BODY_IMU"]

_FILES = ("metadata.csv", "imu.csv", "contacts.csv")


def _example_T_body_imu() -> np.ndarray:
    """The IMU mount GTSAM's example uses for its sample (``body_P_imu``: 0.30 m ahead, 0.15 m up)."""
    T = np.eye(4)
    T[:3, 3] = [0.30, 0.0, 0.15]
    return T


#: T_body_imu of the sample (GTSAM's example, ``make_legged_estimator_params().body_P_imu``)
DEFAULT_T_BODY_IMU = _example_T_body_imu()


@dataclass(frozen=True, eq=False)
class FootPointLog:
    """A foot-point log read: ``feet`` (names, foot_index order); IMU ``imu_times`` (M,) s,
    ``gyro`` (M, 3) rad/s, ``accel`` (M, 3) m/s^2 (IMU frame); contact events ``event_times`` (E,)
    s, ``event_stance`` (E, n_feet) bool, ``event_p_body`` (E, n_feet, 3) m (NaN where not in
    stance), ``event_touchdown`` (E, n_feet) bool; ``source`` the folder."""

    feet: tuple
    imu_times: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    event_times: np.ndarray
    event_stance: np.ndarray
    event_p_body: np.ndarray
    event_touchdown: np.ndarray
    source: Path


def is_foot_point_folder(path: str | Path) -> bool:
    """Whether ``path`` is a folder of that form (metadata.csv, imu.csv and contacts.csv)."""
    p = Path(path)
    return p.is_dir() and all((p / f).is_file() for f in _FILES)


def _rows(path: Path, columns: tuple) -> list[dict]:
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise DatasetError(path, "file", "a readable CSV file", exc.strerror or str(exc)) from None
    missing = [c for c in columns if rows and c not in rows[0]]
    if not rows or missing:
        raise DatasetError(path, f"header, column {missing[0] if missing else columns[0]}",
                           f"the columns {', '.join(columns)} and at least one row", "missing")
    return rows


def _feet(path: Path) -> tuple:
    with path.open(newline="", encoding="utf-8") as fh:
        for row in csv.reader(fh):
            if row and row[0] == "foot_names":
                return tuple(v for v in row[1:] if v)
    raise DatasetError(path, "row foot_names", "the foot names (foot_names,<foot 0>,<foot 1>,...)", "missing")


def read_foot_point_folder(folder: str | Path) -> FootPointLog:
    """Read the folder (module docstring); DatasetError naming the file and column at fault."""
    folder = Path(folder)
    feet = _feet(folder / "metadata.csv")
    imu = _rows(folder / "imu.csv", ("timestamp_s", "omega_x", "omega_y", "omega_z", "acc_x", "acc_y", "acc_z"))
    A = np.array([[float(r[c]) for c in ("timestamp_s", "omega_x", "omega_y", "omega_z", "acc_x", "acc_y", "acc_z")]
                  for r in imu])
    cols = ("event_index", "timestamp_s", "foot_index", "is_new_contact", "body_x", "body_y", "body_z")
    con = _rows(folder / "contacts.csv", cols)
    ev_index = np.array([int(r["event_index"]) for r in con])
    uniq, first = np.unique(ev_index, return_index=True)
    order = np.argsort(first)
    E, n = len(uniq), len(feet)
    slot = {int(u): i for i, u in enumerate(uniq[order])}
    t_ev = np.empty(E)
    stance = np.zeros((E, n), dtype=bool)
    touch = np.zeros((E, n), dtype=bool)
    P = np.full((E, n, 3), np.nan)
    for r, e in zip(con, ev_index):
        i, f = slot[int(e)], int(r["foot_index"])
        if not 0 <= f < n:
            raise DatasetError(folder / "contacts.csv", "column foot_index", f"0..{n - 1} (metadata.csv's feet)", f)
        t_ev[i] = float(r["timestamp_s"])
        stance[i, f] = True
        touch[i, f] = r["is_new_contact"] == "1"
        P[i, f] = [float(r["body_x"]), float(r["body_y"]), float(r["body_z"])]
    if np.any(np.diff(A[:, 0]) <= 0) or np.any(np.diff(t_ev) < 0):
        raise DatasetError(folder, "timestamp_s", "increasing IMU times and non-decreasing event times", "not")
    return FootPointLog(feet, A[:, 0], A[:, 1:4], A[:, 4:7], t_ev, stance, P, touch, folder)


def _samples(log: FootPointLog) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(times (N,), IMU sample index held at each (N,), event index at each sample or -1 (N,))."""
    t0 = log.imu_times[0]
    ev_t = log.event_times[log.event_times >= t0]
    times = np.union1d(log.imu_times, ev_t)
    held = np.searchsorted(log.imu_times, times, side="right") - 1
    ev_at = np.full(len(times), -1, dtype=np.int64)
    off = len(log.event_times) - len(ev_t)
    ev_at[np.searchsorted(times, ev_t)] = np.arange(len(ev_t)) + off
    return times, held, ev_at


def _foot_tracks(log: FootPointLog, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(stance (N, n_feet) bool, p_body_foot (n_feet, N, 3)) at the samples (module docstring)."""
    E, n = log.event_stance.shape
    k_ev = np.searchsorted(log.event_times, times, side="right") - 1  # the last event at or before
    e = np.maximum(k_ev, 0)
    stance = (k_ev[:, None] >= 0) & log.event_stance[e]
    e1 = np.minimum(e + 1, E - 1)
    span = log.event_times[e1] - log.event_times[e]
    alpha = np.where(span > 0, (times - log.event_times[e]) / np.where(span > 0, span, 1.0), 0.0).clip(0.0, 1.0)
    pbf = np.zeros((n, len(times), 3))
    for f in range(n):
        ok = log.event_stance[:, f]
        if not ok.any():
            continue
        for a in range(3):  # swing samples: any finite value (not measured)
            pbf[f, :, a] = np.interp(times, log.event_times[ok], log.event_p_body[ok, f, a])
        st = stance[:, f]
        same = st & (e1 > e) & log.event_stance[e1, f]  # the next event continues this stance
        P0, P1 = log.event_p_body[e, f], log.event_p_body[e1, f]
        pbf[f, st] = P0[st]
        pbf[f, same] = (1.0 - alpha[same, None]) * P0[same] + alpha[same, None] * P1[same]
    return stance, pbf


def foot_point_inputs(folder_or_log, *, T_body_imu: np.ndarray | None = None):
    """graphcal's filter inputs (:class:`~graphcal.locomotion.track_inputs.TrackInputs`, with
    ``p_body_foot`` and ``contact``) of a folder (or a read :class:`FootPointLog`), and the sample
    index of each contact event (E,) (where GTSAM's example processes its contacts)."""
    from graphcal.locomotion.track_inputs import TrackInputs

    log = folder_or_log if isinstance(folder_or_log, FootPointLog) else read_foot_point_folder(folder_or_log)
    times, held, ev_at = _samples(log)
    stance, pbf = _foot_tracks(log, times)
    robot = feet_only_robot(log.feet, pbf, stance)
    T_bi = DEFAULT_T_BODY_IMU if T_body_imu is None else np.asarray(T_body_imu, dtype=float)
    inp = TrackInputs(times=times, gyro=log.gyro[held], accel=log.accel[held], robot=robot, groups=(), q={},
                      tau=None, contact=stance, T_body_imu=T_bi, source=str(log.source), p_body_foot=pbf,
                      p_body_measured=ev_at >= 0)
    return inp, np.flatnonzero(ev_at >= 0)


def feet_only_urdf(feet: tuple, p_body_foot: np.ndarray, stance: np.ndarray, *, name: str = "feet_only") -> str:
    """A URDF of the feet only: link ``body`` and one link per foot on a fixed joint at the foot's
    mean stance point (m, body frame): legs without joints (the points come with the data)."""
    parts = [f'<robot name="{name}">', '  <link name="body"/>']
    for i, f in enumerate(feet):
        m = stance[:, i]
        p = p_body_foot[i, m].mean(axis=0) if m.any() else np.zeros(3)
        parts += [f'  <link name="{f}"/>', f'  <joint name="{f}_mount" type="fixed"><parent link="body"/>'
                  f'<child link="{f}"/><origin xyz="{p[0]:.4f} {p[1]:.4f} {p[2]:.4f}" rpy="0 0 0"/></joint>']
    return "\n".join(parts + ["</robot>", ""])


def feet_only_robot(feet: tuple, p_body_foot: np.ndarray, stance: np.ndarray):
    """The :class:`~graphcal.models.robot.RobotModel` of :func:`feet_only_urdf`."""
    from graphcal.models.robot import load_robot

    return load_robot(urdf_xml=feet_only_urdf(feet, p_body_foot, stance), base_frame="body", feet=feet)


def _dataset(inp, ground: str):
    from graphcal.geometry import rpy_from_matrix
    from graphcal.io.dataset.model import Dataset, ImuSpec, PosePrior, RobotSpec, Table

    cols = {"time": inp.times}
    for k, c in enumerate(("imu_ax", "imu_ay", "imu_az")):
        cols[c] = inp.accel[:, k]
    for k, c in enumerate(("imu_gx", "imu_gy", "imu_gz")):
        cols[c] = inp.gyro[:, k]
    for i, f in enumerate(inp.robot.feet):
        cols[f"contact_{f}"] = inp.contact[:, i].astype(float)
        for a, ax in enumerate("xyz"):
            cols[f"p_body_{f}_{ax}"] = inp.p_body_foot[i, :, a]
    cols["p_body_measured"] = inp.p_body_measured.astype(float)
    T = inp.T_body_imu
    imu = ImuSpec(PosePrior(T[:3, 3], rpy_from_matrix(T[:3, :3]), 0.0, 0.0))
    robot = RobotSpec("robot.urdf", None, "body", tuple(inp.robot.feet))
    # not declared level: a log of this form may climb (the sample does: 5 m of stairs), and on declared
    # level ground the filter would hold every touchdown at the starting floor's height
    return Dataset(robot=robot, imu=imu, ground={"type": ground}, timeseries=Table(tuple(cols), cols))


def import_foot_points(folder: str | Path, out_dir: str | Path, *, overwrite: bool = False,
                       ground: str = "uneven") -> tuple[Path, str]:
    """Write the folder as a dataset (module docstring) with ``import_report.yaml`` and
    ``ground: {type: <ground>}`` (not ``level`` by default); returns (the dataset folder, a summary text)."""
    import yaml

    from graphcal.io.dataset.write import write_dataset

    inp, events = foot_point_inputs(folder)
    urdf = feet_only_urdf(inp.robot.feet, inp.p_body_foot, inp.contact)
    report = {"source": str(Path(folder)), "form": "foot points (IMU, body-frame foot contact points)",
              "samples": int(len(inp.times)), "contact_events": int(len(events)),
              "duration_s": float(inp.times[-1] - inp.times[0]), "feet": list(inp.robot.feet),
              "duty_factor": {f: float(inp.contact[:, i].mean()) for i, f in enumerate(inp.robot.feet)},
              "T_body_imu_xyz_m": [float(v) for v in inp.T_body_imu[:3, 3]],
              "notes": ["IMU held from its last sample at the contact events' times",
                        "foot points measured at the contact events only (p_body_measured 1); interpolated "
                        "linearly between a stance's events for the bookkeeping, never used as measurements"]}
    out = write_dataset(_dataset(inp, ground), out_dir, robot_urdf_xml=urdf, overwrite=overwrite,
                        extra_files={"import_report.yaml": yaml.safe_dump(report, sort_keys=False)})
    summary = (f"graphcal import: {len(inp.times)} samples ({report['duration_s']:.1f} s), {len(events)} contact "
               f"events of {len(inp.robot.feet)} feet ({', '.join(inp.robot.feet)}) -> {out}\n"
               f"  a robot given by its feet (robot.urdf: fixed foot frames); report: {Path(out) / 'import_report.yaml'}")
    return Path(out), summary
