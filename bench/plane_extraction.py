"""Benchmark: ground-plane extraction on a 300k-point simulated Kinect frame.

Frame: 50 % floor, 20 % wall, 30 % clutter (boxes standing on the floor, two leg-like cylinders),
as in shared/design/engineering-notes.md. The scene is ray cast once (Open3D, 1280x960 rays); each
frame draws 150k floor, 60k wall and 90k clutter hits and adds fresh Kinect noise along the rays
(sigma_z = 1.425e-3 z^2). Points are in the camera's optical frame (z forward, x right, y down).

Timed side by side in one process, round-robin over frames and repeats, medians:

* graphcal ``extract_planes`` (RANSAC on a 5000-point subsample + Chai's 2-sigma loop on all
  points near it), also with ``range_noise`` and with a 20000-point subsample;
* baseline A: one numpy PCA pass over all points (``graphcal.geometry.plane_from_points_pca``);
* baseline B: Open3D ``segment_plane(0.01, 3, 100)`` on the full frame.

Accuracy: angle between the fitted and the true floor normal (deg) and the error of d (mm).
Target: <= 25 ms per frame for graphcal's default on this machine (2 cores).

Usage: python bench/plane_extraction.py [--frames N] [--repeats R] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

TARGET_MS = 25.0
N_FLOOR, N_WALL, N_CLUTTER = 150_000, 60_000, 90_000
LABEL_WALL = 10


def camera_pose(height_m: float, pitch_deg: float) -> np.ndarray:
    """T_world_sensor: optical frame at ``height_m``, looking along world x, pitched down."""
    from graphcal.geometry import matrix_from_rpy, pose_matrix

    R_body_optical = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    return pose_matrix(matrix_from_rpy([0.0, np.radians(pitch_deg), 0.0]) @ R_body_optical, [0, 0, height_m])


def build_scene_hits(seed: int = 0):
    """Ray cast the scene once: (true points (M, 3) in the sensor frame, labels (M,), T_world_sensor)."""
    from graphcal.models.sensors import DepthCamera
    from graphcal.simulation.sensors import capture
    from graphcal.simulation.terrain import LABEL_OBSTACLE, LABEL_ROBOT, box_mesh, cylinder_mesh, make_terrain

    T = camera_pose(0.6, 20.0)
    meshes = list(make_terrain("level").meshes)
    meshes.append(box_mesh([3.0, 0.0, 1.0], [0.2, 8.0, 2.0], LABEL_WALL))  # wall 3 m ahead
    for center, size in (((1.6, 0.5, 0.2), (0.4, 0.4, 0.4)), ((2.0, -0.5, 0.25), (0.5, 0.4, 0.5)),
                         ((2.4, 0.1, 0.15), (0.3, 0.6, 0.3))):
        meshes.append(box_mesh(center, size, LABEL_OBSTACLE))
    for y in (-0.3, 0.3):
        meshes.append(cylinder_mesh([1.0, y, 0.0], [0.9, y, 0.5], 0.04, LABEL_ROBOT))
    cam = DepthCamera(width_px=1280, height_px=960)
    scan = capture(cam, meshes, T, np.random.default_rng(seed))
    return scan.true_points_sensor, scan.labels, T, cam


def make_frame(true_pts, labels, cam, rng) -> np.ndarray:
    """300k points: 50 % floor, 20 % wall, 30 % clutter, fresh depth noise along the rays."""
    from graphcal.simulation.terrain import LABEL_GROUND

    pick = lambda mask, k: rng.choice(np.flatnonzero(mask), k, replace=False)  # noqa: E731
    idx = np.concatenate([pick(labels == LABEL_GROUND, N_FLOOR), pick(labels == LABEL_WALL, N_WALL),
                          pick((labels != LABEL_GROUND) & (labels != LABEL_WALL), N_CLUTTER)])
    rng.shuffle(idx)
    X = true_pts[idx]
    z = X[:, 2]
    z_meas = z + rng.normal(size=z.shape) * cam.sigma_along_axis(z)
    return np.ascontiguousarray(X * (z_meas / z)[:, None])


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=5, help="distinct noisy frames (default 5)")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs of each method per frame (default 3)")
    ap.add_argument("--json", type=Path, default=None, help="write the results to this JSON file")
    args = ap.parse_args(argv)

    import open3d as o3d

    from graphcal.clouds.planes import extract_planes, kinect_distance_sigma
    from graphcal.geometry import canonical_plane, invert_pose, plane_from_points_pca, transform_plane

    true_pts, labels, T, cam = build_scene_hits()
    n_true, d_true = canonical_plane(*transform_plane(invert_pose(T), [0.0, 0.0, 1.0], 0.0))
    rng = np.random.default_rng(1)
    frames = [make_frame(true_pts, labels, cam, rng) for _ in range(args.frames)]

    def graphcal_default(P, k):
        f = extract_planes(P, rng=k)[0]
        return f.n, f.d, f.n_points

    def graphcal_weighted(P, k):
        f = extract_planes(P, rng=k, range_noise=kinect_distance_sigma)[0]
        return f.n, f.d, f.n_points

    def graphcal_sub20k(P, k):
        f = extract_planes(P, rng=k, subsample=20000)[0]
        return f.n, f.d, f.n_points

    def numpy_pca(P, k):
        n, d, _ = plane_from_points_pca(P)
        return n, d, len(P)

    def open3d_full(P, k):
        o3d.utility.random.seed(k)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
        model, inliers = pcd.segment_plane(0.01, 3, 100)
        n, d = canonical_plane(np.asarray(model[:3]), float(model[3]))
        return n, d, len(inliers)

    methods = {
        "graphcal extract_planes (default, subsample 5000)": graphcal_default,
        "graphcal extract_planes, range_noise=kinect": graphcal_weighted,
        "graphcal extract_planes, subsample 20000": graphcal_sub20k,
        "A: numpy PCA, one pass over all points": numpy_pca,
        "B: Open3D segment_plane(0.01, 3, 100), full frame": open3d_full,
    }
    for fn in methods.values():  # warm up (imports, first calls)
        fn(frames[0], 0)
    times = {m: [] for m in methods}
    errs = {m: [] for m in methods}
    for i, P in enumerate(frames):
        for r in range(args.repeats):
            for name, fn in methods.items():  # round-robin: load changes hit all methods alike
                t0 = time.perf_counter()
                n, d, n_in = fn(P, 1000 * i + r)
                times[name].append(time.perf_counter() - t0)
                if r == 0:
                    ang = float(np.degrees(np.arccos(np.clip(abs(n @ n_true), -1.0, 1.0))))
                    errs[name].append((ang, abs(d - d_true) * 1e3, n_in))

    ref = float(np.median(times["graphcal extract_planes (default, subsample 5000)"])) * 1e3
    rows = []
    for name in methods:
        t = np.array(times[name]) * 1e3
        e = np.array(errs[name])
        rows.append({
            "method": name,
            "median_ms": float(np.median(t)),
            "min_ms": float(np.min(t)),
            "ratio_to_graphcal": float(np.median(t)) / ref,
            "angle_err_deg_median": float(np.median(e[:, 0])),
            "angle_err_deg_max": float(np.max(e[:, 0])),
            "d_err_mm_median": float(np.median(e[:, 1])),
            "d_err_mm_max": float(np.max(e[:, 1])),
            "points_used": int(np.median(e[:, 2])),
        })
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    result = {
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": {"cores": os.cpu_count(), "load_avg_1_5_15": list(load), "python": platform.python_version(),
                    "numpy": np.__version__, "open3d": o3d.__version__},
        "frame": {"points": N_FLOOR + N_WALL + N_CLUTTER, "floor": N_FLOOR, "wall": N_WALL, "clutter": N_CLUTTER,
                  "frames": args.frames, "repeats": args.repeats},
        "target_ms": TARGET_MS,
        "target_met": ref <= TARGET_MS,
        "rows": rows,
    }

    print(f"Plane extraction, {N_FLOOR + N_WALL + N_CLUTTER} points per frame (50 % floor, 20 % wall, "
          f"30 % clutter), {args.frames} frames x {args.repeats} repeats; {os.cpu_count()} cores, "
          f"load average {load[0]:.2f}")
    head = f"{'method':52s} {'median ms':>10s} {'min ms':>8s} {'x graphcal':>10s} {'angle deg':>10s} {'|dd| mm':>8s}"
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['method']:52s} {r['median_ms']:10.1f} {r['min_ms']:8.1f} {r['ratio_to_graphcal']:10.2f} "
              f"{r['angle_err_deg_median']:10.4f} {r['d_err_mm_median']:8.3f}")
    print(f"target: <= {TARGET_MS:.0f} ms per frame for graphcal's default: "
          f"{'MET' if result['target_met'] else 'NOT MET'} ({ref:.1f} ms median)")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")
        print(f"wrote {args.json}")
    return result


if __name__ == "__main__":
    main()
