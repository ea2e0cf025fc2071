"""``scene.mcap``: the calibrated robot with its clouds, as a ROS 2 MCAP file Foxglove and RViz 2 open.

Standard ROS 2 message types only (written with rosbags' writer, CDR, ``ros2`` MCAP profile), so
that nothing needs converting:

* ``/tf_static`` (``tf2_msgs/msg/TFMessage``, transient local): one transform per calibrated sensor,
  ``<base frame> -> <sensor name>`` = ``T_body_sensor`` of calibration.yaml (the last extrinsic
  segment when a sensor moved);
* ``/robot_description`` (``std_msgs/msg/String``, transient local): robot_calibrated.urdf's text;
* ``/tf`` (``tf2_msgs/msg/TFMessage``): ``world -> <base frame>`` = the calibration's body pose
  ``T_world_body`` of each station, stamped with the station's time;
* ``/<sensor>/points`` (``sensor_msgs/msg/PointCloud2``): each station's cloud in the sensor frame
  (``frame_id`` the sensor name), float32 x, y, z, stamped with the station's time, evenly thinned
  to at most ``max_points`` points (:data:`DEFAULT_MAX_POINTS`; every k-th point in file order);
* ``/graphcal/notes`` (``std_msgs/msg/String``, transient local): the frames, units, stamps and
  point cap in words; the same text is in the file's rosbag2 metadata (``custom_data``).

Frames: ``T_a_b`` maps coordinates in frame b to frame a (a TransformStamped's ``header.frame_id``
is a, ``child_frame_id`` b). Units: m, s (stamps are ``stations.csv``'s ``time``; a dataset without
times gets one second per station in file order, said in the notes). A dataset with no clouds
(planes only), or one that cannot be read any more, gives the transforms and the URDF only, and
the notes say so.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from graphcal.geometry import quat_wxyz_from_matrix

__all__ = ["DEFAULT_MAX_POINTS", "WORLD_FRAME", "NOTES_TOPIC", "write_scene_mcap", "thin_evenly",
           "cloud_topic", "readable_dataset", "typestore", "stamp_msg", "transform_msg", "point_cloud_msg", "string_msg",
           "latched_qos", "mcap_file"]

#: the default cap on the points of one cloud in scene.mcap (evenly thinned above it)
DEFAULT_MAX_POINTS = 20_000
#: the fixed frame of the body poses on /tf
WORLD_FRAME = "world"
NOTES_TOPIC = "/graphcal/notes"
_STORE = None


def typestore():
    global _STORE
    if _STORE is None:
        from rosbags.typesys import Stores, get_typestore

        _STORE = get_typestore(Stores.ROS2_HUMBLE)
    return _STORE


def cloud_topic(sensor: str) -> str:
    """The PointCloud2 topic of a sensor: ``/<sensor>/points``, the name made a legal ROS topic
    name (characters other than letters, digits and ``_`` become ``_``; a leading digit gets ``s_``)."""
    name = re.sub(r"[^A-Za-z0-9_]", "_", str(sensor)) or "sensor"
    if name[0].isdigit():
        name = "s_" + name
    return f"/{name}/points"


def thin_evenly(points: np.ndarray, max_points: int | None) -> np.ndarray:
    """``points`` (N, 3) evenly thinned to at most ``max_points`` rows (the rows ``floor(i N / cap)``,
    file order kept); all of them when ``max_points`` is None or 0 or N is within it."""
    n = len(points)
    if not max_points or n <= max_points:
        return points
    return points[(np.arange(int(max_points), dtype=np.int64) * n) // int(max_points)]


@dataclass(frozen=True)
class _Station:
    station: int
    stamp_ns: int


def stamp_msg(ns: int):
    Time = typestore().types["builtin_interfaces/msg/Time"]
    return Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def transform_msg(parent: str, child: str, T: np.ndarray, ns: int):
    t = typestore().types
    T = np.asarray(T, dtype=float)
    w, x, y, z = quat_wxyz_from_matrix(T[:3, :3])
    return t["geometry_msgs/msg/TransformStamped"](
        header=t["std_msgs/msg/Header"](stamp=stamp_msg(ns), frame_id=str(parent)),
        child_frame_id=str(child),
        transform=t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
            rotation=t["geometry_msgs/msg/Quaternion"](x=float(x), y=float(y), z=float(z), w=float(w)),
        ),
    )


def point_cloud_msg(frame: str, points: np.ndarray, ns: int):
    t = typestore().types
    PointField = t["sensor_msgs/msg/PointField"]
    pts = np.ascontiguousarray(points, dtype="<f4").reshape(-1, 3)
    fields = [PointField(name=c, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, c in enumerate("xyz")]
    return t["sensor_msgs/msg/PointCloud2"](
        header=t["std_msgs/msg/Header"](stamp=stamp_msg(ns), frame_id=str(frame)),
        height=1, width=len(pts), fields=fields, is_bigendian=False, point_step=12, row_step=12 * len(pts),
        data=pts.view(np.uint8).reshape(-1), is_dense=bool(np.all(np.isfinite(pts))),
    )  # fmt: skip


def string_msg(text: str):
    return typestore().types["std_msgs/msg/String"](data=str(text))


def latched_qos():
    """QoS a late subscriber still gets the message with (as tf2's static broadcaster offers)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(0, 0)
    return [Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, zero, zero,
                QosLiveliness.AUTOMATIC, zero, False)]


@contextlib.contextmanager
def mcap_file(path: Path, notes: str):
    """Write the ROS 2 MCAP file ``path`` (replaced atomically when the block ends without an error;
    nothing left behind otherwise): yields ``put(topic, msgtype, stamp_ns, msg, latched=False)``,
    which serialises ``msg`` (CDR) on its topic's connection (transient local when ``latched``).
    ``notes`` go into the file's rosbag2 metadata (``custom_data``)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    path = Path(path)
    ts = typestore()
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        writer = Writer(tmp / "scene", version=8, storage_plugin=StoragePlugin.MCAP)
        writer.set_custom_data("graphcal/notes", notes)
        writer.open()
        conns: dict = {}

        def put(topic, msgtype, stamp_ns, msg, latched=False):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts,
                                                     offered_qos_profiles=latched_qos() if latched else ())
            writer.write(conns[topic], int(stamp_ns), ts.serialize_cdr(msg, msgtype))

        try:
            yield put
        except BaseException:
            writer.abort()
            raise
        writer.close()
        os.replace(tmp / "scene" / "scene.mcap", path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def readable_dataset(dataset):
    """(Dataset or None, why not) from a Dataset, a dataset folder, or None."""
    from graphcal.errors import GraphcalError
    from graphcal.io.dataset import Dataset, read_dataset

    if dataset is None or isinstance(dataset, Dataset):
        return dataset, "" if dataset is not None else "no dataset given"
    try:
        return read_dataset(dataset), ""
    except (GraphcalError, OSError, ValueError) as e:
        return None, f"the dataset could not be read ({' '.join(str(e).split())})"


def _stations(ds, result) -> tuple[list[_Station], str]:
    """The stations in time order with their stamps, and how they were stamped."""
    st = ds.stations if ds is not None else None
    if st is not None and "time" in st and len(st["station"]):
        times = np.asarray(st["time"], dtype=float)
        if np.all(np.isfinite(times)):
            t0 = min(0.0, float(times.min()))  # stamps cannot be negative: shift only then
            shift = f" shifted by {-t0:g} s (no negative stamps)" if t0 < 0 else ""
            rows = [_Station(int(s), int(round((t - t0) * 1e9))) for s, t in zip(st["station"], times)]
            return sorted(rows, key=lambda r: r.stamp_ns), f"stamps: stations.csv time (s){shift}"
    ids = [int(s) for s in st["station"]] if st is not None else sorted(int(s) for s in result.T_world_body)
    why = "stations.csv has no time" if st is not None else "no stations.csv read"
    return ([_Station(s, i * 1_000_000_000) for i, s in enumerate(ids)],
            f"stamps: one second per station in file order ({why})")


def _notes(result, max_points, stamps: str, clouds: str, n_poses: int) -> str:
    cap = (f"each cloud evenly thinned to at most {max_points} points (every k-th point in file order)"
           if max_points else "clouds not thinned (no point cap)")
    return "\n".join([
        f"graphcal calibration scene of dataset {result.dataset}.",
        "Frames: T_a_b maps coordinates in frame b to frame a; a transform's header.frame_id is a, its "
        "child_frame_id b.",
        f"/tf_static: {result.base_frame} -> <sensor> = T_body_sensor of calibration.yaml (calibrated; the last "
        "extrinsic segment when a sensor moved). Do not also run robot_state_publisher on /robot_description "
        "for the sensor links: the URDF holds the same poses.",
        "/robot_description: robot_calibrated.urdf.",
        f"/tf: {WORLD_FRAME} -> {result.base_frame} = the calibration's body pose of each station ({n_poses} "
        "stations), at the station's stamp.",
        f"/<sensor>/points: {clouds}",
        f"Units: m, s; {stamps}. Points float32 x, y, z in the sensor frame; {cap}.",
    ])


def _station_clouds(ds, result) -> tuple[dict, list[str]]:
    """(sensor, station) -> cloud file of every station cloud of a calibrated sensor, and the
    sensors whose clouds are left out (no calibrated extrinsic)."""
    from graphcal.io.dataset import cloud_paths

    found = cloud_paths(ds) if ds is not None else {}
    return ({k: v for k, v in found.items() if k[0] in result.sensors},
            sorted({s for s, _ in found} - set(result.sensors)))


def _cloud_text(n: int, thinned: int, skipped: list[str], why: str) -> str:
    if not n:
        return f"none: {why}." if why else "none: the dataset has no clouds (planes only)."
    text = (f"{n} station clouds in the sensor frame (frame_id the sensor name), each at its station's "
            f"stamp; {thinned} of them thinned")
    if skipped:
        text += f"; clouds of {', '.join(skipped)} left out (no calibrated extrinsic)"
    return text + "."


def write_scene_mcap(path: str | Path, result, urdf_text: str, *, dataset=None,
                     max_points: int | None = DEFAULT_MAX_POINTS) -> Path:
    """Write the calibration scene to the MCAP file ``path`` (replaced atomically) and return it.

    Args:
        path: the ``.mcap`` file to write.
        result: a :class:`~graphcal.calibration.result.CalibrationResult`.
        urdf_text: the calibrated URDF (robot_calibrated.urdf's text) for ``/robot_description``.
        dataset: the dataset folder (or a :class:`~graphcal.io.dataset.Dataset`) the clouds and
            station times are read from; None, or one that cannot be read: transforms and URDF only
            (the notes say why).
        max_points: cap on the points of each cloud (evenly thinned above it); None or 0: no cap.
    """
    from graphcal.io.dataset import load_cloud

    path = Path(path)
    ds, why = readable_dataset(dataset)
    stations, stamps = _stations(ds, result)
    found, skipped = _station_clouds(ds, result)
    n_clouds = sum((sensor, r.station) in found for r in stations for sensor in result.sensors)
    thinned = 0
    if max_points and found:  # the notes come first in the file: count the thinned clouds up front
        from graphcal.io.ply import read_ply_header

        def n_points(f: Path) -> int:  # from the header alone (the points are read once, when written)
            with open(f, "rb") as fh:
                return read_ply_header(f, fh.read(1 << 16), file_size=os.fstat(fh.fileno()).st_size).n_vertices

        thinned = sum(n_points(f) > max_points for f in found.values())
    poses = sum(r.station in result.T_world_body for r in stations)
    t0 = stations[0].stamp_ns if stations else 0
    notes = _notes(result, max_points, stamps, _cloud_text(n_clouds, thinned, skipped, why), poses)
    ts, tf = typestore(), "tf2_msgs/msg/TFMessage"
    static = ts.types[tf](transforms=[transform_msg(result.base_frame, name, s.T_body_sensor, t0)
                                      for name, s in result.sensors.items()])
    with mcap_file(path, notes) as put:
        put(NOTES_TOPIC, "std_msgs/msg/String", t0, string_msg(notes), latched=True)
        put("/robot_description", "std_msgs/msg/String", t0, string_msg(urdf_text), latched=True)
        put("/tf_static", tf, t0, static, latched=True)
        for r in stations:  # time order: the body pose, then the station's clouds (one in memory at a time)
            if r.station in result.T_world_body:
                put("/tf", tf, r.stamp_ns, ts.types[tf](transforms=[
                    transform_msg(WORLD_FRAME, result.base_frame, result.T_world_body[r.station], r.stamp_ns)]))
            for sensor in result.sensors:
                if (sensor, r.station) in found:
                    pts = thin_evenly(load_cloud(ds, sensor, r.station), max_points)
                    put(cloud_topic(sensor), "sensor_msgs/msg/PointCloud2", r.stamp_ns,
                        point_cloud_msg(sensor, pts, r.stamp_ns))
    return path
