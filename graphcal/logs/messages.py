"""ROS messages (as rosbags deserialises them) -> numbers in SI units: header stamps (s), joint
positions (rad or m) and efforts (N m or N), IMU specific force (m/s²) and rate (rad/s), points in
the message's frame (m) from PointCloud2, LaserScan (the scan plane z = 0) and depth images (camera
optical frame: x right, y down, z forward), foot loads (N) and static transforms ``T_parent_child``."""

from __future__ import annotations

from typing import Any

import numpy as np

from graphcal.errors import DatasetError
from graphcal.geometry import pose_from_xyz_quat_wxyz

__all__ = ["header_stamp", "joint_state", "joint_efforts", "imu_sample", "cloud_points", "laser_scan_points",
           "depth_image_points", "camera_matrix", "foot_value", "FootForces", "static_transforms", "chain_pose"]

# sensor_msgs/PointField datatypes -> numpy
_POINT_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def header_stamp(msg: Any) -> float | None:
    """``msg.header.stamp`` in seconds, or None when the message has no header."""
    header = getattr(msg, "header", None)
    if header is None:
        return None
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def joint_state(msg: Any) -> tuple[tuple[str, ...], np.ndarray]:
    """``sensor_msgs/JointState`` -> (joint names, positions (rad; m for prismatic joints))."""
    return tuple(msg.name), np.asarray(msg.position, dtype=np.float64)


def joint_efforts(msg: Any) -> np.ndarray | None:
    """``sensor_msgs/JointState`` -> efforts (N m; N for prismatic joints) in the order of
    ``msg.name``, or None when the message has none (an empty or short ``effort``)."""
    e = np.asarray(getattr(msg, "effort", ()), dtype=np.float64).reshape(-1)
    return e if len(e) and len(e) == len(msg.name) else None


def imu_sample(msg: Any) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """``sensor_msgs/Imu`` -> (specific force m/s², angular rate rad/s), x y z of the IMU frame."""
    a, w = msg.linear_acceleration, msg.angular_velocity
    return (a.x, a.y, a.z), (w.x, w.y, w.z)


def cloud_points(msg: Any) -> np.ndarray:
    """``sensor_msgs/PointCloud2`` -> (N, 3) finite points (m) in ``msg.header.frame_id``."""
    fields = {f.name: f for f in msg.fields}
    if not all(k in fields for k in "xyz"):
        raise ValueError(f"PointCloud2 without x, y, z fields (has {sorted(fields)})")
    endian = ">" if msg.is_bigendian else "<"
    dtype = np.dtype({"names": ["x", "y", "z"],
                      "formats": [endian + _POINT_FIELD_TYPES[fields[k].datatype] for k in "xyz"],
                      "offsets": [fields[k].offset for k in "xyz"], "itemsize": msg.point_step})
    n = int(msg.width) * int(msg.height)
    rows = np.frombuffer(np.asarray(msg.data, dtype=np.uint8).tobytes(), dtype=np.uint8)
    rows = rows.reshape(int(msg.height), int(msg.row_step))[:, : int(msg.width) * msg.point_step]
    a = np.frombuffer(np.ascontiguousarray(rows).tobytes(), dtype=dtype, count=n)
    pts = np.stack([a["x"], a["y"], a["z"]], axis=1).astype(np.float64)
    return pts[np.isfinite(pts).all(axis=1)]


def laser_scan_points(msg: Any) -> np.ndarray:
    """``sensor_msgs/LaserScan`` -> (N, 3) points (m) in the scan plane (z = 0) of its frame; ranges
    outside [range_min, range_max] or not finite are dropped."""
    r = np.asarray(msg.ranges, dtype=np.float64)
    a = msg.angle_min + msg.angle_increment * np.arange(r.size)
    ok = np.isfinite(r) & (r >= msg.range_min) & (r <= msg.range_max)
    return np.stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok]), np.zeros(int(ok.sum()))], axis=1)


def camera_matrix(msg: Any) -> np.ndarray:
    """``sensor_msgs/CameraInfo`` -> (fx, fy, cx, cy) in pixels (the ``k`` matrix; ROS 1 ``K``)."""
    k = np.asarray(getattr(msg, "k", None) if hasattr(msg, "k") else msg.K, dtype=np.float64)
    return np.array([k[0], k[4], k[2], k[5]])


def depth_image_points(msg: Any, fx_fy_cx_cy: np.ndarray, stride: int = 1) -> np.ndarray:
    """Depth ``sensor_msgs/Image`` (``16UC1``: millimetres, ``32FC1``: metres) and the camera's
    (fx, fy, cx, cy) -> (N, 3) points (m) in the camera optical frame (x right, y down, z forward);
    pixels without depth (0 or not finite) are dropped; every ``stride``-th row and column."""
    enc = msg.encoding.upper()
    if enc in ("16UC1", "MONO16"):
        dt, scale = np.dtype(">u2" if msg.is_bigendian else "<u2"), 1e-3
    elif enc == "32FC1":
        dt, scale = np.dtype(">f4" if msg.is_bigendian else "<f4"), 1.0
    else:
        raise ValueError(f"depth image encoding 16UC1 or 32FC1, got {msg.encoding}")
    h, w = int(msg.height), int(msg.width)
    buf = np.asarray(msg.data, dtype=np.uint8)
    img = np.ndarray((h, w), dtype=dt, buffer=buf.data, strides=(int(msg.step), dt.itemsize))
    z = img[::stride, ::stride].astype(np.float64) * scale
    v, u = np.mgrid[0:h:stride, 0:w:stride]
    ok = np.isfinite(z) & (z > 0)
    fx, fy, cx, cy = fx_fy_cx_cy
    z = z[ok]
    return np.stack([(u[ok] - cx) * z / fx, (v[ok] - cy) * z / fy, z], axis=1)


class FootForces:
    """The loads of the feet read from one topic (foot -> map entry, all of one topic), as an
    array in the order of ``names`` (N, or raw counts with a raw threshold)."""

    def __init__(self, specs: dict[str, dict]):
        self.names = tuple(specs)
        self.specs = specs
        first = next(iter(specs.values()))
        self.array = first.get("kind", "array") == "array"
        if self.array:
            self.field = first.get("field", "data")
            self.index = np.array([int(s.get("index", 0)) for s in specs.values()])
            self.offset = np.array([float(s.get("offset", 0.0)) for s in specs.values()])
            self.scale = np.array([float(s.get("scale", 1.0)) for s in specs.values()])

    def __call__(self, msg: Any) -> np.ndarray:
        if self.array:
            values = np.asarray(getattr(msg, self.field), dtype=np.float64).reshape(-1)
            return (values[self.index] - self.offset) * self.scale
        return np.array([foot_value(msg, s) for s in self.specs.values()])


def foot_value(msg: Any, spec: dict) -> float:
    """The load of one foot from a message, in the units of ``spec`` (see docs/import.md):
    ``kind: wrench`` (WrenchStamped: the force's norm, N), ``kind: array`` (``spec['field']``,
    default ``data``, element ``index``; then ``(raw - offset) * scale``), ``kind: contact``
    (``data`` of a Bool/UInt8: 1 or 0)."""
    kind = spec.get("kind", "array")
    if kind == "wrench":
        w = msg.wrench if hasattr(msg, "wrench") else msg
        return float(np.linalg.norm([w.force.x, w.force.y, w.force.z]))
    if kind == "contact":
        return float(bool(msg.data))
    values = getattr(msg, spec.get("field", "data"))
    raw = float(np.asarray(values).reshape(-1)[int(spec.get("index", 0))])
    return (raw - float(spec.get("offset", 0.0))) * float(spec.get("scale", 1.0))


def static_transforms(msg: Any) -> list[tuple[str, str, np.ndarray]]:
    """``tf2_msgs/TFMessage`` -> ``(parent, child, T_parent_child 4x4 (m))`` for each transform."""
    out = []
    for ts in msg.transforms:
        t, q = ts.transform.translation, ts.transform.rotation
        T = pose_from_xyz_quat_wxyz([t.x, t.y, t.z], [q.w, q.x, q.y, q.z])
        out.append((ts.header.frame_id.lstrip("/"), ts.child_frame_id.lstrip("/"), T))
    return out


def chain_pose(transforms: dict[str, tuple[str, np.ndarray]], base: str, frame: str, source: str) -> np.ndarray:
    """``T_base_frame`` (4x4, m) from static transforms ``child -> (parent, T_parent_child)``.
    DatasetError naming ``source`` when the two frames are not connected."""
    def to_root(f: str) -> dict[str, np.ndarray]:
        chain, T, seen = {f: np.eye(4)}, np.eye(4), {f}
        while f in transforms:
            parent, T_p_c = transforms[f]
            T = T_p_c @ T
            f = parent
            if f in seen:
                break
            seen.add(f)
            chain[f] = T
        return chain

    a, b = to_root(base), to_root(frame)
    common = next((f for f in b if f in a), None)
    if common is None:
        raise DatasetError(source, f"/tf_static, frames {base} and {frame}",
                           f"a chain of static transforms from {base} to {frame}",
                           f"{base} reaches {sorted(a)}, {frame} reaches {sorted(b)}")
    return np.linalg.inv(a[common]) @ b[common]
