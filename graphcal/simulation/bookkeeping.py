"""Bookkeeping errors hidden in simulated datasets, for the bookkeeping battery
(examples/diagnosis_bookkeeping.py).

Each generator takes a written dataset folder (``src``, as ``graphcal simulate --output planes``
writes it) and writes a mutated copy (``dst``) without ``truth.yaml``; it returns a
:class:`BookkeepingTruth` (the cause, a name of
:data:`graphcal.diagnosis.bookkeeping.BOOKKEEPING_CAUSES`, its place and the value the data should
hold). File edits: :func:`exchange_stations`, :func:`mislabel_row`, :func:`exchange_legs`,
:func:`flip_normal_sign`, :func:`opposite_convention`, :func:`distance_unit`; simulated:
:func:`splice_stations` (height steps, :func:`height_step_config`) and :func:`knock_config`.
:func:`make_case` draws one case of a kind (:data:`DEV_KINDS`, :data:`BLIND_KINDS`) from a seed.
Units are the contract's (m, rad; planes in the sensor frame). The kinds: docs/diagnosis.md,
"Bookkeeping battery".
"""

from __future__ import annotations

import csv
import io
import shutil
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import yaml

from graphcal.errors import GraphcalError

__all__ = [
    "BookkeepingTruth", "DEV_KINDS", "BLIND_KINDS", "KIND_CAUSE", "exchange_stations", "mislabel_row",
    "exchange_legs", "flip_normal_sign", "opposite_convention", "distance_unit", "splice_stations",
    "height_step_config", "knock_config", "base_config", "simulate_base", "make_case", "leg_pairs",
]

#: the kinds the finders are developed against (their seeds: ``first_seed`` 1000 in the battery)
DEV_KINDS = ("stations_exchanged", "station_mislabelled", "legs_exchanged", "normal_sign", "plane_convention",
             "distance_unit", "height_step_mid", "height_step_first", "height_step_last", "knock_mid",
             "knock_first", "knock_last", "clean")
#: the hold-out kinds (run once, at the end, on other seeds and one more robot): exchanged stations
#: far apart, mirrored legs, the sign of the second-largest normal component, centimetres
BLIND_KINDS = ("stations_exchanged_far", "station_mislabelled", "legs_exchanged_mirror", "normal_sign_second",
               "plane_convention", "distance_unit_cm", "height_step_mid", "height_step_first", "height_step_last",
               "knock_mid", "knock_first", "knock_last", "clean")
#: kind -> the bookkeeping cause it hides ("" for clean data)
KIND_CAUSE = {
    "stations_exchanged": "stations_exchanged", "stations_exchanged_far": "stations_exchanged",
    "station_mislabelled": "station_mislabelled", "legs_exchanged": "legs_exchanged",
    "legs_exchanged_mirror": "legs_exchanged", "normal_sign": "normal_sign", "normal_sign_second": "normal_sign",
    "plane_convention": "plane_convention", "distance_unit": "distance_unit", "distance_unit_cm": "distance_unit",
    "height_step_mid": "height_step", "height_step_first": "height_step", "height_step_last": "height_step",
    "knock_mid": "extrinsic_knock", "knock_first": "extrinsic_knock", "knock_last": "extrinsic_knock", "clean": "",
}
#: an undeclared height step, m (|h|; the sign is drawn): the session_offset range of the diagnosis battery
HEIGHT_STEP_M = (0.010, 0.035)
#: a knock's rotation, rad (the extrinsic_change range of the diagnosis battery)
KNOCK_RAD = (float(np.radians(1.5)), float(np.radians(3.0)))
N_STATIONS = 48
N_SESSIONS = 3
HEADING_STEP_DEG = 40.0


@dataclass(frozen=True)
class BookkeepingTruth:
    """What a generator hid.

    Attributes:
        kind: the generator's kind (:data:`KIND_CAUSE`).
        cause: a bookkeeping cause, "" for clean data.
        where: the place, as a dict: ``stations`` (ids as in stations.csv), ``sensor``, ``legs``
            (foot frames), ``component`` (0-2: nx, ny, nz), ``from_station`` (the first station of
            the new state, height steps and knocks), ``station`` (the station a row is filed under).
        corrected: the true values (SI units: metres, radians, unit normals).
        ambiguous: the data cannot tell this cause from another (a knock with one station on one
            side, the first or the last: an outlier station reads the same); a note naming the
            place counts as an honest answer. A height step is never ambiguous: even at one station
            it moves the plane distance alone.
    """

    kind: str
    cause: str
    where: dict = field(default_factory=dict)
    corrected: dict = field(default_factory=dict)
    ambiguous: bool = False

    def to_dict(self) -> dict:
        return {"kind": self.kind, "cause": self.cause, "where": _plain(self.where),
                "corrected": _plain(self.corrected), "ambiguous": bool(self.ambiguous)}


def _plain(v):
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_plain(x) for x in v]
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    return v


# ----------------------------------------------------------------------------- files
def _read(path: Path) -> tuple[list[str], list[list[str]]]:
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    return rows[0], rows[1:]


def _write(path: Path, header: list[str], rows: list[list[str]]) -> None:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    w.writerows(rows)
    path.write_text(buf.getvalue())


def _copy(src: Path, dst: Path) -> None:
    """``src`` copied to ``dst`` (replaced), without the simulator's truth files."""
    src, dst = Path(src), Path(dst)
    if not (src / "dataset.yaml").is_file():
        raise GraphcalError(f"{src}: not a dataset folder (no dataset.yaml)")
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("truth.yaml", "truth_trajectory.csv"))


def _plane_row(rows: list[list[str]], header: list[str], station: int, sensor: str) -> int:
    ci, cs = header.index("station"), header.index("sensor")
    hits = [k for k, r in enumerate(rows) if int(r[ci]) == int(station) and r[cs] == sensor]
    if len(hits) != 1:
        raise GraphcalError(f"planes.csv: expected one row of station {station}, sensor {sensor}; found {len(hits)}")
    return hits[0]


def _normal(row: list[str], header: list[str]) -> np.ndarray:
    return np.array([float(row[header.index(c)]) for c in ("nx", "ny", "nz")])


def exchange_stations(src: Path, dst: Path, a: int, b: int) -> BookkeepingTruth:
    """Stations ``a`` and ``b`` exchange their sensor data (every planes.csv row, every sensor);
    their joints, IMU and commanded poses stay (stations.csv)."""
    _copy(src, dst)
    header, rows = _read(Path(dst) / "planes.csv")
    ci = header.index("station")
    swap = {str(a): str(b), str(b): str(a)}
    for r in rows:
        r[ci] = swap.get(str(int(r[ci])), r[ci])
    rows.sort(key=lambda r: int(r[ci]))  # stable: a station's rows keep their order
    _write(Path(dst) / "planes.csv", header, rows)
    return BookkeepingTruth("stations_exchanged", "stations_exchanged", {"stations": sorted((int(a), int(b)))})


def mislabel_row(src: Path, dst: Path, station: int, sensor: str, to_station: int) -> BookkeepingTruth:
    """``sensor``'s row of ``station`` is filed under ``to_station``, whose own row of that sensor is
    lost (overwritten); ``station`` has no row of ``sensor``."""
    _copy(src, dst)
    header, rows = _read(Path(dst) / "planes.csv")
    k_from, k_to = _plane_row(rows, header, station, sensor), _plane_row(rows, header, to_station, sensor)
    moved = list(rows[k_from])
    moved[header.index("station")] = str(int(to_station))
    rows[k_to] = moved
    del rows[k_from]
    _write(Path(dst) / "planes.csv", header, rows)
    return BookkeepingTruth("station_mislabelled", "station_mislabelled",
                            {"sensor": sensor, "station": int(to_station), "stations": sorted((int(station), int(to_station)))},
                            {"belongs_to_station": int(station)})


def _robot(folder: Path):
    from graphcal.io.dataset.read import read_dataset
    from graphcal.io.dataset.robot import load_dataset_robot

    return load_dataset_robot(read_dataset(folder))


def exchange_legs(src: Path, dst: Path, foot_a: str, foot_b: str) -> BookkeepingTruth:
    """The joint columns (``q_``, ``tau_``) of the legs of ``foot_a`` and ``foot_b`` exchanged in
    stations.csv, joint by joint along the chain (the legs must have as many joints)."""
    robot = _robot(Path(src))
    ja, jb = robot.legs[foot_a].joint_names, robot.legs[foot_b].joint_names
    if len(ja) != len(jb):
        raise GraphcalError(f"legs {foot_a} and {foot_b} have {len(ja)} and {len(jb)} joints")
    _copy(src, dst)
    header, rows = _read(Path(dst) / "stations.csv")
    rename = {}
    for prefix in ("q_", "tau_"):
        for x, y in zip(ja, jb):
            if prefix + x in header:
                rename[prefix + x], rename[prefix + y] = prefix + y, prefix + x
    header = [rename.get(c, c) for c in header]
    _write(Path(dst) / "stations.csv", header, rows)
    return BookkeepingTruth("legs_exchanged", "legs_exchanged", {"legs": sorted((foot_a, foot_b))},
                            {"joints": [list(ja), list(jb)]})


def _edit_plane(src: Path, dst: Path, station: int, sensor: str, edit) -> tuple[np.ndarray, float, np.ndarray, float]:
    """Apply ``edit(n, d) -> (n', d')`` to one plane; returns (n, d, n', d')."""
    _copy(src, dst)
    header, rows = _read(Path(dst) / "planes.csv")
    k = _plane_row(rows, header, station, sensor)
    n, d = _normal(rows[k], header), float(rows[k][header.index("d")])
    n2, d2 = edit(n.copy(), d)
    for c, v in zip(("nx", "ny", "nz", "d"), (*n2, d2)):
        rows[k][header.index(c)] = repr(float(v))
    _write(Path(dst) / "planes.csv", header, rows)
    return n, d, n2, d2


def flip_normal_sign(src: Path, dst: Path, station: int, sensor: str, component: int) -> BookkeepingTruth:
    """Component ``component`` (0, 1, 2: nx, ny, nz) of one plane's normal with the wrong sign."""

    def edit(n, d):
        n[component] = -n[component]
        return n, d

    n, d, n2, _ = _edit_plane(src, dst, station, sensor, edit)
    return BookkeepingTruth("normal_sign", "normal_sign", {"station": int(station), "sensor": sensor,
                                                           "component": int(component)},
                            {"n_given": n2.tolist(), "n_corrected": n.tolist()})


def opposite_convention(src: Path, dst: Path, station: int, sensor: str) -> BookkeepingTruth:
    """One plane in the opposite convention: n . x = d with n pointing away from the sensor,
    written (-n, d) where the contract's n . x + d = 0 has (n, d)."""
    n, d, n2, _ = _edit_plane(src, dst, station, sensor, lambda n, d: (-n, d))
    return BookkeepingTruth("plane_convention", "plane_convention", {"station": int(station), "sensor": sensor},
                            {"n_given": n2.tolist(), "n_corrected": n.tolist(), "d_m": d})


def distance_unit(src: Path, dst: Path, station: int, sensor: str, factor: float = 1000.0) -> BookkeepingTruth:
    """One plane's d written in millimetres (``factor`` 1000) or centimetres (100)."""
    n, d, _, d2 = _edit_plane(src, dst, station, sensor, lambda n, d: (n, d * factor))
    return BookkeepingTruth("distance_unit", "distance_unit", {"station": int(station), "sensor": sensor},
                            {"d_given": d2, "d_corrected_m": d, "factor": float(factor)})


def splice_stations(src: Path, other: Path, dst: Path, stations) -> None:
    """``src`` with every file row of ``stations`` (stations.csv, planes.csv) taken from ``other``
    (a simulation of the same program and seed, with another effect hidden)."""
    _copy(src, dst)
    wanted = {int(s) for s in stations}
    for name in ("stations.csv", "planes.csv"):
        header, rows = _read(Path(dst) / name)
        h2, rows2 = _read(Path(other) / name)
        if h2 != header:
            raise GraphcalError(f"{other / name}: columns differ from {src / name}")
        ci = header.index("station")
        merged = [r for r in rows if int(r[ci]) not in wanted] + [r for r in rows2 if int(r[ci]) in wanted]
        merged.sort(key=lambda r: int(r[ci]))
        _write(Path(dst) / name, header, merged)


# ----------------------------------------------------------------------------- simulation
def base_config(robot: str, seed: int, *, custom_robot=None, n_stations: int = N_STATIONS,
                n_sessions: int = N_SESSIONS):
    """The battery's simulation: the ``random`` program on level ground, planes only, sessions
    turned by 40 deg (as examples/diagnosis_battery.py); ``custom_robot``: a
    :class:`~graphcal.simulation.session.CustomRobot` (then ``robot`` is its name)."""
    from graphcal.simulation.session import SimulationConfig

    return SimulationConfig(robot=robot, program="random", ground="level", seed=int(seed), n_stations=n_stations,
                            n_sessions=n_sessions, cloud_stride=8, session_heading_step_deg=HEADING_STEP_DEG,
                            custom_robot=custom_robot)


def height_step_config(config, offset_m: float):
    """``config`` with every session's feet sunk by ``offset_m`` (m; < 0: raised), nothing else changed."""
    from graphcal.simulation.effects import Effects

    sessions = [f"s{k + 1}" for k in range(config.n_sessions)]
    return replace(config, effects=Effects(session_offset={s: float(offset_m) for s in sessions}))


def knock_config(config, sensor: str, station: int, angle_rad: float, axis):
    """``config`` with ``sensor`` knocked just before ``station`` (rotated by ``angle_rad`` about the
    body-frame unit ``axis``)."""
    from graphcal.simulation.effects import Effects, ExtrinsicChange

    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    change = ExtrinsicChange(sensor, int(station), float(angle_rad), tuple(float(a) for a in axis))
    return replace(config, effects=Effects(extrinsic_change=change))


def simulate_base(config, folder: Path) -> Path:
    """Simulate ``config`` into ``folder`` (planes only) unless it is there already (a cache: the
    folder is reused when its dataset.yaml exists). Returns ``folder``."""
    from graphcal.simulation.session import simulate
    from graphcal.simulation.write import write_simulation

    folder = Path(folder)
    if (folder / "dataset.yaml").is_file() and (folder / "planes.csv").is_file():
        return folder
    tmp = folder.with_name(folder.name + ".partial")
    write_simulation(simulate(config), tmp, output="planes", overwrite=True)
    if folder.exists():
        shutil.rmtree(folder)
    tmp.rename(folder)
    return folder


def _standable_base(config, cache: Path) -> tuple:
    """(config, folder) of the clean base: a drawn program the robot cannot stand is drawn again
    from a derived seed (seed + 1000 k), deterministically, as the diagnosis battery does."""
    last = None
    for attempt in range(3):
        c = replace(config, seed=config.seed + 1000 * attempt)
        try:
            return c, simulate_base(c, Path(cache) / f"{c.robot}_{c.seed}" / "clean")
        except GraphcalError as exc:
            if "cannot reach" not in str(exc) and "cannot stay planted" not in str(exc):
                raise
            last = exc
    raise last


def _stations_sessions_sensors(folder: Path) -> tuple[list[int], list[str], list[str]]:
    header, rows = _read(Path(folder) / "stations.csv")
    ids = [int(r[header.index("station")]) for r in rows]
    sessions = [r[header.index("session")] for r in rows] if "session" in header else ["s1"] * len(ids)
    ph, prow = _read(Path(folder) / "planes.csv")
    sensors = sorted({r[ph.index("sensor")] for r in prow})
    return ids, sessions, sensors


def leg_pairs(folder: Path, how: str = "neighbour") -> list[tuple[str, str]]:
    """Pairs of feet whose joint columns a logger could exchange: ``neighbour`` (each foot and the
    foot nearest it on the same side, at the first station's measured joints) or ``mirror`` (each foot and the one
    nearest its mirror image across the body's x-z plane)."""
    from graphcal.models.kinematics import fk_leg

    robot = _robot(Path(folder))
    header, rows = _read(Path(folder) / "stations.csv")
    p = {}
    for f in robot.feet:
        leg = robot.legs[f]
        q = np.array([float(rows[0][header.index(f"q_{j}")]) for j in leg.joint_names])
        p[f] = np.asarray(fk_leg(leg, q))[:3, 3]  # T_base_foot (4, 4) of one configuration
    out = set()
    for f in robot.feet:
        target = p[f] * (np.array([1.0, -1.0, 1.0]) if how == "mirror" else 1.0)
        others = [g for g in robot.feet if g != f and len(robot.legs[g].joint_names) == len(robot.legs[f].joint_names)
                  and (how == "mirror" or np.sign(p[g][1]) == np.sign(p[f][1]))]  # neighbours: the same side
        g = min(others, key=lambda o: float(np.linalg.norm((p[o] - target)[:2])))
        out.add(tuple(sorted((f, g))))
    return sorted(out)


def _kind_rng(kind: str, seed: int) -> np.random.Generator:
    import zlib

    return np.random.default_rng([int(seed), zlib.crc32(kind.encode())])


def _pick_plane(rng, folder: Path, ids: list[int], sensors: list[str], rank: int | None = None):
    """(station, sensor, component) of a plane drawn from ``rng``; with ``rank`` (0: largest) the
    component of that rank in |n|, drawn again until |n_component| >= 0.2 (a sign flip of a
    near-zero component changes nothing the data can show)."""
    header, rows = _read(Path(folder) / "planes.csv")
    for _ in range(200):
        station, sensor = int(rng.choice(ids)), str(rng.choice(sensors))
        try:
            k = _plane_row(rows, header, station, sensor)
        except GraphcalError:
            continue  # no plane of that sensor there
        if rank is None:
            return station, sensor, -1
        n = _normal(rows[k], header)
        comp = int(np.argsort(-np.abs(n))[rank])
        if abs(n[comp]) >= 0.2:
            return station, sensor, comp
    raise GraphcalError(f"{folder}: no plane to edit")


def _edit_case(kind: str, rng, base: Path, dst: Path, ids: list[int], sensors: list[str]) -> BookkeepingTruth:
    """The kinds that edit files of the clean base."""
    if kind in ("stations_exchanged", "stations_exchanged_far"):
        gap = int(rng.integers(1, 4)) if kind == "stations_exchanged" else int(rng.integers(8, 21))
        k = int(rng.integers(0, len(ids) - gap))
        return replace(exchange_stations(base, dst, ids[k], ids[k + gap]), kind=kind)
    if kind == "station_mislabelled":
        gap = int(rng.integers(1, 4)) * int(rng.choice([-1, 1]))
        k = int(rng.integers(3, len(ids) - 3))
        return mislabel_row(base, dst, ids[k], str(rng.choice(sensors)), ids[k + gap])
    if kind in ("legs_exchanged", "legs_exchanged_mirror"):
        pairs = leg_pairs(base, "mirror" if kind.endswith("mirror") else "neighbour")
        a, b = pairs[int(rng.integers(len(pairs)))]
        return replace(exchange_legs(base, dst, a, b), kind=kind)
    if kind in ("normal_sign", "normal_sign_second"):
        station, sensor, comp = _pick_plane(rng, base, ids, sensors, rank=0 if kind == "normal_sign" else 1)
        return replace(flip_normal_sign(base, dst, station, sensor, comp), kind=kind)
    if kind == "plane_convention":
        station, sensor, _ = _pick_plane(rng, base, ids, sensors)
        return opposite_convention(base, dst, station, sensor)
    if kind in ("distance_unit", "distance_unit_cm"):
        station, sensor, _ = _pick_plane(rng, base, ids, sensors)
        return replace(distance_unit(base, dst, station, sensor, 1000.0 if kind == "distance_unit" else 100.0), kind=kind)
    raise GraphcalError(f"unknown kind {kind!r}; expected one of {', '.join(KIND_CAUSE)}")


def _step_block(kind: str, rng, ids: list[int], sessions: list[str]) -> tuple[list[int], int]:
    """(stations at the new height, first station after the boundary) of a height step."""
    m = int(rng.integers(1, 3))
    if kind == "height_step_first":
        return ids[:m], ids[m]
    if kind == "height_step_last":
        return ids[-m:], ids[-m]
    labels = list(dict.fromkeys(sessions))
    s = str(rng.choice(labels))
    idx = [i for i, x in enumerate(sessions) if x == s]
    k = int(rng.integers(idx[0] + 3, idx[-1] - 1))  # >= 3 stations before, >= 2 at the new height
    block = [ids[i] for i in range(k, idx[-1] + 1)]
    return block, ids[k]


def _sim_case(kind: str, rng, config, base: Path, cache: Path, dst: Path, ids, sessions, sensors) -> BookkeepingTruth:
    """The kinds the simulator makes: undeclared height steps (spliced from a sunk twin) and knocks."""
    root = Path(cache) / f"{config.robot}_{config.seed}"
    if kind.startswith("height_step"):
        h = float(rng.uniform(*HEIGHT_STEP_M)) * float(rng.choice([-1.0, 1.0]))
        block, boundary = _step_block(kind, rng, ids, sessions)
        twin = simulate_base(height_step_config(config, h), root / f"step_{h:+.5f}")
        splice_stations(base, twin, dst, block)
        # never ambiguous: even at one station a height step moves d alone, which a knock (a rotation)
        # or another station's data do not
        return BookkeepingTruth(kind, "height_step", {"from_station": boundary, "stations": block},
                                {"offset_m": h, "note": "offset_m > 0: the feet of these stations sank by it"})
    m = int(rng.integers(1, 3))
    if kind == "knock_first":
        k = ids[m]  # m stations before the knock
    elif kind == "knock_last":
        k = ids[-m]  # m stations after it, k included
    elif kind == "knock_mid":
        k = ids[int(rng.integers(len(ids) // 3, 2 * len(ids) // 3))]
        m = 3
    else:
        raise GraphcalError(f"unknown kind {kind!r}; expected one of {', '.join(KIND_CAUSE)}")
    sensor = str(rng.choice(sensors))
    angle = float(rng.uniform(*KNOCK_RAD))
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    folder = simulate_base(knock_config(config, sensor, k, angle, axis), root / f"knock_{sensor}_{k}_{angle:.5f}")
    _copy(folder, dst)
    return BookkeepingTruth(kind, "extrinsic_knock", {"sensor": sensor, "from_station": k},
                            {"angle_rad": angle, "axis": axis.tolist()}, m == 1)


def make_case(kind: str, robot: str, seed: int, cache: Path, dst: Path, *, custom_robot=None) -> BookkeepingTruth:
    """Write the dataset of one battery case to ``dst``: ``robot``'s clean base of ``seed`` (simulated
    once into ``cache``) with one bookkeeping error of ``kind`` drawn from the seed; returns its truth
    (also written as ``dst``'s sibling ``<dst name>.truth.yaml``, outside the dataset folder)."""
    if kind not in KIND_CAUSE:
        raise GraphcalError(f"unknown kind {kind!r}; expected one of {', '.join(KIND_CAUSE)}")
    config, base = _standable_base(base_config(robot, seed, custom_robot=custom_robot), Path(cache))
    rng = _kind_rng(kind, seed)
    ids, sessions, sensors = _stations_sessions_sensors(base)
    if kind == "clean":
        _copy(base, dst)
        truth = BookkeepingTruth("clean", "")
    elif kind.startswith(("height_step", "knock")):
        truth = _sim_case(kind, rng, config, base, Path(cache), Path(dst), ids, sessions, sensors)
    else:
        truth = _edit_case(kind, rng, base, Path(dst), ids, sensors)
    Path(dst).with_name(Path(dst).name + ".truth.yaml").write_text(
        yaml.safe_dump({**truth.to_dict(), "robot": robot, "seed": int(config.seed)}, sort_keys=False))
    return truth
