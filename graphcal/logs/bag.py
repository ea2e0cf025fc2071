"""Import a ROS 1 bag, ROS 2 bag or bare MCAP file: detect or read the map, then two streaming
passes. Pass 1 reads the log once: joints, IMU, feet and /tf_static are deserialised and the still windows
found; of the point topics only the receive times are kept (8 bytes a message). Pass 2 reads, through
the log's index, only the message nearest each window's centre; with ``--timeseries`` also the
messages along the walk, thinned to ``--cloud-rate``, each staged as a PLY file at once. Memory does
not grow with the log's length (except those receive times and the optional timeseries). Times in
s, SI units."""

from __future__ import annotations

import logging
from array import array
from pathlib import Path

import numpy as np

from graphcal.errors import DatasetError
from graphcal.io.dataset.model import ImuSpec, PosePrior, RobotSpec, SensorSpec
from graphcal.logs import messages as M
from graphcal.logs.assemble import DatasetParts, SampleSink, StampCheck, foot_thresholds, write_imported
from graphcal.logs.mapping import IMAGE, SCAN, check_map, detect_map, map_yaml_text, read_map, thresholds_of
from graphcal.logs.reader import LogReader, types_from_msg_dir
from graphcal.logs.stations import StationFinder
from graphcal.logs.urdf_frames import UrdfFrames, check_robot, resolve_map_path
from graphcal.progress import ProgressBar

__all__ = ["import_bag", "urdf_feet_and_root", "staged_ply", "thinned_receive_times", "WALK_CLOUD_RATE_HZ"]

log = logging.getLogger(__name__)

#: default rate (Hz) of the clouds kept along a walk with ``--timeseries`` (``--cloud-rate``)
WALK_CLOUD_RATE_HZ = 5.0


def urdf_feet_and_root(urdf_xml: str, source: str) -> tuple[str, tuple[str, ...]]:
    """(root link, leaf links named like feet: ``*foot*`` or ``*toe*``) of a URDF."""
    from graphcal.models.urdf_xml import parse_urdf

    try:
        root = parse_urdf(urdf_xml)
    except Exception as exc:
        raise DatasetError(source, "URDF", "a valid URDF", str(exc)) from None
    links = [e.get("name") for e in root.findall("link")]
    parents = {j.find("parent").get("link") for j in root.findall("joint") if j.find("parent") is not None}
    children = {j.find("child").get("link") for j in root.findall("joint") if j.find("child") is not None}
    roots = [l for l in links if l not in children]
    feet = tuple(l for l in links if l not in parents and ("foot" in l.lower() or "toe" in l.lower()))
    return (roots[0] if roots else ""), feet


def _first_message(reader: LogReader, topic: str):
    for topic_, t_ns, raw in reader.messages([topic]):
        return reader.deserialize(raw, topic_, t_ns)
    return None


def _robot(reader: LogReader, m: dict | None, urdf_file: Path | None,
           map_path: Path | None = None) -> tuple[str | None, str | None]:
    """(URDF text or None, where it came from): ``urdf_file``, else the map's ``robot.urdf`` (a
    topic of the log or a file, relative to the map's folder), else (no map) the log's
    ``/robot_description``."""
    if m is not None:
        source = (m.get("robot") or {}).get("urdf")
    else:
        source = "/robot_description" if "/robot_description" in reader.topics else None
    if urdf_file is not None:
        source = str(urdf_file)
    if not source:
        return None, None
    if source in reader.topics:
        msg = _first_message(reader, source)
        return (msg.data if msg is not None else None), source
    if urdf_file is None:
        source = str(resolve_map_path(source, map_path))
    try:
        return Path(source).read_text(encoding="utf-8"), source
    except OSError as exc:
        raise DatasetError(source, "file", "a readable URDF (robot.urdf of the map, or --urdf)",
                           exc.strerror or str(exc)) from None


def _pass1(reader: LogReader, m: dict, sink_args: dict, progress: bool):
    """Every topic of the map in one read: joints, IMU, feet and /tf_static deserialised; the point
    topics only timed (receive times, ns) and each camera's first CameraInfo kept. Returns
    (joint names, sink, static transforms, IMU frame, clock jumps, sensor -> receive times,
    sensor -> (fx, fy, cx, cy))."""
    stamps = StampCheck(reader.path)
    use_header = m["stamps"] == "header"
    jt = m["joints"]["topic"]
    it = (m.get("imu") or {}).get("topic")
    feet = m.get("feet") or {}
    by_topic: dict[str, dict] = {}
    for name, f in feet.items():
        by_topic.setdefault(f["topic"], {})[name] = f
    foot_topics = {t: M.FootForces(specs) for t, specs in by_topic.items()}
    tf = m.get("tf_static")
    sensors = m.get("sensors") or {}
    point_topics = {s["topic"]: name for name, s in sensors.items()}
    info_topics = {s["camera_info"]: name for name, s in sensors.items() if s.get("camera_info")}
    topics = [t for t in [jt, it, tf, *foot_topics] if t]
    for t in [*topics, *point_topics, *info_topics]:
        reader.check_type_known(t)
    th = sink_args["thresholds"]
    learn = [f for f, spec in feet.items() if "threshold_n" not in spec and "threshold_raw" not in spec]
    samples = _foot_samples(reader, foot_topics, learn) if learn else {}
    thresholds = foot_thresholds(samples, feet, th.force_threshold_n)
    names: tuple[str, ...] | None = None
    sink = None
    offset = 0.0
    transforms: dict = {}
    imu_frame = None
    received: dict[str, array] = {name: array("q") for name in sensors}
    K: dict[str, np.ndarray] = {}
    every = [*topics, *point_topics, *info_topics]
    bar = ProgressBar(total=sum(reader.topics[t].count for t in every), unit="msg", desc="import", disable=not progress,
               mininterval=0.5)
    for n, (topic, t_ns, raw) in enumerate(reader.messages(every)):
        if n % 1000 == 0:
            bar.update(1000 if n else 0)
        if topic in point_topics:
            received[point_topics[topic]].append(t_ns)
            continue
        if topic in info_topics:
            if info_topics[topic] not in K:
                K[info_topics[topic]] = M.camera_matrix(reader.deserialize(raw, topic, t_ns))
            continue
        msg = reader.deserialize(raw, topic, t_ns)
        if topic == tf:
            for parent, child, T in M.static_transforms(msg):
                transforms[child] = (parent, T)
            continue
        t = M.header_stamp(msg) if use_header else None
        t = t_ns * 1e-9 if t is None else t
        stamps(topic, t)
        if topic == jt:
            jn, q = M.joint_state(msg)
            if names is None:
                names = jn
                offset = t_ns * 1e-9 - t  # receive time minus stamp (s): where to look for clouds
                finder = StationFinder(names, tuple(feet), bool(it), th)
                sink = SampleSink(finder, thresholds, sink_args["timeseries"])
            tau = M.joint_efforts(msg)
            if jn != names:
                q = _reorder(reader, topic, t, names, jn, q)
                tau = _reorder(reader, topic, t, names, jn, tau) if tau is not None else None
            sink.joints(t, q, tau)
        elif sink is None:
            continue  # nothing before the first joint sample
        elif topic == it:
            imu_frame = imu_frame or msg.header.frame_id.lstrip("/")
            sink.imu(t, *M.imu_sample(msg))
        else:
            reader_ = foot_topics[topic]
            sink.feet_array(t, reader_.names, reader_(msg))
    bar.close()
    if sink is None:
        raise DatasetError(reader.path, f"topic {jt}", "sensor_msgs/msg/JointState messages", "none")
    sink.finder.finish()
    sink.receive_offset_s = offset
    return names, sink, transforms, imu_frame, stamps.jumps, received, K


def _foot_samples(reader: LogReader, foot_topics: dict, feet: list[str]) -> dict[str, np.ndarray]:
    """A first read of the foot topics only: foot -> its loads (the map's unit), for the feet
    ``feet`` whose contact thresholds are learned from their own signal."""
    topics = [t for t, r in foot_topics.items() if set(r.names) & set(feet)]
    values: dict[str, list] = {f: [] for f in feet}
    for topic, t_ns, raw in reader.messages(topics):
        r = foot_topics[topic]
        v = r(reader.deserialize(raw, topic, t_ns))
        for name, x in zip(r.names, v):
            if name in values:
                values[name].append(float(x))
    return {f: np.asarray(v, dtype=float) for f, v in values.items()}


def _reorder(reader: LogReader, topic: str, t: float, names, jn, q) -> np.ndarray:
    """``q`` (in the order ``jn``) in the order ``names``; DatasetError when one is missing."""
    index = {j: i for i, j in enumerate(jn)}
    missing = [j for j in names if j not in index]
    if missing or len(q) != len(jn):
        raise DatasetError(reader.path, f"topic {topic} at t = {t:.6f} s",
                           f"positions of the joints {', '.join(names)}", f"missing {missing}")
    return q[[index[j] for j in names]]


def _points(reader: LogReader, s: dict, topic: str, msg, K, t: float) -> np.ndarray:
    try:
        if s["msgtype"] == IMAGE:
            return M.depth_image_points(msg, K, int(s.get("stride", 1)))
        if s["msgtype"] == SCAN:
            return M.laser_scan_points(msg)
        return M.cloud_points(msg)
    except (ValueError, KeyError) as exc:
        raise DatasetError(reader.path, f"topic {topic} at t = {t:.6f} s", f"a usable {s['msgtype']}", str(exc)) from None


def staged_ply(path: Path, points: np.ndarray) -> None:
    """(N, 3) points (m) as a binary little-endian float64 PLY (x, y, z), without Open3D or fsync:
    a staging file, copied into the dataset (which is written atomically) at the end."""
    pts = np.ascontiguousarray(points, dtype="<f8")
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ValueError(f"{path}: points must be a non-empty (N, 3) array, got shape {pts.shape}")
    header = (f"ply\nformat binary_little_endian 1.0\ncomment frame: sensor, units: m\nelement vertex {len(pts)}\n"
              "property double x\nproperty double y\nproperty double z\nend_header\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(pts.tobytes())


def _pass2(reader: LogReader, m: dict, windows, received: dict, K: dict, progress: bool,
           staging: Path, offset: float = 0.0) -> dict[str, str]:
    """Set ``w.clouds[sensor]`` to a PLY file under ``staging`` holding the points (m, sensor
    frame) of the message nearest each window's centre among those stamped inside it (so that no
    cloud stays in memory): the candidates are read by receive time through the log's index
    (nearest first, a few at most), nothing else; ``offset`` (s) is the receive time minus the stamp
    of the first joint message (a recorder whose clock differs from the robot's). Returns sensor ->
    frame id."""

    sensors = m.get("sensors") or {}
    use_header = m["stamps"] == "header"
    pad_ns = 1_000_000_000  # receive time may lag the header stamp (s -> ns)
    frames: dict[str, str] = {}
    for w in ProgressBar(windows, desc="import: clouds", unit="station", disable=not progress or not sensors):
        for name, s in sensors.items():
            r = np.frombuffer(received[name], dtype=np.int64) if len(received[name]) else np.zeros(0, np.int64)
            lo, hi = np.searchsorted(r, [int((w.start + offset) * 1e9) - pad_ns, int((w.end + offset) * 1e9) + pad_ns])
            cand = r[lo:hi]
            for t_ns in cand[np.argsort(np.abs(cand * 1e-9 - offset - w.centre))][:5]:
                got = next(reader.messages([s["topic"]], int(t_ns), int(t_ns) + 1), None)
                if got is None:
                    continue
                msg = reader.deserialize(got[2], s["topic"], int(t_ns))
                t = M.header_stamp(msg) if use_header else t_ns * 1e-9
                if not w.start <= t <= w.end or (s["msgtype"] == IMAGE and name not in K):
                    continue
                path = staging / "pending" / name / f"{len(frames)}_{int(t_ns)}.ply"
                path.parent.mkdir(parents=True, exist_ok=True)
                staged_ply(path, _points(reader, s, s["topic"], msg, K.get(name), t))
                w.clouds[name] = path
                frames[name] = msg.header.frame_id.lstrip("/")
                break
    return frames


def thinned_receive_times(received: np.ndarray, rate_hz: float) -> np.ndarray:
    """The receive times (ns, increasing) of the messages kept along a walk at ``rate_hz``: the one
    nearest each tick of a 1 / ``rate_hz`` s grid from the first message (all of them when they come
    slower than that); none for ``rate_hz`` <= 0."""
    r = np.asarray(received, dtype=np.int64)
    if rate_hz <= 0 or len(r) == 0:
        return r[:0]
    if len(r) == 1:
        return r
    rel = (r - r[0]).astype(np.float64)  # ns from the first (float64 keeps ns exactly over ~100 days)
    step = 1e9 / float(rate_hz)
    grid = step * np.arange(int(rel[-1] // step) + 1)
    i = np.searchsorted(rel, grid).clip(1, len(r) - 1)
    i = np.where(np.abs(rel[i - 1] - grid) <= np.abs(rel[i] - grid), i - 1, i)
    return r[np.unique(i)]


def _walk_clouds(reader: LogReader, m: dict, received: dict, K: dict, rate_hz: float, progress: bool,
                 staging: Path) -> tuple[dict[str, list[tuple[float, Path]]], dict[str, str], list[str]]:
    """The clouds along the walk: each sensor's point messages thinned to ``rate_hz``
    (:func:`thinned_receive_times`), read one by one by receive time through the log's index (as
    :func:`_pass2` does) and staged as PLY files under ``staging/walk/<sensor>/`` (no cloud stays in
    memory). Returns (sensor -> [(stamp s, staged file)], sensor -> frame id, notes)."""
    sensors = m.get("sensors") or {}
    use_header = m["stamps"] == "header"
    picked = {name: thinned_receive_times(np.frombuffer(received[name], dtype=np.int64), rate_hz)
              for name in sensors}
    out: dict[str, list[tuple[float, Path]]] = {name: [] for name in sensors}
    frames: dict[str, str] = {}
    notes: list[str] = []
    bar = ProgressBar(total=sum(len(v) for v in picked.values()), desc="import: walk clouds", unit="cloud",
                      disable=not progress or not any(len(v) for v in picked.values()))
    for name, s in sensors.items():
        if s["msgtype"] == IMAGE and name not in K and len(picked[name]):
            notes.append(f"sensors.{name}: no CameraInfo on {s.get('camera_info')}: its depth images along the "
                         "walk are not written")
            bar.update(len(picked[name]))
            continue
        empty = 0
        for t_ns in picked[name]:
            bar.update(1)
            got = next(reader.messages([s["topic"]], int(t_ns), int(t_ns) + 1), None)
            if got is None:
                continue
            msg = reader.deserialize(got[2], s["topic"], int(t_ns))
            t = M.header_stamp(msg) if use_header else None
            t = int(t_ns) * 1e-9 if t is None else t
            pts = _points(reader, s, s["topic"], msg, K.get(name), t)
            if not len(pts):
                empty += 1
                continue
            path = staging / "walk" / name / f"{len(out[name]):06d}.ply"
            path.parent.mkdir(parents=True, exist_ok=True)
            staged_ply(path, pts)
            out[name].append((t, path))
            frames.setdefault(name, msg.header.frame_id.lstrip("/"))
        if empty:
            notes.append(f"sensors.{name}: {empty} message(s) along the walk without a point (not written)")
    bar.close()
    return {k: v for k, v in out.items() if v}, frames, notes


def _prior(m: dict, transforms: dict, base: str, frame: str | None, what: str, source, default_sigma=None):
    p = m.get("priors") or {}
    sig_m = 1e-3 * float(p.get("sigma_mm", 50.0))
    sig_r = np.radians(float(p.get("sigma_rpy_deg", 5.0)))
    if default_sigma is not None and frame is None:
        return PosePrior(np.zeros(3), np.zeros(3), *default_sigma)
    if not transforms:
        raise DatasetError(source, f"{what} (frame {frame})", f"a static transform from {base} on /tf_static "
                           "(set tf_static in the import map)", "no /tf_static")
    return PosePrior.from_matrix(M.chain_pose(transforms, base, frame, str(source)), sig_m, sig_r)


def _frames(urdf_xml: str | None, urdf_src: str | None, rob: dict) -> UrdfFrames:
    """The robot's link tree: its URDF, or the built-in model's."""
    if urdf_xml:
        return UrdfFrames(urdf_xml, str(urdf_src))
    from graphcal.models.builtin import builtin_urdf

    return UrdfFrames(builtin_urdf(rob["model"]), f"of the built-in model {rob['model']}")


def _imu_link_prior(m: dict, frames: UrdfFrames, map_file) -> PosePrior | None:
    """The base frame and feet checked against the URDF, and the ``T_body_imu`` prior of the
    map's ``imu.link`` (the URDF's fixed transform), before the log is read."""
    rob = m["robot"]
    check_robot(frames, rob["base_frame"], rob["feet"], (), map_file)
    spec = m.get("imu") or {}
    return frames.imu_prior(rob["base_frame"], spec, map_file) if spec.get("link") is not None else None


def _imu_spec(m: dict, link_prior, transforms: dict, base: str, imu_frame: str | None, frames: UrdfFrames,
              log_path: Path, notes: list[str]) -> ImuSpec | None:
    """The IMU's mount: the map's ``imu.link`` in the URDF, else /tf_static from the base to the
    IMU messages' frame, else that frame as a URDF link fixed to the base, else identity (1 deg)."""
    if not m.get("imu"):
        return None
    if link_prior is not None:
        return ImuSpec(link_prior)
    if not imu_frame or imu_frame == base:
        return ImuSpec(PosePrior(np.zeros(3), np.zeros(3), 0.0, np.radians(1.0)))
    try:
        return ImuSpec(_prior(m, transforms, base, imu_frame, "imu", log_path))
    except DatasetError:
        pass
    try:
        prior = frames.imu_prior(base, {"link": imu_frame}, log_path, "imu (frame of the IMU messages)")
        notes.append(f"IMU mount from the URDF link {imu_frame} (no /tf_static from {base} to it)")
        return ImuSpec(prior)
    except DatasetError:
        notes.append(f"no /tf_static or URDF link from {base} to the IMU frame {imu_frame}: IMU prior identity, "
                     "1 deg (name the IMU's URDF link as imu.link in the import map)")
        return ImuSpec(PosePrior(np.zeros(3), np.zeros(3), 0.0, np.radians(1.0)))


def import_bag(log_path: Path, out_dir: Path, *, map_path: Path | None = None, urdf_file: Path | None = None,
               receive_time: bool = False, msg_dir: Path | None = None, timeseries: bool = False,
               progress: bool = True, overwrite: bool = False,
               cloud_rate_hz: float = WALK_CLOUD_RATE_HZ) -> tuple[Path, str]:
    """``graphcal import`` of a bag or MCAP file (see the module docstring); returns (folder, summary).
    With ``timeseries``, the point messages along the walk are also written, thinned to
    ``cloud_rate_hz`` (Hz; 0: none), and named in timeseries.csv's ``cloud_<sensor>`` column on the
    joint row nearest each one's stamp."""
    if not np.isfinite(cloud_rate_hz) or cloud_rate_hz < 0:
        raise DatasetError(log_path, "--cloud-rate", "a rate >= 0 Hz (0: no clouds along the walk)", cloud_rate_hz)
    import tempfile

    extra = types_from_msg_dir(msg_dir) if msg_dir is not None else None
    Path(out_dir).absolute().parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".graphcal-import-", dir=Path(out_dir).absolute().parent) as staging:
        return _import_bag(log_path, Path(out_dir), Path(staging), map_path=map_path, urdf_file=urdf_file,
                           receive_time=receive_time, extra=extra, timeseries=timeseries, progress=progress,
                           overwrite=overwrite, cloud_rate_hz=cloud_rate_hz)


def _import_bag(log_path: Path, out_dir: Path, staging: Path, *, map_path, urdf_file, receive_time, extra,
                timeseries, progress, overwrite, cloud_rate_hz) -> tuple[Path, str]:
    with LogReader(log_path, extra) as reader:
        given = read_map(map_path) if map_path is not None else None
        urdf_xml, urdf_src = _robot(reader, given, urdf_file, map_path)
        root, feet_guess = urdf_feet_and_root(urdf_xml, urdf_src) if urdf_xml else ("", ())
        m = given or detect_map(reader.topics, feet_guess)
        if receive_time:
            m["stamps"] = "receive"
        if urdf_file is not None:
            m["robot"]["urdf"] = str(urdf_file)
        rob = m["robot"]
        if not urdf_xml and rob.get("model"):
            from graphcal.models.builtin import builtin_info

            info = builtin_info(rob["model"])  # ModelError (one line) for an unknown name
            root, feet_guess = info.base_frame, tuple(info.feet)
        rob["base_frame"] = rob.get("base_frame") or root or None
        rob["feet"] = rob.get("feet") or list(feet_guess) or None
        map_text = map_yaml_text(m, log_path)
        log.info("import map (%s):\n%s", map_path or "detected", map_text)
        m = check_map(m, reader.topics, log_path, str(map_path or "the import map (--map)"))
        rob = m["robot"]
        if not urdf_xml and not rob.get("model"):
            raise DatasetError(log_path, "robot", "a URDF (/robot_description, --urdf) or robot.model in the map",
                               "none")
        if not rob.get("feet") or not rob.get("base_frame"):
            raise DatasetError(map_path or log_path, "robot.feet / robot.base_frame",
                               "the robot's foot frames and base frame (set them in the import map)", None)
        th = thresholds_of(m, str(map_path or "import map"))
        imu_link_prior = _imu_link_prior(m, _frames(urdf_xml, urdf_src, rob), map_path or log_path)
        names, sink, transforms, imu_frame, jumps, received, K = _pass1(
            reader, m, {"thresholds": th, "timeseries": timeseries}, progress)
        frames = _pass2(reader, m, sink.finder.accepted, received, K, progress, staging, sink.receive_offset_s)
        walk, walk_frames, walk_notes = _walk_clouds(reader, m, received, K, cloud_rate_hz if timeseries else 0.0,
                                                     progress, staging)
        frames = {**walk_frames, **frames}
    base = rob["base_frame"]
    sensors = {}
    for name, s in (m.get("sensors") or {}).items():
        prior = s.get("prior")
        if isinstance(prior, dict):
            pp = PosePrior(prior.get("xyz", [0, 0, 0]), np.radians(prior.get("rpy_deg", [0, 0, 0])),
                           1e-3 * float(prior.get("sigma_mm", 50)), np.radians(float(prior.get("sigma_rpy_deg", 5))))
        elif name in frames:
            pp = _prior(m, transforms, base, frames[name], f"sensors.{name}", log_path)
        else:
            pp = PosePrior(np.zeros(3), np.zeros(3), 0.05, np.radians(5.0))
        sensors[name] = SensorSpec(name, s["type"], pp)
    notes: list[str] = list(walk_notes)
    imu = _imu_spec(m, imu_link_prior, transforms, base, imu_frame, _frames(urdf_xml, urdf_src, rob), log_path,
                    notes)
    robot = RobotSpec("robot.urdf" if urdf_xml else None, None if urdf_xml else rob["model"], base, rob["feet"])
    parts = DatasetParts(robot, urdf_xml, names, sensors, imu, sink.finder, sink, notes=notes,
                         source=str(log_path), map_text=map_text, walk_clouds=walk,
                         walk_cloud_rate_hz=cloud_rate_hz if timeseries else None)
    return write_imported(parts, Path(out_dir), overwrite=overwrite, jumps=jumps, staging=staging)
