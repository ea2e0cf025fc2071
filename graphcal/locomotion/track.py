"""Run the legged EKF over a dataset (:func:`track`) and the pieces of its outputs that are
estimation, not file writing: the TUM trajectory text (:func:`tum_text`) and the choice of the
keyframe clouds for the stairs model (:func:`stairs_keyframes`, :func:`ascending_flight`), and the
noise the filter uses (:func:`track_run`: the user's values, learned ones, defaults). The
``graphcal track`` command (outputs, metrics, report) is :mod:`graphcal.commands.track`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

__all__ = ["track", "tum_text", "stairs_keyframes", "ascending_flight", "TrackRun", "track_run", "learned_noise"]


def tum_text(times: np.ndarray, T_world_body: np.ndarray) -> str:
    """TUM trajectory text: one line ``t x y z qx qy qz qw`` per pose (s, m, unit quaternion)."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(T_world_body[:, :3, :3]).as_quat()  # x, y, z, w
    q[q[:, 3] < 0] *= -1.0
    A = np.column_stack([times, T_world_body[:, :3, 3], q])
    lines = ["# graphcal track: T_world_body, TUM format: t x y z qx qy qz qw (s, m)"]
    lines += [" ".join(f"{v:.9f}" if i == 0 else f"{v:.9g}" for i, v in enumerate(row)) for row in A]
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- stairs hook
def stairs_keyframes(
    clouds_sensor,
    T_world_sensor: list,
    *,
    max_depth_m: float = 2.5,
    min_rise_m: float = 0.05,
    min_slope_corr: float = 0.3,
    min_move_m: float = 0.02,
    min_turn_rad: float = float(np.radians(1.0)),
    max_clouds: int = 20,
) -> tuple[list[int], list[dict | None]]:
    """The clouds for :func:`graphcal.locomotion.stairs.model_stairs`: the views of a flight rising ahead.
    ``clouds_sensor``: an iterable of (N_k, 3) sensor-frame clouds (m; a generator is fine);
    ``T_world_sensor``: the list of their estimated 4x4 poses.

    A cloud (points within ``max_depth_m`` along the optical axis, put in the world with its
    estimated pose) is a view of a rising flight when the heights of its points span at least
    ``min_rise_m`` (5-95 % quantiles: a step, not a floor's noise) and grow with the horizontal
    distance along the viewing direction (correlation >= ``min_slope_corr``). That keeps the
    approach and the climb (the floor, the steps and the landing in view) and leaves out the views of
    one level (the landing alone, the floor) -- they add nothing to the heights and slide along
    their plane in the ICP -- and those of a flight going down (its risers face away; its treads
    are coplanar with the ascending flight's, seen with other pose errors). Of those, a cloud is
    dropped when the sensor moved less than ``min_move_m`` and turned less than ``min_turn_rad``
    since the last kept one (standing still), and at most ``max_clouds`` are kept, evenly spread.

    Returns:
        (indices into the inputs, per input cloud ``{"rise_m", "slope_corr"}`` or None when it has
        fewer than 100 points in range).
    """
    stats: list[dict | None] = []
    cand: list[int] = []
    for k, (c, T) in enumerate(zip(clouds_sensor, T_world_sensor)):
        c = np.asarray(c, dtype=float)
        c = c[np.all(np.isfinite(c), axis=1)]
        c = c[(c[:, 2] > 0) & (c[:, 2] <= max_depth_m)]
        fwd = np.array([T[0, 2], T[1, 2]])  # the optical axis, horizontal part
        if len(c) < 100 or np.linalg.norm(fwd) < 1e-6:
            stats.append(None)
            continue
        P = c @ T[:3, :3].T + T[:3, 3]
        s = (P[:, :2] - T[:2, 3]) @ (fwd / np.linalg.norm(fwd))
        h = P[:, 2]
        lo, hi = np.quantile(h, [0.05, 0.95])
        corr = float(np.corrcoef(s, h)[0, 1]) if hi - lo > 1e-9 and np.ptp(s) > 1e-9 else 0.0
        stats.append({"rise_m": float(hi - lo), "slope_corr": corr})
        if hi - lo >= min_rise_m and corr >= min_slope_corr:
            cand.append(k)
    kept: list[int] = []
    for k in cand:
        if kept:
            A, B = T_world_sensor[kept[-1]], T_world_sensor[k]
            turn = np.arccos(np.clip((np.trace(A[:3, :3].T @ B[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))
            if np.linalg.norm(B[:3, 3] - A[:3, 3]) < min_move_m and turn < min_turn_rad:
                continue
        kept.append(k)
    if len(kept) > max_clouds:
        kept = [kept[i] for i in np.unique(np.round(np.linspace(0, len(kept) - 1, max_clouds)).astype(np.int64))]
    return kept, stats


def ascending_flight(steps) -> tuple[list, list]:
    """The true steps (records with ``x_start_m``, ``height_m``, ...) split into the first flight
    going up -- the leading run of rising heights along x, its last step the landing -- and the
    rest (the flight down of the ``tripod-stairs`` walk)."""
    steps = sorted(steps, key=lambda s: s.x_start_m)
    n = 0
    while n < len(steps) and (n == 0 or steps[n].height_m > steps[n - 1].height_m):
        n += 1
    return steps[:n], steps[n:]


def track(dataset, *, config=None, progress: bool = False):
    """Read a dataset and run the filter: returns (dataset, inputs, TrackResult)."""
    from graphcal.io.dataset import read_dataset
    from graphcal.locomotion.estimator import TrackerConfig, run_filter
    from graphcal.locomotion.track_inputs import inputs_from_dataset

    ds = read_dataset(dataset)
    inp = inputs_from_dataset(ds)
    return ds, inp, run_filter(inp, config or TrackerConfig(), progress=progress)


@dataclass(frozen=True, eq=False)
class TrackRun:
    """One tracking run: the dataset read, the filter's inputs and result, the noise used
    (:class:`~graphcal.locomotion.noise_settings.NoiseSettings`) and how it was learned (a plain dict)."""

    dataset: object
    inputs: object
    result: object
    noise: object
    learning: dict


def _still_part(inp, settings):
    """The still windows' IMU and encoder noise learned into ``settings``; (settings, learning dict)."""
    from graphcal.locomotion.noise_learning import still_noise

    q = np.column_stack([inp.q[j] for j in inp.q]) if inp.q else np.zeros((len(inp.times), 0))
    sn = still_noise(inp.times, q, inp.gyro, inp.accel)
    if sn is None:
        return settings, {"found": False, "note": "no still windows of 0.5 s in all (every joint and IMU channel "
                                                  "white over 0.25 s): the IMU and encoder noise are not learned"}
    spans = ", ".join(f"{a:.2f}-{b:.2f} s" for a, b in sn.windows[:4]) + (", ..." if len(sn.windows) > 4 else "")
    where = f"learned: still windows ({sn.duration_s:.1f} s: {spans})"
    vals = {"gyro_noise_density": sn.gyro_noise_density, "accel_noise_density": sn.accel_noise_density,
            "encoder_sigma_rad": sn.encoder_sigma_rad}
    doc = {"found": True, "duration_s": sn.duration_s, "windows_s": [list(w) for w in sn.windows],
           "sample_interval_s": sn.dt_s, "gyro_sigma_rad_s": sn.gyro_sigma, "accel_sigma_m_s2": sn.accel_sigma,
           "encoder_sigma_rad": sn.encoder_sigma_rad}
    return settings.with_learned(vals, dict.fromkeys(vals, where)), doc


def learned_noise(inp, cfg, settings, *, learn: bool = True):
    """The noise the filter runs with: ``settings`` (the user's and the defaults) with, when ``learn``,
    what the log tells learned into the values the user did not give -- the IMU and encoder noise from
    its still windows, the kinematic noise (or a default encoder noise) from the stance innovations.
    Returns (settings, learning dict, (noise, result) of the last matching pass or None)."""
    from graphcal.locomotion.estimator import run_filter
    from graphcal.locomotion.noise_learning import match_measurement_noise

    if not learn:
        return settings, {"enabled": False}, None
    settings, still = _still_part(inp, settings)
    # what the innovations may set: what no user gave and the still windows did not measure
    free = frozenset(("kinematic_sigma_m", "foot_rw", "encoder_sigma_rad", "floor_sigma_m")) - settings.given()
    learning: dict = {"enabled": True, "still": still}
    if not free:
        return settings, learning, None
    match_cfg = replace(cfg, icp=False)
    m = match_measurement_noise(lambda nz: run_filter(inp, replace(match_cfg, noise=nz)), settings.noise, free=free)
    where = (f"learned: stance innovations (covariance matching, {len(m.passes)} pass"
             f"{'es' if len(m.passes) > 1 else ''}, NIS per dof {m.passes[-1]['stance_nis_per_dof']:.3g})")
    vals = {k: getattr(m.noise, k) for k in free if getattr(m.noise, k) != getattr(settings.noise, k)}
    learning["matching"] = {"passes": list(m.passes), "converged": m.converged, "note": m.note,
                            "icp": "off in the matching passes (the stance updates' NIS is matched)"}
    return settings.with_learned(vals, dict.fromkeys(vals, where)), learning, (m.noise, m.result)


def track_run(dataset, *, config=None, progress: bool = False, noise_file: Path | None = None,
              noise: dict | None = None, learn_noise: bool = True) -> TrackRun:
    """Read a dataset, settle the noise and run the filter (:class:`TrackRun`).

    The noise: the real-robot defaults, dataset.yaml's ``tracker: noise:`` over them, ``noise_file``'s
    (noise.yaml's format) over those, ``noise`` (name -> SI value) over all; then, with
    ``learn_noise``, the values none of them gave learned from the log (:func:`learned_noise`).
    ``config``'s other settings are used; its ``noise`` is replaced by these."""
    from graphcal.io.dataset import read_dataset
    from graphcal.locomotion.estimator import TrackerConfig, run_filter
    from graphcal.locomotion.noise_settings import noise_values_from_dataset, noise_values_from_file, settings_from
    from graphcal.locomotion.track_inputs import inputs_from_dataset

    given = noise_values_from_file(noise_file) if noise_file is not None else {}
    ds = read_dataset(dataset)
    settings = settings_from(noise_values_from_dataset(ds), given, file_name=f"--noise {noise_file}")
    if noise:
        from graphcal.locomotion.noise_settings import NoiseSettings

        settings = NoiseSettings(replace(settings.noise, **noise), {**settings.sources, **dict.fromkeys(noise, "caller")})
    inp = inputs_from_dataset(ds)
    cfg = replace(config or TrackerConfig(), level_ground=str(ds.ground.get("type", "")) == "level")
    settings, learning, last = learned_noise(inp, cfg, settings, learn=learn_noise)
    cfg = replace(cfg, noise=settings.noise)
    # the last matching pass is the result when it ran with these values and ICP has nothing to add
    reuse = last is not None and last[0] == settings.noise and not (cfg.icp and inp.clouds)
    res = last[1] if reuse else run_filter(inp, cfg, progress=progress)
    return TrackRun(ds, inp, res, settings, learning)
