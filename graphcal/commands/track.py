"""``graphcal track DATASET --out DIR``: run the legged EKF over a dataset's timeseries and write

* ``trajectory.tum``  -- the estimate, TUM format ``t x y z qx qy qz qw`` (T_world_body), at
  ``tum_rate_hz`` (default 100 Hz; every sample with 0);
* ``metrics.json``    -- ``ape_rmse_m``, ``rpe_rmse_m``, ``drift_percent``, ``distance_m``,
  ``nees_mean`` (null when the dataset has no truth), NIS, whiteness, real-time factor, ...,
  and ``consistency``: the verdict of the NIS of each update kind over 10 s windows
  (:mod:`graphcal.locomotion.consistency`; a warning on the console when it is ``inconsistent``);
  ``plausibility``: whether the trajectory is physically possible (:mod:`graphcal.locomotion.plausibility`;
  a warning naming the first failure's time and size when it is not); ``contacts`` (per-foot
  thresholds, duty factors), ``phases`` (lying, standing up, walking, ...), ``floor`` (the
  level-floor updates) and ``noise`` (values and sources);
* ``trajectory.png``, ``errors.png``, ``nis.png``, ``contacts.png`` (the stance diagram) -- plots;
* ``report.html``     -- the report (:func:`graphcal.report.track_page.track_html`, the plots embedded);
* ``noise.yaml``      -- the noise the filter used, each value with where it came from (``--noise``,
  dataset.yaml's ``tracker: noise:``, learned from the log, or the real-robot default;
  :mod:`graphcal.locomotion.noise_settings`); give it back with ``--noise`` to use it as it is;
* ``stairs.json``     -- on a stairs dataset, the stairs model of :mod:`graphcal.locomotion.stairs` from the
  keyframe clouds (:func:`stairs_keyframes`) placed with the estimated poses, with per-tread errors
  against the truth's ascending flight (:func:`ascending_flight`) when there is a truth;
* ``scene.mcap``      -- the tracked robot for Foxglove and RViz 2 (:mod:`graphcal.report.track_mcap`).

The outputs are written as one atomic set (:func:`graphcal.io.atomic.atomic_directory`); an
existing ``DIR`` is replaced only if it is empty or holds a previous ``graphcal track`` output
(``metrics.json`` with ``format: graphcal-track/1`` and nothing else graphcal did not write).
Truth is read from ``truth.yaml`` beside the dataset (simulated data) by the evaluation only.
"""


from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from graphcal.errors import GraphcalError
from graphcal.io.atomic import atomic_directory, atomic_write_bytes, check_command_output
from graphcal.locomotion.noise_settings import noise_document
from graphcal.locomotion.track import ascending_flight, stairs_keyframes, track_run, tum_text
from graphcal.report.track_page import track_figures, track_html

__all__ = ["TRACK_FORMAT", "OUTPUT_FILES", "run", "TrackResult", "summary_lines", "consistency_section",
           "consistency_warning", "noise_line", "plausibility_warning", "bias_warning"]

log = logging.getLogger(__name__)

TRACK_FORMAT = "graphcal-track/1"
OUTPUT_FILES = ("trajectory.tum", "metrics.json", "trajectory.png", "errors.png", "nis.png", "contacts.png",
                "report.html", "stairs.json", "noise.yaml", "scene.mcap")
#: what a previous track output may hold (before 2026-11-27 the report was report.md)
_PREVIOUS_FILES = OUTPUT_FILES + ("report.md",)


def _check_out(out: Path, overwrite: bool) -> None:
    """The output-folder policy of graphcal.io.atomic.check_output_folder, for a track output."""
    check_command_output(out, "metrics.json", _PREVIOUS_FILES, TRACK_FORMAT, what="graphcal track output",
                         overwrite=overwrite)


def _stairs_model(ds, inp, result, truth, *, max_clouds: int = 20):
    """The stairs model (graphcal.locomotion.stairs) from the keyframe clouds (:func:`stairs_keyframes`)
    placed with the estimate, compared with the truth's ascending flight when there is a truth.
    Errors of the model become {"error": ...}."""
    from graphcal.locomotion import stairs as stairs_mod
    from graphcal.report.stairs_json import stairs_to_json

    if inp.T_body_sensor is None or not inp.clouds:
        return None
    idx_all = np.array(sorted(inp.clouds), dtype=np.int64)
    poses_all = [result.T_world_body[int(k)] @ inp.T_body_sensor for k in idx_all]
    # one cloud in memory at a time for the choice (a 30 Hz walk has hundreds); the chosen are re-read
    pick, _ = stairs_keyframes((inp.clouds[int(k)]() for k in idx_all), poses_all, max_clouds=max_clouds)
    method = "views of a rising flight"
    if len(pick) < 2:  # no such views: every cloud is a candidate
        method = "evenly spread (no view of a rising flight)"
        pick = sorted(set(np.round(np.linspace(0, len(idx_all) - 1, min(max_clouds, len(idx_all)))).astype(int).tolist()))
    idx = idx_all[pick]
    meta = {
        "n_clouds_used": int(len(idx)),
        "n_clouds_available": int(len(idx_all)),
        "keyframes": {"method": method, "samples": [int(k) for k in idx],
                      "times_s": [float(result.times[int(k)]) for k in idx]},
    }
    try:
        clouds = [np.asarray(inp.clouds[int(idx_all[i])](), dtype=float) for i in pick]
        model = stairs_mod.model_stairs(clouds, [poses_all[i] for i in pick])
        errors = None
        compared = None
        if truth is not None:
            from graphcal.simulation.terrain import Stair

            steps = [Stair(**s) for s in (truth.doc.get("ground", {}) or {}).get("stairs", []) or []]
            up, rest = ascending_flight(steps)
            if up:
                errors = stairs_mod.tread_errors(model, up)
                compared = {
                    "flight": "ascending",
                    "selection": "the true steps sorted by x, the leading run of rising heights; the last one "
                                 "is the landing",
                    "true_treads": [
                        {"true_index": j, "x_start_m": s.x_start_m, "height_m": s.height_m, "depth_m": s.depth_m,
                         "width_m": s.width_m, "landing": j == len(up) - 1}
                        for j, s in enumerate(up)
                    ],
                    "not_compared": [
                        {"x_start_m": s.x_start_m, "height_m": s.height_m, "depth_m": s.depth_m} for s in rest
                    ],
                    "note": "depth errors only for treads with depth_complete: the landing has no riser "
                            "behind it (it ends where the flight down begins, at the depth limit of the "
                            "views of the approach), so its depth is its visible extent; the flight down is "
                            "not modelled (its risers face away; the keyframes are views of the flight up)",
                }
        doc = dict(stairs_to_json(model, errors))
        if compared is not None:
            found = {e.true_index for e in errors if e.true_index >= 0}
            compared["all_true_treads_found"] = found == set(range(len(compared["true_treads"])))
            doc["truth_compared"] = compared
    except GraphcalError as exc:
        doc = {"error": str(exc)}
    doc.update(meta)
    return doc


def consistency_section(res, *, window_s: float = 10.0) -> dict:
    """metrics.json's ``consistency``: the verdict of :func:`graphcal.locomotion.consistency.consistency_verdict`
    on the stance and ICP updates of a :class:`~graphcal.locomotion.estimator.TrackResult` (10 s windows)."""
    from graphcal.locomotion.consistency import consistency_verdict

    dofs = res.stance_dofs if res.stance_dofs is not None else res.stance_dof
    return consistency_verdict({"stance": (res.stance_times, res.stance_nis, dofs),
                                "icp": (res.icp_times, res.icp_nis, res.icp_dof)}, window_s=window_s)


def consistency_warning(section: dict) -> str | None:
    """The console warning for an ``inconsistent`` verdict (None otherwise): which update kinds,
    their mean NIS per dof, windows outside and p-value, and what it means."""
    if section.get("verdict") != "inconsistent":
        return None
    parts = []
    for name in section["inconsistent_kinds"]:
        r = section["kinds"][name]
        parts.append(f"{name} mean NIS per dof {r['mean_nis_per_dof']:.3g} (1 expected), {r['statistic']} of "
                     f"{r['n_windows']} windows outside their 95 % interval, p = {r['p_value']:.2g}")
    return ("the filter's innovations are inconsistent with its covariance: " + "; ".join(parts)
            + ": the noise settings (encoder, IMU, ICP) or the model (kinematics, contacts) do not fit the data; "
              "the trajectory's sigma and NEES are not to be trusted")


def _footholds(inp, res) -> np.ndarray:
    """(K, 3) world foot points (m), one per stance of each foot (graphcal.report.scene_3d.stance_footholds)."""
    from graphcal.locomotion.gtsam_legged import foot_points_from_joints
    from graphcal.report.scene_3d import stance_footholds

    if res.stance_mask is None:
        return np.zeros((0, 3))
    return stance_footholds(res.T_world_body, res.stance_mask, foot_points_from_joints(inp))


def _scene(res, feet, stairs_doc, truth):
    """The report's 3-D scene: trajectory (and truth), stance footholds, perceived stairs."""
    from graphcal.locomotion.metrics import interp_truth
    from graphcal.report.scene_3d import track_scene

    true = interp_truth(truth, res.times) if truth is not None else None
    return track_scene(res.T_world_body, feet, stairs_doc=stairs_doc, T_world_body_true=true)


def _write_scene_mcap(path: Path, ds, inp, res, feet, stairs_doc) -> None:
    """scene.mcap (graphcal.report.track_mcap): poses, the dataset's URDF, clouds, footholds, stairs."""
    from graphcal.report.scene_3d import stairs_segments
    from graphcal.report.track_mcap import write_track_mcap

    names = [s for s in ds.timeseries.suffixes("cloud_") if s in ds.sensors] if ds.timeseries is not None else []
    stairs = stairs_segments(stairs_doc) if stairs_doc and stairs_doc.get("treads") else None
    write_track_mcap(path, times=res.times, T_world_body=res.T_world_body, base_frame=inp.robot.base_frame,
                     urdf_text=inp.robot.urdf_xml, T_body_imu=inp.T_body_imu, sensor=names[0] if names else None,
                     T_body_sensor=inp.T_body_sensor, clouds=inp.clouds, footholds=feet, stair_segments=stairs)


def _innovation_bias(inp, res) -> dict:
    """metrics.json's ``innovation_bias`` (:func:`graphcal.locomotion.consistency.innovation_bias`): per
    foot (slot) axis, the stance innovations' mean; a biased one points at the leg model."""
    from graphcal.locomotion.consistency import innovation_bias

    n_slots = res.stance_innovations.shape[1] // 3 if res.stance_innovations.ndim == 2 else 0
    names = list(inp.robot.feet) if not res.groups and n_slots == len(inp.robot.feet) else [
        f"tripod slot {i}" for i in range(n_slots)]
    return innovation_bias(res.stance_times, res.stance_innovations, names)


def bias_warning(section: dict) -> str | None:
    """The console warning for biased stance innovations (None otherwise)."""
    if section.get("verdict") != "biased":
        return None
    w = section["worst"]
    return (f"the stance innovations of {w['slot']} are biased along body {w['axis']} (mean {w['mean_sigma']:+.2f} "
            f"sigma, t = {w['t']:.1f} over {w['blocks']} s; {len(section['biased'])} foot axes in all): the leg "
            "model is off by a constant (joint zero offsets, link lengths): the trajectory drifts with it; identify "
            "the legs (graphcal identify-legs) or calibrate them")


def _plausibility(ds, inp, res) -> dict:
    """metrics.json's ``plausibility``: :func:`graphcal.locomotion.plausibility.track_plausibility` on
    the samples where the leg model was used (the log's phases), level checks on declared level ground."""
    from graphcal.locomotion.plausibility import plausibility_section, track_plausibility

    active = res.phases.leg_model_mask if res.phases is not None else None
    level = str(ds.ground.get("type", "")) == "level"
    return plausibility_section(track_plausibility(res, inp, level_ground=level, active=active))


def plausibility_warning(section: dict) -> str | None:
    """The console warning for an ``implausible`` trajectory (None otherwise): the first failure."""
    if section.get("verdict") != "implausible":
        return None
    f = section["failures"]
    more = f" (and {len(f) - 1} more failure{'s' if len(f) > 2 else ''}: metrics.json plausibility)" if len(f) > 1 else ""
    floor = ("; touchdowns off the floor: if the ground is not level, declare it (dataset.yaml ground: {type: "
             "stairs} or {type: uneven}), since on level ground the filter holds every touchdown at the floor's height"
             if any(x["kind"] == "touchdown" for x in f) else "")
    return (f"the trajectory is physically implausible: {f[0]['message']}{more}: the leg model, the contacts or the "
            f"noise settings do not fit this robot{floor}; the trajectory and its sigma are not to be trusted")


def _phases_section(ph) -> dict | None:
    """metrics.json's ``phases``: the segments (phase, start s, end s) and where the leg model was used."""
    if ph is None:
        return None
    return {"segments": [{"phase": s.phase, "start_s": s.start_s, "end_s": s.end_s} for s in ph.segments],
            "standing_height_m": ph.standing_height_m, "lying_height_m": ph.lying_height_m,
            "leg_model_fraction": float(np.mean(ph.leg_model_mask)),
            "note": "no leg model while lying (a zero-velocity update instead) or lifted"}


def _floor_section(res) -> dict:
    """metrics.json's ``floor``: the level-floor updates at touchdowns and the zero-velocity updates."""
    n = int(np.sum(res.floor_dofs))
    return {"updates": int(len(res.floor_nis)), "feet_measured": n,
            "nis_per_dof": float(np.sum(res.floor_nis)) / n if n else None,
            "zero_velocity_updates": int(res.n_zero_velocity)}


# ----------------------------------------------------------------------------- the command
def _clean(x):
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items() if not k.startswith("_")}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.ndarray):
        return _clean(x.tolist())
    return x


@dataclass(frozen=True)
class TrackResult:
    """What ``graphcal track`` did (the filter's own result,
    :class:`graphcal.locomotion.estimator.TrackResult`, is ``estimate``).

    Attributes:
        estimate: the filter's result (poses, NIS, innovations, timings).
        metrics: metrics.json's document (accuracy against the truth, NIS, consistency, ...).
        consistency: the consistency verdict's section (:func:`consistency_section`).
        stairs: stairs.json's document on a stairs dataset, else None.
        dataset: the dataset folder, as given.
        out: the output folder.
        files: the files written (trajectory.tum, metrics.json, plots, report.html, stairs.json).
        warnings: the inconsistency warning (:func:`consistency_warning`), if any.
        verdict: the filter's consistency (``consistent``, ``inconsistent``, ...).
    """

    estimate: object
    metrics: dict
    consistency: dict
    stairs: dict | None
    dataset: str
    out: Path
    files: tuple[Path, ...]
    warnings: tuple[str, ...]
    verdict: str | None

    def summary_text(self) -> str:
        return "\n".join(summary_lines(self.metrics, self.consistency, self.stairs, self.dataset, self.out))


def run(dataset: str | Path, out: str | Path, *, progress: bool = True, config=None,
        tum_rate_hz: float = 100.0, overwrite: bool = True, stairs: bool = True, noise_file: str | Path | None = None,
        noise: dict | None = None, learn_noise: bool = True) -> TrackResult:
    """The ``graphcal track`` command (see the module docstring). Returns a :class:`TrackResult`.

    Args:
        dataset: dataset folder with a timeseries (``truth.yaml`` beside it is read for the evaluation only).
        out: output folder (replaces only an empty folder or a previous track output).
        progress: progress bar (tqdm) of the filter.
        config: :class:`~graphcal.locomotion.estimator.TrackerConfig` (default: its defaults); its
            ``noise`` is replaced by the noise settled from the next three and the log.
        noise_file: a noise file (noise.yaml's format): its values are used as they are.
        noise: EkfNoise name -> value (SI), over the file's and dataset.yaml's.
        learn_noise: learn the values nobody gave from the log (the still windows, the stance
            innovations); False: the real-robot defaults for them.
        tum_rate_hz: poses per second in trajectory.tum (Hz; 0 = every filter sample).
        overwrite: replace a previous track output in ``out``.
        stairs: on a stairs dataset, also model the stairs (stairs.json).

    Raises:
        DatasetError: the dataset is malformed or lacks what the filter needs (file and field named).
        OutputExistsError: ``out`` is not empty and not a previous track output.
    """
    from graphcal.locomotion.metrics import chi2_band, load_truth, nees_against_truth, trajectory_metrics, whiteness

    out = Path(out)
    if not (np.isfinite(tum_rate_hz) and tum_rate_hz >= 0):
        raise GraphcalError(f"--tum-rate must be a finite number >= 0 (Hz; 0 = every sample), got {tum_rate_hz}")
    _check_out(out, overwrite)
    tr = track_run(dataset, config=config, progress=progress, noise_file=None if noise_file is None else Path(noise_file),
                   noise=noise, learn_noise=learn_noise)
    ds, inp, res = tr.dataset, tr.inputs, tr.result
    noise_doc = noise_document(tr.noise, tr.learning)
    truth = load_truth(ds.root) if ds.root is not None else None

    m: dict = {"format": TRACK_FORMAT, "dataset": str(dataset), "truth": truth is not None}
    nees_t = nees = None
    nees_dof = 6
    est_len = float(np.linalg.norm(np.diff(res.T_world_body[:, :3, 3], axis=0), axis=1).sum())
    if truth is not None:
        tm = trajectory_metrics(res.times, res.T_world_body, truth)
        tm.pop("_series")
        m.update(tm)
        m["distance_source"] = "truth"
        nees_t, nees = nees_against_truth(res, truth)
        lo, hi = chi2_band(nees_dof)
        m.update({
            "nees_mean": float(nees.mean()) if len(nees) else None,
            "nees_dof": nees_dof,
            "nees_band_95_single": [lo, hi],
            "nees_fraction_in_band": float(np.mean((nees >= lo) & (nees <= hi))) if len(nees) else None,
            "nees_fraction_above_band": float(np.mean(nees > hi)) if len(nees) else None,
        })
    else:
        m.update({"ape_rmse_m": None, "ape_max_m": None, "rpe_rmse_m": None, "drift_percent": None,
                  "final_error_m": None, "distance_m": est_len, "distance_source": "estimate",
                  "nees_mean": None, "nees_dof": nees_dof, "nees_band_95_single": None,
                  "nees_fraction_in_band": None, "nees_fraction_above_band": None})
    m["distance_estimated_m"] = est_len
    consistency = consistency_section(res)
    m["consistency"] = consistency
    m["innovation_bias"] = _innovation_bias(inp, res)
    plaus = _plausibility(ds, inp, res)
    m["plausibility"] = plaus
    m["contacts"] = res.contacts
    m["phases"] = _phases_section(res.phases)
    m["floor"] = _floor_section(res)
    m["noise"] = {"values": noise_doc["noise"], "sources": noise_doc["sources"], "units": noise_doc["units"],
                  "file": "noise.yaml"}
    white = whiteness(res.stance_innovations)
    white.pop("autocorr", None)
    dofs = res.stance_dofs if res.stance_dofs is not None else np.full(len(res.stance_nis), res.stance_dof)
    band = {int(d): chi2_band(int(d)) for d in np.unique(dofs)}  # per update: its dof's 95 % band
    lo_s = np.array([band[int(d)][0] for d in dofs])
    hi_s = np.array([band[int(d)][1] for d in dofs])
    in_band = (res.stance_nis >= lo_s) & (res.stance_nis <= hi_s)
    m.update({
        "stance_nis_mean": float(res.stance_nis.mean()) if len(res.stance_nis) else None,
        "stance_nis_dof": res.stance_dof,
        "stance_nis_dof_mean": float(np.mean(dofs)) if len(dofs) else None,
        "stance_nis_fraction_in_band": float(np.mean(in_band)) if len(res.stance_nis) else None,
        "stance_updates": int(len(res.stance_nis)),
        "innovation_whiteness": white,
        "icp_updates": int(len(res.icp_nis)),
        "icp_rejected": int(res.n_icp_rejected),
        "icp_nis_mean": float(res.icp_nis.mean()) if len(res.icp_nis) else None,
        "icp_dof_mean": float(res.icp_dof.mean()) if len(res.icp_dof) else None,
        "support_switches": int(np.count_nonzero(np.diff(res.support_group))),
        "support_model": "two tripods" if res.groups else "stance mask per foot",
        "n_samples": int(len(res.times)),
        "duration_s": res.duration_s,
        "processing_s": res.processing_s,
        "real_time_factor": res.real_time_factor,
        "output_files": [],
    })

    stairs_doc = None
    if stairs and str(ds.ground.get("type", "")) == "stairs":
        stairs_doc = _stairs_model(ds, inp, res, truth)

    # TUM at the requested rate (always including the last sample)
    if tum_rate_hz and tum_rate_hz > 0:
        keep = np.r_[0, np.flatnonzero(np.diff(np.floor(res.times * tum_rate_hz + 1e-9)) > 0) + 1]
        keep = np.union1d(keep, [len(res.times) - 1])
    else:
        keep = np.arange(len(res.times))
    files: dict[str, bytes] = {"trajectory.tum": tum_text(res.times[keep], res.T_world_body[keep]).encode(),
                               "noise.yaml": yaml.safe_dump(_clean(noise_doc), sort_keys=False).encode()}
    # the metrics are of the filter (every sample), not of the thinned file: evo on trajectory.tum
    # at --tum-rate 10 matches a tenth of the poses and reads a slightly different RMS
    m["metrics_samples"] = "every filter sample (n_samples), whatever --tum-rate"
    m["tum_samples"] = int(len(keep))
    pngs = track_figures(res, truth, nees_t, nees, nees_dof, feet=tuple(inp.robot.feet))
    files.update(pngs)
    if stairs_doc is not None:
        files["stairs.json"] = json.dumps(_clean(stairs_doc), indent=2).encode()
    names = sorted(list(files) + ["metrics.json", "report.html", "scene.mcap"])
    m["output_files"] = names
    m = _clean(m)
    files["metrics.json"] = (json.dumps(m, indent=2) + "\n").encode()
    feet = _footholds(inp, res)
    files["report.html"] = track_html(m, stairs_doc, pngs, title=f"graphcal track: {Path(str(dataset)).name}",
                                      scene=_scene(res, feet, stairs_doc, truth)).encode()

    with atomic_directory(out, overwrite=True) as tmp:
        for name, data in files.items():
            atomic_write_bytes(tmp / name, data)
        _write_scene_mcap(tmp / "scene.mcap", ds, inp, res, feet, stairs_doc)
        _check_out(out, overwrite)
    warnings = tuple(w for w in (plausibility_warning(plaus), consistency_warning(consistency),
                                 bias_warning(m["innovation_bias"])) if w is not None)
    for w in warnings:
        log.warning("WARNING: %s", w)
    return TrackResult(estimate=res, metrics=m, consistency=consistency, stairs=stairs_doc, dataset=str(dataset),
                       out=out, files=tuple(out / name for name in sorted([*files, "scene.mcap"])), warnings=warnings,
                       verdict=consistency["verdict"])


def noise_line(section: dict) -> str:
    """The console's noise line: which values were learned, given or defaults (metrics.json's ``noise``)."""
    src = section["sources"]
    kinds = {"learned": [k for k, s in src.items() if s.startswith("learned")],
             "given": [k for k, s in src.items() if not s.startswith(("learned", "default"))],
             "default": [k for k, s in src.items() if s.startswith("default")]}
    v = section["values"]
    parts = [f"{name} {', '.join(keys)}" for name, keys in kinds.items() if keys]
    return (f"{'; '.join(parts)} (encoder {np.degrees(v['encoder_sigma_rad']):.3g} deg, kinematic "
            f"{1e3 * v['kinematic_sigma_m']:.3g} mm, foot {1e3 * v['foot_rw']:.3g} mm/sqrt(s), gyro "
            f"{v['gyro_noise_density']:.3g} rad/s/sqrt(Hz), accel {v['accel_noise_density']:.3g} m/s^2/sqrt(Hz); "
            f"{section['file']})")


def summary_lines(m: dict, consistency: dict, stairs_doc: dict | None, dataset, out) -> list[str]:
    """The console summary of a track run: samples and speed, the consistency verdict, the accuracy
    against the truth (``m``: metrics.json's document), the stairs model."""
    lines = [f"tracked {dataset}: {m['n_samples']} samples, {m['duration_s']:.1f} s in {m['processing_s']:.1f} s "
             f"({m['real_time_factor']:.1f}x real time); wrote {out}"]
    lines.append(f"  consistency: {consistency['verdict']}" + "".join(
        f"; {k} {r['verdict']} (mean NIS per dof {r['mean_nis_per_dof']:.3f}, p = {r['p_value']:.2g})"
        for k, r in consistency["kinds"].items() if r["verdict"] != "not tested"))
    ib = m.get("innovation_bias") or {}
    if ib.get("worst"):
        w = ib["worst"]
        lines.append(f"  leg model: stance innovations {ib['verdict']} (worst {w['slot']} {w['axis']}: mean "
                     f"{w['mean_sigma']:+.2f} sigma, t = {w['t']:.1f})")
    pl = m.get("plausibility") or {}
    if pl:
        lines.append(f"  plausibility: {pl['verdict']}" + (f" ({pl['reason']})" if pl.get("reason") else ""))
    lines.append("  noise: " + noise_line(m["noise"]))
    if m["truth"]:
        lines.append(f"  against the truth: APE {1e3 * m['ape_rmse_m']:.1f} mm RMS, drift {m['drift_percent']:.3f} % "
                     f"of {m['distance_m']:.2f} m, NEES mean {m['nees_mean']:.2f} (dof {m['nees_dof']})")
    else:
        lines.append("  no truth.yaml beside the dataset: accuracy metrics are null")
    if stairs_doc is not None:
        if "error" in stairs_doc:
            lines.append(f"  stairs: {stairs_doc['error']}")
        else:
            line = f"  stairs: {len(stairs_doc.get('treads', []))} treads from {stairs_doc['n_clouds_used']} clouds"
            if stairs_doc.get("max_abs_height_error_m") is not None:
                dep = stairs_doc.get("max_abs_depth_error_m")
                line += (f"; max |error| height {1e3 * stairs_doc['max_abs_height_error_m']:.1f} mm, depth "
                         f"{'n/a' if dep is None else format(1e3 * dep, '.1f') + ' mm'}")
            lines.append(line)
    return lines
