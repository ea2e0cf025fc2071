"""Simulate an Octopus calibration session (Chai 2015, Table A1) and check it against the dataset
contract; print how far the commanded poses are from the real ones and how good the ground planes are.

Run:  python examples/simulate_and_validate.py [OUT_DIR]
The test suite imports ``main`` and asserts on what it returns.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
import yaml

from graphcal.commands.simulate import run as simulate_to_folder
from graphcal.geometry import invert_pose, pose_from_xyz_quat_wxyz, transform_plane
from graphcal.io.dataset import read_dataset, validate_dataset


def main(out_dir: str | Path | None = None, *, seed: int = 0, progress: bool = False) -> dict:
    """Simulate, validate, and compare the fitted ground planes with the truth.

    Returns a dict: ``stations``, ``plane_angle_err_deg`` and ``plane_dist_err_mm`` (mean and max
    over the stations of the fitted plane against the true ground seen from the true sensor pose).
    """
    out = Path(out_dir) if out_dir is not None else Path(tempfile.mkdtemp(prefix="graphcal-")) / "octopus-chai2015"
    print(simulate_to_folder(robot="octopus", program="chai2015", ground="level", out_dir=out, seed=seed,
                             overwrite=True, progress=progress).summary_text())
    print(validate_dataset(out).summary())
    ds = read_dataset(out)
    truth = yaml.safe_load((out / "truth.yaml").read_text())
    t = truth["sensors"]["depth"]["T_body_sensor"]
    T_body_sensor = pose_from_xyz_quat_wxyz(t["xyz"], t["quaternion_wxyz"])
    ang, dist = [], []
    planes = ds.planes
    for k in range(len(planes)):
        st = int(planes["station"][k])
        tb = truth["stations"][st]["T_world_body"]
        T_world_sensor = pose_from_xyz_quat_wxyz(tb["xyz"], tb["quaternion_wxyz"]) @ T_body_sensor
        # the ground z = 0 of the world, seen in the sensor frame
        n_true, d_true = transform_plane(invert_pose(T_world_sensor), [0.0, 0.0, 1.0], 0.0)
        if d_true < 0:
            n_true, d_true = -n_true, -d_true
        n_fit = np.array([planes["nx"][k], planes["ny"][k], planes["nz"][k]])
        ang.append(np.degrees(np.arccos(np.clip(n_fit @ n_true, -1, 1))))
        dist.append(1e3 * abs(planes["d"][k] - d_true))
    result = {
        "stations": len(ds.stations),
        "plane_angle_err_deg": (float(np.mean(ang)), float(np.max(ang))),
        "plane_dist_err_mm": (float(np.mean(dist)), float(np.max(dist))),
    }
    print(f"ground planes vs truth over {len(ang)} stations: angle mean {result['plane_angle_err_deg'][0]:.3f} deg "
          f"(max {result['plane_angle_err_deg'][1]:.3f}), distance mean {result['plane_dist_err_mm'][0]:.2f} mm "
          f"(max {result['plane_dist_err_mm'][1]:.2f})")
    return result


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else None, progress=True)
