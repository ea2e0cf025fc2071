"""Łabęcki & Belter 2012 on a simulated Messor: a Hokuyo-like laser scanner and a stereo camera
calibrated together, on a floor with box obstacles, from Łabęcki's tilt sequence (Fig. 3).

Side by side with the paper:
* Tables 1-2: the calibration error epsilon (RMS height of the ground points in the map frame, mm)
  with the CAD extrinsic and after calibration (paper: laser 8.566 -> 7.441 mm, stereo 4.145 ->
  2.085 mm with LM);
* Eq. 9: the mean absolute difference between the elevation maps built from the laser and from the
  stereo camera over the cells both see (paper: 0.041 m with CAD, 0.014 m after);
* Tables 3-4: the spread of the result over 50 random starting points at three levels of starting
  error (paper's LM: ~1e-5 m at sigma_d = 0.01 / 0.1 m, but 0.16-0.55 m and 35-135 deg at
  sigma_d = 0.2 m, sigma_a = 50 deg, where it fell into local minima).

Run:  python examples/labecki2012_reproduction.py [--starts 50]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

import numpy as np

from graphcal.calibration.calibrate import calibrate
from graphcal.geometry import pose_from_xyz_quat_wxyz, rotation_angle_between, se3_exp, transform_points
from graphcal.io.dataset import load_cloud, read_dataset
from graphcal.simulation.session import SimulationConfig, simulate
from graphcal.simulation.write import write_simulation

PAPER = {"epsilon_laser_mm": (8.566, 7.441), "epsilon_stereo_mm": (4.145, 2.085), "elevation_m": (0.041, 0.014)}
START_LEVELS = ((0.01, 5.0), (0.1, 10.0), (0.2, 50.0))  # (sigma_d m, sigma_a deg), the paper's Tables 3-4
CELL_M = 0.05


def _epsilon_mm(ds, sensor, T_body_sensor, T_world_body, labels_ground=None) -> float:
    """Łabęcki's epsilon: RMS height of the sensor's points in the world (map) frame, mm."""
    z = []
    for station, T_wb in T_world_body.items():
        P = load_cloud(ds, sensor, station)
        z.append(transform_points(T_wb @ T_body_sensor, P)[:, 2])
    z = np.concatenate(z)
    z = z[np.abs(z) < 0.05]  # the floor (Łabęcki's filter keeps only points on the flat floor)
    return float(1e3 * np.sqrt(np.mean(z**2)))


def _elevation_map(ds, sensor, T_body_sensor, T_world_body) -> dict:
    cells: dict = {}
    for station, T_wb in T_world_body.items():
        W = transform_points(T_wb @ T_body_sensor, load_cloud(ds, sensor, station))
        keys = np.floor(W[:, :2] / CELL_M).astype(int)
        for (i, j), z in zip(map(tuple, keys), W[:, 2]):
            if z > cells.get((i, j), -np.inf):
                cells[(i, j)] = z  # the highest point of the cell (the paper's elevation map)
    return cells


def _map_difference_m(a: dict, b: dict) -> tuple[float, int]:
    common = set(a) & set(b)
    if not common:
        return float("nan"), 0
    return float(np.mean([abs(a[c] - b[c]) for c in common])), len(common)


def main(starts: int = 50, seed: int = 2012, stride: int = 2) -> dict:
    """Returns ``epsilon_mm`` (sensor -> (CAD, calibrated)), ``error`` (vs the truth),
    ``elevation_m`` ("cad"/"calibrated" -> (mean |difference| m, cells)) and ``stability``
    ((sigma_d, sigma_a) -> sensor -> largest deviation from the reference result over the starts)."""
    res = simulate(SimulationConfig(robot="messor", program="labecki2012", ground="boxes", seed=seed,
                                    cloud_stride=stride, extrinsic_sigma_m=0.01, extrinsic_sigma_rad=np.radians(2.0)))
    folder = Path(tempfile.mkdtemp(prefix="graphcal-labecki-")) / "messor"
    write_simulation(res, folder, output="both")
    ds = read_dataset(folder)
    truth = {s: pose_from_xyz_quat_wxyz(res.truth["sensors"][s]["T_body_sensor"]["xyz"],
                                        res.truth["sensors"][s]["T_body_sensor"]["quaternion_wxyz"]) for s in ("laser", "stereo")}
    result = calibrate(ds)
    T_wb = result.T_world_body
    out = {"epsilon_mm": {}, "error": {}, "elevation_m": {}, "stability": {}}
    for s in ("laser", "stereo"):
        cad = ds.sensors[s].T_body_sensor_prior.matrix
        est = result.sensors[s].T_body_sensor
        out["epsilon_mm"][s] = (_epsilon_mm(ds, s, cad, T_wb), _epsilon_mm(ds, s, est, T_wb))
        def deg_mm(T, s=s):  # (rotation error deg, translation error mm) against the truth
            return (float(np.degrees(rotation_angle_between(T[:3, :3], truth[s][:3, :3]))),
                    float(1e3 * np.linalg.norm(T[:3, 3] - truth[s][:3, 3])))

        out["error"][s] = {"cad": deg_mm(cad), "calibrated": deg_mm(est)}
    for label, Ts in (("cad", {s: ds.sensors[s].T_body_sensor_prior.matrix for s in ("laser", "stereo")}),
                      ("calibrated", {s: result.sensors[s].T_body_sensor for s in ("laser", "stereo")})):
        m_l = _elevation_map(ds, "laser", Ts["laser"], T_wb)
        m_s = _elevation_map(ds, "stereo", Ts["stereo"], T_wb)
        out["elevation_m"][label] = _map_difference_m(m_l, m_s)
    rng = np.random.default_rng(seed)
    ref = {s: result.sensors[s].T_body_sensor for s in ("laser", "stereo")}
    for sd, sa in START_LEVELS:
        spread = {s: [] for s in ("laser", "stereo")}
        for _ in range(starts):
            sensors = {}
            for s, spec in ds.sensors.items():
                D = se3_exp(np.r_[rng.normal(0, np.radians(sa), 3), rng.normal(0, sd, 3)])
                prior = spec.T_body_sensor_prior.from_matrix(spec.T_body_sensor_prior.matrix @ D,
                                                             spec.T_body_sensor_prior.sigma_m, spec.T_body_sensor_prior.sigma_rad)
                sensors[s] = dataclasses.replace(spec, T_body_sensor_prior=prior)
            r = calibrate(dataclasses.replace(ds, sensors=sensors))
            for s in spread:
                T = r.sensors[s].T_body_sensor
                spread[s].append(np.r_[1e3 * (T[:3, 3] - ref[s][:3, 3]), np.degrees(rotation_angle_between(T[:3, :3], ref[s][:3, :3]))])
        out["stability"][(sd, sa)] = {s: {"max_dev_mm": float(np.abs(np.array(v)[:, :3]).max()),
                                          "max_dev_deg": float(np.array(v)[:, 3].max())} for s, v in spread.items()}
    return out


def _print(out: dict) -> None:
    for s in ("laser", "stereo"):
        b, a = out["epsilon_mm"][s]
        pb, pa = PAPER[f"epsilon_{s}_mm"]
        e = out["error"][s]
        print(f"{s:7s} epsilon CAD -> calibrated {b:6.3f} -> {a:6.3f} mm (paper {pb} -> {pa}); error vs truth: "
              f"CAD {e['cad'][0]:.2f} deg {e['cad'][1]:.1f} mm, calibrated {e['calibrated'][0]:.3f} deg {e['calibrated'][1]:.2f} mm")
    (b, nb), (a, na) = out["elevation_m"]["cad"], out["elevation_m"]["calibrated"]
    print(f"elevation maps, laser vs stereo (Eq. 9): CAD {b:.4f} m over {nb} cells -> calibrated {a:.4f} m over {na} cells "
          f"(paper {PAPER['elevation_m'][0]} -> {PAPER['elevation_m'][1]} m)")
    for (sd, sa), v in out["stability"].items():
        print(f"random starts sigma_d {sd} m, sigma_a {sa} deg: " + "; ".join(
            f"{s} max deviation {x['max_dev_mm']:.2e} mm {x['max_dev_deg']:.2e} deg" for s, x in v.items()))


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--starts", type=int, default=50)
    ap.add_argument("--stride", type=int, default=2)
    a = ap.parse_args()
    _print(main(a.starts, stride=a.stride))
