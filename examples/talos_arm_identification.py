"""Real data: kinematic identification of a TALOS arm from motion capture (61 static postures).

Data: ``examples/data/talos_left_arm_mocap/measurements.csv`` (from figaroh-plus, Apache-2.0;
README there): per posture the joint angles of ``torso_1_joint``, ``torso_2_joint``,
``arm_left_1_joint`` ... ``arm_left_7_joint`` and one marker on the left hand, expressed in a
motion-capture rigid body fixed to the waist. Robot: ``talos_data/robots/talos_reduced.urdf`` of
the PyPI package ``example-robot-data`` (optional extra ``graphcal[talos]``).

An arm is a serial chain like a leg: ``load_robot(..., base_frame="base_link",
feet=("gripper_left_base_link",))`` makes the chain base -> torso -> arm -> hand a "leg" of 9
revolute joints. Unknowns: ``T_body_mocap`` (the waist rigid body in ``base_link``), the marker's
position on the hand, and the leg model of :mod:`graphcal.models.legs` (joint offsets, link
lengths, 3-D position of the first joint; ``origins="all"`` gives every joint a 3-D origin change).

Postures are split once: every third posture (index 2, 5, 8, ...) is for validation only, the
others train. "Nominal" fits only ``T_body_mocap`` and the marker (the URDF as it is); "calibrated"
adds the identifiable leg parameters. Both are evaluated on the validation postures with the pose
and marker of their own training fit.

``main()`` returns the numbers (tests assert them; docs/legs.md quotes them).
Run: ``python examples/talos_arm_identification.py [measurements.csv]``.
"""

from __future__ import annotations

import argparse
import csv
import importlib.metadata
from pathlib import Path

import numpy as np

from graphcal.errors import GraphcalError
from graphcal.factors.mocap_marker import mocap_marker_error
from graphcal.legs.identify import IdentifyOptions, identify_legs
from graphcal.legs.mocap_data import MarkerTrack
from graphcal.models.robot import load_robot

#: the measurements, copied unchanged into the repository (examples/data/talos_left_arm_mocap/README.md)
DEFAULT_DATA = Path(__file__).resolve().parent / "data" / "talos_left_arm_mocap" / "measurements.csv"
URDF_IN_PACKAGE = "cmeel.prefix/share/example-robot-data/robots/talos_data/robots/talos_reduced.urdf"
BASE = "base_link"
HAND = "gripper_left_base_link"
JOINTS = ("torso_1_joint", "torso_2_joint") + tuple(f"arm_left_{i}_joint" for i in range(1, 8))
MARKER = "hand"


def talos_urdf_path() -> Path:
    """Path of talos_reduced.urdf inside the installed example-robot-data distribution.

    Raises:
        GraphcalError: example-robot-data is not installed (``pip install example-robot-data``) or
            does not ship the file.
    """
    try:
        dist = importlib.metadata.distribution("example-robot-data")
    except importlib.metadata.PackageNotFoundError:
        raise GraphcalError("the TALOS example needs the PyPI package example-robot-data "
                            "(pip install 'graphcal[talos]' or pip install example-robot-data)") from None
    for f in dist.files or ():
        if str(f).replace("\\", "/").endswith("talos_data/robots/talos_reduced.urdf"):
            p = Path(f.locate())
            if p.is_file():
                return p
    raise GraphcalError(f"example-robot-data {dist.version} does not ship {URDF_IN_PACKAGE}")


def read_measurements(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t (N,), q (N, 9) in JOINTS order, p_mocap (N, 3)) from the figaroh CSV (SI units).

    Raises:
        GraphcalError: missing file or column, a value that is not a number.
    """
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise GraphcalError(f"{path}: cannot read: {exc.strerror or exc}") from None
    need = ("t", "x1", "y1", "z1") + JOINTS
    if not rows or any(c not in rows[0] for c in need):
        missing = [c for c in need if not rows or c not in rows[0]]
        raise GraphcalError(f"{path}: missing columns {missing}")
    try:
        t = np.array([float(r["t"]) for r in rows])
        q = np.array([[float(r[j]) for j in JOINTS] for r in rows])
        p = np.array([[float(r[c]) for c in ("x1", "y1", "z1")] for r in rows])
    except ValueError as exc:
        raise GraphcalError(f"{path}: not a number: {exc}") from None
    return t, q, p


def _rms_mm(e) -> float:
    return 1e3 * float(np.sqrt(np.mean(np.sum(np.asarray(e) ** 2, axis=1))))


def _validation_errors(res, leg, q, p, *, before: bool) -> np.ndarray:
    model = res.models[HAND]
    if before:
        return mocap_marker_error(res.T_body_mocap_before, np.zeros(model.dim), res.marker_positions_before[MARKER],
                                  q, p, leg, model, False)[0]
    return mocap_marker_error(res.T_body_mocap, res.theta[HAND], res.marker_positions[MARKER], q, p, leg, model, False)[0]


def identify(robot, t, q, p, train, origins: str):
    track = MarkerTrack(MARKER, HAND, t[train], q[train], p[train])
    return identify_legs(robot, [track], options=IdentifyOptions(sigma_marker_m=0.001, origins=origins),
                         source="TALOS left arm (figaroh-plus)")


def main(path: str | Path = DEFAULT_DATA, *, origins: str = "first", every: int = 3) -> dict:
    """Identify the TALOS left arm; returns nominal and calibrated training/validation RMS and the
    identifiable set. ``every``: every ``every``-th posture (from index ``every - 1``) validates."""
    urdf = talos_urdf_path()
    robot = load_robot(urdf, base_frame=BASE, feet=(HAND,))
    leg = robot.leg(HAND)
    if tuple(leg.joint_names) != JOINTS:
        raise GraphcalError(f"unexpected chain {leg.joint_names} in {urdf}")
    t, q, p = read_measurements(path)
    idx = np.arange(len(t))
    val = idx % every == every - 1
    train = ~val
    out = {"postures": int(len(t)), "train": int(train.sum()), "validation": int(val.sum()), "urdf": str(urdf)}
    variants = {}
    for org in dict.fromkeys((origins, "all")):
        res = identify(robot, t, q, p, train, org)
        ident = res.identifiability
        variants[org] = {
            "nominal_train_mm": res.residuals[0].rmse_before_mm,
            "nominal_validation_mm": _rms_mm(_validation_errors(res, leg, q[val], p[val], before=True)),
            "calibrated_train_mm": res.residuals[0].rmse_after_mm,
            "calibrated_validation_mm": _rms_mm(_validation_errors(res, leg, q[val], p[val], before=False)),
            "sigma0": res.sigma0,
            "identifiable": ident.by_status("identifiable"),
            "combination_structural": tuple(x.name for x in ident.parameters if x.status == "combination" and x.structural),
            "combination_weak": tuple(x.name for x in ident.parameters if x.status == "combination" and not x.structural),
            "unidentifiable": ident.by_status("unidentifiable"),
            "free": ident.free,
            "rank": ident.rank,
            "candidates": len(ident.names),
            "found": {x.name: (x.value, x.sigma) for x in res.legs[HAND] if x.free},
            "marker_xyz_m": tuple(float(v) for v in res.marker_positions[MARKER]),
            "texts": {x.name: x.text for x in ident.parameters},
            "result": res,
        }
    out["variants"] = variants
    out["main"] = variants[origins]
    return out


def _print(out: dict) -> None:
    print(f"TALOS left arm: {out['postures']} postures, {out['train']} training, {out['validation']} validation "
          f"(every third); URDF {out['urdf']}")
    for org, v in out["variants"].items():
        print(f"\nleg model origins={org!r}: {v['candidates']} candidate parameters, rank {v['rank']}, "
              f"{len(v['free'])} estimated; sigma0 {v['sigma0']:.2f} (a-priori marker noise 1 mm)")
        for label, key in (("nominal (pose + marker fitted):", "nominal"), ("calibrated:", "calibrated")):
            print(f"  {label:33s} train {v[key + '_train_mm']:.2f} mm RMS, validation {v[key + '_validation_mm']:.2f} mm")
        print("  estimated leg parameters:")
        for name, (val, sig) in v["found"].items():
            f, u = (57.29577951308232, "deg") if name.endswith("_rad") else (1e3, "mm")
            print(f"    {name:34s} {f * val:+8.3f} ± {f * sig:.3f} {u}")
        print(f"  marker on the hand frame: {np.round(np.array(v['marker_xyz_m']) * 1e3, 1).tolist()} mm")
        print("  identifiable: " + ", ".join(v["identifiable"]))
        print("  exactly aliased: " + ", ".join(v["combination_structural"]))
        print("  weakly determined by these postures: " + ", ".join(v["combination_weak"]))
        if v["unidentifiable"]:
            print("  not identifiable: " + ", ".join(v["unidentifiable"]))


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("measurements", nargs="?", default=str(DEFAULT_DATA))
    ap.add_argument("--origins", default="first", choices=("first", "all", "none"))
    a = ap.parse_args()
    _print(main(a.measurements, origins=a.origins))
