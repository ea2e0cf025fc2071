"""``scene.mcap`` of a track output: the tracked robot, its clouds, footholds and perceived stairs as a
ROS 2 MCAP file Foxglove and RViz 2 open (standard message types, rosbags' writer, CDR).

* ``/tf`` (``tf2_msgs/msg/TFMessage``): ``world -> <base frame>`` = the filter's ``T_world_body``,
  at most :data:`TF_RATE_HZ` per second (every sample below that rate), at the sample's stamp;
* ``/tf_static`` (transient local): ``<base frame> -> <sensor>`` and ``-> imu`` as the track used them;
* ``/robot_description`` (``std_msgs/msg/String``, transient local): the dataset's URDF;
* ``/<sensor>/points`` (``sensor_msgs/msg/PointCloud2``): every cloud the track read, in the sensor
  frame at its stamp, evenly thinned to at most ``max_points`` points;
* ``/graphcal/trajectory`` (``nav_msgs/msg/Path``, world, transient local): the trajectory as above;
* ``/graphcal/footholds`` (``PointCloud2``, world, transient local): one point per stance of each foot;
* ``/graphcal/stairs`` (``visualization_msgs/msg/MarkerArray``, world, transient local): the perceived
  treads and risers (stairs.json) as one LINE_LIST, when there are stairs;
* ``/graphcal/notes`` (``std_msgs/msg/String``, transient local): frames, units, rates and caps.

Frames: ``T_a_b`` maps b-coordinates to a. Units: m, s; stamps are the dataset's times, shifted to
start at 0 when they are negative.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from graphcal.report.scene_mcap import (
    NOTES_TOPIC,
    WORLD_FRAME,
    cloud_topic,
    mcap_file,
    point_cloud_msg,
    stamp_msg,
    string_msg,
    thin_evenly,
    transform_msg,
    typestore,
)

__all__ = ["TF_RATE_HZ", "TRACK_MAX_POINTS", "write_track_mcap"]

#: /tf and /graphcal/trajectory carry at most this many poses per second
TF_RATE_HZ = 50.0
#: the default cap on the points of one cloud in a track's scene.mcap
TRACK_MAX_POINTS = 5000


def _rate_indices(times: np.ndarray, rate_hz: float) -> np.ndarray:
    keep = np.r_[0, np.flatnonzero(np.diff(np.floor(times * rate_hz + 1e-9)) > 0) + 1]
    return np.union1d(keep, [len(times) - 1])


def _line_marker(segments: np.ndarray, ns: int):
    t = typestore().types
    Marker, Point = t["visualization_msgs/msg/Marker"], t["geometry_msgs/msg/Point"]
    pose = t["geometry_msgs/msg/Pose"](position=Point(x=0.0, y=0.0, z=0.0),
                                       orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    return Marker(
        header=t["std_msgs/msg/Header"](stamp=stamp_msg(ns), frame_id=WORLD_FRAME), ns="stairs", id=0,
        type=Marker.LINE_LIST, action=Marker.ADD, pose=pose,
        scale=t["geometry_msgs/msg/Vector3"](x=0.01, y=0.0, z=0.0),
        color=t["std_msgs/msg/ColorRGBA"](r=0.58, g=0.40, b=0.74, a=1.0),
        lifetime=t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0), frame_locked=False,
        points=[Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in segments.reshape(-1, 3)], colors=[],
        texture_resource="", texture=t["sensor_msgs/msg/CompressedImage"](
            header=t["std_msgs/msg/Header"](stamp=stamp_msg(ns), frame_id=""), format="", data=np.zeros(0, np.uint8)),
        uv_coordinates=[], text="", mesh_resource="",
        mesh_file=t["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8)),
        mesh_use_embedded_materials=False,
    )  # fmt: skip


def _path(times_ns: np.ndarray, T: np.ndarray):
    t = typestore().types
    poses = []
    for ns, Ti in zip(times_ns, T):
        tf = transform_msg(WORLD_FRAME, "", Ti, int(ns)).transform
        p = t["geometry_msgs/msg/Point"](x=tf.translation.x, y=tf.translation.y, z=tf.translation.z)
        poses.append(t["geometry_msgs/msg/PoseStamped"](
            header=t["std_msgs/msg/Header"](stamp=stamp_msg(int(ns)), frame_id=WORLD_FRAME),
            pose=t["geometry_msgs/msg/Pose"](position=p, orientation=tf.rotation)))
    return t["nav_msgs/msg/Path"](header=t["std_msgs/msg/Header"](stamp=stamp_msg(int(times_ns[0])),
                                                                 frame_id=WORLD_FRAME), poses=poses)


def _notes(base: str, sensor: str | None, n_clouds: int, max_points: int | None, shift_s: float) -> str:
    cap = f"each evenly thinned to at most {max_points} points" if max_points else "not thinned"
    return "\n".join([
        "graphcal track scene. Frames: T_a_b maps coordinates in frame b to frame a; a transform's "
        "header.frame_id is a, its child_frame_id b.",
        f"/tf: {WORLD_FRAME} -> {base} = the filter's estimate, at most {TF_RATE_HZ:g} per second.",
        f"/tf_static: {base} -> the cloud sensor and the IMU, as the track used them (the dataset's priors).",
        "/robot_description: the dataset's URDF.",
        f"/{sensor or 'sensor'}/points: {n_clouds} clouds in the sensor frame, {cap}." if sensor else "no clouds.",
        "/graphcal/trajectory (nav_msgs/Path), /graphcal/footholds (one point per stance of each foot) and "
        "/graphcal/stairs (the perceived treads and risers, LINE_LIST) are in the world frame.",
        f"Units: m, s; stamps: the dataset's times{f' shifted by {shift_s:g} s' if shift_s else ''}.",
    ])


def write_track_mcap(path: str | Path, *, times: np.ndarray, T_world_body: np.ndarray, base_frame: str,
                     urdf_text: str, T_body_imu: np.ndarray, sensor: str | None = None,
                     T_body_sensor: np.ndarray | None = None, clouds: dict | None = None,
                     footholds: np.ndarray | None = None, stair_segments: np.ndarray | None = None,
                     max_points: int | None = TRACK_MAX_POINTS) -> Path:
    """Write the track scene to ``path`` (replaced atomically) and return it. ``times`` (N,) s,
    ``T_world_body`` (N, 4, 4); ``clouds``: sample index -> loader of (M, 3) points in the sensor
    frame (m); ``footholds`` (K, 3) and ``stair_segments`` (S, 2, 3) in the world frame (m)."""
    path, times = Path(path), np.asarray(times, dtype=float)
    shift = max(0.0, -float(times.min()))
    ns = np.rint((times + shift) * 1e9).astype(np.int64)
    keep = _rate_indices(times, TF_RATE_HZ)
    clouds = clouds or {}
    ts, tf = typestore(), "tf2_msgs/msg/TFMessage"
    notes = _notes(base_frame, sensor if clouds else None, len(clouds), max_points, shift)
    statics = [transform_msg(base_frame, "imu", T_body_imu, int(ns[0]))]
    if sensor and T_body_sensor is not None:
        statics.insert(0, transform_msg(base_frame, sensor, T_body_sensor, int(ns[0])))
    with mcap_file(path, notes) as put:
        t0 = int(ns[0])
        put(NOTES_TOPIC, "std_msgs/msg/String", t0, string_msg(notes), latched=True)
        put("/robot_description", "std_msgs/msg/String", t0, string_msg(urdf_text), latched=True)
        put("/tf_static", tf, t0, ts.types[tf](transforms=statics), latched=True)
        put("/graphcal/trajectory", "nav_msgs/msg/Path", t0, _path(ns[keep], T_world_body[keep]), latched=True)
        if footholds is not None and len(footholds):
            put("/graphcal/footholds", "sensor_msgs/msg/PointCloud2", t0,
                point_cloud_msg(WORLD_FRAME, np.asarray(footholds), t0), latched=True)
        if stair_segments is not None and len(stair_segments):
            put("/graphcal/stairs", "visualization_msgs/msg/MarkerArray", t0,
                ts.types["visualization_msgs/msg/MarkerArray"](markers=[_line_marker(stair_segments, t0)]),
                latched=True)
        cloud_at, posed = dict(sorted(clouds.items())), set(keep.tolist())
        for i in np.union1d(keep, list(cloud_at)).astype(int):  # time order: the pose, then its cloud
            if i in posed:
                put("/tf", tf, ns[i], ts.types[tf](transforms=[
                    transform_msg(WORLD_FRAME, base_frame, T_world_body[i], int(ns[i]))]))
            if i in cloud_at and sensor:
                pts = thin_evenly(np.asarray(cloud_at[i](), dtype=float), max_points)
                put(cloud_topic(sensor), "sensor_msgs/msg/PointCloud2", ns[i], point_cloud_msg(sensor, pts, int(ns[i])))
    return path
