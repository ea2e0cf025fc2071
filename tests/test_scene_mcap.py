"""scene.mcap (graphcal.report.scene_mcap), written by calibrate beside calibration.yaml, read back
with rosbags' MCAP reader: the transforms are calibration.yaml's, every station's cloud is there in
its frame at its time, the URDF is the calibrated one, the point cap holds."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from graphcal.geometry import matrix_from_quat_wxyz
from graphcal.io.calibration_yaml import pose_from_dict, read_calibration_yaml
from graphcal.io.dataset import cloud_paths, load_cloud, read_dataset
from graphcal.report import write as write_mod
from graphcal.report.scene_mcap import DEFAULT_MAX_POINTS, NOTES_TOPIC, WORLD_FRAME, thin_evenly, write_scene_mcap


def read_scene(path: Path) -> dict:
    """topic -> [(log time ns, message)] and topic -> offered QoS, read with rosbags' AnyReader (a
    standalone .mcap file, no metadata.yaml beside it, as Foxglove and ``ros2 bag play`` take it)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        qos = {c.topic: c.ext.offered_qos_profiles for c in reader.connections}
        msgs = defaultdict(list)
        for c, t, data in reader.messages(reader.connections):
            msgs[c.topic].append((t, reader.deserialize(data, c.msgtype)))
    return {"types": types, "qos": qos, "msgs": dict(msgs)}


def _pose(tf) -> np.ndarray:
    q, p = tf.transform.rotation, tf.transform.translation
    T = np.eye(4)
    T[:3, :3] = matrix_from_quat_wxyz([q.w, q.x, q.y, q.z])
    T[:3, 3] = [p.x, p.y, p.z]
    return T


def _ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def _points(msg) -> np.ndarray:
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1)]  # fmt: skip
    assert msg.point_step == 12 and msg.height == 1 and not msg.is_bigendian
    return np.frombuffer(bytes(msg.data), dtype="<f4").reshape(msg.width, 3)


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A small simulated octopus session (6 stations, depth clouds) calibrated by the calibrate command."""
    from graphcal.commands.calibrate import run as calibrate
    from graphcal.commands.simulate import run as simulate

    root = tmp_path_factory.mktemp("scene")
    ds = root / "octopus"
    simulate(robot="octopus", program="random", ground="level", out_dir=ds, n_stations=6, cloud_stride=16,
             progress=False)
    out = root / "cal"
    res = calibrate(ds, out, progress=False)
    return ds, out, res.calibration, read_scene(out / "scene.mcap")


def test_calibrate_writes_scene_mcap_beside_calibration_yaml(calibrated):
    ds, out, result, scene = calibrated
    assert (out / "scene.mcap").stat().st_size > 0
    assert "scene.mcap" in read_calibration_yaml(out / "calibration.yaml")["output_files"]
    assert scene["types"] == {NOTES_TOPIC: "std_msgs/msg/String", "/robot_description": "std_msgs/msg/String",
                              "/tf_static": "tf2_msgs/msg/TFMessage", "/tf": "tf2_msgs/msg/TFMessage",
                              "/depth/points": "sensor_msgs/msg/PointCloud2"}
    for topic in (NOTES_TOPIC, "/robot_description", "/tf_static"):  # latched, as tf2's static broadcaster
        assert [q.durability.name for q in scene["qos"][topic]] == ["TRANSIENT_LOCAL"], topic
    assert not list(out.parent.glob(".*"))  # no temporary folder left


def test_scene_static_transforms_equal_calibration_yaml(calibrated):
    ds, out, result, scene = calibrated
    doc = read_calibration_yaml(out / "calibration.yaml")
    (t0, msg), = scene["msgs"]["/tf_static"]
    got = {tf.child_frame_id: tf for tf in msg.transforms}
    assert set(got) == set(doc["sensors"]) == set(result.sensors)
    for name, tf in got.items():
        assert tf.header.frame_id == result.base_frame
        assert _ns(tf.header.stamp) == t0
        np.testing.assert_allclose(_pose(tf), pose_from_dict(doc["sensors"][name]["T_body_sensor"]), rtol=0, atol=1e-9)
        np.testing.assert_allclose(_pose(tf), result.sensors[name].T_body_sensor, rtol=0, atol=1e-12)


def test_scene_robot_description_is_robot_calibrated_urdf(calibrated):
    ds, out, result, scene = calibrated
    (_, msg), = scene["msgs"]["/robot_description"]
    assert msg.data == (out / "robot_calibrated.urdf").read_text(encoding="utf-8")
    assert msg.data != result.robot_urdf_xml  # the calibrated one, not the nominal


def test_scene_every_station_cloud_in_its_frame_at_its_time(calibrated):
    ds_dir, out, result, scene = calibrated
    ds = read_dataset(ds_dir)
    times = dict(zip(ds.stations["station"].tolist(), ds.stations["time"].tolist()))
    files = cloud_paths(ds)
    assert files and len({st for _, st in files}) == len(times)
    clouds = scene["msgs"]["/depth/points"]
    assert len(clouds) == len(files)
    by_stamp = {t: m for t, m in clouds}
    for (sensor, station), _ in files.items():
        ns = int(round(times[station] * 1e9))
        msg = by_stamp[ns]  # the cloud's log time is its station's time
        assert msg.header.frame_id == sensor and _ns(msg.header.stamp) == ns
        want = thin_evenly(load_cloud(ds, sensor, station), DEFAULT_MAX_POINTS).astype(np.float32)
        np.testing.assert_array_equal(_points(msg), want)  # the sensor frame: the PLY's own points
    # the body poses: world -> base at every station's time, the calibration's T_world_body
    poses = scene["msgs"]["/tf"]
    assert [t for t, _ in poses] == sorted(int(round(t * 1e9)) for t in times.values())
    for t, msg in poses:
        (tf,) = msg.transforms
        station = next(s for s, ts in times.items() if int(round(ts * 1e9)) == t)
        assert (tf.header.frame_id, tf.child_frame_id) == (WORLD_FRAME, result.base_frame)
        np.testing.assert_allclose(_pose(tf), result.T_world_body[station], rtol=0, atol=1e-9)


def test_scene_notes_state_frames_units_and_the_point_cap(calibrated):
    ds, out, result, scene = calibrated
    (_, msg), = scene["msgs"][NOTES_TOPIC]
    for words in ("T_a_b maps coordinates in frame b to frame a", "Units: m, s", "stations.csv time",
                  f"at most {DEFAULT_MAX_POINTS} points", f"{len(scene['msgs']['/depth/points'])} station clouds"):
        assert words in msg.data, words


def test_scene_point_cap_is_honoured_and_evenly_spread(calibrated, tmp_path):
    ds_dir, out, result, _ = calibrated
    ds = read_dataset(ds_dir)
    urdf = (out / "robot_calibrated.urdf").read_text(encoding="utf-8")
    sizes = {k: len(load_cloud(ds, *k)) for k in cloud_paths(ds)}
    cap = min(sizes.values()) // 3
    path = write_scene_mcap(tmp_path / "capped.mcap", result, urdf, dataset=ds_dir, max_points=cap)
    scene = read_scene(path)
    clouds = scene["msgs"]["/depth/points"]
    assert len(clouds) == len(sizes) and all(m.width == cap for _, m in clouds)
    assert f"at most {cap} points" in scene["msgs"][NOTES_TOPIC][0][1].data
    assert f"{len(sizes)} of them thinned" in scene["msgs"][NOTES_TOPIC][0][1].data
    # the kept points span the whole cloud (evenly thinned, not its first rows)
    full = read_scene(write_scene_mcap(tmp_path / "all.mcap", result, urdf, dataset=ds_dir, max_points=None))
    for (_, small), (_, big) in zip(clouds, full["msgs"]["/depth/points"]):
        assert big.width > cap
        np.testing.assert_array_equal(_points(small), thin_evenly(_points(big), cap))
    assert path.stat().st_size < (tmp_path / "all.mcap").stat().st_size


def test_thin_evenly_keeps_cap_points_spread_over_the_file_order():
    pts = np.arange(30_000, dtype=float).repeat(3).reshape(-1, 3)
    kept = thin_evenly(pts, 7)
    assert len(kept) == 7 and kept[0, 0] == 0
    np.testing.assert_array_equal(kept[:, 0], [(i * 30_000) // 7 for i in range(7)])
    assert thin_evenly(pts, None) is pts and thin_evenly(pts, 0) is pts and thin_evenly(pts, 40_000) is pts


def test_scene_of_a_planes_only_dataset_has_transforms_and_urdf_only(calibrated, tmp_path):
    from graphcal.commands.simulate import run as simulate

    ds_dir, out, result, _ = calibrated
    planes = tmp_path / "planes"
    simulate(robot="octopus", program="random", ground="level", out_dir=planes, n_stations=6, output="planes",
             progress=False)
    urdf = (out / "robot_calibrated.urdf").read_text(encoding="utf-8")
    scene = read_scene(write_scene_mcap(tmp_path / "scene.mcap", result, urdf, dataset=planes))
    assert "sensor_msgs/msg/PointCloud2" not in scene["types"].values()
    assert {"/tf_static", "/robot_description", NOTES_TOPIC} <= set(scene["types"])
    assert "none: the dataset has no clouds (planes only)" in scene["msgs"][NOTES_TOPIC][0][1].data


def test_scene_without_a_readable_dataset_says_why(calibrated, tmp_path):
    _, out, result, _ = calibrated
    scene = read_scene(write_scene_mcap(tmp_path / "s.mcap", result, "<robot/>", dataset=tmp_path / "gone"))
    assert "sensor_msgs/msg/PointCloud2" not in scene["types"].values()
    note = scene["msgs"][NOTES_TOPIC][0][1].data
    assert "the dataset could not be read" in note and "one second per station" in note
    assert len(scene["msgs"]["/tf"]) == len(result.T_world_body)


def test_a_failing_scene_leaves_the_previous_calibration(calibrated, tmp_path, monkeypatch):
    import shutil

    _, out, result, _ = calibrated
    prev = tmp_path / "cal"
    shutil.copytree(out, prev)
    before = {p.name: p.read_bytes() for p in prev.iterdir()}

    def boom(path, *a, **k):
        Path(path).write_bytes(b"half")
        raise RuntimeError("disk full")

    monkeypatch.setattr(write_mod, "write_scene_mcap", boom)
    monkeypatch.setattr(write_mod, "_write_report", lambda folder, res, title, ds: write_mod.atomic_write_text(
        folder / "report.html", "<html></html>\n"))
    with pytest.raises(RuntimeError, match="disk full"):
        write_mod.write_calibration_outputs(result, prev)
    assert {p.name: p.read_bytes() for p in prev.iterdir()} == before


def test_calibrate_scene_max_points_from_the_command_line(calibrated, tmp_path, capsys):
    """--scene-max-points N caps every station's cloud in scene.mcap; a value under 100 (not 0) is one line, exit 2."""
    from graphcal.cli import main

    ds_dir = calibrated[0]
    assert main(["calibrate", str(ds_dir), "--out", str(tmp_path / "cal"), "--quiet", "--scene-max-points", "500"]) == 0
    clouds = read_scene(tmp_path / "cal" / "scene.mcap")["msgs"]["/depth/points"]
    assert clouds and all(m.width == 500 for _, m in clouds)
    capsys.readouterr()
    assert main(["calibrate", str(ds_dir), "--out", str(tmp_path / "cal2"), "--quiet", "--scene-max-points", "7"]) == 2
    err = capsys.readouterr().err
    assert "--scene-max-points must be a whole number of points >= 100" in err and "Traceback" not in err
