"""A fleet's calibrations side by side, and the robots whose values lie outside the fleet's spread.

Every robot (one output folder of ``graphcal batch``) contributes the values it has: per sensor the
extrinsic T_body_sensor as six numbers -- the translation along the body axes (mm) and the rotation
as a rotation vector about the body axes (deg) relative to the fleet's medoid rotation (the robot
rotation with the smallest sum of angles to the others), each with its 1-sigma in the same body axes
from ``calibration.yaml`` -- and per leg its parameters with sigma (``calibration.yaml`` with legs, or
``legs.yaml``; angles in deg, lengths in mm).

The statistic (leave-one-out Student t, per degree of freedom): for robot i and value v_i, with m
other robots that have the value, their mean and sample standard deviation s,

    t_i = (v_i - mean_{j != i} v_j) / (max(s_{j != i}, sigma_i) * sqrt(1 + 1/m))

which for a fleet of normally spread values follows Student's t with m - 1 degrees of freedom (the
prediction interval of one more robot), so its two-sided p-value is exact whatever the fleet's size.
A robot is flagged on a DoF when p < :data:`ALPHA` (0.001: about one false flag per thousand values
of a normal fleet) and m >= :data:`MIN_OTHERS`. Leaving robot i out keeps an outlier from widening
the spread it is judged against; the spread is floored at the robot's own sigma (the fleet cannot be
resolved finer than that, and a fleet of identical values would divide by zero). A median/MAD
robust z-score was tried first and rejected: with 7 to 19 other robots the MAD is so noisy that
|z| > 3.5 flagged 1 to 6 % of the values of normal fleets (tests/test_batch.py's fleet, 60 seeds).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from graphcal.geometry import pose_from_xyz_quat_wxyz, so3_log_batch

__all__ = ["ALPHA", "MIN_OTHERS", "Value", "Robot", "Flag", "read_robot", "loo_t", "fleet_flags",
           "rotation_vectors_deg"]

ALPHA = 0.001
MIN_OTHERS = 3
_AXES = ("x", "y", "z")


@dataclass(frozen=True)
class Value:
    """One degree of freedom of one robot: ``group`` (a sensor name, or ``leg FOOT``), ``name`` (e.g.
    ``x``, ``rot x``, a leg parameter), ``value`` and ``sigma`` in ``unit`` (mm or deg)."""

    group: str
    name: str
    value: float
    sigma: float
    unit: str

    @property
    def key(self) -> tuple[str, str]:
        return (self.group, self.name)


@dataclass(frozen=True)
class Robot:
    """What one output folder says about its robot. ``rotations`` holds each sensor's R_body_sensor
    (3x3) until :func:`fleet_flags` has turned it into rotation-vector values; ``warnings`` the
    verdicts and warnings of the outputs (calibration, identification); ``findings`` the diagnosis'
    named causes (one line each); ``notes`` anything unreadable."""

    name: str
    folder: str
    values: tuple[Value, ...] = ()
    rotations: dict = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    findings: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class Flag:
    """Robot ``robot`` lies outside the fleet on ``group``/``name``: its ``value`` (``unit``), the
    others' ``mean`` and ``spread`` (their standard deviation, or the robot's sigma if larger), the
    leave-one-out ``t`` and its two-sided ``p`` (Student t, ``n_others`` - 1 dof)."""

    robot: str
    group: str
    name: str
    value: float
    mean: float
    spread: float
    t: float
    p: float
    unit: str
    n_others: int

    def text(self) -> str:
        return (f"{self.robot}: {self.group} {self.name} = {self.value:.3f} {self.unit}, fleet mean "
                f"{self.mean:.3f} {self.unit}, spread {self.spread:.3g} {self.unit}: t {self.t:+.1f} "
                f"(p {self.p:.1e}, {self.n_others} others)")


def _legs_values(legs: dict) -> list[Value]:
    out = []
    for foot, params in (legs or {}).items():
        for pname, e in (params or {}).items():
            if not isinstance(e, dict) or "value" not in e:
                continue
            angle = str(pname).endswith("_rad")
            f, unit = (180.0 / math.pi, "deg") if angle else (1e3, "mm")
            v, s = e.get("value"), e.get("sigma")
            shown = str(pname).removesuffix("_rad").removesuffix("_m")  # the unit is in ``unit``
            out.append(Value(f"leg {foot}", shown, f * float(v) if v is not None else math.nan,
                             f * float(s) if s is not None else math.nan, unit))
    return out


def _calibration(doc: dict) -> tuple[list[Value], dict, list[str]]:
    values, rotations = [], {}
    for name, s in (doc.get("sensors") or {}).items():
        t = s["T_body_sensor"]
        T = pose_from_xyz_quat_wxyz(t["xyz"], t["quaternion_wxyz"])
        sig = s.get("sigma") or {}
        sxyz = sig.get("xyz_mm") or [math.nan] * 3
        values += [Value(str(name), a, 1e3 * float(T[k, 3]), float(sxyz[k]), "mm") for k, a in enumerate(_AXES)]
        rotations[str(name)] = (T[:3, :3], [float(x) for x in (sig.get("rot_deg") or [math.nan] * 3)])
    values += _legs_values(doc.get("legs"))
    return values, rotations, [str(w) for w in doc.get("warnings") or []]


def _findings(doc: dict) -> list[str]:
    out = []
    for fd in doc.get("findings") or []:
        where = ", ".join(f"{k}={v}" for k, v in (fd.get("where") or {}).items())
        ev = fd.get("evidence") or {}
        out.append(f"{fd.get('cause')}" + (f" ({where})" if where else "")
                   + (f": LR {ev['statistic']:.1f} on {ev.get('dof')} dof" if "statistic" in ev else ""))
    if doc.get("unexplained_structure"):
        out.append("structure remains that no catalogued effect explains")
    return out


def read_robot(folder: str | Path, name: str | None = None) -> Robot:
    """The values, warnings and findings in one output folder (``calibration.yaml``, ``legs.yaml``,
    ``diagnosis.json``, ``metrics.json``; whichever are there). Unreadable files become ``notes``."""
    folder = Path(folder)
    values, rotations, warnings, findings, notes = [], {}, [], [], []
    readers = {"calibration.yaml": "cal", "legs.yaml": "legs", "diagnosis.json": "diag", "metrics.json": "track"}
    for fname, kind in readers.items():
        path = folder / fname
        if not path.is_file():
            continue
        try:
            text = path.read_text(encoding="utf-8")
            doc = json.loads(text) if fname.endswith(".json") else yaml.safe_load(text)
            if kind == "cal":
                v, r, w = _calibration(doc)
                values += v
                rotations.update(r)
                warnings += w
            elif kind == "legs":
                values += _legs_values(doc.get("legs"))
                warnings += [f"identify-legs: {w}" for w in doc.get("warnings") or []]
            elif kind == "diag":
                findings += _findings(doc)
            elif doc.get("nees_mean") is not None:
                warnings.append(f"track: NEES mean {doc['nees_mean']:.2f} (dof {doc.get('nees_dof')}), "
                                f"drift {doc.get('drift_percent')} %")
        except (OSError, ValueError, KeyError, TypeError, AttributeError, yaml.YAMLError) as exc:
            notes.append(f"{fname}: unreadable ({type(exc).__name__}: {exc})")
    return Robot(name or folder.name, str(folder), tuple(values), rotations, tuple(warnings), tuple(findings),
                 tuple(notes))


def _angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def rotation_vectors_deg(rotations: list[np.ndarray]) -> np.ndarray:
    """Rotation vectors (deg, about the body axes) of R_i R_ref^T, ref the medoid of ``rotations``
    (the one with the smallest sum of angles to the others); shape (n, 3)."""
    n = len(rotations)
    cost = [sum(_angle(rotations[i], rotations[j]) for j in range(n)) for i in range(n)]
    ref = rotations[int(np.argmin(cost))]
    return np.degrees(so3_log_batch(np.array([R @ ref.T for R in rotations]))).reshape(n, 3)


def _with_rotations(robots: list[Robot]) -> list[list[Value]]:
    """Each robot's values plus its sensors' rotation vectors about the fleet's medoid per sensor."""
    values = [list(r.values) for r in robots]
    sensors = sorted({s for r in robots for s in r.rotations})
    for s in sensors:
        idx = [i for i, r in enumerate(robots) if s in r.rotations]
        vecs = rotation_vectors_deg([robots[i].rotations[s][0] for i in idx])
        for k, i in enumerate(idx):
            sig = robots[i].rotations[s][1]
            values[i] += [Value(s, f"rot {a}", float(vecs[k, j]), float(sig[j]), "deg") for j, a in enumerate(_AXES)]
    return values


def loo_t(values: np.ndarray, sigmas: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Leave-one-out t statistics (module docstring): for each i, (t_i, two-sided p_i, mean of the
    others, spread = max(standard deviation of the others, sigma_i)). NaN sigmas count as 0; NaN
    where fewer than 2 others have a value."""
    from scipy.stats import t as student_t

    v = np.asarray(values, float)
    s = np.nan_to_num(np.asarray(sigmas, float), nan=0.0)
    n = len(v)
    t, p, mean, spread = (np.full(n, np.nan) for _ in range(4))
    for i in range(n):
        others = np.delete(v, i)
        others = others[np.isfinite(others)]
        m = len(others)
        if m < 2 or not np.isfinite(v[i]):
            continue
        mean[i] = float(others.mean())
        spread[i] = max(float(others.std(ddof=1)), float(s[i]))
        d = v[i] - mean[i]
        t[i] = d / (spread[i] * math.sqrt(1 + 1 / m)) if spread[i] > 0 else (0.0 if d == 0 else math.copysign(math.inf, d))
        p[i] = float(2 * student_t.sf(abs(t[i]), m - 1))
    return t, p, mean, spread


def fleet_flags(robots: list[Robot], *, alpha: float = ALPHA,
                min_others: int = MIN_OTHERS) -> tuple[dict, list[Flag]]:
    """Per robot its values (rotation vectors included) with their t, and the flags.

    Returns:
        ``(table, flags)``: ``table[robot name][(group, name)] = (Value, t, p)`` (t, p NaN where fewer
        than ``min_others`` other robots have the value) and the :class:`Flag` s with p < ``alpha``,
        sorted by robot then |t| (largest first).
    """
    values = _with_rotations(robots)
    keys = sorted({v.key for vs in values for v in vs})
    table: dict = {r.name: {} for r in robots}
    flags: list[Flag] = []
    for key in keys:
        have = [(i, v) for i, vs in enumerate(values) for v in vs if v.key == key]
        t, p, mean, spread = loo_t(np.array([v.value for _, v in have]), np.array([v.sigma for _, v in have]))
        enough = len(have) - 1 >= min_others
        for k, (i, v) in enumerate(have):
            tk, pk = (float(t[k]), float(p[k])) if enough else (math.nan, math.nan)
            table[robots[i].name][key] = (v, tk, pk)
            if enough and np.isfinite(p[k]) and p[k] < alpha:
                flags.append(Flag(robots[i].name, v.group, v.name, v.value, float(mean[k]), float(spread[k]),
                                  float(t[k]), float(p[k]), v.unit, len(have) - 1))
    flags.sort(key=lambda f: (f.robot, -abs(f.t)))
    return table, flags
