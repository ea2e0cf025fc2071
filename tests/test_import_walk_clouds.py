"""Clouds along a walk (issue 42 item 5, issue 43 item 1): a ROS bag of a simulated hexapod walk --
JointState with efforts and Imu at 200 Hz, 16UC1 depth images + CameraInfo (or PointCloud2) at 15 Hz,
/tf_static with the camera's CAD pose, /robot_description, no still window -- imports with
``--timeseries`` alone as a walking dataset whose ``cloud_<sensor>`` cells name the clouds at the
``--cloud-rate`` chosen, each the simulated cloud of its joint row; ``graphcal validate`` accepts it
and ``graphcal track`` fuses ICP updates from it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from graphcal.cli import main
from graphcal.io.dataset import read_dataset
from graphcal.io.ply import read_ply
from graphcal.simulation.walking import WalkingConfig, simulate_walking

T0 = 1000.0  # stamp of the first sample (s)
CAMERA_LATENCY_S = 0.004  # receive time minus stamp of the camera's messages


def write_walk_bag(result, out: Path, *, fmt: str = "sqlite3", points: str = "depth") -> None:
    """The simulated walk as a robot's log (see the module docstring); ``points``: ``depth`` (16UC1
    images in mm + CameraInfo) or ``cloud`` (PointCloud2)."""
    from graphcal.models.builtin import builtin_info, builtin_urdf
    from graphcal.simulation.ros_log import _cloud_msg, _image_msgs, _Out, _static_tf, _vec, cloud_depth_image, simulated_camera_intrinsics

    info = builtin_info(result.config.robot)
    joints = [j for f in result.feet for j in result.robot.leg(f).joint_names]
    q = np.stack([result.q_measured[j] for j in joints], axis=1)
    tau = np.stack([result.tau_measured[j] for j in joints], axis=1)
    K, shape = simulated_camera_intrinsics("depth_camera", result.config.cloud_stride)
    cloud_at = dict(zip(result.cloud_indices.tolist(), result.clouds))
    with _Out(out, fmt) as o:
        T = o.T
        o.write("/robot_description", "std_msgs/msg/String", T["std_msgs/msg/String"](data=builtin_urdf(
            result.config.robot)), T0 - 0.5)
        o.write("/tf_static", "tf2_msgs/msg/TFMessage", _static_tf(o, T0 - 0.5, [
            (info.base_frame, "depth", info.sensors["depth"].T_body_sensor),
            (info.base_frame, "imu_link", result.T_body_imu)]), T0 - 0.5)
        for k, ts in enumerate(result.times):
            t = T0 + float(ts)
            js = T["sensor_msgs/msg/JointState"](header=o.header(t, ""), name=joints, position=q[k],
                                                 velocity=np.zeros(0), effort=tau[k])
            o.write("/joint_states", "sensor_msgs/msg/JointState", js, t)
            imu = T["sensor_msgs/msg/Imu"](header=o.header(t, "imu_link"),
                                           orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                                           orientation_covariance=np.full(9, -1.0),
                                           angular_velocity=_vec(T, result.imu_gyro[k]),
                                           angular_velocity_covariance=np.zeros(9),
                                           linear_acceleration=_vec(T, result.imu_accel[k]),
                                           linear_acceleration_covariance=np.zeros(9))
            o.write("/imu", "sensor_msgs/msg/Imu", imu, t + 1e-4)
            if k not in cloud_at or not len(cloud_at[k]):
                continue
            tr = t + CAMERA_LATENCY_S
            if points == "cloud":
                o.write("/camera/points", "sensor_msgs/msg/PointCloud2", _cloud_msg(o, t, "depth", cloud_at[k]), tr)
                continue
            z = cloud_depth_image(cloud_at[k], K, shape)
            mm = np.round(z.astype(np.float64) * 1000.0).astype("<u2")
            h, w = mm.shape
            _, cam_info = _image_msgs(o, t, "depth", z, K)
            img = T["sensor_msgs/msg/Image"](header=o.header(t, "depth"), height=h, width=w, encoding="16UC1",
                                             is_bigendian=0, step=2 * w,
                                             data=np.frombuffer(mm.tobytes(), dtype=np.uint8))
            o.write("/camera/depth/camera_info", "sensor_msgs/msg/CameraInfo", cam_info, tr)
            o.write("/camera/depth/image_raw", "sensor_msgs/msg/Image", img, tr)


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """A 10 s tripod walk (no still window: 0.3 s standing at each end), 200 Hz, clouds at 15 Hz,
    and its ROS 2 bag with 16UC1 depth images."""
    d = tmp_path_factory.mktemp("walk")
    result = simulate_walking(WalkingConfig(program="tripod-walk", duration_s=10.0, rate_hz=200.0,
                                            cloud_rate_hz=15.0, still_s=0.3, seed=3))
    write_walk_bag(result, d / "bag", fmt="sqlite3", points="depth")
    return result, d / "bag"


def _cells(ds_dir: Path, sensor: str | None = "camera_depth") -> tuple[np.ndarray, np.ndarray]:
    """(times, paths) of the rows of timeseries.csv with a cloud of ``sensor`` (None: the only sensor)."""
    ds = read_dataset(ds_dir)
    ts = ds.timeseries
    sensor = sensor or next(iter(ds.sensors))
    assert f"cloud_{sensor}" in ts.columns, ts.columns
    col = ts[f"cloud_{sensor}"]
    rows = np.flatnonzero(col != "")
    return ts["time"][rows], col[rows]


def test_thinned_receive_times():
    from graphcal.logs.bag import thinned_receive_times

    r = (np.arange(0, 10.0, 1 / 15) * 1e9).astype(np.int64) + 1_700_000_000 * 10**9  # 15 Hz, epoch ns
    kept = thinned_receive_times(r, 5.0)
    assert len(kept) == 50 and np.allclose(np.diff(kept) * 1e-9, 0.2, atol=1e-6)
    assert len(thinned_receive_times(r, 30.0)) == len(r)  # slower than asked: all of them
    assert len(thinned_receive_times(r, 0.0)) == 0 and len(thinned_receive_times(r[:1], 5.0)) == 1


def test_walk_bag_imports_with_clouds_at_the_rate_and_validates(walk, tmp_path):
    result, bag = walk
    ds = tmp_path / "ds"
    assert main(["import", str(bag), "--timeseries", "--cloud-rate", "5", "--out", str(ds), "--quiet"]) == 0
    assert not (ds / "stations.csv").exists()  # no still window: a walking dataset
    times, paths = _cells(ds)
    duration = result.times[-1] - result.times[0]
    assert abs(len(times) - 5.0 * duration) <= 2, len(times)
    assert np.allclose(np.diff(times), 0.2, atol=0.006)  # 5 Hz out of 15 Hz, on the joint rows (5 ms)
    # each cell names the simulated cloud of its row (16UC1: depth to 0.5 mm)
    sim_t = T0 + result.times[result.cloud_indices]
    for t, rel in list(zip(times, paths))[::10]:
        j = int(np.argmin(np.abs(sim_t - t)))
        assert abs(sim_t[j] - t) <= 0.0051  # the joint row nearest its stamp (200 Hz)
        pts, truth = read_ply(ds / rel), result.clouds[j]
        assert pts.shape == truth.shape
        order = lambda a: a[np.lexsort(np.round(a[:, :2] / a[:, 2:], 6).T)]  # noqa: E731 (by pixel ray)
        np.testing.assert_allclose(order(pts), order(truth), atol=1e-3)
    report = yaml.safe_load((ds / "import_report.yaml").read_text())
    assert report["walk_clouds"]["rate_hz"] == 5.0 and report["walk_clouds"]["sensors"]["camera_depth"]["clouds"] == len(times)
    # the camera's prior comes from /tf_static (the frame of the walk's clouds), not the identity
    cad = read_dataset(ds).sensors["camera_depth"].T_body_sensor_prior.matrix
    from graphcal.models.builtin import builtin_info

    np.testing.assert_allclose(cad, builtin_info("qingzhui").sensors["depth"].T_body_sensor, atol=1e-6)
    assert main(["validate", str(ds), "--quiet"]) == 0


def test_cloud_rate_default_and_zero(walk, tmp_path):
    _, bag = walk
    ds = tmp_path / "default"
    assert main(["import", str(bag), "--timeseries", "--out", str(ds), "--quiet"]) == 0
    times, _ = _cells(ds)
    assert np.allclose(np.diff(times), 0.2, atol=0.006)  # 5 Hz by default
    none = tmp_path / "none"
    assert main(["import", str(bag), "--timeseries", "--cloud-rate", "0", "--out", str(none), "--quiet"]) == 0
    assert "cloud_camera_depth" not in read_dataset(none).timeseries.columns
    assert not (none / "clouds").exists()


def test_negative_cloud_rate_refused(walk, tmp_path, capsys):
    _, bag = walk
    assert main(["import", str(bag), "--timeseries", "--cloud-rate", "-1", "--out", str(tmp_path / "x"),
                 "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--cloud-rate" in err[0] and "expected a rate >= 0 Hz" in err[0]
    assert not (tmp_path / "x").exists()


def test_imported_walk_tracks_with_icp(walk, tmp_path):
    _, bag = walk
    ds = tmp_path / "ds"
    assert main(["import", str(bag), "--timeseries", "--cloud-rate", "10", "--out", str(ds), "--quiet"]) == 0
    assert main(["track", str(ds), "--out", str(tmp_path / "track"), "--quiet"]) == 0
    metrics = json.loads((tmp_path / "track" / "metrics.json").read_text())
    assert metrics["icp_updates"] > 0
    # the IMU interpolated to the joint stamps (held, it was one IMU period late: stance NIS 0.82-0.85)
    assert metrics["consistency"]["kinds"]["stance"]["verdict"] == "consistent"


def test_pointcloud2_walk_in_mcap(tmp_path):
    result = simulate_walking(WalkingConfig(program="tripod-walk", duration_s=4.0, rate_hz=100.0,
                                            cloud_rate_hz=10.0, still_s=0.3, seed=1))
    write_walk_bag(result, tmp_path / "bag", fmt="mcap", points="cloud")
    ds = tmp_path / "ds"
    assert main(["import", str(tmp_path / "bag"), "--timeseries", "--cloud-rate", "2.5", "--out", str(ds),
                 "--quiet"]) == 0
    times, paths = _cells(ds, None)
    assert np.allclose(np.diff(times), 0.4, atol=0.011) and len(times) >= 9
    j = int(np.argmin(np.abs(T0 + result.times[result.cloud_indices] - times[3])))
    np.testing.assert_allclose(read_ply(ds / paths[3]), result.clouds[j], atol=1e-6)  # float32 points
    assert main(["validate", str(ds), "--quiet"]) == 0


@pytest.mark.slow
def test_walk_bag_to_calibration_in_three_commands(walk, tmp_path):
    """import, validate, calibrate: the README's three commands on the ROS 2 bag of a walk (issue 43)
    give the camera's pose and a time offset near 0 (the images' stamps are their capture times)."""
    from graphcal.geometry import rotation_angle_between
    from graphcal.solvers.covariance import extrinsic_errors
    from graphcal.stats import ppf

    result, bag = walk
    ds, out = tmp_path / "walk", tmp_path / "walk-cal"
    assert main(["import", str(bag), "--timeseries", "--cloud-rate", "15", "--out", str(ds), "--quiet"]) == 0
    assert main(["validate", str(ds), "--quiet"]) == 0
    assert main(["calibrate", str(ds), "--out", str(out), "--quiet"]) == 0
    doc = yaml.safe_load((out / "calibration.yaml").read_text())
    entry = doc["sensors"]["camera_depth"]
    from graphcal.io.calibration_yaml import pose_from_dict

    T = pose_from_dict(entry["T_body_sensor"])
    e = extrinsic_errors(T, result.T_body_sensor, np.array(entry["covariance"]))
    assert np.degrees(rotation_angle_between(T[:3, :3], result.T_body_sensor[:3, :3])) < 0.1
    assert e["distance_mm"] < 3.0 and e["nees"] < float(ppf(0.999, 6))
    assert entry["time_offset_source"] == "estimated" and abs(entry["time_offset_s"]) < 0.002
    assert doc["walk"]["frames"]["camera_depth"] >= 100
