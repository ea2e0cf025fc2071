"""Accuracy and consistency of a tracking run: trajectory errors through evo, NEES, NIS and the
whiteness of the innovations.

* Trajectory errors (evo 1.x: ``evo.core.trajectory``, ``evo.core.sync``, ``evo.core.metrics``):
  the estimate is associated with the truth by nearest time (within ``max_diff_s``), **without
  alignment** (the filter's world frame is defined like the simulator's: origin on the ground under
  the start pose, x along the initial heading; see :mod:`graphcal.locomotion.estimator`).
  ``ape_rmse_m``: RMS of the absolute position error; ``rpe_rmse_m``: RMS of the relative
  translation error over ``rpe_delta_m`` (1 m) of travelled distance; ``drift_percent``: final
  position error / path length of the truth x 100; ``distance_m``: path length of the truth.
* NEES of the pose (position world, orientation body: 6 dof, the order of ``TrackResult.cov_pose``)
  against the truth at the samples where the filter kept its covariance: ``e^T P^-1 e``; a
  consistent filter has mean 6 and each sample inside the chi-square(6) 95 % band [1.24, 14.45]
  95 % of the time.
* NIS of every update (stance kinematics: 3 x stance feet dof; ICP: the directions fused).
* Whiteness: autocorrelation of each whitened innovation component (lags 1..``lags``): the
  fraction inside the 95 % band +-1.96/sqrt(n) of white noise, and the Ljung-Box statistic.

Truth: ``truth.yaml`` beside the dataset (written by the simulator; only evaluations read it)
naming a trajectory CSV (time, x, y, z, qw, qx, qy, qz of T_world_body).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from graphcal.errors import DatasetError
from graphcal.geometry import so3_log_batch

__all__ = ["Truth", "load_truth", "trajectory_metrics", "interp_truth", "pose_errors", "nees_against_truth",
           "whiteness", "chi2_band", "evo_trajectory"]


@dataclass(frozen=True, eq=False)
class Truth:
    """The true body trajectory: ``times`` (N,) s, ``T_world_body`` (N, 4, 4); ``doc`` the
    truth.yaml content."""

    times: np.ndarray
    T_world_body: np.ndarray
    doc: dict


def load_truth(dataset_root: str | Path) -> Truth | None:
    """The truth trajectory of a simulated dataset, or None when the folder has no truth.yaml or it
    names no trajectory. DatasetError when the files are there but malformed."""
    import yaml

    root = Path(dataset_root)
    path = root / "truth.yaml"
    if not path.is_file():
        return None
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise DatasetError(path, "file", "readable YAML", str(exc).splitlines()[0]) from None
    if not isinstance(doc, dict) or not isinstance(doc.get("trajectory"), dict):
        return None
    rel = doc["trajectory"].get("file")
    if not isinstance(rel, str) or not rel:
        raise DatasetError(path, "trajectory.file", "the relative path of the truth trajectory CSV", rel)
    csv = root / rel
    try:
        with open(csv, encoding="utf-8") as fh:
            header = fh.readline().strip().split(",")
            data = np.loadtxt(fh, delimiter=",", ndmin=2)
    except (OSError, ValueError) as exc:
        raise DatasetError(csv, "file", "a CSV of numbers with a header line", str(exc).splitlines()[0]) from None
    need = ("time", "x", "y", "z", "qw", "qx", "qy", "qz")
    for c in need:
        if c not in header:
            raise DatasetError(csv, f"header, column {c}", f"the columns {', '.join(need)}", "missing")
    if data.shape[1] != len(header) or len(data) < 2:
        raise DatasetError(csv, "rows", f"at least two rows of {len(header)} numbers", data.shape)
    col = {c: data[:, header.index(c)] for c in need}
    from scipy.spatial.transform import Rotation

    q = np.column_stack([col["qx"], col["qy"], col["qz"], col["qw"]])
    from graphcal.io.dataset import UNIT_NORM_TOL

    norm = np.linalg.norm(q, axis=1)
    bad = ~(np.abs(norm - 1.0) <= UNIT_NORM_TOL)  # the contract's tolerance for body_q* (NaN fails too)
    if bad.any():
        i = int(np.argmax(bad))
        raise DatasetError(csv, f"row {i + 1}, columns qw..qz", f"a unit quaternion (norm within {UNIT_NORM_TOL:g} of 1)",
                           f"norm {norm[i]:.6g}")
    if np.any(np.diff(col["time"]) <= 0):
        i = int(np.argmax(np.diff(col["time"]) <= 0)) + 1
        raise DatasetError(csv, f"row {i + 1}, column time", "strictly increasing times", float(col["time"][i]))
    T = np.zeros((len(data), 4, 4))
    T[:, :3, :3] = Rotation.from_quat(q).as_matrix()
    T[:, :3, 3] = np.column_stack([col["x"], col["y"], col["z"]])
    T[:, 3, 3] = 1.0
    return Truth(col["time"], T, doc)


def evo_trajectory(times: np.ndarray, T_world_body: np.ndarray):
    """An ``evo.core.trajectory.PoseTrajectory3D`` of (N,) times and (N, 4, 4) poses."""
    from evo.core.trajectory import PoseTrajectory3D
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(T_world_body[:, :3, :3]).as_quat()
    return PoseTrajectory3D(positions_xyz=T_world_body[:, :3, 3].copy(),
                            orientations_quat_wxyz=np.column_stack([q[:, 3], q[:, :3]]),
                            timestamps=np.asarray(times, dtype=float).copy())


def trajectory_metrics(times, T_est, truth: Truth, *, max_diff_s: float = 0.002, rpe_delta_m: float = 1.0) -> dict:
    """APE, RPE, drift and distance (see the module docstring), with evo. Returns a dict of floats
    (``ape_rmse_m``, ``ape_max_m``, ``rpe_rmse_m``, ``drift_percent``, ``final_error_m``,
    ``distance_m``, ``yaw_error_final_deg``, ``n_matched``) and the per-pose errors under ``_series``."""
    import copy

    from evo.core import metrics, sync

    ref = evo_trajectory(truth.times, truth.T_world_body)
    est = evo_trajectory(times, T_est)
    try:
        ref, est = sync.associate_trajectories(ref, est, max_diff=max_diff_s)
    except sync.SyncException:
        ref = None
    if ref is None or ref.num_poses < 2:
        raise DatasetError("truth.yaml", "trajectory.file, column time",
                           f"truth samples within {max_diff_s * 1e3:g} ms of the estimate's times (the timeseries' clock)",
                           f"truth {float(truth.times[0]):.6g}..{float(truth.times[-1]):.6g} s, estimate "
                           f"{float(times[0]):.6g}..{float(times[-1]):.6g} s")
    data = (ref, est)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data(data)
    out = {
        "ape_rmse_m": float(ape.get_statistic(metrics.StatisticsType.rmse)),
        "ape_max_m": float(ape.get_statistic(metrics.StatisticsType.max)),
    }
    distance = float(ref.path_length)
    rpe_rmse = None
    if distance > 1.5 * rpe_delta_m:
        rpe = metrics.RPE(metrics.PoseRelation.translation_part, delta=rpe_delta_m, delta_unit=metrics.Unit.meters,
                          all_pairs=False)
        try:
            rpe.process_data((copy.deepcopy(ref), copy.deepcopy(est)))
            rpe_rmse = float(rpe.get_statistic(metrics.StatisticsType.rmse))
        except Exception:  # evo raises its own errors when no pair is at that distance
            rpe_rmse = None
    final = float(np.linalg.norm(est.positions_xyz[-1] - ref.positions_xyz[-1]))
    Rf = ref.poses_se3[-1][:3, :3].T @ est.poses_se3[-1][:3, :3]
    out.update({
        "rpe_rmse_m": rpe_rmse,
        "rpe_delta_m": rpe_delta_m,
        "final_error_m": final,
        "distance_m": distance,
        "drift_percent": 100.0 * final / distance if distance > 0 else None,
        "yaw_error_final_deg": float(np.degrees(np.arctan2(Rf[1, 0], Rf[0, 0]))),
        "n_matched": int(ref.num_poses),
        "_series": {"times": np.asarray(est.timestamps), "ape_m": np.asarray(ape.error)},
    })
    return out


def interp_truth(truth: Truth, t: np.ndarray) -> np.ndarray:
    """(M, 4, 4) true T_world_body at times ``t`` (M,) s: position linear, rotation slerped between
    the truth's samples; times outside the truth's span are clamped to its ends."""
    from scipy.spatial.transform import Rotation, Slerp

    t = np.clip(t, truth.times[0], truth.times[-1])
    T = np.zeros((len(t), 4, 4))
    for k in range(3):
        T[:, k, 3] = np.interp(t, truth.times, truth.T_world_body[:, k, 3])
    T[:, :3, :3] = Slerp(truth.times, Rotation.from_matrix(truth.T_world_body[:, :3, :3]))(t).as_matrix()
    T[:, 3, 3] = 1.0
    return T


def pose_errors(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """(N, 6) errors of the poses T_est (N, 4, 4) against T_true (N, 4, 4) in the filter's
    error-state order (that of ``TrackResult.cov_pose``, not docs/conventions.md's ``[omega, v]``):
    [p_true - p_est (world frame, m), Log(R_est^T R_true) (body frame, rad)]."""
    e = np.empty((len(T_est), 6))
    e[:, :3] = T_true[:, :3, 3] - T_est[:, :3, 3]
    dR = np.swapaxes(T_est[:, :3, :3], 1, 2) @ T_true[:, :3, :3]
    e[:, 3:] = so3_log_batch(dR)
    return e


def nees_against_truth(result, truth: Truth) -> tuple[np.ndarray, np.ndarray]:
    """(times (M,), NEES (M,)) of the pose (6 dof) at the samples where the filter kept its
    covariance (``result.cov_index``), truth interpolated at those times: ``e^T P^-1 e`` with ``e``
    from :func:`pose_errors` and ``P = result.cov_pose``, both in the filter's order [dp world,
    dtheta body] (the NEES is the same in the ``[omega, v]`` order: ``xi = J e``, ``P_xi = J P J^T``)."""
    idx = result.cov_index
    t = result.times[idx]
    inside = (t >= truth.times[0]) & (t <= truth.times[-1])
    idx, t = idx[inside], t[inside]
    e = pose_errors(result.T_world_body[idx], interp_truth(truth, t))
    P = result.cov_pose[inside]
    nees = np.einsum("ni,ni->n", e, np.linalg.solve(P, e[:, :, None])[:, :, 0])
    return t, nees


def chi2_band(dof: float, n: int = 1, prob: float = 0.95) -> tuple[float, float]:
    """Two-sided ``prob`` band of the mean of ``n`` independent chi-square(dof) samples."""
    from scipy.stats import chi2

    a = (1.0 - prob) / 2.0
    return float(chi2.ppf(a, dof * n) / n), float(chi2.ppf(1.0 - a, dof * n) / n)


def whiteness(innovations: np.ndarray, *, lags: int = 20) -> dict:
    """Whiteness of a whitened innovation sequence (K, m) (rows with NaN are left out; when every
    row has some, each component's finite entries are taken in order): per component autocorrelations at lags
    1..``lags``; ``fraction_inside`` of them within +-1.96/sqrt(K) (white noise: ~0.95),
    ``max_abs_autocorr``, and the Ljung-Box statistic Q per component with its 95 % chi-square(lags)
    threshold and the smallest p-value."""
    from scipy.stats import chi2

    W = np.asarray(innovations, dtype=float)
    if W.ndim == 2 and W.size and not np.all(np.isfinite(W), axis=1).any():
        # every update left some slots unmeasured (feet in swing, NaN): each component's own updates
        cols = [W[np.isfinite(W[:, j]), j] for j in range(W.shape[1])]
        K = min(len(c) for c in cols)
        W = np.column_stack([c[:K] for c in cols]) if K else np.zeros((0, W.shape[1]))
    W = W[np.all(np.isfinite(W), axis=1)]
    K, m = W.shape
    if K <= lags + 1:
        return {"n": int(K), "lags": lags, "fraction_inside": None, "max_abs_autocorr": None,
                "ljung_box_q": None, "ljung_box_threshold": None, "ljung_box_p_min": None}
    X = W - W.mean(axis=0)
    var = (X * X).sum(axis=0)
    rho = np.empty((lags, m))
    for k in range(1, lags + 1):
        rho[k - 1] = (X[k:] * X[:-k]).sum(axis=0) / var
    bound = 1.96 / np.sqrt(K)
    q = K * (K + 2) * ((rho**2) / (K - np.arange(1, lags + 1))[:, None]).sum(axis=0)
    return {
        "n": int(K),
        "lags": int(lags),
        "bound": float(bound),
        "fraction_inside": float(np.mean(np.abs(rho) <= bound)),
        "max_abs_autocorr": float(np.abs(rho).max()),
        "ljung_box_q": [float(v) for v in q],
        "ljung_box_threshold": float(chi2.ppf(0.95, lags)),
        "ljung_box_p_min": float(chi2.sf(q, lags).min()),
        "autocorr": rho,
    }
