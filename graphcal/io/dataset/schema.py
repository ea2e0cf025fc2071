"""``dataset.yaml``: its keys and types, read (:func:`parse_dataset_yaml`, every problem one
:class:`~graphcal.errors.DatasetError` naming the key) and written (:func:`dataset_yaml_text`).
Degrees and millimetres live only in the keys that say so (``rpy_deg``, ``sigma_rpy_deg``,
``sigma_mm``); they are converted here, both ways, so that a value read is written back as the
same number. YAML is read with a subclass of ``yaml.SafeLoader``."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import yaml

from graphcal.errors import DatasetError
from graphcal.io.dataset.model import (
    FORMAT,
    MAX_PRIOR_SIGMA_DEG,
    MAX_PRIOR_SIGMA_MM,
    MIN_PRIOR_SIGMA,
    MM_LIMIT_PRIOR_M,
    Dataset,
    ImuSpec,
    MarkerSpec,
    PosePrior,
    RobotSpec,
    SensorSpec,
)
from graphcal.io.dataset.text import MILLIMETRES_HINT, decode_utf8, did_you_mean, one_line, shown_value
from graphcal.io.files import read_regular_file
from graphcal.io.yaml_strict import StrictSafeLoader as _YamlLoader
from graphcal.models.sensors import SENSOR_TYPES

_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+-]*")


class _YamlDumper(yaml.SafeDumper):
    """``yaml.SafeDumper`` that quotes text the loader would read as a YAML 1.2 float (``1e3``) and
    writes no aliases (the loader refuses them): a value used twice is written out twice."""

    def ignore_aliases(self, data):
        return True


_YamlDumper.yaml_implicit_resolvers = {k: list(v) for k, v in yaml.SafeDumper.yaml_implicit_resolvers.items()}
for _first, _resolvers in _YamlLoader.yaml_implicit_resolvers.items():
    for _tag, _regexp in _resolvers:
        known = _YamlDumper.yaml_implicit_resolvers.setdefault(_first, [])
        if _tag == "tag:yaml.org,2002:float" and (_tag, _regexp) not in known:
            known.append((_tag, _regexp))


def _load_yaml(path: Path) -> Any:
    try:
        raw = read_regular_file(path)
    except OSError as exc:
        raise DatasetError(path, "file", "a readable dataset.yaml", exc.strerror or str(exc)) from None
    text = decode_utf8(raw, path)
    try:
        return yaml.load(text, Loader=_YamlLoader)  # noqa: S506 -- a SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark is not None else "YAML syntax"
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise DatasetError(path, where, "valid YAML", one_line(problem)) from None
    except RecursionError:
        raise DatasetError(path, "YAML syntax", "valid YAML of reasonable nesting depth") from None
    except (ValueError, TypeError, OverflowError) as exc:  # e.g. a date such as 2024-13-45
        raise DatasetError(path, "YAML value", "valid YAML values", one_line(str(exc))) from None


class _Y:
    """Typed access to the parsed dataset.yaml with errors naming the key."""

    def __init__(self, path: Path):
        self.path = path

    def err(self, key: str, expected: str, got: object = None) -> DatasetError:
        return DatasetError(self.path, key, expected, got)

    def mapping(self, v, key: str) -> dict:
        if not isinstance(v, dict):
            raise self.err(key or "top level", "a mapping (key: value lines)", shown_value(v))
        for k in v:
            if not isinstance(k, str):
                raise self.err(f"{key}.{k}" if key else str(k), "text keys", shown_value(k))
        return v

    def text(self, v, key: str) -> str:
        if not isinstance(v, str) or not v.strip():
            raise self.err(key, "a non-empty text", shown_value(v))
        return v.strip()

    def number(self, v, key: str) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.err(key, "a number", shown_value(v))
        try:
            x = float(v)
        except OverflowError:
            x = math.inf
        if not math.isfinite(x):
            raise self.err(key, "a finite number", shown_value(v))
        return x

    def vec3(self, v, key: str) -> list[float]:
        if not isinstance(v, list) or len(v) != 3:
            raise self.err(key, "a list of 3 numbers", shown_value(v))
        return [self.number(x, f"{key}[{i}]") for i, x in enumerate(v)]

    def keys(self, m: dict, key: str, required: Sequence[str], allowed: Sequence[str] | None) -> None:
        for r in required:
            if r not in m:
                raise self.err(f"{key}.{r}" if key else r, f"the required key '{r}'", "missing")
        if allowed is not None:
            for k in m:
                if k not in allowed:
                    raise self.err(
                        f"{key}.{k}", f"one of the keys {', '.join(allowed)}{did_you_mean(k, allowed)}",
                        f"unknown key {k!r}",
                    )


#: the keys graphcal reads under ``ground:`` and ``stance:`` (others are kept as given)
GROUND_KEYS = ("type", "bump_rms_m", "stairs")
STANCE_KEYS = ("feet_fixed_within",)


def _refuse_misspelt(y: _Y, m: dict, key: str, known: Sequence[str]) -> None:
    """An unknown key of ``m`` close to a known one (``feet_fixed_whithin``, ``tpye``) is refused as
    a misspelling: it would be kept and ignored, and the default it meant to change used instead.
    Other unknown keys are kept (the contract lets a dataset carry its own)."""
    for k in m:
        if k not in known and did_you_mean(str(k), known):
            raise y.err(f"{key}.{k}", f"one of the keys {', '.join(known)}{did_you_mean(str(k), known)}",
                        f"unknown key {k!r}")


def _parse_prior(y: _Y, v, key: str) -> PosePrior:
    m = y.mapping(v, key)
    names = ("xyz", "rpy_deg", "sigma_mm", "sigma_rpy_deg")
    y.keys(m, key, names, names)
    xyz = y.vec3(m["xyz"], f"{key}.xyz")
    if math.hypot(*xyz) > MM_LIMIT_PRIOR_M:
        raise y.err(f"{key}.xyz", f"metres (norm <= {MM_LIMIT_PRIOR_M:g} m); {MILLIMETRES_HINT}", xyz)
    rpy_deg = y.vec3(m["rpy_deg"], f"{key}.rpy_deg")
    for i, a in enumerate(rpy_deg):
        if abs(a) > 360.0:
            raise y.err(f"{key}.rpy_deg[{i}]", "degrees in [-360, 360]", a)
    sigma_mm = y.number(m["sigma_mm"], f"{key}.sigma_mm")
    sigma_deg = y.number(m["sigma_rpy_deg"], f"{key}.sigma_rpy_deg")
    for k, s, top in (("sigma_mm", sigma_mm, MAX_PRIOR_SIGMA_MM), ("sigma_rpy_deg", sigma_deg, MAX_PRIOR_SIGMA_DEG)):
        if s < 0:
            raise y.err(f"{key}.{k}", "a standard deviation >= 0", s)
        if s > top or 0 < s < MIN_PRIOR_SIGMA:
            raise y.err(f"{key}.{k}", f"a standard deviation of 0 (fixed) or within [{MIN_PRIOR_SIGMA:g}, {top:g}]",
                        shown_value(s))
    return PosePrior(
        np.array(xyz), np.array([_deg_to_rad(a) for a in rpy_deg]), _mm_to_m(sigma_mm), _deg_to_rad(sigma_deg)
    )


# Unit conversions, used in both directions so that a value read from a file is written back as
# the same number (see _file_number).
def _deg_to_rad(x: float) -> float:
    return math.radians(x)


def _rad_to_deg(x: float) -> float:
    return math.degrees(x)


def _mm_to_m(x: float) -> float:
    return x / 1000.0


def _m_to_mm(x: float) -> float:
    return x * 1000.0


def _file_number(si: float, to_file, from_file) -> float:
    """The number to write in a file so that reading it back gives exactly ``si``: the shortest
    decimal that does, else the nearest float that does, else the plain conversion (1 ulp off)."""
    v = to_file(si)
    if from_file(v) == si:
        for digits in range(1, 17):
            s = float(f"{v:.{digits}g}")
            if from_file(s) == si:
                return s
        return v
    lo = hi = v
    for _ in range(64):
        lo, hi = math.nextafter(lo, -math.inf), math.nextafter(hi, math.inf)
        if from_file(lo) == si:
            return lo
        if from_file(hi) == si:
            return hi
    return v


def _prior_to_yaml(p: PosePrior) -> dict:
    return {
        "xyz": [float(x) for x in p.xyz],
        "rpy_deg": [_file_number(float(a), _rad_to_deg, _deg_to_rad) for a in p.rpy_rad],
        "sigma_mm": _file_number(p.sigma_m, _m_to_mm, _mm_to_m),
        "sigma_rpy_deg": _file_number(p.sigma_rad, _rad_to_deg, _deg_to_rad),
    }


@dataclass(frozen=True)
class YamlHeader:
    """``dataset.yaml`` read and checked: the fields of :class:`~graphcal.io.dataset.model.Dataset`
    that come from it (SI units)."""

    format: str
    robot: RobotSpec | None
    sensors: dict
    imu: ImuSpec | None
    ground: dict
    stance: dict
    extra: dict
    mocap_markers: dict
    mocap_noise: dict = field(default_factory=dict)


_TOP_KEYS = ("format", "robot", "sensors", "imu", "ground", "stance", "mocap")


def parse_dataset_yaml(path: Path) -> YamlHeader:
    """Read and check the ``dataset.yaml`` at ``path`` (the checks that need the robot or the CSV
    files are made by the reader). DatasetError naming the key, for the first problem."""
    doc = _load_yaml(path)
    y = _Y(path)
    if doc is None:
        raise y.err("format", f"the key 'format: {FORMAT}'", "an empty file")
    doc = y.mapping(doc, "")
    if "format" not in doc:
        raise y.err("format", f"the key 'format: {FORMAT}'", "missing")
    if doc["format"] != FORMAT:
        raise y.err("format", f"'{FORMAT}' (the format this graphcal reads)", shown_value(doc["format"]))

    robot = None
    if doc.get("robot") is not None:
        m = y.mapping(doc["robot"], "robot")
        y.keys(m, "robot", ("base_frame", "feet"), ("urdf", "model", "base_frame", "feet"))
        n_src = ("urdf" in m) + ("model" in m)
        if n_src != 1:
            raise y.err("robot", "exactly one of the keys 'urdf' (a URDF file) or 'model' (a built-in model)",
                        "both" if n_src == 2 else "neither")
        urdf = y.text(m["urdf"], "robot.urdf") if "urdf" in m else None
        model = y.text(m["model"], "robot.model") if "model" in m else None
        base_frame = y.text(m["base_frame"], "robot.base_frame")
        if not isinstance(m["feet"], list):
            raise y.err("robot.feet", "a list of URDF frame names", shown_value(m["feet"]))
        feet = [y.text(f, f"robot.feet[{i}]") for i, f in enumerate(m["feet"])]
        for i, f in enumerate(feet):
            if f in feet[:i]:
                raise y.err(f"robot.feet[{i}]", "each foot frame once", f)
        robot = RobotSpec(urdf, model, base_frame, tuple(feet))

    sensors: dict[str, SensorSpec] = {}
    if doc.get("sensors") is not None:
        for name, v in y.mapping(doc["sensors"], "sensors").items():
            key = f"sensors.{name}"
            if not _NAME_RE.fullmatch(name) or name in (".", ".."):
                raise y.err(key, "a sensor name of letters, digits and _ . + - (it is used in file names)", name)
            m = y.mapping(v, key)
            y.keys(m, key, ("type", "T_body_sensor_prior"), None)
            stype = m["type"]
            if stype not in SENSOR_TYPES:
                raise y.err(f"{key}.type", f"one of {', '.join(SENSOR_TYPES)}", shown_value(stype))
            prior = _parse_prior(y, m["T_body_sensor_prior"], f"{key}.T_body_sensor_prior")
            extra = {k: x for k, x in m.items() if k not in ("type", "T_body_sensor_prior")}
            sensors[name] = SensorSpec(name, stype, prior, extra)

    imu = None
    if doc.get("imu") is not None:
        m = y.mapping(doc["imu"], "imu")
        y.keys(m, "imu", ("T_body_imu_prior",), None)
        prior = _parse_prior(y, m["T_body_imu_prior"], "imu.T_body_imu_prior")
        imu = ImuSpec(prior, {k: x for k, x in m.items() if k != "T_body_imu_prior"})

    ground = {"type": "level"}
    if doc.get("ground") is not None:
        ground = dict(y.mapping(doc["ground"], "ground"))
        _refuse_misspelt(y, ground, "ground", GROUND_KEYS)
        if "type" in ground:
            y.text(ground["type"], "ground.type")
    stance = {"feet_fixed_within": "session"}
    if doc.get("stance") is not None:
        stance = dict(y.mapping(doc["stance"], "stance"))
        _refuse_misspelt(y, stance, "stance", STANCE_KEYS)
        if "feet_fixed_within" in stance:
            y.text(stance["feet_fixed_within"], "stance.feet_fixed_within")

    markers: dict[str, MarkerSpec] = {}
    noise: dict[str, float] = {}
    if doc.get("mocap") is not None:
        m = y.mapping(doc["mocap"], "mocap")
        y.keys(m, "mocap", (), ("markers", "sigma_mm", "sigma_joint_deg"))
        for key, to_si, name in (("sigma_mm", 1e-3, "sigma_m"), ("sigma_joint_deg", math.pi / 180.0, "sigma_joint_rad")):
            if m.get(key) is not None:
                v = m[key]
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0 or (
                        key == "sigma_mm" and v == 0):
                    raise y.err(f"mocap.{key}", "a standard deviation > 0 (mm)" if key == "sigma_mm"
                                else "a standard deviation >= 0 (deg)", shown_value(v))
                noise[name] = float(v) * to_si
        if m.get("markers") is not None:
            for name, v in y.mapping(m["markers"], "mocap.markers").items():
                key = f"mocap.markers.{name}"
                mm = y.mapping(v, key)
                y.keys(mm, key, ("link",), ("link", "xyz"))
                xyz = None
                if mm.get("xyz") is not None:
                    xyz = y.vec3(mm["xyz"], f"{key}.xyz")
                    if math.hypot(*xyz) > MM_LIMIT_PRIOR_M:
                        raise y.err(f"{key}.xyz", f"metres (norm <= {MM_LIMIT_PRIOR_M:g} m); {MILLIMETRES_HINT}", xyz)
                markers[name] = MarkerSpec(y.text(mm["link"], f"{key}.link"), xyz)

    extra = {k: v for k, v in doc.items() if k not in _TOP_KEYS}
    return YamlHeader(FORMAT, robot, sensors, imu, ground, stance, extra, markers, noise)


def _yaml_document(ds: Dataset) -> dict:
    doc: dict[str, Any] = {"format": FORMAT}
    if ds.robot is not None:
        r: dict[str, Any] = {}
        if ds.robot.urdf is not None:
            r["urdf"] = ds.robot.urdf
        if ds.robot.model is not None:
            r["model"] = ds.robot.model
        r["base_frame"] = ds.robot.base_frame
        r["feet"] = list(ds.robot.feet)
        doc["robot"] = r
    if ds.sensors:
        sensors = {}
        for name, s in ds.sensors.items():
            if name != s.name:
                raise ValueError(f"Dataset.sensors: key {name!r} holds SensorSpec named {s.name!r}")
            clash = {"type", "T_body_sensor_prior"} & set(s.extra)
            if clash:
                raise ValueError(f"SensorSpec {name!r}: extra must not hold {sorted(clash)}")
            sensors[name] = {"type": s.type, "T_body_sensor_prior": _prior_to_yaml(s.T_body_sensor_prior), **s.extra}
        doc["sensors"] = sensors
    if ds.imu is not None:
        if "T_body_imu_prior" in ds.imu.extra:
            raise ValueError("ImuSpec.extra must not hold 'T_body_imu_prior'")
        doc["imu"] = {"T_body_imu_prior": _prior_to_yaml(ds.imu.T_body_imu_prior), **ds.imu.extra}
    doc["ground"] = dict(ds.ground)
    doc["stance"] = dict(ds.stance)
    if ds.mocap_markers:
        markers = {}
        for name, m in ds.mocap_markers.items():
            markers[name] = {"link": m.link} if m.xyz is None else {"link": m.link, "xyz": [float(x) for x in m.xyz]}
        doc["mocap"] = {"markers": markers}
    if ds.mocap_noise:
        mo = doc.setdefault("mocap", {})
        if "sigma_m" in ds.mocap_noise:
            mo["sigma_mm"] = _file_number(ds.mocap_noise["sigma_m"], _m_to_mm, _mm_to_m)
        if "sigma_joint_rad" in ds.mocap_noise:
            mo["sigma_joint_deg"] = _file_number(ds.mocap_noise["sigma_joint_rad"], _rad_to_deg, _deg_to_rad)
    clash = set(_TOP_KEYS) & set(ds.extra)
    if clash:
        raise ValueError(f"Dataset.extra must not hold the contract's keys {sorted(clash)}")
    doc.update(ds.extra)
    return doc


def dataset_yaml_text(ds: Dataset, out: Path) -> str:
    """The text of ``dataset.yaml`` for ``ds`` (``xyz`` in metres; ``rpy_deg``, ``sigma_mm``,
    ``sigma_rpy_deg`` as the shortest decimals that read back as the exact SI values where there
    are such). ``out``: the dataset folder being written, for the message. ValueError when
    ``ds.sensors``' keys, an ``extra`` or ``ds.extra`` contradict the contract's keys; DatasetError
    when ``ds.extra`` holds what YAML cannot write."""
    doc = _yaml_document(ds)
    try:
        return yaml.dump(
            doc, Dumper=_YamlDumper, sort_keys=False, default_flow_style=None, allow_unicode=True, width=100
        )
    except yaml.YAMLError as exc:
        raise DatasetError(out / "dataset.yaml", "extra", "plain YAML values (text, numbers, lists, mappings)",
                           str(exc)) from None  # fmt: skip
