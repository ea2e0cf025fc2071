"""Simulated motion capture of legs with kinematic errors (for leg identification, Yuan et al.).

The robot's body is held still in the motion-capture room (``T_mocap_body``) while its legs move
through random joint configurations (uniform within the joint limits, or within given ranges); the
"true" robot is the nominal URDF with a :class:`~graphcal.models.perturb.LegPerturbation` applied
(:func:`~graphcal.models.perturb.apply_perturbation`). Each sample records

* the joint values the encoders report: the configuration plus joint noise;
* one marker per simulated foot (named after the foot frame), at ``p_foot_marker`` in the true
  foot frame, plus marker noise;
* optionally the four body markers ``body.1 ... body.4`` (Yuan's virtual base, counter-clockwise
  from the left front) on a rectangle on the body. ``dataset.yaml`` lists their NOMINAL layout
  (``mocap.markers``); the true layout may be displaced by ``T_layout_error`` (Yuan's alpha_h,
  z_h: markers glued slightly rotated and higher than the drawing says).

Noise: ``"uniform"`` draws from ``[-a, a]`` (Yuan's +-1 deg, +-1 mm; standard deviation ``a / sqrt 3``),
``"gaussian"`` from ``N(0, a^2)``.

:func:`simulate_mocap` returns a :class:`MocapSimulation` (an in-memory
:class:`~graphcal.io.dataset.Dataset` and the truth); :func:`write_mocap_simulation` writes it with
``truth.yaml`` beside ``dataset.yaml``. Units: metres, radians.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.geometry import invert_pose, pose_from_xyz_rpy, xyz_quat_wxyz_from_pose
from graphcal.io.calibration_yaml import pose_to_dict
from graphcal.models.perturb import LegPerturbation, apply_perturbation

__all__ = [
    "DEFAULT_T_MOCAP_BODY",
    "a1_body_marker_layout",
    "MocapSimulation",
    "simulate_mocap",
    "write_mocap_simulation",
    "YUAN_FOOT",
    "YUAN_PERTURBATION",
    "YUAN_LAYOUT_ERROR",
    "simulate_yuan_session",
]

#: the body somewhere in the motion-capture room (m, rad): 1.2 m forward, 0.3 m up, turned 30 deg
DEFAULT_T_MOCAP_BODY = pose_from_xyz_rpy([1.2, -0.4, 0.3], np.radians([2.0, -1.0, 30.0]))
DEFAULT_T_MOCAP_BODY.setflags(write=False)

#: Yuan et al.'s Table I set-up: the A1's front-left leg in the air, its foot marked
YUAN_FOOT = "fl_foot"
#: the errors Yuan et al. injected (Table I): joint zeros 1, 1.5, 2 deg; the hip-thigh offset omega
#: +3.8 mm, the thigh and calf 10 and 20 mm longer
YUAN_PERTURBATION = LegPerturbation(
    {"fl_hip_joint": float(np.radians(1.0)), "fl_thigh_joint": float(np.radians(1.5)),
     "fl_calf_joint": float(np.radians(2.0))},
    {"fl_thigh_joint": (0.0, 0.0038, 0.0), "fl_calf_joint": (0.0, 0.0, -0.010), "fl_foot_joint": (0.0, 0.0, -0.020)},
)
#: the true body-marker layout of Table I: turned by alpha_h = 3 deg and 5 mm higher than drawn
YUAN_LAYOUT_ERROR = pose_from_xyz_rpy([0.0, 0.0, 0.005], [0.0, 0.0, float(np.radians(3.0))])
YUAN_LAYOUT_ERROR.setflags(write=False)


def a1_body_marker_layout(height_m: float = 0.06, half_length_m: float = 0.15, half_width_m: float = 0.07) -> np.ndarray:
    """(4, 3) nominal body markers in the body frame: a rectangle ``height_m`` above the body
    origin (Yuan's z_h = 0.06 m), counter-clockwise from the left front (body.1 ... body.4)."""
    a, b, h = half_length_m, half_width_m, height_m
    return np.array([[a, b, h], [-a, b, h], [-a, -b, h], [a, -b, h]], dtype=float)


@dataclass(frozen=True, eq=False)
class MocapSimulation:
    """A simulated motion-capture session.

    Attributes:
        dataset: the :class:`~graphcal.io.dataset.Dataset` (stations.csv + mocap.csv, root None).
        truth: plain dict for ``truth.yaml``.
        urdf_true: the perturbed ("true") URDF.
        q_true: foot -> (N, n) joint values without encoder noise (the configurations).
        T_body_mocap_true: (4, 4) the true measurement frame in the body frame: the virtual base of
            the true body markers (with body markers), else the motion-capture frame.
        robot_urdf: URDF text to write as robot.urdf (custom robot), or None (built-in model).
    """

    dataset: object
    truth: dict
    urdf_true: str
    q_true: dict
    T_body_mocap_true: np.ndarray
    robot_urdf: str | None = None


def _noise(rng, kind: str, a: float, shape) -> np.ndarray:
    if a == 0.0:
        return np.zeros(shape)
    if kind == "uniform":
        return rng.uniform(-a, a, size=shape)
    if kind == "gaussian":
        return rng.normal(0.0, a, size=shape)
    raise GraphcalError(f"noise must be 'uniform' or 'gaussian', got {kind!r}")


def simulate_mocap(
    model: str | None = "a1",
    *,
    urdf_xml: str | None = None,
    base_frame: str = "body",
    feet: Sequence[str] = ("fl_foot",),
    n_samples: int = 1000,
    perturbation: LegPerturbation = LegPerturbation(),
    joint_noise_rad: float = 0.0,
    marker_noise_m: float = 0.0,
    noise: str = "uniform",
    body_markers: bool = True,
    body_marker_noise_m: float | None = None,
    body_marker_layout=None,
    T_layout_error=None,
    T_mocap_body=None,
    p_foot_marker: Mapping[str, Sequence[float]] | None = None,
    marker_xyz_known: bool = True,
    q_ranges: Mapping[str, tuple[float, float]] | None = None,
    seed: int = 0,
    pose_sigma: Sequence[float] | None = None,
    foot_markers: bool = True,
) -> MocapSimulation:
    """Simulate a motion-capture session of legs held in the air (body fixed).

    Args:
        model: built-in robot model (default ``"a1"``), or None with ``urdf_xml``.
        urdf_xml: a custom robot's URDF text (written as robot.urdf).
        base_frame: the body frame.
        feet: the feet that carry a marker (their legs move).
        n_samples: number of samples (stations).
        perturbation: the true robot's kinematic errors.
        joint_noise_rad: encoder noise amplitude (half-width for uniform, sigma for gaussian), rad.
        marker_noise_m: noise amplitude of each marker coordinate, m.
        noise: ``"uniform"`` or ``"gaussian"``.
        body_markers: record body.1 ... body.4 (virtual base) or not (mocap frame fixed to the body).
        body_marker_noise_m: noise amplitude of the body markers (default ``marker_noise_m``).
        body_marker_layout: (4, 3) nominal body markers in the body frame (default
            :func:`a1_body_marker_layout`).
        T_layout_error: (4, 4) true layout = ``T_layout_error`` applied to the nominal one (default identity).
        T_mocap_body: (4, 4) the body in the motion-capture frame (default :data:`DEFAULT_T_MOCAP_BODY`).
        p_foot_marker: foot -> (3,) true marker position in the foot frame, m (default the foot origin).
        marker_xyz_known: write the foot markers' positions into dataset.yaml (else they are unknown).
        q_ranges: joint -> (low, high) sampling range of the true angles, rad / m (default the
            joint limits less the encoder noise, its half-width or 3 sigma, so that the readings stay
            within the limits; +-pi where unlimited).
        seed: random seed.
        pose_sigma: when given, also measure the 6-D pose of every simulated foot frame
            (``mocap_poses.csv``): per-axis sigma [rx, ry, rz (rad), x, y, z (m)] of a Gaussian right
            perturbation ``T_meas = T_true Exp(xi)``, written into the sigma columns.
        foot_markers: record the foot markers (False with ``pose_sigma``: poses only).
    dataset.yaml declares the noise drawn (``mocap.sigma_mm``, ``sigma_joint_deg``; :func:`_declared_noise`).

    Raises:
        GraphcalError / ModelError: bad arguments (unknown foot or joint, n_samples < 1, bad noise kind).
    """
    from graphcal.io.dataset import Dataset, MarkerSpec, RobotSpec, Table
    from graphcal.legs.virtual_base import BODY_MARKERS, virtual_base
    from graphcal.models.kinematics import fk_leg
    from graphcal.models.robot import load_robot

    if n_samples < 1:
        raise GraphcalError(f"n_samples must be >= 1, got {n_samples}")
    if noise not in ("uniform", "gaussian"):
        raise GraphcalError(f"noise must be 'uniform' or 'gaussian', got {noise!r}")
    feet = tuple(feet)
    if model is not None:
        robot = load_robot(model=model, base_frame=base_frame, feet=feet)
    else:
        robot = load_robot(urdf_xml=urdf_xml, base_frame=base_frame, feet=feet)
    urdf_true = apply_perturbation(robot.urdf_xml, perturbation)
    robot_true = load_robot(urdf_xml=urdf_true, base_frame=base_frame, feet=feet)
    rng = np.random.default_rng(seed)
    T_mb = DEFAULT_T_MOCAP_BODY if T_mocap_body is None else np.asarray(T_mocap_body, dtype=float)
    sb = marker_noise_m if body_marker_noise_m is None else float(body_marker_noise_m)
    markers = {} if p_foot_marker is None else {f: np.asarray(v, dtype=float) for f, v in p_foot_marker.items()}
    if set(markers) - set(feet):
        raise GraphcalError(f"p_foot_marker names feet that are not simulated: {sorted(set(markers) - set(feet))}")
    time = np.arange(n_samples) * 0.01
    cols: dict[str, np.ndarray] = {"station": np.arange(n_samples), "time": time}
    q_true = {}
    mocap_rows: list[tuple[float, str, np.ndarray]] = []
    pose_rows: list[dict] = []
    for foot in feet:
        leg = robot.leg(foot)
        # the encoders read the true angle plus noise: drawn this far inside the limits, a reading
        # stays within them (graphcal validate warns about readings beyond a URDF limit)
        margin = joint_noise_rad if noise == "uniform" else 3.0 * joint_noise_rad
        room = np.isfinite(leg.lower) & np.isfinite(leg.upper) & (leg.upper - leg.lower > 4.0 * margin)
        lo = np.where(np.isfinite(leg.lower), leg.lower + np.where(room, margin, 0.0), -np.pi)
        hi = np.where(np.isfinite(leg.upper), leg.upper - np.where(room, margin, 0.0), np.pi)
        for j, name in enumerate(leg.joint_names):
            if q_ranges and name in q_ranges:
                lo[j], hi[j] = q_ranges[name]
        q = rng.uniform(lo, hi, size=(n_samples, leg.n_joints))
        q_true[foot] = q
        for j, name in enumerate(leg.joint_names):
            cols[f"q_{name}"] = q[:, j] + _noise(rng, noise, joint_noise_rad, n_samples)
        T = fk_leg(robot_true.leg(foot), q)
        m = markers.get(foot, np.zeros(3))
        p_body = T[:, :3, 3] + T[:, :3, :3] @ m
        p_mocap = p_body @ T_mb[:3, :3].T + T_mb[:3, 3] + _noise(rng, noise, marker_noise_m, (n_samples, 3))
        if foot_markers:
            mocap_rows += [(float(t), foot, p) for t, p in zip(time, p_mocap)]
        if pose_sigma is not None:
            pose_rows += _pose_rows(rng, foot, time, T_mb @ T, pose_sigma)

    layout = a1_body_marker_layout() if body_marker_layout is None else np.asarray(body_marker_layout, dtype=float)
    T_err = np.eye(4) if T_layout_error is None else np.asarray(T_layout_error, dtype=float)
    layout_true = layout @ T_err[:3, :3].T + T_err[:3, 3]
    if body_markers:
        T_body_meas = virtual_base(layout_true)
        for k, name in enumerate(BODY_MARKERS):
            p = layout_true[k] @ T_mb[:3, :3].T + T_mb[:3, 3]
            pn = p + _noise(rng, noise, sb, (n_samples, 3))
            mocap_rows += [(float(t), name, pn[i]) for i, t in enumerate(time)]
    else:
        T_body_meas = invert_pose(T_mb)
    mocap_rows.sort(key=lambda r: (r[0], r[1]))
    mocap = Table.from_columns({"time": [r[0] for r in mocap_rows], "marker": [r[1] for r in mocap_rows],
                                **{c: [r[2][i] for r in mocap_rows] for i, c in enumerate("xyz")}})
    mspecs = {}
    if body_markers:
        for k, name in enumerate(BODY_MARKERS):
            mspecs[name] = MarkerSpec(base_frame, layout[k])
    if marker_xyz_known:
        for foot in feet:
            mspecs[foot] = MarkerSpec(foot, markers.get(foot, np.zeros(3)))
    spec = RobotSpec(None, model, base_frame, feet) if model is not None else RobotSpec("robot.urdf", None, base_frame, feet)
    ds = Dataset(None, robot=spec, stations=Table.from_columns(cols), mocap=mocap if len(mocap) else None, mocap_markers=mspecs,
                 mocap_poses=_pose_table(pose_rows), mocap_noise=_declared_noise(noise, marker_noise_m, joint_noise_rad))
    truth = {
        "format": "graphcal-truth/1",
        "note": "hidden simulation truth; only evaluations read this file",
        "kind": "mocap",
        "seed": int(seed),
        "legs": {
            "joint_offsets_rad": {k: float(v) for k, v in perturbation.joint_offsets_rad.items()},
            "origin_deltas_m": {k: [float(x) for x in v] for k, v in perturbation.origin_deltas_m.items()},
        },
        "T_mocap_body": pose_to_dict(T_mb),
        "T_body_mocap" if not body_markers else "T_body_vbase": pose_to_dict(T_body_meas),
        "body_markers_true": {n: [float(x) for x in layout_true[k]] for k, n in enumerate(BODY_MARKERS)} if body_markers else {},
        "p_foot_marker": {f: [float(x) for x in markers.get(f, np.zeros(3))] for f in feet},
        "noise": {"kind": noise, "joint_rad": float(joint_noise_rad), "marker_m": float(marker_noise_m),
                  "body_marker_m": float(sb) if body_markers else 0.0,
                  "pose_sigma": None if pose_sigma is None else [float(x) for x in pose_sigma]},
    }
    return MocapSimulation(ds, truth, urdf_true, q_true, T_body_meas, None if model is not None else robot.urdf_xml)


def _declared_noise(kind: str, marker_noise_m: float, joint_noise_rad: float) -> dict:
    """dataset.yaml's ``mocap.sigma_mm`` / ``sigma_joint_deg`` (SI here) as a producer declares its
    sensors: the standard deviation of the noise drawn (uniform half-width a: a / sqrt 3); only
    what is > 0."""
    f = 1.0 / np.sqrt(3.0) if kind == "uniform" else 1.0
    out = {}
    if marker_noise_m > 0:
        out["sigma_m"] = float(marker_noise_m * f)
    if joint_noise_rad > 0:
        out["sigma_joint_rad"] = float(joint_noise_rad * f)
    return out


def _pose_table(pose_rows: list[dict]):
    """mocap_poses.csv as a Table (rows sorted by time, frame), or None without rows."""
    from graphcal.io.dataset import Table

    if not pose_rows:
        return None
    pose_rows = sorted(pose_rows, key=lambda r: (r["time"], r["frame"]))
    return Table.from_columns({k: [r[k] for r in pose_rows] for k in pose_rows[0]})


def _pose_rows(rng, foot: str, time, T_mocap_foot, sigma) -> list[dict]:
    """Rows of mocap_poses.csv: ``T_meas = T_true Exp(xi)``, ``xi ~ N(0, diag(sigma^2))`` (GTSAM order)."""
    import gtsam

    s = np.asarray(sigma, dtype=float).reshape(6)
    if not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise GraphcalError(f"pose_sigma must be six numbers > 0 (rad, rad, rad, m, m, m), got {list(s)}")
    rows = []
    for t, T in zip(time, T_mocap_foot):
        Tm = T @ gtsam.Pose3.Expmap(rng.normal(0.0, s)).matrix()
        xyz, quat = xyz_quat_wxyz_from_pose(Tm)
        row = {"time": float(t), "frame": foot, "x": xyz[0], "y": xyz[1], "z": xyz[2],
               "qw": quat[0], "qx": quat[1], "qy": quat[2], "qz": quat[3]}
        row.update({c: float(v) for c, v in zip(("sigma_rx", "sigma_ry", "sigma_rz", "sigma_x", "sigma_y", "sigma_z"), s)})
        rows.append(row)
    return rows


def simulate_yuan_session(n_samples: int = 1000, seed: int = 2023, *,
                          perturbation: LegPerturbation = YUAN_PERTURBATION) -> MocapSimulation:
    """Yuan et al.'s Table I simulation: the A1's front-left leg through ``n_samples`` random
    configurations, uniform noise of +-1 deg on the encoders and +-1 mm on the foot marker,
    noise-free body markers glued ``YUAN_LAYOUT_ERROR`` off their drawing, the leg's true errors
    ``perturbation`` (default Table I's)."""
    return simulate_mocap(
        "a1", feet=(YUAN_FOOT,), n_samples=n_samples, perturbation=perturbation,
        joint_noise_rad=float(np.radians(1.0)), marker_noise_m=0.001, noise="uniform", body_markers=True,
        body_marker_noise_m=0.0, T_layout_error=YUAN_LAYOUT_ERROR, seed=seed)


def write_mocap_simulation(sim: MocapSimulation, out_dir: str | Path, *, overwrite: bool = False) -> Path:
    """Write ``sim`` as a dataset folder (``dataset.yaml``, ``stations.csv``, ``mocap.csv``, a custom
    robot's ``robot.urdf``) with ``truth.yaml`` beside ``dataset.yaml``, atomically."""
    import yaml

    from graphcal.io.dataset import write_dataset

    return write_dataset(sim.dataset, out_dir, robot_urdf_xml=sim.robot_urdf, overwrite=overwrite,
                         extra_files={"truth.yaml": yaml.safe_dump(sim.truth, sort_keys=False)})
