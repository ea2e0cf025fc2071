"""Benchmark of ``graphcal import`` on a generated ROS 2 MCAP log of realistic rates: 1 kHz
JointState (12 joints) and Imu, 1 kHz raw foot forces (Float32MultiArray), 30 Hz 640x480 16UC1 depth
images + CameraInfo, /tf_static and /robot_description; the robot (an A1) stands still 3 s of every
10 s. Measures, each in a fresh process: the import's wall time and peak memory (ru_maxrss) against
rosbags alone reading and deserialising every message of the same log; two lengths show whether the
memory grows with the log.

    PYTHONPATH=$PWD .venv/bin/python bench/import_bag.py [--seconds 20 40] [--dir /tmp/gc_bench]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

K = (525.0, 525.0, 319.5, 239.5)
FEET = ("fl_foot", "fr_foot", "rl_foot", "rr_foot")


def generate(path: Path, seconds: float) -> None:
    """Write the log (see the module docstring) with rosbags' MCAP writer."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from graphcal.logs.reader import default_typestore
    from graphcal.models.builtin import builtin_urdf
    from graphcal.simulation.ros_log import depth_image

    ts = default_typestore("ros2")
    T = ts.types
    joints = [f"{leg}_{j}_joint" for leg in ("fl", "fr", "rl", "rr") for j in ("hip", "thigh", "calf")]
    q0 = np.tile([0.0, 0.8, -1.5], 4)

    def hdr(t, frame=""):
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int((t % 1) * 1e9)),
                                        frame_id=frame)

    def vec(x, y, z):
        return T["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z))

    z = depth_image(np.array([0.0, -0.6, -0.8, 0.5]), K, (480, 640))
    depth = (z * 1000).astype("<u2")
    ser = ts.serialize_cdr
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = {name: w.add_connection(name, typ, typestore=ts) for name, typ in (
            ("/robot_description", "std_msgs/msg/String"), ("/tf_static", "tf2_msgs/msg/TFMessage"),
            ("/joint_states", "sensor_msgs/msg/JointState"), ("/imu", "sensor_msgs/msg/Imu"),
            ("/foot_force", "std_msgs/msg/Float32MultiArray"), ("/camera/depth/image_raw", "sensor_msgs/msg/Image"),
            ("/camera/depth/camera_info", "sensor_msgs/msg/CameraInfo"))}
        t0 = 1.7e9
        w.write(c["/robot_description"], int(t0 * 1e9) - 1, ser(T["std_msgs/msg/String"](data=builtin_urdf("a1")),
                                                                "std_msgs/msg/String"))
        tf = T["geometry_msgs/msg/TransformStamped"](
            header=hdr(t0, "body"), child_frame_id="camera_depth_optical_frame",
            transform=T["geometry_msgs/msg/Transform"](translation=vec(0.25, 0, 0.05), rotation=T[
                "geometry_msgs/msg/Quaternion"](x=-0.65, y=0.65, z=-0.27, w=0.27)))
        w.write(c["/tf_static"], int(t0 * 1e9) - 1, ser(T["tf2_msgs/msg/TFMessage"](transforms=[tf]), "tf2_msgs/msg/TFMessage"))
        info = T["sensor_msgs/msg/CameraInfo"](
            header=hdr(t0, "camera_depth_optical_frame"), height=480, width=640, distortion_model="plumb_bob",
            d=np.zeros(5), k=np.array([K[0], 0, K[2], 0, K[1], K[3], 0, 0, 1.0]), r=np.eye(3).ravel(),
            p=np.zeros(12), binning_x=0, binning_y=0,
            roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
        for i in range(int(seconds * 1000)):
            t = t0 + i * 1e-3
            phase = (i % 10000) / 1000.0  # s into the 10 s cycle: still for the first 3 s
            moving = phase >= 3.0
            q = q0 + (0.2 * np.sin(np.pi * (phase - 3.0) / 7.0) if moving else 0.0)
            ns = int(t * 1e9)
            w.write(c["/joint_states"], ns, ser(T["sensor_msgs/msg/JointState"](
                header=hdr(t), name=joints, position=q, velocity=np.zeros(12), effort=np.zeros(12)),
                "sensor_msgs/msg/JointState"))
            w.write(c["/imu"], ns + 1000, ser(T["sensor_msgs/msg/Imu"](
                header=hdr(t, "imu_link"), orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.zeros(9), angular_velocity=vec(0, 0, 0.3 if moving else 0.001),
                angular_velocity_covariance=np.zeros(9), linear_acceleration=vec(0.1, 0.0, 9.8),
                linear_acceleration_covariance=np.zeros(9)), "sensor_msgs/msg/Imu"))
            w.write(c["/foot_force"], ns + 2000, ser(T["std_msgs/msg/Float32MultiArray"](
                layout=T["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0),
                data=np.full(4, 150.0, dtype=np.float32)), "std_msgs/msg/Float32MultiArray"))
            if i % 33 == 0:  # 30 Hz
                info.header = hdr(t, "camera_depth_optical_frame")
                w.write(c["/camera/depth/camera_info"], ns + 3000, ser(info, "sensor_msgs/msg/CameraInfo"))
                img = T["sensor_msgs/msg/Image"](header=hdr(t, "camera_depth_optical_frame"), height=480, width=640,
                                                 encoding="16UC1", is_bigendian=0, step=1280,
                                                 data=np.frombuffer(depth.tobytes(), dtype=np.uint8))
                w.write(c["/camera/depth/image_raw"], ns + 4000, ser(img, "sensor_msgs/msg/Image"))


def rosbags_alone(log: str) -> None:
    """Read and deserialise every message with rosbags' AnyReader (the baseline)."""
    from rosbags.highlevel import AnyReader

    n = 0
    with AnyReader([Path(log)]) as r:
        for conn, _, raw in r.messages():
            r.deserialize(raw, conn.msgtype)
            n += 1
    print(n)


def timed(cmd: list[str]) -> tuple[float, float, str]:
    """(wall s, peak RSS MiB, stdout) of ``cmd`` in a fresh process."""
    t = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t
    out = p.stdout.read()
    if status != 0:
        raise SystemExit(f"{cmd} failed: {p.stderr.read()}")
    return wall, ru.ru_maxrss / 1024.0, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, nargs="+", default=[20.0, 40.0])
    ap.add_argument("--dir", type=Path, default=Path("/tmp/gc_bench_import"))
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--repeats", type=int, default=3, help="runs of each, alternated; medians reported")
    args = ap.parse_args()
    args.dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for s in args.seconds:
        log = args.dir / f"log_{int(s)}s"
        if not log.exists():
            t = time.perf_counter()
            generate(log, s)
            print(f"generated {log} in {time.perf_counter() - t:.1f} s", file=sys.stderr)
        size = sum(f.stat().st_size for f in log.iterdir())
        base, imp = [], []
        for _ in range(args.repeats):  # alternated, so that load changes hit both alike
            base.append(timed([sys.executable, __file__, "--rosbags-alone", str(log)]))
            out = args.dir / f"ds_{int(s)}s"
            shutil.rmtree(out, ignore_errors=True)
            imp.append(timed([sys.executable, "-m", "graphcal", "import", str(log), "--out", str(out), "--quiet"]))
        base_wall, imp_wall = float(np.median([b[0] for b in base])), float(np.median([i[0] for i in imp]))
        rows.append({"seconds": s, "size_MB": size / 1e6, "rosbags_s": base_wall,
                     "rosbags_MiB": max(b[1] for b in base), "import_s": imp_wall, "import_MiB": max(i[1] for i in imp),
                     "speed_ratio": base_wall / imp_wall, "rosbags_all_s": [b[0] for b in base],
                     "import_all_s": [i[0] for i in imp], "summary": imp[0][2].splitlines()[0]})
        print(json.dumps(rows[-1]))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    print("| log | size (MB) | rosbags alone (s) | import (s) | import speed / rosbags | peak MiB rosbags | peak MiB import |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['seconds']:g} s | {r['size_MB']:.0f} | {r['rosbags_s']:.1f} | {r['import_s']:.1f} | "
              f"{r['speed_ratio']:.2f} | {r['rosbags_MiB']:.0f} | {r['import_MiB']:.0f} |")
    if len(rows) >= 2:
        a, b = rows[0], rows[-1]
        per_s_base = (b["rosbags_s"] - a["rosbags_s"]) / (b["seconds"] - a["seconds"])
        per_s_imp = (b["import_s"] - a["import_s"]) / (b["seconds"] - a["seconds"])
        mb_per_s = (b["size_MB"] - a["size_MB"]) / (b["seconds"] - a["seconds"])
        log_s = 10e3 / mb_per_s
        fixed_imp = a["import_s"] - per_s_imp * a["seconds"]
        fixed_base = a["rosbags_s"] - per_s_base * a["seconds"]
        print(f"margin: rosbags {per_s_base:.3f} s, import {per_s_imp:.3f} s per log second "
              f"({mb_per_s:.1f} MB/s of log): ratio {per_s_base / per_s_imp:.2f}; fixed costs {fixed_base:.1f} s, "
              f"{fixed_imp:.1f} s; 10 GB = {log_s:.0f} s of log: rosbags {fixed_base + per_s_base * log_s:.0f} s, "
              f"import {fixed_imp + per_s_imp * log_s:.0f} s, ratio "
              f"{(fixed_base + per_s_base * log_s) / (fixed_imp + per_s_imp * log_s):.2f}")


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--rosbags-alone":
        rosbags_alone(sys.argv[2])
    else:
        main()
