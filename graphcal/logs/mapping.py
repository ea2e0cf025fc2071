"""Which topic is what: the import map, detected from the log's message types, printed, written
beside the dataset as ``import_map.yaml`` and read back (edited) with ``--map``. Layout and keys:
docs/import.md."""

from __future__ import annotations

import copy
import re
from pathlib import Path

import yaml

from graphcal.errors import DatasetError
from graphcal.logs.reader import LogTopic
from graphcal.logs.stations import StationThresholds
from graphcal.models.sensors import SENSOR_TYPE_RECORDS

__all__ = ["MAP_FORMAT", "TYPES", "detect_map", "read_map", "map_yaml_text", "check_map", "thresholds_of", "load_yaml",
           "sensor_name_of"]

MAP_FORMAT = "graphcal-import-map/1"

JOINT_STATE = "sensor_msgs/msg/JointState"
IMU = "sensor_msgs/msg/Imu"
CLOUD = "sensor_msgs/msg/PointCloud2"
SCAN = "sensor_msgs/msg/LaserScan"
IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF = "tf2_msgs/msg/TFMessage"
STRING = "std_msgs/msg/String"
WRENCH = "geometry_msgs/msg/WrenchStamped"
ARRAYS = tuple(f"std_msgs/msg/{k}MultiArray" for k in ("Float32", "Float64", "Int16", "Int32", "UInt16", "Int64"))
CONTACTS = ("std_msgs/msg/Bool", "std_msgs/msg/UInt8")

#: what each entry of the map must be (the message types it accepts)
TYPES = {"joints": (JOINT_STATE,), "imu": (IMU,), "tf_static": (TF,), "robot_description": (STRING,),
         "camera_info": (CAMERA_INFO,),
         **{t.name: t.log_messages for t in SENSOR_TYPE_RECORDS.values() if t.log_messages}}
#: the sensor types a log can hold (models/sensors.py's records with message types)
LOG_SENSOR_TYPES = tuple(t.name for t in SENSOR_TYPE_RECORDS.values() if t.log_messages)

_DEFAULT_PRIOR = {"sigma_mm": 50.0, "sigma_rpy_deg": 5.0}


def sensor_name_of(topic: str) -> str:
    """A sensor name (letters, digits, ``_``) from a topic: ``/camera/depth/points`` -> ``camera_depth``."""
    parts = [p for p in topic.strip("/").split("/") if p]
    while len(parts) > 1 and parts[-1] in ("points", "image_raw", "image_rect_raw", "image", "scan", "cloud"):
        parts.pop()
    return re.sub(r"[^A-Za-z0-9_]", "_", "_".join(parts)) or "sensor"


def _pick(topics: list[LogTopic], preferred: str) -> LogTopic | None:
    if not topics:
        return None
    return next((t for t in topics if t.name.rstrip("/").endswith(preferred)), max(topics, key=lambda t: t.count))


def detect_map(topics: dict[str, LogTopic], feet_hint: tuple[str, ...] = ()) -> dict:
    """The import map guessed from the log's topics and their message types (docs/import.md).
    ``feet_hint``: the robot's feet (URDF frames), to name the elements of a foot-force array."""
    by_type: dict[str, list[LogTopic]] = {}
    for t in topics.values():
        by_type.setdefault(t.msgtype, []).append(t)
    joints = _pick(by_type.get(JOINT_STATE, []), "joint_states")
    imu = _pick(by_type.get(IMU, []), "imu")
    m: dict = {"format": MAP_FORMAT, "stamps": "header",
               "robot": {"urdf": "/robot_description" if "/robot_description" in topics else None,
                         "model": None, "base_frame": None, "feet": list(feet_hint) or None},
               "joints": {"topic": joints.name if joints else None},
               "imu": {"topic": imu.name} if imu else None,
               "tf_static": "/tf_static" if "/tf_static" in topics else None,
               "sensors": {}, "feet": {},
               "stations": dict(StationThresholds().__dict__), "priors": dict(_DEFAULT_PRIOR)}
    infos = by_type.get(CAMERA_INFO, [])
    for t in by_type.get(CLOUD, []):
        m["sensors"][sensor_name_of(t.name)] = {"type": "depth_camera", "topic": t.name}
    for t in by_type.get(SCAN, []):
        m["sensors"][sensor_name_of(t.name)] = {"type": "laser_scanner", "topic": t.name}
    for t in by_type.get(IMAGE, []):
        if "depth" not in t.name:
            continue
        ns = t.name.rsplit("/", 1)[0]
        info = next((i.name for i in infos if i.name.rsplit("/", 1)[0] == ns), None)
        if info is not None:
            m["sensors"][sensor_name_of(t.name)] = {"type": "depth_camera", "topic": t.name, "camera_info": info,
                                                    "stride": 1}
    _detect_feet(m, by_type, feet_hint)
    return m


def _detect_feet(m: dict, by_type: dict, feet_hint: tuple[str, ...]) -> None:
    for t in sorted(by_type.get(WRENCH, []), key=lambda t: t.name):
        if re.search("foot|feet|force|contact", t.name):
            m["feet"][_foot_name(t.name, feet_hint)] = {"topic": t.name, "kind": "wrench"}
    for typ in CONTACTS:
        for t in sorted(by_type.get(typ, []), key=lambda t: t.name):
            if "contact" in t.name:
                m["feet"][_foot_name(t.name, feet_hint)] = {"topic": t.name, "kind": "contact", "threshold_n": 0.5}
    for typ in ARRAYS:
        for t in sorted(by_type.get(typ, []), key=lambda t: t.name):
            if re.search("foot|feet|force|contact", t.name) and not m["feet"]:
                names = feet_hint or tuple(f"foot{i}" for i in range(4))
                for i, name in enumerate(names):
                    m["feet"][name] = {"topic": t.name, "kind": "array", "index": i, "offset": 0.0, "scale": 1.0}


def _foot_name(topic: str, feet_hint: tuple[str, ...]) -> str:
    last = topic.strip("/").split("/")[-1]
    return next((f for f in feet_hint if f.split("_")[0] == last.split("_")[0] or f == last), last)


def map_yaml_text(m: dict, log_path: Path | None = None) -> str:
    """The map as YAML (units in the key names: s, rad/s, N, mm, deg)."""
    head = ("# graphcal import map: which topic is what (docs/import.md). Edit it and pass it back with --map.\n"
            "# Units: stamps in s; stations.* in rad/s, s, N; priors in mm and deg; feet offset/scale map raw\n"
            "# values to newtons: force_N = (raw - offset) * scale.\n")
    if log_path is not None:
        head += f"# detected from {log_path}\n"
    return head + yaml.safe_dump(m, sort_keys=False, default_flow_style=None)


def read_map(path: str | Path) -> dict:
    """A map written by :func:`map_yaml_text` (maybe edited); missing keys take the defaults."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise DatasetError(path, "file", "a readable import map (YAML)", exc.strerror or str(exc)) from None
    m = load_yaml(text, path)
    if not isinstance(m, dict) or m.get("format") != MAP_FORMAT:
        raise DatasetError(path, "format", MAP_FORMAT, (m or {}).get("format") if isinstance(m, dict) else m)
    base = detect_map({})
    for key, value in m.items():
        if key not in base:
            raise DatasetError(path, key, f"one of the keys {', '.join(base)}", key)
        if isinstance(base[key], dict) and isinstance(value, dict) and key in ("robot", "stations", "priors"):
            base[key].update(value)
        else:
            base[key] = value
    return base


def load_yaml(text: str, path: Path):
    """YAML text -> plain Python (graphcal's strict safe loader); DatasetError naming ``path``."""
    from graphcal.io.yaml_strict import StrictSafeLoader

    try:
        return yaml.load(text, Loader=StrictSafeLoader)  # noqa: S506 (a safe loader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else "file"
        raise DatasetError(path, where, "valid YAML", getattr(exc, "problem", None) or str(exc)) from None


def thresholds_of(m: dict, source: str) -> StationThresholds:
    """The ``stations`` entry of a map as :class:`StationThresholds`."""
    s = dict(m.get("stations") or {})
    known = StationThresholds().__dict__
    for k, v in s.items():
        if k not in known:
            raise DatasetError(source, f"stations.{k}", f"one of {', '.join(known)}", k)
        if not isinstance(v, (int, float)) or not v >= 0:
            raise DatasetError(source, f"stations.{k}", "a number >= 0", v)
    return StationThresholds(**{k: float(v) for k, v in s.items()})


def check_map(m: dict, topics: dict[str, LogTopic], log: Path, map_source: str) -> dict:
    """Check every topic the map names against the log: present, of an accepted type. Returns a copy
    with each sensor's ``msgtype``. DatasetError (one line: the topic, the map key, what was expected)."""
    m = copy.deepcopy(m)

    def need(topic, key: str, kinds: tuple[str, ...]) -> None:
        if topic is None:
            raise DatasetError(log, key, f"a topic of type {' or '.join(kinds)} (none in the log; set {key} in "
                               f"{map_source})", None)
        if topic not in topics:
            raise DatasetError(log, f"topic {topic} ({key})", "a topic of the log",
                               f"not there (the log has {', '.join(sorted(topics))})")
        if topics[topic].msgtype not in kinds:
            raise DatasetError(log, f"topic {topic} ({key})", f"messages of type {' or '.join(kinds)}",
                               topics[topic].msgtype)

    if m.get("stamps") not in ("header", "receive"):
        raise DatasetError(map_source, "stamps", "header or receive", m.get("stamps"))
    need((m.get("joints") or {}).get("topic"), "joints.topic", TYPES["joints"])
    if m.get("imu"):
        need(m["imu"].get("topic"), "imu.topic", TYPES["imu"])
    if m.get("tf_static"):
        need(m["tf_static"], "tf_static", TYPES["tf_static"])
    urdf = (m.get("robot") or {}).get("urdf")
    if isinstance(urdf, str) and urdf.startswith("/") and not Path(urdf).is_file():
        need(urdf, "robot.urdf", TYPES["robot_description"])
    for name, s in (m.get("sensors") or {}).items():
        if s.get("type") not in LOG_SENSOR_TYPES:
            raise DatasetError(map_source, f"sensors.{name}.type", " or ".join(LOG_SENSOR_TYPES), s.get("type"))
        need(s.get("topic"), f"sensors.{name}.topic", TYPES[s["type"]])
        s["msgtype"] = topics[s["topic"]].msgtype
        if s["msgtype"] == IMAGE:
            need(s.get("camera_info"), f"sensors.{name}.camera_info", TYPES["camera_info"])
    for foot, f in (m.get("feet") or {}).items():
        kinds = {"wrench": (WRENCH,), "contact": CONTACTS}.get(f.get("kind", "array"))
        need(f.get("topic"), f"feet.{foot}.topic", kinds or (topics[f["topic"]].msgtype,)
             if f.get("topic") in topics else ARRAYS)
    return m
